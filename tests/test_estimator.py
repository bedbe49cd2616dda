"""StreamingSVD: scikit-learn conventions, partial_fit == fit, centering as IncrementalPCA."""

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.estimator import NotFittedError, StreamingSVD
from streamsvd.testing import with_spectrum

EPS = np.finfo(float).eps


def _data(rng, n_samples=120, n_features=30):
    return with_spectrum(np.logspace(0, -6, 20), n_samples, n_features, rng) + 0.3


@pytest.mark.parametrize("splits", [[120], [1] * 120, [7, 50, 63], [60, 60]])
@pytest.mark.parametrize("center", [False, True])
def test_partial_fit_over_any_split_equals_fit(rng, splits, center):
    X = _data(rng)
    full = StreamingSVD(center=center).fit(X)
    inc = StreamingSVD(center=center)
    start = 0
    for size in splits:
        inc.partial_fit(X[start : start + size])
        start += size
    assert inc.n_samples_seen_ == full.n_samples_seen_ == 120
    k = 20
    s1 = full.singular_values_[0]
    np.testing.assert_allclose(
        inc.singular_values_[:k], full.singular_values_[:k], rtol=0, atol=50 * 120 * EPS * s1
    )
    np.testing.assert_allclose(inc.mean_, full.mean_, rtol=1e-13, atol=1e-15)
    # compare the well-separated leading subspace through projectors
    P1 = inc.components_[:10].T @ inc.components_[:10]
    P2 = full.components_[:10].T @ full.components_[:10]
    assert np.linalg.norm(P1 - P2, 2) <= 1e-10


def test_uncentered_is_the_truncated_svd(rng):
    X = _data(rng)
    est = StreamingSVD(n_components=5).fit(X)
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    np.testing.assert_allclose(est.singular_values_, s[:5], rtol=1e-12)
    np.testing.assert_allclose(np.abs(est.components_ @ Vt[:5].T), np.eye(5), atol=1e-10)
    Z = est.transform(X)
    np.testing.assert_allclose(np.abs(Z), np.abs(U[:, :5] * s[:5]), rtol=1e-9, atol=1e-12)
    X5 = est.inverse_transform(Z)
    assert np.linalg.norm(X - X5) == pytest.approx(np.sqrt(np.sum(s[5:] ** 2)), rel=1e-8)


def test_centered_matches_scikit_learn_pca_and_incremental_pca(rng):
    skd = pytest.importorskip("sklearn.decomposition")
    X = _data(rng)
    pca = skd.PCA(svd_solver="full").fit(X)
    # untruncated: the exact PCA of all the data, whatever the batches
    ours = StreamingSVD(center=True)
    for j in range(0, 120, 20):
        ours.partial_fit(X[j : j + 20])
    s1 = pca.singular_values_[0]
    np.testing.assert_allclose(ours.mean_, pca.mean_, rtol=1e-13)
    np.testing.assert_allclose(ours.singular_values_[:20], pca.singular_values_[:20], atol=50 * 120 * EPS * s1)
    np.testing.assert_allclose(ours.explained_variance_ratio_[:20], pca.explained_variance_ratio_[:20], atol=1e-12)
    np.testing.assert_allclose(np.abs(ours.components_[:6] @ pca.components_[:6].T), np.eye(6), atol=1e-9)
    # truncated to 6 after every batch: as accurate as IncrementalPCA, within sigma_7
    ours6 = StreamingSVD(n_components=6, center=True)
    ipca = skd.IncrementalPCA(n_components=6)
    for j in range(0, 120, 20):
        ours6.partial_fit(X[j : j + 20])
        ipca.partial_fit(X[j : j + 20])
    err_ours = np.abs(ours6.singular_values_ - pca.singular_values_[:6])
    err_ipca = np.abs(ipca.singular_values_ - pca.singular_values_[:6])
    assert np.all(err_ours <= pca.singular_values_[6])
    assert np.max(err_ours) <= np.max(err_ipca) * (1 + 1e-6) + 50 * 120 * EPS * s1


def test_float_n_components_selects_by_explained_variance(rng):
    X = _data(rng)
    est = StreamingSVD(n_components=0.99, center=True).fit(X)
    cum = np.cumsum(est.explained_variance_ratio_)
    assert cum[-1] >= 0.99 and (len(cum) == 1 or cum[-2] < 0.99)


def test_not_fitted_and_bad_arguments(rng):
    est = StreamingSVD()
    with pytest.raises(NotFittedError, match="not fitted yet"):
        est.transform(np.ones((2, 3)))
    est.fit(_data(rng))
    with pytest.raises(ss.ShapeMismatchError, match=r"X has 4 features, but StreamingSVD is expecting 30"):
        est.transform(np.ones((2, 4)))
    with pytest.raises(ss.InputError, match=r"`n_components` must be None, an int >= 1 or a float in \(0, 1\); got 1.5"):
        StreamingSVD(n_components=1.5).fit(np.ones((3, 3)))
    with pytest.raises(ss.NonFiniteError, match=r"`X` must be finite"):
        StreamingSVD().fit(np.full((3, 3), np.nan))


def _sklearn_checks():
    try:
        from sklearn.utils.estimator_checks import parametrize_with_checks
    except ImportError:  # scikit-learn is an optional test dependency
        return pytest.mark.skip(reason="scikit-learn not installed")
    return parametrize_with_checks(
        [StreamingSVD(), StreamingSVD(n_components=2, center=True),
         StreamingSVD(n_components=0.9, rule="paper", sweeps=2)]
    )


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.SkipTestWarning")
@_sklearn_checks()
def test_scikit_learn_estimator_checks(estimator, check):
    check(estimator)
