"""Block iterators over snapshot sources (columns are snapshots).

:func:`~streamsvd.io.open.open_source` wraps an in-memory or on-disk ``n x m`` snapshot
matrix in a :class:`Source`, which reads column blocks as float64 arrays one at a time:

* a numpy array (or anything :func:`numpy.asarray` turns into a real 2-D array);
* a ``.npy`` file, memory-mapped;
* an HDF5 file (``.h5``, ``.hdf5``) and a dataset name (optional when the file holds
  exactly one dataset), or an open :class:`h5py.Dataset`;
* a zarr array or group (a directory, or a path ending in ``.zarr``) and an array name
  (optional when the group holds exactly one array), or an open :class:`zarr.Array`;
* a zarr array or group at a URL (``file://...``, ``s3://bucket/run.zarr``, any fsspec
  URL; ``storage_options`` go to the file system, the ``AWS_*`` environment variables
  apply), opened through :class:`zarr.storage.FsspecStore`. ``.npy`` and HDF5 files are
  read from local paths only;
* a dask array, of which each block is computed on its own with ``.compute()`` (the
  whole array is never materialised).

Files and URLs are opened by :mod:`streamsvd.io.formats`, the one place that knows their
formats.

``Source.blocks`` is the one block reader of the package (the command line, the tall
mode and the tree leaves all read through it, driven by :func:`streamsvd.stream.ingest.ingest`).
For the tall mode it yields each block unread, as a
:class:`~streamsvd.algebra.panels.lazy.LazyBlock` whose row chunks the update's dask pass
reads and checks (``rows=``); otherwise
a background thread reads the next blocks while the caller works on the current one,
through a bounded queue (``depth`` blocks ahead, one by default, so at most two blocks
are in memory), and each block of the range is read exactly once. That hides the read
time of compressed on-disk data behind the update of the basis. Every block read is
checked for NaN and infinite entries, which are reported by their row and column in the
source (not by their index inside the block).

Blocks are column-major (the layout the update's BLAS-3 products and copies want) and
keep a float32 source's dtype: half the bytes in memory and in the queue. The compressor
converts each block to float64 when it absorbs it (:meth:`StreamCompressor.absorb
<streamsvd.StreamCompressor.absorb>`), so every product is computed in float64 on the
float32 values exactly as stored; any other dtype is read as float64.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable, Generator
from types import TracebackType
from typing import Any, cast

import numpy as np

from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.panels.lazy import LazyBlock
from streamsvd.errors import InputError, ShapeMismatchError
from streamsvd.io.chunks import ChunkFiles
from streamsvd.io.readahead import (
    FIRST_THREADS,
    EarlyRead,
    _check_finite,
    _checked_chunk,
    _ChunkReader,
    _fill,
    _read_failed,
    read_ahead,
)

__all__ = ["Source"]

logger = logging.getLogger(__name__)


class Source:
    """An ``n x m`` snapshot matrix read by column blocks.

    Build one with :func:`~streamsvd.io.open.open_source`. Columns are snapshots: ``n`` is
    the size of one snapshot and ``m`` the number of snapshots. Every read returns a new
    column-major array of dtype :attr:`block_dtype` that does not share memory with the
    underlying data.

    Parameters
    ----------
    data : object
        An object with ``shape``, ``dtype`` and 2-D slicing ``data[:, a:b]`` (numpy
        array or memmap, h5py dataset, zarr array, dask array).
    description : str
        How the source is named in messages (for example ``"HDF5 dataset '/u' in
        run.h5"``).
    compute : bool
        Whether a slice must be evaluated with ``.compute()`` (dask arrays).
    on_close : callable, optional
        Called once by :meth:`close` (for example to close a file the source opened).

    Attributes
    ----------
    n : int
        Number of rows (size of one snapshot).
    m : int
        Number of columns (number of snapshots).
    dtype : numpy.dtype
        Dtype of the underlying data.
    block_dtype : numpy.dtype
        Dtype of the blocks read: float32 for float32 data, float64 otherwise.
    description : str
        How the source is named in messages.
    """

    def __init__(
        self,
        data: Any,
        description: str,
        *,
        compute: bool = False,
        on_close: Callable[[], None] | None = None,
    ) -> None:
        shape = tuple(getattr(data, "shape", ()))
        dtype = np.dtype(getattr(data, "dtype", np.float64))
        _check_matrix(shape, dtype, description)
        self._data = data
        self._compute = compute
        self._on_close = on_close
        self.n = int(shape[0])
        self.m = int(shape[1])
        self.dtype = dtype
        self.block_dtype = np.dtype(np.float32 if dtype == np.float32 else np.float64)
        self.description = description
        # a local zarr array of the blocks' dtype is decoded chunk by chunk (io/chunks.py)
        self._files = None if compute or dtype != self.block_dtype else ChunkFiles.of(data)
        self._early: EarlyRead | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(n, m)``."""
        return (self.n, self.m)

    @property
    def row_chunks(self) -> int | None:
        """Rows per chunk when the data is chunked uniformly by rows (zarr, HDF5, dask).

        None for unchunked data (numpy arrays, ``.npy`` files, contiguous HDF5) or chunks
        of several sizes (the last chunk may be shorter).
        """
        chunks = getattr(self._data, "chunks", None)
        if not chunks:
            return None
        rows = chunks[0]
        if isinstance(rows, int | np.integer):
            return int(rows)
        rows = tuple(rows)
        if len(rows) > 1 and all(c == rows[0] for c in rows[:-1]):
            return int(rows[0])
        return None

    def read(self, start: int, stop: int) -> np.ndarray:
        """Return columns ``start:stop`` as a new array of shape ``(n, stop-start)``.

        The array is column-major, of dtype :attr:`block_dtype`.

        Parameters
        ----------
        start, stop : int
            Column range, ``0 <= start <= stop <= m``.

        Raises
        ------
        InputError
            When the range is outside ``[0, m]`` or reversed.
        NonFiniteError
            When the columns hold NaN or infinite entries; the message names the first
            one (in column order) by its row and column in the source.
        SourceError
            When the underlying read fails (chained to the original exception).
        """
        start = _check_index(start, "start", self.m)
        stop = _check_index(stop, "stop", self.m)
        if stop < start:
            raise InputError(
                f"`stop` must be >= `start` ({start}); got {stop}. Pass an increasing range."
            )
        return self._read_checked(start, stop)

    def _read_checked(self, start: int, stop: int, out: np.ndarray | None = None, *,
                      threads: int = 1) -> np.ndarray:
        """Read columns ``start:stop`` (into ``out`` if it fits, on ``threads``) and check them."""
        try:
            out, finite = self._read_slabs(start, stop, out, threads=threads)
        except Exception as exc:  # any reader failure is reported with its offset
            raise _read_failed(exc, start, stop, self.description) from exc
        if not finite:
            _check_finite(out, start, 0, self.n, self.description)
        return out

    def _read_slabs(
        self, start: int, stop: int, out: np.ndarray | None = None, *, threads: int = 1
    ) -> tuple[np.ndarray, bool]:
        """Read columns ``start:stop`` into a column-major array, by slabs of rows.

        ``out`` is a block of an earlier read that nobody holds any more (see
        :func:`~streamsvd.io.readahead.read_ahead`), filled again when it has the block's
        shape, dtype and layout; otherwise a new array is made. A slab is a whole number of
        the data's row chunks, about 8 MiB, so that a read never holds the block twice in the data's
        layout (a dask array, or data one chunk tall, is read whole). Each slab is checked
        for NaN and infinite entries while it is in the cache; returns the block and
        whether every slab was finite. A local zarr array is decoded by
        :class:`~streamsvd.io.chunks.ChunkFiles` instead, on ``threads`` threads.
        """
        cols = stop - start
        if (out is None or out.shape != (self.n, cols) or out.dtype != self.block_dtype
                or not out.flags.f_contiguous or not out.flags.writeable):
            out = np.empty((self.n, cols), dtype=self.block_dtype, order="F")
        if self._files is not None and cols:
            return out, self._files.fill(out, 0, start, threads=threads)
        rows = self.n
        if not self._compute:
            # whole row chunks (all rows when the data is one chunk tall: never recompute
            # or decode a chunk twice); single rows for unchunked data
            chunked = getattr(self._data, "chunks", None) is not None
            unit = self.row_chunks or (self.n if chunked else 1)
            rows = max(unit, _READ_BYTES // max(1, cols * self.dtype.itemsize) // unit * unit)
        finite = True
        for r0 in range(0, self.n, rows):
            slab = out[r0:r0 + rows]
            _fill(slab, self._data, r0, start, stop, compute=self._compute)
            finite = finite and bool(np.isfinite(slab).all())
        return out, finite

    def read_early(self, start: int, stop: int) -> None:
        """Start reading columns ``start:stop`` now, in a background thread (:class:`EarlyRead`).

        The next :meth:`blocks` (read ahead) takes its first block from it when it is this
        range, with its errors; otherwise the read is dropped.
        """
        start = _check_index(start, "start", self.m)
        stop = _check_index(stop, "stop", self.m)
        self._early = EarlyRead(self, start, stop) if stop > start else None

    def lazy(self, start: int, stop: int, *, rows: int) -> LazyBlock:
        """Return columns ``start:stop`` as a :class:`LazyBlock` read by chunks of ``rows`` rows.

        Nothing is read here: each row chunk is read (and checked for NaN and infinite
        entries, named in source coordinates) by the task that needs it, so a product
        over the row chunks holds a few chunks at a time, never the ``n x b`` block.
        The chunks have dtype :attr:`block_dtype`.
        """
        import dask.array as da

        start = _check_index(start, "start", self.m)
        stop = _check_index(stop, "stop", self.m)
        rows = cast(int, check_positive_int(rows, "rows"))
        chunks = ((rows,) * (self.n // rows) + ((self.n % rows,) if self.n % rows else ()),
                  (stop - start,))
        name = f"streamsvd-source-{uuid.uuid4().hex}"
        if self._compute:
            part = self._data[:, start:stop].rechunk(chunks).astype(self.block_dtype)
            data = part.map_blocks(_checked_chunk, start, self.n, self.description,
                                   dtype=self.block_dtype, name=name,
                                   meta=np.empty((0, 0), self.block_dtype))
        else:
            data = da.from_array(_ChunkReader(self, start, stop), chunks=chunks, name=name,
                                 meta=np.empty((0, 0), self.block_dtype))
        return LazyBlock(data, start, self.description)

    def blocks(
        self, block: int = 100, *, start: int = 0, stop: int | None = None,
        prefetch: bool = True, depth: int = 1, min_last: int = 0, rows: int | None = None,
    ) -> Generator[tuple[int, np.ndarray | LazyBlock], None, None]:
        """Yield ``(offset, X)`` for consecutive column blocks of columns ``start:stop``.

        ``X`` holds columns ``offset:offset + b`` as a column-major array of dtype
        :attr:`block_dtype` and shape ``(n, b)``, with ``b = block`` except for the last,
        shorter block (or a longer one, with ``min_last``). Each block is read exactly once.

        Parameters
        ----------
        block : int
            Number of columns per block, >= 1.
        start : int
            First column, ``0 <= start <= m`` (``start = stop`` yields nothing); used to
            resume from a recorded source offset.
        stop : int, optional
            End of the range, ``start <= stop <= m`` (default ``m``).
        prefetch : bool
            Read ahead in a background thread while the caller works on the current
            block; a block that the caller no longer refers to when it asks for the next
            one is filled again by a later read
            (:func:`~streamsvd.io.readahead.read_ahead`).
        depth : int
            Blocks read ahead with ``prefetch`` (>= 1): at most ``depth + 1`` blocks are
            in memory, the caller's included.
        min_last : int
            A last block shorter than this joins the one before it, as often as needed
            (the batches of scikit-learn's ``gen_batches`` with ``min_batch_size``).
        rows : int, optional
            Yield each block as a :class:`LazyBlock` read by chunks of this many rows
            when its products run (:meth:`lazy`; ``prefetch`` and ``depth`` then do not
            apply: the reads of a block's row chunks overlap its own products).

        Yields
        ------
        offset : int
            Index of the block's first column.
        X : numpy.ndarray or LazyBlock, shape (n, b)
            The block.

        Raises
        ------
        InputError
            When ``block < 1``, ``depth < 1`` or the range is outside ``[0, m]`` or
            reversed.
        NonFiniteError
            When a block holds NaN or infinite entries; raised when the caller asks for
            that block, naming the first one by its row and column in the source.
        SourceError
            When reading a block fails; raised when the caller asks for that block, with
            its offset in the message and the original exception chained.
        """
        block = cast(int, check_positive_int(block, "block"))
        depth = cast(int, check_positive_int(depth, "depth"))
        start = _check_index(start, "start", self.m)
        stop = self.m if stop is None else _check_index(stop, "stop", self.m)
        if stop < start:
            raise InputError(
                f"`stop` must be >= `start` ({start}); got {stop}. Pass an increasing range."
            )
        ranges = [(a, min(a + block, stop)) for a in range(start, stop, block)]
        while len(ranges) > 1 and ranges[-1][1] - ranges[-1][0] < min_last:
            last = ranges.pop()
            ranges[-1] = (ranges[-1][0], last[1])
        if rows is not None:
            return ((a, self.lazy(a, b, rows=rows)) for a, b in ranges)
        if not prefetch:
            return ((a, self._read_checked(a, b)) for a, b in ranges)
        first = ranges[0] if ranges else (0, 0)
        early, self._early = self._early, None

        def read(a: int, b: int, spare: np.ndarray | None) -> np.ndarray:
            if early is not None and (a, b) == first:
                return early.result()
            # the caller waits for the first block with nothing to overlap: two cores
            # decode it; later blocks are decoded by the reader alone, beside the update
            threads = FIRST_THREADS if (a, b) == first else 1
            return self._read_checked(a, b, spare, threads=threads)

        return read_ahead(read, ranges, depth)

    def close(self) -> None:
        """Release what the source opened (an HDF5 file, for instance); idempotent."""
        on_close, self._on_close = self._on_close, None
        early, self._early = self._early, None
        if early is not None:
            early.join()  # the file it reads stays open until it is done
        if on_close is not None:
            on_close()

    def __enter__(self) -> Source:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __len__(self) -> int:
        return self.m

    def __repr__(self) -> str:
        return f"Source({self.description}, n={self.n}, m={self.m}, dtype={self.dtype})"


_READ_BYTES = 1 << 23  # rows read at a time from the data (8 MiB)


def _check_matrix(shape: tuple[int, ...], dtype: np.dtype, description: str) -> None:
    if dtype.kind == "c":
        raise InputError(
            f"`source` must be real; {description} has complex dtype {dtype}. "
            "Pass the real and imaginary parts as separate snapshots."
        )
    if dtype.kind not in "biuf":
        raise InputError(
            f"`source` must hold real numbers; {description} has dtype {dtype}. "
            "Convert it to a float array first."
        )
    if len(shape) != 2:
        raise ShapeMismatchError(
            f"`source` must be 2-D (n x m, one snapshot per column); {description} is "
            f"{len(shape)}-D of shape {shape}. Reshape it so that columns are snapshots."
        )


def _check_index(value: Any, name: str, m: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise InputError(f"`{name}` must be an integer in [0, {m}]; got {value!r}.")
    if not 0 <= value <= m:
        raise InputError(
            f"`{name}` must be in [0, {m}] (the source has m = {m} columns); got {value}. "
            "Pass a column offset inside the source."
        )
    return int(value)
