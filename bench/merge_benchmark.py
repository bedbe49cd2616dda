"""A merge of two compressors: the Gram path against the exact path, time and accuracy.

```
python bench/merge_benchmark.py [--n 200000] [--m 1000] [--repeat 3] [--out DIR] [--quick]
```

The root merge of the out-of-core benchmark's tree (two leaves of ``m / 2`` columns,
blocks of 100, ``max_rank=60`` with the tree's oversampling of 20: 80 terms each), on
``A = U diag(s) V^T`` (rank 200, ``s`` from 1 to 1e-10, ``U``, ``V`` orthonormal, in
memory). ``StreamCompressor.merge`` takes the Gram path
(:func:`streamsvd.engine.update_gram.plan_merge_by_gram`) when the cut allows it; the exact
path (:func:`streamsvd.engine.update.plan_merge`: the other's left vectors orthonormalised
against the basis, the core converged by sweeps) is timed by disabling the Gram path in
this process. Each path merges once untimed (the sweeps' compiled kernels load on first
use), then ``--repeat`` times; the median is reported, with one BLAS thread. The accuracy
of each merged expansion, cut to rank 60: its error over the optimum
``sqrt(sum_{i>60} s_i^2)``, its largest singular-value error relative to ``s_1``, and
``||U^T U - I||_2`` measured from the factors.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import time
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot
from threadpoolctl import threadpool_limits

import streamsvd.stream.updates as stream_module
from streamsvd import StreamCompressor

RANK, OVERSAMPLING, BLOCK, SIGNAL = 60, 20, 100, 200


def make_matrix(n: int, m: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return ``A`` (``n x m``, column-major) and its singular values."""
    rng = np.random.default_rng(seed)
    s = np.logspace(0, -10, SIGNAL)
    U, _ = np.linalg.qr(rng.standard_normal((n, SIGNAL)))
    V, _ = np.linalg.qr(rng.standard_normal((m, SIGNAL)))
    return np.asfortranarray((U * s) @ V.T), s


def leaf(A: np.ndarray, a: int, b: int) -> StreamCompressor:
    """Compress columns ``a:b`` as a leaf of the tree does."""
    sc = StreamCompressor(A.shape[0], max_rank=RANK, oversampling=OVERSAMPLING)
    for j in range(a, b, BLOCK):
        sc.absorb(A[:, j:j + BLOCK])
    return sc


def merged(left: StreamCompressor, right: StreamCompressor) -> tuple[StreamCompressor, float]:
    """Return ``left`` copied with ``right`` merged in, and the seconds of the merge."""
    out = left.copy()
    t0 = time.perf_counter()
    out.merge(right, spend_target=False)
    return out, time.perf_counter() - t0


def accuracy(sc: StreamCompressor, A: np.ndarray, s: np.ndarray) -> dict[str, float]:
    """Return the error over the optimum, the singular-value error and the orthogonality."""
    sc = sc._copy_with(oversampling=0)
    sc.finalize(max_rank=RANK)
    U, V = sc.expansion.U, sc.expansion.V
    err = float(np.linalg.norm(A - U @ V.T))
    opt = float(np.sqrt(np.sum(s[RANK:] ** 2)))
    amps = sc.amplitudes
    return {"err_over_opt": err / opt,
            "sv_error": float(np.max(np.abs(amps[:RANK] - s[:RANK])) / s[0]),
            "orthogonality": float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2))}


def run(n: int, m: int, repeat: int) -> dict[str, Any]:
    """Time both paths on one pair of leaves; return the report."""
    A, s = make_matrix(n, m)
    with threadpool_limits(limits=1):
        left, right = leaf(A, 0, m // 2), leaf(A, m // 2, m)
        gram_path = stream_module.plan_merge_by_gram
        rows = []
        for path in ("gram", "exact"):
            stream_module.plan_merge_by_gram = (
                gram_path if path == "gram" else (lambda *args, **kwargs: None))
            try:
                out, _ = merged(left, right)  # warm-up: kernels load on first use
                times = [merged(left, right)[1] for _ in range(repeat)]
            finally:
                stream_module.plan_merge_by_gram = gram_path
            record = out.history[-1]
            rows.append({"path": path, "seconds": statistics.median(times), "runs": times,
                         "passes": record.passes, "sweeps": record.sweeps,
                         "bound": out.error_bound, "load": os.getloadavg()[0],
                         **accuracy(out, A, s)})
    return {"n": n, "m": m, "rank": RANK, "oversampling": OVERSAMPLING, "rows": rows,
            "machine": machine_info()}


def plot(report: dict[str, Any], path: Any) -> None:
    """Draw the merge time of each path, annotated with its error over the optimum."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    rows = report["rows"]
    ax.bar([r["path"] for r in rows], [r["seconds"] for r in rows], color=["C0", "C1"])
    for i, r in enumerate(rows):
        ax.annotate(f"err/opt {r['err_over_opt']:.7f}\n{r['passes']} passes, "
                    f"{r['sweeps']} sweeps", (i, r["seconds"]), ha="center", va="bottom",
                    fontsize=8)
    ax.set_ylabel("merge time (s, median, 1 BLAS thread)")
    ax.set_xlabel("merge path")
    ax.set_title(f"merge of two {report['n']} x {report['m'] // 2} leaves (80 terms each)",
                 fontsize=9)
    ax.set_ylim(0, 1.3 * max(r["seconds"] for r in rows))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("merge_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200000)
    ap.add_argument("--m", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.m, args.repeat = 3000, 400, 1
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("streamsvd").setLevel(logging.WARNING)
    report = run(args.n, args.m, args.repeat)
    print_table(["path", "seconds", "passes", "sweeps", "err/opt", "sv error", "||U^T U - I||",
                 "load"],
                [[r["path"], f"{r['seconds']:.3f}", r["passes"], r["sweeps"],
                  f"{r['err_over_opt']:.7f}", f"{r['sv_error']:.1e}",
                  f"{r['orthogonality']:.1e}", f"{r['load']:.1f}"] for r in report["rows"]],
                title=f"merge, {args.n} x {args.m}")
    out = out_dir(args.out)
    record.write(out / "merge_benchmark.json", report)
    plot(report, out / "merge_benchmark.png")
    return report


if __name__ == "__main__":
    main()
