"""Numbers drawn from a solution: SVD modes, MAC matrices (eq. 21), checks of the laws.

Nothing here plots; :mod:`contact.figures` does.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla

from .problem import Problem

__all__ = ["LawCheck", "SVDModes", "check_laws", "mac", "optimal_rank", "svd_modes"]


@dataclass(frozen=True, eq=False)
class SVDModes:
    """Singular value decomposition ``Y = sum_i s_i x_i t_i^T`` of a space-time field.

    Attributes
    ----------
    values : ndarray, shape (r,)
        Singular values, decreasing.
    space : ndarray, shape (n, r)
        Orthonormal spatial modes ``x_i``.
    time : ndarray, shape (m, r)
        Orthonormal temporal modes ``t_i`` (divide by ``max |t_i|`` to normalise a plot).
    """

    values: np.ndarray
    space: np.ndarray
    time: np.ndarray

    def rank(self, rtol: float) -> int:
        """Return ``#{i : s_i >= rtol * s_1}``, the optimal basis size at ``rtol``."""
        return optimal_rank(self.values, rtol)

    def tail_rank(self, rtol: float) -> int:
        """Return the smallest ``r`` with ``||Y - Y_r||_F <= rtol ||Y||_F`` (tail energy)."""
        s2 = np.asarray(self.values, dtype=float) ** 2
        tail = np.sqrt(np.append(np.cumsum(s2[::-1])[::-1], 0.0))  # tail[r] = ||Y - Y_r||
        return int(np.argmax(tail <= rtol * tail[0])) if s2.size else 0

    def sizes(self, rtol: float) -> dict[str, int]:
        """Return both optimal sizes at ``rtol``: ``{"sigma_ratio": ..., "tail_energy": ...}``."""
        return {"sigma_ratio": self.rank(rtol), "tail_energy": self.tail_rank(rtol)}


def svd_modes(Y: np.ndarray, *, inner: Any = None) -> SVDModes:
    """Return the SVD of ``Y`` (n x m) with deterministic signs, in the norm of ``inner``.

    With ``inner`` (an SPD matrix, dense or sparse, for instance
    :func:`contact.indicator_metric`), ``Y = sum_i s_i x_i t_i^T`` with ``x_i``
    orthonormal in ``x^T M x`` and ``s`` the singular values in that norm. They come from
    the Euclidean SVD ``Y = Q S T^T`` restricted to its numerical rank (so that every
    ``x_i`` lies in the range of ``Y``, and vanishes where all of ``Y`` does), the Cholesky
    factor ``L`` of ``Q^T M Q`` and the SVD of ``L^T S T^T`` (``O(n m^2)``). The sign of
    each pair is chosen so that the largest entry of the temporal mode is positive (as
    ``svd_flip`` of scikit-learn does with the right vectors).
    """
    Y = np.asarray(Y, dtype=float)
    X, s, Tt = np.linalg.svd(Y, full_matrices=False)
    if inner is not None:
        r = int(np.count_nonzero(s > max(Y.shape) * np.finfo(float).eps * s[0])) if (
            s.size and s[0] > 0) else 0
        Q = X[:, :r]
        Lm = np.linalg.cholesky(Q.T @ (inner @ Q))
        Xs, s, Tt = np.linalg.svd(Lm.T @ (s[:r, None] * Tt[:r]), full_matrices=False)
        X = Q @ sla.solve_triangular(Lm.T, Xs)
    T = Tt.T
    signs = np.sign(T[np.argmax(np.abs(T), axis=0), np.arange(T.shape[1])])
    signs[signs == 0] = 1.0
    return SVDModes(s, X * signs, T * signs)


def optimal_rank(values: np.ndarray, rtol: float) -> int:
    """Return ``#{i : s_i >= rtol * s_1}`` for decreasing singular values ``s``."""
    values = np.asarray(values)
    if values.size == 0 or values[0] <= 0:
        return 0
    return int(np.count_nonzero(values >= rtol * values[0]))


def mac(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Return the MAC matrix of eq. (21), ``M_ij = (X_i^T Y_j)^2 / (||X_i||^2 ||Y_j||^2)``.

    Parameters
    ----------
    X : ndarray, shape (n, p)
    Y : ndarray, shape (n, q)

    Returns
    -------
    ndarray, shape (p, q), entries in [0, 1]; zero columns give zero entries.
    """
    nx = np.sum(X * X, axis=0)
    ny = np.sum(Y * Y, axis=0)
    den = np.outer(nx, ny)
    num = (X.T @ Y) ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        M = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.clip(M, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class LawCheck:
    """Violations of the contact laws by a state ``(w, lam)``, each made dimensionless.

    Scales: ``G = max(max gap, max |w_N|)`` for displacements, ``F = max |lam_N|`` for
    normal tractions and ``F_T = mu F`` (``F`` when ``mu = 0``), the largest admissible
    ``|lam_T|``, for the tangential traction; ``dw_T`` is the tangential increment between
    instants.

    Attributes
    ----------
    penetration : float
        ``max(w_N - g, 0) / G``.
    tension : float
        ``max(lam_N, 0) / F`` (tractions must be compressive).
    complementarity : float
        ``max |lam_N (g - w_N)| / (F G)``.
    cone : float
        ``max(|lam_T| + mu lam_N, 0) / F_T`` (inside the Coulomb cone): the excess of
        ``|lam_T|`` over ``-mu lam_N`` relative to the largest admissible ``|lam_T|``.
    slip_direction : float
        ``max(lam_T dw_T, 0) / (F_T G)`` (slip opposite to the tangential traction).
    stick_slip : float
        ``max |dw_T| (mu |lam_N| - |lam_T|) / (F_T G)`` (slip only on the cone).
    dissipation : float
        Total frictional dissipation ``-sum L lam_T dw_T`` (N mm, per radian when
        axisymmetric); non-negative for an admissible state.
    """

    penetration: float
    tension: float
    complementarity: float
    cone: float
    slip_direction: float
    stick_slip: float
    dissipation: float

    def worst(self) -> float:
        """Return the largest of the dimensionless violations."""
        return max(self.penetration, self.tension, self.complementarity, self.cone,
                   self.slip_direction, self.stick_slip)


def check_laws(problem: Problem, w: np.ndarray, lam: np.ndarray) -> LawCheck:
    """Measure how well ``(w, lam)`` (2 nc x m) satisfies Signorini and Coulomb."""
    nc = problem.nc
    g = problem.gaps[:, None]
    wN, wT = w[:nc], w[nc:]
    lN, lT = lam[:nc], lam[nc:]
    dwT = np.diff(np.concatenate([np.zeros((nc, 1)), wT], axis=1), axis=1)
    G = max(float(np.max(problem.gaps, initial=0.0)), float(np.max(np.abs(wN))), 1e-300)
    F = max(float(np.max(np.abs(lN))), 1e-300)
    mu = problem.mu
    FT = max(mu * F, 1e-300) if mu > 0 else F  # scale of the tangential traction
    D = -lT * dwT
    return LawCheck(
        penetration=float(np.max(np.maximum(wN - g, 0.0))) / G,
        tension=float(np.max(np.maximum(lN, 0.0))) / F,
        complementarity=float(np.max(np.abs(lN * (g - wN)))) / (F * G),
        cone=float(np.max(np.maximum(np.abs(lT) + mu * lN, 0.0))) / FT,
        slip_direction=float(np.max(np.maximum(-D, 0.0))) / (FT * G),
        stick_slip=float(np.max(np.abs(dwT) * np.maximum(mu * np.abs(lN) - np.abs(lT), 0.0)))
        / (FT * G),
        dissipation=float(np.sum(problem.weights[:, None] * D)),
    )
