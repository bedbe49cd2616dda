import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from contact import local_stage

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_subnormal=False)


@st.composite
def local_inputs(draw):
    nc = draw(st.integers(1, 5))
    m = draw(st.integers(1, 8))
    w = draw(arrays(np.float64, (2 * nc, m), elements=finite))
    lam = draw(arrays(np.float64, (2 * nc, m), elements=finite))
    gaps = draw(arrays(np.float64, (nc,), elements=st.floats(0.0, 2.0)))
    k = draw(st.floats(0.1, 10.0))
    mu = draw(st.floats(0.0, 1.0))
    return w, lam, gaps, k, mu


def assert_in_gamma(w, lam, gaps, mu, scale):
    nc = gaps.size
    tol = 1e-12 * scale
    wN, wT, lN, lT = w[:nc], w[nc:], lam[:nc], lam[nc:]
    g = gaps[:, None] - wN
    assert np.all(g >= -tol), "penetration"
    assert np.all(lN <= tol), "tensile normal traction"
    assert np.all(np.abs(lN * g) <= tol * scale), "complementarity"
    assert np.all(np.abs(lT) <= -mu * lN + tol), "outside the friction cone"
    dwT = np.diff(np.concatenate([np.zeros((nc, 1)), wT], axis=1), axis=1)
    assert np.all(lT * dwT <= tol * scale), "slip along the tangential traction"
    slipping = np.abs(dwT) > tol
    assert np.all(np.abs(np.abs(lT[slipping]) + mu * lN[slipping]) <= tol * 10), \
        "slip inside the cone"


@given(local_inputs())
def test_output_satisfies_the_contact_and_friction_laws(data):
    w, lam, gaps, k, mu = data
    w_hat, lam_hat = local_stage(w, lam, k=k, gaps=gaps, mu=mu)
    scale = 1.0 + k * (np.abs(w).max() + gaps.max()) + np.abs(lam).max()
    assert_in_gamma(w_hat, lam_hat, gaps, mu, scale)


@given(local_inputs())
def test_output_lies_on_the_ascent_search_direction(data):
    w, lam, gaps, k, mu = data
    w_hat, lam_hat = local_stage(w, lam, k=k, gaps=gaps, mu=mu)
    scale = 1.0 + k * (np.abs(w).max() + gaps.max()) + np.abs(lam).max()
    assert np.allclose(lam_hat - lam, k * (w_hat - w), atol=1e-12 * scale)


@given(local_inputs())
def test_idempotent_on_admissible_input(data):
    w, lam, gaps, k, mu = data
    w_hat, lam_hat = local_stage(w, lam, k=k, gaps=gaps, mu=mu)
    w2, lam2 = local_stage(w_hat, lam_hat, k=k, gaps=gaps, mu=mu)
    scale = 1.0 + k * (np.abs(w).max() + gaps.max()) + np.abs(lam).max()
    assert np.allclose(w2, w_hat, atol=1e-12 * scale / k)
    assert np.allclose(lam2, lam_hat, atol=1e-12 * scale)


def test_explicit_cases_contact_separation_stick_slip():
    gaps = np.array([0.1])
    k, mu = 2.0, 0.5
    # penetrating and sliding: contact, then slip
    w = np.array([[0.3, 0.3], [0.0, 1.0]])
    lam = np.zeros((2, 2))
    w_hat, lam_hat = local_stage(w, lam, k=k, gaps=gaps, mu=mu)
    assert np.allclose(w_hat[0], 0.1)
    assert np.allclose(lam_hat[0], k * (0.1 - 0.3))
    assert lam_hat[1, 0] == 0.0 and w_hat[1, 0] == 0.0  # nothing to resist at t0
    assert np.isclose(lam_hat[1, 1], -mu * 0.4)  # slip: on the cone, against the motion
    assert w_hat[1, 1] > 0
    # separated: zero traction, displacement follows the direction
    w_hat, lam_hat = local_stage(np.array([[-1.0], [0.5]]), np.zeros((2, 1)), k=k,
                                 gaps=gaps, mu=mu)
    assert lam_hat[0, 0] == 0.0 and lam_hat[1, 0] == 0.0
    assert w_hat[0, 0] == -1.0 and w_hat[1, 0] == 0.5
    # stick: small tangential trial inside the cone
    w_hat, lam_hat = local_stage(np.array([[0.3], [0.01]]), np.zeros((2, 1)), k=k,
                                 gaps=gaps, mu=mu)
    assert w_hat[1, 0] == 0.0
    assert np.isclose(lam_hat[1, 0], -k * 0.01)
