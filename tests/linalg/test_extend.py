"""Tests of streamsvd.linalg.extend: setting directions aside on the residual's Gram."""

from __future__ import annotations

import numpy as np
import pytest

from streamsvd.algebra.inner import as_inner
from streamsvd.algebra.memory import MemoryBasis
from streamsvd.linalg.blocks import set_aside
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.rejection import default_reject_tol
from tests.linalg._snapshots import mass as _mass

EPS = np.finfo(np.float64).eps


def _collinear(n=400, b=30, seed=0):
    """Snapshots of a drifting pulse: a residual spanning many decades."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 0.3, b)[np.newaxis, :]
    rng = np.random.default_rng(seed)
    return np.exp(-((x - 0.3 - t) / 0.1) ** 2) * (1 + 1e-9 * rng.standard_normal((1, b)))



def test_set_aside_takes_the_tail_within_the_budget():
    rng = np.random.default_rng(1)
    W, _ = np.linalg.qr(rng.standard_normal((8, 8)))
    lam = np.array([1.0, 1e-3, 1e-6, 1e-14, 1e-16, 1e-18, 1e-20, 0.0])
    S = (W * lam) @ W.T
    S = 0.5 * (S + S.T)
    assert set_aside(S, 0.0, 1000, 4.0) is None
    Wk, lam_k, Wt, Gt = set_aside(S, 1e-6, 1000, 4.0)
    # the smallest directions whose energy, rounding counted, fits the budget
    assert Wt.shape[1] == 5 and np.all(lam_k >= 0.5e-6)
    np.testing.assert_allclose(Wk.T @ Wk, np.eye(Wk.shape[1]), atol=10 * EPS)
    # the tail's account: its eigenvalues and the rounding allowance, within the budget
    assert np.trace(Gt) <= 1e-6
    assert np.trace(Gt) >= np.sum(np.linalg.eigvalsh(Wt.T @ S @ Wt).clip(0))
    # a budget below the allowance sets nothing aside
    assert set_aside(S, 1e-15, 1000, 4.0) is None


# 1e-12: set aside on the block's residual Gram; 1e-15: below that Gram's rounding
# allowance (about 2e-14 of the energy), set aside on the Gram of a later round's tail
@pytest.mark.parametrize("share", [1e-12, 1e-15])
@pytest.mark.parametrize("euclidean", [True, False])
def test_a_block_with_a_budget_keeps_x_within_the_rejected_norm(euclidean, share):
    n = 400
    X = _collinear(n)
    M = None if euclidean else _mass(n)
    ip = as_inner(M, n)
    energy = float(np.sum(X * ip.apply(X)))
    basis = MemoryBasis(n, ip, capacity=2 * X.shape[1])
    plain = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n))
    basis = MemoryBasis(n, ip, capacity=2 * X.shape[1])
    budget = share * energy
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                       aside=(budget, 0.0))
    r = ext.rank
    assert r < plain.rank
    Q = basis.workspace(X.shape[1])[0][:, :r].copy()
    # the new directions are M-orthonormal
    G = Q.T @ ip.apply(Q)
    assert np.linalg.norm(G - np.eye(r), 2) <= 100 * n * EPS
    # X = Q_new R_new + Res, and ||Res|| is within the reported rejected norm (rounding
    # counted) and within the budget given
    res = X - Q @ ext.R_new
    true = float(np.sqrt(max(np.sum(res * ip.apply(res)), 0.0)))
    reported = ext.rejected_norm()
    assert true <= reported * (1 + 1e-6) + 10 * n * EPS * np.sqrt(energy)
    assert reported**2 <= budget * (1 + 1e-9) + plain.rejected_norm() ** 2


def test_no_budget_is_the_plain_extension():
    n = 300
    X = _collinear(n, b=20)
    ip = as_inner(None, n)
    exts = []
    for aside in ((0.0, 0.0), None):
        basis = MemoryBasis(n, ip, capacity=40)
        kw = {} if aside is None else {"aside": aside}
        exts.append(extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n), **kw))
    np.testing.assert_array_equal(exts[0].R_new, exts[1].R_new)
    assert exts[0].rejected_norm() == exts[1].rejected_norm()


def test_the_budget_sets_directions_aside():
    n = 400
    X = _collinear(n)
    ip = as_inner(_mass(n), n)
    energy = float(np.sum(X * ip.apply(X)))
    ranks = []
    for budget in (0.0, 1e-12 * energy):
        basis = MemoryBasis(n, ip, capacity=2 * X.shape[1])
        ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                           aside=(budget, 0.0))
        ranks.append(ext.rank)
    assert ranks[1] < ranks[0]


def test_a_budget_below_the_first_grams_rounding_is_spent_on_a_later_round():
    n = 400
    X = _collinear(n)
    ip = as_inner(_mass(n), n)
    S = X.T @ ip.apply(X)
    budget = 1e-15 * float(np.trace(S))
    # the block's Gram cannot set anything aside: its rounding allowance is larger
    assert set_aside(0.5 * (S + S.T), budget, n, 4.0) is None
    ranks, rejected = [], []
    for aside in ((0.0, 0.0), (budget, 0.0)):
        basis = MemoryBasis(n, ip, capacity=2 * X.shape[1])
        ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                           aside=aside)
        ranks.append(ext.rank)
        rejected.append(ext.rejected_norm())
    # the tail of a later round, of a smaller trace, is set aside within the budget
    assert ranks[1] < ranks[0]
    assert rejected[1] ** 2 <= budget * (1 + 1e-9) + rejected[0] ** 2


def _widening_pulse(n, m):
    """Snapshots of a pulse that drifts and widens: nearly collinear blocks."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 1.0, m)[np.newaxis, :]
    return np.exp(-((x - 0.2 - 0.6 * t) / (0.05 + 0.05 * t)) ** 2)


def _assert_within_bound(sc, A, M, rounding):
    """``||A - U V^T||_M <= error_bound`` (relatively to 1e-9) plus ``rounding``."""
    E = sc.expansion
    R = A - E.U @ E.V.T
    err = float(np.sqrt(max(np.sum(R * (M @ R)), 0.0)))
    assert err <= sc.error_bound * (1 + 1e-9) + rounding


@pytest.mark.parametrize("measure", ["mean_l2", "relative"])
def test_a_stream_at_a_tight_target_holds_its_bound_on_the_exact_path(monkeypatch, measure):
    import streamsvd as ss
    import streamsvd.stream.updates as stream_module

    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    n, m = 300, 120
    A, M = _widening_pulse(n, m), _mass(n)
    sc = ss.StreamCompressor(n, inner=M, target_error=1e-6, error_measure=measure,
                             rule="jacobi", sweeps=None)
    for j in range(0, m, 30):
        sc.absorb(A[:, j : j + 30])
        _assert_within_bound(sc, A[:, : j + 30], M, 10 * n * EPS * np.linalg.norm(A))
    sc.finalize()
    assert sc.error_in_measure <= 1e-6


@pytest.mark.parametrize("scale", [0, -50, -100, -200])
@pytest.mark.parametrize("euclidean", [True, False])
def test_a_zero_column_is_represented_by_zeros_at_every_scale(scale, euclidean):
    # a zero column's scale (2^0) says nothing of the rounding the other, scaled,
    # columns leave in its coordinates: it must come back as exact zeros, not as
    # rounding at the size of 1 (an absolute error of 1e-16 beside data of 1e-30)
    n = 300
    X = np.ldexp(_collinear(n, b=16) + 1e-3 * np.random.default_rng(2).standard_normal((n, 16)),
                 scale)
    X[:, 5] = 0.0
    ip = as_inner(None if euclidean else _mass(n), n)
    basis = MemoryBasis(n, ip, capacity=32)
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n))
    assert not ext.accepted[5]
    assert np.all(ext.R_new[:, 5] == 0.0) and np.all(ext.rejected_map[:, 5] == 0.0)
    Q = basis.workspace(16)[0][:, :ext.rank]
    res = X - Q @ ext.R_new
    norm = np.sqrt(np.sum(X * ip.apply(X)))
    true = np.sqrt(max(float(np.sum(res * ip.apply(res))), 0.0))
    assert true <= ext.rejected_norm() * (1 + 1e-6) + 10 * n * EPS * norm


def test_a_zero_column_beside_a_basis_has_zero_coefficients():
    # the directions set aside hand their part along the basis to the coefficients,
    # through the residual's eigenvectors, whose rows of a zero column hold rounding
    X, basis, ip, H = _on_a_basis()
    X = np.ldexp(X, -100)
    X[:, 3] = 0.0
    energy = float(np.sum(X * ip.apply(X)))
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(X.shape[0]),
                       basis_gram=H, aside=(1e-12 * energy, 0.0))
    assert np.all(ext.coeffs[:, 3] == 0.0) and np.all(ext.R_new[:, 3] == 0.0)
    assert np.all(ext.rejected_map[:, 3] == 0.0)


def _on_a_basis(n=400, b=30):
    """A basis of the first block of a drifting pulse, and the next block."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 0.6, 2 * b)[np.newaxis, :]
    A = np.exp(-((x - 0.2 - t) / 0.1) ** 2)
    ip = as_inner(_mass(n), n)
    basis = MemoryBasis(n, ip, capacity=4 * b)
    first = extend_basis(basis, None, A[:, :b], inner=ip, reject_tol=default_reject_tol(n))
    basis.accept(first.rank)
    H = basis.measure_gram()
    return A[:, b:], basis, ip, H


def test_a_block_projected_once_keeps_its_decomposition_and_measures_its_skew(monkeypatch):
    import streamsvd.linalg.extend as extend_module

    n = 400
    X, basis, ip, H = _on_a_basis(n)
    energy = float(np.sum(X * ip.apply(X)))
    # the loss of every column is above the per-column threshold: without the budget
    # the residual is projected twice; with it, once (its kept directions are clean)
    monkeypatch.setattr(extend_module, "_LOSS_MAX", 0.0)
    w = basis.width
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n),
                       basis_gram=H, aside=(1e-14 * energy, 0.0))
    assert ext.skewed
    r = ext.rank
    Q = basis.Q[:, :w].copy()
    Qn = basis.workspace(X.shape[1])[0][:, :r].copy()
    MQn = ip.apply(Qn)
    # the cross block of the basis Gram is measured, and within the kept loss
    np.testing.assert_allclose(ext.cross_gram, Q.T @ MQn, rtol=0, atol=100 * n * EPS)
    assert np.max(np.abs(ext.cross_gram)) <= extend_module._KEPT_LOSS_MAX
    # X = Q coeffs + Q_new R_new + Res, ||Res|| within the rejected norm, Res M-orthogonal
    # to the basis up to rounding (the directions set aside left their part to coeffs)
    res = X - Q @ ext.coeffs - Qn @ ext.R_new
    true = float(np.sqrt(max(np.sum(res * ip.apply(res)), 0.0)))
    assert true <= ext.rejected_norm() * (1 + 1e-6) + 10 * n * EPS * np.sqrt(energy)
    along = Q.T @ ip.apply(res)
    assert np.linalg.norm(along) <= 100 * n * EPS * np.sqrt(energy)


@pytest.mark.parametrize("measure", ["mean_l2", "relative"])
def test_a_stream_projected_once_stays_orthonormal_and_holds_its_bound(monkeypatch, measure):
    import streamsvd as ss
    import streamsvd.linalg.extend as extend_module
    import streamsvd.linalg.slices as slices_module
    import streamsvd.stream.updates as stream_module

    monkeypatch.setattr(stream_module, "plan_absorb_by_gram", lambda *a, **k: None)
    monkeypatch.setattr(extend_module, "_LOSS_MAX", 0.0)  # every block takes the new branch
    skewed = []
    original = slices_module.extend_basis

    def spy(*args, **kwargs):
        ext = original(*args, **kwargs)
        skewed.append(ext.skewed)
        return ext

    monkeypatch.setattr(slices_module, "extend_basis", spy)
    n, m, b = 300, 150, 30
    A, M = _widening_pulse(n, m), _mass(n)
    sc = ss.StreamCompressor(n, inner=M, target_error=1e-6, error_measure=measure,
                             rule="jacobi", sweeps=None)
    for j in range(0, m, b):
        sc.absorb(A[:, j : j + b])
        _assert_within_bound(sc, A[:, : j + b], M, 10 * n * EPS * np.linalg.norm(A))
        U = sc.expansion.U
        assert np.linalg.norm(U.T @ (M @ U) - np.eye(U.shape[1]), 2) <= 50 * n * EPS
    assert any(skewed[1:])
    sc.finalize()
    assert sc.error_in_measure <= 1e-6


def test_norms_of_tiny_columns_beside_a_zero_column_do_not_underflow():
    # a zero column's exponent (0) was the common scale of columns of 2^-996: their
    # scaled values fell to 1e-300, whose squares vanish (a rejected norm of 0)
    from streamsvd._util.scaling import scaled_norm

    assert scaled_norm(np.array([0.75, 0.0]), np.array([-996, 0])) == np.ldexp(0.75, -996)
    n = 300
    X = _collinear(n, b=16) + 1e-10 * np.random.default_rng(4).standard_normal((n, 16))
    ip = as_inner(_mass(n), n)
    exts = []
    for scale in (0, -996):
        Xs = np.ldexp(X, scale)
        Xs[:, 5] = 0.0
        basis = MemoryBasis(n, ip, capacity=32)
        exts.append(extend_basis(basis, None, Xs, inner=ip, reject_tol=1e-8))
    plain, tiny = exts
    assert plain.rejected_norm() > 0
    # the same digits but the rounding of the tail's energies (1e-11 here)
    np.testing.assert_allclose(np.ldexp(tiny.rejected_norm(), 996), plain.rejected_norm(),
                               rtol=1e-8)
    np.testing.assert_allclose(np.ldexp(tiny.block_norm, 996), plain.block_norm, rtol=1e-14)


# the P1 mass matrix has 3 entries per row: a block of fewer than 6 columns has its image
# mapped by the CholeskyQR solve, a wider one has M applied again
@pytest.mark.parametrize("b", [1, 2, 5, 6, 12])
def test_the_new_directions_image_is_m_times_them(b):
    n = 500
    M = _mass(n)
    ip = as_inner(M, n)
    rng = np.random.default_rng(b)
    basis = MemoryBasis(n, ip, capacity=40)
    first = extend_basis(basis, None, rng.standard_normal((n, 10)), inner=ip,
                         reject_tol=default_reject_tol(n))
    basis.accept(first.rank)
    # well-conditioned columns: one CholeskyQR pass (cond(S) <= 16)
    X = rng.standard_normal((n, b)) * (1 + 0.1 * rng.random(b))
    ext = extend_basis(basis, None, X, inner=ip, reject_tol=default_reject_tol(n))
    assert ext.rank == b and ext.passes == 3  # projection, subtraction, cross block
    basis.accept(b)
    Q, MQ = basis.Q[:, 10:], basis.MQ[:, 10:]
    exact = M @ Q
    # a product with M rounds by about 3 eps |M| |Q| per entry; the solve by a factor of
    # condition <= 4 adds a few eps of the image: within 8 b eps of ||M|| ||Q||
    err = np.abs(MQ - exact).max()
    assert err <= 8 * b * EPS * abs(M).max() * 3 * np.abs(Q).max()
    if b >= 6:
        np.testing.assert_array_equal(MQ, ip.apply(np.asfortranarray(Q)))
    gram = Q.T @ MQ
    assert np.abs(gram - np.eye(b)).max() <= 10 * b * EPS
    assert np.abs(Q.T @ exact - np.eye(b)).max() <= 10 * b * EPS
