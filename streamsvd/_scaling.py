"""Exact power-of-two scaling and overflow-safe norms.

Multiplying by a power of two is exact in binary floating point (away from the
subnormal range), so arrays whose entries lie anywhere between 1e-300 and 1e300 can be
brought near 1 before squares or inner products are formed, and the result scaled back.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["pow2_exponent", "safe_column_norms", "safe_m_norms", "safe_norm"]


def pow2_exponent(x: np.ndarray) -> int:
    """Return ``e`` such that ``max(abs(x)) * 2**-e`` lies in [0.5, 1), or 0 for a zero array."""
    if x.size == 0:
        return 0
    peak = float(np.max(np.abs(x)))
    if peak == 0.0:
        return 0
    return int(np.frexp(peak)[1])


def safe_column_norms(X: np.ndarray) -> np.ndarray:
    """Euclidean norms of the columns of ``X`` without overflow or harmful underflow.

    Each column is scaled by the power of two nearest its largest entry before squaring,
    as LAPACK's ``dnrm2`` does with a running scale.
    """
    if X.shape[0] == 0:
        return np.zeros(X.shape[1])
    peak = np.max(np.abs(X), axis=0)
    exps = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0)
    # Fortran order makes the summation order, hence the rounding, independent of the
    # caller's memory layout: equal columns always get bit-identical norms
    scaled = np.asfortranarray(np.ldexp(X, -exps[np.newaxis, :]))
    return np.ldexp(np.sqrt(np.einsum("ij,ij->j", scaled, scaled)), exps)


def safe_norm(X: np.ndarray) -> float:
    """Frobenius norm without overflow (the array scaled by a power of two first)."""
    e = pow2_exponent(X)
    return math.ldexp(float(np.linalg.norm(np.ldexp(X, -e))), e)


def safe_m_norms(X: np.ndarray, inner: Any) -> np.ndarray:
    """``M``-norms of the columns, each scaled by a power of two first (no overflow)."""
    if inner.is_euclidean:
        return safe_column_norms(X)
    peak = np.max(np.abs(X), axis=0) if X.shape[0] else np.zeros(X.shape[1])
    e = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0)
    Y = np.ldexp(X, -e[np.newaxis, :])
    return np.ldexp(np.sqrt(np.maximum(np.einsum("ij,ij->j", Y, inner.apply(Y)), 0.0)), e)
