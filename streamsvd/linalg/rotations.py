"""The compression function F (eqs 5-11), its dynamics (eq. 14) and rotation sweeps.

F acts on two terms ``u_j v_j^T + u_i v_i^T`` of an expansion with orthonormal left
vectors and ``||v_j|| >= ||v_i||``. With ``alpha = (v_j | v_i) / (v_j | v_j)`` (eq. 5) and
``rho = sqrt(1 + alpha^2)`` it returns

    u_j <- (u_j + alpha u_i) / rho,     v_j <- (v_j + alpha v_i) / rho,
    u_i <- (u_i - alpha u_j) / rho,     v_i <- (v_i - alpha v_j) / rho,

which is the plane rotation of eq. (19) with ``tan(theta) = alpha`` applied to both
factors, so the product ``U V^T`` is unchanged and ``U`` stays orthonormal. The
``"jacobi"`` rule uses instead the angle that zeroes the new coupling ``(v_j | v_i)``
(one-sided Jacobi, as LAPACK's ``dgesvj``).

Two implementations of the sweep of Algorithms 2 and 3 are kept:

* :func:`sweep_literal` transcribes Algorithm 3 loop by loop on the full factors; it is
  the reference.
* :func:`sweep_core` runs the same rotations on a small core. Writing ``V = Q_v R`` with
  ``Q_v`` orthonormal, every inner product ``(v_j | v_i)`` equals ``(r_j | r_i)``, so the
  rotation angles can be computed on the columns of ``R`` (``k x p``, ``k <= p``) and
  accumulated in a ``p x p`` orthogonal matrix that is applied to ``U`` and ``Q_v`` once,
  by BLAS-3 products. The two give the same iterates up to rounding.
"""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "PairDynamics",
    "PairRotation",
    "SweepStats",
    "load_kernels_in_background",
    "pair_dynamics",
    "rotate_pair",
    "rotation_tangent",
    "sweep_core",
    "sweep_until",
    "sweep_literal",
]

RULES = ("paper", "jacobi")


@dataclass(frozen=True)
class PairRotation:
    """The new pair returned by F (eq. 4) and the coefficient ``alpha`` of eq. (5)."""

    u1: np.ndarray
    v1: np.ndarray
    u2: np.ndarray
    v2: np.ndarray
    alpha: float


def rotate_pair(u1: np.ndarray, v1: np.ndarray, u2: np.ndarray, v2: np.ndarray) -> PairRotation:
    """Apply the compression function F of eq. (4), literally as eqs (5)-(11).

    Parameters
    ----------
    u1, u2 : ndarray, shape (n,)
        Orthonormal left vectors.
    v1, v2 : ndarray, shape (m,)
        Right vectors with ``||v1|| >= ||v2|| > 0`` (conditions 3).

    Returns
    -------
    PairRotation
        ``(u1~, v1~, u2~, v2~)`` with ``u1~ v1~^T + u2~ v2~^T = u1 v1^T + u2 v2^T``,
        ``(u~i | u~j) = delta_ij`` and a smaller coupling ``(v1~ | v2~)``, and ``alpha``.
    """
    u1, v1, u2, v2 = (np.asarray(x, dtype=np.float64) for x in (u1, v1, u2, v2))
    alpha = float(v1 @ v2) / float(v1 @ v1)  # eq. (5)
    a2 = 1.0 + alpha * alpha
    gamma = math.sqrt(a2)
    u1_bar = u1 + alpha * u2  # eq. (6)
    v1_bar = v1 / a2 + alpha * v2 / a2  # eq. (7)
    u2_bar = -alpha * u1 / a2 + u2 / a2  # eq. (8)
    v2_bar = v2 - alpha * v1  # eq. (9)
    # ||u1_bar|| = gamma (eq. 10) and ||u2_bar|| = 1 / gamma (eq. 11)
    return PairRotation(u1_bar / gamma, gamma * v1_bar, gamma * u2_bar, v2_bar / gamma, alpha)


@dataclass(frozen=True)
class PairDynamics:
    """Iterates of eq. (14) and their invariants.

    Attributes
    ----------
    eta, alpha : ndarray, shape (steps + 1,)
        ``eta_xi = ||v2||^2 / ||v1||^2`` and ``alpha_xi`` for ``xi = 0 .. steps``.
    delta : float
        The preserved quantity ``2 delta = eta_xi + 1 / eta_{xi+1}
        = (1 + 2 alpha_0^2 + eta_0^2) / (eta_0 - alpha_0^2)``.
    eta_limit : float
        The asymptotic rate ``eta = delta - sqrt(delta^2 - 1)``.
    """

    eta: np.ndarray
    alpha: np.ndarray
    delta: float
    eta_limit: float


def pair_dynamics(eta0: float, alpha0: float, steps: int) -> PairDynamics:
    """Iterate the recursion (14) of a rank-2 expansion from ``(eta0, alpha0)``.

    ``eta_{xi+1} = (eta_xi - alpha_xi^2) / (1 + alpha_xi^2 (2 + eta_xi))`` and
    ``alpha_{xi+1} = eta_{xi+1} alpha_xi``, valid for ``0 <= alpha_0^2 < eta_0 <= 1``
    (inequality 13, strict so that ``delta`` is finite).
    """
    if not (0.0 <= alpha0 * alpha0 < eta0 <= 1.0):
        from streamsvd.errors import InputError

        raise InputError(
            f"`eta0` and `alpha0` must satisfy 0 <= alpha0^2 < eta0 <= 1 (inequality 13); "
            f"got eta0 = {eta0!r}, alpha0 = {alpha0!r}."
        )
    eta = np.empty(steps + 1)
    alpha = np.empty(steps + 1)
    eta[0], alpha[0] = eta0, alpha0
    for k in range(steps):
        a2 = alpha[k] * alpha[k]
        eta[k + 1] = (eta[k] - a2) / (1.0 + a2 * (2.0 + eta[k]))
        alpha[k + 1] = eta[k + 1] * alpha[k]
    delta = 0.5 * (1.0 + 2.0 * alpha0**2 + eta0**2) / (eta0 - alpha0**2)
    eta_limit = delta - math.sqrt(max(delta * delta - 1.0, 0.0))
    return PairDynamics(eta, alpha, float(delta), float(eta_limit))


def rotation_tangent(wjj: float, wii: float, wij: float, jacobi: bool) -> float:
    """Return ``tan(theta)`` of the rotation of a pair with Gram entries ``wjj >= wii, wij``.

    The compiled kernel of the sweeps (:func:`streamsvd.linalg.sweep_kernels.rotation_tangent`,
    where the two rules are written), called from Python.
    """
    from streamsvd.linalg.sweep_kernels import rotation_tangent as kernel

    return float(kernel(wjj, wii, wij, jacobi))


@dataclass(frozen=True)
class SweepStats:
    """What one sweep did.

    Attributes
    ----------
    rank : int
        Number of terms kept after the sweep's cuts.
    indicator : float
        Root mean square of every ``alpha_ij`` of eq. (5) met in the sweep (the paper's
        indicator I, Fig. 3).
    max_cosine : float
        ``max |(v_j | v_i)| / (||v_j|| ||v_i||)`` over the pairs met (before rotation).
    rotations : int
        Number of rotations applied (pairs above the threshold).
    cut_energy : float
        ``sum ||v_i||^2`` of the terms cut at threshold ``eps`` during the sweep.
    """

    rank: int
    indicator: float
    max_cosine: float
    rotations: int
    cut_energy: float


def sweep_core(
    Rt: np.ndarray,
    Qt: np.ndarray,
    order: np.ndarray,
    q: int,
    *,
    rule: str,
    eps: float,
    tol: float,
    nrm2: np.ndarray | None = None,
) -> SweepStats:
    """One sweep of Algorithm 3 on a small core, in place.

    Parameters
    ----------
    Rt : ndarray, shape (p, k), C-contiguous
        Row ``r`` holds the core vector of one term: ``V = Q_v Rt.T`` with ``Q_v``
        orthonormal. Scaled so that its squared norms are representable.
    Qt : ndarray, shape (p, p0), C-contiguous
        Row ``r`` accumulates the rotations of that term.
    order : ndarray of int64, shape (p,)
        ``order[:q]`` lists the rows of the live terms by decreasing amplitude.
    q : int
        Number of live terms.
    rule : {"paper", "jacobi"}
        The rotation angle (module docstring).
    eps : float
        Cut threshold on ``||v_i||`` in the units of ``Rt`` (Algorithm 3).
    tol : float
        A pair is rotated only when ``|(v_j|v_i)| > tol ||v_j|| ||v_i||``.
    nrm2 : ndarray, shape (p,), optional
        Squared norms of the terms, the sort keys, updated in place (only the rotated
        terms' keys change). Passing the keys of the full ``V`` and keeping them across
        sweeps makes exact ties sort as in :func:`sweep_literal`; by default they are
        computed from ``Rt``.
    """
    from streamsvd.linalg.sweep_kernels import sweep_rows  # numba, imported at the first sweep

    if nrm2 is None:
        nrm2 = np.einsum("ij,ij->i", Rt, Rt)
    out = np.zeros(4)
    q = int(sweep_rows(Rt, Qt, order, q, nrm2, rule == "jacobi", eps * eps, tol, out))
    return SweepStats(q, float(out[0]), float(out[1]), int(out[2]), float(out[3]))


_loading: threading.Thread | None = None


def load_kernels_in_background() -> threading.Thread | None:
    """Start loading the compiled sweep kernels in a daemon thread (once per process).

    A process's first sweep loads them from numba's cache (0.2-0.4 s: numba's typing
    registries and the cached code), and on a stream whose updates all take the Gram
    path that first sweep is the final one (:meth:`~streamsvd.StreamCompressor.finalize`):
    a driver calls this when a core is free, so that the load overlaps an update. A
    sweep that starts before the load ends waits for it (numba's compiler lock); nothing
    else changes. Returns the loading thread (started now or before), or None when a
    sweep loaded them.
    """
    global _loading
    kernels = sys.modules.get("streamsvd.linalg.sweep_kernels")
    if _loading is None and (kernels is None or not kernels.sweep_rows.signatures):
        _loading = threading.Thread(target=_sweep_once, name="streamsvd-kernels",
                                    daemon=True)
        _loading.start()
    return _loading


def _sweep_once() -> None:
    """Run one sweep on a 2 x 2 core: the argument types of every sweep of the package."""
    Rt, Qt = np.eye(2), np.eye(2)
    sweep_core(Rt, Qt, np.arange(2, dtype=np.int64), 2, rule="jacobi", eps=0.0, tol=0.0)


def sweep_literal(
    U: np.ndarray,
    V: np.ndarray,
    *,
    rule: str,
    eps: float,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, SweepStats]:
    """One sweep of Algorithm 3, transcribed loop by loop on the full factors.

    The reference implementation: ``U`` (``n x p``) and ``V`` (``m x p``) are copied,
    sorted by decreasing ``||v_i||``, cut at ``eps`` and rotated pair by pair exactly as
    Algorithm 3 (with Algorithm 2 when ``eps = 0``). Pairs whose cosine is at most ``tol``
    are skipped, as in :func:`sweep_core`.

    Returns
    -------
    U, V : ndarray
        The new factors, sorted, with the cut terms removed.
    stats : SweepStats
    """
    U = np.array(U, dtype=np.float64)
    V = np.array(V, dtype=np.float64)
    cols_u = [U[:, c].copy() for c in range(U.shape[1])]
    cols_v = [V[:, c].copy() for c in range(V.shape[1])]
    jacobi = rule == "jacobi"
    alphas: list[float] = []
    max_cos = 0.0
    n_rot = 0
    cut = 0.0

    def sort_and_cut() -> float:
        keys = sorted(range(len(cols_v)), key=lambda c: -float(cols_v[c] @ cols_v[c]))
        cols_u[:] = [cols_u[c] for c in keys]
        cols_v[:] = [cols_v[c] for c in keys]
        removed = 0.0
        while cols_v and float(cols_v[-1] @ cols_v[-1]) < eps * eps:
            removed += float(cols_v[-1] @ cols_v[-1])
            cols_u.pop()
            cols_v.pop()
        return removed

    i = len(cols_v) - 1
    while i >= 1:
        cut += sort_and_cut()
        i = min(i, len(cols_v) - 1)
        if i < 1:
            break
        for j in range(i):
            vj, vi = cols_v[j], cols_v[i]
            wjj, wii, wij = float(vj @ vj), float(vi @ vi), float(vj @ vi)
            if wjj == 0.0:
                continue
            alpha = wij / wjj  # alpha_ij of Algorithm 3
            alphas.append(alpha)
            if wii == 0.0:
                continue
            cosine = abs(wij) / (math.sqrt(wjj) * math.sqrt(wii))
            max_cos = max(max_cos, cosine)
            if cosine <= tol:
                continue
            t = alpha if not jacobi else float(rotation_tangent(wjj, wii, wij, True))
            rho = math.sqrt(1.0 + t * t)
            uj = cols_u[j] / rho + (t / rho) * cols_u[i]
            cols_u[i] = rho * cols_u[i] - t * uj
            cols_u[j] = uj
            vj = cols_v[j] / rho + (t / rho) * cols_v[i]
            cols_v[i] = rho * cols_v[i] - t * vj
            cols_v[j] = vj
            n_rot += 1
        i -= 1
    cut += sort_and_cut()
    n, m = U.shape[0], V.shape[0]
    U_out = np.column_stack(cols_u) if cols_u else np.zeros((n, 0))
    V_out = np.column_stack(cols_v) if cols_v else np.zeros((m, 0))
    indicator = math.sqrt(sum(a * a for a in alphas) / len(alphas)) if alphas else 0.0
    return U_out, V_out, SweepStats(len(cols_v), indicator, max_cos, n_rot, cut)


def sweep_until(
    Rt: np.ndarray,
    Qt: np.ndarray,
    order: np.ndarray,
    q: int,
    *,
    rule: str,
    eps: float,
    tol: float,
    limit: int,
    done: int = 0,
    nrm2: np.ndarray | None = None,
    after: Callable[[SweepStats, int], bool | None] | None = None,
) -> tuple[int, int, bool]:
    """Run sweeps (:func:`sweep_core`) until one rotates nothing or ``limit`` sweeps ran.

    The one sweep loop of the package: :func:`streamsvd.linalg.compress` and the update step's
    core (:func:`streamsvd.engine.core.core_step`) both drive it. ``done`` sweeps already ran
    (they count towards ``limit``); ``after(stats, done)`` is called after every sweep
    and stops the loop when it returns True. Returns the number of live terms, of sweeps
    run (with ``done``) and whether the last sweep rotated nothing.
    """
    converged = False
    while done < limit:
        s = sweep_core(Rt, Qt, order, q, rule=rule, eps=eps, tol=tol, nrm2=nrm2)
        q = s.rank
        done += 1
        converged = s.rotations == 0
        if (after is not None and after(s, done)) or converged:
            break
    return q, done, converged
