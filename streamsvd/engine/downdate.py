"""Remove absorbed snapshots from an expansion: Brand's downdate on the small core.

The expansion is ``U V^T`` with ``V = Y R``, ``Y`` (``m x k``) orthonormal and ``R``
(``k x p``) the small core (:mod:`streamsvd.engine.update`). Removing the columns ``J`` of the
snapshot matrix removes the rows ``J`` of ``Y``; write ``Z = Y_J`` (``r x k``) and
``Y_rest`` for the others. Brand's identity for a downdate (M. Brand, *Fast low-rank
modifications of the thin singular value decomposition*, Linear Algebra Appl. 415, 2006,
section 4: a column removal is the update ``A - A e_J e_J^T`` followed by dropping the
zero columns) reduces, because the removed columns ``U R^T Z^T`` already lie in the span
of ``U``, to a change of the right factor only:

* ``Y_rest^T Y_rest = I - Z^T Z``; with the SVD ``Z = A diag(s) B^T`` (``B`` square),
  the columns of ``Y_rest B`` are orthogonal with norms ``c_i = sqrt((1 - s_i)(1 + s_i))``;
* so ``Y' = Y_rest B diag(1 / c)`` is orthonormal, and
  ``U (Y_rest R)^T = U (Y' R')^T`` with the new core ``R' = diag(c) B^T R``.

``U`` is unchanged, so ``||U^T M U - I||`` is unchanged by a removal, and the new core is
then swept and truncated as any other (the rotation sweeps of the paper, Algorithms 2-3,
by :func:`plan_remove`). Cost: ``O(r k w + (r + k) k^2 + k^2 p)`` (``w`` the stored width
of ``Y``), nothing in the number of snapshots absorbed; the rows are not read but the
``r`` removed ones (except as below).

Accuracy, and when the rows are read. ``Y`` is orthonormal to rounding ``delta`` (a few
``eps``), so the computed ``c_i^2`` has an absolute error of about ``delta``: a direction
that keeps a share ``c_i`` of its support is recovered with a relative error of about
``delta / c_i^2``, and ``Y'`` loses orthogonality by as much. Directions concentrated on
the removed columns are common (the transient of a time series, a mode that left a
window; ``examples/moving_source.py`` has them), and the loss compounds over removals.
So the small
downdate is used only while every share is at least ``EXACT_BELOW = 0.5``
(``delta / c^2 <= 4 delta``); otherwise the remaining rows themselves are orthonormalised
again by a Householder QR, ``Y_rest = Q T``, ``Y' = Q``, ``R' = T R``: exact whatever the
shares, at ``O(m_rest w k)``, which for a window is ``O(W w k)``, still nothing in the
number of snapshots absorbed before it. The same QR writes the live rows anew once the
dead rows outnumber them, which also resets the orthogonality lost by the small downdates
in between. No direction is ever dropped from the shares: a share computed as
``sqrt((1 - s)(1 + s))`` is only known to about ``sqrt(delta)`` (``1.5e-8`` at
``delta = eps``), so a direction that keeps ``1e-8`` of its support would be counted as
carrying nothing; the QR recovers it to working accuracy instead.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np

from streamsvd._util.scaling import safe_column_norms
from streamsvd.engine.bound import Bound
from streamsvd.engine.state import Plan, State, StepOptions
from streamsvd.engine.update import _plan, cutting_rounding
from streamsvd.linalg.extension import BasisExtension

__all__ = [
    "EXACT_BELOW", "Downdate", "Ledger", "bound_after_removal", "downdate", "intervals_add",
    "intervals_contain", "intervals_count_below", "intervals_skip", "physical_rows", "plan_remove",
]

logger = logging.getLogger(__name__)

_EPS = float(np.finfo(np.float64).eps)
LEDGER_SIZE = 32  # entries of the error ledger (older ones are merged)
_MIN_DEAD = 64  # dead rows kept stored at least, before the live ones are written anew
EXACT_BELOW = 0.5  # a smaller remaining share c_min orthonormalises the live rows again


@dataclass(frozen=True)
class Downdate:
    """The small matrices of a removal (see the module docstring).

    Attributes
    ----------
    S : ndarray, shape (k, k)
        ``Y' = Y_rest S``: the new orthonormal factor in the coordinates of the old one.
    R : ndarray, shape (k, p)
        The new core ``R' = diag(c) B^T R``.
    c_min : float
        Smallest remaining share ``c_i`` (1 when the removed rows were orthogonal to
        every direction).
    """

    S: np.ndarray
    R: np.ndarray
    c_min: float


def downdate(Z: np.ndarray, R: np.ndarray) -> Downdate | None:
    """Return the downdate of the core ``R`` when the rows ``Z = Y_J`` of ``Y`` are removed.

    Parameters
    ----------
    Z : ndarray, shape (r, k)
        The rows of the orthonormal right factor ``Y`` at the removed columns.
    R : ndarray, shape (k, p)
        The core (``V = Y R``).

    Returns
    -------
    Downdate or None
        ``Y_rest R = (Y_rest S) R'`` (module docstring); ``None`` when a remaining share
        is below ``EXACT_BELOW``, where the small downdate would lose accuracy and the
        remaining rows are to be orthonormalised again instead.
    """
    k = Z.shape[1]
    _, sv, Bt = np.linalg.svd(Z, full_matrices=True)
    s = np.zeros(k)
    s[: sv.size] = np.minimum(sv, 1.0)
    c = np.sqrt((1.0 - s) * (1.0 + s))
    c_min = float(c.min()) if c.size else 1.0
    if c_min < EXACT_BELOW:
        return None
    return Downdate(S=Bt.T / c, R=c[:, np.newaxis] * (Bt @ R), c_min=c_min)


# ----------------------------------------------------------------- index bookkeeping
def physical_rows(dead: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Return the stored rows of the live rows at ``positions`` (dead rows skipped).

    ``dead`` holds the sorted stored rows that were removed but are still stored; the
    live rows keep their order. ``O(len(dead) + r log)``, nothing in the stored rows.
    """
    e = dead - np.arange(dead.size)  # live rows before each dead one
    return positions + np.searchsorted(e, positions, side="right")


def intervals_count_below(intervals: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Return, for each index of ``g``, how many indices below it the intervals hold.

    ``intervals`` (``q x 2``) are sorted disjoint half-open ``[start, stop)``.
    """
    if not intervals.size:
        return np.zeros(np.shape(g), dtype=np.int64)
    start, stop = intervals[:, 0], intervals[:, 1]
    lengths = np.concatenate([[0], np.cumsum(stop - start)])
    i = np.searchsorted(start, g, side="right")  # intervals starting at or below g
    prev = np.maximum(i - 1, 0)
    partial = np.where(i > 0, np.minimum(g, stop[prev]) - start[prev], 0)
    return lengths[prev] * (i > 0) + partial


def intervals_skip(intervals: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Return the indices at ``positions`` among those the intervals do not hold.

    The inverse of ``g - intervals_count_below(intervals, g)`` on indices not held.
    """
    if not intervals.size:
        return np.asarray(positions, dtype=np.int64)
    lengths = intervals[:, 1] - intervals[:, 0]
    before = np.concatenate([[0], np.cumsum(lengths)])
    free = intervals[:, 0] - before[:-1]  # indices not held below each interval
    return positions + before[np.searchsorted(free, positions, side="right")]


def intervals_contain(intervals: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Return whether each index of ``g`` lies in one of the sorted intervals."""
    if not intervals.size:
        return np.zeros(np.shape(g), dtype=bool)
    i = np.searchsorted(intervals[:, 0], g, side="right") - 1
    return (i >= 0) & (g < intervals[np.maximum(i, 0), 1])


def intervals_add(intervals: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Return the sorted disjoint intervals of the union of ``intervals`` and ``g``."""
    runs = [np.asarray(intervals, dtype=np.int64).reshape(-1, 2)]
    g = np.unique(np.asarray(g, dtype=np.int64))
    if g.size:
        breaks = np.flatnonzero(np.diff(g) != 1) + 1
        starts = g[np.concatenate([[0], breaks])]
        stops = g[np.concatenate([breaks - 1, [g.size - 1]])] + 1
        runs.append(np.stack([starts, stops], axis=1))
    allr = np.concatenate(runs)
    if not allr.size:
        return np.zeros((0, 2), dtype=np.int64)
    allr = allr[np.argsort(allr[:, 0], kind="stable")]
    out = [list(allr[0])]
    for a, b in allr[1:]:
        if a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return np.array(out, dtype=np.int64)


# ----------------------------------------------------------------- the error ledger
@dataclass(frozen=True)
class Ledger:
    """What each update discarded, and on how many of the current columns it lies.

    The error ``E = A - U V^T`` of the current columns is the sum of every update's
    discard ``D_t`` (truncated terms, rejected residuals: :mod:`streamsvd.engine.bound`),
    restricted to the current columns and scaled by the forgetting factors since. A
    discard lies on the columns present at its update, which are always a *prefix* of
    the current ones (an update appends columns after the old ones, a removal keeps the
    order), so an entry ``(L, d)`` says: ``||D_t restricted|| <= d`` and it lies on the
    first ``L`` current columns. A removal of positions ``J`` lowers ``L`` by the number
    of ``J`` below it; an entry with ``L = 0`` lies on no current column and is dropped.
    By the triangle inequality ``||E|| <= sum d`` over the entries: a bound that, unlike
    the recursion of :mod:`streamsvd.engine.bound`, forgets what left a window. Entries beyond
    ``LEDGER_SIZE`` are merged two by two (the larger ``L``, the sum of ``d``; the pair
    whose ``d_i (L_(i+1) - L_i)`` is smallest), which keeps the bound valid and the
    state small.

    Attributes
    ----------
    entries : ndarray, shape (q, 2)
        Rows ``(L, d)``, ``L`` increasing.
    """

    entries: np.ndarray

    @classmethod
    def start(cls, m: int, bound: float) -> Ledger:
        """Return the ledger of a compressor whose error is at most ``bound`` on ``m`` columns."""
        rows = [[float(m), bound]] if bound > 0.0 and m > 0 else []
        return cls(np.array(rows, dtype=np.float64).reshape(-1, 2))

    @property
    def total(self) -> float:
        """``sum d``: a bound on ``||E||``."""
        return float(math.fsum(self.entries[:, 1]))

    def removed(self, positions: np.ndarray) -> Ledger:
        """Return the ledger after the current columns at ``positions`` were removed."""
        below = np.searchsorted(np.sort(positions), self.entries[:, 0], side="left")
        e = np.column_stack([self.entries[:, 0] - below, self.entries[:, 1]])
        return Ledger(e[e[:, 0] > 0])

    def scaled(self, factor: float) -> Ledger:
        """Return the ledger after every column was scaled by ``factor`` (forgetting)."""
        return Ledger(self.entries * np.array([1.0, factor]))

    def appended(self, m: int, d: float) -> Ledger:
        """Return the ledger after an update discarded ``d`` on all ``m`` current columns."""
        if d <= 0.0 or m <= 0:
            return self
        e = self.entries
        if e.shape[0] and e[-1, 0] == m:
            e = e.copy()
            e[-1, 1] += d
        else:
            e = np.vstack([e, [[float(m), d]]])
        while e.shape[0] > LEDGER_SIZE:
            # merge the adjacent pair whose merge costs least: entry i's d then lies on
            # L_(i+1) - L_i more columns (it leaves a window that much later)
            i = int(np.argmin(e[:-1, 1] * np.diff(e[:, 0])))
            e = np.vstack([e[:i], [[e[i + 1, 0], e[i, 1] + e[i + 1, 1]]], e[i + 2 :]])
        return Ledger(e)


def bound_after_removal(bound: Bound, ledger: Ledger) -> Bound:
    """Return the bound account once columns were removed (before the removal's own cut).

    Restricting the error to fewer columns never increases its Frobenius norm, so the
    bound stays valid, and the ledger's sum bounds it as well: the smaller is kept. The
    couplings of earlier cuts are not known on the remaining columns (they change when
    rows of the right factor leave), so the coupling account becomes ``inf`` and the next
    cuts add by the triangle inequality (:mod:`streamsvd.engine.bound`); the discarded energy
    is kept (it is not subtracted: the energy of what left is not tracked per column).
    """
    return bound.uncoupled(min(bound.bound, ledger.total))


# ----------------------------------------------------------------- the plan
def plan_remove(
    state: State, positions: np.ndarray, opts: StepOptions, *, prior: Bound, t0: float
) -> Plan:
    """Plan the removal of the current columns at ``positions`` (sorted, distinct).

    The rows of ``Y`` at ``positions`` are read (``O(r w k)``), the core is downdated
    (:func:`downdate`) and then swept and truncated by ``opts`` like any update
    (:func:`streamsvd.engine.update._plan`), ``prior`` being the bound account after the removal
    (:func:`bound_after_removal`). The removed rows stay stored, marked dead, so that a
    store only appends. When a share is below ``EXACT_BELOW``, or once the dead rows
    outnumber the live ones (and 64), the live rows are orthonormalised again and
    written anew instead (``O(m_live w k)``; see the module docstring). Without a target
    error, a term left below ``reject_tol`` times the largest amplitude before the
    removal is cut as by ``eps``, its norm counted in the bound.
    """
    rows = state.rows
    assert rows is not None
    state = state.as_settled()
    phys = physical_rows(rows.dead, positions)
    dd = downdate(rows.V0[phys] @ rows.Vp, state.R)
    dead = np.union1d(rows.dead, phys)
    m = state.m - positions.size
    ext = BasisExtension.empty(state.rank, state.basis.width)
    Y_replace = Y_map = None
    if dd is None or dead.size > max(m, _MIN_DEAD):
        # the remaining rows orthonormalised again (Householder QR): exact whatever the
        # shares, and the dead rows are no longer stored
        Y_replace, T = np.linalg.qr(np.delete(rows.V0, dead, axis=0) @ rows.Vp)
        K = T @ state.R
        logger.debug("remove %d columns: the remaining rows orthonormalised again",
                     positions.size)
    else:
        Y_map, K = dd.S, dd.R
        logger.debug("remove %d columns: smallest remaining share %.3e", positions.size,
                     dd.c_min)
    k_new = K.shape[0]
    # the remaining rows of Y were written relative to the amplitudes before the removal:
    # a term below reject_tol times the largest of them is rounding of what left (a
    # direction the removed columns alone carried), as an absorbed residual that weak is
    # rejected
    opts = cutting_rounding(
        opts, opts.reject_tol * float(np.max(safe_column_norms(state.R), initial=0.0)))
    if k_new < state.rank:
        # directions left with the removed columns: the core has rank k_new at most, and
        # its other terms are rounding; a cap at k_new converges the core and cuts them
        cap = opts.truncation.max_rank
        opts = dataclasses.replace(opts, truncation=dataclasses.replace(
            opts.truncation, max_rank=k_new if cap is None else min(cap, k_new)))
    return _plan(
        state, ext, K, opts, kind="remove", columns=int(positions.size), m=m, t0=t0,
        d_rej=0.0, rejection_root=0.0, prior=prior, Y_replace=Y_replace,
        Y_map=Y_map,
        dead=None if Y_replace is not None else dead,
    )
