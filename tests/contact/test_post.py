import numpy as np
import pytest

import contact


def sticking_state(mu, lam_T):
    """A block pressed on the floor (lam_N = -1, F = 1), not moving, with tangential
    tractions ``lam_T`` (one per contact node)."""
    P = contact.block(np.zeros(2), nx=4, ny=1, mu=mu)
    nc, m = P.nc, P.m
    w = np.zeros((2 * nc, m))
    lam = np.zeros((2 * nc, m))
    lam[:nc] = -1.0
    lam[nc:] = np.asarray(lam_T, dtype=float)[:, None]
    return P, w, lam


def test_an_admissible_state_has_no_violation():
    P, w, lam = sticking_state(0.1, [0.0, 0.05, -0.1, 0.1, 0.0])
    check = contact.check_laws(P, w, lam)
    assert check.worst() == 0.0
    assert check.dissipation == 0.0


def test_cone_violation_is_relative_to_the_admissible_tangential_traction():
    # |lam_T| = 1.05 mu |lam_N|: 5% outside the cone. Scaled by mu F the violation is
    # 0.05; scaled by F (10 times smaller with mu = 0.1) it would read as 0.005 and pass
    # a 1% tolerance.
    P, w, lam = sticking_state(0.1, [0.0, 0.0, -0.105, 0.0, 0.0])
    check = contact.check_laws(P, w, lam)
    assert check.cone == pytest.approx(0.05)
    assert check.worst() > 1e-2


def test_cone_violation_without_friction_is_relative_to_the_normal_traction():
    P, w, lam = sticking_state(0.0, [0.0, 0.02, 0.0, 0.0, 0.0])
    assert contact.check_laws(P, w, lam).cone == pytest.approx(0.02)


def test_slip_tests_are_relative_to_the_admissible_tangential_traction():
    P, w, lam = sticking_state(0.1, [0.0, 0.0, 0.0, 0.0, 0.0])
    nc = P.nc
    # node 0 is separated by 1 (so G = 1); node 2 slips by 1 at the second instant
    w[0], lam[0] = -1.0, 0.0
    w[nc + 2, 1] = 1.0
    # inside the cone, 5% of mu |lam_N| short of it: slip is not allowed there
    lam[nc + 2, 1] = -0.095
    assert contact.check_laws(P, w, lam).stick_slip == pytest.approx(0.05)
    # on the cone but along the slip: the traction must oppose it
    lam[nc + 2, 1] = 0.1
    check = contact.check_laws(P, w, lam)
    assert check.slip_direction == pytest.approx(1.0)
    assert check.cone == 0.0 and check.stick_slip == 0.0


def test_svd_in_a_metric_is_orthonormal_there_and_reconstructs():
    rng = np.random.default_rng(0)
    n, m, r = 30, 12, 8
    Y = rng.standard_normal((n, r)) @ rng.standard_normal((r, m))
    Y[:3] = 0.0  # rows where every column vanishes (prescribed dofs)
    B = rng.standard_normal((n, n))
    M = B @ B.T + n * np.eye(n)
    svd = contact.svd_modes(Y, inner=M)
    eps = np.finfo(float).eps
    assert svd.values.size == r
    X, T, s = svd.space, svd.time, svd.values
    scale = np.linalg.norm(M, 2)
    assert np.abs(X.T @ M @ X - np.eye(r)).max() < 100 * n * eps * np.linalg.cond(M)
    assert np.abs(T.T @ T - np.eye(r)).max() < 100 * m * eps
    assert np.linalg.norm((X * s) @ T.T - Y) < 100 * n * eps * np.linalg.norm(Y)
    assert np.abs(X[:3]).max() < 100 * n * eps * np.abs(X).max()
    # the singular values in M are those of the Cholesky factor times Y
    Rm = np.linalg.cholesky(M).T
    ref = np.linalg.svd(Rm @ Y, compute_uv=False)[:r]
    assert np.allclose(s, ref, rtol=100 * n * eps * np.sqrt(scale), atol=0)


def test_optimal_sizes_by_singular_value_ratio_and_by_tail_energy():
    values = np.array([1.0, 0.5, 1e-2, 1e-3, 1e-3, 1e-5])
    svd = contact.SVDModes(values, np.eye(6), np.eye(6))
    assert svd.rank(1e-3) == 5  # s_i >= 1e-3 s_1
    # ||Y - Y_r||_F <= rtol ||Y||_F with ||Y||_F = 1.118: the tail after 3 terms is
    # 1.41e-3, after 4 terms 1.00e-3
    assert svd.tail_rank(1e-3) == 4
    assert svd.tail_rank(2e-3) == 3
    assert svd.tail_rank(0.0) == 6
    assert svd.sizes(1e-3) == {"sigma_ratio": 5, "tail_energy": 4}


def test_indicator_metric_checks_its_arguments():
    with pytest.raises(contact.SolverOptionError, match="`problem` must be a contact.Problem"):
        contact.indicator_metric("billet")
    P = contact.billet(dt=0.5)
    with pytest.raises(contact.SolverOptionError, match="`k` must be a positive number"):
        contact.indicator_metric(P, k=-1.0)
    M = contact.indicator_metric(P)
    assert M.shape == (P.n, P.n)
    assert abs(M - M.T).max() <= 1e-15 * abs(M).max()
