"""Arrays that the tall mode's tasks read and write by rows, without zarr.

:class:`RawArray` is an ``n x c`` array in one row-major file (the block's scratch copy,
and the panels that no commit lists); :class:`RowView` lets dask see an in-memory block
through row slices, without a copy.
"""

from __future__ import annotations

import copy
import os
from typing import Any

import numpy as np

from streamsvd.errors import StoreError

__all__ = ["RawArray", "RowView"]


class RawArray:
    """An ``n x c`` array in a local directory, read by no reopened store: one row-major file.

    The block's scratch copy (it serves one update: written by the pass that reads the
    block, read by the compaction, then kept to be written over, removed at close) and the
    panels as the passes use them (they live while the compressor does; a commit lists
    only panels with a zarr copy beside the file). A leftover is removed when the store or work
    directory is next opened for writing, like a panel: its directory is named as one. It is
    read by the process that wrote it or by workers sharing its directory; so no codec or
    checksum (a zarr write of a 10000 x 100 float64 chunk took 17.7 ms in the tall mode, the
    raw write about 4 ms: ``bench/README.md``). Each task opens the file for its rows, so a
    worker reads what the others wrote once their tasks have ended.
    """

    def __init__(self, directory: Any, shape: tuple[int, int], dtype: Any, *,
                 chunk_rows: int) -> None:
        directory.mkdir(parents=True, exist_ok=True)
        self.path = directory / "block"
        self.shape, self.dtype, self.ndim = shape, np.dtype(dtype), 2
        self.chunks = (chunk_rows, max(shape[1], 1))
        self._row_bytes = shape[1] * self.dtype.itemsize
        with open(self.path, "wb") as f:
            f.truncate(shape[0] * self._row_bytes)

    @property
    def name(self) -> str:
        """The panel's name: its directory's."""
        return str(self.path.parent.name)

    def moved_to(self, directory: Any) -> RawArray | None:
        """Rename the file's directory to ``directory``; return the array there.

        Its rows are as they were. None when the file is gone or has another size (it was
        removed meanwhile).
        """
        try:
            if os.path.getsize(self.path) != self.shape[0] * self._row_bytes:
                return None
            os.rename(self.path.parent, directory)
        except OSError:
            return None
        out = copy.copy(self)
        out.path = directory / self.path.name
        return out

    def __setitem__(self, key: slice | tuple[slice, ...], value: np.ndarray) -> None:
        r0 = (key[0] if isinstance(key, tuple) else key).indices(self.shape[0])[0]
        data = np.ascontiguousarray(value, dtype=self.dtype)
        assert data.shape[1] == self.shape[1], "rows are written whole"
        fd = os.open(self.path, os.O_WRONLY)
        try:
            view = data.data.cast("B")
            done = 0
            while done < len(view):
                done += os.pwrite(fd, view[done:], r0 * self._row_bytes + done)
        finally:
            os.close(fd)

    def __getitem__(self, key: slice | tuple[slice, ...]) -> np.ndarray:
        key = key if isinstance(key, tuple) else (key,)
        r0, r1, _ = key[0].indices(self.shape[0])
        out = np.empty((r1 - r0, self.shape[1]), dtype=self.dtype)
        with open(self.path, "rb") as f:
            f.seek(r0 * self._row_bytes)
            read = f.readinto(out.data.cast("B"))
        if read != out.nbytes:
            raise StoreError(
                f"{self.path} holds {r0 * self._row_bytes + read} bytes "
                f"up to row {r1}, expected {r1 * self._row_bytes}: it was truncated "
                "while in use (a full disk, or another process). Resume from the last "
                "commit, or start again without one."
            )
        return out[(slice(None), *key[1:])]


class RowView:
    """An in-memory block seen by dask through row slices (views).

    ``dask.array.from_array`` copies a numpy array whole before slicing it (a copy of the
    ``n x b`` block per product); this wrapper has no ``copy``, so each task takes a view
    of its rows.
    """

    def __init__(self, X: np.ndarray) -> None:
        self.X = X
        self.shape, self.dtype, self.ndim = X.shape, X.dtype, X.ndim

    def __getitem__(self, key: Any) -> np.ndarray:
        return self.X[key]
