"""The arithmetic of :class:`~streamsvd.sklearn.estimator.StreamingSVD`, as plain functions.

scikit-learn's convention: samples are rows (``n_samples x n_features``), components
are rows of ``components_``. Nothing here keeps state; the estimator holds the running
moments and the compressor, and passes them in.

* :func:`absorbed_batch`: what the compressor absorbs for a batch (centered, with the
  mean-correction column) and the running moments after it (Chan, Golub and LeVeque's
  pairwise update).
* :func:`pca_components`: the components, variances and ratios of the principal
  component analysis from the compressor's directions and amplitudes, padded to the
  requested number of components.
* The probabilistic-PCA model (Tipping and Bishop, 1999): :func:`noise_variance`,
  :func:`covariance` and :func:`precision`.
* :func:`transform` and :func:`inverse_transform`: coordinates on the components.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from streamsvd._util.scaling import safe_column_norms
from streamsvd.algebra.inner import InnerProduct
from streamsvd.linalg.compress import fix_signs

__all__ = [
    "Batch",
    "Components",
    "absorbed_batch",
    "covariance",
    "inverse_transform",
    "noise_variance",
    "pca_components",
    "precision",
    "transform",
]


@dataclass(frozen=True)
class Batch:
    """A batch of samples as the compressor absorbs it, and the moments after it.

    Attributes
    ----------
    columns : ndarray, shape (n_features, c)
        The columns to absorb, ``c <= n_features`` (see :func:`absorbed_batch`).
    energy : float
        The energy the batch adds to the (centered) data: its squared Frobenius norm.
    n_samples : int
        Samples seen, this batch included.
    mean : ndarray, shape (n_features,)
        Running mean of every sample seen.
    m2 : ndarray, shape (n_features,)
        Running sum of squared deviations from the mean, per feature.
    """

    columns: np.ndarray
    energy: float
    n_samples: int
    mean: np.ndarray
    m2: np.ndarray


def absorbed_batch(X: np.ndarray, *, n_seen: int, mean: np.ndarray, m2: np.ndarray,
                   center: bool) -> Batch:
    """Return what absorbing the dense batch ``X`` (samples as rows) adds.

    With ``center``, a batch of mean ``mu_b`` after ``n_seen`` samples of mean ``mu`` is
    absorbed together with the correction column ``sqrt(n_seen n_b / (n_seen + n_b))
    (mu - mu_b)``, so that the absorbed matrix has the Gram matrix of the centered data;
    without it, the batch itself is absorbed. The columns are then reduced by
    :func:`_condition` to at most ``n_features``.

    Parameters
    ----------
    X : ndarray, shape (n_b, n_features)
        The batch.
    n_seen : int
        Samples seen before the batch.
    mean, m2 : ndarray, shape (n_features,)
        Running mean and sum of squared deviations before the batch (zeros at first).
    center : bool
        Whether the running mean is subtracted.
    """
    n_b = X.shape[0]
    n_new = n_seen + n_b
    mu_b = X.mean(axis=0)
    Xc = X - mu_b
    m2_b = np.sum(Xc**2, axis=0)
    delta = mu_b - mean
    if center:
        block = Xc
        if n_seen:
            corr = math.sqrt(n_seen * n_b / n_new) * (mean - mu_b)
            block = np.vstack([Xc, corr])
        energy = float(np.sum(m2_b)) + (n_seen * n_b / n_new) * float(delta @ delta)
    else:
        block = X
        energy = float(np.sum(safe_column_norms(X.T) ** 2))
    return Batch(
        columns=_condition(block.T),
        energy=energy,
        n_samples=n_new,
        # running moments: Chan, Golub and LeVeque's pairwise update
        mean=mean + (n_b / n_new) * delta,
        m2=m2 + m2_b + (n_seen * n_b / n_new) * delta**2,
    )


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


@dataclass(frozen=True)
class Components:
    """The principal components and their variances (the estimator's learned arrays).

    Attributes
    ----------
    components : ndarray, shape (k, n_features)
        ``U.T``, ``M``-orthonormal rows.
    projection : ndarray, shape (n_features, k)
        ``M U``: :func:`transform` multiplies by it.
    singular_values, explained_variance, explained_variance_ratio : ndarray, shape (k,)
    noise_variance : float
    """

    components: np.ndarray
    projection: np.ndarray
    singular_values: np.ndarray
    explained_variance: np.ndarray
    explained_variance_ratio: np.ndarray
    noise_variance: float

    @property
    def n_components(self) -> int:
        """``k``, the number of components."""
        return int(self.singular_values.size)


def pca_components(U: np.ndarray, s: np.ndarray, *, n_components: int | float | None,
                   n_samples: int, energy: float, inner: InnerProduct) -> Components:
    """Return the first components of the compressor's directions ``U`` and amplitudes ``s``.

    The number of components ``k`` is ``n_components`` when it is an int; for a float in
    (0, 1), scikit-learn's ``PCA`` rule, the smallest ``k`` whose cumulative
    ``explained_variance_ratio_`` exceeds it; for None, ``q = min(n_samples,
    n_features)``. Directions the data do not fill are padded with zero-variance
    directions orthogonal to the others (:func:`_complement`), so ``k`` depends on the
    shapes only.

    Parameters
    ----------
    U : ndarray, shape (n_features, r)
        The compressor's ``M``-orthonormal directions, by decreasing amplitude.
    s : ndarray, shape (r,)
        Their amplitudes (singular values of the centered data).
    n_components : int, float or None
        The estimator's option.
    n_samples : int
        Samples seen.
    energy : float
        The total energy of the (centered) data.
    inner : InnerProduct
        The inner product ``M`` on feature space.
    """
    n, p = n_samples, U.shape[0]
    q = int(min(n, p))
    ratio = s**2 / energy if energy > 0 else np.zeros_like(s)
    if isinstance(n_components, int):
        k = n_components
    elif isinstance(n_components, float):
        # scikit-learn's PCA: the smallest k whose cumulative ratio exceeds the fraction
        k = int(np.searchsorted(np.cumsum(ratio), n_components, side="right")) + 1
        k = min(k, max(s.size, 1), q)
    else:
        k = q
    r = min(k, s.size)
    U, s, ratio = U[:, :r], s[:r], ratio[:r]
    if r < k:
        U = np.hstack([U, _complement(U, k - r, inner)])
        s = np.concatenate([s, np.zeros(k - r)])
        ratio = np.concatenate([ratio, np.zeros(k - r)])
    denom = max(n - 1, 1)
    explained = s**2 / denom
    return Components(
        components=np.ascontiguousarray(U.T),
        projection=U if inner.is_euclidean else inner.apply(U),
        singular_values=s,
        explained_variance=explained,
        explained_variance_ratio=ratio,
        noise_variance=noise_variance(energy / denom, explained, n_candidates=q),
    )


@dataclass(frozen=True)
class WeightedComponents:
    """Components of weighted samples kept as an expansion, and their weighted moments."""

    components: Components
    mean: np.ndarray
    variance: np.ndarray


def weighted_components(U: np.ndarray, R: np.ndarray, Y: np.ndarray, g: np.ndarray, *,
                        center: bool, n_components: int | float | None,
                        inner: InnerProduct) -> WeightedComponents:
    """Return the PCA of the samples ``A_g = U R^T Y^T`` (columns weighted by ``g``).

    ``A_g = [g_1 x_1, ..., g_m x_m]``; the weighted mean is ``mu = A_g g / ||g||^2`` and
    the centred weighted samples ``A_g (I - h h^T)``, ``h = g / ||g||``. With ``Y``
    orthonormal and ``y = Y^T h``, ``(I - h h^T) Y = Y (I - y y^T)`` on the left, so the
    centred samples are ``U R_c^T Z^T`` with ``Z`` orthonormal and the small core
    ``R_c = (I - y y^T)^(1/2) R``: their SVD is that of ``R_c`` (``O(m k + k^2 p)``).

    Parameters
    ----------
    U : ndarray, shape (n_features, p)
        ``M``-orthonormal left vectors.
    R : ndarray, shape (k, p)
        The core.
    Y : ndarray, shape (m, k)
        Orthonormal right factor (one row per sample).
    g : ndarray, shape (m,)
        The samples' weights.
    center, n_components, inner
        As for :func:`pca_components`.
    """
    h = g / np.linalg.norm(g)
    y = Y.T @ h
    Rc = R
    mean = np.zeros(U.shape[0])
    if center:
        mean = U @ (R.T @ y) / np.linalg.norm(g)
        ny2 = float(y @ y)
        if ny2 > 0.0:
            shrink = (1.0 - math.sqrt(max(1.0 - ny2, 0.0))) / ny2
            Rc = R - shrink * np.outer(y, y @ R)
    _, s, Zt = np.linalg.svd(Rc, full_matrices=False)
    Uc = U @ Zt.T
    fix_signs(Uc, np.zeros((0, Uc.shape[1])))
    m = g.size
    found = pca_components(Uc, s, n_components=n_components, n_samples=m,
                           energy=float(np.sum(s * s)), inner=inner)
    variance = np.sum((Uc * s) ** 2, axis=1) / float(g @ g)
    return WeightedComponents(components=found, mean=mean, variance=variance)


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


def noise_variance(total_variance: float, explained_variance: np.ndarray, *,
                   n_candidates: int) -> float:
    """Return the probabilistic-PCA noise: the mean variance of the discarded directions.

    ``max(total_variance - sum(explained_variance), 0) / (q - k)`` with ``q =
    n_candidates`` (``min(n_samples, n_features)``) and ``k`` the number of components
    kept (Tipping and Bishop, 1999, eq. 8, as scikit-learn's ``PCA`` computes it for a
    truncated SVD); 0 when ``k == q``.
    """
    k = explained_variance.size
    if k >= n_candidates:
        return 0.0
    return max(total_variance - float(np.sum(explained_variance)), 0.0) / (n_candidates - k)


def covariance(components: np.ndarray, explained_variance: np.ndarray,
               noise_variance: float) -> np.ndarray:
    """Covariance of the probabilistic-PCA model (Tipping and Bishop, 1999).

    ``C^T diag(max(explained_variance - nv, 0)) C + nv I`` with ``C = components`` and
    ``nv = noise_variance``; shape ``(n_features, n_features)``.
    """
    C, nv = components, noise_variance
    diff = np.maximum(explained_variance - nv, 0.0)
    cov = (C.T * diff) @ C
    cov.flat[:: cov.shape[0] + 1] += nv
    return cov


def precision(components: np.ndarray, explained_variance: np.ndarray,
              noise_variance: float) -> np.ndarray:
    """Inverse of :func:`covariance`, by the matrix inversion lemma.

    ``(I - C^T (C C^T + nv diag(1/d))^{-1} C) / nv`` with ``d = max(explained_variance -
    nv, 0)`` and ``nv = noise_variance`` (scikit-learn's formula, a ``k x k`` inverse);
    ``inv(covariance(...))`` when ``nv == 0``.
    """
    nv = noise_variance
    if nv == 0.0:
        return scipy.linalg.inv(covariance(components, explained_variance, nv))
    C = components
    diff = np.maximum(explained_variance - nv, 0.0)
    with np.errstate(divide="ignore"):
        inv_diff = 1.0 / diff
    small = C @ C.T / nv
    small.flat[:: small.shape[0] + 1] += inv_diff
    out = C.T @ scipy.linalg.inv(small) @ C
    out /= -(nv**2)
    out.flat[:: out.shape[0] + 1] += 1.0 / nv
    return out


def transform(X: Any, *, mean: np.ndarray, projection: np.ndarray,
              explained_variance: np.ndarray, whiten: bool) -> np.ndarray:
    """Coordinates of the samples ``X`` on the components.

    ``Z = (X - mean) P`` with ``P = projection`` (``M components.T``), divided
    column-wise by ``max(sqrt(explained_variance), eps)`` when ``whiten``. A sparse ``X``
    is never densified: ``Z = X P - mean P``.
    """
    P = projection
    if sp.issparse(X):
        Z = np.asarray(X @ P) - mean @ P
    else:
        Z = (X - mean) @ P
    if whiten:
        Z /= np.maximum(np.sqrt(explained_variance), np.finfo(np.float64).eps)
    return Z


def inverse_transform(Z: np.ndarray, *, mean: np.ndarray, components: np.ndarray,
                      explained_variance: np.ndarray, whiten: bool) -> np.ndarray:
    """Map coordinates back to feature space.

    ``Z @ components + mean``, with ``components`` scaled row-wise by
    ``sqrt(explained_variance)`` when ``whiten``.
    """
    C = components
    if whiten:
        C = np.sqrt(explained_variance)[:, None] * C
    return Z @ C + mean
