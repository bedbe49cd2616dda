"""Properties of F (eqs 5-11), of eq. (14), and of one sweep (Algorithms 2, 3)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import streamsvd as ss
from streamsvd.linalg.rotations import rotation_tangent, sweep_core, sweep_literal
from streamsvd.testing import rank2_expansions

EPS = np.finfo(float).eps


@given(rank2_expansions())
def test_F_keeps_product_orthonormality_and_order_and_compresses(e):
    (u1, u2), (v1, v2) = e.U.T, e.V.T
    r = ss.rotate_pair(u1, v1, u2, v2)
    A = e.to_dense()
    scale = max(e.n, e.m) * EPS * np.linalg.norm(A)
    new = np.outer(r.u1, r.v1) + np.outer(r.u2, r.v2)
    assert np.linalg.norm(new - A) <= 10 * scale  # product unchanged
    Ut = np.column_stack([r.u1, r.u2])
    assert np.linalg.norm(Ut.T @ Ut - np.eye(2)) <= 10 * e.n * EPS  # orthonormality
    c0 = abs(v1 @ v2)
    c1 = abs(r.v1 @ r.v2)
    assert c1 <= c0 * (1 + 10 * EPS) + 10 * EPS * (v1 @ v1)  # compression
    if c0 > 1e-8 * (v1 @ v1):
        assert c1 < c0
    assert r.v1 @ r.v1 >= r.v2 @ r.v2 * (1 - 10 * EPS)  # order preservation
    assert r.alpha == pytest.approx((v1 @ v2) / (v1 @ v1), rel=1e-14, abs=0)


@given(rank2_expansions(), st.integers(1, 8))
def test_eq14_recursion_matches_iterates_of_F(e, steps):
    (u1, u2), (v1, v2) = e.U.T, e.V.T
    eta0 = (v2 @ v2) / (v1 @ v1)
    alpha0 = (v1 @ v2) / (v1 @ v1)
    if not alpha0**2 < eta0 * (1 - 1e-6):  # rank-1 pairs sit on the boundary of (13)
        return
    dyn = ss.pair_dynamics(eta0, alpha0, steps)
    for k in range(steps):
        r = ss.rotate_pair(u1, v1, u2, v2)
        u1, v1, u2, v2 = r.u1, r.v1, r.u2, r.v2
        eta = (v2 @ v2) / (v1 @ v1)
        alpha = (v1 @ v2) / (v1 @ v1)
        assert eta == pytest.approx(dyn.eta[k + 1], rel=1e-8, abs=1e-14)
        assert alpha == pytest.approx(dyn.alpha[k + 1], rel=1e-6, abs=1e-13)
    # the preserved quantity 2 delta = eta_xi + 1 / eta_{xi+1}
    for k in range(steps):
        if dyn.eta[k + 1] > 1e-12:
            assert dyn.eta[k] + 1 / dyn.eta[k + 1] == pytest.approx(2 * dyn.delta, rel=1e-9)


def test_pair_dynamics_converges_to_predicted_rate():
    dyn = ss.pair_dynamics(0.8, 0.5, 60)
    assert dyn.alpha[-1] < 1e-6
    assert dyn.eta[-1] == pytest.approx(dyn.eta_limit, rel=1e-10)
    # strictly decreasing while eta is distinguishable from its limit
    assert np.all(np.diff(dyn.eta[:6]) < 0) and np.all(np.diff(np.abs(dyn.alpha)) < 0)
    assert np.all(np.diff(dyn.eta) <= 0)


def test_pair_dynamics_rejects_points_outside_inequality_13():
    with pytest.raises(ss.InputError, match=r"`eta0` and `alpha0` must satisfy"):
        ss.pair_dynamics(0.2, 0.9, 3)


@pytest.mark.parametrize("wjj,wii,wij", [(4.0, 1.0, 0.7), (1.0, 1.0, 0.3), (5.0, 4.999, -1e-3),
                                         (1.0, 0.5, 1e-200), (2.0, 1.0, -0.9)])
def test_jacobi_angle_zeroes_coupling(wjj, wii, wij):
    t = rotation_tangent(wjj, wii, wij, True)
    new = wij * (1 - t * t) + t * (wii - wjj)
    assert abs(new) <= 10 * EPS * max(wjj, abs(wij))
    assert abs(t) <= 1.0
    assert rotation_tangent(wjj, wii, wij, False) == wij / wjj


@given(st.integers(0, 2**32 - 1), st.integers(2, 12), st.integers(1, 15),
       st.sampled_from(["paper", "jacobi"]), st.sampled_from([0.0, 0.3]))
def test_sweep_core_equals_literal_sweep(seed, p, m, rule, eps):
    # full-rank V (m >= p): with m < p some vectors become rounding noise, whose
    # cosines are arbitrary in either path
    rng = np.random.default_rng(seed)
    m = m + p
    n = p + 3
    U = np.linalg.qr(rng.standard_normal((n, p)))[0]
    V = rng.standard_normal((m, p)) * np.logspace(0, -1, p)
    U1, V1, s1 = sweep_literal(U, V, rule=rule, eps=eps, tol=0.0)
    Qv, R = np.linalg.qr(V)
    Rt = np.ascontiguousarray(R.T)
    Qt = np.eye(p)
    order = np.arange(p, dtype=np.int64)
    s2 = sweep_core(Rt, Qt, order, p, rule=rule, eps=eps, tol=0.0)
    sel = order[: s2.rank]
    U2, V2 = U @ Qt[sel].T, Qv @ Rt[sel].T
    assert s1.rank == s2.rank and s1.rotations == s2.rotations
    tol = 1e3 * max(n, m) * EPS
    assert np.allclose(U1, U2, atol=tol) and np.allclose(V1, V2, atol=tol * np.abs(V).max())
    assert s1.indicator == pytest.approx(s2.indicator, rel=1e-9, abs=1e-15)
    assert s1.cut_energy == pytest.approx(s2.cut_energy, rel=1e-9, abs=1e-15)


@given(st.integers(0, 2**32 - 1), st.sampled_from(["paper", "jacobi"]))
def test_sweep_compresses_the_coupling_of_W(seed, rule):
    # the off-diagonal part of W = V^T V (eq. 15) shrinks and U V^T is unchanged (eq. 17)
    rng = np.random.default_rng(seed)
    p = 6
    U = np.linalg.qr(rng.standard_normal((10, p)))[0]
    V = rng.standard_normal((9, p)) * np.logspace(0, -2, p)
    U1, V1, _ = sweep_literal(U, V, rule=rule, eps=0.0, tol=0.0)
    off = lambda W: math.sqrt(max(np.sum(W**2) - np.sum(np.diag(W) ** 2), 0.0))  # noqa: E731
    assert off(V1.T @ V1) < off(V.T @ V)
    assert np.linalg.norm(U1 @ V1.T - U @ V.T) <= 100 * EPS * np.linalg.norm(V)
    assert np.linalg.norm(U1.T @ U1 - np.eye(p)) <= 100 * EPS * p


def test_the_compiled_kernels_are_imported_by_the_first_sweep_only():
    """Importing the compressor does not import numba (a third of a second): a process
    that only reads a store never pays for it; the first sweep does."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, streamsvd as ss\n"
            "sc = ss.StreamCompressor(20, max_rank=2, oversampling=0)\n"
            "A = np.random.default_rng(0).standard_normal((20, 8))\n"
            "assert sc.absorb(A).sweeps == 0  # the Gram path: no sweep\n"
            "assert 'numba' not in sys.modules, 'imported before any sweep'\n"
            "sc.finalize()\n"
            "assert 'numba' in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)
