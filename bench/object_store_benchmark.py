"""Object-store benchmark: a local directory, and S3 through s3fs or through obstore.

    python bench/object_store_benchmark.py               # n = 100, b = 5, 40 commits
    python bench/object_store_benchmark.py --updates 10 --n 1000 --repeats 1

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
read of the current generation are timed once per run.

The S3 runs are made twice, with the zarr arrays written and read through s3fs
(``FsspecStore``, the default) and through obstore (``storage_options={"zarr_store":
"obstore"}``, zarr's ``ObjectStore``; :mod:`streamsvd.storage.zarr_stores`); the small
objects (pointer, lease, listings) go through s3fs in both. Two heavier workloads are
timed too, wall and CPU time of this process (moto's is not counted): a source read (a
``--source-rows x --source-cols`` zarr array on S3, chunked ``16384 x 20``, read block
by block of 20 columns through :func:`streamsvd.io.open_source`) and a tall stream (a
:class:`~streamsvd.parallel.TallCompressor` of ``--source-rows`` rows with its store on
S3, absorbing the array's first 100 columns in 5 updates: its panels are written and
read through the zarr store). The contenders run interleaved, ``--repeats`` times
(3); the table gives medians over the repeats. Against moto on the same machine a
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
    p.add_argument("--source-rows", type=int, default=100_000,
                   help="rows of the source array (and of the tall stream)")
    p.add_argument("--source-cols", type=int, default=100, help="columns of the source")
    p.add_argument("--repeats", type=int, default=3, help="interleaved runs per contender")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


CONTENDERS = {"fsspec": {}, "obstore": {"zarr_store": "obstore"}}
"""The S3 contenders: their ``storage_options``."""


def _clocked(fn: Any) -> dict[str, float]:
    """Run ``fn()``; return its wall and CPU seconds (this process, every thread)."""
    w, c = time.perf_counter(), time.process_time()
    fn()
    return {"wall": time.perf_counter() - w, "cpu": time.process_time() - c}


def source_read(url: str, options: dict[str, Any]) -> dict[str, float]:
    """Read the source at ``url`` block by block of 20 columns; wall and CPU seconds."""
    from streamsvd.io.open import open_source

    def read() -> None:
        with open_source(url, storage_options=options) as src:
            m = src.shape[1]
            for j in range(0, m, 20):
                src.read(j, min(j + 20, m))

    return _clocked(read)


def tall_stream(url: str, store: str, options: dict[str, Any]) -> dict[str, float]:
    """Stream the source's first 100 columns into a tall store at ``store`` (5 updates)."""
    from streamsvd.io.open import open_source
    from streamsvd.parallel.tall import TallCompressor

    with open_source(url, storage_options=options) as src:
        n, m = src.shape
        blocks = [src.read(j, min(j + 20, m)) for j in range(0, min(m, 100), 20)]

    def stream() -> None:
        tc = TallCompressor(n, store=store, chunk_rows=16384, max_rank=10,
                            storage_options=options)
        for B in blocks:
            tc.absorb(B)
        tc.close(finalize=False)

    return _clocked(stream)


def _write_source(url: str, args: argparse.Namespace) -> None:
    """Write the ``--source-rows x --source-cols`` array to ``url`` (zarr, chunked)."""
    import zarr

    rng = np.random.default_rng(args.seed)
    n, m = args.source_rows, args.source_cols
    A = rng.standard_normal((n, m))
    z = zarr.create_array(url, shape=(n, m), chunks=(min(16384, n), min(20, m)),
                          dtype="f8")
    z[:] = A


def run_one(location: Any, label: str, args: argparse.Namespace,
            options: dict[str, Any] | None = None) -> dict[str, Any]:
    """Create a store at ``location``, time ``args.updates`` updates with their commits."""
    rng = np.random.default_rng(args.seed)
    n = args.n
    k = min(40, n)
    Q1 = np.linalg.qr(rng.standard_normal((n, k)))[0]
    s = np.logspace(0, -4, k)
    blocks = [_columns(Q1, s, args.block, rng) for _ in range(args.updates)]
    t0 = time.perf_counter()
    sc = StreamCompressor(n, max_rank=args.max_rank, store=location,
                          storage_options=options or None)
    create_seconds = time.perf_counter() - t0
    store = sc._life.persistence.handle
    assert store is not None
    with timed_commits(store) as commit_times:  # the updates' commits only
        for B in blocks:
            sc.absorb(B)
    sc.close()  # the final sweeps and their commit, not timed
    with StreamCompressor.open(location, mode="r", storage_options=options or None) as closed:
        U = closed.expansion.U
    t0 = time.perf_counter()
    with open_store(location, "a", storage_options=options or None) as again:
        reopen_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        again.read()
        read_seconds = time.perf_counter() - t0
    with StreamCompressor.open(location, mode="r", storage_options=options or None) as back:
        same = bool(np.array_equal(back.expansion.U, U))
    return {
        "store": label, "n": n, "block": args.block, "updates": args.updates,
        "create_seconds": create_seconds, "reopen_seconds": reopen_seconds,
        "read_seconds": read_seconds, "commit_seconds": _summary(commit_times),
        "commit_seconds_all": commit_times, "reopens_bit_for_bit": same,
    }


def _median_run(label: str, rs: list[dict[str, Any]]) -> dict[str, Any]:
    """Return the last run of a contender with its figures replaced by the medians."""
    out = dict(rs[-1], store=label, repeats=len(rs), runs=rs)
    for key in ("create_seconds", "reopen_seconds", "read_seconds"):
        out[key] = float(np.median([r[key] for r in rs]))
    out["commit_seconds"] = {k: float(np.median([r["commit_seconds"][k] for r in rs]))
                             for k in rs[0]["commit_seconds"]}
    out["reopens_bit_for_bit"] = all(r["reopens_bit_for_bit"] for r in rs)
    for key in ("source_read", "tall_stream"):
        if rs[0][key] is not None:
            out[key] = {k: float(np.median([r[key][k] for r in rs])) for k in ("wall", "cpu")}
    return out


def _plot(results: list[dict[str, Any]], path: Path, load: str) -> None:
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    for r, style in zip(results, ("o-", "s-", "^-"), strict=False):
        ax.plot(np.arange(1, r["updates"] + 1), 1e3 * np.asarray(r["commit_seconds_all"]),
                style, ms=3, label=f"{r['store']} (median "
                f"{1e3 * r['commit_seconds']['median']:.1f} ms)")
    ax.set_yscale("log")
    ax.set_xlabel("commit number (one per update of b columns)")
    ax.set_ylabel("wall time of the commit (ms)")
    ax.set_title(f"commits, n = {results[0]['n']}, b = {results[0]['block']} (last repeat)",
                 fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, which="both", alpha=0.3)
    s3 = [r for r in results if r.get("source_read")]
    x = np.arange(len(s3))
    for i, (key, what) in enumerate([("source_read", "source read"),
                                     ("tall_stream", "tall stream")]):
        for j, clock in enumerate(("wall", "cpu")):
            bx.bar(x + (2 * i + j - 1.5) * 0.2, [r[key][clock] for r in s3], 0.2,
                   label=f"{what}, {clock}")
    bx.set_xticks(x, [r["store"].rsplit(", ", 1)[-1] for r in s3])
    bx.set_ylabel("seconds (median over the repeats)")
    bx.set_xlabel("zarr store of the s3:// prefix")
    bx.set_title("source read and tall stream on S3 (moto), this process's time", fontsize=9)
    bx.legend(fontsize=7)
    bx.grid(True, axis="y", alpha=0.3)
    fig.suptitle(f"local directory vs S3 through s3fs or obstore (load average {load})",
                 fontsize=9)
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
        base = f"s3://{args.bucket}/bench-{os.getpid()}-{time.time_ns()}"
        source = f"{base}/source.zarr"
        _write_source(source, args)
        s3_label = "S3 (moto, localhost)" if server else "S3"
        labels = ["local directory", *(f"{s3_label}, {c}" for c in CONTENDERS)]
        runs: dict[str, list[dict[str, Any]]] = {label: [] for label in labels}
        for rep in range(args.repeats):  # interleaved: every contender once per repeat
            for label, choice in zip(labels, [None, *CONTENDERS], strict=True):
                if choice is None:
                    shutil.rmtree(root / "basis.zarr", ignore_errors=True)
                    r = run_one(root / "basis.zarr", label, args)
                    r["source_read"] = r["tall_stream"] = None
                else:
                    options = CONTENDERS[choice]
                    r = run_one(f"{base}/{choice}-{rep}.zarr", label, args, options)
                    r["source_read"] = source_read(source, options)
                    r["tall_stream"] = tall_stream(source, f"{base}/tall-{choice}-{rep}.zarr",
                                                   options)
                r["load_average"] = [round(x, 2) for x in os.getloadavg()]
                runs[label].append(r)
        results = [_median_run(label, rs) for label, rs in runs.items()]
        fs.rm(base, recursive=True)
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
    _plot(results, out / "object_store_benchmark.png",
          f"{machine['load_average'][0]:.1f} before, {machine['load_average_after'][0]:.1f} after")
    print_table(
        ["store", "commit ms (med/p90/max)", "create s", "reopen (lease) s", "read s",
         "source read s (wall/CPU)", "tall stream s (wall/CPU)"],
        [
            [
                r["store"],
                "{median:.1f} / {p90:.1f} / {max:.1f}".format(
                    **{k: 1e3 * v for k, v in r["commit_seconds"].items()}),
                f"{r['create_seconds']:.3f}", f"{r['reopen_seconds']:.3f}",
                f"{r['read_seconds']:.3f}",
                *("-" if r.get(key) is None else
                  f"{r[key]['wall']:.2f} / {r[key]['cpu']:.2f}"
                  for key in ("source_read", "tall_stream")),
            ]
            for r in results
        ],
        title=f"object-store benchmark, medians of {args.repeats} interleaved runs (load "
        f"average before {machine['load_average']}, after {machine['load_average_after']})",
    )
    return report


if __name__ == "__main__":
    main()
