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

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from ._scaling import safe_column_norms
from ._validation import (
    as_float_array,
    check_choice,
    check_finite,
    check_nonnegative,
    check_positive_int,
)
from .compress import fix_signs
from .errors import InputError, ShapeMismatchError, SparseInputError
from .inner import InnerProduct, as_inner
from .rotations import RULES
from .stream import StreamCompressor

__all__ = ["NotFittedError", "StreamingSVD"]

try:  # scikit-learn is optional: use its base classes when present
    from sklearn.base import BaseEstimator as _Base
    from sklearn.base import TransformerMixin as _Mixin
    from sklearn.exceptions import NotFittedError as _NotFitted
except ImportError:  # pragma: no cover - exercised only without scikit-learn

    class _Base:  # type: ignore[no-redef]
        """``get_params`` / ``set_params`` from the ``__init__`` signature."""

        def get_params(self, deep: bool = True) -> dict[str, Any]:
            import inspect

            names = [p for p in inspect.signature(type(self).__init__).parameters if p != "self"]
            return {k: getattr(self, k) for k in names}

        def set_params(self, **params: Any) -> Any:
            for k, v in params.items():
                setattr(self, k, v)
            return self

    class _Mixin:  # type: ignore[no-redef]
        def fit_transform(self, X: Any, y: Any = None, **kw: Any) -> np.ndarray:
            return self.fit(X, y, **kw).transform(X)  # type: ignore[attr-defined]

    class _NotFitted(ValueError, AttributeError):  # type: ignore[no-redef]
        pass


class NotFittedError(_NotFitted, InputError):
    """The estimator is used before ``fit`` or ``partial_fit``."""


# learned state, removed by ``fit`` before it starts again
_LEARNED = (
    "compressor_", "n_samples_seen_", "n_features_in_", "mean_", "var_", "components_",
    "singular_values_", "explained_variance_", "explained_variance_ratio_",
    "noise_variance_", "n_components_", "error_bound_", "batch_size_",
    "_options", "_inner_arg", "_inner", "_energy", "_mu", "_m2", "_projection",
)
# options the compressor's state is built with: changing one between two ``partial_fit``
# calls is refused (as ``IncrementalPCA`` refuses a change of ``n_components``)
_STATEFUL = ("n_components", "tol", "center", "rule", "sweeps")


@dataclass(frozen=True)
class _Options:
    """The estimator's options, validated and normalised (see ``_validate_options``)."""

    n_components: int | float | None
    tol: float | None
    center: bool
    whiten: bool
    batch_size: int | None
    rule: str
    sweeps: int | None

    @property
    def max_rank(self) -> int | None:
        """The compressor's rank cap: ``n_components`` when it is an int."""
        return self.n_components if isinstance(self.n_components, int) else None


def _check_bool(value: Any, name: str) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise InputError(f"`{name}` must be True or False; got {value!r}.")
    return bool(value)


def _validate_options(est: StreamingSVD, n_features: int) -> _Options:
    """Validate every option of ``est`` for data with ``n_features`` features."""
    k = est.n_components
    if isinstance(k, bool) or not (
        k is None
        or (isinstance(k, int | np.integer) and k >= 1)
        or (isinstance(k, float) and 0.0 < k < 1.0)
    ):
        raise InputError(
            f"`n_components` must be None, an int >= 1 or a float in (0, 1); got {k!r}."
        )
    if isinstance(k, int | np.integer):
        k = int(k)
        if k > n_features:
            raise InputError(
                f"`n_components` must be <= n_features = {n_features}: n_components={k} "
                f"invalid for n_features={n_features}, need more rows than columns for "
                f"StreamingSVD processing. Pass `n_components` <= {n_features} or None."
            )
    return _Options(
        n_components=k,
        tol=None if est.tol is None else check_nonnegative(est.tol, "tol"),
        center=_check_bool(est.center, "center"),
        whiten=_check_bool(est.whiten, "whiten"),
        batch_size=check_positive_int(est.batch_size, "batch_size", allow_none=True),
        rule=check_choice(est.rule, "rule", RULES),
        sweeps=check_positive_int(est.sweeps, "sweeps", allow_none=True),
    )


def _gen_batches(n: int, batch_size: int, min_batch_size: int) -> Iterator[slice]:
    """Consecutive slices of ``batch_size`` rows, the last one at least ``min_batch_size``.

    The batches of scikit-learn's ``gen_batches`` (what ``IncrementalPCA.fit`` uses): a
    remainder shorter than ``min_batch_size`` is appended to the previous batch.
    """
    start = 0
    for _ in range(n // batch_size):
        end = start + batch_size
        if end + min_batch_size > n:
            continue
        yield slice(start, end)
        start = end
    if start < n:
        yield slice(start, n)


def _condition(B: np.ndarray) -> np.ndarray:
    """Return a block with the Gram matrix ``B B^T`` of ``B`` and at most ``n`` columns.

    Without right vectors the compressor's directions and amplitudes depend on the
    absorbed columns only through ``B B^T`` (the SVD of ``[U S, B]`` does), so a block of
    more samples than features is replaced by ``R^T`` with ``B^T = Q R`` (Householder):
    ``n`` columns instead of ``b``, at ``O(b n^2)``, the cost of ``IncrementalPCA``'s SVD.
    """
    n, b = B.shape
    if b > n:
        B = scipy.linalg.qr(B.T, mode="r", check_finite=False)[0][:n].T  # R is b x n
    return B


def _complement(U: np.ndarray, count: int, inner: InnerProduct) -> np.ndarray:
    """``count`` ``M``-orthonormal directions ``M``-orthogonal to the columns of ``U``.

    With ``W = M U``, the directions ``Z`` with ``W^T Z = 0`` are the columns ``r, r+1,
    ...`` of the Householder factor of ``W`` (``Q e_j``, applied by LAPACK ``dormqr``,
    ``O(n r count)``, never the ``n x n`` ``Q``); they are then ``M``-orthonormalised by
    the Cholesky factor of ``Z^T M Z`` and signed so that their largest entry is positive.
    Deterministic, so the width of ``transform`` depends on the shapes only.
    """
    n, r = U.shape
    Z = np.zeros((n, count))
    Z[r + np.arange(count), np.arange(count)] = 1.0
    if r:
        W = np.asarray(inner.apply(U), dtype=np.float64)
        (qr, tau), _ = scipy.linalg.qr(W, mode="raw")
        Z, _, info = scipy.linalg.lapack.dormqr(
            "L", "N", qr, tau, Z, max(1, 64 * count), overwrite_c=1
        )
        if info != 0:  # pragma: no cover - LAPACK argument errors only
            raise RuntimeError(f"LAPACK dormqr failed with info={info}")
    if not inner.is_euclidean:
        G = inner.gram(Z, Z)
        L = np.linalg.cholesky(0.5 * (G + G.T))
        Z = scipy.linalg.solve_triangular(L, Z.T, lower=True).T
    fix_signs(Z, np.zeros((0, count)))
    return Z


class StreamingSVD(_Mixin, _Base):
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
    n_features_in_: int
    n_components_: int
    mean_: np.ndarray
    var_: np.ndarray
    components_: np.ndarray
    explained_variance_: np.ndarray
    noise_variance_: float
    _options: _Options
    _inner: InnerProduct
    _energy: float
    _mu: np.ndarray
    _m2: np.ndarray
    _projection: np.ndarray

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
    ) -> None:
        self.n_components = n_components
        self.center = center
        self.whiten = whiten
        self.batch_size = batch_size
        self.tol = tol
        self.rule = rule
        self.sweeps = sweeps
        self.inner = inner

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
        X = self._check_X(X, allow_sparse=True)
        opts = _validate_options(self, X.shape[1])
        for name in _LEARNED:
            if name in self.__dict__:
                delattr(self, name)
        self.batch_size_ = opts.batch_size or 5 * X.shape[1]
        min_batch = opts.max_rank or 0
        for rows in _gen_batches(X.shape[0], self.batch_size_, min_batch):
            batch = X[rows]
            if sp.issparse(batch):
                batch = np.asarray(batch.toarray(), dtype=np.float64)
            self._absorb(batch, opts)
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
        X = self._check_X(X, allow_sparse=False)
        if hasattr(self, "n_features_in_") and X.shape[1] != self.n_features_in_:
            raise self._features_error(X.shape[1])
        opts = _validate_options(self, X.shape[1])
        self._absorb(X, opts)
        return self

    def _absorb(self, X: np.ndarray, opts: _Options) -> None:
        """Check the options against the state, then absorb the dense batch ``X``.

        Nothing is assigned before the compressor has absorbed the batch, so an error
        leaves the fitted state as it was.
        """
        n_b, n_features = X.shape
        first = not hasattr(self, "compressor_")
        if not first:
            self._check_unchanged(opts)
            sc, inner = self.compressor_, self._inner
            n_old, mu, m2 = self.n_samples_seen_, self._mu, self._m2
        else:
            if opts.max_rank is not None and opts.max_rank > n_b:
                raise InputError(
                    "`n_components` must be at most the number of samples of the first "
                    f"batch (n_components={opts.max_rank} must be less or equal to the "
                    f"batch number of samples {n_b} for the first partial_fit call); got "
                    f"n_samples={n_b}. Pass at least {opts.max_rank} samples first, or a "
                    "smaller `n_components`."
                )
            inner = as_inner(self.inner, n_features)
            sc = StreamCompressor(
                n_features, inner=inner, rtol=opts.tol, max_rank=opts.max_rank,
                oversampling=0, rule=opts.rule, sweeps=opts.sweeps, right_vectors=False,
            )
            n_old, mu, m2 = 0, np.zeros(n_features), np.zeros(n_features)
        n_new = n_old + n_b
        mu_b = X.mean(axis=0)
        Xc = X - mu_b
        m2_b = np.sum(Xc**2, axis=0)
        delta = mu_b - mu
        if opts.center:
            block = Xc
            if n_old:
                corr = math.sqrt(n_old * n_b / n_new) * (mu - mu_b)
                block = np.vstack([Xc, corr])
            energy = float(np.sum(m2_b)) + (n_old * n_b / n_new) * float(delta @ delta)
        else:
            block = X
            energy = float(np.sum(safe_column_norms(X.T) ** 2))
        sc.absorb(_condition(block.T))
        if first:
            self.compressor_, self._options = sc, opts
            self._inner_arg, self._inner = self.inner, inner
            self.n_features_in_, self._energy = n_features, 0.0
        # running moments: Chan, Golub and LeVeque's pairwise update
        self._m2 = m2 + m2_b + (n_old * n_b / n_new) * delta**2
        self._mu = mu + (n_b / n_new) * delta
        self.mean_ = self._mu if opts.center else np.zeros(n_features)
        self._energy += energy
        self.n_samples_seen_ = n_new
        self._publish()

    def _check_unchanged(self, opts: _Options) -> None:
        """Refuse a change of an option the state was built with (see the class notes)."""
        for name in _STATEFUL:
            old, new = getattr(self._options, name), getattr(opts, name)
            if old != new:
                raise InputError(
                    f"`{name}` must stay {old!r} between calls to partial_fit (the fitted "
                    f"state was built with it); got {new!r}. Set it back, or call `fit` to "
                    "start again with the new value."
                )
        if self.inner is not self._inner_arg:
            new_inner = as_inner(self.inner, self.n_features_in_)
            if new_inner.fingerprint != self._inner.fingerprint:
                raise InputError(
                    f"`inner` must stay {self._inner!r} between calls to partial_fit (the "
                    f"fitted state was built with it); got {new_inner!r}. Set it back, or "
                    "call `fit` to start again with the new value."
                )

    def _publish(self) -> None:
        """Expose the first ``n_components_`` directions (small arrays only)."""
        sc = self.compressor_
        U, s = sc.left_vectors, sc.amplitudes
        n, p = self.n_samples_seen_, self.n_features_in_
        q = int(min(n, p))
        total = self._energy
        ratio = s**2 / total if total > 0 else np.zeros_like(s)
        k_opt = self._options.n_components
        if isinstance(k_opt, int):
            k = k_opt
        elif isinstance(k_opt, float):
            # scikit-learn's PCA: the smallest k whose cumulative ratio exceeds the fraction
            k = int(np.searchsorted(np.cumsum(ratio), k_opt, side="right")) + 1
            k = min(k, max(s.size, 1), q)
        else:
            k = q
        r = min(k, s.size)
        U, s, ratio = U[:, :r], s[:r], ratio[:r]
        if r < k:
            U = np.hstack([U, _complement(U, k - r, self._inner)])
            s = np.concatenate([s, np.zeros(k - r)])
            ratio = np.concatenate([ratio, np.zeros(k - r)])
        denom = max(n - 1, 1)
        self.components_ = np.ascontiguousarray(U.T)
        self._projection = U if self._inner.is_euclidean else self._inner.apply(U)
        self.singular_values_ = s
        self.explained_variance_ = s**2 / denom
        self.explained_variance_ratio_ = ratio
        self.noise_variance_ = (
            max(total / denom - float(np.sum(self.explained_variance_)), 0.0) / (q - k)
            if k < q
            else 0.0
        )
        self.var_ = self._m2 / n
        self.n_components_ = k
        self.error_bound_ = sc.error_bound

    # ------------------------------------------------------------------ using the model
    def transform(self, X: Any) -> np.ndarray:
        """Project ``X`` on the components.

        ``Z = (X - mean_) M components_.T`` (``M = I`` unless ``inner``), divided
        column-wise by ``max(sqrt(explained_variance_), eps)`` when ``whiten``.

        Parameters
        ----------
        X : array_like or scipy.sparse matrix, shape (n_samples, n_features)

        Returns
        -------
        ndarray, shape (n_samples, n_components_)
        """
        self._check_fitted()
        X = self._check_X(X, allow_sparse=True)
        if X.shape[1] != self.n_features_in_:
            raise self._features_error(X.shape[1])
        P = self._projection
        if sp.issparse(X):
            Z = np.asarray(X @ P) - self.mean_ @ P
        else:
            Z = (X - self.mean_) @ P
        if _check_bool(self.whiten, "whiten"):
            Z /= np.maximum(np.sqrt(self.explained_variance_), np.finfo(np.float64).eps)
        return Z

    def inverse_transform(self, X: Any) -> np.ndarray:
        """Map coordinates back to feature space.

        ``X @ components_ + mean_``, with ``components_`` scaled row-wise by
        ``sqrt(explained_variance_)`` when ``whiten``.

        Parameters
        ----------
        X : array_like, shape (n_samples, n_components_)

        Returns
        -------
        ndarray, shape (n_samples, n_features)
        """
        self._check_fitted()
        Z = as_float_array(X, "X", ndim=2, cols=self.n_components_)
        C = self.components_
        if _check_bool(self.whiten, "whiten"):
            C = np.sqrt(self.explained_variance_)[:, None] * C
        return Z @ C + self.mean_

    def get_covariance(self) -> np.ndarray:
        """Covariance of the probabilistic-PCA model (Tipping and Bishop, 1999).

        ``C^T diag(max(explained_variance_ - noise_variance_, 0)) C + noise_variance_ I``
        with ``C = components_``.

        Returns
        -------
        ndarray, shape (n_features, n_features)
        """
        self._check_fitted()
        C, nv = self.components_, self.noise_variance_
        diff = np.maximum(self.explained_variance_ - nv, 0.0)
        cov = (C.T * diff) @ C
        cov.flat[:: cov.shape[0] + 1] += nv
        return cov

    def get_precision(self) -> np.ndarray:
        """Inverse of :meth:`get_covariance`, by the matrix inversion lemma.

        ``(I - C^T (C C^T + nv diag(1/d))^{-1} C) / nv`` with ``d = max(explained_variance_
        - nv, 0)`` and ``nv = noise_variance_`` (scikit-learn's formula, a ``k x k``
        inverse); ``inv(get_covariance())`` when ``nv == 0``.

        Returns
        -------
        ndarray, shape (n_features, n_features)
        """
        self._check_fitted()
        nv = self.noise_variance_
        if nv == 0.0:
            return scipy.linalg.inv(self.get_covariance())
        C = self.components_
        diff = np.maximum(self.explained_variance_ - nv, 0.0)
        with np.errstate(divide="ignore"):
            inv_diff = 1.0 / diff
        small = C @ C.T / nv
        small.flat[:: small.shape[0] + 1] += inv_diff
        precision = C.T @ scipy.linalg.inv(small) @ C
        precision /= -(nv**2)
        precision.flat[:: precision.shape[0] + 1] += 1.0 / nv
        return precision

    def get_feature_names_out(self, input_features: Any = None) -> np.ndarray:
        """Names of the output columns: ``streamingsvd0``, ``streamingsvd1``, ...

        Parameters
        ----------
        input_features : array_like of str, optional
            Checked only: it must have ``n_features_in_`` entries.

        Returns
        -------
        ndarray of object, shape (n_components_,)
        """
        self._check_fitted()
        if input_features is not None:
            names = np.asarray(input_features, dtype=object)
            if names.ndim != 1 or len(names) != self.n_features_in_:
                raise ShapeMismatchError(
                    "input_features should have length equal to number of features: "
                    f"`input_features` must have {self.n_features_in_} names; got "
                    f"{names.size}. Pass one name per column of X, or None."
                )
        prefix = type(self).__name__.lower()
        return np.asarray([f"{prefix}{i}" for i in range(self.n_components_)], dtype=object)

    def __sklearn_tags__(self) -> Any:
        """Declare sparse input (accepted by :meth:`fit` and :meth:`transform`)."""
        tags = super().__sklearn_tags__()
        tags.input_tags.sparse = True
        return tags

    # ------------------------------------------------------------------ internals
    def _check_X(self, X: Any, *, allow_sparse: bool) -> Any:
        """Return ``X`` as a finite float64 array (or CSR matrix when allowed)."""
        if allow_sparse and sp.issparse(X):
            arr = sp.csr_matrix(X)
            if arr.dtype.kind not in "biuf":
                raise InputError(
                    f"`X` must hold real numbers; got a sparse matrix of dtype {arr.dtype}."
                )
            arr = arr.astype(np.float64)
            check_finite(arr.data, "X.data")
        else:
            arr = as_float_array(X, "X", ndim=2)
        if arr.shape[0] == 0 or arr.shape[1] == 0:
            axis = "feature" if arr.shape[0] else "sample"
            raise InputError(
                f"`X` must not be empty; got 0 {axis}(s) (shape={arr.shape}) while a minimum "
                "of 1 is required."
            )
        return arr

    def _features_error(self, got: int) -> ShapeMismatchError:
        return ShapeMismatchError(
            f"`X` must have {self.n_features_in_} columns (samples are rows): X has "
            f"{got} features, but StreamingSVD is expecting {self.n_features_in_} features "
            "as input."
        )

    def _check_fitted(self) -> None:
        if not hasattr(self, "components_"):
            raise NotFittedError(
                "This StreamingSVD instance is not fitted yet. Call 'fit' or 'partial_fit' "
                "with appropriate arguments before using this estimator."
            )
