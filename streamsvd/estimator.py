"""A scikit-learn style estimator on top of :class:`StreamCompressor`.

scikit-learn's convention is the transpose of streamsvd's: its ``X`` has one *sample per
row* (``n_samples x n_features``); streamsvd's snapshots are columns. ``partial_fit(X)``
therefore absorbs ``X.T``, and ``components_`` (``n_components x n_features``) is
``U.T``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ._scaling import safe_column_norms
from ._validation import as_float_array
from .errors import InputError, ShapeMismatchError
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


class StreamingSVD(_Mixin, _Base):
    """Truncated SVD / PCA fitted incrementally by rotation sweeps.

    Parameters
    ----------
    n_components : int, float or None
        ``int``: keep at most this many components (the compressor's ``max_rank``).
        ``float`` in (0, 1): expose the smallest number of components whose explained
        variance ratio reaches it (the compressor keeps everything above ``tol``).
        ``None``: keep every component above ``tol``.
    tol : float, optional
        Relative truncation threshold ``||v_i|| >= tol * ||v_1||`` (the compressor's
        ``rtol``); ``None`` truncates nothing but exact zeros.
    center : bool
        Subtract a running mean, as scikit-learn's ``IncrementalPCA``: a batch of mean
        ``mu_b`` after ``n_old`` samples of mean ``mu`` is absorbed together with the
        correction column ``sqrt(n_old n_b / (n_old + n_b)) (mu - mu_b)``, which makes the
        absorbed matrix have the Gram matrix of the centered data.
    rule : {"paper", "jacobi"}
        Rotation rule.
    sweeps : int or None
        Sweeps per batch; ``None`` (default) converges each batch, so ``partial_fit``
        over any split of the data equals ``fit`` to rounding.
    inner : optional
        Inner product on feature space (see :func:`streamsvd.as_inner`).

    Attributes
    ----------
    components_ : ndarray, shape (n_components, n_features)
    singular_values_ : ndarray, shape (n_components,)
    explained_variance_ : ndarray, shape (n_components,)
        ``singular_values_**2 / (n_samples_seen_ - 1)``.
    explained_variance_ratio_ : ndarray, shape (n_components,)
        Fraction of the total variance (of the centered data when ``center``).
    mean_ : ndarray, shape (n_features,)
        Running mean (zeros without centering).
    n_samples_seen_ : int
    n_features_in_ : int
    n_components_ : int
    error_bound_ : float
        Guaranteed bound on the Frobenius norm of the discarded part.
    """

    compressor_: StreamCompressor
    n_samples_seen_: int
    mean_: np.ndarray
    var_energy_: float

    def __init__(
        self,
        n_components: int | float | None = None,
        *,
        tol: float | None = None,
        center: bool = False,
        rule: str = "jacobi",
        sweeps: int | None = None,
        inner: Any = None,
    ) -> None:
        self.n_components = n_components
        self.tol = tol
        self.center = center
        self.rule = rule
        self.sweeps = sweeps
        self.inner = inner

    # ------------------------------------------------------------------ fitting
    def fit(self, X: Any, y: Any = None) -> StreamingSVD:
        """Fit on ``X`` (``n_samples x n_features``) from scratch."""
        for name in ("compressor_", "n_samples_seen_"):
            if hasattr(self, name):
                delattr(self, name)
        return self.partial_fit(X)

    def partial_fit(self, X: Any, y: Any = None) -> StreamingSVD:
        """Absorb the samples (rows) of ``X``."""
        X = self._check_X(X, fitting=True)
        if not hasattr(self, "compressor_"):
            self._start(X.shape[1])
        n_old = self.n_samples_seen_
        block = X.T
        if self.center:
            mu_b = X.mean(axis=0)
            n_b = X.shape[0]
            block = (X - mu_b).T
            if n_old:
                corr = math.sqrt(n_old * n_b / (n_old + n_b)) * (self.mean_ - mu_b)
                block = np.concatenate([block, corr[:, None]], axis=1)
            self.mean_ = (n_old * self.mean_ + n_b * mu_b) / (n_old + n_b)
            self.var_energy_ += float(np.sum(block**2))
        else:
            self.var_energy_ += float(np.sum(safe_column_norms(block) ** 2))
        self.compressor_.absorb(block)
        self.n_samples_seen_ = n_old + X.shape[0]
        self._publish()
        return self

    def transform(self, X: Any) -> np.ndarray:
        """Project ``X`` on the components: ``(X - mean_) @ components_.T``."""
        self._check_fitted()
        X = self._check_X(X, fitting=False)
        return (X - self.mean_) @ self.components_.T

    def inverse_transform(self, X: Any) -> np.ndarray:
        """Map coordinates back to feature space: ``X @ components_ + mean_``."""
        self._check_fitted()
        Z = as_float_array(X, "X", ndim=2, cols=self.n_components_)
        return Z @ self.components_ + self.mean_

    # ------------------------------------------------------------------ internals
    def _start(self, n_features: int) -> None:
        if isinstance(self.n_components, bool) or not (
            self.n_components is None
            or (isinstance(self.n_components, int | np.integer) and self.n_components >= 1)
            or (isinstance(self.n_components, float) and 0.0 < self.n_components < 1.0)
        ):
            raise InputError(
                "`n_components` must be None, an int >= 1 or a float in (0, 1); got "
                f"{self.n_components!r}."
            )
        is_int = isinstance(self.n_components, int | np.integer)
        max_rank = int(self.n_components) if is_int else None  # type: ignore[arg-type]
        self.compressor_ = StreamCompressor(
            n_features, inner=self.inner, rtol=self.tol, max_rank=max_rank,
            rule=self.rule, sweeps=self.sweeps,
        )
        self.n_features_in_ = n_features
        self.n_samples_seen_ = 0
        self.mean_ = np.zeros(n_features)
        self.var_energy_ = 0.0

    def _publish(self) -> None:
        e = self.compressor_.expansion
        s = e.amplitudes
        total = self.var_energy_
        ratio = s**2 / total if total > 0 else np.zeros_like(s)
        k = e.rank
        if isinstance(self.n_components, float):
            k = int(np.searchsorted(np.cumsum(ratio), self.n_components) + 1)
            k = min(k, e.rank)
        denom = max(self.n_samples_seen_ - 1, 1)
        self.components_ = e.U[:, :k].T.copy()
        self.singular_values_ = s[:k].copy()
        self.explained_variance_ = s[:k] ** 2 / denom
        self.explained_variance_ratio_ = ratio[:k]
        self.n_components_ = k
        self.error_bound_ = self.compressor_.error_bound

    def _check_X(self, X: Any, *, fitting: bool) -> np.ndarray:
        arr = as_float_array(X, "X", ndim=2)
        if arr.size == 0:
            axis = "feature" if arr.shape[0] else "sample"
            raise InputError(
                f"`X` must not be empty; got 0 {axis}(s) (shape={arr.shape}) while a minimum "
                "of 1 is required."
            )
        if hasattr(self, "n_features_in_") and arr.shape[1] != self.n_features_in_:
            raise ShapeMismatchError(
                f"`X` must have {self.n_features_in_} columns (samples are rows): X has "
                f"{arr.shape[1]} features, but StreamingSVD is expecting "
                f"{self.n_features_in_} features as input."
            )
        return arr

    def _check_fitted(self) -> None:
        if not hasattr(self, "components_"):
            raise NotFittedError(
                "This StreamingSVD instance is not fitted yet. Call 'fit' or 'partial_fit' "
                "with appropriate arguments before using this estimator."
            )
