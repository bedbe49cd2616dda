"""streamsvd's dask modes on a shared-nothing cluster, against dask and pyMOR, in one run.

A ``dask scheduler`` and ``--workers`` ``dask worker`` processes (one thread each), each
in its own working directory and ``TMPDIR`` (and, where ``unshare -rm`` is allowed, with
this process's directories hidden: :mod:`streamsvd.testing.cluster`); a moto S3 server on
localhost holds the source, a zarr array of ``A = Q1 diag(s) Q2^T + noise`` (``n x m``,
``s`` log-spaced from 1 to 1e-4 over ``2k`` values, noise 1e-6, seed 0, chunks of
``chunk_rows x block``), and the stores. The workers get their credentials from their
own environment. Contenders, interleaved (repeat r of each before repeat r + 1 of any):

* ``tree``: ``tree_compress(URL, client=..., store=s3://..., max_rank=k, finalize=True)``
  (default leaves: ten blocks, fewer to give every worker one; each leaf reads its
  columns from S3 on its worker; nodes committed beside the store);
* ``tall``: ``tall_compress(URL, client=..., store=s3://..., max_rank=k, finalize=True)``
  (the workers read the source's row chunks and the panels from S3);
* ``tall_tree``: ``tall_tree_compress(URL, workdir=s3://..., client=..., store=s3://...,
  max_rank=k, finalize=True)``: tall leaves in parallel on the workers, every panel on
  S3, each leaf's row-chunk products on its own worker;
* ``svd_compressed``: ``dask.array.linalg.svd_compressed(da.from_zarr(URL), k,
  n_power_iter=2)`` computed on the same cluster (the workers read S3), the factors
  gathered to this process;
* ``dist_hapod``: pyMOR's ``dist_vectorarray_hapod(workers, U, eps, omega=0.9,
  executor=client.get_executor())`` on the same cluster, with ``eps`` the optimal rank-k
  mean-l2 error (so that it keeps about ``k`` modes); ``U`` is read from S3 into this
  process first (pyMOR's vector arrays live in memory; that read is timed apart), and
  the executor is given ``_max_workers``, which pyMOR reads from a
  ``concurrent.futures`` executor and dask's ``ClientExecutor`` lacks.

Reported per contender: median wall time, this process's CPU time, the modes returned,
``err/opt = ||A - Q Q^T A||_F / ||A - A_k||_F`` (``Q`` the returned modes, ``A_k`` from
LAPACK), how far the resident memory of this process (the client) rose above what it held
before the run (the benchmark's own ``A`` and its SVD), the peak resident memory of the
busiest worker (its nanny and worker processes; both sampled every 50 ms), and the
1-minute load before every run. ``--quick`` runs a tiny size (the smoke test).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ProcessPeaks, Run, load_average, out_dir, print_table, pyplot  # noqa: E402

BUCKET = "cluster-bench"
CONTENDERS = ("tree", "tall", "tall_tree", "svd_compressed", "dist_hapod")


def make_data(n: int, m: int, k: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = np.logspace(0, -4, 2 * k)
    Q1 = np.linalg.qr(rng.standard_normal((n, s.size)))[0]
    Q2 = np.linalg.qr(rng.standard_normal((m, s.size)))[0]
    return (Q1 * s) @ Q2.T + 1e-6 * rng.standard_normal((n, m)) / np.sqrt(n)


def err_over_opt(A: np.ndarray, Q: np.ndarray, opt: float) -> float:
    Q = np.asarray(Q)
    R = A - Q @ (Q.T @ A)
    return float(np.linalg.norm(R) / opt)


def run_one(name: str, r: int, cfg: dict[str, Any], client: Any, url: str) -> dict[str, Any]:
    from streamsvd.parallel import tall_compress, tree_compress

    k, block = cfg["k"], cfg["block"]
    out: dict[str, Any] = {}
    if name == "tree":
        with tree_compress(url, block=block, client=client, max_rank=k, finalize=True,
                           store=f"s3://{BUCKET}/tree-{r}") as sc:
            out["Q"] = sc.expansion.U
    elif name == "tall":
        with tall_compress(url, block=block, client=client, max_rank=k, finalize=True,
                           chunk_rows=cfg["chunk_rows"], store=f"s3://{BUCKET}/tall-{r}") as sc:
            out["Q"] = np.asarray(sc.factors()[0])
    elif name == "tall_tree":
        from streamsvd.parallel import tall_tree_compress

        with tall_tree_compress(url, workdir=f"s3://{BUCKET}/scratch-{r}", block=block,
                                chunk_rows=cfg["chunk_rows"], client=client, max_rank=k,
                                finalize=True, store=f"s3://{BUCKET}/tall-tree-{r}") as sc:
            out["Q"] = np.asarray(sc.factors()[0])
    elif name == "svd_compressed":
        import dask
        import dask.array as da

        x = da.from_zarr(url)
        u, s, v = da.linalg.svd_compressed(x, k, n_power_iter=2, seed=0)
        out["Q"] = dask.compute(u, scheduler=client.get)[0]
    elif name == "dist_hapod":
        import zarr
        from pymor.algorithms.hapod import dist_vectorarray_hapod
        from pymor.vectorarrays.numpy import NumpyVectorSpace

        t0 = time.perf_counter()
        A = zarr.open_array(url, mode="r")[...]
        out["read_seconds"] = time.perf_counter() - t0
        U = NumpyVectorSpace(A.shape[0]).from_numpy(A)
        executor = client.get_executor()
        executor._max_workers = cfg["workers"]  # pyMOR reads it (concurrent.futures')
        modes = dist_vectorarray_hapod(cfg["workers"], U, cfg["hapod_eps"], 0.9,
                                       executor=executor)[0]
        out["Q"] = modes.to_numpy()
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=20000)
    parser.add_argument("--m", type=int, default=2000)
    parser.add_argument("--k", type=int, default=60)
    parser.add_argument("--block", type=int, default=100)
    parser.add_argument("--chunk-rows", type=int, default=5000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--contenders", default=",".join(CONTENDERS))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", default=None)
    parser.add_argument("--tag", default="", help="suffix of the results' file names")
    args = parser.parse_args(argv)
    run = Run("cluster_benchmark", argv)
    if args.quick:
        args.n, args.m, args.k, args.block, args.chunk_rows, args.repeat = (
            400, 120, 8, 20, 100, 1)
    cfg = {"n": args.n, "m": args.m, "k": args.k, "block": args.block,
           "chunk_rows": args.chunk_rows, "workers": args.workers}
    contenders = [c for c in args.contenders.split(",") if c]
    out = out_dir(args.out)

    from distributed import Client

    from streamsvd.testing import cluster as isolated
    from streamsvd.testing import s3server

    A = make_data(args.n, args.m, args.k)
    s = np.linalg.svd(A, compute_uv=False)
    opt = float(np.sqrt(np.sum(s[args.k:] ** 2)))
    cfg["hapod_eps"] = opt / np.sqrt(args.m)
    server = s3server.start()
    saved = dict(os.environ)
    os.environ.update(server.environment())
    rows: dict[str, list[dict[str, Any]]] = {c: [] for c in contenders}
    try:
        import s3fs
        import zarr
        from zarr.storage import FsspecStore

        s3fs.S3FileSystem().mkdir(BUCKET)
        url = f"s3://{BUCKET}/a.zarr"
        z = zarr.create_array(store=FsspecStore.from_url(url, read_only=False),
                              shape=A.shape, dtype="float64",
                              chunks=(args.chunk_rows, args.block))
        z[...] = A
        env = {k: v for k, v in saved.items() if not k.startswith("AWS_")}
        env.update(server.environment())
        cl = isolated.start(workers=args.workers, env=env)
        try:
            with Client(cl.address, timeout="60s") as client:
                for r in range(args.repeat):
                    for name in contenders:
                        load = load_average()
                        with ProcessPeaks(workers=cl.processes[1:]) as peaks:
                            t0, c0 = time.perf_counter(), time.process_time()
                            try:
                                res = run_one(name, r, cfg, client, url)
                                failed = None
                            except Exception as exc:  # recorded: a contender may fail
                                res, failed = {}, f"{type(exc).__name__}: {exc}"[:300]
                            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                        row = {"seconds": wall, "client_cpu": cpu, "load": load,
                               "client_peak_mb": peaks.client / 1e6,
                               "client_growth_mb": (peaks.client - peaks.base) / 1e6,
                               "worker_peak_mb": max(peaks.worker) / 1e6, "failed": failed,
                               "read_seconds": res.get("read_seconds")}
                        if "Q" in res:
                            row["modes"] = int(np.asarray(res["Q"]).shape[1])
                            row["err_over_opt"] = err_over_opt(A, res["Q"], opt)
                        rows[name].append(row)
                        print(name, r, {k: v for k, v in row.items() if k != "load"},
                              flush=True)
        finally:
            cl.stop()
    finally:
        server.stop()
        os.environ.clear()
        os.environ.update(saved)
    summary = {}
    for name, runs in rows.items():
        ok = [x for x in runs if x["failed"] is None]
        if not ok:
            summary[name] = {"failed": runs[0]["failed"] if runs else "not run"}
            continue
        summary[name] = {
            "seconds": statistics.median(x["seconds"] for x in ok),
            "client_cpu": statistics.median(x["client_cpu"] for x in ok),
            "modes": ok[-1].get("modes"), "err_over_opt": ok[-1].get("err_over_opt"),
            "client_peak_mb": max(x["client_peak_mb"] for x in ok),
            "client_growth_mb": max(x["client_growth_mb"] for x in ok),
            "load": statistics.median(x["load"][0] for x in ok if x["load"]),
            "worker_peak_mb": max(x["worker_peak_mb"] for x in ok),
            "read_seconds": ok[-1].get("read_seconds"), "runs": len(ok)}
    results = {"config": cfg, "hidden": bool(isolated.can_hide()), "summary": summary,
               "runs": rows}
    name = ("cluster_benchmark_quick" if args.quick else
            "cluster_benchmark" + (f"_{args.tag}" if args.tag else ""))
    run.write(out / f"{name}.json", results)
    headers = ["contender", "time s", "client CPU s", "modes", "err/opt",
               "client +MB", "worker MB", "load"]
    table = [[c, v.get("seconds"), v.get("client_cpu"), v.get("modes"),
              v.get("err_over_opt"), v.get("client_growth_mb"), v.get("worker_peak_mb"),
              v.get("load")] for c, v in summary.items()]
    print_table(headers, table, title=f"n={args.n} m={args.m} k={args.k}, "
                f"{args.workers} isolated workers, S3 (moto)")
    _plot(out / f"{name}.png", summary, cfg)
    return results


def _plot(path: Path, summary: dict[str, Any], cfg: dict[str, Any]) -> None:
    plt = pyplot()
    ok = {c: v for c, v in summary.items() if "seconds" in v}
    if not ok:
        return
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    names = list(ok)
    axes[0].bar(names, [ok[c]["seconds"] for c in names])
    axes[0].set_ylabel("wall time (s)")
    axes[1].bar(names, [ok[c]["err_over_opt"] for c in names])
    axes[1].set_yscale("log")
    axes[1].set_ylabel("error / optimal rank-k error")
    width = 0.4
    x = np.arange(len(names))
    axes[2].bar(x - width / 2, [ok[c]["client_growth_mb"] for c in names], width,
                label="client (growth during the run)")
    axes[2].bar(x + width / 2, [ok[c]["worker_peak_mb"] for c in names], width,
                label="busiest worker")
    axes[2].set_xticks(x, names)
    axes[2].set_ylabel("peak RSS (MB)")
    axes[2].legend()
    for ax in axes:
        ax.tick_params(axis="x", rotation=20)
    fig.suptitle(f"{cfg['n']} x {cfg['m']}, rank {cfg['k']}, {cfg['workers']} isolated "
                 "dask workers, source and stores on S3 (moto)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
