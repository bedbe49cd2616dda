"""The out-of-core backend: a compressor's n-sized factor in panels chunked by rows.

:class:`PanelBackend` is the :class:`~streamsvd.algebra.interface.Backend` that keeps the
basis in a :class:`~streamsvd.algebra.panels.basis.PanelBasis` (panels in ``<root>/panels/``,
products over row chunks with dask) and checks the blocks it is given (a dask block is
read by row chunks, each checked for NaN and infinite entries, by :func:`_checked_dask`);
:class:`~streamsvd.parallel.tall.TallCompressor` is the stream compressor built with it.
"""

from __future__ import annotations

import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any, cast

import numpy as np

from streamsvd._util.scheduling import check_client, execute
from streamsvd._util.validation import (
    as_float_array,
    check_finite,
    check_positive_int,
    first_non_finite,
)
from streamsvd.algebra.inner import DiagonalInner, InnerProduct
from streamsvd.algebra.interface import BasisBackend
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.algebra.panels.lazy import LazyBlock
from streamsvd.errors import InputError, NonFiniteError, ShapeMismatchError, StreamSVDError
from streamsvd.storage import LocalStorage, ObjectStorage, open_storage

__all__ = ["DEFAULT_CHUNK_ROWS", "KIND", "PanelBackend"]

DEFAULT_CHUNK_ROWS = 16384
"""Rows per chunk of the stored panels when ``chunk_rows`` is not given."""

KIND = "streamsvd.TallCompressor"


class PanelBackend:
    """The basis in panels chunked by rows (:class:`~streamsvd.algebra.panels.basis.PanelBasis`).

    Parameters
    ----------
    root : LocalStorage or ObjectStorage
        Where the ``panels/`` prefix is: the store's root, or a work directory.
    chunk_rows : int
        Rows per chunk of the panels and of the products.
    client : distributed.Client or None
        Where the row-chunk products run (the threaded scheduler when None).
    temporary : bool
        ``root`` is a temporary directory of this backend, removed by :meth:`close` (or
        when the backend is garbage collected).
    committed : bool
        ``root`` is a store whose commits refer to the panels; else a work directory,
        whose panels :meth:`into_store` copies into a store.
    """

    kind = KIND

    def __init__(self, root: LocalStorage | ObjectStorage, *, chunk_rows: int, client: Any,
                 temporary: bool = False, committed: bool = True) -> None:
        self.root = root
        self.committed = committed
        self.chunk_rows = int(chunk_rows)
        self.client = client
        self.temporary = temporary
        self._cleanup = (
            weakref.finalize(self, shutil.rmtree, cast(LocalStorage, root).root, True)
            if temporary else None
        )

    @classmethod
    def create(
        cls, *, store: Any, workdir: Any, chunk_rows: int | None, client: Any,
        storage_options: dict[str, Any] | None,
    ) -> PanelBackend:
        """Check the tall mode's arguments; return its backend (panels in ``store``, or else)."""
        if store is not None and workdir is not None:
            raise InputError(
                f"`workdir` must be None when `store` is given (the panels live in the "
                f"store); got workdir={workdir!r}. Drop one of them."
            )
        rows = int(check_positive_int(  # type: ignore[arg-type]
            DEFAULT_CHUNK_ROWS if chunk_rows is None else chunk_rows, "chunk_rows"))
        client = check_client(client)
        if store is not None:
            root = open_storage(store, storage_options=storage_options, argument="store")
        elif workdir is None:
            return cls.temporary_for(chunk_rows=rows, client=client)
        else:
            root = open_storage(workdir, storage_options=storage_options, argument="workdir")
            root.prepare()
            return cls(root, chunk_rows=rows, client=client, committed=False)
        return cls(root, chunk_rows=rows, client=client)

    @classmethod
    def temporary_for(cls, *, chunk_rows: int, client: Any) -> PanelBackend:
        """Return a backend whose panels live in a new temporary directory."""
        root = LocalStorage(Path(tempfile.mkdtemp(prefix="streamsvd-tall-")))
        return cls(root, chunk_rows=chunk_rows, client=client, temporary=True,
                   committed=False)

    def new_basis(self, n: int, inner: InnerProduct) -> PanelBasis:
        """Return an empty basis of panels; ``inner`` must be Euclidean or diagonal."""
        if not (inner.is_euclidean or isinstance(inner, DiagonalInner)):
            raise InputError(
                f"`inner` must be Euclidean or diagonal weights out of core; got {inner!r}, "
                "which couples the row chunks. Use the in-memory StreamCompressor, or "
                "lump the mass matrix into weights."
            )
        return PanelBasis(n, inner, chunk_rows=self.chunk_rows, client=self.client,
                          root=self.root)

    @classmethod
    def for_store(cls, basis_attrs: dict[str, Any], root: Any, *, client: Any) -> PanelBackend:
        """Return the backend of the store at ``root``, with the row chunks it recorded."""
        storage = open_storage(root, argument="path")
        storage.prepare()
        return cls(storage, chunk_rows=int(basis_attrs["chunk_rows"]), client=client)

    def fresh(self) -> PanelBackend:
        """Return a backend with the same settings and its own temporary directory."""
        return PanelBackend.temporary_for(chunk_rows=self.chunk_rows, client=self.client)

    def copied(self, basis: BasisBackend, blank: BasisBackend) -> BasisBackend:
        """Return the panels copied into ``blank``'s root, as one panel.

        The copy is written chunk by chunk (``O(n w)`` on disk, never in memory), so the
        copy outlives the original and its store.
        """
        assert isinstance(basis, PanelBasis) and isinstance(blank, PanelBasis)
        blank.adopt(basis)
        return blank

    def into_store(self, basis: BasisBackend, storage: Any) -> tuple[PanelBackend, BasisBackend]:
        """Return the backend and basis that a new store in ``storage`` commits.

        Panels that no commit refers to (a work directory's) are copied into the store as
        one panel, chunk by chunk (``O(n w)`` on disk, never in memory); a store's own
        panels are committed where they are.
        """
        if self.committed:
            return self, basis
        assert isinstance(basis, PanelBasis)
        backend = PanelBackend(storage, chunk_rows=self.chunk_rows, client=self.client)
        return backend, self.copied(basis, backend.new_basis(basis.n, basis.inner))

    def load(self, columns: Any, *, rows: int, first: int) -> Any:
        """Return a checked block: a dask array becomes a :class:`~.lazy.LazyBlock`.

        A dask array (or a source's :class:`~streamsvd.algebra.panels.lazy.LazyBlock`) is not read
        here: the update reads it by row chunks (on the cluster when there is one), each
        chunk checked for NaN and infinite entries; anything else is checked and
        converted in memory. ``first`` is the block's source offset (named when a read
        fails).
        """
        import dask.array as da

        if isinstance(columns, LazyBlock):
            block = columns
        elif isinstance(columns, da.Array):
            block = LazyBlock(_checked_dask(columns), first, "dask array `columns`")
        else:  # checked finite later, as by MemoryBackend
            return as_float_array(columns, "columns", ndim=2, rows=rows, allow_empty=False,
                                  finite=False)
        shape = block.shape
        if len(shape) != 2 or shape[0] != rows:
            raise ShapeMismatchError(
                f"`columns` must have {rows} rows; got shape {shape}. Pass snapshots as "
                "columns."
            )
        if shape[1] == 0:
            raise InputError(f"`columns` must not be empty; got shape {shape}.")
        return block

    def in_memory(self, block: Any, *, check: bool = True) -> np.ndarray:
        """Return a block as a float64 array: a lazy block is read by row chunks.

        Raises the block's :class:`~streamsvd.errors.SourceError` when the read fails.
        ``check=False`` leaves the entries of a block in memory to the caller
        (:meth:`Backend.in_memory <streamsvd.algebra.interface.Backend.in_memory>`).
        """
        if not isinstance(block, LazyBlock):
            if check:
                check_finite(block, "columns")
            return cast(np.ndarray, block)
        try:
            (out,) = execute([block.data.astype(np.float64)], client=self.client,
                             overlap_io=True)
        except StreamSVDError:
            raise
        except Exception as exc:
            raise block.failed(exc) from exc
        return np.asfortranarray(out)

    def use_client(self, basis: BasisBackend, client: Any) -> None:
        """Run ``basis``'s row-chunk products (and this backend's reads) on ``client``.

        A compressor built inside a dask task (a tall tree's node) computes on its
        worker's threads; handed back to the client, it is given the cluster again, so
        that its later passes (the copy into a store, the finalisation) run on the
        workers instead of streaming every row chunk through the client.
        """
        assert isinstance(basis, PanelBasis)
        self.client = basis.rows.client = client

    def describe(self, basis: BasisBackend) -> str:
        """Return the number of panels and the rows per chunk."""
        assert isinstance(basis, PanelBasis)
        return f"panels={len(basis.panels)}, chunk_rows={self.chunk_rows}, "

    def close(self) -> None:
        """Remove a temporary directory with its panels."""
        if self._cleanup is not None:
            self._cleanup()
            self._cleanup = None


def _checked_dask(columns: Any) -> Any:
    """Return a dask block as float64 or float32 chunks checked for NaN and infinities.

    Raises :class:`~streamsvd.errors.InputError` on a dtype that is not real; the finite
    check runs in each chunk's task and names the entry by its row and column in the
    block.
    """
    if columns.ndim != 2:
        raise ShapeMismatchError(
            f"`columns` must be 2-D (n x b); got shape {columns.shape}. Pass snapshots "
            "as columns."
        )
    if columns.dtype.kind not in "biuf":
        raise InputError(
            f"`columns` must hold real numbers; got dtype {columns.dtype}. "
            "Convert it with `.astype(float)`."
        )
    dtype = np.dtype(np.float32 if columns.dtype == np.float32 else np.float64)
    return columns.astype(dtype).map_blocks(_finite_chunk, dtype=dtype)


def _finite_chunk(part: np.ndarray, block_info: dict | None = None) -> np.ndarray:
    """Return a chunk of a dask block; raise NonFiniteError naming its first bad entry."""
    bad = first_non_finite(part)
    if bad is None:
        return part
    row, col, _ = bad
    r0, c0 = ((0, 0) if block_info is None
              else (int(block_info[0]["array-location"][0][0]),
                    int(block_info[0]["array-location"][1][0])))
    raise NonFiniteError(
        f"`columns` must be finite; got {float(part[row, col])} at row {r0 + row}, column "
        f"{c0 + col} of the block. Repair or remove that snapshot."
    )
