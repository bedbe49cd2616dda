"""Exact power-of-two scaling and overflow-safe norms.

Multiplying by a power of two is exact in binary floating point (away from the
subnormal range), so arrays whose entries lie anywhere between 1e-300 and 1e300 can be
brought near 1 before squares or inner products are formed, and the result scaled back.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from streamsvd._util.slabs import copy_by_row_slabs, row_slabs
from streamsvd._util.validation import check_finite

__all__ = [
    "block_exponents", "column_exponents", "pow2_exponent", "safe_column_norms",
    "safe_m_norms", "safe_norm", "scale_by", "scale_into", "scaled_norm", "top_exponent",
]


def pow2_exponent(x: np.ndarray) -> int:
    """Return ``e`` such that ``max(abs(x)) * 2**-e`` lies in [0.5, 1), or 0 for a zero array."""
    if x.size == 0:
        return 0
    peak = float(np.abs(x).max())
    if peak == 0.0:
        return 0
    return math.frexp(peak)[1]


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


def scale_into(X: np.ndarray, Y: np.ndarray, *, name: str | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Write ``X 2^-e`` into ``Y``, ``e`` per column, so that its peak lies in [1/2, 1).

    ``name`` given, a NaN or infinite entry (a peak that is not finite: NaN and
    infinities propagate through the maxima) raises
    :class:`~streamsvd.errors.NonFiniteError` naming it, before ``Y`` is scaled.

    Returns the exponents (0 for a zero column) and the mask of the zero columns. The
    copy is made first and the peaks
    are taken on ``Y`` (column-major: contiguous columns, whatever the layout of ``X``);
    a column-major ``X`` is measured where it is and scaled into ``Y`` in one pass.
    The scaling is exact, subnormal peaks included.
    """
    if Y.shape[0] == 0:
        return np.zeros(Y.shape[1], dtype=np.int64), np.ones(Y.shape[1], dtype=bool)
    if (isinstance(X, np.ndarray) and X.dtype in (np.float64, np.float32)
            and X.flags.f_contiguous):
        # already column-major: each column's peak taken where it lies and the column
        # written scaled while it is in the cache (float32 widened exactly on the way);
        # a block with a NaN, an infinity or an extreme exponent takes the numpy form
        scaled = _scale_columns(X, Y)
        if scaled is not None:
            return scaled
        exps, peak = column_exponents(X)
        _check_peaks(X, peak, name)
        scale_by(X, exps, Y)
        return exps, peak == 0
    copy_by_row_slabs(Y, X)
    exps, peak = column_exponents(Y)
    _check_peaks(X, peak, name)
    if np.all(np.abs(exps) < 1000):  # the factors 2^-e are representable: one multiply
        Y *= np.ldexp(1.0, -exps)
    else:
        np.ldexp(Y, -exps[np.newaxis, :], out=Y)
    return exps, peak == 0


# the integer image of each float format: (integer type, mask of the sign bit, mantissa
# bits, exponent bias)
_FORMATS: dict[np.dtype[Any], tuple[type[np.signedinteger[Any]], int, int, int]] = {
    np.dtype(np.float64): (np.int64, 0x7FFF_FFFF_FFFF_FFFF, 52, 1023),
    np.dtype(np.float32): (np.int32, 0x7FFF_FFFF, 23, 127),
}


def _scale_columns(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Scale ``X`` into ``Y`` by the compiled kernel; None when it declines the block.

    It declines a block holding a NaN or an infinity, or with a column whose exponent
    lies beyond +-1000 (:func:`streamsvd._util.scaling_kernels.scale_columns`).
    """
    from streamsvd._util.scaling_kernels import scale_columns

    ints, mask, mantissa, bias = _FORMATS[X.dtype]
    exps = np.zeros(X.shape[1], dtype=np.int64)
    zero = np.zeros(X.shape[1], dtype=np.bool_)
    if scale_columns(X, X.view(ints), ints(mask), mantissa, bias, Y, exps, zero):
        return None
    return exps, zero


def block_exponents(X: np.ndarray, *, name: str | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Return the exponents :func:`scale_into` scales ``X``'s columns by, and its zero columns.

    ``name`` given, a NaN or infinite entry raises
    :class:`~streamsvd.errors.NonFiniteError` naming it. For a block scaled later in
    parts (:func:`scale_by`).
    """
    exps, peak = column_exponents(X)
    _check_peaks(X, peak, name)
    return exps, peak == 0


def scale_by(X: np.ndarray, exps: np.ndarray, Y: np.ndarray) -> None:
    """Write ``X 2^-e`` into ``Y`` (exact), ``e = exps`` per column."""
    if np.all(np.abs(exps) < 1000):  # the factors 2^-e are representable: one multiply
        np.multiply(X, np.ldexp(1.0, -exps), out=Y)
    else:
        copy_by_row_slabs(Y, X)
        np.ldexp(Y, -exps[np.newaxis, :], out=Y)


def _check_peaks(X: np.ndarray, peak: np.ndarray, name: str | None) -> None:
    """Raise :class:`~streamsvd.errors.NonFiniteError` naming ``X`` if a peak is not finite."""
    if name is not None and not np.isfinite(peak).all():
        check_finite(np.asarray(X), name)


def scaled_norm(x: np.ndarray, exps: np.ndarray) -> float:
    """``sqrt(sum (x_k 2^e_k)^2)`` without overflow or underflow.

    The common scale is the largest exponent of a nonzero ``x_k``: a zero column's
    exponent (0 by convention) beside columns of 1e-300 would push them below the
    normal range, where their squares vanish.
    """
    top = top_exponent(exps, x != 0)
    if top is None:
        return 0.0
    return math.ldexp(float(np.linalg.norm(np.ldexp(x, exps - top))), top)


def top_exponent(exps: np.ndarray, live: np.ndarray) -> int | None:
    """Return the largest of the exponents ``exps`` where ``live`` (None: nothing live)."""
    return int(exps[live].max()) if np.any(live) else None
