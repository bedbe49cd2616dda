"""The compiled kernel of a sparse ``M`` times a column-major block, by numba.

scipy's sparse product takes its dense operand row-major: a column-major block (the
layout of every basis and workspace here) is copied to row-major, the product is
allocated row-major and copied back, which on a mass matrix of about seven entries per
row costs three to four times the product itself (5101 x 91 block, pyMOR's heat
example: 4.8 to 5.7 ms against 1.5 to 1.9 ms here, ``bench/studies/tight-targets.md``). This
kernel reads the columns where they are and writes into the caller's buffer. It sums
each row's entries in the stored order, as scipy does, so the digits are the same.

Kept apart so that importing the package does not import numba
(:mod:`streamsvd.linalg.sweep_kernels` is kept apart for the same reason).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["csr_times_columns"]


@numba.njit(cache=True, inline="always")
def _dots(X: np.ndarray, out: np.ndarray, j: int, width: int,
          dots: np.ndarray) -> None:  # pragma: no cover - compiled
    """Add ``x_c^T (A x_c)`` of the columns ``j .. j + width`` to ``dots`` (none if empty).

    Read right after the group was written, while both are in the cache; four partial
    sums over the rows (rows ``i mod 4``) run side by side, so that the additions do not
    wait on one another, and are added pairwise.
    """
    if dots.size == 0:
        return
    n = X.shape[0]
    for c in range(j, j + width):
        t0 = t1 = t2 = t3 = 0.0
        i = 0
        while i + 4 <= n:
            t0 += X[i, c] * out[i, c]
            t1 += X[i + 1, c] * out[i + 1, c]
            t2 += X[i + 2, c] * out[i + 2, c]
            t3 += X[i + 3, c] * out[i + 3, c]
            i += 4
        while i < n:
            t0 += X[i, c] * out[i, c]
            i += 1
        dots[c] = (t0 + t1) + (t2 + t3)


@numba.njit(cache=True)
def csr_times_columns(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray,
                      X: np.ndarray, out: np.ndarray,
                      dots: np.ndarray) -> None:  # pragma: no cover - compiled
    """Write ``A X`` into ``out`` (``A`` in CSR arrays, ``X`` and ``out`` column-major).

    ``dots`` (one entry per column, or empty) receives each column's ``x_c^T A x_c``,
    measured on each group right after it is written (the block is not read again).

    Eight columns at a time, then four, two and one: each entry of ``A`` is read once
    per group (91 columns of pyMOR's heat example: 1.23 ms against 1.34 ms four at a time
    and 3.1 ms for scipy's product, one thread; the groups of the remainder halve the
    time of a block of 3 to 7 columns: 0.16 ms against 0.31 ms for 7); every column's
    sums run in the stored order whatever the grouping, so the digits do not depend on
    it.
    """
    n, b = out.shape
    j = 0
    while j + 8 <= b:
        for i in range(n):
            s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                c = indices[k]
                d = data[k]
                s0 += d * X[c, j]
                s1 += d * X[c, j + 1]
                s2 += d * X[c, j + 2]
                s3 += d * X[c, j + 3]
                s4 += d * X[c, j + 4]
                s5 += d * X[c, j + 5]
                s6 += d * X[c, j + 6]
                s7 += d * X[c, j + 7]
            out[i, j] = s0
            out[i, j + 1] = s1
            out[i, j + 2] = s2
            out[i, j + 3] = s3
            out[i, j + 4] = s4
            out[i, j + 5] = s5
            out[i, j + 6] = s6
            out[i, j + 7] = s7
        _dots(X, out, j, 8, dots)
        j += 8
    if j + 4 <= b:
        for i in range(n):
            s0 = s1 = s2 = s3 = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                c = indices[k]
                d = data[k]
                s0 += d * X[c, j]
                s1 += d * X[c, j + 1]
                s2 += d * X[c, j + 2]
                s3 += d * X[c, j + 3]
            out[i, j] = s0
            out[i, j + 1] = s1
            out[i, j + 2] = s2
            out[i, j + 3] = s3
        _dots(X, out, j, 4, dots)
        j += 4
    if j + 2 <= b:
        for i in range(n):
            s0 = s1 = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                c = indices[k]
                d = data[k]
                s0 += d * X[c, j]
                s1 += d * X[c, j + 1]
            out[i, j] = s0
            out[i, j + 1] = s1
        _dots(X, out, j, 2, dots)
        j += 2
    if j < b:
        for i in range(n):
            s = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                s += data[k] * X[indices[k], j]
            out[i, j] = s
        _dots(X, out, j, 1, dots)
