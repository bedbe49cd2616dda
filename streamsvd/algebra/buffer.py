"""The growable buffer of an in-memory basis: ``Q`` and ``M Q``, and how a plan is staged.

:class:`BasisBuffer` keeps ``Q`` (and ``M Q`` for a non-Euclidean inner product) in
column-major buffers whose capacity grows geometrically, so appending columns never
copies the basis (the buffers are reallocated ``O(log)`` times over a stream, counted in
:attr:`BasisBuffer.reallocations`); a compaction writes into a second buffer of the same
capacity (the spare), swapped in by :meth:`BasisBuffer.swap`. It is the staging half of
:class:`~streamsvd.algebra.interface.BasisStaging` (accepting workspace columns, swapping
in a compacted basis, what a commit writes and how it is restored, pickling);
:class:`~streamsvd.algebra.memory.MemoryBasis` adds the products and the compactions.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from streamsvd.algebra.inner import InnerProduct
from streamsvd.errors import BrokenStateError

__all__ = ["BasisBuffer"]

_GROWTH = 2.0  # capacity factor when the buffers are full


class BasisBuffer:
    """The stored columns of an in-memory basis, their workspace and a compaction buffer.

    Parameters
    ----------
    n : int
        Rows (size of a snapshot).
    inner : InnerProduct
        The inner product ``M`` (``M Q`` is kept beside ``Q`` unless it is Euclidean).
    capacity : int
        Initial number of columns the buffers hold.
    compact_in_place : bool
        Keep no compaction buffer between updates (a subclass then writes its
        compactions over the stored columns, :class:`~streamsvd.algebra.memory.MemoryBasis`).

    Notes
    -----
    A subclass writes a planned basis into ``_spare`` (or, with ``_overwritten`` set,
    over ``_bufs``), its width in ``_planned_width``, and stages a block in ``_block``
    (``(X, M X)``; ``_beside`` when it is in the workspace).
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

    @property
    def pieces(self) -> int:
        """One: the stored columns are contiguous."""
        return 1

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

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return views ``(Y, MY)`` of ``b`` columns after the stored ones.

        Their content is scratch until :meth:`accept`; the stored columns are untouched
        (the buffers may be reallocated here, never afterwards in the same update).
        """
        w = self._w
        self._ensure(w + b)
        Q, MQ = self._bufs
        return Q[:, w : w + b], MQ[:, w : w + b]

    # ------------------------------------------------------------------ staging
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
        """Make the basis a compaction wrote the stored one.

        The spare buffer that a compaction wrote aside is swapped in
        (:meth:`~streamsvd.algebra.memory.MemoryBasis.compact_planned`); one written over
        the stored columns is in place already. A basis made with ``compact_in_place=True``
        frees the replaced buffer (it keeps no compaction buffer between updates).
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
