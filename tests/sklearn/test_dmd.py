"""StreamingDMD: partial_fit over any split equals fit; predictions; messages."""

import numpy as np
import pytest

from streamsvd.errors import FloatRangeError, InputError
from streamsvd.sklearn import StreamingDMD
from streamsvd.sklearn._model import NotFittedError
from streamsvd.testing.systems import match_eigenvalues, normal_system


def _samples(rng, m=60):
    sysm = normal_system(25, np.array([0.97, 0.9]), np.array([0.4, 1.4]), rng)
    return sysm, sysm.trajectory(rng.standard_normal(4), m).T  # samples are rows


def test_partial_fit_over_any_split_equals_fit(rng):
    sysm, X = _samples(rng)
    whole = StreamingDMD(dt=0.1).fit(X)
    parts = StreamingDMD(dt=0.1)
    for a, b in [(0, 7), (7, 30), (30, 60)]:
        parts.partial_fit(X[a:b])
    assert np.allclose(np.sort_complex(whole.eigenvalues_), np.sort_complex(parts.eigenvalues_),
                       atol=1e-12)
    assert np.max(match_eigenvalues(whole.eigenvalues_, sysm.eigenvalues)) < 1e-12
    assert np.all(whole.residual_bounds_ < 1e-10)
    assert whole.modes_.shape == (4, 25) and whole.n_samples_seen_ == 60
    future = sysm.trajectory(sysm.Q.T @ X[-1], 4).T[1:]
    assert np.allclose(whole.predict(3), future, atol=1e-10)
    assert whole.continuous_eigenvalues_.shape == (4,)


def test_trajectories_and_refit(rng):
    sysm, X = _samples(rng, 30)
    est = StreamingDMD().fit(X[:15])
    est.partial_fit(X[15:] + 1.0, new_trajectory=True)  # another run: no pair across
    assert est.result_.pairs == 28
    est.fit(X)
    assert est.result_.pairs == 29


def test_messages(rng):
    _, X = _samples(rng, 10)
    with pytest.raises(NotFittedError, match="not fitted yet"):
        StreamingDMD().predict(2)
    with pytest.raises(InputError, match="`X` must be a 2-D array"):
        StreamingDMD().fit(X[0])
    est = StreamingDMD().fit(X)
    with pytest.raises(InputError, match="`X` must have 25 features"):
        est.partial_fit(X[:, :3])
    with pytest.raises(InputError, match="`n_steps` must be an integer >= 1"):
        est.predict(0)
    with pytest.raises(InputError, match="unknown parameter `bogus`"):
        est.set_params(bogus=1)
    assert est.set_params(rank=2).get_params()["rank"] == 2
    with pytest.raises(FloatRangeError, match="^`X` would take the expansion beyond"):
        StreamingDMD().partial_fit(np.full((4, 25), 1e308 / 5.0))  # rows of norm 1e308
