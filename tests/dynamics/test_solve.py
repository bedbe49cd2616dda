"""The DMD query and its certificate on linear systems with known eigenvalues."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import streamsvd as ss
from streamsvd.dynamics import dmd_from_pairs, pair_factor, pair_positions
from streamsvd.errors import InputError
from streamsvd.testing.systems import batch_dmd, match_eigenvalues, normal_system

EPS = np.finfo(float).eps


def _stream(X, block, **options):
    sc = ss.StreamCompressor(X.shape[0], dynamics=True, **options)
    for j in range(0, X.shape[1], block):
        sc.absorb(X[:, j:j + block])
    return sc


def _system(rng, n=40, pairs=3, real=(0.5,)):
    return normal_system(n, rng.uniform(0.85, 1.0, pairs), rng.uniform(0.1, 2.5, pairs), rng,
                         real=np.array(real))


def test_exact_data_gives_eigenvalues_to_rounding_with_small_eta(rng):
    sysm = _system(rng)
    X = sysm.trajectory(rng.standard_normal(7), 120)
    res = _stream(X, 16).dmd()
    assert res.rank == 7
    err = match_eigenvalues(res.eigenvalues, sysm.eigenvalues)
    assert np.max(err) < 1e3 * EPS
    assert np.all(err <= res.residual_bounds)  # the certificate (A normal)
    assert np.max(res.residual_bounds) < 1e-10  # informative on clean data


@pytest.mark.parametrize("exponent", [-996, -664, 664, 996])
def test_the_certificate_does_not_depend_on_the_scale(rng, exponent):
    """Data scaled by 2^exponent (1e-300 .. 1e300, exact): the same eigenvalues and
    bounds. ``||S^-1 w||`` was a norm of entries near 1e200 (data at 1e-200), whose
    squares overflow: ``eta`` was infinite; at 1e200 they underflowed and ``eta`` came
    out 0.6 times its value."""
    sysm = _system(rng)
    X = sysm.trajectory(rng.standard_normal(7), 120)
    ref = _stream(X, 16).dmd()
    res = _stream(np.ldexp(X, exponent), 16).dmd()
    np.testing.assert_allclose(res.eigenvalues, ref.eigenvalues, rtol=0, atol=1e3 * EPS)
    # the bounds are rounding-sized here (rho): the streams' roundings differ by 1%
    np.testing.assert_allclose(res.residual_bounds, ref.residual_bounds, rtol=0.05)
    err = match_eigenvalues(res.eigenvalues, sysm.eigenvalues)
    assert np.all(err <= res.residual_bounds)
    assert np.max(res.residual_bounds) < 1e-10


def test_a_direction_beyond_the_range_is_not_certified(rng):
    """Two noisy trajectories at 1e-300 under weights and forgetting, one snapshot per
    update: the noise (1e-310) is subnormal and ``||S^-1 w||`` of its directions passes
    1.8e308. With a bound of 0 that was ``0 * inf`` (a RuntimeWarning, an exception under
    ``-W error``; 40 of 40 seeds). Such an eigenvalue gets ``eta = inf``: nothing
    certified; the others keep their certificate."""
    n = 60
    sysm = normal_system(n, rng.uniform(0.85, 1.0, 2), rng.uniform(0.1, 2.5, 2), rng,
                         real=np.array([0.5]))
    sc = ss.StreamCompressor(n, dynamics=True, forget=0.97,
                             inner=10 ** rng.uniform(-2, 2, n))
    for t in range(2):
        X = sysm.trajectory(rng.standard_normal(5), 40, noise=1e-10, rng=rng) * 1e-300
        for j in range(40):
            sc.absorb(X[:, j:j + 1], new_trajectory=bool(t and not j))
    res = sc.dmd()
    eta = res.residual_bounds
    assert not np.isnan(eta).any() and np.isinf(eta).any()
    assert np.all(np.isfinite(res.eigenvalues))


def test_forecast_continues_the_trajectory(rng):
    sysm = _system(rng)
    X = sysm.trajectory(rng.standard_normal(7), 80)
    res = _stream(X, 10).dmd(dt=0.1)
    future = sysm.trajectory(sysm.Q.T @ X[:, -1], 6)
    F = res.forecast(np.arange(6))
    assert np.linalg.norm(F - future) <= 1e-10 * np.linalg.norm(future)
    assert np.allclose(np.exp(res.continuous_eigenvalues * 0.1), res.eigenvalues)
    assert res.modes.shape == (40, 7)
    assert np.allclose(np.linalg.norm(res.modes, axis=0), 1.0)


@given(seed=st.integers(0, 2**31 - 1), noise=st.sampled_from([0.0, 1e-8, 1e-4]),
       block=st.integers(1, 30), pairs=st.integers(1, 4), cut=st.booleans())
def test_no_certificate_violation(seed, noise, block, pairs, cut):
    """Every eigenvalue lies within eta of an eigenvalue of the true (normal) A."""
    rng = np.random.default_rng(seed)
    n = 24
    sysm = normal_system(n, rng.uniform(0.5, 1.0, pairs), rng.uniform(0.05, 3.0, pairs),
                         rng, real=rng.uniform(-0.9, 0.9, 1))
    k = sysm.D.shape[0]
    X = sysm.trajectory(rng.standard_normal(k), 60, noise=noise, rng=rng)
    delta = np.linalg.norm(sysm.apply(X[:, :-1]) - X[:, 1:])  # the model error, noise in it
    sc = _stream(X, block, **({"rtol": 1e-3} if cut else {}))
    res = sc.dmd(model_error=delta)
    spectrum = np.concatenate([sysm.eigenvalues, [0.0]])  # A = Q D Q^T is 0 beyond Q
    err = match_eigenvalues(res.eigenvalues, spectrum)
    assert np.all(err <= res.residual_bounds * (1 + 1e-12) + 1e-14)


@pytest.mark.parametrize("noise", [0.0, 1e-8, 1e-4])
def test_within_ten_times_the_batch_error(rng, noise):
    sysm = _system(rng, n=60)
    k = sysm.D.shape[0]
    X = sysm.trajectory(rng.standard_normal(k), 150, noise=noise, rng=rng)
    batch = batch_dmd(X, rank=k)
    res = _stream(X, 25).dmd(rank=k)
    e_batch = np.max(match_eigenvalues(batch, sysm.eigenvalues))
    e_stream = np.max(match_eigenvalues(res.eigenvalues, sysm.eigenvalues))
    assert e_stream <= 10 * e_batch + 1e3 * EPS


def test_pair_positions_skip_removed_and_trajectory_starts():
    first, second = pair_positions(np.array([0, 1, 2, 4, 5, 6, 7]), np.array([6]))
    assert first.tolist() == [0, 1, 3, 5]  # 2 -> 4 skips, 6 starts a trajectory
    assert second.tolist() == [1, 2, 4, 6]


def test_expansion_query_equals_the_compressor_query(rng):
    sysm = _system(rng)
    X = sysm.trajectory(rng.standard_normal(7), 50)
    sc = _stream(X, 7)
    a, b = sc.dmd(), ss.dmd(sc.expansion)
    assert np.allclose(np.sort_complex(a.eigenvalues), np.sort_complex(b.eigenvalues),
                       atol=1e-12)


def test_rank_cut_and_messages(rng):
    sysm = _system(rng)
    X = sysm.trajectory(rng.standard_normal(7), 40)
    sc = _stream(X, 40)
    assert sc.dmd(rank=3).rank == 3
    with pytest.raises(InputError, match="`rank` must be"):
        sc.dmd(rank=0)
    with pytest.raises(InputError, match="`dt` must be a finite number > 0"):
        sc.dmd(dt=-1.0)
    with pytest.raises(InputError, match="pass `dt` to the DMD query"):
        _ = sc.dmd().continuous_eigenvalues
    with pytest.raises(InputError, match="with `modes=True`"):
        sc.dmd(modes=False).forecast([1])
    one = ss.StreamCompressor(40, dynamics=True)
    one.absorb(X[:, :1])
    with pytest.raises(InputError, match="got 0 pairs"):
        one.dmd()
    cut = ss.StreamCompressor(40, dynamics=True, target_error=2 * np.linalg.norm(X),
                              error_measure="absolute")  # cuts every term
    cut.absorb(X)
    cut.finalize()
    assert cut.rank == 0
    with pytest.raises(InputError, match="39 pairs in a basis of rank 0: the\n?.*truncation"):
        cut.dmd()
    with pytest.raises(InputError, match="right_vectors=False. Pass `right_vectors=True`"):
        ss.StreamCompressor(40, dynamics=True, right_vectors=False)
    bare = ss.StreamCompressor(40, right_vectors=False)
    bare.absorb(X)
    with pytest.raises(InputError, match="create it with\n?.*`dynamics=True`"):
        bare.dmd()


def test_empty_pairs_factor():
    pf = pair_factor(np.zeros((3, 2)), np.zeros(0, dtype=int), np.zeros(0, dtype=int))
    with pytest.raises(InputError, match="got 0 pairs"):
        dmd_from_pairs(pf)
