"""A sparse mass matrix must be symmetric positive definite, not only positive on its diagonal.

Below ``n = 10000`` definiteness is decided by an LDL^T factorisation (its inertia), above
by a Lanczos estimate of the smallest eigenvalue: each refusal is checked on both sides.
"""

import logging

import numpy as np
import pytest
import scipy.sparse as sp

import streamsvd as ss
import streamsvd.algebra.spd as inner_module
from streamsvd.algebra.blas import subtract_product
from streamsvd.cli import main

EPS = np.finfo(np.float64).eps
EXACT, LANCZOS = 40, 110  # grids of (m+1)^2 nodes: 1681 and 12321, either side of 10000


def p1_mass(m):
    """The P1 mass matrix of the unit square cut into 2 m^2 right triangles."""
    idx = np.arange((m + 1) ** 2).reshape(m + 1, m + 1)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                  idx[1:, 1:].ravel())
    tris = np.vstack([np.c_[a, b, d], np.c_[a, d, c]])
    local = 0.5 / m**2 / 12 * (np.ones((3, 3)) + np.eye(3))
    rows = np.repeat(tris, 3, axis=1).ravel()
    cols = np.tile(tris, (1, 3)).ravel()
    n = (m + 1) ** 2
    return sp.csr_array((np.tile(local.ravel(), len(tris)), (rows, cols)), shape=(n, n))


def indefinite(m):
    """A P1 mass matrix with one coupling too strong: a positive diagonal, one negative
    eigenvalue, and the direction ``x`` it belongs to (x^T M x < 0)."""
    M = p1_mass(m)
    n = M.shape[0]
    i, j = n // 3, 2 * n // 3
    d = M.diagonal()
    v = 1.5 * np.sqrt(d[i] * d[j])
    M = (M + sp.csr_array(([v, v], ([i, j], [j, i])), shape=(n, n))).tocsr()
    x = np.zeros(n)
    x[i], x[j] = 1 / np.sqrt(d[i]), -1 / np.sqrt(d[j])
    assert x @ (M @ x) < 0
    return M, x


def duplicated_node(m):
    """A P1 mass matrix assembled with its last node twice: singular, positive diagonal."""
    M = p1_mass(m)
    n = M.shape[0]
    P = sp.vstack([sp.identity(n), sp.csr_array(([1.0], ([0], [n - 1])), shape=(1, n))])
    return (P @ M @ P.T).tocsr()


def neumann_laplacian(m):
    """The 5-point Laplacian with Neumann ends: semi-definite, the constants its kernel."""
    T = sp.diags_array([-np.ones(m), np.r_[1.0, 2 * np.ones(m - 1), 1.0], -np.ones(m)],
                       offsets=[-1, 0, 1])
    eye = sp.identity(m + 1)
    return (sp.kron(T, eye) + sp.kron(eye, T)).tocsr()


@pytest.mark.parametrize("m", [EXACT, LANCZOS])
def test_indefinite_sparse_matrix_with_positive_diagonal_is_refused(m):
    M, _ = indefinite(m)
    assert np.all(M.diagonal() > 0)
    how = "the LDL\\^T factorisation .* has 1 negative pivot" if m == EXACT else "a Lanczos"
    with pytest.raises(ss.InputError, match=rf"`M` must be symmetric positive definite to "
                                            rf"define an inner product; it is indefinite: {how}"):
        ss.StreamCompressor(M.shape[0], inner=M)


@pytest.mark.parametrize("m", [EXACT, LANCZOS])
def test_singular_sparse_matrix_is_refused(m):
    M = duplicated_node(m)
    with pytest.raises(ss.InputError, match=r"`M` must be symmetric positive definite .*; it is "
                                            r"singular"):
        ss.StreamCompressor(M.shape[0], inner=M)


def test_semidefinite_matrix_with_a_cluster_at_zero_is_refused_exactly():
    """The LDL^T sees the zero eigenvalue of a Neumann Laplacian, the bottom of a cluster."""
    M = neumann_laplacian(EXACT)
    with pytest.raises(ss.InputError, match=r"singular to working precision: the LDL\^T "
                                            r"factorisation .* has a pivot of .*, within "):
        ss.MatrixInner(M)


def test_lanczos_that_does_not_settle_is_logged(caplog):
    """Above 10000 the same matrix passes the Lanczos estimate unproven, which is logged."""
    M = neumann_laplacian(LANCZOS)
    with caplog.at_level(logging.WARNING, logger="streamsvd.algebra.spd"):
        ss.MatrixInner(M)
    assert "is taken as positive definite without proof: after 150 Lanczos steps" in caplog.text


@pytest.mark.parametrize("m", [EXACT, LANCZOS])
def test_fem_mass_matrix_is_accepted(m, rng, caplog, monkeypatch):
    M = p1_mass(m)
    scaled = (1e-9 * M).tocsr()  # the test does not depend on the units
    calls = []  # which test ran

    def counted(name):
        test = getattr(inner_module, name)
        return lambda *args: calls.append(name) or test(*args)

    for name in ("_ldlt_pivots", "_lanczos_smallest"):
        monkeypatch.setattr(inner_module, name, counted(name))
    with caplog.at_level(logging.WARNING, logger="streamsvd.algebra.spd"):
        for mat in (M, scaled):
            sc = ss.StreamCompressor(M.shape[0], inner=mat)
            A = rng.standard_normal((M.shape[0], 6))
            sc.absorb(A)
            U = sc.expansion.U
            assert np.linalg.norm(U.T @ (mat @ U) - np.eye(U.shape[1]), 2) <= 1e3 * EPS
    assert caplog.text == ""
    assert calls == ["_ldlt_pivots" if m == EXACT else "_lanczos_smallest"] * 2


def test_diagonal_sparse_matrix_takes_the_fast_path(monkeypatch):
    def refuse(*args):
        raise AssertionError("a diagonal matrix is not factorised")

    monkeypatch.setattr(inner_module, "_ldlt_pivots", refuse)
    monkeypatch.setattr(inner_module, "_lanczos_smallest", refuse)
    for n in (50, 20000):
        w = np.linspace(1.0, 2.0, n)
        ip = ss.StreamCompressor(n, inner=sp.diags_array(w).tocsr()).inner
        X = np.ones((n, 2))
        np.testing.assert_array_equal(ip.apply(X), w[:, None] * X)


def test_symmetry_tolerance_grows_with_the_rows():
    """An asymmetry within the rounding of M @ x (w eps |M|, w the longest row) passes."""
    n = 1500
    M = np.eye(n) + 0.1 * np.eye(n, k=1) + 0.1 * np.eye(n, k=-1)
    M[0, 1] += 1400 * EPS
    ss.MatrixInner(M)
    M[0, 1] += 200 * EPS
    with pytest.raises(ss.InputError, match=r"`M` must be symmetric; got max \|M - M\^T\|"):
        ss.MatrixInner(M)


@pytest.mark.parametrize("m", [EXACT, LANCZOS])
@pytest.mark.parametrize("kind", ["indefinite", "singular"])
def test_cli_refuses_the_matrix_in_one_line_and_leaves_no_store(tmp_path, capsys, m, kind):
    """The issue: along the negative direction, ingest ended with rank 0, bound 0 and rc 0."""
    if kind == "indefinite":
        M, x = indefinite(m)
    else:
        M = duplicated_node(m)
        x = np.zeros(M.shape[0])
        x[0], x[-1] = 1.0, -1.0  # M x = 0
    sp.save_npz(tmp_path / "m.npz", M)
    np.save(tmp_path / "a.npy", np.outer(x, [1.0, 2.0]))
    store = tmp_path / "s.zarr"
    status = main(["ingest", str(tmp_path / "a.npy"), str(store), "--inner",
                   str(tmp_path / "m.npz"), "--quiet"])
    out, err = capsys.readouterr()
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("streamsvd: error: --inner (its matrix) must be symmetric positive "
                          f"definite to define an inner product; it is {kind}"), err
    assert not store.exists()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("b", [1, 2, 3, 4, 5, 6, 7, 9, 15, 23])
def test_a_sparse_product_with_a_column_major_block_has_scipys_digits(b, dtype):
    # every grouping of the columns (8, 4, 2, 1) and their combinations
    rng = np.random.default_rng(b)
    n = 200
    A = sp.random(n, n, density=0.03, random_state=rng, format="csr")
    M = (A @ A.T + sp.identity(n)).tocsr()
    ip = ss.MatrixInner(M)
    X = np.asfortranarray(rng.standard_normal((n, b)).astype(dtype))
    expected = np.asarray(ip.matrix @ np.ascontiguousarray(X, dtype=np.float64))
    np.testing.assert_array_equal(ip.apply(X), expected)
    out = np.empty((n, b), order="F")
    assert ip.apply(X, out=out) is out
    np.testing.assert_array_equal(out, expected)
    # the columns' energies measured within the product, the product unchanged
    MX, energies = ip.apply_with_energies(X, out=np.empty((n, b), order="F"))
    np.testing.assert_array_equal(MX, expected)
    X64 = X.astype(np.float64)
    np.testing.assert_allclose(energies, np.einsum("ij,ij->j", X64, expected), rtol=1e-13)
    # a row-major block and a vector go through scipy
    np.testing.assert_array_equal(ip.apply(np.ascontiguousarray(X)), expected)
    np.testing.assert_array_equal(ip.apply(X[:, 0]), expected[:, 0])


def test_a_sparse_matrix_is_factorised_once_per_process(monkeypatch):
    import streamsvd.algebra.inner as inner_module

    calls = []
    original = inner_module.check_sparse_definite
    monkeypatch.setattr(inner_module, "check_sparse_definite",
                        lambda *a: calls.append(1) or original(*a))
    n = 50
    M = sp.diags([np.full(n - 1, -0.25), np.full(n, 1.0), np.full(n - 1, -0.25)],
                 [-1, 0, 1], format="csr")
    ss.MatrixInner(M)
    ss.MatrixInner(M.copy())
    assert len(calls) <= 1
    # other entries are checked again, and an indefinite matrix still refused
    bad = M.copy()
    bad.setdiag(np.full(n, 0.1))
    with pytest.raises(ss.InputError):
        ss.MatrixInner(bad)


@pytest.mark.parametrize("kind", ["weights", "uniform sparse", "varying sparse"])
@pytest.mark.parametrize("b", [3, 40])
def test_a_diagonal_gram_is_the_weighted_product(kind, b, rng):
    """With a diagonal M the Gram is a rank-k update of the weighted columns (wide
    blocks): X^T M X to the rounding of a product of n terms, symmetric exactly."""
    from streamsvd.algebra.blas import gram

    n = 3000
    w = np.full(n, 1 / 3600) if kind == "uniform sparse" else rng.uniform(0.1, 2.0, n)
    inner = (ss.DiagonalInner(w) if kind == "weights"
             else ss.StreamCompressor(n, inner=sp.diags_array(w).tocsr()).inner)
    assert inner.diagonal is not None
    assert (inner.diagonal.uniform is not None) == (kind == "uniform sparse")
    X = np.asfortranarray(rng.standard_normal((n, b)))
    G = gram(X, inner)
    want = X.T @ (w[:, None] * X)
    np.testing.assert_array_equal(G, G.T)
    scale = np.sqrt(np.outer(np.diag(want), np.diag(want)))
    assert np.max(np.abs(G - want) / scale) <= 4 * n * np.finfo(float).eps


def test_a_diagonal_matrix_writes_its_product_where_asked(rng):
    n = 500
    w = rng.uniform(0.5, 1.5, n)
    inner = ss.StreamCompressor(n, inner=sp.diags_array(w).tocsr()).inner
    X = np.asfortranarray(rng.standard_normal((n, 6)))
    out = np.empty_like(X, order="F")
    assert inner.apply(X, out=out) is out
    np.testing.assert_array_equal(out, w[:, None] * X)


@pytest.mark.parametrize("order", ["F", "C"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_subtract_product_subtracts_in_place(order, dtype):
    rng = np.random.default_rng(3)
    X = np.array(rng.standard_normal((50, 7)), dtype=dtype, order=order)
    A, K = rng.standard_normal((50, 4)), rng.standard_normal((4, 7))
    expected = X - A @ K
    before = X
    subtract_product(X, A, K)
    assert X is before
    np.testing.assert_allclose(X, expected, rtol=0,
                               atol=8 * 4 * np.finfo(dtype).eps * np.abs(expected).max())
    subtract_product(X, A[:, :0], K[:0])  # nothing to subtract
    np.testing.assert_allclose(X, expected, rtol=0,
                               atol=8 * 4 * np.finfo(dtype).eps * np.abs(expected).max())


@pytest.mark.parametrize("kind", ["sparse", "dense", "diagonal", "weights", "euclidean"])
def test_the_norm_bound_bounds_the_largest_eigenvalue(kind):
    # Gershgorin's row sums (raised by their rounding) for a matrix, the largest weight
    # for a diagonal one: never below ||M||_2, which the Gram path's early refusal needs
    rng = np.random.default_rng(3)
    n = 300
    A = sp.random(n, n, density=0.02, random_state=rng, format="csr")
    S = (A @ A.T + 1e-3 * sp.identity(n)).tocsr()
    w = rng.uniform(0.1, 2.0, n)
    M = {"sparse": S, "dense": S.toarray(), "diagonal": sp.diags_array(w).tocsr(),
         "weights": w, "euclidean": None}[kind]
    ip = ss.as_inner(M, n) if M is not None else ss.as_inner(None, n)
    dense = np.eye(n) if M is None else (np.diag(w) if kind in ("diagonal", "weights")
                                        else S.toarray())
    top = float(np.linalg.eigvalsh(dense)[-1])
    assert ip.norm_bound >= top
    assert ip.norm_bound <= np.max(np.sum(np.abs(dense), axis=1)) * (1 + 1e-12)
