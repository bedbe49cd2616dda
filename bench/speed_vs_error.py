"""Time against error: rotation sweeps (fast and literal paths) against LAPACK's SVD.

Matrices
--------
* ``rbs480a`` (Matrix Market, 480 x 480), read with ``scipy.io.mmread``.
* ``generated``: ``A = Q1 diag(sigma) Q2^T`` of size ``n x n`` (``--n``, 2000 by default),
  ``Q1, Q2`` Haar-random orthogonal (QR of a Gaussian matrix, seed ``--seed``) and the
  geometric spectrum ``sigma_i = 10^(-D i / (n - 1))``, ``i = 0 .. n-1``, ``D = --decades``
  (6: successive ratio ``10^(-6/1999) = 0.9931`` for n = 2000). Its SVD is known exactly.

Methods
-------
Every rotation run starts from the canonical expansion ``U = I, V = A^T``
(``streamsvd.Expansion.canonical``, built inside the timed call; its cost alone is
reported) and calls ``streamsvd.linalg.compress(e, rule=..., method=..., max_sweeps=k)`` for
``k = 1, 2, 3, 5, 8, 13, ...`` until the run reports convergence (default stopping test
``tol = sqrt(m) eps``). Each ``k`` is a separate timed run, best of 3 when a run takes
under 5 s. A series stops when the next run is predicted (linearly in ``k``) to exceed
``--run-cap`` seconds. Series: fast path with ``rule="paper"`` and ``rule="jacobi"``;
literal path (loop by loop on the full factors) with ``rule="jacobi"``, only for
matrices with ``n <= --literal-max-n`` and capped by ``--literal-cap`` seconds.
Baselines: ``scipy.linalg.svd(A, lapack_driver="gesdd")`` and ``"gesvd"``, with the
default BLAS threads and limited to one thread (``-1t``, threadpoolctl; the sweeps run on
one core), each timed before and after the rotation series (the best is kept).

Errors
------
* singular values: ``max_i |s_i - sigma_i| / sigma_1`` with ``s_i = ||v_i||`` (sorted)
  and ``sigma`` the reference (exact spectrum for ``generated``; LAPACK ``gesvd`` for
  rbs480a, so on rbs480a each LAPACK driver is measured against the other one);
* quasi-optimal basis, for target ranks ``k`` (``--ranks``, 20 and 100): the relative
  excess of the rank-k truncation over the optimal (Eckart-Young) error,
  ``||A - U_k V_k^T||_F / sqrt(sum_{i>k} sigma_i^2) - 1``; since ``U`` is orthonormal
  and ``U V^T = A``, ``||A - U_k V_k^T||_F = ||V[:, k:]||_F``, the error of projecting
  ``A`` on the span of the first k left vectors. Also the subspace distance
  ``||U_k U_k^T - Uref_k Uref_k^T||_2``.

Writes ``speed_vs_error_<matrix>.png`` (Pareto plots, log-log) and
``speed_vs_error_<matrix>.json`` for each matrix.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla
from _common import Run, best_time, load_rbs480a, machine_info, out_dir, print_table, pyplot

import streamsvd as ss

SWEEPS = (1, 2, 3, 5, 8, 13, 21, 34, 55, 89, 144, 233, 377, 610, 987)
SHORT = 5.0  # runs shorter than this (seconds) are repeated, the best time is kept
LEVELS = (1e-1, 1e-2, 1e-4, 1e-8, 1e-12)
SERIES = (
    ("fast", "paper"),
    ("fast", "jacobi"),
    ("literal", "jacobi"),
)


def generated_matrix(
    n: int, decades: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``A = Q1 diag(sigma) Q2^T`` with Haar ``Q1, Q2``; returns ``A, sigma, Q1``."""
    rng = np.random.default_rng(seed)

    def haar(k: int) -> np.ndarray:
        Q, R = np.linalg.qr(rng.standard_normal((k, k)))
        return Q * np.where(np.diag(R) < 0.0, -1.0, 1.0)

    sigma = 10.0 ** (-decades * np.arange(n) / max(n - 1, 1))
    Q1 = haar(n)
    Q2 = haar(n)
    return (Q1 * sigma) @ Q2.T, sigma, Q1


class Errors:
    """The error measures of one matrix, against a reference SVD."""

    def __init__(self, A: np.ndarray, sigma: np.ndarray, Uref: np.ndarray,
                 ranks: Sequence[int]) -> None:
        self.sigma = sigma
        self.ranks = [k for k in ranks if 0 < k < sigma.size]
        self.Uref = Uref
        tail = np.sqrt(np.cumsum((sigma**2)[::-1])[::-1])  # tail[k] = sqrt(sum_{i>=k})
        self.opt = {k: float(tail[k]) for k in self.ranks}

    def of(self, U: np.ndarray, V: np.ndarray) -> dict[str, Any]:
        """Errors of an expansion ``U V^T`` of ``A`` with orthonormal ``U``, sorted terms."""
        amp = np.linalg.norm(V, axis=0)
        q = min(amp.size, self.sigma.size)
        sv = float(np.max(np.abs(amp[:q] - self.sigma[:q])) / self.sigma[0])
        excess, subspace = {}, {}
        for k in self.ranks:
            rest = float(np.linalg.norm(V[:, k:]))
            excess[k] = rest / self.opt[k] - 1.0
            Uk, Rk = U[:, :k], self.Uref[:, :k]
            subspace[k] = float(np.linalg.norm(Rk - Uk @ (Uk.T @ Rk), 2))
        return {"sv": sv, "excess": excess, "subspace": subspace}


def run_series(A: np.ndarray, errors: Errors, method: str, rule: str, *,
               run_cap: float, max_sweeps: int, repeat: int) -> dict[str, Any]:
    """Timed runs ``max_sweeps = 1, 2, 3, 5, ...`` until convergence or the time cap."""
    runs: list[dict[str, Any]] = []
    capped = False
    for k in (s for s in SWEEPS if s < max_sweeps):
        if runs:
            last = runs[-1]
            if last["converged"]:
                break
            predicted = last["seconds"] * k / max(last["sweeps"], 1)
            if predicted > run_cap:
                capped = True
                break
        runs.append(_timed_compress(A, errors, method, rule, k, repeat))
    else:
        if not runs:
            runs.append(_timed_compress(A, errors, method, rule, max_sweeps, repeat))
        elif not runs[-1]["converged"]:
            if runs[-1]["seconds"] * max_sweeps / max(runs[-1]["sweeps"], 1) > run_cap:
                capped = True
            else:
                runs.append(_timed_compress(A, errors, method, rule, max_sweeps, repeat))
    return {"method": method, "rule": rule, "runs": runs, "capped": capped,
            "converged": bool(runs and runs[-1]["converged"])}


def _timed_compress(A: np.ndarray, errors: Errors, method: str, rule: str,
                    k: int, repeat: int) -> dict[str, Any]:
    def fn() -> ss.CompressResult:
        return ss.compress(ss.Expansion.canonical(A), rule=rule, method=method, max_sweeps=k)

    timing, res = best_time(fn, repeat=repeat, short=SHORT)
    err = errors.of(res.expansion.U, res.expansion.V)
    return {"max_sweeps": k, "sweeps": res.sweeps, "converged": res.converged,
            "seconds": timing.best, "cpu_seconds": timing.best_cpu, "times": timing.wall,
            **err}


def breakdown(A: np.ndarray, rule: str, max_sweeps: int) -> dict[str, Any]:
    """Where the time of one fast-path run goes: QR of V, sweeps, final products."""
    stamps: list[float] = []
    t0 = time.perf_counter()
    e = ss.Expansion.canonical(A)
    t_canon = time.perf_counter() - t0
    t1 = time.perf_counter()
    res = ss.compress(e, rule=rule, max_sweeps=max_sweeps,
                      callback=lambda state: stamps.append(time.perf_counter()))
    total = time.perf_counter() - t1
    t_qr = best_time(lambda: np.linalg.qr(A.T), repeat=1)[0].best
    sweep_times = np.diff([t1, *stamps])
    return {
        "rule": rule, "sweeps": res.sweeps, "canonical_seconds": t_canon,
        "compress_seconds": total,
        "qr_seconds_separate": t_qr,
        "sweep_seconds": sweep_times,
        "first_sweep_minus_qr": float(sweep_times[0] - t_qr) if sweep_times.size else None,
        "after_last_sweep_seconds": float(t1 + total - stamps[-1]) if stamps else None,
    }


def lapack(A: np.ndarray, errors: Errors, driver: str, *, threads: int | None,
           repeat: int, other: Errors | None = None) -> dict[str, Any]:
    """Timed ``scipy.linalg.svd`` and its errors (``other``: reference to use instead).

    ``threads=1`` limits the BLAS/LAPACK thread pools to one thread for the call.
    """

    def fn() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if threads is None:
            return sla.svd(A, lapack_driver=driver)
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=threads, user_api="blas"):
            return sla.svd(A, lapack_driver=driver)

    timing, (U, s, _) = best_time(fn, repeat=repeat, short=SHORT)
    V = A.T @ U  # coefficients of A on the basis U (amplitudes s_i), for the error only
    err = (other or errors).of(U, V)
    err["sv"] = float(np.max(np.abs(s - (other or errors).sigma)) / s[0])
    return {"driver": driver, "threads": threads or "default", "seconds": timing.best,
            "cpu_seconds": timing.best_cpu, "times": timing.wall, **err}


def time_to_levels(points: list[tuple[float, float]]) -> dict[str, float | None]:
    """Smallest time among the points whose error is at most each level."""
    out: dict[str, float | None] = {}
    for lev in LEVELS:
        ok = [t for t, e in points if e <= lev]
        out[f"{lev:g}"] = min(ok) if ok else None
    return out


def _baselines(A: np.ndarray, errors: Errors, lapack_errors: dict[str, Errors] | None,
               repeat: int) -> dict[str, dict[str, Any]]:
    out = {}
    try:
        import threadpoolctl  # noqa: F401

        variants: tuple[tuple[int | None, str], ...] = ((None, ""), (1, "-1t"))
    except ImportError:  # the single-thread baselines need threadpoolctl
        variants = ((None, ""),)
    for driver in ("gesdd", "gesvd"):
        ref = (lapack_errors or {}).get(driver)
        for threads, suffix in variants:
            out[driver + suffix] = lapack(A, errors, driver, threads=threads, repeat=repeat,
                                          other=ref)
    return out


def _ratios(series: dict[str, dict[str, Any]], baselines: dict[str, dict[str, Any]],
            levels: dict[str, dict[str, Any]], ranks: Sequence[int]) -> dict[str, Any]:
    """Times relative to LAPACK gesdd: full accuracy and quasi-optimal bases."""
    gesdd = baselines["gesdd"]["seconds"]
    gesdd1 = baselines.get("gesdd-1t", baselines["gesdd"])["seconds"]
    out: dict[str, Any] = {"gesdd_seconds": gesdd, "gesdd_1t_seconds": gesdd1, "lines": []}
    for label, s in series.items():
        if s["converged"]:
            t = s["runs"][-1]["seconds"]
            out[f"{label}/converged"] = {"seconds": t, "sweeps": s["runs"][-1]["sweeps"],
                                         "x_gesdd": t / gesdd, "x_gesdd_1t": t / gesdd1}
            out["lines"].append(
                f"{label}: converged in {s['runs'][-1]['sweeps']} sweeps, {t:.3g} s = "
                f"{t / gesdd:.1f} x gesdd ({gesdd:.3g} s), {t / gesdd1:.1f} x gesdd-1t "
                f"({gesdd1:.3g} s)")
        elif s["runs"]:
            r = s["runs"][-1]
            out["lines"].append(
                f"{label}: not converged; last run {r['sweeps']} sweeps, {r['seconds']:.3g} s, "
                f"sv error {r['sv']:.2g}" + (" (time cap)" if s["capped"] else ""))
        for k in ranks:
            for lev in ("0.01", "0.0001"):
                t = levels[f"excess{k}"][label].get(lev)
                key = f"{label}/excess{k}<={lev}"
                out[key] = None if t is None else {"seconds": t, "x_gesdd": t / gesdd,
                                                   "x_gesdd_1t": t / gesdd1}
                if t is not None:
                    out["lines"].append(
                        f"{label}: rank-{k} basis within {float(lev):g} of optimal in "
                        f"{t:.3g} s = {t / gesdd:.2f} x gesdd, {t / gesdd1:.2f} x gesdd-1t")
    return out


def _blas_threads(n: int | None) -> contextlib.AbstractContextManager[Any]:
    """Limit the BLAS thread pools to ``n`` threads for the block (no limit for None)."""
    if not n:
        return contextlib.nullcontext()
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=n, user_api="blas")


def _load() -> list[float] | None:
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def _measure(key: str, rank: int | None = None) -> Callable[[dict[str, Any]], float]:
    """Return a function reading one error (its modulus) from a run's record."""

    def get(r: dict[str, Any]) -> float:
        value = r[key] if rank is None else r[key][rank]
        return abs(float(value))

    return get


def study(name: str, A: np.ndarray, errors: Errors, args: argparse.Namespace,
          lapack_errors: dict[str, Errors] | None = None) -> dict[str, Any]:
    """All series and baselines of one matrix."""
    n = A.shape[0]
    t_canon = best_time(lambda: ss.Expansion.canonical(A), repeat=3, short=10.0)[0].best
    load_before = _load()
    baselines = _baselines(A, errors, lapack_errors, args.repeat)
    series: dict[str, dict[str, Any]] = {}
    for method, rule in SERIES:
        if method == "literal" and n > args.literal_max_n:
            continue
        cap = args.literal_cap if method == "literal" else args.run_cap
        label = f"{method}/{rule}"
        series[label] = run_series(A, errors, method, rule, run_cap=cap,
                                   max_sweeps=args.max_sweeps, repeat=args.repeat)
        print(f"  {name}: {label} done ({len(series[label]['runs'])} runs)", flush=True)
    # LAPACK is timed before and after the rotation series (best of both), so that a
    # change of machine load during the study biases neither side
    for label, b in _baselines(A, errors, lapack_errors, args.repeat).items():
        first = baselines[label]
        b["times"] = list(first["times"]) + list(b["times"])
        if first["seconds"] < b["seconds"]:
            b["seconds"], b["cpu_seconds"] = first["seconds"], first["cpu_seconds"]
        baselines[label] = b
    jac = series.get("fast/jacobi")
    conv_k = jac["runs"][-1]["max_sweeps"] if jac and jac["runs"] else 1
    prof = breakdown(A, "jacobi", conv_k)

    measures: dict[str, Callable[[dict[str, Any]], float]] = {"sv": _measure("sv")}
    for k in errors.ranks:
        measures[f"excess{k}"] = _measure("excess", k)
        measures[f"subspace{k}"] = _measure("subspace", k)
    levels: dict[str, dict[str, Any]] = {}
    for mname, get in measures.items():
        levels[mname] = {label: time_to_levels([(r["seconds"], get(r)) for r in s["runs"]])
                         for label, s in series.items()}
        for driver, b in baselines.items():
            levels[mname][driver] = time_to_levels([(b["seconds"], get(b))])
    ratios = _ratios(series, baselines, levels, errors.ranks)
    return {"name": name, "shape": A.shape, "canonical_seconds": t_canon, "ratios": ratios,
            "load_average_before": load_before, "load_average_after": _load(),
            "series": series, "lapack": baselines, "breakdown": prof,
            "time_to_level": levels}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    record = Run("speed_vs_error", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="output directory (default bench/results)")
    parser.add_argument("--data", default=None,
                        help="path of rbs480a.mtx (default ../shared/data/rbs480a.mtx)")
    parser.add_argument("--matrices", default="rbs480a,generated",
                        help="comma-separated subset of rbs480a,generated")
    parser.add_argument("--n", type=int, default=2000, help="size of the generated matrix")
    parser.add_argument("--decades", type=float, default=6.0,
                        help="sigma_n / sigma_1 = 10^-DECADES for the generated matrix")
    parser.add_argument("--seed", type=int, default=20261122)
    parser.add_argument("--ranks", default="20,100", help="target ranks of the basis error")
    parser.add_argument("--max-sweeps", type=int, default=1000)
    parser.add_argument("--run-cap", type=float, default=60.0,
                        help="largest predicted time of one run of a fast series (s)")
    parser.add_argument("--literal-cap", type=float, default=30.0,
                        help="largest predicted time of one run of the literal series (s)")
    parser.add_argument("--repeat", type=int, default=3,
                        help=f"best of REPEAT for runs shorter than {SHORT:g} s")
    parser.add_argument("--blas-threads", type=int, default=None,
                        help="limit BLAS to this many threads for the whole study "
                             "(threadpoolctl; default: as the environment sets it); "
                             "outputs get the suffix _blasN")
    parser.add_argument("--literal-max-n", type=int, default=500,
                        help="run the literal path only when n <= this")
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.matrices.split(",") if s.strip()]
    unknown = sorted(set(names) - {"rbs480a", "generated"})
    if unknown:
        parser.error(f"--matrices accepts rbs480a and generated; got {', '.join(unknown)}")
    if args.n < 4:
        parser.error(f"--n must be >= 4; got {args.n}")
    ranks = [int(k) for k in args.ranks.split(",") if k.strip()]
    out = out_dir(args.out)
    t_start = time.perf_counter()
    # compile (or load) the numba kernels outside the timings
    ss.compress(ss.Expansion.canonical(np.eye(4) + 0.1), max_sweeps=2)

    studies: dict[str, dict[str, Any]] = {}
    suffix = f"_blas{args.blas_threads}" if args.blas_threads else ""
    with _blas_threads(args.blas_threads):
        for name in names:
            t_study = time.perf_counter()
            if name == "rbs480a":
                A = load_rbs480a(args.data)
                U1, s1, _ = sla.svd(A, lapack_driver="gesvd")
                U2, s2, _ = sla.svd(A, lapack_driver="gesdd")
                ref = Errors(A, s1, U1, ranks)
                cross = {"gesvd": Errors(A, s2, U2, ranks), "gesdd": ref}
                st = study(name, A, ref, args, lapack_errors=cross)
                st["reference"] = "LAPACK gesvd (each LAPACK driver against the other)"
            else:
                A, sigma, Q1 = generated_matrix(args.n, args.decades, args.seed)
                st = study(name, A, Errors(A, sigma, Q1, ranks), args)
                st["reference"] = (f"exact: sigma_i = 10^(-{args.decades:g} i/(n-1)), "
                                   f"U = Q1 (Haar, seed {args.seed})")
            studies[name] = st
            st["seconds"] = time.perf_counter() - t_study
            _plot(st, ranks, out / f"speed_vs_error_{name}{suffix}.png")
            record.write(out / f"speed_vs_error_{name}{suffix}.json",
                         {"levels": LEVELS, "ranks": ranks, "args": vars(args), **st,
                          "machine": machine_info()})
            _print_summary(st)
            print(f"wrote speed_vs_error_{name}{suffix}.png and .json to {out} "
                  f"in {st['seconds']:.0f} s")

    data = {"levels": LEVELS, "ranks": ranks, "args": vars(args), "studies": studies,
            "seconds": time.perf_counter() - t_start}
    return data


def _print_summary(st: dict[str, Any]) -> None:
    rows = []
    for label, s in st["series"].items():
        for r in s["runs"]:
            rows.append([label, r["max_sweeps"], r["sweeps"], "yes" if r["converged"] else "",
                         r["seconds"], r["cpu_seconds"], r["sv"],
                         *(r["excess"][k] for k in sorted(r["excess"]))])
    for driver, b in st["lapack"].items():
        rows.append([driver, "-", "-", "-", b["seconds"], b["cpu_seconds"], b["sv"],
                     *(b["excess"][k] for k in sorted(b["excess"]))])
    ranks = sorted(next(iter(st["lapack"].values()))["excess"])
    print_table(["series", "k", "sweeps", "conv", "wall s", "cpu s", "sv err",
                 *(f"excess@{k}" for k in ranks)], rows,
                title=f"{st['name']} {st['shape'][0]}x{st['shape'][1]} "
                      f"(canonical expansion: {st['canonical_seconds'] * 1e3:.1f} ms)")
    for line in st["ratios"]["lines"]:
        print("  " + line)


def _plot(st: dict[str, Any], ranks: Sequence[int], path: Path) -> None:
    plt = pyplot()
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    panels: list[tuple[str, Callable[[dict[str, Any]], float]]] = [
        (r"singular values: $\max_i |s_i-\sigma_i|/\sigma_1$", _measure("sv"))]
    for k in ranks:
        if k in next(iter(st["lapack"].values()))["excess"]:
            panels.append((rf"rank-{k} basis: $\|A-U_kV_k^T\|_F/\|A-A_k\|_F - 1$",
                           _measure("excess", k)))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.3 * len(panels), 4.8), sharex=True)
    axes = np.atleast_1d(axes)
    style = {"fast/paper": ("C0", "o"), "fast/jacobi": ("C3", "s"),
             "literal/jacobi": ("C2", "^")}
    floor = 1e-17
    for ax, (title, get) in zip(axes, panels, strict=True):
        for label, s in st["series"].items():
            col, mk = style.get(label, ("C4", "d"))
            t = [r["seconds"] for r in s["runs"]]
            e = [max(get(r), floor) for r in s["runs"]]
            ax.loglog(t, e, "-", color=col, marker=mk, ms=4, label=f"streamsvd {label}")
            for r, ti, ei in zip(s["runs"], t, e, strict=True):
                if r["max_sweeps"] in (1, 5, 21, 89, 377):
                    ax.annotate(str(r["sweeps"]), (ti, ei), fontsize=7, color=col,
                                xytext=(3, 3), textcoords="offset points")
        for driver, mk, fill in (("gesdd", "*", "k"), ("gesvd", "P", "k"),
                                 ("gesdd-1t", "*", "none"), ("gesvd-1t", "P", "none")):
            if driver not in st["lapack"]:
                continue
            b = st["lapack"][driver]
            ax.loglog([b["seconds"]], [max(get(b), floor)], mk, color="k", mfc=fill, ms=11,
                      label=f"LAPACK {driver}")
        ax.set_title(title, fontsize=10)
        ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("wall time (s), canonical expansion included")
        ax.grid(True, which="major", alpha=0.3)
    axes[0].set_ylabel(f"error (floored at {floor:g})")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9, frameon=False)
    fig.suptitle(f"Time against error, {st['name']} ({st['shape'][0]} x {st['shape'][1]}); "
                 "numbers = sweeps")
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
