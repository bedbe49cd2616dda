"""Peak memory of every dask worker (and of the client) for tall data, against ``n``.

    python bench/cluster_memory.py [--ns 200000,1000000,2000000] [--m 400] [--k 60]
           [--block 100] [--chunk-rows 20000] [--workers 2] [--repeat 1]
           [--contenders tall,tall_tree,svd_compressed] [--storage local|s3] [--quick]

For every ``n`` the data (``A = U diag(s) V^T + noise``: ``2k`` modes over four decades,
noise 1e-3, by row chunks as in ``bench_dask.py``) is written once as a zarr array of
``chunk_rows x block`` chunks: in a local directory (a file system every worker sees at
the same path, as a shared file system), or with ``--storage s3`` on a moto S3 server.
Then every contender runs in a process of its own (the client), which starts a FRESH
isolated cluster (:mod:`streamsvd.testing.cluster`: a ``dask scheduler`` and
``--workers`` ``dask worker`` processes, one thread each, own working directories), so
that no peak is shared between contenders or sizes. That process samples every 50 ms the
resident memory of itself, of the scheduler and of each worker's process tree (its nanny
and its worker process), and reports the peaks, the wall time, its own CPU time and the
CPU time of each worker process (their sum over the wall time is the parallelism the
workers achieved). Contenders (``max_rank = k``, ``finalize=True``, results in a store
beside the data, nothing ``n``-sized gathered):

* ``tall``: :func:`streamsvd.parallel.tall_compress` (the basis in row panels in the
  store, every update's products one task per row chunk on the workers);
* ``tall_tree``: :func:`streamsvd.parallel.tall_tree_compress` (tall leaves in parallel,
  one per worker, panels under a work directory beside the store);
* ``svd_compressed``: ``dask.array.linalg.svd_compressed(da.from_zarr(...), k,
  n_power_iter=2)``, ``u`` written to a zarr array by the workers, ``s`` and ``v``
  gathered.

Reported per ``n`` and contender: the peak of each worker (MB), the scheduler's and the
client's peak, the client's rise above its state after start-up, wall and CPU times, the
singular values' agreement with ``svd_compressed``, and ``uptime``'s load before each run.
Writes ``cluster_memory.json``, ``cluster_memory.png`` (peak MB per worker against ``n``,
and the wall time) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ProcessPeaks, Run, load_average, out_dir, print_table, pyplot  # noqa: E402

BUCKET = "cluster-memory"
CONTENDERS = ("tall", "tall_tree", "svd_compressed")
MB = 1e6


def data_config(n: int, m: int, k: int, block: int, chunk_rows: int) -> dict[str, Any]:
    """The data's configuration for ``bench_dask.write_data`` (rows by chunk, seeded)."""
    return {"n": n, "m": m, "chunk_rows": chunk_rows, "block": block, "extra": 0,
            "signal": 2 * k, "decades": 4.0, "noise": 1e-3, "seed": 0}


def run_contender(name: str, cfg: dict[str, Any], client: Any, src: str, work: str
                  ) -> dict[str, Any]:
    """Run one contender on the cluster; return its singular values (nothing n-sized)."""
    k, block, rows = cfg["k"], cfg["block"], cfg["chunk_rows"]
    if name == "tall":
        from streamsvd.parallel import tall_compress

        with tall_compress(src, block=block, client=client, max_rank=k, finalize=True,
                           chunk_rows=rows, store=f"{work}/tall.store") as sc:
            return {"s": np.asarray(sc.amplitudes), "modes": sc.rank}
    if name == "tall_tree":
        from streamsvd.parallel import tall_tree_compress

        with tall_tree_compress(src, workdir=f"{work}/tall-tree.work", block=block,
                                chunk_rows=rows, client=client, max_rank=k, finalize=True,
                                store=f"{work}/tall-tree.store") as sc:
            return {"s": np.asarray(sc.amplitudes), "modes": sc.rank}
    if name == "svd_compressed":
        import dask
        import dask.array as da

        x = da.from_zarr(src)
        u, s, v = da.linalg.svd_compressed(x, k, n_power_iter=2, seed=0)
        stored = u.to_zarr(f"{work}/svd-u.zarr", compute=False)
        _, s, _ = dask.compute(stored, s, v, scheduler=client.get)
        return {"s": np.asarray(s), "modes": int(np.asarray(s).size)}
    raise ValueError(f"unknown contender {name!r}")


def child(spec: dict[str, Any]) -> dict[str, Any]:
    """Measure one contender at one ``n`` on a fresh isolated cluster (in its own process)."""
    import dask.array  # noqa: F401 - imported before the client's baseline is taken
    import zarr  # noqa: F401
    from distributed import Client

    import streamsvd.parallel  # noqa: F401
    from streamsvd.testing import cluster as isolated

    cfg = spec["cfg"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    env.update(spec.get("env", {}))
    cl = isolated.start(workers=cfg["workers"], env=env)
    try:
        with Client(cl.address, timeout="60s") as client:
            load = load_average()
            with ProcessPeaks(scheduler=cl.processes[0], workers=cl.processes[1:]) as peaks:
                t0, c0 = time.perf_counter(), time.process_time()
                out = run_contender(spec["name"], cfg, client, spec["src"], spec["work"])
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        cl.stop()
    return {"contender": spec["name"], "n": cfg["n"], "seconds": wall, "client_cpu": cpu,
            "load": load, "modes": out["modes"], "s": [float(x) for x in out["s"]],
            "worker_peaks_mb": [w / MB for w in peaks.worker],
            "worker_start_mb": [w / MB for w in peaks.worker_base],
            "worker_peak_mb": max(peaks.worker) / MB,
            "worker_cpu": peaks.worker_cpu,
            "parallelism": sum(peaks.worker_cpu) / wall,
            "scheduler_peak_mb": peaks.sched / MB,
            "client_peak_mb": peaks.client / MB,
            "client_growth_mb": (peaks.client - peaks.base) / MB}


def _spawn(spec: dict[str, Any]) -> dict[str, Any]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    env.update(spec.get("env", {}))
    done = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                          capture_output=True, text=True, env=env, check=False)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    if done.returncode != 0 or not lines:
        return {"contender": spec["name"], "n": spec["cfg"]["n"],
                "failed": (done.stderr or done.stdout)[-1500:]}
    return json.loads(lines[-1])


def _write_source(cfg: dict[str, Any], url: str) -> float:
    import dask
    import dask.array as da
    import zarr
    from bench_dask import data_array

    x = data_array(cfg)
    if url.startswith("s3://"):
        from zarr.storage import FsspecStore

        store: Any = FsspecStore.from_url(url, read_only=False)
    else:
        store = url
    z = zarr.create_array(store=store, shape=(cfg["n"], cfg["m"]), dtype="float64",
                          chunks=(cfg["chunk_rows"], cfg["block"]))
    t0 = time.perf_counter()
    with dask.config.set(scheduler="threads"):
        da.store(x.rechunk((cfg["chunk_rows"], cfg["block"])), z, lock=False)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ns", default="200000,1000000,2000000")
    parser.add_argument("--m", type=int, default=400)
    parser.add_argument("--k", type=int, default=60)
    parser.add_argument("--block", type=int, default=100)
    parser.add_argument("--chunk-rows", type=int, default=20000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--contenders", default=",".join(CONTENDERS))
    parser.add_argument("--storage", choices=("local", "s3"), default="local")
    parser.add_argument("--work", default=None, help="data directory (default: temporary)")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=None)
    parser.add_argument("--tag", default="")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))), flush=True)
        return {}
    run = Run("cluster_memory", argv)
    if args.quick:
        args.ns, args.m, args.k, args.block, args.chunk_rows = "2000,6000", 60, 6, 20, 500
    ns = [int(float(x)) for x in args.ns.split(",")]
    contenders = [c for c in args.contenders.split(",") if c]
    out = out_dir(args.out)
    work = Path(args.work or tempfile.mkdtemp(prefix="streamsvd-cluster-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    server = None
    env: dict[str, str] = {}
    if args.storage == "s3":
        import s3fs

        from streamsvd.testing import s3server

        server = s3server.start()
        env = dict(server.environment())
        os.environ.update(env)
        s3fs.S3FileSystem().mkdir(BUCKET)
    rows: list[dict[str, Any]] = []
    writes: dict[int, float] = {}
    try:
        for n in ns:
            cfg = dict(data_config(n, args.m, args.k, args.block, args.chunk_rows),
                       k=args.k, workers=args.workers)
            base = f"s3://{BUCKET}/n{n}" if server else str(work / f"n{n}")
            src = f"{base}/a.zarr"
            writes[n] = _write_source(cfg, src)
            print(f"n={n}: data written in {writes[n]:.1f} s", flush=True)
            for r in range(args.repeat):
                order = contenders[r % len(contenders):] + contenders[:r % len(contenders)]
                for name in order:
                    spec = {"name": name, "cfg": cfg, "src": src, "env": env,
                            "work": f"{base}/{name}-{r}"}
                    row = _spawn(spec)
                    row["uptime"] = _uptime()
                    rows.append(row)
                    print({k: v for k, v in row.items() if k != "s"}, flush=True)
            if not server:
                shutil.rmtree(work / f"n{n}", ignore_errors=True)
    finally:
        if server is not None:
            server.stop()
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    summary = summarise(rows, ns, contenders)
    results = {"config": {"ns": ns, "m": args.m, "k": args.k, "block": args.block,
                          "chunk_rows": args.chunk_rows, "workers": args.workers,
                          "storage": args.storage, "repeat": args.repeat},
               "write_seconds": writes, "summary": summary, "runs": rows}
    name = "cluster_memory_quick" if args.quick else "cluster_memory" + (
        f"_{args.tag}" if args.tag else "")
    run.write(out / f"{name}.json", results)
    headers = ["contender", "n", "time s", "parallelism", "worker MB (each)",
               "scheduler MB", "client MB", "client +MB", "modes", "s rel. diff", "load"]
    table = [[r["contender"], r["n"], r.get("seconds"), r.get("parallelism"),
              r.get("worker_peaks"), r.get("scheduler_peak_mb"), r.get("client_peak_mb"),
              r.get("client_growth_mb"), r.get("modes"), r.get("s_rel_diff"), r.get("load")]
             for r in summary]
    print_table(headers, table, title=f"m={args.m} k={args.k} block={args.block} "
                f"chunk_rows={args.chunk_rows}, {args.workers} fresh isolated workers per "
                f"run, {args.storage} storage")
    plot(out / f"{name}.png", summary, results["config"])
    return results


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return ""


def summarise(rows: list[dict[str, Any]], ns: list[int], contenders: list[str]
              ) -> list[dict[str, Any]]:
    """Medians over repeats per ``(contender, n)``; peaks are the maxima over repeats."""
    ref = {n: next((np.asarray(r["s"]) for r in rows if r["n"] == n and "s" in r
                    and r["contender"] == "svd_compressed"), None) for n in ns}
    out = []
    for name in contenders:
        for n in ns:
            ok = [r for r in rows if r["contender"] == name and r["n"] == n and "s" in r]
            if not ok:
                bad = [r for r in rows if r["contender"] == name and r["n"] == n]
                out.append({"contender": name, "n": n,
                            "failed": bad[0].get("failed", "not run") if bad else "not run"})
                continue
            peaks = np.max([r["worker_peaks_mb"] for r in ok], axis=0)
            s, s_ref = np.asarray(ok[-1]["s"]), ref[n]
            diff = (None if s_ref is None else
                    float(np.max(np.abs(s[:s_ref.size] - s_ref[:s.size])) / s_ref[0]))
            out.append({
                "contender": name, "n": n,
                "seconds": statistics.median(r["seconds"] for r in ok),
                "client_cpu": statistics.median(r["client_cpu"] for r in ok),
                "parallelism": statistics.median(r["parallelism"] for r in ok),
                "worker_peaks": "/".join(f"{p:.0f}" for p in peaks),
                "worker_peaks_mb": peaks.tolist(), "worker_peak_mb": float(peaks.max()),
                "scheduler_peak_mb": max(r["scheduler_peak_mb"] for r in ok),
                "client_peak_mb": max(r["client_peak_mb"] for r in ok),
                "client_growth_mb": max(r["client_growth_mb"] for r in ok),
                "modes": ok[-1]["modes"], "s_rel_diff": diff,
                "load": statistics.median(r["load"][0] for r in ok if r.get("load")),
                "runs": len(ok)})
    return out


def plot(path: Path, summary: list[dict[str, Any]], cfg: dict[str, Any]) -> None:
    """Peak MB of each worker and of the client against ``n``; wall time against ``n``."""
    plt = pyplot()
    ok = [r for r in summary if "seconds" in r]
    if not ok:
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    names = list(dict.fromkeys(r["contender"] for r in ok))
    for i, name in enumerate(names):
        rs = sorted((r for r in ok if r["contender"] == name), key=lambda r: r["n"])
        n = [r["n"] for r in rs]
        color = f"C{i}"
        for w in range(len(rs[0]["worker_peaks_mb"])):
            axes[0].plot(n, [r["worker_peaks_mb"][w] for r in rs], "o-", color=color,
                         label=f"{name}: each worker" if w == 0 else None)
        axes[0].plot(n, [r["client_peak_mb"] for r in rs], "s--", color=color,
                     label=f"{name}: client")
        axes[1].plot(n, [r["seconds"] for r in rs], "o-", color=color, label=name)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("peak resident memory (MB, log scale)")
    axes[1].set_ylabel("wall time (s)")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_xlabel("n (rows of the snapshot matrix)")
        ax.legend(fontsize=8)
    loads = [r["load"] for r in ok if r.get("load") is not None]
    fig.suptitle(f"m = {cfg['m']}, rank {cfg['k']}, blocks of {cfg['block']}, chunks of "
                 f"{cfg['chunk_rows']} rows, {cfg['workers']} fresh isolated workers per run, "
                 f"{cfg['storage']} storage; load {min(loads):.1f}-{max(loads):.1f}",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
