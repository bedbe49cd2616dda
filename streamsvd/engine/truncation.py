"""Which terms survive a cut, and the bound the cut leaves.

A :class:`Truncation` keeps the terms above ``eps`` and ``rtol``, at most ``max_rank``
of them, and with a ``target`` error the fewest whose guaranteed bound stays within the
share of the budget (:func:`error_budget`); :class:`Before` is the bound's account of an
update before its cut (:mod:`streamsvd.engine.bound`), which sizes such a cut. The cut
itself is made on the converged core by :func:`streamsvd.engine.core.core_step`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from streamsvd._util.scaling import pow2_exponent
from streamsvd.engine.bound import Bound

__all__ = ["ERROR_MEASURES", "NOTHING_BEFORE", "Before", "Truncation", "error_budget"]


@dataclass(frozen=True)
class Before:
    """The error-bound account of an update before its cut.

    Attributes
    ----------
    prior : Bound
        The account before the update.
    decided : float
        The norm this update discards whatever it cuts (rejected residuals, a rounding
        allowance), orthogonal to every cut term.
    overlapping : bool
        Whether the update touches columns received before (``add``).
    decided_new : bool
        Whether ``decided`` lies in the update's own new columns (the residuals an
        absorbed block rejects), where the error before the update is zero.
    """

    prior: Bound = Bound()
    decided: float = 0.0
    overlapping: bool = False
    decided_new: bool = False

    def bounds(self, cut_norms: np.ndarray, cut_before: np.ndarray | None = None
               ) -> np.ndarray:
        """Return the bound after the update for each candidate norm of the cut terms.

        ``cut_before``: each candidate cut's norm in the columns received before the
        update (``||D_cut P_old||``, :mod:`streamsvd.engine.bound`), when known.
        """
        discarded = np.hypot(self.decided, cut_norms)
        old = None
        if cut_before is not None:
            old = cut_before if self.decided_new else np.hypot(self.decided, cut_before)
        return self.prior.after(discarded, overlapping=self.overlapping, before=old)


NOTHING_BEFORE = Before()  # the account of a compressor that discarded nothing yet


@dataclass(frozen=True)
class Truncation:
    """Which terms survive an update, after its sweeps.

    A term is kept when ``||v_i|| >= eps``, ``||v_i|| >= rtol * ||v_1||`` and it is among
    the ``max_rank`` largest; terms of amplitude exactly zero carry nothing and are dropped.

    With a ``target`` error, the fewest terms are kept whose error bound stays within
    ``share`` of the budget (:func:`error_budget`): the smallest terms are cut while the
    bound after the cut fits, as :meth:`streamsvd.engine.bound.Bound.after` gives it from the
    account before the update (:class:`Before`). The cut is made on the converged core,
    so its terms are orthogonal to the kept ones; how the bound then grows depends on the
    cuts before it (the Pythagorean rule when their couplings vanish, the triangle
    inequality after an ``add`` or a removal), and the cut is sized by the same rule.
    """

    eps: float = 0.0
    rtol: float | None = None
    max_rank: int | None = None
    target: float | None = None
    measure: str = "relative"
    share: float = 1.0

    def keep_count(
        self, amps_sorted: np.ndarray, *, before: Before = NOTHING_BEFORE, m: int = 0,
        olds_from: Callable[[int], np.ndarray] | None = None,
    ) -> int:
        """Return how many leading terms are kept (amplitudes sorted decreasingly).

        ``before`` is the bound account before this cut and ``m`` the number of snapshots
        (for a ``target``); ``olds_from(j)``, when known, the norms of the terms ``j,
        j + 1, ...`` (in this order) in the columns received before the update
        (:meth:`Before.bounds`), asked only for the terms a cut may drop.
        """
        if amps_sorted.size == 0:
            return 0
        thresh = self.eps
        if self.rtol is not None:
            thresh = max(thresh, self.rtol * float(amps_sorted[0]))
        keep = int(np.count_nonzero(amps_sorted >= thresh)) if thresh > 0 else amps_sorted.size
        keep = min(keep, int(np.count_nonzero(amps_sorted > 0)))
        if self.target is not None:
            keep = min(keep, self._within_budget(amps_sorted, before, m, olds_from))
        if self.max_rank is not None:
            keep = min(keep, self.max_rank)
        return keep

    def _within_budget(self, amps_sorted: np.ndarray, before: Before, m: int,
                       olds_from: Callable[[int], np.ndarray] | None) -> int:
        """Return the fewest leading terms whose cut keeps the bound within the share."""
        assert self.target is not None
        e = pow2_exponent(amps_sorted)
        a = np.ldexp(amps_sorted, -e)
        # tail[k] = ||terms k, k+1, ...||^2: the energy cut when k terms are kept
        tail = _tails(a)
        norms = np.ldexp(np.sqrt(tail), e)
        if olds_from is None:
            fits = self._fits(before.bounds(norms), tail, e, m)
        else:
            # a cut's part in the columns before lies between none and the whole cut,
            # and its bound rises with it: one evaluation of both ends brackets the first
            # cut that fits, and only a cut between them needs the terms' parts, measured
            # for the terms from the lower end on
            c = norms.size
            ends = self._fits(before.bounds(np.concatenate([norms, norms]),
                                            np.concatenate([0.0 * norms, norms])),
                              np.concatenate([tail, tail]), e, m)
            low, high = np.flatnonzero(ends[:c]), np.flatnonzero(ends[c:])
            if low.size == 0:
                return amps_sorted.size
            lo, hi = int(low[0]), int(high[0]) if high.size else c
            if lo == hi:
                return lo
            o = np.ldexp(olds_from(lo), -e)
            cut_before = np.ldexp(np.sqrt(_tails(o)), e)
            fits = np.zeros(c, dtype=bool)
            fits[lo:hi] = self._fits(before.bounds(norms[lo:hi], cut_before[:hi - lo]),
                                     tail, e, m, rows=slice(lo, hi))
            fits[hi:] = True
        ok = np.flatnonzero(fits)
        return int(ok[0]) if ok.size else amps_sorted.size

    def _fits(self, bound: np.ndarray, tail: np.ndarray, e: int, m: int,
              rows: slice = slice(None)) -> np.ndarray:
        """Whether each candidate's bound (its cut ``tail[rows]``, scaled by ``4^-e``) fits."""
        assert self.target is not None
        if self.measure == "relative":
            # ||A|| >= ||U V^T|| - bound, so bound (1 + s eps) <= s eps ||U V^T|| makes
            # bound <= s eps ||A||, whatever the discarded part
            se = self.share * self.target
            kept = np.ldexp(np.sqrt(np.maximum(tail[0] - tail[rows], 0.0)), e)
            return bound * (1.0 + se) <= se * kept
        return bound <= self.share * error_budget(self.target, self.measure, m)

    def needs_convergence(
        self, amps: np.ndarray, *, before: Before, m: int,
        olds: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> bool:
        """Whether a cut by ``max_rank`` or by the ``target`` would drop terms.

        Such a cut is made on the converged core (the optimal cut of the expansion).
        ``amps`` holds the amplitudes, in any order; ``olds(idx)``, when known, the norms
        of the terms ``idx`` in the columns received before the update.
        """
        if self.max_rank is None and self.target is None:
            return False
        order = np.argsort(-amps, kind="stable")
        amps_sorted = amps[order]
        unbounded = Truncation(self.eps, self.rtol)
        kept = self.keep_count(amps_sorted, before=before, m=m,
                               olds_from=None if olds is None else lambda j: olds(order[j:]))
        return kept < unbounded.keep_count(amps_sorted)


def _tails(x: np.ndarray) -> np.ndarray:
    """Return ``t[k] = sum_{i >= k} x_i^2`` for ``k = 0 .. len(x)`` (``t[len(x)] = 0``)."""
    return np.append(np.cumsum((x * x)[::-1])[::-1], 0.0)


def error_budget(target: float, measure: str, m: int, data_norm: float = 0.0) -> float:
    """Return the bound on ``||A - U V^T||_F`` (in ``M``) that a target error allows.

    ``"absolute"``: ``target``; ``"mean_l2"`` (pyMOR HAPOD's measure,
    ``sqrt(sum_j ||a_j - P a_j||_M^2 / m)``): ``target sqrt(m)``; ``"relative"``:
    ``target ||A||_F``, with ``data_norm`` standing for ``||A||_F``.
    """
    if measure == "absolute":
        return target
    if measure == "mean_l2":
        return target * math.sqrt(m)
    return target * data_norm


ERROR_MEASURES = ("relative", "mean_l2", "absolute")
