"""The basis in memory: :class:`MemoryBasis` and :class:`MemoryBackend`, the default backend.

:class:`MemoryBasis` implements the backend interface (:mod:`streamsvd.algebra.interface`)
on the growable buffers of :class:`~streamsvd.algebra.buffer.BasisBuffer`: ``Q`` (and
``M Q`` for a non-Euclidean inner product) in column-major buffers that appending columns
never copies; a compaction writes into a second buffer of the same capacity, swapped in by
``swap``. Made with ``compact_in_place=True``, it writes the Gram
path's compactions over the stored columns instead, slab of rows by slab of rows (each row
of ``[Q, X] G`` depends on the same row of ``Q`` and ``X`` only), and keeps no second
buffer between updates: one ``n x k`` buffer less, for compactions about 20% slower (the
slabs of a column-major basis are strided). The stored columns are then gone as soon as
the compaction starts: an update that does not complete afterwards (an interrupt, or the
Gram path declining the basis it wrote, which its rounding bound rules out) leaves the
basis unusable (:class:`~streamsvd.errors.BrokenStateError`), so only a compressor thrown
away or recomputed on failure should be made so (the leaves and merges of
:func:`~streamsvd.parallel.tree_compress`).

:class:`MemoryBackend` is the default :class:`~streamsvd.algebra.interface.Backend` of a
compressor; :class:`streamsvd.algebra.panels.backend.PanelBackend` keeps the basis in
panels on disk.
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import scipy.linalg.blas as blas

from streamsvd._util.validation import as_float_array, check_finite
from streamsvd.algebra.blas import apply_into as m_apply_into
from streamsvd.algebra.blas import gram, subtract_product
from streamsvd.algebra.buffer import BasisBuffer
from streamsvd.algebra.compaction import combine, combine_by_slabs, write_compaction
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisBackend

__all__ = ["MEMORY_KIND", "MemoryBackend", "MemoryBasis"]

MEMORY_KIND = "streamsvd.StreamCompressor"
"""The kind recorded in the store of a compressor whose basis is in memory."""


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

    def in_memory(self, block: Any, *, check: bool = True) -> np.ndarray:
        """Return the block (in memory already) once its entries are checked finite.

        ``check=False`` leaves them to the caller (:meth:`Backend.in_memory
        <streamsvd.algebra.interface.Backend.in_memory>`).
        """
        if check:
            check_finite(block, "columns")
        return block

    def describe(self, basis: BasisBackend) -> str:
        """Nothing beyond the compressor's own fields."""
        return ""

    def close(self) -> None:
        """Nothing to release."""


class MemoryBasis(BasisBuffer):
    """In-memory basis: the products and compactions of an update on its buffers.

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

    @property
    def defers_gram(self) -> bool:
        """Whether the Gram path's compactions leave their Gram to the next update.

        Those aside do (the next block is copied beside them, :meth:`joint_products`);
        those in place measure it at once (their basis may then be broken).
        """
        return not self.compact_in_place

    # ------------------------------------------------------------------ products
    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)``, the coefficients of ``X`` on the basis ``Q G``.

        ``G = None`` stands for the identity (the basis is ``Q`` itself).
        """
        C = self.MQ.T @ X
        return C if G is None else G.T @ C

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place (``G = None``: the identity), one gemm when possible."""
        if self._w:
            subtract_product(X, self.Q, C if G is None else G @ C)

    def residual_products(self, Z: np.ndarray, MZ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``MQ^T Z`` and ``Z^T M Z`` for the workspace ``Z`` (``MZ`` its image).

        With a matrix ``M`` the image is stored after ``M Q``, so both are the one
        product ``[MQ, MZ]^T Z`` (91 columns on 31 at n = 5101: 1.79 ms against 1.98 ms
        apart, one thread); the Euclidean Gram stays a rank-k update (half the flops).
        """
        w, b = self._w, Z.shape[1]
        MQZ = self._bufs[1][:, :w + b]
        if (self.inner.is_euclidean or getattr(self.inner, "diagonal", None) is not None
                or not np.shares_memory(MQZ[:, w:], MZ)):
            # a diagonal M's Gram is a rank-k update as well (algebra.blas.gram)
            return self.project(Z, None), gram(Z, self.inner, MZ)
        K = MQZ.T @ Z
        return K[:w], 0.5 * (K[w:] + K[w:].T)

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
            m_apply_into(self.inner, X, MY)
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
        computed from the stored rows, then written over them
        (:func:`~streamsvd.algebra.compaction.combine_by_slabs`).
        Returns the Gram of the columns written.
        """
        p = G.shape[1]
        self._planned_width, self._overwritten = p, True
        Q, MQ = self._bufs[0][:, :p], self._bufs[1][:, :p]
        write_compaction(self.inner, Q, MQ, G, parts, combine=combine_by_slabs)
        return self._gram_of(Q, MQ)

    def _compact(self, G: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray]], *,
                 measure: bool = True) -> np.ndarray | None:
        """Write ``[A_1, A_2, ...] G`` (and its ``M`` image) into the spare buffer.

        ``parts`` are the ``(A_i, M A_i)`` whose columns the rows of ``G`` combine, in
        order; the image as :func:`~streamsvd.algebra.compaction.write_compaction`
        decides. Returns the Gram of the columns written (None unless ``measure``).
        """
        p = G.shape[1]
        if self._spare is None or self._spare[0].shape[1] < max(self.capacity, p):
            self._spare = self._allocate(max(self.capacity, p))
        self._planned_width = p
        if p == 0:
            return np.zeros((0, 0))
        Q, MQ = self._spare[0][:, :p], self._spare[1][:, :p]
        write_compaction(self.inner, Q, MQ, G, parts, combine=combine)
        if not measure:
            return None
        return self._gram_of(Q, MQ)

    def _gram_of(self, Q: np.ndarray, MQ: np.ndarray) -> np.ndarray:
        """Return the Gram ``Q^T M Q`` of written columns, symmetric."""
        if self.inner.is_euclidean:
            return Q.T @ Q  # a rank-k update (numpy calls syrk), symmetric
        if getattr(self.inner, "diagonal", None) is not None:
            return gram(Q, self.inner, MQ)  # a rank-k update of the weighted columns
        H = MQ.T @ Q
        return 0.5 * (H + H.T)

    def lincomb(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` as a new column-major array."""
        if self._w == 0 or G.shape[1] == 0:
            return np.zeros((self.n, G.shape[1]), order="F")
        return blas.dgemm(1.0, self.Q, G)
