"""The choices of LATIN-PGD measured on the paper's scene (368 dofs, 201 instants).

    python bench/bench_contact_pgd.py --out bench/results/contact

Every variant is solved to indicator ``--level`` (1e-4) with 1 BLAS thread; the CPU time
is the process time of the whole solve (setup included), the best of ``--repeat`` runs
after a warm-up. Each row changes one option of the default (``block=32``, ``power=0``,
``enrich="departure"`` with ``enrich_tol=0.03``, ``trunc = tol / 10``), against LATIN and
LATIN-P3 measured in the same process. The errors are
those of the local-stage contact forces against :func:`contact.reference_solve`.
Writes ``pgd_choices.json`` and ``pgd_choices.png`` (CPU time and iterations per variant).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from _common import Run
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from threadpoolctl import threadpool_limits

import contact

VARIANTS = [
    ("LATIN", "latin", {}),
    ("LATIN-P3 (one pair when the time functions do not suffice)", "latin-p3", {}),
    ("LATIN-PGD default", "latin-pgd", {}),
    ("block 1", "latin-pgd", {"block": 1}),
    ("block 8", "latin-pgd", {"block": 8}),
    ("block 16", "latin-pgd", {"block": 16}),
    ("block 64", "latin-pgd", {"block": 64}),
    ("power 1 (one subspace iteration)", "latin-pgd", {"power": 1}),
    ("power 2", "latin-pgd", {"power": 2}),
    ("rule: a block every iteration", "latin-pgd", {"enrich": "always"}),
    ("rule: stall (eta_i > 0.9 eta_i-1)", "latin-pgd", {"enrich": "stall"}),
    ("rule: departure 0.1", "latin-pgd", {"enrich_tol": 0.1}),
    ("rule: departure 0.01", "latin-pgd", {"enrich_tol": 0.01}),
    ("fixed trunc 1e-5", "latin-pgd", {"trunc": 1e-5}),
    ("fixed trunc 1e-6", "latin-pgd", {"trunc": 1e-6}),
    ("fixed trunc 1e-4", "latin-pgd", {"trunc": 1e-4}),
    ("fixed trunc 1e-4, block 16", "latin-pgd", {"trunc": 1e-4, "block": 16}),
]


def _rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def measure(P, ref, method, kwargs, level, max_iter, repeat):
    contact.solve(P, method, tol=level, max_iter=max_iter, **kwargs)  # warm-up
    best, out = np.inf, None
    for _ in range(repeat):
        c0 = time.process_time()
        out = contact.solve(P, method, tol=level, max_iter=max_iter, **kwargs)
        best = min(best, time.process_time() - c0)
    row = {"cpu_s": best, "iterations": out.iterations, "converged": out.converged,
           "lowest_indicator": float(out.indicator.min()),
           "error_u": _rel(out.displacement(), ref.u),
           "error_forces": _rel(out.lam_hat, ref.lam)}
    if method != "latin":
        row["max_basis"] = int(out.basis_size.max())
        row["final_rank"] = int(out.correction.rank)
    for key in ("enrichments", "pairs_added", "solves", "compactions"):
        if key in out.info:
            row[key] = int(out.info[key])
    if "truncations" in out.info:
        row["truncations"] = list(out.info["truncations"])
    return row


def plot(rows, path):
    fig = Figure(figsize=(11, 5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, sharey=True)
    names = [r["variant"] for r in rows]
    y = np.arange(len(rows))
    ax1.barh(y, [1e3 * r["cpu_s"] for r in rows],
             color=["C1" if r["converged"] else "C7" for r in rows])
    ax1.set_yticks(y, names, fontsize=7)
    ax1.invert_yaxis()
    ax1.set_xlabel("CPU time to indicator 1e-4 (ms, grey: not reached)")
    ax2.barh(y, [r["iterations"] for r in rows])
    ax2.set_xscale("log")
    ax2.set_xlabel("iterations")
    for ax in (ax1, ax2):
        ax.grid(True, axis="x", alpha=0.3)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


def main(argv=None):
    record = Run("bench_contact_pgd", argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/contact")
    parser.add_argument("--level", type=float, default=1e-4)
    parser.add_argument("--max-iter", type=int, default=400)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--dt", type=float, default=5e-3)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    P = contact.billet(dt=args.dt)
    ref = contact.reference_solve(P)
    load = {"start": os.getloadavg()}
    rows = []
    with threadpool_limits(1):
        for name, method, kwargs in VARIANTS:
            r = {"variant": name, "method": method, "options": kwargs,
                 **measure(P, ref, method, kwargs, args.level, args.max_iter, args.repeat)}
            rows.append(r)
            print(f"{name:>58s}: {1e3 * r['cpu_s']:7.1f} ms, {r['iterations']:4d} it"
                  f"{'' if r['converged'] else ' (not reached)'}, basis "
                  f"{r.get('max_basis', '-')}/{r.get('final_rank', '-')}, enrichments "
                  f"{r.get('enrichments', '-')}, forces {r['error_forces']:.1e}", flush=True)
    load["end"] = os.getloadavg()
    result = {"problem": P.summary(), "level": args.level, "load_average": load,
              "rows": rows}
    record.write(out / "pgd_choices.json", result)
    plot(rows, out / "pgd_choices.png")
    return result


if __name__ == "__main__":
    main()
