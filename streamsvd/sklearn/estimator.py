"""A scikit-learn style estimator on top of :class:`StreamCompressor`.

scikit-learn's convention is the transpose of streamsvd's: its ``X`` has one *sample per
row* (``n_samples x n_features``); streamsvd's snapshots are columns. ``partial_fit(X)``
therefore absorbs ``X.T``, and ``components_`` (``n_components x n_features``) is
``U.T``.

The estimator mirrors scikit-learn's ``IncrementalPCA`` (same defaults, attributes,
errors and generative model) and keeps, as it does, nothing that grows with the number
of samples seen: the compressor is created with ``right_vectors=False`` and only ``U``
(``n_features x p``), the amplitudes and the running moments are read after each batch.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.errors import SparseInputError
from streamsvd.io.sources import Source
from streamsvd.sklearn import _math as _pca_math
from streamsvd.sklearn._checks import (
    _LEARNED,
    _Batches,
    _check_unchanged,
    _new_compressor,
    _Options,
    _SparseSamples,
    _validate_options,
)
from streamsvd.sklearn._model import (
    FittedPCA,
    NotFittedError,
    check_samples,
    features_error,
)
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest

__all__ = ["NotFittedError", "StreamingSVD"]


class StreamingSVD(FittedPCA):
    """PCA / truncated SVD fitted incrementally by rotation sweeps (``IncrementalPCA``).

    Parameters
    ----------
    n_components : int, float or None
        ``int``: exactly this many components (at most ``n_features``); directions the
        data do not fill are padded with zero-variance directions orthogonal to the
        others, as ``IncrementalPCA`` does, so the width of :meth:`transform` never
        depends on the values of the data. It is also the compressor's rank cap, so the
        state is truncated to it after every batch, as ``IncrementalPCA`` truncates.
        ``float`` in (0, 1): the rule of scikit-learn's ``PCA``, the smallest number of
        components ``k`` with ``sum(explained_variance_ratio_[:k]) > n_components``
        (nothing is truncated by rank).
        ``None`` (default): ``min(n_samples_seen_, n_features_in_)`` components, as
        ``PCA(n_components=None)`` fitted on all the samples seen (``IncrementalPCA``
        fixes it at the first batch; growing it keeps ``partial_fit`` over any split
        equal to ``fit``).
    center : bool
        Subtract a running mean (default, as ``IncrementalPCA``): a batch of mean
        ``mu_b`` after ``n_old`` samples of mean ``mu`` is absorbed together with the
        correction column ``sqrt(n_old n_b / (n_old + n_b)) (mu - mu_b)``, which makes the
        absorbed matrix have the Gram matrix of the centered data. ``False``: the
        truncated SVD of the data themselves.
    whiten : bool
        :meth:`transform` divides each coordinate by ``sqrt(explained_variance_)`` (at
        least ``eps``), :meth:`inverse_transform` multiplies by it. Applied as soon as it
        is set: it changes nothing in the fitted state.
    batch_size : int or None
        Rows per batch in :meth:`fit`; ``None``: ``5 * n_features``. A last batch shorter
        than an int ``n_components`` is merged into the previous one (scikit-learn's
        ``gen_batches``).
    tol : float, optional
        Relative truncation threshold ``||v_i|| >= tol * ||v_1||`` (the compressor's
        ``rtol``); ``None`` truncates nothing but the directions Gram-Schmidt rejects.
        Components it removes are reported as zero-variance directions.
    rule : {"jacobi", "paper"}
        Rotation rule.
    sweeps : int or None
        Sweeps per batch; ``None`` (default) converges each batch, so ``partial_fit``
        over any split of the data equals ``fit`` to rounding.
    inner : optional
        Inner product ``M`` on feature space (see :func:`streamsvd.as_inner`); the
        components are then ``M``-orthonormal and :meth:`transform` returns the
        coordinates ``(X - mean_) M components_.T``.
    window : int, optional
        Fit the ``window`` most recent samples only (:class:`StreamCompressor`'s
        ``window``: the samples that leave are removed exactly), centred by their mean.
    forget : float
        Forgetting factor in (0, 1] (1: none): sample ``j`` of ``m`` weighs
        ``forget^(m - j)``; the mean is the weighted one, ``sum_j w_j x_j / sum_j w_j``
        with ``w_j = forget^(2 (m - j))``, and the components are those of the weighted
        centred samples ``forget^(m - j) (x_j - mean_)``. With ``window`` or ``forget``
        the samples are absorbed as they are and the compressor keeps its right vectors
        (``O(window n_features)`` memory with a window, growing with the samples
        without one); the mean is removed from the expansion afterwards (a rank-one
        downdate of its small core), and nothing is truncated but by ``tol``, so the
        result is the PCA of the (weighted) window to rounding. ``n_samples_seen_``
        then counts the samples in the window, ``explained_variance_`` divides by it
        minus one.

    Attributes
    ----------
    components_ : ndarray, shape (n_components_, n_features)
        ``U.T``, sorted by decreasing singular value, the largest entry of each row
        positive (``svd_flip``'s convention, as ``IncrementalPCA``).
    singular_values_ : ndarray, shape (n_components_,)
    explained_variance_ : ndarray, shape (n_components_,)
        ``singular_values_**2 / (n_samples_seen_ - 1)``.
    explained_variance_ratio_ : ndarray, shape (n_components_,)
        ``singular_values_**2`` over the total energy of the (centered) data.
    noise_variance_ : float
        The probabilistic-PCA noise (Tipping and Bishop, 1999, eq. 8), the mean variance
        of the discarded directions, computed as scikit-learn's ``PCA`` does for a
        truncated SVD: ``(total_variance - sum(explained_variance_)) / (q - k)`` with
        ``q = min(n_samples_seen_, n_features_in_)``; 0 when ``k == q``.
    mean_ : ndarray, shape (n_features,)
        Running mean (zeros without centering).
    var_ : ndarray, shape (n_features,)
        Running per-feature variance (Chan, Golub and LeVeque's pairwise update).
    n_samples_seen_ : int
    n_features_in_ : int
    n_components_ : int
    batch_size_ : int
        Batch size used by the last :meth:`fit`.
    error_bound_ : float
        Guaranteed bound on the Frobenius norm of the part of the (centered) data that
        the kept directions do not represent (see :class:`StreamCompressor`).
    compressor_ : StreamCompressor
        The compressor (``right_vectors=False``: nothing in it grows with the samples).

    Notes
    -----
    Options that the compressor's state is built with (``n_components``, ``tol``,
    ``center``, ``rule``, ``sweeps``, ``inner``) may not change between two
    :meth:`partial_fit` calls: the change is refused with an
    :class:`~streamsvd.errors.InputError` (a ``ValueError``, as ``IncrementalPCA``
    refuses a change of ``n_components``); :meth:`fit` starts again with the new ones.

    :meth:`get_covariance` is the covariance of the generative model whatever
    ``whiten`` (scikit-learn scales its components by ``sqrt(explained_variance_)``
    there when ``whiten=True``, although whitening changes only the transform).
    """

    compressor_: StreamCompressor
    n_samples_seen_: int
    var_: np.ndarray
    _options: _Options
    _inner: InnerProduct
    _energy: float
    _mu: np.ndarray
    _m2: np.ndarray

    def __init__(
        self,
        n_components: int | float | None = None,
        *,
        center: bool = True,
        whiten: bool = False,
        batch_size: int | None = None,
        tol: float | None = None,
        rule: str = "jacobi",
        sweeps: int | None = None,
        inner: Any = None,
        window: int | None = None,
        forget: float = 1.0,
    ) -> None:
        self.n_components = n_components
        self.center = center
        self.whiten = whiten
        self.batch_size = batch_size
        self.tol = tol
        self.rule = rule
        self.sweeps = sweeps
        self.inner = inner
        self.window = window
        self.forget = forget

    # ------------------------------------------------------------------ fitting
    def fit(self, X: Any, y: Any = None) -> StreamingSVD:
        """Fit on ``X`` from scratch, in batches of ``batch_size_`` rows.

        Parameters
        ----------
        X : array_like or scipy.sparse matrix, shape (n_samples, n_features)
            Samples as rows. A sparse matrix is densified one batch at a time.
        y : ignored

        Returns
        -------
        self
            Every learned attribute is reset first (``n_features_in_`` included), so
            data with another number of features can be fitted.
        """
        X = check_samples(X, allow_sparse=True)
        opts = _validate_options(self, X.shape[1])
        for name in _LEARNED:
            if name in self.__dict__:
                delattr(self, name)
        self.batch_size_ = opts.batch_size or 5 * X.shape[1]
        # the batches of scikit-learn's gen_batches: a remainder shorter than
        # n_components joins the batch before it
        samples = Source(_SparseSamples(X) if sp.issparse(X) else X.T, "`X`")
        ingest(samples, _Batches(self, opts), start=0, block=self.batch_size_,
               min_last=opts.max_rank or 0)
        return self

    def partial_fit(self, X: Any, y: Any = None) -> StreamingSVD:
        """Absorb the samples (rows) of ``X`` as one batch.

        Parameters
        ----------
        X : array_like, shape (n_samples, n_features)
            Dense samples as rows (use :meth:`fit` for a sparse matrix). The first batch
            needs at least ``n_components`` rows when it is an int.
        y : ignored

        Returns
        -------
        self

        Raises
        ------
        InputError
            On bad input or when an option the state is built with has changed since
            the first call (see the class notes); the fitted state is then unchanged.
        """
        if sp.issparse(X):
            raise SparseInputError(
                "`X` must be dense in `partial_fit`: StreamingSVD.partial_fit does not "
                "support sparse input. Either convert data to dense or use "
                f"StreamingSVD.fit to do so in batches. Got a {type(X).__name__} of shape "
                f"{X.shape}."
            )
        X = check_samples(X, allow_sparse=False)
        if hasattr(self, "n_features_in_") and X.shape[1] != self.n_features_in_:
            raise features_error(self.n_features_in_, X.shape[1])
        opts = _validate_options(self, X.shape[1])
        self._absorb(X, opts)
        return self

    def _absorb(self, X: np.ndarray, opts: _Options) -> None:
        """Check the options against the state, then absorb the dense batch ``X``.

        Nothing is assigned before the compressor has absorbed the batch, so an error
        leaves the fitted state as it was.
        """
        n_b, n_features = X.shape
        if opts.window is not None or opts.forget < 1.0:
            self._absorb_window(X, opts)
            return
        first = not hasattr(self, "compressor_")
        if not first:
            _check_unchanged(self, opts)
            sc, inner = self.compressor_, self._inner
            n_old, mu, m2 = self.n_samples_seen_, self._mu, self._m2
        else:
            inner = as_inner(self.inner, n_features)
            sc = _new_compressor(opts, n_features=n_features, inner=inner, n_samples=n_b)
            n_old, mu, m2 = 0, np.zeros(n_features), np.zeros(n_features)
        batch = _pca_math.absorbed_batch(X, n_seen=n_old, mean=mu, m2=m2, center=opts.center)
        sc.absorb(batch.columns)
        if first:
            self.compressor_, self._options = sc, opts
            self._inner_arg, self._inner = self.inner, inner
            self.n_features_in_, self._energy = n_features, 0.0
        self._m2, self._mu = batch.m2, batch.mean
        self.mean_ = self._mu if opts.center else np.zeros(n_features)
        self._energy += batch.energy
        self.n_samples_seen_ = batch.n_samples
        self._publish()

    def _absorb_window(self, X: np.ndarray, opts: _Options) -> None:
        """Absorb the samples themselves into a compressor with a window or forgetting."""
        n_features = X.shape[1]
        if hasattr(self, "compressor_"):
            _check_unchanged(self, opts)
            sc, inner = self.compressor_, self._inner
        else:
            inner = as_inner(self.inner, n_features)
            sc = StreamCompressor(
                n_features, inner=inner, rtol=opts.tol, rule=opts.rule, sweeps=opts.sweeps,
                window=opts.window, forget=opts.forget,
            )
        sc.absorb(X.T)
        if not hasattr(self, "compressor_"):
            self.compressor_, self._options = sc, opts
            self._inner_arg, self._inner = self.inner, inner
            self.n_features_in_ = n_features
        m = sc.n_seen
        g = opts.forget ** np.arange(m - 1, -1, -1, dtype=np.float64)
        state = sc._life.state
        assert state.rows is not None
        coords, _, R = state.settled()
        found = _pca_math.weighted_components(
            state.basis.lincomb(coords), R, state.rows.value(), g,
            center=opts.center, n_components=opts.n_components, inner=inner,
        )
        self.mean_, self._mu = found.mean, found.mean
        self.components_ = found.components.components
        self._projection = found.components.projection
        self.singular_values_ = found.components.singular_values
        self.explained_variance_ = found.components.explained_variance
        self.explained_variance_ratio_ = found.components.explained_variance_ratio
        self.noise_variance_ = found.components.noise_variance
        self.var_ = found.variance
        self.n_samples_seen_ = m
        self.n_components_ = self.components_.shape[0]
        self.error_bound_ = sc.error_bound

    def _publish(self) -> None:
        """Expose the first ``n_components_`` directions (small arrays only)."""
        sc = self.compressor_
        found = _pca_math.pca_components(
            sc.left_vectors, sc.amplitudes, n_components=self._options.n_components,
            n_samples=self.n_samples_seen_, energy=self._energy, inner=self._inner,
        )
        self.components_ = found.components
        self._projection = found.projection
        self.singular_values_ = found.singular_values
        self.explained_variance_ = found.explained_variance
        self.explained_variance_ratio_ = found.explained_variance_ratio
        self.noise_variance_ = found.noise_variance
        self.var_ = self._m2 / self.n_samples_seen_
        self.n_components_ = found.n_components
        self.error_bound_ = sc.error_bound

    def __sklearn_tags__(self) -> Any:
        """Declare sparse input (accepted by :meth:`fit` and :meth:`transform`)."""
        tags = super().__sklearn_tags__()
        tags.input_tags.sparse = True
        return tags
