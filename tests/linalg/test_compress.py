"""compress() converges to the SVD: LAPACK test ratios (threshold 50) on hard matrices."""

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings

import streamsvd as ss
from streamsvd.testing import assert_svd_contract, hard_matrices, low_rank_matrices, with_spectrum
from tests._examples import examples

EPS = np.finfo(float).eps
HARD = hard_matrices(np.random.default_rng(7))


def _both_starts(A):
    """The canonical expansion (U = I, V = A^T) and the Gram-Schmidt one (U = A, V = I)."""
    yield "canonical", ss.Expansion.canonical(A)
    yield "gram_schmidt", ss.orthonormalize(A, np.eye(A.shape[1])).expansion


@pytest.mark.parametrize("name", sorted(HARD))
def test_jacobi_rule_reaches_lapack_accuracy(name):
    A = HARD[name]
    for start, e in _both_starts(A):
        r = ss.compress(e, rule="jacobi", max_sweeps=60)
        assert r.converged, (name, start, r.max_cosine[-3:])
        assert_svd_contract(A, r.expansion)


PAPER_CASES = ["zero", "one_column", "one_row", "zero_columns", "identity",
               "geometric", "scaled_up", "scaled_down", "kahan",
               "lauchli", "rank_deficient_product", "graded_two_sided"]


@pytest.mark.parametrize("name", PAPER_CASES)
def test_paper_rule_reaches_lapack_accuracy(name):
    # the paper's alpha converges linearly at the rate of eq. (14): fine for separated
    # spectra, slow for close singular values (arithmetic spectra, Hilbert); those are
    # left to the jacobi rule
    A = HARD[name]
    e = ss.Expansion.canonical(A)
    r = ss.compress(e, rule="paper", max_sweeps=3000)
    assert r.converged, (name, r.sweeps, r.max_cosine[-3:])
    assert_svd_contract(A, r.expansion)


@pytest.mark.parametrize("name", ["repeated", "cluster_at_eps"])
def test_paper_rule_on_exactly_repeated_values_is_an_svd_whether_or_not_it_converges(name):
    # between equal amplitudes eta = 1, so eq. (14) gives no contraction: a rounding-level
    # coupling may stay above tol (whether it does depends on the rounding of the BLAS),
    # but it moves the singular values by less than LAPACK's ratio. cluster_at_eps holds
    # 20 values equal to eps: their pairs' cosines stay at 1e-6 relative to their own
    # norms, a coupling of 1e-38 against the largest value
    A = HARD[name]
    r = ss.compress(ss.Expansion.canonical(A), rule="paper", max_sweeps=3000)
    if name == "repeated":
        assert r.max_cosine[-1] < 1e3 * EPS
    assert_svd_contract(A, r.expansion)


def test_nearly_repeated_singular_values_give_the_right_cluster_projector(rng):
    s = np.r_[2.0, 1.0 + 1e-12, 1.0, 1.0 - 1e-12, 0.25, 0.1]
    A = with_spectrum(s, 30, 20, rng)
    r = ss.compress(ss.Expansion.canonical(A), rule="jacobi", max_sweeps=60)
    assert_svd_contract(A, r.expansion)
    Uref = scipy.linalg.svd(A)[0]
    P = r.expansion.U[:, 1:4] @ r.expansion.U[:, 1:4].T
    Pref = Uref[:, 1:4] @ Uref[:, 1:4].T
    gap = 0.75  # distance of the cluster to the rest of the spectrum
    assert np.linalg.norm(P - Pref, 2) <= 50 * 30 * EPS * s[0] / gap


@settings(max_examples=examples(25))
@given(low_rank_matrices())
def test_compress_matches_lapack_on_random_low_rank_matrices(A):
    e = ss.orthonormalize(A, np.eye(A.shape[1])).expansion
    r = ss.compress(e, rule="jacobi", max_sweeps=60)
    assert_svd_contract(A, r.expansion)


@pytest.mark.parametrize("rule", ["paper", "jacobi"])
def test_fast_path_gives_the_literal_iterates(rng, rule):
    A = with_spectrum(np.logspace(0, -4, 12), 25, 18, rng)
    e = ss.orthonormalize(A, np.eye(18)).expansion
    for sweeps in (1, 2, 5):
        f = ss.compress(e, rule=rule, max_sweeps=sweeps, tol=0.0)
        lit = ss.compress(e, rule=rule, max_sweeps=sweeps, tol=0.0, method="literal")
        assert np.allclose(f.expansion.U, lit.expansion.U, atol=1e-12)
        assert np.allclose(f.expansion.V, lit.expansion.V, atol=1e-12)
        np.testing.assert_allclose(f.indicator, lit.indicator, rtol=1e-9)


def test_eps_truncation_cuts_weak_modes_and_bounds_the_error(rng):
    s = np.logspace(0, -6, 15)
    A = with_spectrum(s, 40, 30, rng)
    e = ss.Expansion.canonical(A)
    optimal = np.sqrt(np.sum(s[s < 1e-3] ** 2))  # Eckart-Young
    for method in ("fast", "literal"):
        r = ss.compress(e, rule="jacobi", eps=1e-3, max_sweeps=60, method=method)
        # Algorithm 3 cuts during the sweeps, before the amplitudes have converged, so it
        # may cut a term whose singular value is above eps; never one it keeps
        assert r.expansion.rank <= np.count_nonzero(s >= 1e-3)
        assert np.all(r.expansion.amplitudes >= 1e-3)
        err = np.linalg.norm(A - r.expansion.to_dense())
        # the cuts are orthogonal to each other: the bound is the exact error
        assert r.error_bound == pytest.approx(err, rel=1e-6)
        assert err >= optimal * (1 - 1e-9)
    # converging first and cutting afterwards gives the optimal truncation
    full = ss.compress(e, rule="jacobi", max_sweeps=60).expansion
    cut = ss.compress(full, rule="jacobi", eps=1e-3, max_sweeps=60)
    assert cut.expansion.rank == np.count_nonzero(s >= 1e-3)
    assert cut.error_bound == pytest.approx(optimal, rel=1e-6)


def test_paper_rule_eps_cut_during_sweeps_keeps_bound_exact(rng):
    A = with_spectrum(np.logspace(0, -8, 25), 30, 30, rng)
    r = ss.compress(ss.Expansion.canonical(A), rule="paper", eps=1e-4, max_sweeps=4)
    err = np.linalg.norm(A - r.expansion.to_dense())
    assert r.discarded_energy > 0
    assert r.error_bound == pytest.approx(err, rel=1e-6)


def test_indicator_and_callback(rng):
    A = with_spectrum(np.logspace(0, -3, 10), 20, 20, rng)
    seen = []
    r = ss.compress(ss.Expansion.canonical(A), callback=seen.append, max_sweeps=500)
    assert [s.sweep for s in seen] == list(range(1, r.sweeps + 1))
    assert r.indicator.shape == (r.sweeps,)
    assert r.indicator[-1] < 1e-10 < r.indicator[0]
    stopped = ss.compress(ss.Expansion.canonical(A), callback=lambda s: s.sweep == 3)
    assert stopped.sweeps == 3 and not stopped.converged


def test_signs_are_deterministic(rng):
    A = rng.standard_normal((12, 9))
    r1 = ss.compress(ss.Expansion.canonical(A), rule="jacobi").expansion
    r2 = ss.compress(ss.orthonormalize(A, np.eye(9)).expansion, rule="jacobi").expansion
    # the canonical start carries 3 extra terms of zero amplitude (n = 12 > m = 9)
    np.testing.assert_allclose(r1.U[:, :9], r2.U, atol=1e-12)
    np.testing.assert_allclose(r1.V[:, :9], r2.V, atol=1e-12)


@pytest.mark.parametrize(
    "kwargs,match",
    [({"rule": "qr"}, r"`rule` must be one of \('paper', 'jacobi'\); got str 'qr'"),
     ({"eps": -1.0}, r"`eps` must be a finite number >= 0; got -1.0"),
     ({"max_sweeps": 0}, r"`max_sweeps` must be an integer >= 1; got int 0"),
     ({"method": "fastest"}, r"`method` must be one of"),
     ({"tol": float("nan")}, r"`tol` must be a finite number >= 0")],
)
def test_bad_options_are_refused(rng, kwargs, match):
    e = ss.Expansion.canonical(rng.standard_normal((4, 3)))
    with pytest.raises(ss.InputError, match=match):
        ss.compress(e, **kwargs)


def test_non_expansion_is_refused():
    with pytest.raises(ss.InputError, match=r"`expansion` must be a streamsvd.Expansion; got ndarray"):
        ss.compress(np.eye(3))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_nan_or_inf_is_refused_before_any_work(bad):
    V = np.ones((5, 3))
    V[2, 1] = bad
    with pytest.raises(ss.NonFiniteError, match=r"`V` must be finite; got 1 NaN or infinite entries, the first at index \(2, 1\)"):
        ss.Expansion(np.eye(4, 3), V)
    with pytest.raises(ss.NonFiniteError, match=r"`U` must be finite"):
        ss.orthonormalize(V, np.eye(3))


@pytest.mark.parametrize("name", sorted(HARD))
def test_preconditioned_sweeps_reach_lapack_accuracy(name):
    A = HARD[name]
    for start, e in _both_starts(A):
        for At, f in ((A, e), (A.T, ss.Expansion.canonical(A.T))):  # V tall and wide
            r = ss.compress(f, rule="jacobi", max_sweeps=60, precondition=True)
            assert r.converged, (name, start, r.max_cosine[-3:])
            assert_svd_contract(At, r.expansion)


def test_preconditioning_keeps_cuts_and_wide_factors():
    rng = np.random.default_rng(3)
    A = with_spectrum(np.logspace(0, -12, 20), 30, 20, rng)
    e = ss.Expansion.canonical(A)
    r = ss.compress(e, rule="jacobi", eps=1e-6, precondition=True)
    plain = ss.compress(e, rule="jacobi", eps=1e-6)
    assert r.expansion.rank == plain.expansion.rank
    np.testing.assert_allclose(r.expansion.amplitudes, plain.expansion.amplitudes,
                               rtol=0, atol=100 * 30 * EPS)
    assert np.linalg.norm(A - r.expansion.U @ r.expansion.V.T) <= r.error_bound + 100 * 30 * EPS
    # more terms than rows of V: the plain start (nothing to precondition)
    W = ss.Expansion(np.linalg.qr(rng.standard_normal((40, 25)))[0], rng.standard_normal((10, 25)))
    w = ss.compress(W, rule="jacobi", precondition=True)
    assert w.converged


@pytest.mark.slow
def test_rbs480a_preconditioned_to_lapack_accuracy(rbs480a_path):
    import scipy.io

    A = scipy.io.mmread(rbs480a_path).toarray()
    r = ss.compress(ss.Expansion.canonical(A), rule="jacobi", max_sweeps=40, precondition=True)
    assert r.converged
    assert_svd_contract(A, r.expansion)
    assert r.expansion.amplitudes[0] == pytest.approx(857.4829, rel=1e-6)


@pytest.mark.slow
def test_rbs480a_converges_to_lapack_accuracy(rbs480a_path):
    import scipy.io

    A = scipy.io.mmread(rbs480a_path).toarray()
    r = ss.compress(ss.Expansion.canonical(A), rule="jacobi", max_sweeps=40)
    assert r.converged
    assert_svd_contract(A, r.expansion)
    assert r.expansion.amplitudes[0] == pytest.approx(857.4829, rel=1e-6)


@pytest.mark.parametrize("rule", ["paper", "jacobi"])
def test_fast_path_orders_exact_ties_as_the_literal_path(rng, rule):
    # integer rows with equal norms (as in rbs480a): exact ties in the sort of Algorithm 2
    bases = rng.integers(-9, 10, size=(3, 40)).astype(float)
    A = np.vstack([np.roll(bases[k % 3], k) for k in range(30)])  # 3 norms, 10 rows each
    assert np.unique(np.sum(A**2, axis=1)).size == 3
    e = ss.Expansion.canonical(A)
    for sweeps in (1, 2):
        f = ss.compress(e, rule=rule, max_sweeps=sweeps, tol=0.0)
        lit = ss.compress(e, rule=rule, max_sweeps=sweeps, tol=0.0, method="literal")
        s1 = lit.expansion.amplitudes[0]
        np.testing.assert_allclose(f.expansion.amplitudes, lit.expansion.amplitudes, atol=1e-12 * s1)
