"""Reading a source's blocks: the read-ahead thread, the reads and their checks.

:func:`read_ahead` reads the next column ranges in a background thread while the caller
works on the current one; :func:`_fill` copies rows and columns of the underlying data
into a block, :func:`_check_finite` reports a NaN or infinite entry by its place in the
source, and :func:`_read_failed` the failure of a read, with its offset.
"""

from __future__ import annotations

import queue
import sys
import threading
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from streamsvd._util.slabs import copy_by_row_slabs
from streamsvd._util.validation import first_non_finite
from streamsvd.errors import NonFiniteError, SourceError
from streamsvd.io.chunks import ChunkFiles

if TYPE_CHECKING:
    from streamsvd.io.sources import Source

__all__ = ["FIRST_THREADS", "EarlyRead", "read_ahead"]

#: Threads that decode a block the caller waits for with nothing to overlap (the first)
FIRST_THREADS = 2

# sys.getrefcount of a block that only the generator's own name refers to (the count
# includes the call's argument)
_UNREFERENCED = 2


def read_ahead(
    read: Callable[[int, int, np.ndarray | None], np.ndarray],
    ranges: list[tuple[int, int]],
    depth: int,
) -> Generator[tuple[int, np.ndarray], None, None]:
    """Yield ``(a, read(a, b, spare))`` for each range, read by a background thread.

    The thread reads at most ``depth`` ranges ahead of the one the caller holds (a
    semaphore of ``depth + 1`` permits, one given back each time the caller asks for the
    next block); an exception of ``read`` is raised to the caller when it asks for that
    range, after every range before it was yielded. Closing the generator stops the
    thread (after the read in progress) and waits for it.

    A block that nobody refers to any more when the caller asks for the next one (the
    caller dropped it, as :func:`streamsvd.stream.ingest.ingest` does) is handed to a later
    read as ``spare``, to be filled again (``None`` when there is none): the memory of a
    new block is zeroed by the kernel as it is first written. A block the caller still
    holds, or any view of it, is never reused (its reference count says so).
    """
    if not ranges:
        return
    done: queue.SimpleQueue[tuple[int, np.ndarray | None, BaseException | None]] = (
        queue.SimpleQueue())
    permits = threading.Semaphore(depth + 1)
    stopping = threading.Event()
    spares: queue.SimpleQueue[np.ndarray] = queue.SimpleQueue()

    def reader() -> None:
        for a, b in ranges:
            permits.acquire()
            if stopping.is_set():
                return
            try:
                # the spare is not named here: a name would keep it referenced
                done.put((a, read(a, b, None if spares.empty() else spares.get()), None))
            except BaseException as exc:  # handed to the caller, at this block
                done.put((a, None, exc))
                return

    thread = threading.Thread(target=reader, name="streamsvd-reader", daemon=True)
    thread.start()
    try:
        for _ in ranges:
            a, X, exc = done.get()
            if exc is not None:
                raise exc
            yield a, cast(np.ndarray, X)
            if sys.getrefcount(X) == _UNREFERENCED:
                spares.put(cast(np.ndarray, X))
            del X
            permits.release()
    finally:
        stopping.set()
        permits.release()
        thread.join()


def _read_failed(exc: Exception, start: int, stop: int, description: str) -> SourceError:
    """Return the error that reports a failed read of columns ``start:stop``."""
    return SourceError(
        f"reading columns {start}:{stop} (offset {start}) of {description} failed: "
        f"{type(exc).__name__}: {exc}. Check that the data is readable and resume from "
        f"offset {start}."
    )


def _checked_chunk(part: np.ndarray, start: int, n: int, description: str,
                   block_info: dict | None = None) -> np.ndarray:
    """Check a chunk of a dask source's columns from ``start`` (``block_info``: its rows)."""
    row0 = 0 if block_info is None else int(block_info[0]["array-location"][0][0])
    _check_finite(part, start, row0, n, description)
    return part


def _check_finite(block: np.ndarray, start: int, row0: int, n: int, description: str) -> None:
    """Raise :class:`NonFiniteError` naming the first bad entry in source coordinates.

    ``block`` holds columns ``start:start + b`` of rows ``row0:`` of a source of ``n``
    rows; the first bad entry is the first in column order (the earliest snapshot),
    reported by its row and its column in the whole source, not by its index inside
    the block.
    """
    bad = first_non_finite(block)
    if bad is None:
        return
    row, col, count = bad
    rows = "" if row0 == 0 and block.shape[0] == n else (
        f" rows {row0}:{row0 + block.shape[0]} of")
    raise NonFiniteError(
        f"`source` must be finite; {description} holds {float(block[row, col])} "
        f"at column {start + col}, row {row0 + row} (counted from 0; {count} NaN or "
        f"infinite entries in{rows} columns {start}:{start + block.shape[1]}). Repair or "
        "remove that snapshot."
    )


def _fill(out: np.ndarray, data: Any, r0: int, start: int, stop: int, *,
          compute: bool = False) -> None:
    """Fill ``out`` with rows ``r0:r0 + len(out)``, columns ``start:stop``, of ``data``.

    A zarr (v3) array of ``out``'s dtype decodes each chunk straight into ``out``
    (column-major), where indexing would decode into a row-major slab copied again (20%
    of the read time, and a slab of transients, on a 200000 x 1000 float64 array);
    other data are indexed (``compute``: a dask slice) and copied by row slabs,
    converting their dtype.
    """
    rows = slice(r0, r0 + out.shape[0])
    if type(data).__module__.startswith("zarr") and np.dtype(data.dtype) == out.dtype:
        from zarr.core.buffer.cpu import NDBuffer

        data.get_basic_selection((rows, slice(start, stop)), out=NDBuffer.from_numpy_array(out))
        return
    part = data[rows, start:stop]
    copy_by_row_slabs(out, part.compute() if compute else part)


class EarlyRead:
    """Columns ``start:stop`` of a source, read by a daemon thread from now on.

    ``streamsvd ingest`` reads its first block while it imports the update step and
    creates its store: those run the interpreter, decoding does not need it, so the two
    share the cores. The block is checked as any other, and its error is raised by
    :meth:`result`, where the block is asked for.
    """

    def __init__(self, source: Source, start: int, stop: int) -> None:
        self.range = (start, stop)
        self._block: np.ndarray | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(source,),
                                        name="streamsvd-early-read", daemon=True)
        self._thread.start()

    def _run(self, source: Source) -> None:
        try:
            self._block = source._read_checked(*self.range, threads=FIRST_THREADS)
        except BaseException as exc:  # raised where the block is asked for
            self._error = exc

    def join(self) -> None:
        """Wait for the read to end."""
        self._thread.join()

    def result(self) -> np.ndarray:
        """Return the block (waiting for it), or raise the read's error."""
        self._thread.join()
        block, self._block = self._block, None
        if self._error is not None:
            raise self._error
        return cast(np.ndarray, block)


class _ChunkReader:
    """Columns ``start:stop`` of a source seen by dask: each row slice is read and checked.

    It holds what a task needs and nothing more (it is shipped to the workers of a
    cluster): the data, or for an in-memory array only the view of its columns. A row
    slice is read row-major, as the tall mode's scratch copy stores it (no copy before
    the write: 5% of ``tall_compress`` on 200000 x 1000, ``bench/README.md``).
    """

    def __init__(self, source: Source, start: int, stop: int) -> None:
        data = source._data
        self.offset = 0 if isinstance(data, np.ndarray) else start
        self.data = data[:, start:stop] if isinstance(data, np.ndarray) else data
        self.start, self.stop, self.description = start, stop, source.description
        self.shape = (source.n, stop - start)
        self.dtype, self.ndim = source.block_dtype, 2

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        r0, r1, _ = rows.indices(self.shape[0])
        c0, c1, _ = cols.indices(self.shape[1])
        out = np.empty((r1 - r0, c1 - c0), dtype=self.dtype, order="C")
        finite = False
        try:
            # a local zarr array is decoded chunk by chunk (looked up here, in the task:
            # the reader is shipped to a cluster's workers without it)
            files = None if isinstance(self.data, np.ndarray) else ChunkFiles.of(self.data)
            if files is not None and files.dtype == self.dtype and out.size:
                finite = files.fill(out, r0, self.offset + c0)
            else:
                _fill(out, self.data, r0, self.offset + c0, self.offset + c1)
        except Exception as exc:  # any reader failure is reported with its offset
            raise _read_failed(exc, self.start, self.stop, self.description) from exc
        if not finite:
            _check_finite(out, self.start + c0, r0, self.shape[0], self.description)
        return out
