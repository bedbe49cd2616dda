"""Scale study of the contact solvers, and the effect of the search direction k.

    python bench/bench_contact_scale.py --out bench/results/contact          # everything
    python bench/bench_contact_scale.py --study k --out bench/results/contact
    python bench/bench_contact_scale.py --quick --out /tmp/contact-bench  # small

``--study scale`` solves the billet at the paper's size, refined in space (refine 2 and 4:
about x3.5 and x12.8 dofs) and in time (dt / 4: x4 instants) with ``reference_solve`` and the
three LATIN methods (stopped at indicator ``--level``), and records CPU time, iterations,
peak traced memory (tracemalloc, in a second untimed run) and the bytes of the
displacement representation (full space-time field against separated modes).
``--study k`` runs LATIN with multiples of the default search direction.
Writes ``scale.json``/``scale.png`` and ``k.json``/``k.png``.
"""

from __future__ import annotations

import argparse
import json
import time
import tracemalloc
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import contact

CASES = {
    "paper": {"refine": 1, "dt": 5e-3},
    "space x3.5 (refine 2)": {"refine": 2, "dt": 5e-3},
    "space x12.8 (refine 4)": {"refine": 4, "dt": 5e-3},
    "time x4": {"refine": 1, "dt": 5e-3 / 4},
}
QUICK = {
    "paper, dt x10": {"refine": 1, "dt": 5e-2},
    "refine 2, dt x10": {"refine": 2, "dt": 5e-2},
}


def measured(fn, *args, **kwargs):
    """Run ``fn`` twice: timed, then under tracemalloc for the peak (tracing slows it)."""
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn(*args, **kwargs)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    tracemalloc.start()
    fn(*args, **kwargs)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, cpu, wall, peak


def scale_study(cases, level, trunc, max_iter):
    rows = []
    for name, opts in cases.items():
        P = contact.billet(**opts)
        ref, cpu, wall, peak = measured(contact.reference_solve, P)
        full = P.n * P.m * 8
        row = {"case": name, **P.summary(), "full_field_bytes": full,
               "reference": {"cpu_s": cpu, "wall_s": wall, "peak_bytes": peak,
                             "newton_iterations": int(ref.newton_iterations.sum())}}
        svd = contact.svd_modes(ref.u - contact.solve(P, max_iter=1).lift.to_dense())
        row["optimal_svd_size"] = {f"{t:g}": svd.rank(t) for t in (1e-4, 1e-6)}
        for method, extra in (("latin", {}), ("latin-p3", {}),
                              ("latin-pgd", {"trunc": trunc})):
            r, cpu, wall, peak = measured(contact.solve, P, method, tol=level,
                                          max_iter=max_iter, **extra)
            u = r.displacement()
            row[method] = {
                "cpu_s": cpu, "wall_s": wall, "peak_bytes": peak,
                "iterations": r.iterations, "converged": r.converged,
                "basis_size": int(r.basis_size[-1]) if method != "latin" else None,
                "representation_bytes": r.memory(),
                "error_u": float(np.linalg.norm(u - ref.u) / np.linalg.norm(ref.u)),
            }
            print(f"{name:>22s} {method:>10s}: {cpu:7.2f} s, {r.iterations:4d} it, "
                  f"basis {row[method]['basis_size']}, {r.memory() / 1e6:6.2f} MB "
                  f"(full {full / 1e6:6.2f} MB), err {row[method]['error_u']:.1e}",
                  flush=True)
        print(f"{name:>22s} reference : {row['reference']['cpu_s']:7.2f} s", flush=True)
        rows.append(row)
    return rows


def k_study(factors, tol, max_iter, dt=5e-3):
    P = contact.billet(dt=dt)
    k0 = contact.default_search_direction(P)
    rows = []
    for f in factors:
        r = contact.solve(P, "latin", tol=tol, max_iter=max_iter, k=f * k0)
        rows.append({"factor": f, "k": f * k0, "iterations": r.iterations,
                     "converged": r.converged, "iterations_to_1e-4": r.iterations_to(1e-4),
                     "cpu_s": float(r.setup_time + r.cpu_time.sum())})
        print(f"k = {f:5.2f} k0: {r.iterations:5d} iterations to {tol:g}", flush=True)
    return {"k0": k0, "tol": tol, "rows": rows}


def plot_scale(rows, path):
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    names = [r["case"] for r in rows]
    x = np.arange(len(rows))
    width = 0.2
    for i, key in enumerate(["reference", "latin", "latin-p3", "latin-pgd"]):
        ax1.bar(x + (i - 1.5) * width, [r[key]["cpu_s"] for r in rows], width, label=key)
    ax1.set_xticks(x, names, fontsize=7)
    ax1.set_yscale("log")
    ax1.set_ylabel("CPU time (s)")
    ax1.legend()
    ax2.bar(x - width, [r["full_field_bytes"] / 1e6 for r in rows], width,
            label="full space-time field")
    ax2.bar(x, [r["latin-p3"]["representation_bytes"] / 1e6 for r in rows], width,
            label="LATIN-P3 modes")
    ax2.bar(x + width, [r["latin-pgd"]["representation_bytes"] / 1e6 for r in rows], width,
            label="LATIN-PGD modes")
    ax2.set_xticks(x, names, fontsize=7)
    ax2.set_ylabel("displacement representation (MB)")
    ax2.legend()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


def plot_k(result, path):
    fig = Figure(figsize=(5, 4), layout="constrained")
    ax = fig.subplots()
    rows = result["rows"]
    ax.loglog([r["factor"] for r in rows], [r["iterations"] for r in rows], "o-")
    ax.set_xlabel("k / k0 (k0 = E / h, the default)")
    ax.set_ylabel(f"LATIN iterations to indicator {result['tol']:g}")
    ax.grid(True, which="both", alpha=0.3)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/contact")
    parser.add_argument("--study", choices=["scale", "k", "all"], default="all")
    parser.add_argument("--level", type=float, default=1e-4)
    parser.add_argument("--trunc", type=float, default=1e-6)
    parser.add_argument("--max-iter", type=int, default=600)
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {}
    if args.study in ("k", "all"):
        factors = [0.3, 1.0, 3.0] if args.quick else [0.1, 0.3, 0.5, 1.0, 2.0, 3.0, 10.0]
        result["k"] = k_study(factors, 1e-6, 5000, dt=5e-2 if args.quick else 5e-3)
        (out / "k.json").write_text(json.dumps(result["k"], indent=1))
        plot_k(result["k"], out / "k.png")
    if args.study in ("scale", "all"):
        rows = scale_study(QUICK if args.quick else CASES, args.level, args.trunc,
                           args.max_iter)
        result["scale"] = rows
        (out / "scale.json").write_text(json.dumps(rows, indent=1))
        plot_scale(rows, out / "scale.png")
    return result


if __name__ == "__main__":
    main()
