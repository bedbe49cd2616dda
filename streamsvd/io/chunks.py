"""Reading a local zarr v3 array by whole chunks, decoded straight into a block.

A zarr array's read (``get_basic_selection``) runs each chunk through zarr's codec
pipeline: an event loop in a thread of its own, a decode in a pool of threads, a new
buffer per chunk, then a copy into the result. For the arrays snapshots come in (a local
directory, a regular grid, the ``bytes`` codec and at most a ``zstd`` or ``blosc``
compressor, the data's own dtype) :class:`ChunkFiles` does the same work with none of
that: it reads each chunk's file into a buffer of its thread, decodes it into a second
one (zstd and blosc release the GIL) and copies the part the block needs into the block,
column-major or row-major. On a 200000 x 500 float64 array in chunks of 10000 x 50
(zstd) a read by blocks of 100 columns took 1.29 s of CPU against 1.42 s through zarr
(``bench/studies/tight-targets.md``), and the threads are the caller's: ``threads=2``
decodes the chunks of a block on two cores, for a first block that nothing else overlaps.

Any other array (an object store, sharding, filters, another codec, a format 2 array)
is read through zarr: :meth:`ChunkFiles.of` returns None for it.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from streamsvd.errors import SourceError

__all__ = ["ChunkFiles"]

logger = logging.getLogger(__name__)

_buffers = threading.local()  # each thread's file buffer and decoded chunk


class ChunkFiles:
    """The chunk files of a local zarr v3 array, decoded without zarr's pipeline.

    Build one with :meth:`of`; :meth:`fill` reads a block.

    Parameters
    ----------
    root : pathlib.Path
        The array's directory.
    metadata : zarr.core.metadata.ArrayV3Metadata
        Its metadata (chunk grid, key encoding, fill value).
    decode : callable or None
        ``decode(raw, out)`` decompresses a chunk's bytes into ``out``; None when the
        chunks are stored uncompressed.
    shape, chunks : tuple of int
        The array's and its chunks' shapes.
    dtype : numpy.dtype
        The array's dtype.
    """

    def __init__(self, root: Path, metadata: Any, decode: Any, shape: tuple[int, int],
                 chunks: tuple[int, int], dtype: np.dtype) -> None:
        self.root = root
        self.metadata = metadata
        self.decode = decode
        self.shape = shape
        self.chunks = chunks
        self.dtype = dtype
        self.fill_value = metadata.fill_value

    @classmethod
    def of(cls, data: Any) -> ChunkFiles | None:
        """Return the chunk files of ``data``, or None when zarr must read it.

        ``data`` qualifies when it is a 2-D zarr (v3) array in a local directory, on a
        regular chunk grid, whose codecs are ``bytes`` (little-endian) and at most one
        ``zstd`` or ``blosc`` compressor, of a floating-point dtype.
        """
        if not type(data).__module__.startswith("zarr"):
            return None
        try:
            return cls._of(data)
        except Exception as exc:  # any surprise in zarr's objects: zarr reads it
            logger.debug("reading %r through zarr: %s", data, exc)
            return None

    @classmethod
    def _of(cls, data: Any) -> ChunkFiles | None:
        from zarr.codecs import BloscCodec, BytesCodec, ZstdCodec
        from zarr.core.chunk_grids import RegularChunkGrid
        from zarr.storage import LocalStore

        meta = data.metadata
        store = data.store_path.store
        dtype = np.dtype(data.dtype)
        if (getattr(meta, "zarr_format", None) != 3 or not isinstance(store, LocalStore)
                or not isinstance(meta.chunk_grid, RegularChunkGrid) or len(data.shape) != 2
                or dtype.kind != "f" or not dtype.isnative or dtype.byteorder == ">"):
            return None
        codecs = tuple(meta.codecs)
        if not codecs or not isinstance(codecs[0], BytesCodec) or len(codecs) > 2:
            return None
        if str(getattr(codecs[0].endian, "value", codecs[0].endian)) != "little":
            return None
        decode = None
        if len(codecs) == 2:
            import numcodecs

            if isinstance(codecs[1], ZstdCodec):
                decode = numcodecs.Zstd().decode
            elif isinstance(codecs[1], BloscCodec):
                decode = numcodecs.Blosc().decode
            else:
                return None
        root = Path(store.root) / data.store_path.path
        chunks = tuple(int(c) for c in meta.chunk_grid.chunk_shape)
        return cls(root, meta, decode, (int(data.shape[0]), int(data.shape[1])),
                   (chunks[0], chunks[1]), dtype)

    def fill(self, out: np.ndarray, r0: int, c0: int, *, threads: int = 1) -> bool:
        """Fill ``out`` with rows ``r0:``, columns ``c0:`` of the array; return whether finite.

        ``out`` is 2-D, of the array's dtype, column- or row-major; every chunk it
        overlaps is read and decoded once (align ``out`` on the chunks to decode none
        twice). Each chunk's part is checked for NaN and infinite entries while it is in
        the cache. ``threads`` > 1 decodes the chunks on that many threads (this one
        among them).
        """
        R, C = self.chunks
        rows, cols = out.shape
        tasks = [(i, j) for i in range(r0 // R, -(-(r0 + rows) // R))
                 for j in range(c0 // C, -(-(c0 + cols) // C))]
        if threads <= 1 or len(tasks) < 2:
            return all([self._chunk(i, j, out, r0, c0) for i, j in tasks])
        with ThreadPoolExecutor(threads - 1, thread_name_prefix="streamsvd-decode") as pool:
            half = len(tasks) * (threads - 1) // threads
            helpers = [pool.submit(self._chunk, i, j, out, r0, c0) for i, j in tasks[:half]]
            mine = all([self._chunk(i, j, out, r0, c0) for i, j in tasks[half:]])
            return all([f.result() for f in helpers]) and mine

    def _chunk(self, i: int, j: int, out: np.ndarray, r0: int, c0: int) -> bool:
        """Decode chunk ``(i, j)`` and copy its part into ``out``; return whether finite."""
        R, C = self.chunks
        a, b = max(i * R, r0), min((i + 1) * R, r0 + out.shape[0], self.shape[0])
        c, d = max(j * C, c0), min((j + 1) * C, c0 + out.shape[1], self.shape[1])
        target = out[a - r0 : b - r0, c - c0 : d - c0]
        chunk = self._decoded(i, j)
        if chunk is None:  # never written: the fill value
            target[...] = self.fill_value
            return bool(np.isfinite(self.fill_value))
        part = chunk[a - i * R : b - i * R, c - j * C : d - j * C]
        finite = bool(np.isfinite(part).all())
        target[...] = part
        return finite

    def _decoded(self, i: int, j: int) -> np.ndarray | None:
        """Chunk ``(i, j)`` decoded into this thread's buffer (None: no such file)."""
        R, C = self.chunks
        size = R * C * self.dtype.itemsize
        path = self.root / self.metadata.encode_chunk_key((i, j))
        try:
            f = open(path, "rb", buffering=0)  # noqa: SIM115
        except FileNotFoundError:
            return None
        with f:
            length = int(f.seek(0, 2))
            f.seek(0)
            raw = _buffer("raw", max(length, size) if self.decode is None else length)
            view = memoryview(raw)[:length]
            got = 0
            while got < length:
                n = f.readinto(view[got:])
                if not n:
                    raise SourceError(f"chunk file {path}: {length - got} bytes short.")
                got += n
        if self.decode is None:
            if length != size:
                raise SourceError(f"chunk file {path}: {length} bytes, expected {size}.")
            return np.frombuffer(raw, dtype=self.dtype, count=R * C).reshape(R, C)
        chunk = _buffer("chunk", size)
        try:
            self.decode(view, out=memoryview(chunk)[:size])
        except (RuntimeError, ValueError):  # a frame that does not state its size
            decoded = memoryview(self.decode(bytes(view))).cast("B")
            if decoded.nbytes != size:
                raise SourceError(
                    f"chunk file {path}: {decoded.nbytes} bytes decoded, expected {size}."
                ) from None
            chunk[:size] = decoded
        return np.frombuffer(chunk, dtype=self.dtype, count=R * C).reshape(R, C)


def _buffer(name: str, size: int) -> bytearray:
    """Return this thread's buffer ``name``, of at least ``size`` bytes (grown when short)."""
    buf = getattr(_buffers, name, None)
    if buf is None or len(buf) < size:
        buf = bytearray(size)
        setattr(_buffers, name, buf)
    return buf
