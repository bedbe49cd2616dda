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
