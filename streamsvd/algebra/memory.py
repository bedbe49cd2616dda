"""The n-sized factor of an expansion: the stored basis ``Q`` and the few products on it.

An update of a compressor touches the ``n``-sized data only through a handful of
operations (:class:`BasisAlgebra`; how a planned basis is switched to and committed is
:class:`BasisStaging`), all BLAS-3 (written once in :mod:`streamsvd.engine.update`, as pyMOR writes
``gram_schmidt`` once over its vector arrays):

* ``project(X, G)``: ``G^T (MQ^T X)``, the coefficients of a block on the basis ``Q G``;
* ``subtract(X, G, C)``: ``X -= Q (G C)``;
* ``workspace(b)``: room for ``b`` new columns right after the stored ones, where a block
  is orthonormalised in place; ``accept(r)`` makes the first ``r`` of them basis columns;
* ``compact_planned(G, r)`` then ``swap(p)``: ``Q <- [Q, Y_r] G`` (and ``M Q`` likewise),
  written aside first so that nothing stored changes before ``swap``; its Gram is
  measured from the written columns;
* ``block_products(X)`` then ``compact_with_block(G)``: the Gram path's two passes
  (:mod:`streamsvd.engine.update_gram`): the block's Gram ``X^T M X`` and its projection
  ``MQ^T X`` with the block staged as it is (in memory: referenced, not copied; a block
  read by row chunks: written once to a scratch panel as it is read), then
  ``Q <- [Q, X] G`` written aside like ``compact_planned`` (or over ``Q`` itself by a
  basis made to, below). A basis that ``defers_gram`` (in memory, compacting aside)
  leaves the Gram of the columns it writes there to the next update, whose
  ``joint_products(X)`` copies the block beside ``Q`` and measures the Gram of ``[Q, X]``
  whole, ``Q^T M Q`` with it, in one product (``measure_gram()`` measures ``Q^T M Q``
  alone for whoever reads the basis before; :class:`~streamsvd.engine.state.State`); its
  ``products_beside(X)`` copies a narrow block beside ``Q`` and returns ``X^T M X`` and
  ``MQ^T X`` in one product, so that the update may keep the block as stored columns
  (``accept``) instead of compacting;
* ``stage_new(r)``, ``commit_arrays(...)``, ``restore(...)``, ``collect(...)``,
  ``release(...)``: what a commit to a store needs, what it may delete afterwards, and
  what an update replaced that no recent commit uses; ``compactions`` counts the swaps,
  so a commit tells the columns appended since the previous one (the others are
  unchanged) from a basis replaced whole.
* ``lincomb(G)``: ``Q G``. (The new block of the basis Gram, ``MQ^T Y``, is measured by
  Gram-Schmidt with ``project``, never formed again.)

:class:`MemoryBasis` keeps ``Q`` (and ``M Q`` for a non-Euclidean inner product) in
column-major buffers whose capacity grows geometrically, so appending columns never
copies the basis (the buffers are reallocated ``O(log)`` times over a stream, counted in
:attr:`MemoryBasis.reallocations`); a compaction writes into a second buffer of the same
capacity, swapped in by ``swap``. Made with ``compact_in_place=True``, it writes the Gram
path's compactions over the stored columns instead, slab of rows by slab of rows (each row
of ``[Q, X] G`` depends on the same row of ``Q`` and ``X`` only), and keeps no second
buffer between updates: one ``n x k`` buffer less, for compactions about 20% slower (the
slabs of a column-major basis are strided). The stored columns are then gone as soon as
the compaction starts: an update that does not complete afterwards (an interrupt, or the
Gram path declining the basis it wrote, which its rounding bound rules out) leaves the
basis unusable (:class:`~streamsvd.errors.BrokenStateError`), so only a compressor thrown
away or recomputed on failure should be made so (the leaves and merges of
:func:`~streamsvd.parallel.tree_compress`).

A compressor does not choose its basis class: it is given a :class:`Backend`, which
makes its basis and says what that choice implies (the kind of store it writes, how a
copy gets its own basis, how a block reaches memory). :class:`MemoryBackend` is the
default; :class:`streamsvd.algebra.panels.backend.PanelBackend` keeps the basis in panels on disk.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np
import scipy.linalg.blas as blas

from streamsvd._util.slabs import row_slabs
from streamsvd._util.validation import as_float_array, check_finite
from streamsvd.algebra.blas import gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.errors import BrokenStateError

__all__ = [
    "Backend", "BasisAlgebra", "BasisBackend", "BasisStaging", "DeferredGram", "MEMORY_KIND",
    "MemoryBackend", "MemoryBasis",
]

MEMORY_KIND = "streamsvd.StreamCompressor"
"""The kind recorded in the store of a compressor whose basis is in memory."""

_GROWTH = 2.0  # capacity factor when the buffers are full


class BasisAlgebra(Protocol):
    """The products an update computes on the n-sized factor (module docstring)."""

    n: int

    @property
    def width(self) -> int:
        """Number of stored columns ``w``."""

    @property
    def capacity(self) -> int:
        """Columns the basis can hold (stored and workspace) without growing its storage."""

    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)`` (``G = None``: the identity)."""

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place."""

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return views ``(Y, MY)`` of ``b`` columns after the stored ones."""

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` aside; return its Gram ``Q'^T M Q'``."""

    def block_products(self, X: Any, *, project: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Stage the block ``X``; return ``X^T M X`` and ``MQ^T X`` (None unless ``project``).

        A backend that reads ``X`` in one pass computes ``MQ^T X`` whatever ``project``.
        """

    def compact_with_block(self, G: np.ndarray) -> np.ndarray | None:
        """Write ``[Q, X] G`` aside (``X`` the staged block); return its Gram ``Q'^T M Q'``.

        None when the basis ``defers_gram``: the next update measures it.
        """

    @property
    def defers_gram(self) -> bool:
        """Whether ``compact_with_block`` leaves its Gram to be measured later.

        Such a basis is a :class:`DeferredGram` as well.
        """

    def lincomb(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` as a new array."""


class BasisStaging(Protocol):
    """How a planned basis becomes the stored one, and what a commit of it writes."""

    compactions: int  # number of swaps: the stored columns were all replaced

    def accept(self, r: int) -> None:
        """Make the first ``r`` workspace columns stored columns."""

    def stage_new(self, r: int) -> None:
        """Make the first ``r`` workspace columns durable before a commit refers to them."""

    def swap(self, p: int) -> None:
        """Make the basis written by ``compact_planned`` the stored one."""

    def discard_planned(self) -> None:
        """Forget what a plan staged (the update was abandoned)."""

    def commit_arrays(self, r: int, *, compacted: bool) -> tuple[dict[str, np.ndarray], dict]:
        """Return the arrays and attributes a commit of the planned basis writes."""

    def restore(self, arrays: dict[str, np.ndarray], attrs: dict) -> None:
        """Load the basis a commit wrote."""

    def collect(self, committed: Sequence[dict]) -> None:
        """Delete stored data that neither the state nor these commits' attributes use."""

    def release(self, committed: Sequence[dict]) -> None:
        """Delete what this basis replaced and none of these commits' attributes use."""

    def drop_scratch(self) -> None:
        """Free the scratch kept between updates (a compaction buffer, ...)."""


class BasisBackend(BasisAlgebra, BasisStaging, Protocol):
    """What an update needs from the n-sized factor: its algebra and its staging."""


class DeferredGram(BasisBackend, Protocol):
    """A basis whose compactions leave their Gram to be measured later (``defers_gram``)."""

    def joint_products(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X``, ``MQ^T X`` and ``Q^T M Q``."""

    def measure_gram(self) -> np.ndarray:
        """Return the Gram ``Q^T M Q`` of the stored columns, measured."""

    def products_beside(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X`` and ``MQ^T X`` (one product)."""

    @property
    def block_beside(self) -> bool:
        """Whether the staged block is in the workspace, after the stored columns."""


class Backend(Protocol):
    """Where a compressor keeps its n-sized factor, and what that choice implies."""

    kind: str  # recorded in the store: a store is reopened with the backend that wrote it
    temporary: bool  # the basis is removed by close() (nothing left to finalise)

    def new_basis(self, n: int, inner: InnerProduct) -> BasisBackend:
        """Return an empty basis for snapshots of size ``n`` in the inner product ``inner``."""

    def fresh(self) -> Backend:
        """Return a backend of the same settings whose basis is independent of this one."""

    def copied(self, basis: BasisBackend, blank: BasisBackend) -> BasisBackend:
        """Return ``basis`` copied for a compressor whose own empty basis is ``blank``."""

    def into_store(self, basis: BasisBackend, storage: Any) -> tuple[Backend, BasisBackend]:
        """Return the backend and basis that a new store in ``storage`` commits.

        This backend and ``basis`` when a commit writes the basis itself; else a copy
        of the basis written into ``storage``, which ``basis`` is left as it was.
        """

    def load(self, columns: Any, *, rows: int, first: int) -> Any:
        """Return ``columns`` checked as a block of ``rows`` rows the basis takes.

        An array, or a block its basis reads when the update needs it (``first``: its
        offset in the source, named when that read fails).
        """

    def in_memory(self, block: Any) -> np.ndarray:
        """Return a block from :meth:`load` as a float64 array, its entries checked finite."""

    def describe(self, basis: BasisBackend) -> str:
        """Return what ``repr`` of a compressor shows of its basis (may be empty)."""

    def close(self) -> None:
        """Release what the backend holds (a temporary directory, ...)."""


class MemoryBackend:
    """The basis in memory (:class:`MemoryBasis`): the default of every compressor.

    Parameters
    ----------
    compact_in_place : bool
        Make bases that write the Gram path's compactions over their stored columns (see
        :class:`MemoryBasis`): one ``n x k`` buffer less, for compressors thrown away or
        made again when an update fails (the leaves and merges of a tree).
    """

    kind = MEMORY_KIND
    temporary = False

    def __init__(self, *, compact_in_place: bool = False) -> None:
        self.compact_in_place = bool(compact_in_place)

    def new_basis(self, n: int, inner: InnerProduct) -> MemoryBasis:
        """Return an empty in-memory basis."""
        return MemoryBasis(n, inner, compact_in_place=self.compact_in_place)

    def fresh(self) -> MemoryBackend:
        """Return this backend (it holds nothing)."""
        return self

    def copied(self, basis: BasisBackend, blank: BasisBackend) -> BasisBackend:
        """Return a deep copy of the stored columns (no workspace, no compaction buffer).

        The copy compacts as ``blank`` (the new compressor's own basis) does.
        """
        out = copy.deepcopy(basis)
        assert isinstance(out, MemoryBasis) and isinstance(blank, MemoryBasis)
        out.compact_in_place = blank.compact_in_place
        return out

    def into_store(self, basis: BasisBackend, storage: Any) -> tuple[MemoryBackend, BasisBackend]:
        """Return this backend and ``basis``: a commit writes its stored columns."""
        return self, basis

    def load(self, columns: Any, *, rows: int, first: int) -> np.ndarray:
        """Return the block checked and converted to a float64 array.

        Its entries are checked later: by :meth:`in_memory`, or by the Gram path from
        the block's Gram (:mod:`streamsvd.engine.update_gram`), which costs nothing more.
        """
        return as_float_array(columns, "columns", ndim=2, rows=rows, allow_empty=False,
                              finite=False)

    def in_memory(self, block: Any) -> np.ndarray:
        """Return the block (in memory already) once its entries are checked finite."""
        check_finite(block, "columns")
        return block

    def describe(self, basis: BasisBackend) -> str:
        """Nothing beyond the compressor's own fields."""
        return ""

    def close(self) -> None:
        """Nothing to release."""


class MemoryBasis:
    """In-memory basis buffer (see the module docstring).

    Parameters
    ----------
    n : int
        Rows (size of a snapshot).
    inner : InnerProduct
        The inner product ``M`` (``M Q`` is kept beside ``Q`` unless it is Euclidean).
    capacity : int
        Initial number of columns the buffers hold.
    compact_in_place : bool
        Write the Gram path's compactions over the stored columns, and keep no compaction
        buffer between updates (module docstring).
    """

    def __init__(
        self, n: int, inner: InnerProduct, *, capacity: int = 0, compact_in_place: bool = False
    ) -> None:
        self.n = int(n)
        self.inner = inner
        self.compact_in_place = bool(compact_in_place)
        self._w = 0
        self.reallocations = 0
        self.compactions = 0  # columns only appended between two (what a commit writes)
        self._bufs = self._allocate(int(capacity))
        self._spare: tuple[np.ndarray, np.ndarray] | None = None
        self._planned_width = 0
        self._overwritten = False  # the planned basis is in the stored buffers
        self._broken = False  # they were overwritten by an update that did not complete
        self._block: tuple[np.ndarray, np.ndarray] | None = None
        self._beside = False  # the staged block is in the workspace, after the basis

    @property
    def defers_gram(self) -> bool:
        """Whether the Gram path's compactions leave their Gram to the next update.

        Those aside do (the next block is copied beside them, :meth:`joint_products`);
        those in place measure it at once (their basis may then be broken).
        """
        return not self.compact_in_place

    def __getstate__(self) -> dict[str, Any]:
        """Pickle and copy the stored columns only (not the workspace, not the scratch).

        A copy's buffers hold its ``w`` columns; they grow again when it appends.
        """
        state = dict(self.__dict__)
        w = self._w
        Q, MQ = self._bufs
        state["_bufs"] = (Q[:, :w], None if self.inner.is_euclidean else MQ[:, :w])
        state["_spare"], state["_block"], state["_beside"] = None, None, False
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Restore a pickled or copied basis (``M Q`` is ``Q`` when Euclidean)."""
        self.__dict__.update(state)
        Q, MQ = self._bufs
        self._bufs = (Q, Q if MQ is None else MQ)

    # ------------------------------------------------------------------ buffers
    def _allocate(self, cap: int) -> tuple[np.ndarray, np.ndarray]:
        Q = np.empty((self.n, cap), order="F")
        MQ = Q if self.inner.is_euclidean else np.empty((self.n, cap), order="F")
        return Q, MQ

    @property
    def capacity(self) -> int:
        """Columns the buffers hold (stored and workspace) before they must grow."""
        return int(self._bufs[0].shape[1])

    def _ensure(self, cols: int) -> None:
        if cols <= self.capacity:
            return
        cap = max(cols, int(_GROWTH * self.capacity), 8)
        Q, MQ = self._allocate(cap)
        w = self._w
        Q[:, :w] = self._bufs[0][:, :w]
        if not self.inner.is_euclidean:
            MQ[:, :w] = self._bufs[1][:, :w]
        self._bufs = (Q, MQ)
        self._spare = None
        self.reallocations += 1

    @property
    def width(self) -> int:
        """Number of stored columns ``w``."""
        return self._w

    @property
    def Q(self) -> np.ndarray:
        """The stored columns (a view, ``n x w``)."""
        self._check_usable()
        return self._bufs[0][:, : self._w]

    @property
    def MQ(self) -> np.ndarray:
        """``M Q`` (the same view as :attr:`Q` for the Euclidean inner product)."""
        self._check_usable()
        return self._bufs[1][:, : self._w]

    def _check_usable(self) -> None:
        if self._broken:
            raise BrokenStateError(
                "this compressor's basis was written over by an update that did not "
                "complete (its compactions are made in place, `compact_in_place=True`): "
                "its stored columns are lost. Start again, or reopen its store."
            )

    # ------------------------------------------------------------------ products
    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)``, the coefficients of ``X`` on the basis ``Q G``.

        ``G = None`` stands for the identity (the basis is ``Q`` itself).
        """
        C = self.MQ.T @ X
        return C if G is None else G.T @ C

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place (``G = None``: the identity), one gemm when possible."""
        K = C if G is None else G @ C
        if X.size == 0 or self._w == 0:
            return
        if X.flags.f_contiguous:
            out = blas.dgemm(-1.0, self.Q, K, beta=1.0, c=X, overwrite_c=1)
            if np.shares_memory(out, X):
                return
        X -= self.Q @ K

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return views ``(Y, MY)`` of ``b`` columns after the stored ones.

        Their content is scratch until :meth:`accept`; the stored columns are untouched
        (the buffers may be reallocated here, never afterwards in the same update).
        """
        w = self._w
        self._ensure(w + b)
        Q, MQ = self._bufs
        return Q[:, w : w + b], MQ[:, w : w + b]

    def accept(self, r: int) -> None:
        """Make the first ``r`` workspace columns stored columns."""
        self._w += int(r)
        self._block, self._beside = None, False

    def stage_new(self, r: int) -> None:
        """Nothing to do: the workspace columns are in memory until :meth:`accept`."""

    def _planned(self, r: int, *, compacted: bool) -> tuple[np.ndarray, np.ndarray]:
        """Return the stored columns after :meth:`accept` (``r``) or :meth:`swap` (views)."""
        if compacted:
            p = self._planned_width
            planned = self._bufs if self._overwritten else self._spare
            assert planned is not None
            return planned[0][:, :p], planned[1][:, :p]
        w = self._w + r
        return self._bufs[0][:, :w], self._bufs[1][:, :w]

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` into the spare buffer; :meth:`swap` makes it the basis.

        Returns the Gram ``Q'^T M Q'`` of the columns written (the orthogonality is
        measured from the factor itself). The stored columns are untouched until
        :meth:`swap`.
        """
        w = self._w + r
        H = self._compact(G, [(self._bufs[0][:, :w], self._bufs[1][:, :w])])
        assert H is not None
        return H

    def block_products(
        self, X: np.ndarray, *, project: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Stage ``X`` for :meth:`compact_with_block`; return ``X^T M X`` and ``MQ^T X``.

        The block is referenced, not copied (beside ``M X`` for a non-Euclidean inner
        product); ``MQ^T X`` is None unless ``project``.
        """
        MX = X if self.inner.is_euclidean else self.inner.apply(X)
        self._block, self._beside = (X, MX), False
        return gram(X, self.inner, MX), self.project(X, None) if project else None

    def joint_products(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X``, ``MQ^T X`` and ``Q^T M Q``.

        The block is copied into the workspace, after the stored columns, and the Gram
        of ``[Q, X]`` is one product (a rank-k update when Euclidean): at blocks of 10
        and 100 columns on a basis of 70 (n = 20000, one thread) it took 3.3 and 12 ms
        where ``Q^T Q``, ``Q^T X`` and ``X^T X`` apart took 4.7 and 15 ms, the copy 0.14
        and 1.9 ms (``bench/README.md``); the compaction is then one product as well.
        """
        w, b = self._w, self._stage_beside(X)
        K = self._gram_of(self._bufs[0][:, :w + b], self._bufs[1][:, :w + b])
        return K[w:, w:], K[:w, w:], K[:w, :w]

    def products_beside(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X`` and ``MQ^T X``.

        The block is copied into the workspace, after the stored columns, where an update
        may keep it (:meth:`accept`) instead of compacting; ``[MQ, MX]^T X`` is one
        product.
        """
        w, b = self._w, self._stage_beside(X)
        K = self._bufs[1][:, :w + b].T @ self._bufs[0][:, w:w + b]
        return 0.5 * (K[w:] + K[w:].T), K[:w]

    def _stage_beside(self, X: np.ndarray) -> int:
        """Copy ``X`` (and ``M X``) into the workspace and stage it; return its width."""
        b = X.shape[1]
        Y, MY = self.workspace(b)
        Y[...] = X
        if not self.inner.is_euclidean:
            MY[...] = self.inner.apply(X)
        self._block, self._beside = (Y, MY), True
        return b

    @property
    def block_beside(self) -> bool:
        """Whether the staged block is in the workspace, after the stored columns."""
        return self._beside

    def measure_gram(self) -> np.ndarray:
        """Return the Gram ``Q^T M Q`` of the stored columns, measured."""
        return self._gram_of(self.Q, self.MQ)

    def compact_with_block(self, G: np.ndarray) -> np.ndarray | None:
        """Write ``[Q, X] G`` into the spare buffer; return its Gram, or None.

        ``X`` is staged by :meth:`block_products` or :meth:`joint_products`; None when the
        basis :attr:`defers_gram`. As :meth:`compact_planned`: one product when the block
        is beside the basis, else two, the block never copied. A basis made with
        ``compact_in_place=True`` writes it over ``Q`` instead, when it fits, and measures
        its Gram.
        """
        assert self._block is not None
        if self._beside:
            w = self._w + self._block[0].shape[1]
            parts = [(self._bufs[0][:, :w], self._bufs[1][:, :w])]
        else:
            parts = [(self.Q, self.MQ), self._block]
        if self.compact_in_place and G.shape[1] <= self.capacity:
            return self._compact_over(G, parts)
        return self._compact(G, parts, measure=not self.defers_gram)

    def _compact_over(
        self, G: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray]]
    ) -> np.ndarray:
        """Write ``[Q, X] G`` (and its ``M`` image) over ``Q``, a slab of rows at a time.

        Row ``i`` of the result depends on row ``i`` of ``Q`` and ``X`` only, so each slab is
        computed from the stored rows, then written over them. Returns the Gram of the
        columns written.
        """
        p = G.shape[1]
        self._planned_width, self._overwritten = p, True
        buffers = self._bufs[:1] if self.inner.is_euclidean else self._bufs
        starts = row_slabs(buffers[0][:, :p])
        slabs = [np.empty((starts.step, p), order="F") for _ in parts]
        for image, target in enumerate(buffers):
            for i in starts:
                rows = slice(i, min(i + starts.step, self.n))
                h = rows.stop - i
                out = slabs if h == starts.step else [np.empty((h, p), order="F") for _ in parts]
                row = 0
                for part, slab in zip(parts, out, strict=True):
                    A = part[image]
                    np.matmul(A[rows], G[row:row + A.shape[1]], out=slab)
                    row += A.shape[1]
                for slab in out[1:]:
                    out[0] += slab
                target[rows, :p] = out[0]
        return self._gram_of(self._bufs[0][:, :p], self._bufs[1][:, :p])

    def _compact(self, G: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray]], *,
                 measure: bool = True) -> np.ndarray | None:
        """Write ``[A_1, A_2, ...] G`` (and its ``M`` image) into the spare buffer.

        ``parts`` are the ``(A_i, M A_i)`` whose columns the rows of ``G`` combine, in
        order. Returns the Gram of the columns written (None unless ``measure``).
        """
        p = G.shape[1]
        if self._spare is None or self._spare[0].shape[1] < max(self.capacity, p):
            self._spare = self._allocate(max(self.capacity, p))
        self._planned_width = p
        if p == 0:
            return np.zeros((0, 0))
        out = [self._spare[0][:, :p]] + ([] if self.inner.is_euclidean
                                         else [self._spare[1][:, :p]])
        row = 0
        for i, (A, MA) in enumerate(parts):
            Gi = G[row:row + A.shape[1]]
            row += A.shape[1]
            for target, source in zip(out, (A, MA), strict=False):
                if i == 0:
                    np.matmul(source, Gi, out=target)
                    continue
                if not source.flags.f_contiguous:
                    target += source @ Gi
                    continue
                res = blas.dgemm(1.0, source, Gi, beta=1.0, c=target, overwrite_c=1)
                if not np.shares_memory(res, target):
                    target[...] = res
        if not measure:
            return None
        return self._gram_of(self._spare[0][:, :p], self._spare[1][:, :p])

    def _gram_of(self, Q: np.ndarray, MQ: np.ndarray) -> np.ndarray:
        """Return the Gram ``Q^T M Q`` of written columns, symmetric."""
        if self.inner.is_euclidean:
            return Q.T @ Q  # a rank-k update (numpy calls syrk), symmetric
        H = MQ.T @ Q
        return 0.5 * (H + H.T)

    def discard_planned(self) -> None:
        """Forget the staged block: a plan only wrote scratch columns and the spare buffer.

        A plan that wrote over the stored columns cannot be forgotten: the basis is then
        unusable (:class:`~streamsvd.errors.BrokenStateError` on its next use).
        """
        self._block, self._beside = None, False
        if self._overwritten:
            self._overwritten, self._broken = False, True

    def drop_scratch(self) -> None:
        """Free the compaction buffer kept for the next update (made again when needed)."""
        self._spare = None

    def swap(self, p: int) -> None:
        """Make the spare buffer written by :meth:`compact_planned` the stored basis.

        A basis made with ``compact_in_place=True`` frees the replaced buffer (it keeps no
        compaction buffer between updates).
        """
        assert p == self._planned_width
        if not self._overwritten:
            assert self._spare is not None
            self._spare, self._bufs = self._bufs, self._spare
            if self.compact_in_place:
                self._spare = None
        self._overwritten = False
        self._w = p
        self._block, self._beside = None, False
        self.compactions += 1

    def lincomb(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` as a new column-major array."""
        if self._w == 0 or G.shape[1] == 0:
            return np.zeros((self.n, G.shape[1]), order="F")
        return blas.dgemm(1.0, self.Q, G)

    def commit_arrays(self, r: int, *, compacted: bool) -> tuple[dict[str, np.ndarray], dict]:
        """Return the arrays (views) and attributes a commit of the planned basis writes."""
        Q, MQ = self._planned(r, compacted=compacted)
        arrays = {"Q": Q} if self.inner.is_euclidean else {"Q": Q, "MQ": MQ}
        return arrays, {"capacity": self.capacity}

    def collect(self, committed: Sequence[dict]) -> None:
        """Nothing to delete: the buffers are in memory."""

    def release(self, committed: Sequence[dict]) -> None:
        """Nothing to delete: the buffers are in memory."""

    def restore(self, arrays: dict[str, np.ndarray], attrs: dict) -> None:
        """Load the stored columns, with the capacity they were written with."""
        Q = arrays["Q"]
        w = Q.shape[1]
        self._bufs = self._allocate(max(int(attrs["capacity"]), w))
        self._spare = None
        self._bufs[0][:, :w] = Q
        if not self.inner.is_euclidean:
            self._bufs[1][:, :w] = arrays["MQ"]
        self._w = w
