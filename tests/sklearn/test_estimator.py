"""StreamingSVD: scikit-learn conventions, partial_fit == fit, parity with IncrementalPCA.

scikit-learn's own IncrementalPCA tests run against the estimator in
``test_estimator_sklearn_port.py``; this module checks what they do not: equality with
IncrementalPCA to rounding, the options' semantics, validation messages and the flat cost.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import streamsvd as ss
from streamsvd.errors import SparseInputError
from streamsvd.io.sources import Source
from streamsvd.sklearn.estimator import NotFittedError, StreamingSVD
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum

EPS = np.finfo(float).eps


def _data(rng, n_samples=120, n_features=30):
    return with_spectrum(np.logspace(0, -6, 20), n_samples, n_features, rng) + 0.3


def _noisy(rng, n_samples=120, n_features=30):
    return _data(rng, n_samples, n_features) + 0.01 * rng.standard_normal((n_samples, n_features))


def _feed(est, X, size):
    for j in range(0, X.shape[0], size):
        est.partial_fit(X[j : j + size])
    return est


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
    assert inc.n_components_ == full.n_components_ == 30  # min(n_samples, n_features)
    k = 20
    s1 = full.singular_values_[0]
    np.testing.assert_allclose(
        inc.singular_values_[:k], full.singular_values_[:k], rtol=0, atol=50 * 120 * EPS * s1
    )
    np.testing.assert_allclose(inc.mean_, full.mean_, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(inc.var_, full.var_, rtol=1e-12, atol=1e-15)
    # compare the well-separated leading subspace through projectors
    P1 = inc.components_[:10].T @ inc.components_[:10]
    P2 = full.components_[:10].T @ full.components_[:10]
    assert np.linalg.norm(P1 - P2, 2) <= 1e-10


def test_uncentered_is_the_truncated_svd(rng):
    X = _data(rng)
    est = StreamingSVD(n_components=5, center=False).fit(X)
    U, s, Vt = np.linalg.svd(X, full_matrices=False)
    np.testing.assert_allclose(est.singular_values_, s[:5], rtol=1e-12)
    np.testing.assert_allclose(np.abs(est.components_ @ Vt[:5].T), np.eye(5), atol=1e-10)
    np.testing.assert_array_equal(est.mean_, np.zeros(30))
    Z = est.transform(X)
    np.testing.assert_allclose(np.abs(Z), np.abs(U[:, :5] * s[:5]), rtol=1e-9, atol=1e-12)
    X5 = est.inverse_transform(Z)
    assert np.linalg.norm(X - X5) == pytest.approx(np.sqrt(np.sum(s[5:] ** 2)), rel=1e-8)


def test_centered_matches_scikit_learn_pca_and_incremental_pca(rng):
    skd = pytest.importorskip("sklearn.decomposition")
    X = _data(rng)
    pca = skd.PCA(svd_solver="full").fit(X)
    # untruncated: the exact PCA of all the data, whatever the batches
    ours = _feed(StreamingSVD(), X, 20)
    s1 = pca.singular_values_[0]
    np.testing.assert_allclose(ours.mean_, pca.mean_, rtol=1e-13)
    np.testing.assert_allclose(ours.singular_values_[:20], pca.singular_values_[:20], atol=50 * 120 * EPS * s1)
    np.testing.assert_allclose(ours.explained_variance_ratio_[:20], pca.explained_variance_ratio_[:20], atol=1e-12)
    np.testing.assert_allclose(np.abs(ours.components_[:6] @ pca.components_[:6].T), np.eye(6), atol=1e-9)
    # truncated to 6 after every batch: as accurate as IncrementalPCA, within sigma_7
    ours6 = _feed(StreamingSVD(n_components=6), X, 20)
    ipca = _feed(skd.IncrementalPCA(n_components=6), X, 20)
    err_ours = np.abs(ours6.singular_values_ - pca.singular_values_[:6])
    err_ipca = np.abs(ipca.singular_values_ - pca.singular_values_[:6])
    assert np.all(err_ours <= pca.singular_values_[6])
    assert np.max(err_ours) <= np.max(err_ipca) * (1 + 1e-6) + 50 * 120 * EPS * s1


@pytest.mark.parametrize("k", [1, 6, 20])
def test_truncated_partial_fit_equals_incremental_pca_to_rounding(rng, k):
    """Same batches, same truncation after each: the same numbers (Brand's update)."""
    skd = pytest.importorskip("sklearn.decomposition")
    X = _noisy(rng)
    ours = _feed(StreamingSVD(n_components=k), X, 20)
    ipca = _feed(skd.IncrementalPCA(n_components=k), X, 20)
    s1 = ipca.singular_values_[0]
    tol = 50 * 120 * EPS
    assert ours.n_components_ == ipca.n_components_ == k
    np.testing.assert_allclose(ours.singular_values_, ipca.singular_values_, rtol=0, atol=tol * s1)
    np.testing.assert_allclose(ours.components_[: min(k, 5)], ipca.components_[: min(k, 5)], atol=tol)
    np.testing.assert_allclose(ours.explained_variance_, ipca.explained_variance_, rtol=tol)
    np.testing.assert_allclose(ours.explained_variance_ratio_, ipca.explained_variance_ratio_, rtol=tol)
    np.testing.assert_allclose(ours.mean_, ipca.mean_, rtol=tol)
    np.testing.assert_allclose(ours.var_, ipca.var_, rtol=tol)
    assert ours.n_samples_seen_ == ipca.n_samples_seen_
    Xt = X[:7] + 1.0
    np.testing.assert_allclose(ours.transform(Xt)[:, :5], ipca.transform(Xt)[:, :5], atol=tol * 10)


def test_fit_batches_as_incremental_pca(rng):
    skd = pytest.importorskip("sklearn.decomposition")
    from sklearn.utils import gen_batches

    for n, size, low in [(7, 3, 0), (7, 3, 2), (6, 3, 0), (2, 3, 0), (100, 20, 20), (101, 20, 5),
                         (25, 10, 17), (20, 10, 15)]:
        blocks = Source(np.zeros((1, n)), "x").blocks(size, min_last=low, prefetch=False)
        ours = [slice(a, a + X.shape[1]) for a, X in blocks]
        assert ours == list(gen_batches(n, size, min_batch_size=low))
    X = rng.standard_normal((300, 12)) @ rng.standard_normal((12, 12)) + 1.0
    ours = StreamingSVD(n_components=4).fit(X)
    ipca = skd.IncrementalPCA(n_components=4).fit(X)
    assert ours.batch_size_ == ipca.batch_size_ == 60
    np.testing.assert_allclose(ours.singular_values_, ipca.singular_values_, rtol=1e-12)
    np.testing.assert_allclose(ours.components_, ipca.components_, atol=1e-12)


@pytest.mark.parametrize("frac", [0.5, 0.9, 0.99, 0.999999])
def test_float_n_components_follows_pca(rng, frac):
    skd = pytest.importorskip("sklearn.decomposition")
    X = _noisy(rng)
    est = _feed(StreamingSVD(n_components=frac), X, 25)
    pca = skd.PCA(n_components=frac, svd_solver="full").fit(X)
    assert est.n_components_ == pca.n_components_
    cum = np.cumsum(est.explained_variance_ratio_)
    assert cum[-1] > frac and (len(cum) == 1 or cum[-2] <= frac)
    assert est.transform(X).shape == (120, est.n_components_)


def test_int_n_components_always_gives_k_orthonormal_components(rng):
    # rank 2 (centred: rank 1) data in 10 features: the other directions are padded
    X = rng.standard_normal((40, 2)) @ rng.standard_normal((2, 10)) + 2.0
    for est in (StreamingSVD(n_components=5).fit(X), _feed(StreamingSVD(n_components=5), X, 5)):
        assert est.n_components_ == 5 and est.components_.shape == (5, 10)
        np.testing.assert_allclose(est.components_ @ est.components_.T, np.eye(5), atol=1e-13)
        assert np.all(est.singular_values_[2:] <= 1e-12 * est.singular_values_[0])
        assert est.transform(X).shape == (40, 5)
        # the padded directions are deterministic and signed like the others
        rows = est.components_
        assert np.all(rows[np.arange(5), np.argmax(np.abs(rows), axis=1)] > 0)
        assert est.noise_variance_ <= 50 * 10 * EPS * np.sum(est.var_)  # rounding of a difference
    # zero data: k zero-variance directions, still orthonormal
    Z = StreamingSVD(n_components=3).fit(np.zeros((4, 6)))
    np.testing.assert_allclose(Z.components_ @ Z.components_.T, np.eye(3), atol=1e-15)
    np.testing.assert_array_equal(Z.singular_values_, np.zeros(3))
    # n_components=None: min(n_samples_seen_, n_features_in_), as PCA on what was seen
    est = StreamingSVD().partial_fit(X[:4])
    assert est.n_components_ == 4
    est.partial_fit(X[4:20])
    assert est.n_components_ == 10


def test_inner_product_components_and_coordinates(rng):
    X = rng.standard_normal((60, 12)) @ np.diag(np.logspace(0, -3, 12)) + 1.0
    w = rng.uniform(0.5, 2.0, 12)
    est = StreamingSVD(n_components=12, inner=w).fit(X)
    C = est.components_
    np.testing.assert_allclose((C * w) @ C.T, np.eye(12), atol=1e-12)  # M-orthonormal
    np.testing.assert_allclose(est.inverse_transform(est.transform(X)), X, atol=1e-11)
    # padded directions are M-orthonormal too
    low = StreamingSVD(n_components=6, inner=w).fit(np.outer(X[:, 0], np.ones(12)))
    Cl = low.components_
    np.testing.assert_allclose((Cl * w) @ Cl.T, np.eye(6), atol=1e-12)


def test_set_params_between_partial_fit_calls(rng):
    X = _noisy(rng)
    est = StreamingSVD(n_components=6).partial_fit(X[:40])
    before = (est.n_samples_seen_, est.components_.copy(), est.compressor_.n_seen)
    refused = [
        ("n_components", 4, r"`n_components` must stay 6 between calls to partial_fit .*got 4"),
        ("tol", 1e-3, r"`tol` must stay None between calls to partial_fit .*got 0.001"),
        ("center", False, r"`center` must stay True .*got False"),
        ("rule", "paper", r"`rule` must stay 'jacobi' .*got 'paper'"),
        ("sweeps", 2, r"`sweeps` must stay None .*got 2"),
        ("inner", np.full(30, 2.0), r"`inner` must stay Euclidean\(\) .*got DiagonalInner"),
    ]
    for name, value, msg in refused:
        old = est.get_params()[name]
        est.set_params(**{name: value})
        with pytest.raises(ss.InputError, match=msg):
            est.partial_fit(X[40:60])
        assert est.n_samples_seen_ == before[0] and est.compressor_.n_seen == before[2]
        np.testing.assert_array_equal(est.components_, before[1])
        est.set_params(**{name: old})
    est.set_params(inner=ss.Euclidean())  # another object, the same inner product: accepted
    est.partial_fit(X[40:60])
    # options that the state does not depend on apply at once
    Z = est.transform(X)
    est.set_params(whiten=True)
    np.testing.assert_allclose(est.transform(X), Z / np.sqrt(est.explained_variance_))
    est.set_params(batch_size=7, n_components=3)
    est.fit(X)
    assert est.batch_size_ == 7 and est.n_components_ == 3


def test_fit_resets_everything(rng):
    X = _noisy(rng)
    est = StreamingSVD(n_components=4).fit(X)
    est.fit(X[:, :12])
    assert est.n_features_in_ == 12 and est.components_.shape == (4, 12)
    assert est.n_samples_seen_ == 120 and est.mean_.shape == (12,)
    ref = StreamingSVD(n_components=4).fit(X[:, :12])
    np.testing.assert_allclose(est.singular_values_, ref.singular_values_, rtol=1e-14)
    with pytest.raises(ss.ShapeMismatchError, match="X has 30 features, but StreamingSVD is expecting 12"):
        est.partial_fit(X)


@pytest.mark.parametrize("container", [sp.csr_matrix, sp.csc_matrix, sp.coo_matrix, sp.lil_matrix, sp.csr_array])
def test_sparse_fit_and_transform_equal_dense(rng, container):
    X = _noisy(rng)
    X[np.abs(X) < 0.3] = 0.0
    S = container(X)
    dense = StreamingSVD(n_components=5, batch_size=32).fit(X)
    sparse = StreamingSVD(n_components=5, batch_size=32).fit(S)
    np.testing.assert_allclose(sparse.singular_values_, dense.singular_values_, rtol=1e-13)
    np.testing.assert_allclose(sparse.components_, dense.components_, atol=1e-13)
    np.testing.assert_allclose(sparse.transform(S), dense.transform(X), atol=1e-12)
    with pytest.raises(SparseInputError, match=r"`X` must be dense in `partial_fit`"):
        sparse.partial_fit(S)
    with pytest.raises(TypeError):
        sparse.partial_fit(S)


def test_whiten(rng):
    X = _noisy(rng)
    est = StreamingSVD(n_components=8, whiten=True).fit(X)
    Z = est.transform(X)
    np.testing.assert_allclose(Z.var(axis=0, ddof=1), np.ones(8), rtol=1e-10)
    np.testing.assert_allclose(Z.mean(axis=0), np.zeros(8), atol=1e-12)
    full = StreamingSVD(n_components=30, whiten=True).fit(X)
    np.testing.assert_allclose(full.inverse_transform(full.transform(X)), X, atol=1e-10)


def test_noise_variance_covariance_and_precision_as_pca(rng):
    skd = pytest.importorskip("sklearn.decomposition")
    X = _noisy(rng)
    for k in (3, 10, 30):
        # one batch: the exact PCA, so every model quantity equals PCA's to rounding
        est = StreamingSVD(n_components=k, batch_size=120).fit(X)
        pca = skd.PCA(n_components=k, svd_solver="full").fit(X)
        np.testing.assert_allclose(est.noise_variance_, pca.noise_variance_, rtol=1e-10, atol=1e-18)
        np.testing.assert_allclose(est.get_covariance(), pca.get_covariance(), rtol=1e-9, atol=1e-16)
        cov, prec = est.get_covariance(), est.get_precision()
        np.testing.assert_allclose(cov @ prec, np.eye(30), atol=1e-8)
        # the generative model does not depend on whitening, which changes the transform only
        white = StreamingSVD(n_components=k, batch_size=120, whiten=True).fit(X)
        np.testing.assert_allclose(white.get_covariance(), cov, rtol=1e-12, atol=1e-18)
    # streamed and truncated: the noise is the mean variance left out of the k kept
    est = _feed(StreamingSVD(n_components=5), X, 20)
    total = np.sum(est.var_) * 120 / 119
    expected = (total - np.sum(est.explained_variance_)) / (30 - 5)
    assert est.noise_variance_ == pytest.approx(expected, rel=1e-10, abs=0)


def test_feature_names_out(rng):
    est = StreamingSVD(n_components=3).fit(_noisy(rng))
    np.testing.assert_array_equal(
        est.get_feature_names_out(), np.array(["streamingsvd0", "streamingsvd1", "streamingsvd2"], dtype=object)
    )
    assert est.get_feature_names_out([f"f{i}" for i in range(30)]).dtype == object
    with pytest.raises(ss.ShapeMismatchError, match=r"input_features should have length equal.*must have 30 names; got 2"):
        est.get_feature_names_out(["a", "b"])


def test_not_fitted_and_bad_arguments(rng):
    est = StreamingSVD()
    with pytest.raises(NotFittedError, match="not fitted yet"):
        est.transform(np.ones((2, 3)))
    with pytest.raises(NotFittedError, match="not fitted yet"):
        est.get_covariance()
    est.fit(_data(rng))
    with pytest.raises(ss.ShapeMismatchError, match=r"X has 4 features, but StreamingSVD is expecting 30"):
        est.transform(np.ones((2, 4)))
    with pytest.raises(ss.InputError, match=r"`n_components` must be None, an int >= 1 or a float in \(0, 1\); got 1.5"):
        StreamingSVD(n_components=1.5).fit(np.ones((3, 3)))
    with pytest.raises(ss.InputError, match=r"`n_components` must be <= n_features = 3: n_components=4 invalid"):
        StreamingSVD(n_components=4).fit(np.ones((5, 3)))
    with pytest.raises(ss.InputError, match=r"`n_components` must be at most the number of samples of the first batch .*got n_samples=2"):
        StreamingSVD(n_components=3).partial_fit(np.ones((2, 5)))
    with pytest.raises(ss.InputError, match=r"`tol` must be a finite number >= 0; got -1"):
        StreamingSVD(tol=-1).fit(np.ones((3, 3)))
    with pytest.raises(ss.InputError, match=r"`whiten` must be True or False; got 'yes'"):
        StreamingSVD(whiten="yes").fit(np.ones((3, 3)))
    with pytest.raises(ss.InputError, match=r"`center` must be True or False; got 1"):
        StreamingSVD(center=1).fit(np.ones((3, 3)))
    with pytest.raises(ss.InputError, match=r"`batch_size` must be an integer >= 1 or None; got int 0"):
        StreamingSVD(batch_size=0).fit(np.ones((3, 3)))
    with pytest.raises(ss.InputError, match=r"`rule` must be one of \('paper', 'jacobi'\)"):
        StreamingSVD(rule="qr").fit(np.ones((3, 3)))
    with pytest.raises(ss.NonFiniteError, match=r"`X` must be finite"):
        StreamingSVD().fit(np.full((3, 3), np.nan))
    with pytest.raises(ss.NonFiniteError, match=r"`X.data` must be finite"):
        StreamingSVD().fit(sp.csr_matrix(np.full((3, 3), np.inf)))


def _footprint(est):
    """Bytes of every array the estimator and its compressor hold."""
    sc = est.compressor_
    owners = [est, sc, sc._life.state, sc._life.state.basis]
    total = 0
    for obj in owners:
        for value in vars(obj).values():
            items = value if isinstance(value, list | tuple) else [value]
            total += sum(v.nbytes for v in items if isinstance(v, np.ndarray))
    return total


def test_partial_fit_touches_no_per_sample_state(rng, monkeypatch):
    """No right vectors are kept, `expansion` (which forms V) is never read, and the
    memory held does not grow with the number of samples seen."""

    def forbidden(self):
        raise AssertionError("StreamCompressor.expansion read: it forms V (m x p)")

    monkeypatch.setattr(StreamCompressor, "expansion", property(forbidden))
    spectrum = np.diag(np.linspace(3.0, 0.1, 16))
    for n_components in (5, None, 0.9):
        est = StreamingSVD(n_components=n_components)
        for t in range(150):
            est.partial_fit(rng.standard_normal((7, 16)) @ spectrum + 1.0)
            if t == 29:
                early = _footprint(est)
        assert est.compressor_._life.state.rows is None
        assert est.n_samples_seen_ == 1050
        assert _footprint(est) <= early
        est.transform(np.ones((3, 16)))
        est.inverse_transform(np.ones((3, est.n_components_)))
        est.get_covariance()
        est.get_precision()
        est.fit(rng.standard_normal((200, 16)))
        assert est.compressor_._life.state.rows is None


def test_numerically_low_rank_data_in_wide_batches():
    """Numerically low-rank data (singular values below eps): the block handed to the
    compressor has orthogonal residuals (see `_condition`), so CholeskyQR stays regular."""
    datasets = pytest.importorskip("sklearn.datasets")
    for seed in (0, 1):  # both fail in CholeskyQR when the block is absorbed as R^T
        X = datasets.make_low_rank_matrix(1000, 100, tail_strength=0.0, effective_rank=10, random_state=seed)
        est = StreamingSVD(n_components=10, batch_size=150).fit(X)
        s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
        np.testing.assert_allclose(est.singular_values_, s[:10], rtol=1e-2)


def _sklearn_checks():
    try:
        from sklearn.utils.estimator_checks import parametrize_with_checks
    except ImportError:  # scikit-learn is an optional test dependency
        return pytest.mark.skip(reason="scikit-learn not installed")
    return parametrize_with_checks(
        [StreamingSVD(), StreamingSVD(center=False), StreamingSVD(n_components=2),
         StreamingSVD(n_components=2, whiten=True, batch_size=7),
         StreamingSVD(n_components=0.9, rule="paper", sweeps=2)]
    )


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.SkipTestWarning")
@_sklearn_checks()
def test_scikit_learn_estimator_checks(estimator, check):
    check(estimator)
