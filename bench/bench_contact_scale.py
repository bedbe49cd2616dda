"""Scale study of the contact solvers, cost per iteration, and the search direction k.

    python bench/bench_contact_scale.py --out bench/results/contact          # everything
    python bench/bench_contact_scale.py --study scale --only large --out bench/results/contact
    python bench/bench_contact_scale.py --study cost --out bench/results/contact
    python bench/bench_contact_scale.py --quick --out /tmp/contact-bench  # small

``--study scale`` solves the billet at the paper's size, refined in space (refine 2 and 4:
about x3.5 and x12.8 dofs), in time (dt / 4: x4 instants) and in both (``large``: refine 8
and dt / 4, a full space-time displacement field of 116 MB) with ``reference_solve`` and
the three LATIN methods, LATIN-PGD at each ``--trunc`` (stopped at indicator ``--level``).
Every solve runs in a fresh
process, which reports its CPU time, iterations, peak resident memory (``ru_maxrss``, with
the resident memory before the solve), peak traced memory (tracemalloc, in a second
untimed run in the same process) and the bytes of the displacement representation (full
space-time field against separated modes). The optimal SVD sizes of the reference
correction are computed in the indicator metric (:func:`contact.indicator_metric`), by both
definitions (singular-value ratio and tail energy).
``--study cost`` records the CPU time of every iteration of LATIN-P3 and LATIN-PGD
against the basis size ``p`` (refine 4), with the nf-sized vectors each iteration touched.
``--study breakdown`` profiles 60 iterations of each method on the large scene and
reports the CPU time per iteration of each phase (local stage, solves, time functions,
residual norms, new pair, compressor update, ...).
``--study k`` runs LATIN with multiples of the default search direction.
Writes ``scale.json``/``scale.png``, ``cost.json``/``cost.png``, ``breakdown.json`` and
``k.json``/``k.png``;
a tqdm bar per solve on stderr.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import psutil
from _common import Run
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm import tqdm

import contact

CASES = {
    "paper": {"refine": 1, "dt": 5e-3},
    "refine 4": {"refine": 4, "dt": 5e-3},
    "large (refine 8, time x4)": {"refine": 8, "dt": 5e-3 / 4},
}
QUICK = {
    "paper, dt x10": {"refine": 1, "dt": 5e-2},
    "refine 2, dt x10": {"refine": 2, "dt": 5e-2},
}
# LATIN-PGD options per case (the default truncation tol / 10 is too coarse for the
# large scene, whose correction's spectrum decays slowly: contact/README.md)
PGD_OPTIONS = {"large (refine 8, time x4)": {"trunc": 1e-7}}
# cases with more dofs are solved once (no warm-up solve, no repetition)
REPEAT_MAX_DOFS = 10_000


def _bar(label, max_iter):
    bar = tqdm(total=max_iter, desc=label, leave=False, mininterval=1.0)

    def callback(state):
        bar.update(1)
        bar.set_postfix(eta=f"{state.indicator:.1e}", p=state.basis_size, refresh=False)

    return bar, callback


def _solve(opts, method, kwargs, ref_path, level, max_iter, trace, repeat=1):
    """One solve in this (fresh) process: the timed run(s), then a traced one.

    The numba kernels are compiled first on a small problem; with ``repeat > 1`` a
    warm-up solve precedes ``repeat`` timed ones, and the best CPU time is kept.
    """
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    contact.solve(contact.billet(dt=0.5), "latin", max_iter=2)  # numba compilation
    P = contact.billet(**opts)
    rss_before = psutil.Process().memory_info().rss
    load = os.getloadavg()
    label = f"{opts} {method}"
    if method == "reference":
        def run(callback=None):
            return contact.reference_solve(P)
    else:
        def run(callback=None):
            return contact.solve(P, method, tol=level, max_iter=max_iter, callback=callback,
                                 **kwargs)
    if repeat > 1:
        run()
    cpu = wall = np.inf
    for _ in range(repeat):
        bar, cb = _bar(label, max_iter) if method != "reference" else (None, None)
        c0, t0 = time.process_time(), time.perf_counter()
        out = run(cb)
        cpu = min(cpu, time.process_time() - c0)
        wall = min(wall, time.perf_counter() - t0)
        if bar is not None:
            bar.close()
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    row = {"cpu_s": cpu, "wall_s": wall, "rss_before_bytes": rss_before,
           "peak_rss_bytes": peak_rss, "repeat": repeat, "options": kwargs,
           "load_average": [load, os.getloadavg()]}
    if method == "reference":
        np.save(ref_path, out.u)
        np.save(ref_path.replace(".npy", "_lam.npy"), out.lam)
        row["newton_iterations"] = int(out.newton_iterations.sum())
        M = contact.indicator_metric(P)
        y = out.u - contact.solve(P, max_iter=1).lift.to_dense()
        svd = contact.svd_modes(y, inner=M)
        row["optimal_svd_size"] = {f"{t:g}": svd.sizes(t) for t in (1e-4, 1e-5, 1e-6)}
    else:
        u = out.displacement()
        row.update({
            "iterations": out.iterations, "converged": out.converged,
            "iterations_to_level": out.iterations_to(level),
            "cpu_to_level_s": out.cpu_time_to(level),
            "setup_s": out.setup_time,
            "basis_size": int(out.basis_size[-1]) if method != "latin" else None,
            "max_basis_size": int(out.basis_size.max()) if method != "latin" else None,
            "final_rank": out.correction.rank if out.correction is not None else None,
            "representation_bytes": out.memory(),
            "cpu_per_iteration_s": float(np.median(out.cpu_time)),
        })
        if ref_path is not None and Path(ref_path).exists():
            u_ref = np.load(ref_path)
            lam_ref = np.load(ref_path.replace(".npy", "_lam.npy"))
            row["error_u"] = float(np.linalg.norm(u - u_ref) / np.linalg.norm(u_ref))
            row["error_lam"] = float(np.linalg.norm(out.lam_hat - lam_ref)
                                     / np.linalg.norm(lam_ref))
            del u_ref
        for key in ("enrichments", "pairs_added", "solves", "compactions",
                    "direct_residuals"):
            if key in out.info:
                row[key] = int(out.info[key])
        if "nf_columns" in out.info:
            row["nf_columns_total"] = int(out.info["nf_columns"].sum())
        del u
    del out
    if trace:
        tracemalloc.start()
        run()
        row["peak_traced_bytes"] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return row


def measured(opts, method, kwargs, ref_path, level, max_iter, trace=True, repeat=1):
    """Run :func:`_solve` in a fresh process (so that its peak RSS is its own)."""
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(1, maxtasksperchild=1) as pool:
        return pool.apply(_solve, (opts, method, kwargs, ref_path, level, max_iter, trace,
                                   repeat))


def scale_study(cases, level, max_iter, trace=True, repeat=3, reference_max_dofs=5000):
    """Reference (below ``reference_max_dofs``), LATIN, LATIN-P3 and LATIN-PGD per case."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, opts in cases.items():
            P = contact.billet(**opts)
            full = P.n * P.m * 8
            rep = repeat if P.n <= REPEAT_MAX_DOFS else 1
            ref_path = str(Path(tmp) / f"u_ref_{len(rows)}.npy")
            row = {"case": name, **P.summary(), "full_field_bytes": full}
            if P.n <= reference_max_dofs:
                ref = measured(opts, "reference", {}, ref_path, level, max_iter, trace)
                row["optimal_svd_size"] = ref.pop("optimal_svd_size")
                row["reference"] = ref
                print(f"{name:>26s} reference : {ref['cpu_s']:8.2f} s CPU, peak RSS "
                      f"{ref['peak_rss_bytes'] / 1e6:7.1f} MB; optimal sizes (metric) "
                      f"{row['optimal_svd_size']}", flush=True)
            runs = [("latin", {}), ("latin-p3", {}), ("latin-pgd", PGD_OPTIONS.get(name, {}))]
            for method, extra in runs:
                r = measured(opts, method, extra, ref_path, level, max_iter, trace, rep)
                row[method] = r
                err = (f", err u {r['error_u']:.1e}, lam {r['error_lam']:.1e}"
                       if "error_u" in r else "")
                print(f"{name:>26s} {method:>10s}: {r['cpu_s']:8.2f} s CPU (best of {rep}), "
                      f"{r['iterations']:4d} it, basis {r['max_basis_size']}/"
                      f"{r['final_rank']}, {r['representation_bytes'] / 1e6:7.2f} MB (full "
                      f"{full / 1e6:7.2f} MB), peak RSS {r['peak_rss_bytes'] / 1e6:7.1f} MB"
                      f"{err}; load {r['load_average'][0][0]:.1f}", flush=True)
            rows.append(row)
    return rows


def cost_study(opts, trunc, max_iter):
    """CPU time of each iteration against the basis size, for P3 and PGD."""
    P = contact.billet(**opts)
    out = {"problem": P.summary(), "trunc": trunc}
    for method, extra in (("latin-p3", {}), ("latin-pgd", {"trunc": trunc})):
        bar, cb = _bar(method, max_iter)
        r = contact.solve(P, method, tol=1e-12, max_iter=max_iter, callback=cb, **extra)
        bar.close()
        p = r.basis_size
        by_p = {}
        for size in np.unique(p):
            sel = p == size
            by_p[int(size)] = {"cpu_s": float(np.median(r.cpu_time[sel])),
                               "nf_columns": float(np.median(r.info["nf_columns"][sel])),
                               "iterations": int(sel.sum())}
        out[method] = {"basis_size": p.tolist(), "cpu_s": r.cpu_time.tolist(),
                       "nf_columns": r.info["nf_columns"].tolist(), "by_basis_size": by_p}
        print(f"{method}: basis size -> median CPU per iteration (ms), nf-sized vectors")
        for size, v in list(by_p.items())[:: max(1, len(by_p) // 12)]:
            print(f"  p = {size:4d}: {1e3 * v['cpu_s']:7.2f} ms, {v['nf_columns']:7.0f}")
    return out


# functions whose cumulated time makes the breakdown (module suffix, function name)
PHASES = {
    "local stage": ("contact/local.py", "local_stage"),
    "full-field solve (LATIN)": ("contact/latin.py", "update"),
    "time functions (P3)": ("contact/pgd.py", "_time_functions"),
    "residual norms (P3)": ("contact/pgd.py", "_residual_norm"),
    "new pair (P3: fixed point, CGS2 against U)": ("contact/pgd.py", "_new_pair"),
    "new column of W (P3: CGS2, projections)": ("contact/pgd.py", "_coordinates"),
    "time functions (PGD)": ("contact/blockpgd.py", "_time_functions"),
    "sketches E Omega (PGD: rule and block)": ("contact/blockpgd.py", "_sketch"),
    "block into W (PGD: CGS2, SVQB, projections)": ("contact/blockpgd.py",
                                                    "_block_coordinates"),
    "compaction of W (PGD)": ("contact/blockpgd.py", "_compact"),
    "StreamCompressor.add": ("streamsvd/stream/updates.py", "add"),
    "StreamCompressor.expansion": ("streamsvd/stream/view.py", "expansion"),
    "projections on U (P3)": ("contact/pgd.py", "_project"),
    "projections on U (PGD)": ("contact/blockpgd.py", "_project"),
    "indicator": ("contact/globalstage.py", "indicator"),
}


def breakdown_study(opts, trunc, iterations):
    """Where the CPU time of an iteration goes (cProfile, cumulated time per phase)."""
    import cProfile
    import pstats

    P = contact.billet(**opts)
    out = {"problem": P.summary(), "trunc": trunc, "iterations": iterations}
    for method, extra in (("latin", {}), ("latin-p3", {}), ("latin-pgd", {"trunc": trunc})):
        contact.solve(P, method, max_iter=3, **extra)  # compiles the numba kernels
        prof = cProfile.Profile()
        prof.enable()
        r = contact.solve(P, method, tol=1e-12, max_iter=iterations, **extra)
        prof.disable()
        stats = pstats.Stats(prof).stats
        phases = {}
        for name, (suffix, func) in PHASES.items():
            t = sum(v[3] for (file, _, fn), v in stats.items()
                    if file.endswith(suffix) and fn == func)
            if t > 0:
                phases[name] = t / r.iterations
        total = float(np.sum(r.cpu_time)) / r.iterations
        phases["other"] = max(total - sum(phases.values()), 0.0)
        out[method] = {"cpu_per_iteration_s": total, "phases_s": phases,
                       "basis_size": int(r.basis_size[-1])}
        print(f"{method}: {1e3 * total:.1f} ms per iteration (CPU, profiled), basis "
              f"{r.basis_size[-1]}")
        for name, t in phases.items():
            print(f"  {name:>40s}: {1e3 * t:8.2f} ms")
    return out


def plot_cost(result, path):
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    for method in ("latin-p3", "latin-pgd"):
        by_p = result[method]["by_basis_size"]
        ps = np.array(sorted(by_p, key=int), dtype=int)
        ax1.plot(ps, [1e3 * by_p[p]["cpu_s"] for p in ps], "o-", ms=3, label=method)
        ax2.plot(ps, [by_p[p]["nf_columns"] for p in ps], "o-", ms=3, label=method)
    ax1.set_xlabel("basis size p")
    ax1.set_ylabel("CPU time per iteration (ms, median)")
    ax2.set_xlabel("basis size p")
    ax2.set_ylabel("nf-sized vectors touched per iteration (median)")
    for ax in (ax1, ax2):
        ax.grid(True, alpha=0.3)
        ax.legend()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=120)


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
    """One figure: CPU time to the level, iterations, modes and peak memory per scene."""
    fig = Figure(figsize=(16, 4), layout="constrained")
    axes = fig.subplots(1, 4)
    x = np.array([r["dofs"] * r["instants"] for r in rows], dtype=float)
    labels = [f"{r['dofs']} x {r['instants']}" for r in rows]
    styles = {"latin": ("o-", "LATIN"), "latin-p3": ("s-", "LATIN-P3"),
              "latin-pgd": ("^-", "LATIN-PGD")}
    for key, (style, label) in styles.items():
        axes[0].plot(x, [r[key]["cpu_s"] for r in rows], style, label=label)
        axes[1].plot(x, [r[key]["iterations"] for r in rows], style, label=label)
        if key != "latin":
            axes[2].plot(x, [r[key]["max_basis_size"] for r in rows], style,
                         label=f"{label} (largest)")
            axes[2].plot(x, [r[key]["final_rank"] for r in rows], style[0] + ":",
                         label=f"{label} (final)")
        axes[3].plot(x, [r[key]["peak_rss_bytes"] / 1e6 for r in rows], style, label=label)
    axes[2].plot(x, [2 * r["contact_nodes"] for r in rows], "k--", lw=0.8,
                 label="2 x contact nodes (upper bound)")
    axes[0].set_ylabel("CPU time to indicator 1e-4 (s, process time)")
    axes[1].set_ylabel("iterations to indicator 1e-4")
    axes[2].set_ylabel("space modes")
    axes[3].set_ylabel("peak resident memory of the process (MB)")
    from matplotlib.ticker import LogFormatter, NullLocator

    for i, ax in enumerate(axes):
        ax.set_xscale("log")
        ax.set_xticks(x, labels, fontsize=7, rotation=15)
        ax.xaxis.set_minor_locator(NullLocator())
        if i < 3:  # CPU time, iterations and modes on log scales, minor ticks labelled
            ax.set_yscale("log")
            ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False,
                                                      minor_thresholds=(2, 0.4)))
        ax.set_xlabel("scene (free and prescribed dofs x instants)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
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
    record = Run("bench_contact_scale", argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/contact")
    parser.add_argument("--study", choices=["scale", "cost", "breakdown", "k", "all"],
                        default="all")
    parser.add_argument("--only", nargs="*", default=None,
                        help="scale study: run the cases whose name contains one of these")
    parser.add_argument("--no-trace", action="store_true",
                        help="scale study: skip the tracemalloc run (half the time)")
    parser.add_argument("--level", type=float, default=1e-4)
    parser.add_argument("--trunc", type=float, nargs="+", default=[1e-5, 1e-6],
                        help="LATIN-PGD truncations (the first is the 'latin-pgd' entry)")
    parser.add_argument("--max-iter", type=int, default=600)
    parser.add_argument("--repeat", type=int, default=3,
                        help="scale study: timed solves after a warm-up (below 10,000 dofs)")
    parser.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {}
    if args.study in ("k", "all"):
        factors = [0.3, 1.0, 3.0] if args.quick else [0.1, 0.3, 0.5, 1.0, 2.0, 3.0, 10.0]
        result["k"] = k_study(factors, 1e-6, 5000, dt=5e-2 if args.quick else 5e-3)
        record.write(out / "k.json", result["k"])
        plot_k(result["k"], out / "k.png")
    if args.study in ("cost", "all"):
        opts = {"refine": 1, "dt": 5e-2} if args.quick else {"refine": 4, "dt": 5e-3}
        result["cost"] = cost_study(opts, args.trunc[0], 60 if args.quick else 200)
        record.write(out / "cost.json", result["cost"])
        plot_cost(result["cost"], out / "cost.png")
    if args.study in ("breakdown", "all"):
        opts = ({"refine": 1, "dt": 5e-2} if args.quick else
                {"refine": 8, "dt": 5e-3 / 4})
        result["breakdown"] = breakdown_study(opts, args.trunc[-1], 10 if args.quick else 60)
        record.write(out / "breakdown.json", result["breakdown"])
    if args.study in ("scale", "all"):
        cases = QUICK if args.quick else CASES
        if args.only:
            cases = {k: v for k, v in cases.items() if any(o in k for o in args.only)}
        rows = scale_study(cases, args.level, args.max_iter, trace=not args.no_trace,
                           repeat=1 if args.quick else args.repeat)
        result["scale"] = rows
        record.write(out / "scale.json", rows)
        plot_scale(rows, out / "scale.png")
    return result


if __name__ == "__main__":
    main()
