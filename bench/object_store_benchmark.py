"""Object-store benchmark: the cost of a commit to a local directory and to an S3 store.

    python bench/object_store_benchmark.py               # n = 100, b = 5, 40 commits
    python bench/object_store_benchmark.py --updates 10 --n 1000

Setup
-----
A :class:`streamsvd.StreamCompressor` (``n`` = ``--n``, 100, ``max_rank`` =
``--max-rank``, 20) with a store absorbs ``--updates`` (40) blocks of ``b`` =
``--block`` (5) columns, committing after each one, as the command line does by default.
The snapshots are those of ``bench/store_benchmark.py`` (``Q1 diag(s) z_j + 1e-3 g_j``).
The same run is made twice: with the store in a local directory (``--dir``, a temporary
directory by default) and in an ``s3://`` bucket on an S3-compatible server on
localhost (moto in server mode, started by the script: ``streamsvd.testing.s3server``;
``--endpoint`` uses another server instead, with the ``AWS_*`` credentials of the
environment).

Measures
--------
Per commit (``BasisStore.commit``: the pack, the lease renewal, the conditional pointer
switch, the pruning; ``fsync`` included locally): wall time, median, 90th percentile and
largest. The creation of the store, the reopening for writing (taking the lease) and one
read of the current generation are timed once. Against moto on the same machine a
request costs what moto's Python HTTP server takes to answer (about a millisecond), not
a network round trip to a cloud region: the S3 figures count requests more than bytes.

Writes ``object_store_benchmark.json`` and ``object_store_benchmark.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

from _common import Run, machine_info, out_dir, print_table, pyplot  # noqa: E402
from store_benchmark import _columns, _summary, timed_commits  # noqa: E402

from streamsvd import StreamCompressor  # noqa: E402
from streamsvd.store import open_store  # noqa: E402


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=None, help="output directory (default bench/results)")
    p.add_argument("--dir", default=None, help="directory for the local store (default: temp)")
    p.add_argument("--endpoint", default=None,
                   help="S3 endpoint URL to use instead of a local moto server")
    p.add_argument("--bucket", default="streamsvd-bench", help="bucket of the S3 store")
    p.add_argument("--n", type=int, default=100, help="snapshot size")
    p.add_argument("--block", type=int, default=5, help="columns per update")
    p.add_argument("--updates", type=int, default=40, help="timed updates (commits)")
    p.add_argument("--max-rank", type=int, default=20, help="max_rank of the compressor")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def run_one(location: Any, label: str, args: argparse.Namespace) -> dict[str, Any]:
    """Create a store at ``location``, time ``args.updates`` updates with their commits."""
    rng = np.random.default_rng(args.seed)
    n = args.n
    k = min(40, n)
    Q1 = np.linalg.qr(rng.standard_normal((n, k)))[0]
    s = np.logspace(0, -4, k)
    blocks = [_columns(Q1, s, args.block, rng) for _ in range(args.updates)]
    t0 = time.perf_counter()
    sc = StreamCompressor(n, max_rank=args.max_rank, store=location)
    create_seconds = time.perf_counter() - t0
    store = sc._life.persistence.handle
    assert store is not None
    with timed_commits(store) as commit_times:  # the updates' commits only
        for B in blocks:
            sc.absorb(B)
    sc.close()  # the final sweeps and their commit, not timed
    with StreamCompressor.open(location, mode="r") as closed:
        U = closed.expansion.U
    t0 = time.perf_counter()
    with open_store(location, "a") as again:
        reopen_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        again.read()
        read_seconds = time.perf_counter() - t0
    with StreamCompressor.open(location, mode="r") as back:
        same = bool(np.array_equal(back.expansion.U, U))
    return {
        "store": label, "n": n, "block": args.block, "updates": args.updates,
        "create_seconds": create_seconds, "reopen_seconds": reopen_seconds,
        "read_seconds": read_seconds, "commit_seconds": _summary(commit_times),
        "commit_seconds_all": commit_times, "reopens_bit_for_bit": same,
    }


def _plot(results: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r, style in zip(results, ("o-", "s-"), strict=False):
        ax.plot(np.arange(1, r["updates"] + 1), 1e3 * np.asarray(r["commit_seconds_all"]),
                style, ms=3, label=f"{r['store']} (median "
                f"{1e3 * r['commit_seconds']['median']:.1f} ms)")
    ax.set_yscale("log")
    ax.set_xlabel("commit number (one per update of b columns)")
    ax.set_ylabel("wall time of the commit (ms)")
    ax.set_title(f"n = {results[0]['n']}, b = {results[0]['block']}: local directory "
                 "vs S3 (moto on localhost)", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; return the report (also written as JSON, with a PNG)."""
    record = Run("object_store_benchmark", argv)
    args = _parse(argv)
    out = out_dir(args.out)
    machine = machine_info()
    tmp = tempfile.mkdtemp(prefix="streamsvd-object-bench-") if args.dir is None else None
    root = Path(tmp) if tmp is not None else Path(args.dir)
    server = None
    saved_env = dict(os.environ)
    try:
        if args.endpoint is None:
            from streamsvd.testing.s3server import start

            server = start()
            os.environ.update(server.environment())
        else:
            os.environ["AWS_ENDPOINT_URL"] = args.endpoint
        import s3fs

        fs = s3fs.S3FileSystem()
        if not fs.exists(args.bucket):
            fs.mkdir(args.bucket)
        url = f"s3://{args.bucket}/bench-{os.getpid()}-{time.time_ns()}.zarr"
        results = [
            run_one(root / "basis.zarr", "local directory", args),
            run_one(url, "S3 (moto, localhost)" if server else "S3", args),
        ]
        fs.rm(url, recursive=True)
    finally:
        if server is not None:
            server.stop()
        os.environ.clear()
        os.environ.update(saved_env)
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    machine["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    report = {"machine": machine, "options": vars(args), "results": results}
    record.write(out / "object_store_benchmark.json", report)
    _plot(results, out / "object_store_benchmark.png")
    print_table(
        ["store", "commit ms (med/p90/max)", "create s", "reopen (lease) s", "read s"],
        [
            [
                r["store"],
                "{median:.1f} / {p90:.1f} / {max:.1f}".format(
                    **{k: 1e3 * v for k, v in r["commit_seconds"].items()}),
                f"{r['create_seconds']:.3f}", f"{r['reopen_seconds']:.3f}",
                f"{r['read_seconds']:.3f}",
            ]
            for r in results
        ],
        title=f"object-store benchmark (load average before {machine['load_average']}, "
        f"after {machine['load_average_after']})",
    )
    return report


if __name__ == "__main__":
    main()
