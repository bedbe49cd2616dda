"""Out-of-core streaming for tall snapshots: the stream compressor over zarr row panels.

:class:`PanelBackend` is the backend (:class:`~streamsvd.algebra.memory.Backend`) that keeps a
compressor's n-sized factor in a :class:`~streamsvd.algebra.panels.basis.PanelBasis`, and
:class:`TallCompressor` is :class:`~streamsvd.StreamCompressor` built with it (a
constructor and nothing else): the basis lives in panels chunked by rows
in the store directory (``<store>/panels/``), and every product with it runs over row
chunks with dask, on the threaded scheduler or on a ``distributed`` cluster. The update
step, the options, ``add``, ``merge``, the error bound, the history and the store are the
in-memory compressor's (one implementation), so both give the same basis to rounding.

Memory: when the update cuts (``max_rank`` or ``target_error``: the Gram path of
:mod:`streamsvd.engine.update_gram`), a block from :func:`~streamsvd.parallel.tall_compress` or a
dask block is read by row chunks in the update's own pass over the panels, each chunk
written to a scratch copy as it enters the products, so neither the block nor the basis
is ever in memory: one row chunk of each input per dask thread (each pass is one task
per row chunk: :mod:`streamsvd.algebra.panels.basis`), the small matrices and the right vectors
(``m x p``, or none with ``right_vectors=False``). At ``b = 100``, rank 60, the process
peaked at 317 to 333 MB at ``n = 2e5`` and 327 MB at ``n = 2e6`` without a store
(``bench/outofcore_benchmark.py``). An update that takes the exact path (no cut, ``eps``
or ``rtol`` alone, ``window``, ``forget``, a block the Gram path declines) reads its block
into memory first (``n x b``) and orthonormalises it there.

Crash safety: an update writes its new panel (or the compacted basis) before the commit
that refers to it; a panel is deleted only when neither the state nor the last two
commits refer to it, so a process or worker killed at any instant leaves the last commit
readable; leftovers are removed when the store is reopened for writing. A store is
created by its first commit, which holds the whole state and the basis's attributes
(``chunk_rows``, the panels): killed before it, the store does not exist (its leftovers,
panels included, are replaced by the next creation), never half of it
(:mod:`streamsvd.store.create`).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any, cast

import numpy as np

from streamsvd._util.scaling import safe_column_norms
from streamsvd._util.scheduling import check_client, execute
from streamsvd._util.validation import (
    as_float_array,
    check_finite,
    check_positive_int,
    first_non_finite,
)
from streamsvd.algebra.inner import DiagonalInner, InnerProduct
from streamsvd.algebra.memory import BasisBackend
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.algebra.panels.lazy import LazyBlock
from streamsvd.errors import InputError, NonFiniteError, ShapeMismatchError, StreamSVDError
from streamsvd.storage import LocalStorage, ObjectStorage, open_storage
from streamsvd.stream.compressor import StreamCompressor

__all__ = ["DEFAULT_CHUNK_ROWS", "KIND", "PanelBackend", "TallCompressor"]

logger = logging.getLogger(__name__)

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

    def in_memory(self, block: Any) -> np.ndarray:
        """Return a block as a float64 array: a lazy block is read by row chunks.

        Raises the block's :class:`~streamsvd.errors.SourceError` when the read fails.
        """
        if not isinstance(block, LazyBlock):
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

    def describe(self, basis: BasisBackend) -> str:
        """Return the number of panels and the rows per chunk."""
        assert isinstance(basis, PanelBasis)
        return f"panels={len(basis.panels)}, chunk_rows={self.chunk_rows}, "

    def close(self) -> None:
        """Remove a temporary directory with its panels."""
        if self._cleanup is not None:
            self._cleanup()
            self._cleanup = None


class TallCompressor(StreamCompressor):
    """Stream snapshots into a basis kept out of core, in panels chunked by rows.

    A :class:`~streamsvd.StreamCompressor` whose backend is a :class:`PanelBackend`: this
    class only builds it from the arguments below.

    Parameters
    ----------
    n : int
        Size of one snapshot.
    store : str, path-like or Storage, optional
        Create a basis store there (a directory, a ``file://`` or ``s3://`` URL, or a
        storage from :func:`streamsvd.storage.open_storage`, which carries
        ``storage_options``); the panels live in its ``panels/`` prefix and the small
        state is committed every ``commit_every`` updates. Continue an existing one
        with :meth:`TallCompressor.open`.
    workdir : str, path-like or Storage, optional
        Without ``store``: directory (or object-store URL) for the panels (a temporary
        directory, removed by :meth:`close`, by default). On a remote cluster it must be
        visible to every worker.
    chunk_rows : int, optional
        Rows per chunk of the panels (default 16384).
    client : distributed.Client, optional
        Run the row-chunk products on this cluster; the threaded scheduler by default.
    inner : None, array of weights or DiagonalInner
        Euclidean or diagonal weights (a matrix inner product couples the row chunks and
        is not offered out of core).
    storage_options : dict, optional
        Options of the object store of a URL ``store`` or ``workdir`` (``s3://``:
        ``key``, ``secret``, ``endpoint_url``, ...).
    **options
        ``eps``, ``rtol``, ``max_rank``, ``oversampling``, ``rule``, ``sweeps``,
        ``reject_tol``, ``reorth_tol``, ``right_vectors``, ``commit_every``, ...: as for
        :class:`~streamsvd.StreamCompressor`.

    Notes
    -----
    Cost of absorbing ``b`` columns at stored width ``w``: the in-memory update's flops
    (:mod:`streamsvd.engine.update`), each product with the basis a dask graph over the row
    chunks that reads the panels once; a new panel of ``n x r`` (or the compacted basis
    ``n x p``) is written per update. A dask block is read by row chunks (on the cluster
    when there is one): within the update's pass when the update cuts (see the module
    docstring), into memory first otherwise; on any error (bad input, a failing read, a
    lost worker) the state in memory and in the store is unchanged, and what the update
    wrote is removed. Without ``store`` or ``workdir``, :meth:`close` removes the panels and
    finalises nothing.
    """

    KIND = KIND

    def __init__(
        self,
        n: int,
        *,
        store: Any = None,
        workdir: Any = None,
        chunk_rows: int | None = None,
        client: Any = None,
        inner: Any = None,
        storage_options: dict[str, Any] | None = None,
        **options: Any,
    ) -> None:
        check_positive_int(n, "n")
        backend = PanelBackend.create(store=store, workdir=workdir, chunk_rows=chunk_rows,
                                      client=client, storage_options=storage_options)
        super().__init__(n, inner=inner, store=None if store is None else backend.root,
                         backend=backend, **options)

    @classmethod
    def open(
        cls, path: Any, *, inner: Any = None, mode: str = "a", client: Any = None,
        storage_options: dict[str, Any] | None = None,
    ) -> TallCompressor:
        """Reopen a tall compressor from its store, exactly as at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``TallCompressor(..., store=path)``.
        inner : optional
            The weights the store was written with (checked by fingerprint).
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock and removes panels left
            by an interrupted update); ``"r"`` reads only.
        client : distributed.Client, optional
            Cluster for the row-chunk products.
        storage_options : dict, optional
            Options of the object store of a URL ``path``.
        """
        client = check_client(client)
        return cls._open(
            path, inner=inner, mode=mode, kind=KIND,
            backend=lambda attrs, root: PanelBackend.for_store(attrs, root, client=client),
            storage_options=storage_options,
        )

    @property
    def chunk_rows(self) -> int:
        """Rows per chunk of the panels."""
        return self._panel_backend.chunk_rows

    @property
    def client(self) -> Any:
        """The cluster the row-chunk products run on (None: the threaded scheduler)."""
        return self._panel_backend.client

    @property
    def _panel_backend(self) -> PanelBackend:
        backend = self._backend
        assert isinstance(backend, PanelBackend)
        return backend

    def expect(self, columns: Any) -> None:
        """Name the block that will follow the one the coming :meth:`absorb` is given.

        A block read from its source (a :class:`~streamsvd.algebra.panels.lazy.LazyBlock`, as
        :func:`~streamsvd.stream.ingest.ingest` hands them out) is then read by the coming
        update's last pass over the panels, which writes its scratch copy and forms its
        products with the new basis: its own update then makes one pass over the panels
        instead of two (``bench/README.md``). The results are the same to the last bit
        (tested); should the call after the coming one get another block, or the coming
        update take another path, the block is read as usual.
        """
        cast(PanelBasis, self._state.basis).expect(columns)

    @property
    def stored_width(self) -> int:
        """Number of stored columns of the basis (all panels)."""
        return self._state.basis.width

    def factors(self) -> tuple[Any, np.ndarray]:
        """Return the expansion as ``(U, V)``: ``U`` lazy (dask, over the panels), ``V`` in memory.

        Terms are sorted by decreasing amplitude and signed as in :attr:`expansion` (the
        largest-modulus entry of each ``u_i`` positive, found by a reduction over the
        row chunks), so neither this call nor computing ``U`` chunk by chunk holds
        ``n x p``; :attr:`left_vectors` and :attr:`expansion` do gather ``U``. Needs
        ``right_vectors=True``.
        """
        s = self._state
        basis = s.basis
        assert isinstance(basis, PanelBasis)
        V = self.right_factor()
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U = basis.lazy(s.settled()[0][:, perm])
        top, bottom = execute([U.max(axis=0), U.min(axis=0)], client=self.client,
                              overlap_io=True)
        signs = np.where(np.asarray(top) >= -np.asarray(bottom), 1.0, -1.0)
        self._exposure = (self._version, perm, signs)  # the coordinates of `add`
        return U * signs, V[:, perm] * signs


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
