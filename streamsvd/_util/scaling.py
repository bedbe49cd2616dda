"""Exact power-of-two scaling and overflow-safe norms.

Multiplying by a power of two is exact in binary floating point (away from the
subnormal range), so arrays whose entries lie anywhere between 1e-300 and 1e300 can be
brought near 1 before squares or inner products are formed, and the result scaled back.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from streamsvd._util.slabs import row_slabs

__all__ = [
    "column_exponents", "pow2_exponent", "safe_column_norms", "safe_m_norms", "safe_norm",
]


def pow2_exponent(x: np.ndarray) -> int:
    """Return ``e`` such that ``max(abs(x)) * 2**-e`` lies in [0.5, 1), or 0 for a zero array."""
    if x.size == 0:
        return 0
    peak = float(np.max(np.abs(x)))
    if peak == 0.0:
        return 0
    return int(np.frexp(peak)[1])


def column_exponents(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return each column's binary exponent ``e`` and its largest absolute entry ``peak``.

    ``peak 2^-e`` lies in [1/2, 1) (``e = 0`` for a zero column); taken by slabs of rows,
    without a copy of ``X``.
    """
    peak = np.zeros(X.shape[1])
    starts = row_slabs(X)
    for i in starts:
        slab = X[i:i + starts.step]
        # max and -min: no temporary |X| (NaN propagates through both, as through abs)
        np.maximum(peak, slab.max(axis=0), out=peak)
        np.maximum(peak, -slab.min(axis=0), out=peak)
    exps = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0)
    return exps.astype(np.int64), peak


def safe_column_norms(X: np.ndarray) -> np.ndarray:
    """Euclidean norms of the columns of ``X`` without overflow or harmful underflow.

    Each column is scaled by the power of two nearest its largest entry before squaring,
    as LAPACK's ``dnrm2`` does with a running scale. The squares are summed by slabs of
    rows, each copied in Fortran order: the summation order, hence the rounding, does
    not depend on the caller's memory layout (equal columns get bit-identical norms),
    and nothing of the size of ``X`` is allocated.
    """
    if X.shape[0] == 0:
        return np.zeros(X.shape[1])
    starts = row_slabs(X)
    exps = column_exponents(X)[0]
    total = np.zeros(X.shape[1])
    for i in starts:
        scaled = np.asfortranarray(np.ldexp(X[i:i + starts.step], -exps[np.newaxis, :]))
        total += np.einsum("ij,ij->j", scaled, scaled)
    return np.ldexp(np.sqrt(total), exps)


def safe_norm(X: np.ndarray) -> float:
    """Frobenius norm without overflow (the array scaled by a power of two first)."""
    e = pow2_exponent(X)
    return math.ldexp(float(np.linalg.norm(np.ldexp(X, -e))), e)


def safe_m_norms(X: np.ndarray, inner: Any) -> np.ndarray:
    """``M``-norms of the columns, each scaled by a power of two first (no overflow)."""
    if inner.is_euclidean:
        return safe_column_norms(X)
    if X.shape[0] == 0:
        return np.zeros(X.shape[1])
    e = column_exponents(X)[0]
    Y = np.ldexp(X, -e[np.newaxis, :])
    return np.ldexp(np.sqrt(np.maximum(np.einsum("ij,ij->j", Y, inner.apply(Y)), 0.0)), e)
