"""Engine benchmark: one update of the stream compressor against Brand's incremental SVD.

    python bench/engine_benchmark.py                       # n = 1e5 and 5e4, b = 50, cap 60
    python bench/engine_benchmark.py --quick               # small sizes (a smoke run)

Block updates
-------------
``A = Q1 diag(s) Q2^T`` (``n x m``), ``s`` log-spaced from 1 to 1e-10 over 300 modes; the
stream is a first block of ``cap`` columns, then ``--updates`` blocks of ``b``. Methods,
each fed the same stream, with one BLAS thread and with two (threadpoolctl):

* ``brand``: ``bench/brand.py`` BrandSVD (block CGS2, Householder QR of the residual,
  LAPACK SVD of the core, ``U`` rotated every update);
* ``brand tuned``: TunedBrandSVD (CholeskyQR2, the rotation as one gemm);
* ``streamsvd jacobi conv``: ``StreamCompressor(max_rank=cap, rule="jacobi",
  sweeps=None)``, the exact SVD of the expansion at every update, as Brand;
* ``streamsvd paper 1``: the paper's rule, one sweep per update (the default);
* ``streamsvd left-only``: the same with ``right_vectors=False``.

Every compressor truncates to the cap at every update (``oversampling=0``), as Brand does.

Measured: the median time of an update (updates after the second; best of
``--repeats`` runs alternating the methods), the flop floor ``8 n p b + 4 n b^2 +
2 n (p + b) p`` (two projections, CholeskyQR2, one rotation: what a Brand-style update
needs) over the time (GFLOP/s achieved), the tall-skinny gemm rate of this machine, the
largest relative error of the top ``cap`` singular values against the exact SVD of the
stream (known from the small factor ``diag(s) Q2^T``), ``||U^T U - I||_2`` from the
factor, and the peak of the numpy allocations during the stream (tracemalloc) over the
data's size.

Long stream
-----------
``--long-updates`` (1e5) single-column updates at ``n = 1000``, cap 20, paper rule, one
sweep, with and without right vectors: the mean update time of the first and the last
1000 updates (wall clock, and the CPU time of the thread with one BLAS thread, which a
shared machine disturbs far less), and ``||U^T U - I||_2`` computed from
``left_vectors`` every ``--long-every`` updates.

Writes ``bench/results/engine_benchmark.{json,png}``.
"""

from __future__ import annotations

import argparse
import logging
import math
import time
import tracemalloc
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot
from _suite import read_payload
from brand import BrandSVD, TunedBrandSVD
from threadpoolctl import threadpool_limits

import streamsvd as ss

logger = logging.getLogger("engine_benchmark")


def orthonormal(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """CholeskyQR2 of a Gaussian ``n x k`` matrix (orthonormal to ~1e-15)."""
    Q = rng.standard_normal((n, k))
    for _ in range(2):
        L = np.linalg.cholesky(Q.T @ Q)
        Q = np.linalg.solve(L, Q.T).T
    return Q


def make_stream(n: int, m: int, rank: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``A = Q1 diag(s) Q2^T``, ``s`` and ``Q2``."""
    rng = np.random.default_rng(seed)
    s = np.logspace(0, -10, rank)
    Q1 = orthonormal(rng, n, rank)
    Q2 = orthonormal(rng, m, rank)
    return np.asfortranarray((Q1 * s) @ Q2.T), s, Q2


def gemm_rate(n: int, p: int, b: int) -> float:
    """GFLOP/s of the tall-skinny products an update makes (best of 5)."""
    rng = np.random.default_rng(0)
    Q = np.asfortranarray(rng.standard_normal((n, p)))
    X = np.asfortranarray(rng.standard_normal((n, b)))
    best = math.inf
    for _ in range(5):
        t = time.perf_counter()
        C = Q.T @ X
        X -= Q @ C
        best = min(best, time.perf_counter() - t)
    return 4 * n * p * b / best / 1e9


def floor_flops(n: int, p: int, b: int) -> float:
    """Flops of a Brand-style update: CGS2, CholeskyQR2, one rotation."""
    return 8.0 * n * p * b + 4.0 * n * b * b + 2.0 * n * (p + b) * p


def methods(n: int, cap: int, m: int, b: int) -> dict[str, Callable[[], Any]]:
    """Constructors of the compared methods."""
    return {
        "brand": lambda: BrandSVD(n, rank=cap, max_columns=m, max_block=max(b, cap)),
        "brand tuned": lambda: TunedBrandSVD(n, rank=cap, max_columns=m, max_block=max(b, cap)),
        "streamsvd jacobi conv": lambda: ss.StreamCompressor(
            n, max_rank=cap, oversampling=0, rule="jacobi", sweeps=None),
        "streamsvd paper 1": lambda: ss.StreamCompressor(
            n, max_rank=cap, oversampling=0, rule="paper", sweeps=1),
        "streamsvd left-only": lambda: ss.StreamCompressor(
            n, max_rank=cap, oversampling=0, rule="paper", sweeps=1, right_vectors=False),
    }


def left_and_sv(obj: Any) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(obj, ss.StreamCompressor):
        return obj.left_vectors, obj.amplitudes
    return obj.U, obj.s


def run_stream(make: Callable[[], Any], A: np.ndarray, cap: int, b: int) -> dict[str, Any]:
    times = []
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    obj = make()  # inside the traced region: preallocated buffers count too
    starts = [0, *range(cap, A.shape[1], b)]
    for i, a in enumerate(starts):
        stop = cap if i == 0 else min(a + b, A.shape[1])
        block = A[:, a:stop]
        t = time.perf_counter()
        obj.absorb(block)
        times.append(time.perf_counter() - t)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    U, sv = left_and_sv(obj)
    return {"times": times, "peak_bytes": peak, "U": U, "sv": sv}


def block_benchmark(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    for n in args.n:
        m = args.cap + args.updates * args.b
        A, s, Q2 = make_stream(n, m, args.rank, args.seed)
        exact = np.linalg.svd(s[:, None] * Q2.T, compute_uv=False)[: args.cap]
        for threads in args.threads:
            rate = None
            with threadpool_limits(limits=threads, user_api="blas"):
                rate = gemm_rate(n, args.cap, args.b)
                found: dict[str, dict[str, Any]] = {}
                names = list(methods(n, args.cap, m, args.b))
                for rep in range(args.repeats):
                    order = names if rep % 2 == 0 else names[::-1]
                    for name in order:
                        res = run_stream(methods(n, args.cap, m, args.b)[name], A,
                                         args.cap, args.b)
                        prev = found.get(name)
                        if prev is None:
                            found[name] = res
                        else:
                            prev["times"] = np.minimum(prev["times"], res["times"]).tolist()
                            prev["peak_bytes"] = max(prev["peak_bytes"], res["peak_bytes"])
            floor = floor_flops(n, args.cap, args.b)
            for name, res in found.items():
                med = float(np.median(res["times"][2:]))
                U, sv = res["U"], res["sv"]
                rows.append({
                    "n": n, "b": args.b, "cap": args.cap, "threads": threads, "method": name,
                    "median_update_s": med, "gflops_floor": floor / med / 1e9,
                    "gemm_gflops": rate,
                    "sv_rel_error": float(np.max(np.abs(sv[: args.cap] - exact) / exact)),
                    "orthogonality": float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2)),
                    "peak_over_data": res["peak_bytes"] / A.nbytes,
                    "peak_bytes": res["peak_bytes"],
                })
                logger.info("n=%d threads=%d %s: %.4f s", n, threads, name, med)
        del A
    return rows


def long_stream(args: argparse.Namespace) -> dict[str, Any]:
    n, cap, total = 1000, 20, args.long_updates
    rng = np.random.default_rng(args.seed + 1)
    Q1 = orthonormal(rng, n, 100)
    s = np.logspace(0, -6, 100)
    out: dict[str, Any] = {}
    for label, right in (("with V", True), ("left-only", False)):
        sc = ss.StreamCompressor(n, max_rank=cap, oversampling=0, rule="paper", sweeps=1,
                                 right_vectors=right)
        times = np.empty(total)
        cpu = np.empty(total)
        ortho = []
        chunk = 1000
        with threadpool_limits(limits=1, user_api="blas"):
            for start in range(0, total, chunk):
                Z = (Q1 * s) @ rng.standard_normal((100, chunk))
                for j in range(chunk):
                    t, c = time.perf_counter(), time.thread_time()
                    sc.absorb(Z[:, j : j + 1])
                    cpu[start + j] = time.thread_time() - c
                    times[start + j] = time.perf_counter() - t
                if (start + chunk) % args.long_every == 0 or start + chunk >= total:
                    U = sc.left_vectors
                    err = float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2))
                    ortho.append((start + chunk, err))
        first, last = float(np.mean(times[:1000])), float(np.mean(times[-1000:]))
        first_cpu, last_cpu = float(np.mean(cpu[:1000])), float(np.mean(cpu[-1000:]))
        out[label] = {
            "first_1000_mean_s": first, "last_1000_mean_s": last, "ratio": last / first,
            "first_1000_cpu_s": first_cpu, "last_1000_cpu_s": last_cpu,
            "cpu_ratio": last_cpu / first_cpu,
            "cpu_per_1000": [float(np.mean(cpu[i : i + 1000])) for i in range(0, total, 1000)],
            "orthogonality": ortho, "max_orthogonality": max(o for _, o in ortho),
            "limit_50_n_eps": 50 * n * np.finfo(float).eps,
            "mean_per_1000": [float(np.mean(times[i : i + 1000])) for i in range(0, total, 1000)],
        }
        logger.info("long stream %s: first %.2e s, last %.2e s", label, first, last)
    return out


def plot(rows: list[dict[str, Any]], long: dict[str, Any], path: Any) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 3, figsize=(17, 4.8))
    configs = sorted({(r["n"], r["threads"]) for r in rows})
    names = list(dict.fromkeys(r["method"] for r in rows))
    width = 0.8 / max(len(names), 1)
    for k, name in enumerate(names):
        vals = [next(r["median_update_s"] for r in rows if (r["n"], r["threads"]) == c
                     and r["method"] == name) * 1e3 for c in configs]
        ax[0].bar(np.arange(len(configs)) + k * width, vals, width, label=name)
    ax[0].set_xticks(np.arange(len(configs)) + 0.4 - width / 2,
                     [f"n={n:.0e}\n{t} thread{'s' * (t > 1)}" for n, t in configs])
    ax[0].set(ylabel="median time per update of 50 columns (ms)",
              title="block update, cap 60 (lower is better)")
    ax[0].legend(fontsize=8)
    for label, res in long.items():
        per = np.array(res["mean_per_1000"]) * 1e6
        x = np.arange(1, per.size + 1) * 1000
        line = ax[1].plot(x, per, alpha=0.5, label=f"{label}: wall clock")[0]
        ax[1].plot(x, np.array(res["cpu_per_1000"]) * 1e6, color=line.get_color(),
                   label=f"{label}: CPU time of the thread")
        o = np.array(res["orthogonality"])
        ax[2].semilogy(o[:, 0], o[:, 1], "o-", label=label)
    ax[1].set(xlabel="updates (single columns, n = 1000, cap 20)",
              ylabel="mean time per update (µs, per 1000 updates)",
              title="long stream: cost per update")
    ax[1].set_ylim(bottom=0)
    ax[1].legend()
    lim = 50 * 1000 * np.finfo(float).eps
    ax[2].axhline(lim, color="k", ls="--", label="50 n eps")
    ax[2].set(xlabel="updates", ylabel="||U^T U - I||_2 (from the factor)",
              title="long stream: orthogonality")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    record = Run("engine_benchmark", argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", default="100000,50000", help="snapshot sizes")
    p.add_argument("--b", type=int, default=50, help="columns per update")
    p.add_argument("--cap", type=int, default=60, help="rank kept")
    p.add_argument("--rank", type=int, default=300, help="modes of the data")
    p.add_argument("--updates", type=int, default=16, help="updates after the first block")
    p.add_argument("--threads", default="1,2", help="BLAS threads")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--long-updates", type=int, default=100000)
    p.add_argument("--long-every", type=int, default=10000)
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    p.add_argument("--only", choices=("block", "long"), help="run one of the two parts")
    p.add_argument("--out", default=None)
    p.add_argument("--seed", type=int, default=20261201)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logger.setLevel(logging.INFO)
    if args.quick:
        args.n, args.updates, args.long_updates, args.long_every = "3000", 4, 3000, 1000
        args.repeats, args.rank = 1, 80
    args.n = [int(float(x)) for x in str(args.n).split(",")]
    args.threads = [int(x) for x in str(args.threads).split(",")]
    rows = block_benchmark(args) if args.only in (None, "block") else []
    long = long_stream(args) if args.only in (None, "long") else {}
    out = out_dir(args.out)
    name = "engine_benchmark_quick" if args.quick else "engine_benchmark"
    previous = out / f"{name}.json"
    if args.only and previous.exists():  # keep the part that was not run again
        old = read_payload(previous)
        rows = rows or old.get("block", [])
        long = long or old.get("long", {})
    plot(rows, long, out / f"{name}.png")
    result = {"machine": machine_info(), "args": {k: v for k, v in vars(args).items()},
              "block": rows, "long": long}
    record.write(out / f"{name}.json", result)
    print_table(
        ["n", "thr", "method", "ms/update", "GFLOP/s (floor)", "gemm GFLOP/s", "sv err",
         "orth", "peak/data"],
        [[r["n"], r["threads"], r["method"], f"{1e3 * r['median_update_s']:.1f}",
          f"{r['gflops_floor']:.1f}", f"{r['gemm_gflops']:.1f}", f"{r['sv_rel_error']:.1e}",
          f"{r['orthogonality']:.1e}", f"{r['peak_over_data']:.2f}"] for r in rows],
        title="block updates",
    )
    print_table(
        ["stream", "first 1000 (µs)", "last 1000 (µs)", "last/first", "CPU first (µs)",
         "CPU last (µs)", "CPU last/first", "max ||U^T U - I||"],
        [[k, f"{1e6 * v['first_1000_mean_s']:.1f}", f"{1e6 * v['last_1000_mean_s']:.1f}",
          f"{v['ratio']:.2f}", f"{1e6 * v['first_1000_cpu_s']:.1f}",
          f"{1e6 * v['last_1000_cpu_s']:.1f}", f"{v['cpu_ratio']:.2f}",
          f"{v['max_orthogonality']:.1e}"] for k, v in long.items()],
        title="long stream (n = 1000, cap 20, single columns)",
    )
    return result


if __name__ == "__main__":
    main()
