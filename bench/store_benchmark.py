"""Store benchmark: the cost of a commit against the number of snapshots already absorbed.

    python bench/store_benchmark.py                      # m = 1e3 ... 1e5, n = 100, b = 5
    python bench/store_benchmark.py --ms 1000,10000 --updates 20
    python bench/store_benchmark.py --inner mass         # in a sparse mass-matrix product

Setup
-----
For each ``m`` (``--ms``), a :class:`streamsvd.StreamCompressor` (``n`` = ``--n``, 100,
``max_rank`` = ``--max-rank``, 20) absorbs ``m`` snapshots in memory in blocks of 500,
then is saved to a new store (:meth:`~streamsvd.StreamCompressor.save`, timed as the
first commit), then absorbs ``--updates`` (40) blocks of ``b`` = ``--block`` (5) columns,
committing after each one, as the command line does by default. The snapshots are
``Q1 diag(s) z_j + 1e-3 g_j`` (``Q1`` orthonormal ``n x 40``, ``s`` log-spaced from 1 to
1e-4, ``z_j`` and ``g_j`` Gaussian), so every block brings new directions and the basis is
compacted from time to time. A copy of the compressor without a store absorbs the same
blocks: the update's own cost. With ``--inner mass`` the basis is orthonormal in the
product of a tridiagonal sparse SPD matrix (a P1 mass matrix on a uniform 1-D mesh),
whose data the store keeps: written by the first commit (the save), kept by the others.

Measures
--------
Per update: wall time of the commit (``BasisStore.commit``, everything from the arrays to
the pointer switch and the pruning, ``fsync`` included), of the whole update with its
commit, and of the same update in memory; the elements the commit wrote
(``BasisStore.last_written``; 8 bytes each). Reported: median, 90th percentile and
largest over the updates. The store lives in ``--dir`` (a temporary directory by default,
on the file system of ``/tmp``), whose ``fsync`` cost dominates a commit.

The same script measures the previous layout (every commit rewrote all arrays): run it
with ``PYTHONPATH`` pointing at a checkout of streamsvd before format version 2 (the
written bytes are then not counted, NaN in the JSON) and ``--out`` elsewhere.

Writes ``store_benchmark.json`` and ``store_benchmark.png`` to ``--out``
(``store_benchmark_mass.*`` with ``--inner mass``).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

from _common import Run, machine_info, out_dir, print_table, pyplot  # noqa: E402
from _suite import read_payload  # noqa: E402

from streamsvd import StreamCompressor  # noqa: E402

_LOAD_BLOCK = 500


@contextlib.contextmanager
def timed_commits(store: Any) -> Iterator[list[float]]:
    """Time every ``store.commit`` while the block runs; yield the list of seconds."""
    seconds: list[float] = []
    real_commit = store.commit

    def timed_commit(*a: Any, **kw: Any) -> int:
        t = time.perf_counter()
        try:
            return real_commit(*a, **kw)
        finally:
            seconds.append(time.perf_counter() - t)

    store.commit = timed_commit
    try:
        yield seconds
    finally:
        store.commit = real_commit



def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=None, help="output directory (default bench/results)")
    p.add_argument("--dir", default=None, help="directory for the stores (default: a temp dir)")
    p.add_argument("--ms", default="1000,3000,10000,30000,100000",
                   help="snapshots absorbed before the timed commits (comma separated)")
    p.add_argument("--n", type=int, default=100, help="snapshot size")
    p.add_argument("--block", type=int, default=5, help="columns per timed update")
    p.add_argument("--updates", type=int, default=40, help="timed updates per m")
    p.add_argument("--max-rank", type=int, default=20, help="max_rank of the compressor")
    p.add_argument("--inner", choices=("euclidean", "mass"), default="euclidean",
                   help="inner product: Euclidean, or a sparse 1-D P1 mass matrix")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--baseline", default=None,
                   help="JSON of a run with the previous layout, plotted for comparison")
    return p.parse_args(argv)


def _columns(Q1: np.ndarray, s: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` snapshots ``Q1 diag(s) z + 1e-3 g``."""
    Z = rng.standard_normal((Q1.shape[1], count))
    return (Q1 * s) @ Z + 1e-3 * rng.standard_normal((Q1.shape[0], count))


def _mass(n: int) -> sp.csr_array:
    """The P1 mass matrix of ``n`` interior nodes of a uniform mesh of [0, 1]."""
    ones = np.ones(n)
    h = 1.0 / (n + 1)
    return sp.csr_array(sp.diags_array([ones[:-1] / 6, 4 * ones / 6, ones[:-1] / 6],
                                       offsets=[-1, 0, 1]) * h)


def _summary(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {
        "median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
        "max": float(a.max()), "mean": float(a.mean()),
    }


def run_one(m: int, args: argparse.Namespace, root: Path) -> dict[str, Any]:
    """Absorb ``m`` snapshots, save, then time ``args.updates`` updates with commits."""
    rng = np.random.default_rng([args.seed, m])
    n = args.n
    k = min(40, n)
    Q1 = np.linalg.qr(rng.standard_normal((n, k)))[0]
    s = np.logspace(0, -4, k)
    inner = _mass(n) if args.inner == "mass" else None
    sc = StreamCompressor(n, inner=inner, max_rank=args.max_rank, oversampling=0)
    for j in range(0, m, _LOAD_BLOCK):
        sc.absorb(_columns(Q1, s, min(_LOAD_BLOCK, m - j), rng))
    memory = sc.copy()
    path = root / f"m{m}.zarr"
    t0 = time.perf_counter()
    sc.save(path)
    save_seconds = time.perf_counter() - t0
    assert sc._life.persistence is not None
    store = sc._life.persistence.handle
    blocks = [_columns(Q1, s, args.block, rng) for _ in range(args.updates)]
    with_store, in_memory, written = [], [], []
    with timed_commits(store) as commit_times:
        for B in blocks:
            t = time.perf_counter()
            sc.absorb(B)
            with_store.append(time.perf_counter() - t)
            # a store of the previous layout (format version 1) does not count: NaN
            counts = getattr(store, "last_written", None)
            written.append(math.nan if counts is None else 8 * sum(counts.values()))
            t = time.perf_counter()
            memory.absorb(B)
            in_memory.append(time.perf_counter() - t)
    same = bool(np.array_equal(sc.expansion.U, memory.expansion.U))
    rows = sc._life.state.rows
    assert rows is not None
    v0_bytes = 8 * rows.m * rows.width
    sc.close(finalize=False)  # the streamed state, as the in-memory copy holds it
    with StreamCompressor.open(path, mode="r") as back:
        resumed = bool(np.array_equal(back.expansion.V, memory.expansion.V))
    shutil.rmtree(path, ignore_errors=True)
    return {
        "m": m, "n": n, "block": args.block, "updates": args.updates, "inner": args.inner,
        "rank": memory.rank, "stored_width": memory._life.state.basis.width,
        "V0_bytes": v0_bytes, "save_seconds": save_seconds,
        "commit_seconds": _summary(commit_times),
        "update_with_commit_seconds": _summary(with_store),
        "update_in_memory_seconds": _summary(in_memory),
        "written_bytes": _summary([float(w) for w in written]),
        "commit_seconds_all": commit_times, "written_bytes_all": written,
        "same_as_in_memory": same, "store_reopens_bit_for_bit": resumed,
    }


def _plot(
    results: list[dict[str, Any]], baseline: list[dict[str, Any]] | None, path: Path
) -> None:
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.4))
    curves = [
        (results, "commit_seconds", "commit, append-only (format 2)", "o-"),
        (results, "update_in_memory_seconds", "update in memory", "s--"),
        (results, "update_with_commit_seconds", "update + commit (format 2)", "^:"),
    ]
    if baseline:
        curves.insert(0, (baseline, "commit_seconds", "commit, previous layout (format 1)",
                          "x-"))
    for rs, key, label, style in curves:
        ms_k = [r["m"] for r in rs]
        med = np.array([r[key]["median"] for r in rs]) * 1e3
        p90 = np.array([r[key]["p90"] for r in rs]) * 1e3
        line = ax.plot(ms_k, med, style, label=label)[0]
        ax.fill_between(ms_k, med, p90, color=line.get_color(), alpha=0.15)
    ms = [r["m"] for r in results]
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("snapshots already absorbed m")
    ax.set_ylabel("wall time per update (ms)")
    ax.text(0.02, 0.02, "lines: median; bands: up to the 90th percentile",
            transform=ax.transAxes, fontsize=7)
    ax.set_title(f"n = {results[0]['n']}, b = {results[0]['block']} columns per update, "
                 f"{results[0].get('inner', 'euclidean')} inner product")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    bx.plot(ms, [r["written_bytes"]["median"] for r in results], "o-",
            label="written per commit, median")
    bx.plot(ms, [r["written_bytes"]["max"] for r in results], "v--",
            label="written per commit, largest")
    bx.plot(ms, [r["V0_bytes"] for r in results], "k:", label="size of V0 (m x wv)")
    bx.set_xscale("log")
    bx.set_yscale("log")
    bx.set_xlabel("snapshots already absorbed m")
    bx.set_ylabel("bytes (uncompressed)")
    bx.set_title("what a commit writes")
    bx.legend(fontsize=8)
    bx.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; return the report (also written as JSON, with a PNG)."""
    record = Run("store_benchmark", argv)
    args = _parse(argv)
    out = out_dir(args.out)
    ms = [int(float(x)) for x in args.ms.split(",") if x.strip()]
    machine = machine_info()
    tmp = None
    if args.dir is None:
        tmp = tempfile.mkdtemp(prefix="streamsvd-store-bench-")
        root = Path(tmp)
    else:
        root = Path(args.dir)
        root.mkdir(parents=True, exist_ok=True)
    try:
        results = [run_one(m, args, root) for m in ms]
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    machine["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    baseline = None
    if args.baseline is not None:
        baseline = read_payload(args.baseline)["results"]
    report = {"machine": machine, "options": vars(args), "results": results}
    stem = "store_benchmark" if args.inner == "euclidean" else f"store_benchmark_{args.inner}"
    record.write(out / f"{stem}.json", report)
    _plot(results, baseline, out / f"{stem}.png")
    print_table(
        ["m", "V0 MB", "commit ms (med/p90/max)", "update in memory ms", "update+commit ms",
         "written B (med/max)", "save s"],
        [
            [
                r["m"], f"{r['V0_bytes'] / 1e6:.2f}",
                "{median:.1f} / {p90:.1f} / {max:.1f}".format(
                    **{k: 1e3 * v for k, v in r["commit_seconds"].items()}),
                f"{1e3 * r['update_in_memory_seconds']['median']:.2f}",
                f"{1e3 * r['update_with_commit_seconds']['median']:.1f}",
                f"{r['written_bytes']['median']:.0f} / {r['written_bytes']['max']:.0f}",
                f"{r['save_seconds']:.2f}",
            ]
            for r in results
        ],
        title=f"store benchmark, {args.inner} inner product (load average before "
        f"{machine['load_average']}, after "
        f"{machine['load_average_after']})",
    )
    return report


if __name__ == "__main__":
    main()
