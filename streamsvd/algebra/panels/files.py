"""The files of a basis's panels: ``<root>/panels/<name>``, created, opened, reused, deleted.

:class:`PanelFiles` keeps the panels of a :class:`~streamsvd.algebra.panels.basis.PanelBasis` where
its root says (:mod:`streamsvd.storage`). In a local directory a panel is a raw row-major
file (:class:`~streamsvd.algebra.panels.raw_array.RawArray`), which the passes read and write, and
once a commit lists it, a zarr copy with checksums beside it (the panel is then *sealed*),
which a reopened store reads. In an object store a panel is a zarr array. A raw file
that nothing refers to any more is kept, up to :data:`SPARES` of them, for the next
panel of its shape and dtype to be written over it.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterable
from typing import Any, cast

import numpy as np

from streamsvd.algebra.panels.raw_array import RawArray
from streamsvd.errors import StoreError
from streamsvd.storage import PANELS, LocalStorage, ObjectStorage

__all__ = ["SPARES", "PanelFiles"]

SPARES = 2
"""Raw files kept to be written over (:meth:`PanelFiles.let_go`)."""


class PanelFiles:
    """The panels of one basis under ``root`` (``n`` rows each, in chunks of ``chunk_rows``).

    Parameters
    ----------
    n : int
        Rows of every panel.
    chunk_rows : int
        Rows per chunk of every panel.
    root : LocalStorage or ObjectStorage
        Where ``panels/`` is (the store's root, or a work directory).
    """

    def __init__(self, n: int, *, chunk_rows: int, root: LocalStorage | ObjectStorage) -> None:
        self.n = int(n)
        self.chunk_rows = int(chunk_rows)
        self.root = root
        self.raw = isinstance(root, LocalStorage)
        self.sealed: set[str] = set()  # raw panels with a zarr copy
        self.spares: list[RawArray] = []  # raw files nothing refers to, kept to write over
        self._arrays: dict[str, Any] = {}
        self._zstore: Any = None

    def _store(self) -> Any:
        if self._zstore is None:
            self._zstore = self.root.zarr_store(read_only=False)
        return self._zstore

    def open(self, name: str) -> Any:
        """Return panel ``name`` (its raw file when this process wrote it, else its zarr array)."""
        z = self._arrays.get(name)
        if z is None:
            import zarr

            try:
                z = zarr.open_array(store=self._store(), path=f"{PANELS}/{name}", mode="r")
            except (OSError, ValueError, KeyError) as exc:
                raise StoreError(
                    f"`store` {self.root}: panel {name} of the basis cannot be opened "
                    f"({type(exc).__name__}: {exc}). Restore the store from a copy."
                ) from exc
            self._arrays[name] = z
        return z

    def new(self, cols: int, dtype: Any = np.float64) -> tuple[str, Any]:
        """Create an ``n x cols`` panel; return its name and array (zarr or raw).

        Every caller writes all its rows. A raw file kept for reuse (:meth:`let_go`) of
        this shape and dtype is renamed and written over: writing a file of the page cache
        again took a third of the CPU time of writing a new one (``bench/README.md``), and
        an array that still names the old file finds it gone, as if it had been deleted.
        """
        name = f"p{uuid.uuid4().hex}"
        if not self.raw:
            return name, self._new_zarr(name, cols, dtype)
        directory = cast(LocalStorage, self.root).root / PANELS / name
        fits = [s for s in self.spares if s.shape == (self.n, cols) and s.dtype == dtype]
        spare = fits[0] if fits else None
        if spare is not None:
            self.spares.remove(spare)
        raw = None if spare is None else spare.moved_to(directory)
        if spare is not None and raw is None:  # removed meanwhile
            self.delete(spare.name)
        if raw is None:
            raw = RawArray(directory, (self.n, cols), dtype, chunk_rows=self.chunk_rows)
        self._arrays[name] = raw
        return name, raw

    def let_go(self, name: str) -> None:
        """Forget panel ``name``, keeping its raw file to write over, or delete it.

        Only a raw file without a zarr copy is kept (no commit ever listed it), and at
        most :data:`SPARES` (an update by the Gram path lets go of the block's scratch
        copy and of the basis it replaced): beyond, the oldest of a shape kept twice
        goes, else the oldest.
        """
        raw = self._arrays.get(name)
        if not isinstance(raw, RawArray) or name in self.sealed:
            self.delete(name)
            return
        self._arrays.pop(name)
        self.spares.append(raw)
        if len(self.spares) > SPARES:
            shapes = [(s.shape, s.dtype) for s in self.spares]
            twice = [i for i, shape in enumerate(shapes) if shapes.count(shape) > 1]
            self.delete(self.spares.pop(twice[0] if twice else 0).name)

    def unsealed(self, names: Iterable[str]) -> list[str]:
        """Return the raw panels of ``names`` that have no zarr copy yet."""
        return [name for name in names
                if name not in self.sealed and isinstance(self._arrays.get(name), RawArray)]

    def zarr_copy(self, name: str) -> Any:
        """Create the zarr copy of raw panel ``name`` (empty: the caller writes every chunk)."""
        return self._new_zarr(name, self._arrays[name].shape[1])

    def _new_zarr(self, name: str, cols: int, dtype: Any = np.float64) -> Any:
        """Create the zarr array of panel ``name`` (``n x cols``, checksummed chunks)."""
        import zarr
        from zarr.codecs import Crc32cCodec

        return zarr.create_array(
            store=self._store(), name=f"{PANELS}/{name}", shape=(self.n, cols),
            chunks=(self.chunk_rows, max(cols, 1)), dtype=np.dtype(dtype).name,
            fill_value=0.0, compressors=[Crc32cCodec()],
            # every chunk is written (no comparison with the fill value first)
            config={"write_empty_chunks": True},
        )

    def delete(self, name: str) -> None:
        """Delete panel ``name``: its raw file and its zarr copy, or its zarr array."""
        self._arrays.pop(name, None)
        self.root.delete(f"{PANELS}/{name}")

    def drop_spares(self) -> None:
        """Delete the raw files kept to be written over."""
        spares, self.spares = self.spares, []
        for spare in spares:
            self.delete(spare.name)

    def listed(self) -> list[str]:
        """Return the names of the panels under the root (spares included)."""
        return [entry for entry in self.root.list(PANELS) if entry.startswith("p")]
