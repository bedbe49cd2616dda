"""The small-core step shared by every compressor, wherever its large factors live.

An update of a compressor reduces to a small matrix ``K`` (the right factor's core after
the new rows and directions were appended, ``V_new = Q K`` with ``Q`` orthonormal). This
module runs the rotation sweeps on ``K``, sorts and truncates the terms (which ones:
:mod:`streamsvd.engine.truncation`), and measures the cut's norm, its part in the columns
received before the update and the coupling between kept and cut terms, from which the
caller advances the error bound; the caller applies the resulting small matrix ``T`` to
its large factors (in memory, or chunk by chunk on disk).
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
from streamsvd.engine.truncation import NOTHING_BEFORE, Before, Truncation
from streamsvd.errors import FloatRangeError
from streamsvd.linalg.compress import _precondition, newton_schulz
from streamsvd.linalg.rotations import SweepStats, sweep_until

__all__ = ["CoreStep", "core_qr", "core_step", "qr_factors", "r_factor"]

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


# entries beyond 2^±500 are scaled first: LAPACK's Householder vector divides by
# alpha - beta, which overflows for entries near 1e308 (|alpha| + ||x|| > 2^1024)
_QR_SAFE = 500


def r_factor(X: np.ndarray) -> np.ndarray:
    """Return the triangular factor of a Householder QR of ``X`` (``min(rows, cols) x cols``).

    Entries beyond ``2^±500`` are scaled by a power of two first (exact), so that entries
    near the ends of the range give ``R`` to rounding wherever ``R`` is representable
    (elsewhere it holds infinities, and the update is refused:
    :class:`~streamsvd.errors.FloatRangeError`).
    """
    if X.size == 0:
        return np.zeros((0, X.shape[1]))
    return _householder(X, want_q=False)[1]


def qr_factors(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(Q, R)`` of a Householder QR of ``X``, scaled as :func:`r_factor` is."""
    Q, R = _householder(X, want_q=True)
    assert Q is not None
    return Q, R


def _householder(X: np.ndarray, *, want_q: bool) -> tuple[np.ndarray | None, np.ndarray]:
    """Return ``(Q or None, R)`` of ``X``, through a power-of-two scaling beyond 2^±500."""
    e = pow2_exponent(X)
    scaled = X if abs(e) <= _QR_SAFE else np.ldexp(X, -e)
    if want_q:
        Q, R = np.linalg.qr(scaled)
    else:
        Q, R = None, np.asarray(np.linalg.qr(scaled, mode="r"))
    if scaled is not X:
        with np.errstate(over="ignore"):  # beyond the range: the update is refused
            R = np.ldexp(R, e)
    return Q, R


def core_qr(K: np.ndarray, *, want_q: bool) -> tuple[np.ndarray | None, np.ndarray]:
    """Return ``(Q, R)`` with ``K = Q R``, ``R`` no taller than wide (``Q = None``: ``I``).

    A core taller than wide is reduced by a Householder QR, whose ``Q`` (formed only when
    the right vectors are kept) is orthonormal to rounding level.
    """
    if K.shape[0] <= K.shape[1]:
        return None, K
    if not want_q:
        return None, r_factor(K)
    return qr_factors(K)


def _check_range(norm_scaled: float, e: int) -> None:
    """Raise :class:`FloatRangeError` unless ``norm_scaled 2^e`` is a finite float64.

    ``norm_scaled 2^e`` is the norm of the expansion (its amplitudes'): every norm,
    energy share and bound the truncation and the measures form lies below it.
    """
    if norm_scaled == 0.0 or (math.isfinite(norm_scaled)
                              and math.frexp(norm_scaled)[1] + e <= 1024):
        return
    raise FloatRangeError("the update")  # the facade names its argument


# what the squares of a term's entries below 2^-511 may lose (_norms_before)
_UNDERFLOW = 2.0**-500


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
    if not np.isfinite(R).all():
        raise FloatRangeError("the update")  # the facade names its argument
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
    _check_range(float(np.linalg.norm(amps_scaled)), e)
    # each term's norm in the columns before the update, at the current rotation
    olds = (None if rows_before is None else
            lambda idx, rows=rows_before: _norms_before(rows, Qt, amps_scaled, e, idx))
    if not converged and truncation.needs_convergence(
        np.ldexp(amps_scaled, e), before=before, m=m, olds=olds,
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
    keep = truncation.keep_count(
        amps[order], before=before, m=m,
        olds_from=None if olds is None else lambda j: olds(order[j:]))
    kept, cut = order[:keep], order[keep:]
    # norms and the coupling are formed on the scaled core and scaled back as roots, so
    # that amplitudes up to 1e300 neither overflow nor lose the bound
    cut_norm = math.ldexp(float(np.linalg.norm(amps_scaled[cut])), e) if cut.size else 0.0
    cut_before = None
    if olds is not None:
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
