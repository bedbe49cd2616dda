"""Compression of an expansion to its SVD by rotation sweeps (Algorithms 2 and 3).

The module also holds the two small steps the engine's core step
(:func:`streamsvd.engine.core.core_step`) shares with the sweeps: the Newton-Schulz step that
brings accumulated rotations back to orthonormal columns, and the preconditioning of the
terms by the core's right singular vectors.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from streamsvd._util.scaling import pow2_exponent, safe_column_norms
from streamsvd._util.validation import check_choice, check_nonnegative, check_positive_int
from streamsvd.errors import InputError
from streamsvd.linalg.expansion import Expansion
from streamsvd.linalg.rotations import RULES, SweepStats, sweep_literal, sweep_until

__all__ = ["CompressResult", "SweepState", "compress", "fix_signs", "newton_schulz"]

logger = logging.getLogger(__name__)

_EPS = np.finfo(np.float64).eps
METHODS = ("fast", "literal")


def newton_schulz(T: np.ndarray) -> np.ndarray:
    """Return ``T (3 I - T^T T) / 2``: one Newton-Schulz step towards orthonormal columns.

    Accumulated rotations drift from orthogonality by about ``sqrt(rotations) eps``; one
    step brings nearly orthonormal columns back to ``eps``.
    """
    return T @ (1.5 * np.eye(T.shape[1]) - 0.5 * (T.T @ T))


def _precondition(Rt: np.ndarray, Qt: np.ndarray) -> None:
    """Rotate the terms onto the right singular vectors of the core, in place.

    The core ``Rt^T`` (``k x p``) is decomposed by LAPACK (``O(k p^2)``); the terms
    rotated by its right singular vectors are orthogonal to working accuracy relative to
    the largest, so that the Jacobi sweeps that follow converge in one or two sweeps
    (they restore the small terms' relative accuracy) instead of tens.
    """
    W = np.linalg.svd(Rt.T, full_matrices=True)[2]  # rows: right singular vectors
    Rt[...] = W @ Rt
    Qt[...] = W @ Qt


@dataclass(frozen=True)
class SweepState:
    """What a ``callback`` receives after each sweep.

    Attributes
    ----------
    sweep : int
        Number of sweeps done so far (1 after the first).
    rank : int
        Number of terms after the sweep.
    indicator : float
        The paper's indicator I (root mean square of the sweep's ``alpha_ij``).
    max_cosine : float
        Largest ``|(v_j|v_i)| / (||v_j|| ||v_i||)`` met in the sweep.
    discarded_energy : float
        Energy ``sum ||v_i||^2`` cut so far.
    """

    sweep: int
    rank: int
    indicator: float
    max_cosine: float
    discarded_energy: float


@dataclass(frozen=True)
class CompressResult:
    """Result of :func:`compress`.

    Attributes
    ----------
    expansion : Expansion
        The compressed expansion, terms sorted by decreasing ``||v_i||``.
    sweeps : int
        Number of sweeps done.
    indicator : ndarray, shape (sweeps,)
        The paper's indicator I per sweep: root mean square of all ``alpha_ij`` (eq. 5)
        computed in the sweep (Fig. 3).
    max_cosine : ndarray, shape (sweeps,)
        ``max |(v_j|v_i)| / (||v_j|| ||v_i||)`` per sweep, the quantity of the stopping test.
    rank : ndarray of int, shape (sweeps,)
        Number of terms after each sweep.
    discarded_energy : float
        ``sum ||v_i||^2`` of the terms cut at threshold ``eps``.
    error_bound : float
        ``sqrt(discarded_energy)``, which equals ``||A_in - A_out||_F`` up to rounding: each
        cut removes terms whose left vectors are orthogonal to all the kept ones, and the
        rotations between cuts only mix kept terms, so the removed parts are mutually
        orthogonal in the Frobenius inner product.
    converged : bool
        Whether the last sweep met the stopping test (no pair above ``tol``).
    """

    expansion: Expansion
    sweeps: int
    indicator: np.ndarray
    max_cosine: np.ndarray
    rank: np.ndarray
    discarded_energy: float
    error_bound: float
    converged: bool


def fix_signs(U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Flip ``(u_i, v_i)`` in place so that the largest-modulus entry of each ``u_i`` is > 0.

    Makes results deterministic across code paths, as scikit-learn's ``svd_flip``.
    Returns the signs applied (+1 or -1 per term).
    """
    if U.shape[1] == 0 or U.shape[0] == 0:
        return np.ones(U.shape[1])
    idx = np.argmax(np.abs(U), axis=0)
    signs = np.sign(U[idx, np.arange(U.shape[1])])
    signs[signs == 0] = 1.0
    U *= signs
    V *= signs
    return signs


def compress(
    expansion: Expansion,
    *,
    rule: str = "paper",
    eps: float = 0.0,
    max_sweeps: int = 100,
    tol: float | None = None,
    method: str = "fast",
    callback: Callable[[SweepState], Any] | None = None,
    precondition: bool = False,
) -> CompressResult:
    """Compress an expansion with orthonormal ``U`` towards its SVD (Algorithms 2 and 3).

    Each sweep visits the pairs ``(i, j)``, ``i = q .. 2``, ``j = 1 .. i-1``, after sorting
    the terms by decreasing ``||v_i||`` and cutting those with ``||v_i|| < eps``, and applies
    the rotation F of eqs (5)-(11) (``rule="paper"``) or the Jacobi rotation that zeroes
    the pair's coupling (``rule="jacobi"``). ``U V^T`` is unchanged except for the cut terms.

    Stopping test (as LAPACK's ``dgesvj``): a pair is rotated only when
    ``|(v_j|v_i)| > tol * ||v_j|| * ||v_i||``, and the iteration stops after the first sweep
    that rotates no pair (``converged``), or after ``max_sweeps`` sweeps.

    Parameters
    ----------
    expansion : Expansion
        ``U`` orthonormal in ``expansion.inner`` (see :func:`orthonormalize`).
    rule : {"paper", "jacobi"}
        Rotation angle: ``alpha`` of eq. (5), which converges as eq. (14) predicts, or the
        one-sided Jacobi angle (quadratic convergence).
    eps : float
        Absolute threshold of Algorithm 3 on ``||v_i||``; 0 gives Algorithm 2.
    max_sweeps : int
        Largest number of sweeps.
    tol : float, optional
        Threshold of the stopping test; default ``sqrt(m) * eps_machine``.
    method : {"fast", "literal"}
        ``"fast"`` rotates a ``p x p`` core and applies the accumulated rotation to
        ``U`` and ``V`` by BLAS-3 products; ``"literal"`` runs Algorithm 3 loop by loop on
        the full factors (the reference). Both give the same iterates up to rounding.
    callback : callable, optional
        ``callback(state)`` with a :class:`SweepState` after each sweep; returning
        ``True`` stops the iteration.
    precondition : bool
        With ``method="fast"``, start the sweeps from a preconditioned core (Drmač and
        Veselić, SIMAX 2008): ``V P = Q_v R`` by a QR with column pivoting, ``R^T = Q_2
        R_2``, and the terms of ``R_2`` rotated onto its right singular vectors
        (LAPACK's ``gesdd``, :func:`_precondition`). The sweeps that follow (the same
        rule, stopping test and cuts) then restore the small terms' accuracy in one or
        two sweeps instead of tens: 2.4x LAPACK's ``gesdd`` on rbs480a (24x without),
        ``bench/studies/tight-targets.md``. The iterates differ from Algorithm 2's,
        so the sweep counts of the paper's study are those without it (the default).
        Used when ``V`` has at least as many rows as there are terms.

    Returns
    -------
    CompressResult
    """
    if not isinstance(expansion, Expansion):
        raise InputError(
            f"`expansion` must be a streamsvd.Expansion; got {type(expansion).__name__}. "
            "Build one with `orthonormalize(U, V)`."
        )
    rule = check_choice(rule, "rule", RULES)
    method = check_choice(method, "method", METHODS)
    eps = check_nonnegative(eps, "eps")
    max_sweeps = int(check_positive_int(max_sweeps, "max_sweeps"))  # type: ignore[arg-type]
    m = expansion.m
    tol = math.sqrt(max(m, 1)) * _EPS if tol is None else check_nonnegative(tol, "tol")
    if method == "literal":
        return _run_literal(expansion, rule=rule, eps=eps, max_sweeps=max_sweeps, tol=tol,
                            callback=callback)
    return _run_fast(expansion, rule=rule, eps=eps, max_sweeps=max_sweeps, tol=tol,
                     callback=callback, precondition=bool(precondition))


def _finish(
    expansion: Expansion,
    U: np.ndarray,
    V: np.ndarray,
    stats: list[SweepStats],
    discarded: float,
    converged: bool,
) -> CompressResult:
    """Sort, fix signs and pack the result; ``discarded`` is the norm of what was cut."""
    # the sweeps order terms by squared norms, which underflow below 1e-154 of the
    # largest amplitude; the final order uses overflow-safe norms
    perm = np.argsort(-safe_column_norms(V), kind="stable")
    U, V = U[:, perm], V[:, perm]
    fix_signs(U, V)
    if not converged:
        logger.info("compress stopped after %d sweeps before convergence", len(stats))
    return CompressResult(
        expansion=Expansion(U, V, inner=expansion.inner),
        sweeps=len(stats),
        indicator=np.array([s.indicator for s in stats]),
        max_cosine=np.array([s.max_cosine for s in stats]),
        rank=np.array([s.rank for s in stats], dtype=np.int64),
        discarded_energy=discarded * discarded,  # inf past 1e154, never an exception
        error_bound=discarded,
        converged=converged,
    )


def _notify(
    callback: Callable[[SweepState], Any] | None, stats: list[SweepStats], energy: float
) -> bool:
    if callback is None:
        return False
    s = stats[-1]
    state = SweepState(len(stats), s.rank, s.indicator, s.max_cosine, energy)
    return bool(callback(state))


def _run_fast(
    expansion: Expansion,
    *,
    rule: str,
    eps: float,
    max_sweeps: int,
    tol: float,
    callback: Callable[[SweepState], Any] | None,
    precondition: bool = False,
) -> CompressResult:
    U, V = expansion.U, expansion.V
    p = expansion.rank
    if p == 0 or expansion.m == 0:
        return _finish(expansion, U[:, :0].copy(), V[:, :0].copy(), [], 0.0, True)
    e = pow2_exponent(V)
    Vs = np.ldexp(V, -e)
    if precondition and Vs.shape[0] >= p:
        Qv, Rt, Qt = _preconditioned(Vs)
        nrm2 = np.einsum("ij,ij->i", Rt, Rt)
    else:
        # sort keys from V itself, kept across sweeps: exact ties order as in the
        # literal path
        nrm2 = np.array([float(Vs[:, c] @ Vs[:, c]) for c in range(p)])
        Qv, R = np.linalg.qr(Vs)
        Rt = np.ascontiguousarray(R.T)
        Qt = np.eye(p)
    order = np.arange(p, dtype=np.int64)
    stats: list[SweepStats] = []
    discarded = 0.0  # kept as a norm: amplitudes from 1e-300 to 1e300 stay representable

    def after(s: SweepStats, done: int) -> bool:
        nonlocal discarded
        discarded = math.hypot(discarded, math.ldexp(math.sqrt(s.cut_energy), e))
        stats.append(s)
        return _notify(callback, stats, discarded * discarded)

    q, _, converged = sweep_until(Rt, Qt, order, p, rule=rule, eps=math.ldexp(eps, -e),
                                  tol=tol, limit=max_sweeps, nrm2=nrm2, after=after)
    sel = order[:q]
    U_out = U @ newton_schulz(Qt[sel].T)
    V_out = np.ldexp(Qv @ Rt[sel].T, e)
    return _finish(expansion, U_out, V_out, stats, discarded, converged)


def _preconditioned(Vs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``(Q_v, Rt, Qt)``, the terms of ``U V^T`` as ``(U Qt^T) (Q_v Rt^T)^T``.

    ``V P = Q_v R`` (column pivoting), ``R^T = Q_2 R_2``: ``U V^T = (U P Q_2) (Q_v
    R_2^T)^T``, so the terms' rows are ``Rt = R_2`` and ``Qt = (P Q_2)^T``; then both are
    rotated onto the right singular vectors of the core (:func:`_precondition`). Every
    factor is orthogonal, so ``U V^T`` is unchanged up to rounding (``eps ||V||``).
    """
    import scipy.linalg

    Qv, R, piv = scipy.linalg.qr(Vs, pivoting=True, mode="economic", check_finite=False)
    Q2, R2 = np.linalg.qr(R.T)
    inv = np.empty_like(piv)
    inv[piv] = np.arange(piv.size)
    Rt = np.ascontiguousarray(R2)
    Qt = np.ascontiguousarray(Q2[inv].T)
    _precondition(Rt, Qt)
    return Qv, Rt, Qt


def _run_literal(
    expansion: Expansion,
    *,
    rule: str,
    eps: float,
    max_sweeps: int,
    tol: float,
    callback: Callable[[SweepState], Any] | None,
) -> CompressResult:
    U = np.array(expansion.U)
    V = np.array(expansion.V)
    stats: list[SweepStats] = []
    energy = 0.0
    converged = expansion.rank == 0
    while not converged and len(stats) < max_sweeps:
        U, V, s = sweep_literal(U, V, rule=rule, eps=eps, tol=tol)
        energy += s.cut_energy
        stats.append(s)
        converged = s.rotations == 0
        if _notify(callback, stats, energy):
            break
    return _finish(expansion, U, V, stats, math.sqrt(energy), converged)
