"""The small-core step shared by every compressor, wherever its large factors live.

An update of a compressor reduces to a small matrix ``K`` (the right factor's core after
the new rows and directions were appended, ``V_new = Q K`` with ``Q`` orthonormal). This
module runs the rotation sweeps on ``K``, sorts and truncates the terms, measures the
coupling between kept and cut terms, and advances the error bound; the caller applies the
resulting small matrix ``T`` to its large factors (in memory, or chunk by chunk on disk).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError
from scipy.linalg.lapack import dgesdd, dgesdd_lwork

from streamsvd._util.scaling import pow2_exponent, safe_column_norms
from streamsvd.engine.bound import Bound
from streamsvd.linalg.compress import _precondition, newton_schulz
from streamsvd.linalg.rotations import SweepStats, sweep_until

__all__ = [
    "Before",
    "CoreStep",
    "ERROR_MEASURES",
    "Truncation",
    "core_step",
    "error_budget",
    "r_factor",
]

logger = logging.getLogger(__name__)

_EPS = np.finfo(np.float64).eps
_MAX_SWEEPS = 200  # cap of ``sweeps=None`` (to convergence)


def _singular_values(W: np.ndarray) -> np.ndarray:
    """Return the singular values of a small finite matrix: ``scipy.linalg.svdvals``'s call.

    LAPACK's ``dgesdd`` with the workspace it asks for, as ``svdvals`` makes it (the same
    digits), without the checks and dispatch around it (11 microseconds against 21 on a
    20 x 10 coupling of a truncation, one thread).
    """
    work, info = dgesdd_lwork(W.shape[0], W.shape[1], compute_uv=0, full_matrices=1)
    s, info = dgesdd(W, compute_uv=0, lwork=int(work.real), full_matrices=1)[1::2]
    if info != 0:
        raise LinAlgError(f"dgesdd failed (info {info}) on a {W.shape} matrix")
    return s


def r_factor(X: np.ndarray) -> np.ndarray:
    """Return the triangular factor of a Householder QR of ``X`` (``min(rows, cols) x cols``)."""
    if X.size == 0:
        return np.zeros((0, X.shape[1]))
    return np.asarray(np.linalg.qr(X, mode="r"))


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


# what the squares of a term's entries below 2^-511 may lose (_norms_before)
_UNDERFLOW = 2.0**-500
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
        tail = np.append(np.cumsum((a * a)[::-1])[::-1], 0.0)
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
            cut_before = np.ldexp(
                np.sqrt(np.append(np.cumsum((o * o)[::-1])[::-1], 0.0)), e)
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


@dataclass(frozen=True)
class CoreStep:
    """Result of :func:`core_step`.

    Attributes
    ----------
    T : ndarray, shape (p, q)
        Orthonormal columns: the kept terms as combinations of the input terms; the caller
        replaces its small factors ``G`` by ``G @ T``.
    R : ndarray, shape (k, q)
        The new core: ``V_new^T V_new = R^T R``.
    sweeps : int
    max_cosine : float
    cut : int
        Number of terms cut.
    cut_norm : float
        ``sqrt(sum ||v_i||^2)`` over the cut terms.
    coupling_root : float
        Square root of the nuclear norm of ``V_kept^T V_cut`` (zero when truncating at
        convergence).
    cut_before : float or None
        The cut terms' norm in the columns received before the update
        (``||D_cut P_old||``), when ``rows_before`` was given.
    """

    T: np.ndarray
    R: np.ndarray
    sweeps: int
    max_cosine: float
    cut: int
    cut_norm: float
    coupling_root: float
    cut_before: float | None = None


def _norms_before(rows_before: np.ndarray, Qt: np.ndarray, amps_scaled: np.ndarray,
                  e: int, idx: np.ndarray) -> np.ndarray:
    """Return the norms of the terms ``idx`` in the columns received before the update.

    The rotated term ``i`` is ``K Qt[i]^T`` in the rows of ``K`` (the rows of ``Rt`` are
    ``Qt Rt_0``), so its part in those columns is ``rows_before Qt[i]^T``; at most its
    amplitude. Formed at the scale ``2^-e`` of ``Rt``, where no entry exceeds the largest
    amplitude: the squares cannot overflow, and what underflows (entries below
    ``2^-511``) is covered by adding ``2^-500 sqrt(k)``, so each norm is an upper bound.
    """
    P = np.ldexp(rows_before, -e) @ Qt[idx].T
    olds = np.sqrt(np.einsum("ij,ij->j", P, P)) + _UNDERFLOW * math.sqrt(P.shape[0])
    return np.ldexp(np.minimum(olds, amps_scaled[idx]), e)


def core_step(
    K: np.ndarray,
    *,
    rule: str,
    sweeps: int | None,
    m: int,
    truncation: Truncation,
    kind: str,
    before: Before = NOTHING_BEFORE,
    on_sweep: Callable[[int, float], None] | None = None,
    rows_before: np.ndarray | None = None,
) -> CoreStep:
    """Rotate the core ``K`` (``V_new = Q K``) by ``sweeps`` sweeps, sort, truncate.

    When ``truncation.max_rank`` would cut terms that its thresholds keep
    (:meth:`Truncation.needs_convergence`; or a ``target`` error would cut) and the
    sweeps have not converged, Jacobi sweeps go on
    until none rotates: the cut by the cap is then the optimal (Eckart-Young) cut of the
    expansion. The thresholds ``eps`` and ``rtol`` act after ``sweeps`` sweeps, as in
    Algorithm 3.

    Parameters
    ----------
    K : ndarray, shape (k, p)
        The core of the right factor of the extended expansion.
    rule : {"paper", "jacobi"}
    sweeps : int or None
        Number of sweeps (``None``: until a sweep rotates nothing).
    m : int
        Number of snapshots (sets the stopping threshold ``sqrt(m) eps``).
    truncation : Truncation
    kind : str
        Name of the update, for the log.
    before : Before
        The bound account before this update's cut (sizes a ``target`` cut).
    on_sweep : callable, optional
        Called after every sweep with the number of sweeps run and the largest pair
        cosine of the last one (progress of long final sweeps).
    rows_before : ndarray, shape (k_old, p), optional
        The rows of ``K`` (before any reduction, in the same columns) that multiply the
        right factor of the columns received before the update (``Y`` in
        ``blockdiag(Y, I_b) K``, ``Y`` orthonormal): the cut is then sized, and
        ``CoreStep.cut_before`` measured, with each term's norm in those columns
        (:mod:`streamsvd.engine.bound`).
    """
    p = K.shape[1]
    R = r_factor(K) if K.shape[0] > p else K
    e = pow2_exponent(R)
    Rt = np.ascontiguousarray(np.ldexp(R, -e).T)
    Qt = np.eye(p)
    order = np.arange(p, dtype=np.int64)
    max_cos = 0.0

    def after(s: SweepStats, done: int) -> None:
        nonlocal max_cos
        max_cos = s.max_cosine
        if on_sweep is not None:
            on_sweep(done, max_cos)

    tol = math.sqrt(m) * _EPS
    done, converged = 0, p <= 1
    if not converged:
        if sweeps is None:
            _precondition(Rt, Qt)
        _, done, converged = sweep_until(
            Rt, Qt, order, p, rule=rule, eps=0.0, tol=tol,
            limit=_MAX_SWEEPS if sweeps is None else sweeps, after=after,
        )
    amps_scaled = safe_column_norms(Rt.T)
    if not converged and truncation.needs_convergence(
        np.ldexp(amps_scaled, e), before=before, m=m,
        olds=None if rows_before is None else
        lambda idx: _norms_before(rows_before, Qt, amps_scaled, e, idx),
    ):
        # a cut by the rank cap is made on the converged core, so that it is the optimal
        # (Eckart-Young) cut of the expansion: cutting unconverged terms by their norms
        # would drop energy of the leading directions for good
        _precondition(Rt, Qt)
        _, done, _ = sweep_until(Rt, Qt, order, p, rule="jacobi", eps=0.0, tol=tol,
                                 limit=_MAX_SWEEPS, done=done, after=after)
        amps_scaled = safe_column_norms(Rt.T)
    amps = np.ldexp(amps_scaled, e)
    order = np.argsort(-amps, kind="stable")
    def olds(idx: np.ndarray) -> np.ndarray:
        assert rows_before is not None
        return _norms_before(rows_before, Qt, amps_scaled, e, idx)

    keep = truncation.keep_count(
        amps[order], before=before, m=m,
        olds_from=None if rows_before is None else lambda j: olds(order[j:]))
    kept, cut = order[:keep], order[keep:]
    # norms and the coupling are formed on the scaled core and scaled back as roots, so
    # that amplitudes up to 1e300 neither overflow nor lose the bound
    cut_norm = math.ldexp(float(np.linalg.norm(amps_scaled[cut])), e) if cut.size else 0.0
    cut_before = None
    if rows_before is not None:
        cut_before = (math.ldexp(float(np.linalg.norm(np.ldexp(olds(cut), -e))), e)
                      if cut.size else 0.0)
    coupling_root = 0.0
    if cut.size and kept.size:
        W_kd = Rt[kept] @ Rt[cut].T
        # the nuclear norm; of a single row or column it is the Euclidean norm
        nuclear = (float(np.linalg.norm(W_kd)) if min(W_kd.shape) == 1
                   else float(np.sum(_singular_values(W_kd))))
        coupling_root = math.ldexp(math.sqrt(nuclear), e)
    if cut.size:
        logger.info(
            "%s: cut %d terms of norm %.3e (amplitudes %.3e .. %.3e)",
            kind, cut.size, cut_norm, amps[cut].max(), amps[cut].min(),
        )
    # the accumulated rotations drift from orthogonality by about sqrt(rotations) * eps;
    # one Newton-Schulz step, T <- T (3 I - T^T T) / 2, brings them back to eps, so that
    # the orthogonality of U does not grow with the number of updates
    T = newton_schulz(Qt[kept].T)
    return CoreStep(
        T=T, R=np.ldexp(Rt[kept], e).T.copy(), sweeps=done, max_cosine=max_cos,
        cut=int(cut.size), cut_norm=cut_norm, coupling_root=coupling_root,
        cut_before=cut_before,
    )
