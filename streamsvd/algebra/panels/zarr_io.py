"""Reads and writes of zarr arrays that run in parallel: one event loop per core.

zarr (v3) runs every synchronous read and write (``z[...]``, ``z[...] = x``) on one
event loop thread shared by the whole process, and its codecs that do not hand their
work to a thread (the ``bytes`` codec, ``crc32c``, the copies into and out of the
chunks) run on that thread, so the reads and writes of dask's threads queue there
behind each other and behind the callbacks of every other read in flight.

Here the same reads and writes of a local or in-memory store run on one of
``os.cpu_count()`` event loops of this module, the least busy. The work done is zarr's
own (:class:`zarr.AsyncArray`'s ``getitem`` and ``setitem``), only the loop differs.
Arrays in other stores (object stores, whose clients belong to zarr's loop) use zarr's
synchronous interface unchanged.

Measured (``bench/zarr_io_benchmark.py``, medians of 4, load 1.8): the tall mode on a
200000 x 1000 float64 zarr array took 15.6 s against 16.9 s through zarr's loop (faster
in each of the 4 pairs); 10000 x 100 float64 chunks from two threads that do nothing
else were written in 5.8 ms against 7.5 ms and read in 8.7 ms against 12.1 ms each.
From one thread they were not faster (read 20.3 ms against 9.8 ms), and one thread
reading a source's blocks in slabs of several chunks was 5 to 15% slower, so the
panels (read and written by dask's threads) use this module and the sources do not.

Since the tall mode's passes use raw panels (:mod:`streamsvd.algebra.panels.basis`), this module
writes the zarr copies its commits list and reads a reopened store's panels. With a
commit at every update the tall mode took 9.8 s against 9.3 s through zarr's loop
(medians of 3 that overlap: no gain); chunks read from two threads took 3.9 ms against
9.5 ms (``results/zarr_io_benchmark_raw_panels.json``).
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Coroutine
from typing import Any

import numpy as np

__all__ = ["Region", "read", "write"]

_lock = threading.Lock()
_loops: list[asyncio.AbstractEventLoop] = []
_running: list[int] = []  # calls in flight on each loop


def _start_loops() -> None:
    for _ in range(os.cpu_count() or 1):
        loop = asyncio.new_event_loop()
        threading.Thread(target=loop.run_forever, name="streamsvd-zarr-io",
                         daemon=True).start()
        _loops.append(loop)
        _running.append(0)


def _forget_loops() -> None:
    """After a fork, the child has none of the parent's loop threads."""
    global _lock
    _lock = threading.Lock()
    _loops.clear()
    _running.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_loops)


def _run(coro: Coroutine[Any, Any, Any]) -> Any:
    """Run ``coro`` on the least busy of this module's loops; return its result."""
    with _lock:
        if not _loops:
            _start_loops()
        i = min(range(len(_loops)), key=_running.__getitem__)
        _running[i] += 1
    try:
        return asyncio.run_coroutine_threadsafe(coro, _loops[i]).result()
    finally:
        with _lock:
            _running[i] -= 1


def _parallel(array: Any) -> bool:
    """Whether ``array``'s store can be used from this module's loops."""
    from zarr.storage import LocalStore, MemoryStore

    return isinstance(array.store, LocalStore | MemoryStore)


def read(array: Any, selection: slice | tuple[slice, ...]) -> np.ndarray:
    """Return ``array[selection]`` (row-major)."""
    if not _parallel(array):
        return np.asarray(array[selection])
    return np.asarray(_run(array.async_array.getitem(selection)))


def write(array: Any, selection: slice | tuple[slice, ...], value: np.ndarray) -> None:
    """``array[selection] = value``."""
    if not _parallel(array):
        array[selection] = value
        return
    _run(array.async_array.setitem(selection, value))


class Region:
    """A zarr array as dask sees an array: read and written through this module.

    ``dask.array.from_array(Region(z), ...)`` reads, ``dask.array.store(x, Region(z))``
    writes. It pickles as its zarr array (a path and its metadata), so it reaches the
    workers of a cluster.
    """

    def __init__(self, array: Any) -> None:
        self.array = array
        self.shape = tuple(array.shape)
        self.dtype = np.dtype(array.dtype)
        self.ndim = len(self.shape)

    def __getitem__(self, key: slice | tuple[slice, ...]) -> np.ndarray:
        return read(self.array, key)

    def __setitem__(self, key: slice | tuple[slice, ...], value: np.ndarray) -> None:
        write(self.array, key, value)
