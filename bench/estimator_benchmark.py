"""Estimator benchmark: the cost of ``partial_fit`` against the samples already seen.

    python bench/estimator_benchmark.py            # 2e5 samples of 300 features, batches of 10
    python bench/estimator_benchmark.py --quick    # a smoke run

``StreamingSVD(n_components=20)`` and scikit-learn's ``IncrementalPCA(n_components=20)``
(when installed) receive the same batches of ``--batch`` rows (samples) of a rank-100
matrix (a first call of 100, since the first call needs at least ``n_components``
samples); the mean time of a ``partial_fit`` call is recorded over windows of 200 calls
around each checkpoint of ``--checkpoints`` samples seen, with one BLAS thread
(threadpoolctl) and the CPU time of the thread beside the wall clock.

Writes ``bench/results/estimator_benchmark.{json,png}``.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot
from threadpoolctl import threadpool_limits

from streamsvd.sklearn.estimator import StreamingSVD

logger = logging.getLogger("estimator_benchmark")


def run(make: Any, X: np.ndarray, batch: int, checkpoints: list[int], window: int) -> dict:
    est = make()
    est.partial_fit(X[:100])  # the first call needs at least n_components samples
    wall, cpu, seen = [], [], []
    targets = iter(sorted(checkpoints))
    nxt = next(targets, None)
    rows = 100
    while nxt is not None and rows < X.shape[0]:
        t, c = time.perf_counter(), time.thread_time()
        est.partial_fit(X[rows : rows + batch])
        wall.append(time.perf_counter() - t)
        cpu.append(time.thread_time() - c)
        rows += batch
        seen.append(rows)
        if rows >= nxt + window * batch:
            nxt = next(targets, None)
    wall_a, cpu_a, seen_a = np.array(wall), np.array(cpu), np.array(seen)
    out = {}
    for cp in checkpoints:
        sel = (seen_a > cp) & (seen_a <= cp + window * batch)
        if sel.any():
            out[str(cp)] = {"wall_s": float(np.mean(wall_a[sel])),
                            "cpu_s": float(np.mean(cpu_a[sel]))}
    return out


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    record = Run("estimator_benchmark", argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--features", type=int, default=300)
    p.add_argument("--batch", type=int, default=10)
    p.add_argument("--checkpoints", default="5000,50000,200000")
    p.add_argument("--window", type=int, default=200, help="calls averaged per checkpoint")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    if args.quick:
        args.features, args.checkpoints, args.window = 40, "200,2000", 20
    cps = [int(float(x)) for x in args.checkpoints.split(",")]
    rng = np.random.default_rng(0)
    total = max(cps) + args.window * args.batch
    X = (rng.standard_normal((total, 100)) * np.logspace(0, -4, 100)) @ rng.standard_normal(
        (100, args.features))
    makers = {"StreamingSVD": lambda: StreamingSVD(n_components=20)}
    try:
        from sklearn.decomposition import IncrementalPCA

        makers["IncrementalPCA"] = lambda: IncrementalPCA(n_components=20)
    except ImportError:  # scikit-learn is a test extra
        logger.warning("scikit-learn is not installed: IncrementalPCA is not measured")
    results = {}
    with threadpool_limits(limits=1, user_api="blas"):
        for name, make in makers.items():
            results[name] = run(make, X, args.batch, cps, args.window)
    out = out_dir(args.out)
    name = "estimator_benchmark_quick" if args.quick else "estimator_benchmark"
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, res in results.items():
        xs = [int(k) for k in res]
        ax.loglog(xs, [1e3 * res[k]["cpu_s"] for k in res], "o-", label=f"{label} (CPU)")
        ax.loglog(xs, [1e3 * res[k]["wall_s"] for k in res], "x--", alpha=0.5,
                  label=f"{label} (wall clock)")
    ax.set(xlabel="samples seen before the call", ylabel=f"time per partial_fit of "
           f"{args.batch} samples (ms)", title=f"{args.features} features, 20 components")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=110)
    plt.close(fig)
    report = {"machine": machine_info(), "args": vars(args), "results": results}
    record.write(out / f"{name}.json", report)
    rows = []
    for label, res in results.items():
        first, last = res[str(cps[0])], res[str(cps[-1])]
        rows.append([label] + [f"{1e3 * res[str(c)]['cpu_s']:.3f}" for c in cps]
                    + [f"{last['cpu_s'] / first['cpu_s']:.2f}"])
    print_table(["estimator"] + [f"CPU ms at {c}" for c in cps] + ["last/first"], rows,
                title="partial_fit cost against samples seen")
    return report


if __name__ == "__main__":
    main()
