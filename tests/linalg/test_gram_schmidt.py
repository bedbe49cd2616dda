"""Algorithm 1 and block CGS2: orthonormality, unchanged product, rejection, inner products."""

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import example, given
from hypothesis import strategies as st

import streamsvd as ss
from streamsvd.testing import assert_svd_contract, with_spectrum

EPS = np.finfo(float).eps


def _spd(n, rng, cond=1e3):
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    return (Q * np.logspace(0, -np.log10(cond), n)) @ Q.T


@given(st.integers(0, 2**32 - 1), st.integers(1, 30), st.integers(1, 25), st.integers(1, 12),
       st.sampled_from([1, 3, 64]))
# a square full-rank U column by column: the small components a first projection leaves
# along the basis must be removed before U is returned (they were: 6.3e-13 = 260 eps)
@example(seed=27, n=11, m=1, p=11, block=1)
def test_orthonormalize_keeps_the_product_and_orthonormalises(seed, n, m, p, block):
    rng = np.random.default_rng(seed)
    U = rng.standard_normal((n, p)) * np.logspace(0, -3, p)
    V = rng.standard_normal((m, p))
    g = ss.orthonormalize(U, V, block=block)
    e = g.expansion
    assert e.rank <= min(n, p)
    assert e.orthogonality_error() <= 50 * n * EPS
    A = U @ V.T
    err = np.linalg.norm(e.to_dense() - A)
    assert err <= np.sqrt(g.discarded_energy) + 50 * max(n, m) * EPS * np.linalg.norm(U) * np.linalg.norm(V)


def test_dependent_directions_are_rejected_not_normalised(rng):
    B = rng.standard_normal((50, 4))
    U = np.column_stack([B, B @ rng.standard_normal(4), B[:, 0] * 1e-3, B @ [1, 2, 3, 4] + 1e-15 * rng.standard_normal(50)])
    V = rng.standard_normal((7, U.shape[1]))
    g = ss.orthonormalize(U, V)
    assert g.rejected == (4, 5, 6)  # B r, a multiple of B[:, 0], B r + 1e-15 noise
    assert g.expansion.rank == 4
    assert g.expansion.orthogonality_error() <= 50 * 50 * EPS
    assert np.linalg.norm(g.expansion.to_dense() - U @ V.T) <= 1e-12 * np.linalg.norm(U @ V.T)
    # the literal Algorithm 1 normalises the rounding noise instead: orthogonality is lost
    lit = ss.orthonormalize_literal(U, V)
    assert lit.rank > 4 and lit.orthogonality_error() > 1e-6


def test_small_but_real_directions_are_kept(rng):
    B = np.linalg.qr(rng.standard_normal((200, 3)))[0]
    for size in (1e-8, 1e-12):
        x = B @ [1.0, 2.0, 3.0] + size * np.linalg.qr(rng.standard_normal((200, 4)))[0][:, 3]
        g = ss.orthonormalize(np.column_stack([B, x]), np.eye(4))
        assert g.expansion.rank == 4, size  # n * eps = 4.4e-14 < size
        assert g.expansion.orthogonality_error() <= 50 * 200 * EPS


def test_literal_algorithm_1_matches_fast_path_on_well_conditioned_input(rng):
    U = rng.standard_normal((30, 6))
    V = rng.standard_normal((12, 6))
    a = ss.orthonormalize(U, V).expansion
    b = ss.orthonormalize_literal(U, V)
    np.testing.assert_allclose(a.U, b.U, atol=1e-12)
    np.testing.assert_allclose(a.V, b.V, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-300, 1e300])
def test_extreme_scales_neither_overflow_nor_underflow(rng, scale):
    U = rng.standard_normal((20, 5)) * scale
    V = rng.standard_normal((8, 5))
    e = ss.orthonormalize(U, V).expansion
    assert e.rank == 5 and e.orthogonality_error() <= 50 * 20 * EPS
    assert np.all(np.isfinite(e.V))
    rel = np.linalg.norm(e.to_dense() / scale - (U / scale) @ V.T) / np.linalg.norm((U / scale) @ V.T)
    assert rel <= 50 * 20 * EPS


@pytest.mark.parametrize("kind", ["dense", "sparse", "weights"])
def test_weighted_inner_product_equals_euclidean_after_cholesky_change_of_variables(rng, kind):
    n, m = 25, 18
    if kind == "weights":
        w = rng.uniform(0.1, 10.0, n)
        M = np.diag(w)
        inner = w
    else:
        M = _spd(n, rng)
        inner = sp.csr_array(M) if kind == "sparse" else M
    A = with_spectrum(np.logspace(0, -5, 10), n, m, rng)
    e = ss.orthonormalize(A, np.eye(m), inner=inner).expansion
    r = ss.compress(e, rule="jacobi", max_sweeps=60).expansion
    G = r.U.T @ M @ r.U
    assert np.linalg.norm(G - np.eye(r.rank), 2) <= 50 * n * EPS * np.linalg.cond(M)
    # with M = L L^T, the M-SVD of A is the Euclidean SVD of L^T A mapped back by L^{-T}
    L = np.linalg.cholesky(M)
    B = L.T @ A
    s = np.linalg.svd(B, compute_uv=False)
    np.testing.assert_allclose(r.amplitudes[:10], s[:10], rtol=1e-10, atol=1e-13)
    mapped = ss.Expansion(L.T @ r.U, r.V)
    assert_svd_contract(B, mapped, threshold=50 * np.linalg.cond(L))


def test_inner_product_checks(rng):
    with pytest.raises(ss.InputError, match=r"`M` must be symmetric; got max \|M - M\^T\|"):
        ss.orthonormalize(np.eye(3), np.eye(3), inner=np.triu(np.ones((3, 3))))
    with pytest.raises(ss.InputError, match=r"`M` must be positive definite; got M\[1, 1\] = -1.0"):
        ss.MatrixInner(np.diag([1.0, -1.0, 2.0]))
    with pytest.raises(ss.InputError, match=r"`M` must be positive definite; its Cholesky"):
        ss.MatrixInner(np.array([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(ss.InputError, match=r"`weights` must all be > 0 .* got weights\[2\] = 0.0"):
        ss.DiagonalInner([1.0, 2.0, 0.0])
    with pytest.raises(ss.InnerProductMismatchError, match=r"`inner` acts on vectors of size 4; the snapshots have size 3"):
        ss.orthonormalize(np.eye(3), np.eye(3), inner=np.ones(4))
    a, b = ss.DiagonalInner([1.0, 2.0]), ss.DiagonalInner(np.array([1.0, 2.0]))
    assert a == b and a.fingerprint == b.fingerprint != ss.DiagonalInner([1.0, 3.0]).fingerprint
    assert ss.MatrixInner(sp.identity(3, format="csr")).fingerprint != ss.Euclidean().fingerprint


@pytest.mark.parametrize(
    "U,V,match",
    [(np.ones((3, 2)), np.ones((4, 3)), r"`U` and `V` must have the same number of columns"),
     (np.ones(3), np.ones((4, 3)), r"`U` must be 2-D; got 1-D of shape \(3,\)"),
     (np.ones((3, 2), dtype=complex), np.ones((4, 2)), r"`U` must be real; got complex dtype"),
     (np.array([["a", "b"]]), np.ones((4, 2)), r"`U` must hold real numbers; got dtype <U1"),
     (sp.eye(3), np.ones((3, 3)), r"`U` must be a dense array; got a sparse matrix")],
)
def test_bad_arrays_are_refused(U, V, match):
    with pytest.raises(ss.InputError, match=match):
        ss.orthonormalize(U, V)
