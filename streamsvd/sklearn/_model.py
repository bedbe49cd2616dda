"""A fitted principal component model, in scikit-learn's conventions.

:class:`FittedPCA` is what a fitted :class:`~streamsvd.sklearn.estimator.StreamingSVD` offers
(as scikit-learn's ``_BasePCA`` is for ``IncrementalPCA``): projection on the
components and back, the probabilistic-PCA covariance and precision, and the names of
the output columns; the arithmetic is :mod:`streamsvd.sklearn._math`'s. Its base classes are
scikit-learn's when it is installed (it is optional) and small stand-ins otherwise; the
input checks shared with the fitting live here too.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from streamsvd._util.validation import as_float_array, check_finite
from streamsvd.errors import InputError, ShapeMismatchError
from streamsvd.sklearn import _math as _pca_math

__all__ = [
    "FittedPCA",
    "NotFittedError",
    "check_bool",
    "check_fitted",
    "check_samples",
    "features_error",
]

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


def check_bool(value: Any, name: str) -> bool:
    """Return ``value`` as a bool; raise InputError unless it is True or False."""
    if not isinstance(value, bool | np.bool_):
        raise InputError(f"`{name}` must be True or False; got {value!r}.")
    return bool(value)


def check_samples(X: Any, *, allow_sparse: bool) -> Any:
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


def features_error(expected: int, got: int) -> ShapeMismatchError:
    """Return the error of samples with ``got`` features where ``expected`` are."""
    return ShapeMismatchError(
        f"`X` must have {expected} columns (samples are rows): X has "
        f"{got} features, but StreamingSVD is expecting {expected} features "
        "as input."
    )


def check_fitted(est: Any) -> None:
    """Raise :class:`NotFittedError` when ``est`` has not been fitted yet."""
    if not hasattr(est, "components_"):
        raise NotFittedError(
            "This StreamingSVD instance is not fitted yet. Call 'fit' or 'partial_fit' "
            "with appropriate arguments before using this estimator."
        )


class FittedPCA(_Mixin, _Base):
    """The use of a fitted principal component model (scikit-learn's ``_BasePCA``).

    Projection on the components and back, the probabilistic-PCA covariance and
    precision, and the names of the output columns, from the learned attributes below
    (set by the subclass's fitting); the arithmetic is :mod:`streamsvd.sklearn._math`'s.
    """

    whiten: bool
    n_features_in_: int
    n_components_: int
    mean_: np.ndarray
    components_: np.ndarray
    explained_variance_: np.ndarray
    noise_variance_: float
    _projection: np.ndarray

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
        check_fitted(self)
        X = check_samples(X, allow_sparse=True)
        if X.shape[1] != self.n_features_in_:
            raise features_error(self.n_features_in_, X.shape[1])
        return _pca_math.transform(
            X, mean=self.mean_, projection=self._projection,
            explained_variance=self.explained_variance_,
            whiten=check_bool(self.whiten, "whiten"),
        )

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
        check_fitted(self)
        Z = as_float_array(X, "X", ndim=2, cols=self.n_components_)
        return _pca_math.inverse_transform(
            Z, mean=self.mean_, components=self.components_,
            explained_variance=self.explained_variance_,
            whiten=check_bool(self.whiten, "whiten"),
        )

    def get_covariance(self) -> np.ndarray:
        """Covariance of the probabilistic-PCA model (Tipping and Bishop, 1999).

        ``C^T diag(max(explained_variance_ - noise_variance_, 0)) C + noise_variance_ I``
        with ``C = components_``.

        Returns
        -------
        ndarray, shape (n_features, n_features)
        """
        check_fitted(self)
        return _pca_math.covariance(self.components_, self.explained_variance_,
                                    self.noise_variance_)

    def get_precision(self) -> np.ndarray:
        """Inverse of :meth:`get_covariance`, by the matrix inversion lemma.

        ``(I - C^T (C C^T + nv diag(1/d))^{-1} C) / nv`` with ``d = max(explained_variance_
        - nv, 0)`` and ``nv = noise_variance_`` (scikit-learn's formula, a ``k x k``
        inverse); ``inv(get_covariance())`` when ``nv == 0``.

        Returns
        -------
        ndarray, shape (n_features, n_features)
        """
        check_fitted(self)
        return _pca_math.precision(self.components_, self.explained_variance_,
                                   self.noise_variance_)

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
        check_fitted(self)
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
