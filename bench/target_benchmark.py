"""Certified POD at a relative target error on the engine benchmark's stream, every mode.

    python bench/target_benchmark.py            # n = 20000, m = 2000, blocks of 100
    python bench/target_benchmark.py --quick    # small sizes (a smoke run)

The stream of ``bench/engine_benchmark.py`` (``A = Q1 diag(s) Q2^T``, ``s`` log-spaced
from 1 to 1e-10 over 300 modes) is compressed with ``target_error=eps``,
``error_measure="relative"`` (``||A - U V^T||_F <= eps ||A||_F``) at eps = 1e-2 ... 1e-6,
in memory (``StreamCompressor``, Jacobi rule converged), in the tall mode
(``tall_compress``) and in the tree mode (``tree_compress``, leaves of 5 blocks), each
then ``finalize()``d. Reported per target and mode: the modes kept against the optimum
(the fewest ``k`` with ``||s[k:]|| <= eps ||s||``, from the exact spectrum), the true
relative error ``||A - U V^T|| / ||A||``, the final bound over the true error, the
largest ratio of the true error to the bound over the updates (memory mode, measured
after every update: it must stay <= 1), and the time (one BLAS thread; the true errors
are measured outside the timed runs).

Writes ``bench/results/target_benchmark.{json,png}``.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot
from engine_benchmark import make_stream
from threadpoolctl import threadpool_limits

import streamsvd as ss
from streamsvd.parallel.cluster import tall_compress, tree_compress

logger = logging.getLogger("target_benchmark")
TARGETS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
KW = {"error_measure": "relative", "rule": "jacobi", "sweeps": None}


def optimal_modes(s: np.ndarray, target: float) -> int:
    """The fewest ``k`` with ``||s[k:]|| <= target ||s||``."""
    tail = np.sqrt(np.append(np.cumsum((s * s)[::-1])[::-1], 0.0))
    return int(np.flatnonzero(tail <= target * tail[0])[0])


def run_mode(mode: str, A: np.ndarray, target: float, block: int) -> tuple[Any, float]:
    """Compress ``A`` in ``mode``; return the finalised compressor and the seconds."""
    t0 = time.perf_counter()
    if mode == "memory":
        sc = ss.StreamCompressor(A.shape[0], target_error=target, **KW)
        for j in range(0, A.shape[1], block):
            sc.absorb(A[:, j : j + block])
    elif mode == "tall":
        sc = tall_compress(A, block=block, chunk_rows=4096, target_error=target, **KW)
    else:
        sc = tree_compress(A, block=block, leaf_columns=5 * block, target_error=target, **KW)
    sc.finalize()
    return sc, time.perf_counter() - t0


def worst_ratio_over_updates(A: np.ndarray, target: float, block: int) -> float:
    """Largest ``||A_j - U V^T|| / bound`` over the updates of the memory mode."""
    sc = ss.StreamCompressor(A.shape[0], target_error=target, **KW)
    worst = 0.0
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
        E = sc.expansion
        err = float(np.linalg.norm(A[:, : j + block] - E.U @ E.V.T))
        if sc.error_bound > 0:
            worst = max(worst, err / sc.error_bound)
    return worst


def factors(sc: Any) -> tuple[np.ndarray, np.ndarray]:
    if hasattr(sc, "factors"):
        U, V = sc.factors()
        return np.asarray(U), V
    E = sc.expansion
    return E.U, E.V


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    record = Run("target_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--m", type=int, default=2000)
    ap.add_argument("--block", type=int, default=100)
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.m, args.block = 600, 200, 20
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("streamsvd").setLevel(logging.WARNING)
    A, s = make_stream(args.n, args.m, 300 if not args.quick else 100, seed=0)[:2]
    norm_A = float(np.linalg.norm(s))
    rows, results = [], []
    with threadpool_limits(limits=1):
        for target in TARGETS:
            opt = optimal_modes(s, target)
            worst = worst_ratio_over_updates(A, target, args.block)
            for mode in ("memory", "tall", "tree"):
                sc, seconds = run_mode(mode, A, target, args.block)
                U, V = factors(sc)
                err = float(np.linalg.norm(A - U @ V.T))
                r = {"target": target, "mode": mode, "modes": sc.rank, "optimum": opt,
                     "true_error": err / norm_A, "bound_over_true": sc.error_bound / err,
                     "bound_relative": sc.error_in_measure, "seconds": seconds,
                     "worst_true_over_bound": worst if mode == "memory" else None,
                     "load": os.getloadavg()[0]}
                results.append(r)
                rows.append([f"{target:g}", mode, sc.rank, opt, f"{err / norm_A:.3e}",
                             f"{r['bound_over_true']:.3f}",
                             "" if r["worst_true_over_bound"] is None else f"{worst:.4f}",
                             f"{seconds:.2f}", f"{r['load']:.1f}"])
                logger.info("target %g %s: %d modes (optimum %d) in %.2f s", target, mode,
                            sc.rank, opt, seconds)
                sc.close(finalize=False)
    print_table(["target", "mode", "modes", "optimum", "true rel. error", "bound/true",
                 "max true/bound", "time s", "load"], rows,
                title=f"\nrelative target, {args.n} x {args.m}, blocks of {args.block}")
    data = {"machine": machine_info(), "n": args.n, "m": args.m, "block": args.block,
            "results": results}
    out = out_dir(args.out)
    record.write(out / "target_benchmark.json", data)
    plot(results, out / "target_benchmark.png")
    return data


def plot(results: list[dict[str, Any]], path: Any) -> None:
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10.5, 4.0))
    for i, mode in enumerate(("memory", "tall", "tree")):
        rs = [r for r in results if r["mode"] == mode]
        t = [r["target"] for r in rs]
        ax1.semilogx(t, [r["modes"] - r["optimum"] for r in rs], "os^"[i] + "-",
                     label=mode, alpha=0.8)
        ax2.loglog(t, [r["true_error"] for r in rs], "os^"[i] + "-", label=f"{mode}: true",
                   alpha=0.8)
        ax2.loglog(t, [r["bound_relative"] for r in rs], "os^"[i] + "--",
                   label=f"{mode}: bound", alpha=0.5)
    t = sorted({r["target"] for r in results})
    ax2.loglog(t, t, "k:", lw=1, label="target")
    ax1.set_xlabel("relative target error")
    ax1.set_ylabel("modes kept - optimal modes")
    ax1.set_title("modes over the optimum")
    ax1.legend(fontsize=8)
    ax2.set_xlabel("relative target error")
    ax2.set_ylabel("relative error ||A - U V^T|| / ||A||")
    ax2.set_title("true error and certified bound")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
