"""Block iterators over snapshot sources (columns are snapshots).

:func:`open_source` wraps an in-memory or on-disk ``n x m`` snapshot matrix in a
:class:`Source`, which reads column blocks as float64 arrays one at a time:

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
For the tall mode it yields each block unread, as a :class:`LazyBlock` whose row chunks
the update's dask pass reads and checks (``rows=``); otherwise
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
import os
import queue
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, cast

import numpy as np

from streamsvd._util.slabs import copy_by_row_slabs
from streamsvd._util.validation import check_positive_int, first_non_finite
from streamsvd.errors import InputError, NonFiniteError, ShapeMismatchError, SourceError
from streamsvd.io.formats import no_dataset, open_file, open_zarr_url
from streamsvd.storage import is_url

__all__ = ["LazyBlock", "Source", "open_source", "open_zarr_url"]

logger = logging.getLogger(__name__)


class Source:
    """An ``n x m`` snapshot matrix read by column blocks.

    Build one with :func:`open_source`. Columns are snapshots: ``n`` is the size of one
    snapshot and ``m`` the number of snapshots. Every read returns a new column-major
    array of dtype :attr:`block_dtype` that does not share memory with the underlying
    data.

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

    def _read_checked(self, start: int, stop: int, out: np.ndarray | None = None) -> np.ndarray:
        """Read columns ``start:stop`` (into ``out`` when it fits) and check them."""
        try:
            out, finite = self._read_slabs(start, stop, out)
        except Exception as exc:  # any reader failure is reported with its offset
            raise _read_failed(exc, start, stop, self.description) from exc
        if not finite:
            _check_finite(out, start, 0, self.n, self.description)
        return out

    def _read_slabs(
        self, start: int, stop: int, out: np.ndarray | None = None
    ) -> tuple[np.ndarray, bool]:
        """Read columns ``start:stop`` into a column-major array, by slabs of rows.

        ``out`` is a block of an earlier read that nobody holds any more (see
        :func:`read_ahead`), filled again when it has the block's shape, dtype and
        layout; otherwise a new array is made. A slab is a whole number of the data's row
        chunks, about 8 MiB, so that a read never holds the block twice in the data's
        layout (a dask array, or data one chunk tall, is read whole). Each slab is checked
        for NaN and infinite entries while it is in the cache; returns the block and
        whether every slab was finite.
        """
        cols = stop - start
        if (out is None or out.shape != (self.n, cols) or out.dtype != self.block_dtype
                or not out.flags.f_contiguous or not out.flags.writeable):
            out = np.empty((self.n, cols), dtype=self.block_dtype, order="F")
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
    ) -> Iterator[tuple[int, np.ndarray | LazyBlock]]:
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
            one is filled again by a later read (:func:`read_ahead`).
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
        return read_ahead(self._read_checked, ranges, depth)

    def close(self) -> None:
        """Release what the source opened (an HDF5 file, for instance); idempotent."""
        on_close, self._on_close = self._on_close, None
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


# sys.getrefcount of a block that only the generator's own name refers to (the count
# includes the call's argument)
_UNREFERENCED = 2


def read_ahead(
    read: Callable[[int, int, np.ndarray | None], np.ndarray],
    ranges: list[tuple[int, int]],
    depth: int,
) -> Iterator[tuple[int, np.ndarray]]:
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
                spares.put(X)
            del X
            permits.release()
    finally:
        stopping.set()
        permits.release()
        thread.join()


@dataclass(frozen=True)
class LazyBlock:
    """Columns ``first:first + b`` of a source, read by row chunks when a product needs them.

    ``data`` is a dask array (``n x b``, float32 or float64, chunked by rows) whose tasks
    read and check the source; :class:`~streamsvd.algebra.panels.basis.PanelBasis` absorbs it in one
    pass over its row chunks, and :meth:`failed` names the columns when a read fails.
    """

    data: Any
    first: int
    description: str

    @property
    def shape(self) -> tuple[int, int]:
        """``(n, b)``."""
        return cast(tuple[int, int], tuple(self.data.shape))

    def failed(self, exc: BaseException) -> SourceError:
        """Return the error that reports a failed read of these columns."""
        a, b = self.first, self.first + self.shape[1]
        return SourceError(
            f"reading columns {a}:{b} (offset {a}) of {self.description} failed: "
            f"{type(exc).__name__}: {exc}. The basis is unchanged and a store holds its "
            f"last commit; fix the cause and resume from offset {a}."
        )


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
        try:
            _fill(out, self.data, r0, self.offset + c0, self.offset + c1)
        except Exception as exc:  # any reader failure is reported with its offset
            raise _read_failed(exc, self.start, self.stop, self.description) from exc
        _check_finite(out, self.start + c0, r0, self.shape[0], self.description)
        return out


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


_READ_BYTES = 1 << 23  # rows read at a time from the data (8 MiB)


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


def _is_dask_array(obj: Any) -> bool:
    module = type(obj).__module__ or ""
    if not module.startswith("dask"):
        return False
    import dask.array as da

    return isinstance(obj, da.Array)


def _is_h5py_dataset(obj: Any) -> bool:
    if not (type(obj).__module__ or "").startswith("h5py"):
        return False
    import h5py

    return isinstance(obj, h5py.Dataset)


def _is_zarr_array(obj: Any) -> bool:
    if not (type(obj).__module__ or "").startswith("zarr"):
        return False
    import zarr

    return isinstance(obj, zarr.Array)


def open_source(
    obj: Any, *, dataset: str | None = None, storage_options: Any = None
) -> Source:
    """Wrap a snapshot matrix (columns are snapshots) in a :class:`Source`.

    Parameters
    ----------
    obj : array_like, str, os.PathLike, h5py.Dataset, zarr.Array, dask array or Source
        A real ``n x m`` matrix: an in-memory array, the path of a ``.npy`` file
        (memory-mapped), of an HDF5 file (``.h5``, ``.hdf5``), of a zarr array or group
        (a ``.zarr`` path or a zarr directory), or an open h5py dataset, zarr array or
        dask array, or the URL of a zarr array or group (``s3://bucket/run.zarr``). A
        :class:`Source` is returned as is.
    dataset : str, optional
        Name of the dataset in an HDF5 file or of the array in a zarr group; may be
        omitted when there is exactly one.
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...); not accepted with anything else.

    Returns
    -------
    Source
        Close it (or use it as a context manager) to release a file it opened.

    Raises
    ------
    SourceError
        When the file does not exist, cannot be opened, or has no such dataset.
    InputError
        When the extension is unknown, ``dataset`` is needed or misplaced, or the data
        is not a real 2-D matrix.
    """
    if dataset is not None and not isinstance(dataset, str):
        raise InputError(f"`dataset` must be a str naming a dataset; got {dataset!r}.")
    if is_url(obj):
        arr = open_zarr_url(obj, dataset=dataset, storage_options=storage_options)
        name = f" '{dataset.strip('/')}'" if dataset else ""
        return Source(arr, f"zarr array{name} at {obj}")
    if storage_options is not None:
        raise InputError(
            f"`storage_options` only apply to a URL source (s3://..., file://...); got "
            f"{storage_options!r} with a {type(obj).__name__}. Drop them."
        )
    if isinstance(obj, Source):
        no_dataset(dataset, "a Source")
        return obj
    if isinstance(obj, str | os.PathLike):
        opened = open_file(Path(obj), dataset)
        return Source(opened.data, opened.description, on_close=opened.close)
    if _is_dask_array(obj):
        no_dataset(dataset, "a dask array")
        return Source(obj, f"dask array of shape {obj.shape}", compute=True)
    if _is_h5py_dataset(obj):
        no_dataset(dataset, "an h5py dataset")
        return Source(obj, f"HDF5 dataset '{obj.name}' in {obj.file.filename}")
    if _is_zarr_array(obj):
        no_dataset(dataset, "a zarr array")
        return Source(obj, f"zarr array {obj.store_path}")
    no_dataset(dataset, f"a {type(obj).__name__}")
    if hasattr(obj, "toarray") and not isinstance(obj, np.ndarray):
        raise InputError(
            f"`source` must be a dense array; got a sparse matrix of shape "
            f"{getattr(obj, 'shape', '?')}. Convert it with `.toarray()`."
        )
    try:
        arr = obj if isinstance(obj, np.ndarray) else np.asarray(obj)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"`source` must be a real 2-D array (n x m); {type(obj).__name__} cannot be "
            f"converted to one ({exc}). Pass a numpy array, a file path or a dask array."
        ) from None
    kind = "memmap" if isinstance(arr, np.memmap) else "array"
    return Source(arr, f"numpy {kind} of shape {arr.shape}")
