"""The n-sized factor of an expansion: the stored basis ``Q`` and the few products on it.

An update of a compressor touches the ``n``-sized data only through a handful of
operations (:class:`BasisAlgebra`; how a planned basis is switched to and committed is
:class:`BasisStaging`), all BLAS-3 (written once in :mod:`streamsvd.update`, as pyMOR writes
``gram_schmidt`` once over its vector arrays):

* ``project(X, G)``: ``G^T (MQ^T X)``, the coefficients of a block on the basis ``Q G``;
* ``subtract(X, G, C)``: ``X -= Q (G C)``;
* ``workspace(b)``: room for ``b`` new columns right after the stored ones, where a block
  is orthonormalised in place; ``accept(r)`` makes the first ``r`` of them basis columns;
* ``compact_planned(G, r)`` then ``swap(p)``: ``Q <- [Q, Y_r] G`` (and ``M Q`` likewise),
  written aside first so that nothing stored changes before ``swap``; its Gram is
  measured from the written columns;
* ``stage_new(r)``, ``persisted(...)``, ``restore(...)``: what a commit to a store needs;
  ``compactions`` counts the swaps, so a commit tells the columns appended since the
  previous one (the others are unchanged) from a basis replaced whole.
* ``take(G)``: ``Q G``. (The new block of the basis Gram, ``MQ^T Y``, is measured by
  Gram-Schmidt with ``project``, never formed again.)

:class:`MemoryBasis` keeps ``Q`` (and ``M Q`` for a non-Euclidean inner product) in
column-major buffers whose capacity grows geometrically, so appending columns never
copies the basis (the buffers are reallocated ``O(log)`` times over a stream, counted in
:attr:`MemoryBasis.reallocations`); a compaction writes into a second buffer of the same
capacity, swapped in by ``swap``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.linalg.blas as blas

from .inner import InnerProduct

__all__ = ["BasisAlgebra", "BasisBackend", "BasisStaging", "MemoryBasis"]

_GROWTH = 2.0  # capacity factor when the buffers are full


class BasisAlgebra(Protocol):
    """The products an update computes on the n-sized factor (module docstring)."""

    n: int

    @property
    def width(self) -> int:
        """Number of stored columns ``w``."""

    @property
    def room(self) -> int:
        """Columns the basis can hold without growing its storage."""

    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)`` (``G = None``: the identity)."""

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place."""

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return views ``(Y, MY)`` of ``b`` columns after the stored ones."""

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` aside; return its Gram ``Q'^T M Q'``."""

    def take(self, G: np.ndarray) -> np.ndarray:
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

    def persisted(self, r: int, *, compacted: bool) -> tuple[dict[str, np.ndarray], dict]:
        """Return the arrays and attributes a commit of the planned basis writes."""

    def restore(self, arrays: dict[str, np.ndarray], attrs: dict) -> None:
        """Load the basis a commit wrote."""


class BasisBackend(BasisAlgebra, BasisStaging, Protocol):
    """What an update needs from the n-sized factor: its algebra and its staging."""


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
    """

    def __init__(self, n: int, inner: InnerProduct, *, capacity: int = 0) -> None:
        self.n = int(n)
        self.inner = inner
        self._w = 0
        self.reallocations = 0
        self.compactions = 0  # columns only appended between two (what a commit writes)
        self._bufs = self._allocate(int(capacity))
        self._spare: tuple[np.ndarray, np.ndarray] | None = None
        self._planned_width = 0

    # ------------------------------------------------------------------ buffers
    def _allocate(self, cap: int) -> tuple[np.ndarray, np.ndarray]:
        Q = np.empty((self.n, cap), order="F")
        MQ = Q if self.inner.is_euclidean else np.empty((self.n, cap), order="F")
        return Q, MQ

    @property
    def capacity(self) -> int:
        """Number of columns the buffers hold."""
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
    def room(self) -> int:
        """Columns the buffers hold (stored and workspace) before they must grow."""
        return self.capacity

    @property
    def Q(self) -> np.ndarray:
        """The stored columns (a view, ``n x w``)."""
        return self._bufs[0][:, : self._w]

    @property
    def MQ(self) -> np.ndarray:
        """``M Q`` (the same view as :attr:`Q` for the Euclidean inner product)."""
        return self._bufs[1][:, : self._w]

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

    def stage_new(self, r: int) -> None:
        """Nothing to do: the workspace columns are in memory until :meth:`accept`."""

    def _planned(self, r: int, *, compacted: bool) -> tuple[np.ndarray, np.ndarray]:
        """Return the stored columns after :meth:`accept` (``r``) or :meth:`swap` (views)."""
        if compacted:
            assert self._spare is not None
            p = self._planned_width
            return self._spare[0][:, :p], self._spare[1][:, :p]
        w = self._w + r
        return self._bufs[0][:, :w], self._bufs[1][:, :w]

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` into the spare buffer; :meth:`swap` makes it the basis.

        Returns the Gram ``Q'^T M Q'`` of the columns written (the orthogonality is
        measured from the factor itself). The stored columns are untouched until
        :meth:`swap`.
        """
        p = G.shape[1]
        if self._spare is None or self._spare[0].shape[1] < self.capacity:
            self._spare = self._allocate(self.capacity)
        S, MS = self._spare
        w = self._w + r
        np.matmul(self._bufs[0][:, :w], G, out=S[:, :p])
        if not self.inner.is_euclidean:
            np.matmul(self._bufs[1][:, :w], G, out=MS[:, :p])
        self._planned_width = p
        if p == 0:
            return np.zeros((0, 0))
        if self.inner.is_euclidean:
            out = S[:, :p]
            return out.T @ out  # a rank-k update (numpy calls syrk), symmetric
        H = MS[:, :p].T @ S[:, :p]
        return 0.5 * (H + H.T)

    def discard_planned(self) -> None:
        """Nothing to undo: a plan only wrote scratch columns and the spare buffer."""

    def swap(self, p: int) -> None:
        """Make the spare buffer written by :meth:`compact_planned` the stored basis."""
        assert self._spare is not None and p == self._planned_width
        self._spare, self._bufs = self._bufs, self._spare
        self._w = p
        self.compactions += 1

    def take(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` as a new array."""
        return self.Q @ G

    def persisted(self, r: int, *, compacted: bool) -> tuple[dict[str, np.ndarray], dict]:
        """Return the arrays (views) and attributes a commit of the planned basis writes."""
        Q, MQ = self._planned(r, compacted=compacted)
        arrays = {"Q": Q} if self.inner.is_euclidean else {"Q": Q, "MQ": MQ}
        return arrays, {"capacity": self.capacity}

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
