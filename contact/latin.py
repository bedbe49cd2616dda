"""The LATIN solver: local and global stages iterated over the whole space-time domain.

``solve(problem, method=...)`` runs one of three variants that share the local stage
(:mod:`contact.local`), the factorised global operator and the indicator
(:mod:`contact.globalstage`):

* ``"latin"`` -- principles P1 and P2: the global stage solves for the full space-time
  displacement field (one back-substitution per instant and iteration);
* ``"latin-p3"`` -- P3: the displacement correction is a sum of orthonormal space modes
  times time functions (:mod:`contact.pgd`);
* ``"latin-pgd"`` -- P3 with block enrichment (:mod:`contact.blockpgd`): every iteration
  updates all time functions on the basis; when the reduced stage departs from the full
  one, a block of space modes from a randomized range finder is added and a
  :class:`streamsvd.StreamCompressor` compresses the expansion (one rotation sweep,
  truncation in the indicator's metric).

Each iteration ``i``: local stage ``s_hat_i`` from ``s_{i-1}`` (direction E+), global stage
``s_i`` from ``s_hat_i`` (direction E-), indicator ``eta_i`` between ``s_i`` and
``s_hat_i`` (:func:`contact.globalstage.indicator`). The iteration stops when
``eta_i <= tol`` or after ``max_iter`` iterations.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from streamsvd import Expansion

from ._threads import blas_threads as limit_blas_threads
from .errors import SolverOptionError
from .globalstage import GlobalStage, default_search_direction, indicator_parts
from .local import local_stage
from .problem import Problem
from .result import IterationState, LatinResult

__all__ = ["METHODS", "TRUNC_PER_TOL", "solve"]

log = logging.getLogger(__name__)

METHODS = ("latin", "latin-p3", "latin-pgd")
# the default truncation of LATIN-PGD is tol / TRUNC_PER_TOL (see `solve`)
TRUNC_PER_TOL = 10.0


class _FullField:
    """Global stage of the ``"latin"`` method: the full space-time correction field."""

    def __init__(self, stage: GlobalStage) -> None:
        self.stage = stage
        self.y = np.zeros((len(stage.free), stage.problem.m))

    @property
    def basis_size(self) -> int:
        return self.stage.problem.m

    def modes(self) -> Callable[[], None]:
        return lambda: None

    def update(self, Z: np.ndarray) -> np.ndarray:
        self.y = self.stage.solve(self.stage.G @ Z)
        return self.stage.Cf @ self.y + self.stage.w_lift

    def finish(self) -> dict[str, Any]:
        return {}


def _check_pgd_options(block: int, power: int, enrich: str,
                       enrich_tol: float | None) -> dict[str, Any]:
    from .blockpgd import ENRICH_RULES, ENRICH_TOL

    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
        raise SolverOptionError(f"`block` must be a positive integer; got {block!r}.")
    if isinstance(power, bool) or not isinstance(power, (int, np.integer)) or power < 0:
        raise SolverOptionError(f"`power` must be a non-negative integer; got {power!r}.")
    if enrich not in ENRICH_RULES:
        raise SolverOptionError(f"`enrich` must be one of {ENRICH_RULES}; got {enrich!r}.")
    if enrich_tol is None:
        enrich_tol = ENRICH_TOL[enrich]
    elif not (isinstance(enrich_tol, (int, float)) and enrich_tol > 0):
        raise SolverOptionError(
            f"`enrich_tol` must be a positive number; got {enrich_tol!r}.")
    return {"block": int(block), "power": int(power), "enrich": enrich,
            "enrich_tol": float(enrich_tol)}


def _check_options(
    problem: Problem, method: str, tol: float, max_iter: int, k: float | None
) -> tuple[str, float, int, float]:
    if not isinstance(problem, Problem):
        raise SolverOptionError(
            f"`problem` must be a contact.Problem; got {type(problem).__name__}. Build one "
            "with contact.billet(...) or contact.block(...)."
        )
    if method not in METHODS:
        raise SolverOptionError(f"`method` must be one of {METHODS}; got {method!r}.")
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise SolverOptionError(f"`tol` must be a positive number; got {tol!r}.")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise SolverOptionError(f"`max_iter` must be a positive integer; got {max_iter!r}.")
    if k is None:
        k = default_search_direction(problem)
    elif not (isinstance(k, (int, float)) and k > 0):
        raise SolverOptionError(f"`k` must be a positive number; got {k!r}.")
    return method, float(tol), int(max_iter), float(k)


def solve(
    problem: Problem,
    method: str = "latin",
    *,
    tol: float = 1e-6,
    max_iter: int = 2000,
    k: float | None = None,
    callback: Callable[[IterationState], Any] | None = None,
    trunc: float | None = None,
    enrich_ratio: float = 0.5,
    fixed_point: int = 4,
    block: int = 32,
    power: int = 0,
    enrich: str = "departure",
    enrich_tol: float | None = None,
    blas_threads: int | None = 1,
) -> LatinResult:
    """Solve a frictional contact problem with a LATIN variant.

    Parameters
    ----------
    problem : Problem
    method : {"latin", "latin-p3", "latin-pgd"}
        Variant (see the module docstring).
    tol : float
        Stop when the indicator ``eta <= tol``.
    max_iter : int
        Largest number of iterations.
    k : float, optional
        Search direction (a stiffness per unit area, MPa/mm for the billet); default
        :func:`contact.globalstage.default_search_direction`: ``k = E / h``, with
        ``h = |Omega| / |Gamma_c|`` the mean depth of the body behind its candidate
        contact zone, the area of the mesh in its own plane divided by the length of the
        polyline of the contact nodes (``h`` = 8.7 mm for the billet).
    callback : callable, optional
        ``callback(state)`` with an :class:`IterationState` after every iteration;
        returning ``True`` stops the iteration.
    trunc : float, optional
        ``"latin-pgd"`` only: at every enrichment the compressor drops the terms with
        ``||v_i|| < trunc * ||v_1||`` (``||v_1||`` the largest amplitude; the paper's
        threshold ``eps`` of Algorithm 3 made relative), the space modes being
        orthonormal in the indicator metric (:func:`contact.indicator_metric`), see
        :mod:`contact.blockpgd`. Default ``tol / 10``: on the billet, reaching an
        indicator ``eta`` takes about ``trunc = eta / 10`` (``contact/README.md``); finer
        meshes need less (``1e-7`` for ``eta = 1e-4`` at refine 8).
    enrich_ratio : float
        ``"latin-p3"``: a new space-time pair is computed when the time-function update
        leaves a residual ``||R|| > enrich_ratio * ||R_before||``, ``R_before`` the
        residual of the previous iterate against the new right-hand side.
    fixed_point : int
        ``"latin-p3"``: alternating space/time iterations for a new pair.
    block : int
        ``"latin-pgd"``: Gaussian columns of the randomized range finder, the most space
        modes one enrichment adds.
    power : int
        ``"latin-pgd"``: subspace iterations of the range finder (0: plain sketch).
    enrich : {"departure", "stall", "always"}
        ``"latin-pgd"``: when to enrich. ``"departure"``: when a 4-column sketch
        estimates that the reduced global stage departs from the full one by more than
        ``enrich_tol`` (default 0.03) times the last indicator; ``"stall"``: when
        ``eta_i > enrich_tol * eta_{i-1}`` (default 0.9); ``"always"``: every iteration.
    enrich_tol : float, optional
        ``"latin-pgd"``: threshold of the rule ``enrich``.
    blas_threads : int or None
        BLAS threads during the solve (None leaves the thread pool alone); the products
        are small, so one thread is the fastest on this problem size.

    Returns
    -------
    LatinResult
        ``converged`` is False when ``max_iter`` was reached first (no exception: the
        partial result is the answer).
    """
    method, tol, max_iter, k = _check_options(problem, method, tol, max_iter, k)
    if not (isinstance(enrich_ratio, (int, float)) and 0 < enrich_ratio <= 1):
        raise SolverOptionError(f"`enrich_ratio` must be in (0, 1]; got {enrich_ratio!r}.")
    if trunc is not None and not (isinstance(trunc, (int, float)) and 0 <= trunc < 1):
        raise SolverOptionError(f"`trunc` must be in [0, 1); got {trunc!r}.")
    if isinstance(fixed_point, bool) or not isinstance(fixed_point, int) or fixed_point < 1:
        raise SolverOptionError(
            f"`fixed_point` must be a positive integer; got {fixed_point!r}."
        )
    pgd = _check_pgd_options(block, power, enrich, enrich_tol)
    if trunc is None:
        trunc = tol / TRUNC_PER_TOL
    with limit_blas_threads(blas_threads):
        return _solve(problem, method, tol, max_iter, k, callback, trunc, enrich_ratio,
                      fixed_point, pgd)


def _solve(
    problem: Problem,
    method: str,
    tol: float,
    max_iter: int,
    k: float,
    callback: Callable[[IterationState], Any] | None,
    trunc: float,
    enrich_ratio: float,
    fixed_point: int,
    pgd: dict[str, Any],
) -> LatinResult:
    c0 = time.process_time()
    stage = GlobalStage(problem, k)
    variant: Any
    if method == "latin":
        variant = _FullField(stage)
    elif method == "latin-pgd":
        from .blockpgd import BlockPGD

        variant = BlockPGD(stage, trunc=trunc, **pgd)
    else:
        from .pgd import SeparatedField

        variant = SeparatedField(
            stage,
            enrich_ratio=enrich_ratio,
            fixed_point=fixed_point,
        )
    setup = time.process_time() - c0
    log.info("%s: global operator factorised (%d free dofs, half-bandwidth %d, k = %.4g) "
             "and lift computed in %.2f s CPU", method, len(stage.free), stage.bandwidth, k,
             setup)
    P = problem
    L = P.weights
    Lc = np.concatenate([L, L])
    w = stage.w_lift.copy()
    lam = np.zeros_like(w)
    w_hat = w
    lam_hat = lam
    etas: list[float] = []
    sizes: list[int] = []
    cpus: list[float] = []
    walls: list[float] = []
    converged = False
    for it in range(1, max_iter + 1):
        c0, t0 = time.process_time(), time.perf_counter()
        w_hat, lam_hat = local_stage(w, lam, k=k, gaps=P.gaps, mu=P.mu)
        w = variant.update(stage.rhs_data(w_hat, lam_hat))
        lam = stage.tractions(w, w_hat, lam_hat)
        eta, den = indicator_parts(w, lam, w_hat, lam_hat, Lc, k)
        if hasattr(variant, "record"):
            variant.record(eta, den)
        cpus.append(time.process_time() - c0)
        walls.append(time.perf_counter() - t0)
        etas.append(eta)
        sizes.append(variant.basis_size)
        if it % 50 == 0:
            log.debug("%s iteration %d: indicator %.3e, basis %d", method, it, eta,
                      variant.basis_size)
        stop = False
        if callback is not None:
            stop = bool(callback(IterationState(it, eta, variant.basis_size, cpus[-1],
                                                variant.modes())))
        if eta <= tol:
            converged = True
            break
        if stop:
            break
    info = variant.finish()
    lift = Expansion(stage.lift_space, stage.lift_time)
    field = correction = None
    if method == "latin":
        field = np.zeros((P.n, P.m))
        field[stage.free] = variant.y
    else:
        correction = info.pop("expansion")
    log.info("%s: %d iterations in %.2f s CPU, indicator %.3e, converged %s", method,
             len(etas), setup + sum(cpus), etas[-1], converged)
    return LatinResult(
        method, k, converged, np.array(etas), np.array(sizes, dtype=int), np.array(cpus),
        np.array(walls), setup, w, lam, w_hat, lam_hat, lift, field, correction, info,
    )
