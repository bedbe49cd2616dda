"""Keep freed memory for reuse in a process that runs a whole job (glibc only).

The drivers of a job (``streamsvd ingest``, :func:`streamsvd.parallel.tall_compress`,
:func:`streamsvd.parallel.tree_compress`) allocate and free arrays of a few MB thousands
of times: row chunks of the source and of the panels, zarr's decoded chunks, blocks.
glibc adapts its thresholds to them, and still gives the memory back to the kernel
whenever the top of a heap holds more than twice the largest recent allocation; the
kernel then zeroes every page again when it is next used. On a 200000 x 1000 zarr array
the tall mode made 400000 to 500000 page faults and spent 3 to 3.7 s of its 11 s of CPU
in the kernel (``bench/README.md``).

:func:`keep_freed_memory` fixes the two thresholds instead: arrays below
:data:`MMAP_THRESHOLD` come from the heaps, and up to :data:`TRIM_THRESHOLD` of free
memory stays at a heap's top for the next array. It also caps the heaps (glibc's arenas)
at one per core, where glibc makes up to eight per core: each thread that allocates
(dask's, zarr's, the codecs') would otherwise keep its own free memory. On the same array
the tall mode peaked at 289 to 293 MB against 338 to 350 MB, in the same time (medians
of 6 interleaved processes: 5.74 against 5.75 s), and with a task per core more
(:func:`streamsvd._util.scheduling.execute`'s ``overlap_io``) at 324 to 334 MB.

It changes the process's allocator, so only the drivers call it, once; it does nothing
when the environment already tunes glibc's malloc (``MALLOC_MMAP_THRESHOLD_``,
``MALLOC_TRIM_THRESHOLD_``, ``MALLOC_TOP_PAD_``, ``MALLOC_ARENA_MAX`` or ``glibc.malloc``
in ``GLIBC_TUNABLES``), or on another C library.
"""

from __future__ import annotations

import ctypes
import logging
import os
import platform
import threading
from collections.abc import Callable

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "keep_freed_memory"]

logger = logging.getLogger(__name__)

MMAP_THRESHOLD = 32 << 20  # glibc's largest adaptive threshold (64-bit)
TRIM_THRESHOLD = 256 << 20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8  # mallopt's (malloc.h)
_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_",
                  "MALLOC_ARENA_MAX")

_lock = threading.Lock()
_applied: bool | None = None  # None: not tried yet in this process


def keep_freed_memory() -> bool:
    """Fix glibc's thresholds and arenas for this process (once); return whether set.

    Returns False, changing nothing, when the environment tunes malloc already, when the
    C library is not glibc, or when ``mallopt`` refuses a value.
    """
    global _applied
    with _lock:
        if _applied is None:
            _applied = _apply()
        return _applied


def _apply() -> bool:
    if any(name in os.environ for name in _USER_SETTINGS) or (
            "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", "")):
        logger.debug("malloc is tuned by the environment: left as it is")
        return False
    mallopt = _glibc_mallopt()
    if mallopt is None:
        return False
    arenas = _usable_cores()
    done = (bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
            and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
            and bool(mallopt(_M_ARENA_MAX, arenas)))
    logger.debug("glibc malloc: mmap threshold %d, trim threshold %d, %d arenas: %s",
                 MMAP_THRESHOLD, TRIM_THRESHOLD, arenas, "set" if done else "refused")
    return done


def _usable_cores() -> int:
    """Return the cores this process may use (its CPU affinity; not importing dask)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return max(os.cpu_count() or 1, 1)


def _glibc_mallopt() -> Callable[[int, int], int] | None:
    """Return glibc's ``mallopt``, or None on another C library."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt
