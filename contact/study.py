"""The paper's study of the billet: three LATIN variants against the reference solver.

:func:`billet_study` runs :func:`contact.reference_solve` and the three methods of
:func:`contact.solve` on :func:`contact.billet`, then writes Figs. 5-9 as PNG files and
every number (histories, agreement with the reference, summary table) as
``summary.json``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from . import figures
from .latin import TRUNC_PER_TOL, solve
from .local import local_stage
from .pgd import indicator_metric
from .post import check_laws, svd_modes
from .problem import billet
from .reference import reference_solve
from .result import IterationState, LatinResult

__all__ = ["billet_study"]

log = logging.getLogger(__name__)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def billet_study(
    out: str | Path,
    *,
    refine: int = 1,
    dt: float = 5e-3,
    tol: float = 1e-6,
    level: float = 1e-4,
    trunc: float | None = None,
    fine_trunc: float | None = 1e-5,
    max_iter: int = 400,
    mac_iterations: tuple[int, ...] = (10,),
    progress: Callable[[str, int], Callable[[IterationState], Any]] | None = None,
) -> dict[str, Any]:
    """Run the billet study and write its figures and numbers into ``out``.

    Parameters
    ----------
    out : path
        Output directory (created when missing).
    refine, dt : int, float
        Passed to :func:`contact.billet`.
    tol : float
        Stopping indicator of the three methods.
    level : float
        Indicator level at which CPU times and iterations are compared.
    trunc : float, optional
        Relative truncation of LATIN-PGD (also the level of the optimal SVD size);
        default ``tol / 10``, the default of :func:`contact.solve`, with which LATIN-PGD
        reaches ``tol``.
    fine_trunc : float or None
        When given, LATIN-PGD is also run with this other truncation.
    max_iter : int
        Largest number of iterations of every method.
    mac_iterations : tuple of int
        Iterations whose bases are drawn in the MAC diagrams, besides the last one.
    progress : callable, optional
        ``progress(label, max_iter)`` returns a per-iteration callback (a progress bar).
        When the callback has a ``close()`` method, it is called once the solve of that
        method has ended (converged or not).

    Notes
    -----
    Every stage is logged at INFO level on the ``contact`` loggers: the mesh and
    operators, the reference solve, each method's factorisation and solve, the SVD and
    each file written. ``contact billet`` shows these messages on stderr.

    Returns
    -------
    dict
        The content of ``summary.json``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log.info("building the billet mesh and its operators (refine %d, dt %g s)", refine, dt)
    P = billet(refine=refine, dt=dt)
    log.info("billet: %d dofs (%d free), %d contact nodes, %d instants", P.n,
             len(P.free_dofs), P.nc, P.m)
    log.debug("billet: %s", P.summary())
    log.info("reference solve: semi-smooth Newton, instant after instant (%d instants)", P.m)
    ref = reference_solve(P)
    if trunc is None:
        trunc = tol / TRUNC_PER_TOL
    runs: dict[str, tuple[str, dict[str, Any]]] = {
        "latin": ("latin", {}),
        "latin-p3": ("latin-p3", {}),
        "latin-pgd": ("latin-pgd", {"trunc": trunc}),
    }
    if fine_trunc is not None:
        runs[f"latin-pgd (trunc {fine_trunc:g})"] = ("latin-pgd", {"trunc": fine_trunc})
    # compile the numba kernels of the local stage first, so that the first method's
    # CPU time does not include the compilation
    local_stage(np.zeros((2, 2)), np.zeros((2, 2)), k=1.0, gaps=np.zeros(1), mu=0.1)
    results: dict[str, LatinResult] = {}
    snapshots: dict[str, list[tuple[int, np.ndarray]]] = {}
    for label, (method, opts) in runs.items():
        log.info("%s: solving (tol %g, at most %d iterations)", label, tol, max_iter)
        bar = progress(label, max_iter) if progress is not None else None
        snaps: list[tuple[int, np.ndarray]] = []

        def callback(state: IterationState, bar: Any = bar, snaps: list[Any] = snaps) -> None:
            if state.basis is not None and state.iteration in mac_iterations:
                snaps.append((state.iteration, np.array(state.basis)))
            if bar is not None:
                bar(state)

        try:
            results[label] = solve(P, method, tol=tol, max_iter=max_iter,
                                   callback=callback, **opts)
        finally:
            close = getattr(bar, "close", None)
            if callable(close):
                close()
        snapshots[label] = snaps
    lift = results["latin"].lift.to_dense()
    y_ref = ref.u - lift
    # the SVD in the norm the indicator measures, the one LATIN-PGD truncates in
    svd = svd_modes(y_ref, inner=indicator_metric(P))
    svd_u = svd_modes(ref.u)
    n_opt = svd.rank(trunc)
    log.info("SVD of the reference correction (indicator metric): %d modes above %g of "
             "the largest", n_opt,
             trunc)

    log.info("drawing Figs. 5-9 into %s", out)
    _save(figures.fig5_convergence(results, optimal=n_opt, level=level),
          out / "fig5_convergence.png")
    _save(figures.fig6_svd(svd, P.times, rtol=trunc), out / "fig6_svd.png")
    _save(figures.fig7_space_modes(P, svd), out / "fig7_space_modes.png")
    q = max(n_opt, 1)
    free = P.free_dofs
    for fig_name, label in (("fig8_mac_p3.png", "latin-p3"), ("fig9_mac_pgd.png", "latin-pgd")):
        bases = []
        for it, B in snapshots[label]:
            full = np.zeros((P.n, B.shape[1]))
            full[free] = B
            bases.append((f"iteration {it}", full))
        final = results[label].correction
        if final is not None:
            bases.append((f"last iteration ({results[label].iterations})", final.U))
        _save(
            figures.fig_mac(bases, svd.space[:, :q],
                            title=f"MAC of the {label.upper()} basis against the SVD "
                                  f"basis of the reference (Fig. {fig_name[3]})"),
            out / fig_name,
        )

    full_field_bytes = P.n * P.m * 8
    table = []
    methods: dict[str, Any] = {}
    for label, r in results.items():
        u = r.displacement()
        t_trunc = runs[label][1].get("trunc")
        row = {
            "method": label,
            "iterations": r.iterations,
            "converged": r.converged,
            "final_indicator": float(r.indicator[-1]),
            "iterations_to_level": r.iterations_to(level),
            "cpu_time_to_level_s": _finite(r.cpu_time_to(level)),
            "cpu_time_total_s": float(r.setup_time + r.cpu_time.sum()),
            "final_basis_size": r.correction.rank if r.correction is not None else None,
            "largest_basis_size": int(r.basis_size.max()) if r.method != "latin" else None,
            "optimal_svd_size": svd.rank(t_trunc) if t_trunc else n_opt,
            "memory_bytes": r.memory(),
            "error_u_vs_reference": _rel(u, ref.u),
            "error_lambda_vs_reference": _rel(r.lam_hat, ref.lam),
        }
        table.append(row)
        methods[label] = {
            **row,
            "k": r.k,
            "laws_worst_violation_global": check_laws(P, r.w, r.lam).worst(),
            "indicator": r.indicator.tolist(),
            "basis_size": r.basis_size.tolist(),
            "cpu_time": r.cpu_time.tolist(),
            "info": {k: v for k, v in r.info.items()
                     if isinstance(v, (int, float)) and np.isfinite(v)},
        }
    laws = check_laws(P, ref.w, ref.lam)
    summary = {
        "problem": P.summary(),
        "level": level,
        "tol": tol,
        "trunc": trunc,
        "reference": {
            "cpu_time_s": ref.cpu_time,
            "newton_iterations": int(ref.newton_iterations.sum()),
            "laws_worst_violation": laws.worst(),
            "dissipation": laws.dissipation,
            "contact_nodes_in_contact": np.count_nonzero(
                ref.lam[: P.nc] < -1e-8 * np.abs(ref.lam[: P.nc]).max(), axis=0
            ).tolist(),
        },
        "svd": {
            "singular_values_correction": svd.values.tolist(),
            "singular_values_displacement": svd_u.values.tolist(),
            "optimal_size_correction": {f"{t:g}": svd.rank(t) for t in (1e-3, 1e-4, 1e-5, 1e-6)},
            "optimal_size_correction_tail_energy": {
                f"{t:g}": svd.tail_rank(t) for t in (1e-3, 1e-4, 1e-5, 1e-6)},
            "optimal_size_displacement": {
                f"{t:g}": svd_u.rank(t) for t in (1e-3, 1e-4, 1e-5, 1e-6)
            },
        },
        "full_field_bytes": full_field_bytes,
        "table": table,
        "methods": methods,
    }
    (out / "summary.json").write_text(
        json.dumps(summary, indent=1, default=_json_default, allow_nan=False)
    )
    log.info("wrote %s", out / "summary.json")
    return summary


def _save(fig: Any, path: Path) -> None:
    figures.save(fig, path)
    log.info("wrote %s", path)


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"cannot serialise {type(value).__name__}")
