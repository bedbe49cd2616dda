"""The compiled kernel of a block's column scaling (:func:`streamsvd._util.scaling.scale_into`).

Each column's peak is taken on the integer image of its entries: ``|x|`` is the bit
pattern with the sign bit cleared, and for non-negative floats the order of the patterns
is the order of the values, so the peak is an integer maximum, which needs no allowance
for NaN (a NaN or an infinity shows as the largest exponent). The exponents follow from
the peaks' bits; every peak is taken before any column is written, so a block with a
NaN leaves the workspace as it was. Two reads of the block where the numpy form made
three (its maximum, its minimum, then the scaled copy): 5101 x 91 columns, 0.49-0.55 ms
against 0.69-0.75 ms (``bench/studies/tight-targets.md``).

Kept apart so that importing the package does not import numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["scale_columns"]

# exponents beyond this take ldexp (the factor 2^-e would not be a normal number)
_FACTOR_LIMIT = 1000


@numba.njit(cache=True)
def scale_columns(X: np.ndarray, bits: np.ndarray, mask: np.integer, mantissa: int, bias: int,
                  Y: np.ndarray, exps: np.ndarray, zero: np.ndarray
                  ) -> int:  # pragma: no cover - compiled
    """Write ``X 2^-e`` into ``Y``, ``e`` per column (``peak 2^-e`` in [1/2, 1)).

    ``bits`` is ``X`` viewed as integers of its width, ``mask`` clears their sign bit,
    ``mantissa`` and ``bias`` are the format's (52 and 1023 for float64, 23 and 127 for
    float32). Writes the exponents (0 for a zero column) and the zero columns' mask.
    Returns 0, or 1 when a column holds a NaN or an infinity or has an exponent beyond
    ``+-1000``: the caller then scales the block by its numpy form, which reports them.
    """
    n, b = X.shape
    top = 2 * bias + 1  # the biased exponent of infinities and NaN
    for j in range(b):
        peak = bits[0, j] & 0
        for i in range(n):
            v = bits[i, j] & mask
            if v > peak:
                peak = v
        biased = int(peak >> mantissa)
        if biased == top:
            return 1
        if biased > 0:
            e = biased - (bias - 1)
        elif peak == 0:
            e = 0
        else:  # subnormal: the value is peak 2^(1 - bias - mantissa)
            length = 0
            rest = int(peak)
            while rest:
                rest >>= 1
                length += 1
            e = length - (bias - 1 + mantissa)
        if e >= _FACTOR_LIMIT or e <= -_FACTOR_LIMIT:
            return 1
        exps[j] = e
        zero[j] = peak == 0
    for j in range(b):
        factor = math.ldexp(1.0, -exps[j])
        for i in range(n):
            Y[i, j] = X[i, j] * factor
    return 0
