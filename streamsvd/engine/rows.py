"""The m-sized factor ``Y = V0 Vp``, kept in Brand's row-append form.

``Y`` (``m x k``) is the orthonormal factor of the right vectors, ``V = Y R`` with ``R``
the compressor's small core (module :mod:`streamsvd.engine.update`); here it is simply a matrix
whose rows grow.

``V0`` (``m x wv``) lives in a row buffer whose capacity grows geometrically; ``Vp``
(``wv x p``) is small. An update acts on ``Vp`` only and appends its new rows once:

* the old rows change by a small matrix: ``V_old <- V_old T_old`` is ``Vp <- Vp T_old``;
* new rows ``N`` (``b x p``, in the current coordinates) are written as
  ``V0_new = N Vp^+``, which is exact when ``Vp`` has full column rank.

So an update never reads or writes an old row of ``V`` (:attr:`RowFactor.old_rows_touched`
counts the ones that were). Brand's ``Vp`` loses conditioning when an update rotates old
terms out (the old rows then carry little of the new terms), and ``N Vp^+`` would amplify
rounding by ``cond(Vp)``. Instead of inverting an ill-conditioned ``Vp``, the directions
of ``Vp`` whose singular value is below ``s_max / cond_limit`` (and, when the rank grows
beyond ``wv``, the missing ones) get new columns of ``V0``, zero in every old row: with
``Vp <- [Vp; s_max Z_bad^T]`` the old rows are unchanged, ``cond(Vp) <= cond_limit``
afterwards, and the new rows are written with a rounding of at most ``cond_limit * eps``.
The new rows are written through the SVD of ``Vp`` (not its Gram matrix) and refined once
by what they miss, so their rounding is ``cond(Vp) eps``, not its square: one solve
through the SVD missed by up to 44 ``cond(Vp) eps`` where two singular values of ``Vp``
are close (``tests/engine/test_update.py``).
When ``wv`` exceeds ``width_limit * p`` the factor is *rebased*, ``V0 <- V0 Vp`` and
``Vp <- I`` (the only operation that reads and writes every row, ``O(m wv p)``), counted
in :attr:`RowFactor.rebases`.

Removed rows (:mod:`streamsvd.engine.downdate`) stay stored and are listed in
:attr:`RowFactor.dead`; ``Y`` is the other rows, in order, so a removal writes nothing
until the live rows are written anew by a replacement.

Between two rebases (or replacements, both counted in :attr:`RowFactor.rewrites`) the
stored rows only grow: a commit to a store writes the rows appended since the previous
one, the old rows being unchanged and zero in every column added since.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["RightFactor", "RowAppend", "RowFactor"]

COND_LIMIT = 16.0  # largest cond(Vp) through which new rows are written
WIDTH_LIMIT = 4.0  # rebase when wv > WIDTH_LIMIT * p
_GROWTH = 2.0
_CHUNK_ROWS = 4096  # rows per block of an in-place rebase


@dataclass(frozen=True)
class RowAppend:
    """New rows of ``V0`` and the small factor after them (:meth:`RowFactor.plan_append`).

    ``rebase``: the plan was made in the coordinates after a rebase, which
    :meth:`RowFactor.stage` writes first.
    """

    Vp: np.ndarray
    rows: np.ndarray
    rebase: bool


class RightFactor(Protocol):
    """What an update and a commit need from the m-sized factor ``Y`` (module docstring).

    Planning reads it (:attr:`Vp`, :attr:`wide`, :meth:`plan_append`, and the rows a
    removal reads, :attr:`V0`, :attr:`dead`); a commit stages the planned rows
    (:meth:`stage`) and writes what it reports (:attr:`V0`, :attr:`capacity`,
    :attr:`rewrites`); applying a plan writes it (:meth:`commit`, :meth:`replace`);
    opening a store loads it (:meth:`restore`).
    """

    Vp: np.ndarray
    dead: np.ndarray
    rewrites: int

    @property
    def m(self) -> int:
        """Number of stored rows."""

    @property
    def capacity(self) -> tuple[int, int]:
        """Rows and columns the storage holds."""

    @property
    def V0(self) -> np.ndarray:
        """The stored rows (``m x wv``)."""

    @property
    def wide(self) -> bool:
        """Whether the next update rebases first."""

    def value(self) -> np.ndarray:
        """Return ``Y`` over the live rows."""

    def plan_append(self, Vp_old_part: np.ndarray, N: np.ndarray, *, rebase: bool
                    ) -> RowAppend:
        """Return the new rows in the stored form and the new ``Vp`` (writes nothing)."""

    def stage(self, append: RowAppend) -> np.ndarray:
        """Write ``append``'s rows as scratch; return the stored rows it leads to."""

    def commit(self, append: RowAppend) -> None:
        """Make ``append``'s rows stored rows."""

    def replace(self, V: np.ndarray) -> None:
        """Set ``Y`` outright."""

    def restore(self, V0: np.ndarray, Vp: np.ndarray, *, capacity: tuple[int, int],
                dead: np.ndarray | None = None) -> None:
        """Load the factor a commit wrote."""


class RowFactor:
    """Right vectors ``V = V0 Vp`` (see the module docstring); empty when created."""

    def __init__(self) -> None:
        self._V0 = np.zeros((0, 0))
        self._m = 0
        self._wv = 0
        self.Vp = np.zeros((0, 0))
        # stored rows removed from Y (streamsvd.engine.downdate), sorted: Y is the other rows
        self.dead = np.zeros(0, dtype=np.int64)
        self.old_rows_touched = 0
        self.rebases = 0
        self.rewrites = 0  # rebases and replacements: every stored row changed
        self.reallocations = 0
        self._staged: RowAppend | None = None

    # ------------------------------------------------------------------ buffer
    @property
    def m(self) -> int:
        """Number of rows (snapshots)."""
        return self._m

    @property
    def width(self) -> int:
        """Stored width ``wv``."""
        return self._wv

    @property
    def capacity(self) -> tuple[int, int]:
        """Rows and columns the buffer holds."""
        return (int(self._V0.shape[0]), int(self._V0.shape[1]))

    @property
    def V0(self) -> np.ndarray:
        """The stored rows (a view, ``m x wv``)."""
        return self._V0[: self._m, : self._wv]

    def _ensure(self, rows: int, cols: int) -> None:
        cap_r, cap_c = self.capacity
        if rows <= cap_r and cols <= cap_c:
            return
        new_r = cap_r if rows <= cap_r else max(rows, int(_GROWTH * cap_r), 64)
        new_c = cap_c if cols <= cap_c else max(cols, int(_GROWTH * cap_c), 8)
        buf = np.zeros((new_r, new_c))
        buf[: self._m, : self._wv] = self.V0
        self._V0 = buf
        self.reallocations += 1

    def value(self) -> np.ndarray:
        """Return ``Y = V0 Vp`` over the live rows (a new array)."""
        V0 = np.delete(self.V0, self.dead, axis=0) if self.dead.size else self.V0
        return V0 @ self.Vp

    # ------------------------------------------------------------------ updates
    @property
    def wide(self) -> bool:
        """Whether the next update rebases first (``wv > WIDTH_LIMIT * p``).

        Decided from the stored factor, exactly as a store holds it, so that a stream
        resumed from its store rebases at the same update, bit for bit.
        """
        return self._wv > WIDTH_LIMIT * max(self.Vp.shape[1], 1)

    def plan_append(self, Vp_old_part: np.ndarray, N: np.ndarray, *, rebase: bool
                    ) -> RowAppend:
        """Return the new rows ``N`` in the stored form, and the new ``Vp`` (writes nothing).

        New columns of ``V0`` are zero in every old row, so the stored ``V`` is unchanged
        until :meth:`commit`.

        Parameters
        ----------
        Vp_old_part : ndarray, shape (wv, p')
            ``Vp T_old``: the old rows' factor after the update (in the coordinates after
            the rebase when ``rebase``, where ``Vp`` is the identity).
        N : ndarray, shape (b, p')
            The new rows in the update's coordinates.
        rebase : bool
            Whether ``V0 <- V0 Vp`` is written first (:attr:`wide`).
        """
        wv, p = Vp_old_part.shape
        b = N.shape[0]
        # Vp_old = W diag(s) Z^T (s = 0 for the directions missing when wv < p); the
        # directions with s < s_max / COND_LIMIT get a row s_max z^T each, so that
        # Vp = B Z^T with B's columns orthogonal, of norms g = s^2 (+ s_max^2 when added),
        # and Vp^+ = Z diag(1 / g) B^T: the new rows are rounded by cond(Vp) eps, not by
        # its square as through the Gram matrix
        W, sv, Zt = np.linalg.svd(Vp_old_part, full_matrices=True)
        s = np.zeros(p)
        s[: sv.size] = sv
        s_max = float(s.max()) if p else 0.0
        bad = np.flatnonzero(s < s_max / COND_LIMIT) if s_max > 0 else np.arange(p)
        scale = s_max if s_max > 0 else 1.0
        Vp = np.vstack([Vp_old_part, scale * Zt[bad]]) if bad.size else Vp_old_part
        Bt = np.zeros((p, Vp.shape[0]))
        q = min(wv, p)
        Bt[:q, :wv] = sv[:, np.newaxis] * W[:, :q].T
        Bt[bad, wv + np.arange(bad.size)] = scale
        g = s * s
        g[bad] += scale * scale
        if not p:
            return RowAppend(Vp=Vp, rows=np.zeros((b, Vp.shape[0])), rebase=rebase)
        rows = ((N @ Zt.T) / g) @ Bt
        # one step of iterative refinement: beside close singular values of Vp the first
        # solve missed N by up to 44 cond(Vp) eps (tests/engine/test_update.py); solved
        # again for what it missed, the rows miss by less than cond(Vp) eps
        rows += (((N - rows @ Vp) @ Zt.T) / g) @ Bt
        return RowAppend(Vp=Vp, rows=rows, rebase=rebase)

    def stage(self, append: RowAppend) -> np.ndarray:
        """Write ``append``'s rows after the stored ones; return the rows it leads to (a view).

        The staged rows are scratch until :meth:`commit` (a commit to a store writes them
        first). A rebase the plan was made for is written here: it changes the
        representation, never ``V``, so an update abandoned afterwards leaves ``V`` as it
        was.
        """
        b, width = append.rows.shape
        if self._staged is append:
            return self._V0[: self._m + b, :width]
        if append.rebase:
            self.rebase()
        self._ensure(self._m + b, width)
        # the whole row span is written: a staged row never keeps a stale entry from an
        # update that failed before its commit
        self._V0[self._m : self._m + b, :] = 0.0
        self._V0[self._m : self._m + b, :width] = append.rows
        self._staged = append
        return self._V0[: self._m + b, :width]

    def commit(self, append: RowAppend) -> None:
        """Make ``append``'s rows stored rows and its ``Vp`` the small factor."""
        if self._staged is not append:
            self.stage(append)
        self._m += append.rows.shape[0]
        self._wv = int(append.Vp.shape[0])
        self.Vp = append.Vp
        self._staged = None

    def rebase(self) -> None:
        """``V0 <- V0 Vp``, ``Vp <- I``, in place by blocks of rows."""
        m, wv = self._m, self._wv
        p = self.Vp.shape[1]
        self._ensure(m, p)
        for start in range(0, m, _CHUNK_ROWS):
            stop = min(start + _CHUNK_ROWS, m)
            block = self._V0[start:stop, :wv] @ self.Vp
            self._V0[start:stop, :p] = block
            self._V0[start:stop, p:wv] = 0.0
        self._wv = p
        self.Vp = np.eye(p)
        self.old_rows_touched += m
        self.rebases += 1
        self.rewrites += 1

    def replace(self, V: np.ndarray) -> None:
        """Set ``V`` outright (``V0 <- V``, ``Vp <- I``): an increment that spans every row."""
        m, p = V.shape
        self._V0 = np.zeros((max(m, 64), max(p, 8)))
        self._V0[:m, :p] = V
        self._m, self._wv = m, p
        self.Vp = np.eye(p)
        self.dead = np.zeros(0, dtype=np.int64)
        self.old_rows_touched += m
        self.rewrites += 1
        self._staged = None

    def restore(self, V0: np.ndarray, Vp: np.ndarray, *, capacity: tuple[int, int],
                dead: np.ndarray | None = None) -> None:
        """Load the factor from a store, with the capacity it was written with."""
        self.dead = np.zeros(0, dtype=np.int64) if dead is None else dead
        m, wv = V0.shape
        self._V0 = np.zeros((max(capacity[0], m), max(capacity[1], wv)))
        self._V0[:m, :wv] = V0
        self._m, self._wv = m, wv
        self.Vp = Vp
        self._staged = None
