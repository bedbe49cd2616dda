"""Row slabs: an ``n``-sized array walked a few MiB of rows at a time.

Reductions and copies over a tall block by slabs of rows that fit in the cache allocate
nothing of the block's size, and a copy that changes the layout (row-major data into a
column-major block) runs several times faster than a transposing copy of the whole.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["copy_by_row_slabs", "row_slabs"]

SLAB_BYTES = 1 << 21  # 2 MiB of rows per slab


def row_slabs(X: Any) -> range:
    """Return the first rows of the slabs of ``X`` (``n x k``): ``range(0, n, step)``."""
    itemsize = np.dtype(X.dtype).itemsize
    return range(0, X.shape[0], max(1, SLAB_BYTES // (itemsize * max(1, X.shape[1]))))


def copy_by_row_slabs(out: np.ndarray, part: Any) -> None:
    """Copy the 2-D block ``part`` into ``out`` slab by slab, converting its dtype."""
    part = np.asarray(part)
    starts = row_slabs(out)
    for i in starts:
        out[i:i + starts.step] = part[i:i + starts.step]
