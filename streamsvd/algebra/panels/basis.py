"""The n-sized factor out of core: the basis in panels chunked by rows, used by dask.

:class:`PanelBasis` implements :class:`~streamsvd.algebra.interface.BasisBackend` for
snapshots too long for the basis ``n x w`` to stay in memory. The stored columns are a list of
*panels*, written once each (``<root>/panels/<name>``, in a local directory or an object
store: :mod:`streamsvd.storage`): in a local directory a raw row-major file, which the
passes use, and, once a commit lists it, a zarr copy with checksums beside it, which a
reopened store reads; in an object store a zarr array (:mod:`streamsvd.algebra.panels.files`
keeps them). Every product with them (``Q^T M X``, ``X - Q K``, ``[Q, Y] G``,
``Q^T M Y``) is a dask graph over the row chunks (:mod:`streamsvd.algebra.panels.row_chunks`), run
on the threaded scheduler or on a ``distributed`` cluster whose workers reach the directory
or the object store (a panel pickles as its path, or as its zarr store: a URL and its
``storage_options``). The basis is never in memory; a block is read by row chunks
within the Gram path's pass (:meth:`PanelBasis.block_products`), while the exact
path orthonormalises an in-memory block (``n x b``) in an in-memory workspace.

The Gram path's two passes (the block's products, then the new basis) are one task per
row chunk each (``map_blocks``): the task reads the chunk's rows of every panel and of
the block, writes what the pass writes (the scratch chunk, the new basis's chunk) and
returns its share of the small products, which a reduction sums. A thread then holds
one chunk of each input, and no chunk waits in the scheduler for its other consumers.
When the next block is known (:meth:`PanelBasis.expect`), the second pass also reads
it and forms its products with the new basis, which are the next update's first pass:
a stream then makes one pass over the panels per update.
A panel's zarr copy is written on :mod:`streamsvd.algebra.panels.zarr_io`'s event loops.

The update step is the in-memory one (:mod:`streamsvd.engine.update`, the same Gram-Schmidt,
sweeps, truncation and bound), so both backends give the same basis to rounding.

Crash safety. A plan writes its new panel (or the compacted basis) before any commit
refers to it, and a commit lists a panel only once its zarr copy is written; a panel is
deleted, or its raw file renamed and written over, only when neither the state nor the
last two commits refer to it (:meth:`PanelBasis.release`, :meth:`PanelBasis.collect`),
so a process or worker killed at any instant leaves the last commit readable.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from streamsvd.algebra.blas import gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.panels import staging
from streamsvd.algebra.panels import tasks as panel_tasks
from streamsvd.algebra.panels.files import PanelFiles
from streamsvd.algebra.panels.row_chunks import RowChunks, io_target
from streamsvd.storage import LocalStorage, ObjectStorage

__all__ = ["PanelBasis"]

logger = logging.getLogger(__name__)

class PanelBasis:
    """Basis in panels chunked by rows (see the module docstring).

    Parameters
    ----------
    n : int
        Rows (size of a snapshot).
    inner : InnerProduct
        Euclidean or :class:`~streamsvd.algebra.inner.DiagonalInner` (a matrix couples the row
        chunks).
    chunk_rows : int
        Rows per chunk of the panels and of the products.
    client : distributed.Client or None
        Where the graphs run (the threaded scheduler when None).
    root : LocalStorage or ObjectStorage
        Where ``panels/`` is (the store's root, or a work directory). In a local
        directory every panel is written as a raw row-major file (:class:`RawArray`),
        which the passes read and write; a commit that lists a panel first writes a zarr
        copy of it beside the file, with checksums (:meth:`commit_arrays`), which a
        reopened store reads. In an object store the panels are zarr arrays.
    """

    defers_gram = False  # each compaction's pass measures the Gram of what it writes

    def __init__(
        self, n: int, inner: InnerProduct, *, chunk_rows: int, client: Any, root: Any
    ) -> None:
        self.n = int(n)
        self.inner = inner
        self.chunk_rows = int(chunk_rows)
        self.root: LocalStorage | ObjectStorage = root
        self.files = PanelFiles(n, chunk_rows=chunk_rows, root=root)
        self.rows = RowChunks(n, chunk_rows=chunk_rows, inner=inner, client=client,
                              files=self.files)
        self.panels: list[str] = []
        self.widths: list[int] = []
        self._ws: np.ndarray | None = None
        self._mws: np.ndarray | None = None
        self._staged_new: tuple[str, int] | None = None
        self._staged_compact: tuple[str, int] | None = None
        self._staged_block: tuple[str, Any] | None = None  # (scratch name or "", dask)
        self._expected: Any = None  # the next update's block, read by this compaction
        self._read_ahead: _ReadAhead | None = None  # what that compaction read of it
        self._retired: list[str] = []  # panels a compaction replaced, not yet deleted
        self.compactions = 0

    # ------------------------------------------------------------------ panels
    @property
    def width(self) -> int:
        """Number of stored columns ``w``."""
        return int(sum(self.widths))

    @property
    def capacity(self) -> int:
        """Columns the basis can hold without growing: panels are added, never grown."""
        return np.iinfo(np.int64).max

    @property
    def pieces(self) -> int:
        """Number of panels: each pass reads every one, in tasks per row chunk."""
        return len(self.panels)

    def _write(self, data: Any) -> tuple[str, int]:
        """Write an ``n x c`` numpy or dask array as a new panel; return its name and width."""
        import dask.array as da

        cols = int(data.shape[1])
        name, z = self.files.new(cols)
        if isinstance(data, np.ndarray):
            z[:] = data
        else:
            self.rows.compute([da.store(data, io_target(z), lock=False, compute=False)])
        return name, cols

    # ------------------------------------------------------------------ products
    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)`` (``G = None``: the identity)."""
        Q = self.rows.stacked(self.panels)
        if Q is None:
            return np.zeros((0 if G is None else G.shape[1], X.shape[1]))
        (C,) = self.rows.compute([self.rows.weighted(Q).T @ self.rows.block(X)])
        C = np.asarray(C)
        return C if G is None else G.T @ C

    def residual_products(self, Z: np.ndarray, MZ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``MQ^T Z`` (by row chunks) and ``Z^T M Z`` (``MZ`` the image of ``Z``)."""
        return self.project(Z, None), gram(Z, self.inner, MZ)

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place, row chunk by row chunk."""
        Q = self.rows.stacked(self.panels)
        if Q is None:
            return
        K = C if G is None else G @ C
        (D,) = self.rows.compute([Q @ K])
        X -= np.asarray(D)

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return in-memory ``(Y, MY)`` for ``b`` new columns (scratch until accepted)."""
        self._ws = np.empty((self.n, b), order="F")
        self._mws = self._ws if self.inner.is_euclidean else np.empty((self.n, b), order="F")
        self._staged_new = self._staged_compact = None
        return self._ws, self._mws

    def planned_new(self, r: int) -> tuple[np.ndarray, np.ndarray]:
        """Return the first ``r`` workspace columns and their ``M`` image."""
        assert self._ws is not None and self._mws is not None
        return self._ws[:, :r], self._mws[:, :r]

    def accept(self, r: int) -> None:
        """Append the staged panel to the stored columns."""
        if r:
            if self._staged_new is None:
                self.stage_new(r)
            assert self._staged_new is not None
            name, cols = self._staged_new
            self.panels.append(name)
            self.widths.append(cols)
        self._staged_new, self._ws, self._mws = None, None, None

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` as one new panel; return its Gram ``Q'^T M Q'``."""
        return self._compact(G, [self.rows.block(self.planned_new(r)[0])] if r else [])

    def block_products(self, X: Any, *, project: bool) -> tuple[np.ndarray, np.ndarray]:
        """Stage ``X`` for :meth:`compact_with_block`; return ``X^T M X`` and ``MQ^T X``.

        One pass over the row chunks computes both (``project`` is not needed), one task
        per chunk (:func:`~streamsvd.algebra.panels.tasks.chunk_products`). A
        :class:`~streamsvd.algebra.panels.lazy.LazyBlock` is read once, chunk by chunk, each chunk
        written to a scratch copy (in the source's dtype: float32 stays float32) by the
        task that uses it in float64, so the ``n x b`` block is never in memory; an
        in-memory block is used where it is.
        The scratch copy is one raw file in a local directory (it serves one update and
        no commit refers to it: no chunks, codec or checksum; 15% faster than a zarr
        panel for the whole tall mode, ``bench/README.md``; the next block writes over
        it, :meth:`~streamsvd.algebra.panels.files.PanelFiles.new`), a zarr panel in an object
        store. A failed read raises the block's :class:`~streamsvd.errors.SourceError`.
        """
        from streamsvd.algebra.panels.lazy import LazyBlock
        from streamsvd.errors import StreamSVDError

        ahead, self._read_ahead = self._read_ahead, None
        if ahead is not None:
            if (ahead.block is X and [ahead.panel] == self.panels and ahead.S is not None
                    and ahead.C is not None):
                self._staged_block = (ahead.scratch,
                                      self.rows.panel(ahead.scratch).astype(np.float64))
                return ahead.S, ahead.C
            self.files.let_go(ahead.scratch)
        b = int(X.shape[1])
        lazy = isinstance(X, LazyBlock)
        Xd = (self.rows.rows_of(X.data) if lazy else self.rows.block(X))
        scratch: Any = None
        if lazy:
            name, scratch = self._new_scratch(b, Xd.dtype)
            self._staged_block = (name, None)
        rows = b + self.width
        shares = self.rows.run_pass(panel_tasks.chunk_products, [Xd, *self._parts()], rows, b,
                                    target=scratch)
        try:
            (done,) = self.rows.compute([shares])
        except StreamSVDError:
            raise
        except Exception as exc:
            if lazy:
                raise X.failed(exc) from exc
            raise
        total = np.asarray(done)
        if lazy:
            self._staged_block = (name, self.rows.panel(name).astype(np.float64))
        else:
            self._staged_block = ("", Xd)
        S = total[:b]
        return 0.5 * (S + S.T), total[b:]

    def expect(self, X: Any) -> None:
        """Name ``X``, the next update's block, for :meth:`compact_with_block` to read.

        Only a :class:`~streamsvd.algebra.panels.lazy.LazyBlock` of ``n`` rows is read ahead (its
        source is read once either way); anything else is ignored.
        """
        from streamsvd.algebra.panels.lazy import LazyBlock

        self._expected = X if isinstance(X, LazyBlock) and X.shape[0] == self.n else None

    def compact_with_block(self, G: np.ndarray) -> np.ndarray:
        """Write ``[Q, X] G`` as one new panel (``X`` staged by :meth:`block_products`).

        With a next block named by :meth:`expect`, the same pass reads it (one task per
        row chunk, :func:`~streamsvd.algebra.panels.tasks.chunk_compaction_and_products`): it
        writes its scratch copy and returns its products with the new basis, which the next
        :meth:`block_products` of that block on that basis takes instead of a pass of its
        own (the same numbers: each chunk's products are the ones that pass would form).
        Should the pass fail, it runs again without the next block, whose update then
        reads it and reports what failed.
        """
        assert self._staged_block is not None and self._staged_block[1] is not None
        following, self._expected = self._expected, None
        if following is not None and G.shape[1]:
            try:
                return self._compact_and_read(G, following)
            except Exception as exc:  # noqa: BLE001 - the next update reports it
                logger.debug("reading the next block ahead failed (%s: %s); its update "
                             "reads it", type(exc).__name__, exc)
                self._drop_read_ahead()
                staged, self._staged_compact = self._staged_compact, None
                if staged is not None:
                    self.files.let_go(staged[0])
        return self._compact(G, [self._staged_block[1]])

    def _compact_and_read(self, G: np.ndarray, following: Any) -> np.ndarray:
        """Write ``[Q, X] G`` as a new panel and read the next block; return the Gram."""
        assert self._staged_block is not None
        parts = [*self._parts(), self._staged_block[1]]
        p, b = G.shape[1], int(following.shape[1])
        name, z = self.files.new(p)
        self._staged_compact = (name, p)
        Xd = self.rows.rows_of(following.data)
        scratch, scratch_target = self._new_scratch(b, Xd.dtype)
        self._read_ahead = _ReadAhead(following, name, scratch)
        shares = self.rows.run_pass(panel_tasks.chunk_compaction_and_products, [*parts, Xd],
                                    p + b, p + b, target=io_target(z),
                                    next_target=scratch_target, G=G)
        (done,) = self.rows.compute([shares])
        total = np.asarray(done)
        H, S = total[:p, :p], total[p:, p:]
        self._read_ahead.S, self._read_ahead.C = 0.5 * (S + S.T), total[:p, p:]
        return 0.5 * (H + H.T)

    def _drop_read_ahead(self) -> None:
        """Forget the next block read ahead, keeping its scratch copy to write over."""
        ahead, self._read_ahead = self._read_ahead, None
        if ahead is not None:
            self.files.let_go(ahead.scratch)

    def _compact(self, G: np.ndarray, extra: list[Any]) -> np.ndarray:
        """Write ``[Q, *extra] G`` as one new panel (``extra``: dask blocks); return its Gram.

        ``Q G_q + X G_x``, a product per part summed in each row chunk's task
        (:func:`~streamsvd.algebra.panels.tasks.chunk_compaction`, as the in-memory basis does), so
        no row chunk of ``[Q, X]`` is ever concatenated; the task writes its rows of the
        new panel and returns their share of its Gram.
        """
        parts = self._parts() + extra
        p = G.shape[1]
        if not parts or p == 0:
            self._staged_compact = ("", 0)
            return np.zeros((p, p))
        name, z = self.files.new(p)
        self._staged_compact = (name, p)
        shares = self.rows.run_pass(panel_tasks.chunk_compaction, parts, p, p,
                                    target=io_target(z), G=G)
        (done,) = self.rows.compute([shares])
        H = np.asarray(done)
        return 0.5 * (H + H.T)

    def _new_scratch(self, cols: int, dtype: Any) -> tuple[str, Any]:
        """Create the block's scratch copy, a panel (``n x cols``); return its name and target.

        The copy that the last block left (:meth:`_drop_block`) is written over when it
        has this shape and dtype (:meth:`~streamsvd.algebra.panels.files.PanelFiles.new`).
        """
        name, z = self.files.new(cols, dtype)
        return name, io_target(z)

    def _parts(self) -> list[Any]:
        """Return the stored panels as dask arrays of their row chunks (not concatenated)."""
        return [self.rows.panel(name) for name in self.panels]

    def _drop_block(self) -> None:
        """Forget the staged block; keep its raw scratch copy for the next block, or remove it.

        No commit refers to a scratch copy, and no array handed out reads it.
        """
        if self._staged_block is not None and self._staged_block[0]:
            self.files.let_go(self._staged_block[0])
        self._staged_block = None

    def lincomb(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` in memory (``n x p``)."""
        Q = self.rows.stacked(self.panels)
        if Q is None:
            return np.zeros((self.n, G.shape[1]))
        (U,) = self.rows.compute([Q @ G])
        return np.asarray(U)

    def lazy(self, G: np.ndarray) -> Any:
        """Return ``Q G`` as a dask array (computed chunk by chunk, never whole)."""
        import dask.array as da

        Q = self.rows.stacked(self.panels)
        if Q is None:
            return da.zeros((self.n, G.shape[1]), chunks=(self.rows.sizes, (1,)))
        return Q @ G

    # ------------------------------------------------------------------ persistence
    # the staging of a commit (:mod:`streamsvd.algebra.panels.staging`), bound as methods
    swap = staging.swap
    discard_planned = staging.discard_planned
    commit_arrays = staging.commit_arrays
    restore = staging.restore
    adopt = staging.adopt
    release = staging.release
    collect = staging.collect
    stage_new = staging.stage_new
    drop_scratch = staging.drop_scratch
    _seal = staging._seal


class _ReadAhead:
    """The next update's block as a compaction read it (:meth:`PanelBasis.expect`).

    ``block`` was read into the scratch copy ``scratch`` by the pass that wrote panel
    ``panel``; ``S = x^T M x`` and ``C = P^T M x`` are set once that pass is done.
    """

    def __init__(self, block: Any, panel: str, scratch: str) -> None:
        self.block, self.panel, self.scratch = block, panel, scratch
        self.S: np.ndarray | None = None
        self.C: np.ndarray | None = None
