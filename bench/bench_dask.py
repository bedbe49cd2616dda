"""streamsvd on dask against dask's own SVDs, on a zarr array written by the benchmark.

    python bench/bench_dask.py                          # 1,000,000 x 2,000 (16 GB)
    python bench/bench_dask.py --size 200000x2000       # 3.2 GB
    python bench/bench_dask.py --size 4000x200 --inprocess --workers 1   # smoke size

The array ``A = U diag(s) V^T + noise`` (``--signal`` modes decaying geometrically over
``--decades``, Gaussian noise of spectral norm ``--noise``) is written by row chunks into
a zarr array (zstd, chunks of ``--chunk-rows`` rows and ``--block`` columns) in a
temporary directory, removed afterwards unless ``--keep``. Every method then runs in its
own process (unless ``--inprocess``), which samples the resident memory of itself and of
its children (dask workers) every 50 ms:

* ``read``: the raw read of the zarr array by dask (the throughput reference);
* ``tsqr``: ``dask.array.linalg.svd`` (TSQR), computing ``u[:, :k], s, v[:k]``: the
  reference of every error;
* ``svd_compressed q=0,1,2``: ``dask.array.linalg.svd_compressed(k, n_power_iter=q)``;
* ``streamsvd tree``: :func:`streamsvd.parallel.tree_compress` (in-memory leaves read
  their own columns, merged in a tree), on the threaded scheduler;
* ``streamsvd tall``: :func:`streamsvd.parallel.tall_compress` (the basis in zarr panels,
  products over row chunks), on the threaded scheduler;
* the two streamsvd modes again on a ``LocalCluster`` of 1 and 2 worker processes.

streamsvd keeps ``k + --oversample`` terms while streaming (as ``svd_compressed``
oversamples its sketch), with converged sweeps, and is truncated to ``k`` at the end by
the SVD of its small ``m x p`` factor. Errors: ``||A - U_k V_k^T||_F`` against the
optimum ``sqrt(sum_{i>k} sigma_i^2)`` of TSQR, the largest singular-value error, the
largest principal angle to TSQR's ``U_k``, and ``||U_k^T U_k - I||_2``. The streamsvd
runs also absorb one block of new snapshots afterwards (time reported): neither dask
method can continue, they recompute. Writes ``bench_dask.json``, ``bench_dask.png`` and
prints the table. BLAS runs one thread per dask thread or worker.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ProcessPeaks, Run, machine_info, out_dir, print_table, pyplot  # noqa: E402

GB = 1e9
STREAM_METHODS = ("streamsvd tree", "streamsvd tall")


# ------------------------------------------------------------------------------ data


def _model(n: int, m: int, signal: int, decades: float, noise: float, seed: int):
    rng = np.random.default_rng(seed)
    V = np.linalg.qr(rng.standard_normal((m, signal)))[0]
    s = np.logspace(0, -decades, signal)
    sigma = noise / (math.sqrt(n) + math.sqrt(m))
    return V, s, sigma


def _rows(n: int, m: int, a: int, b: int, col0: int, cols: int, cfg: dict) -> np.ndarray:
    """Rows ``a:b`` and columns ``col0:col0+cols`` of the data, deterministic per row chunk."""
    V, s, sigma = _model(n, m + cfg["extra"], cfg["signal"], cfg["decades"], cfg["noise"],
                         cfg["seed"])
    rng = np.random.default_rng([cfg["seed"], a])
    U = rng.standard_normal((b - a, cfg["signal"])) / math.sqrt(n)
    G = rng.standard_normal((b - a, m + cfg["extra"]))
    full = (U * s) @ V.T + sigma * G
    return full[:, col0 : col0 + cols]


def data_array(cfg: dict, col0: int = 0, cols: int | None = None):
    """The data (or extra columns past ``m``) as a lazy dask array, chunked by rows."""
    import dask.array as da

    n, m, rc = cfg["n"], cfg["m"], cfg["chunk_rows"]
    cols = m if cols is None else cols
    chunks = tuple(min(rc, n - a) for a in range(0, n, rc))

    def block(block_info=None):
        (a, b), _ = block_info[None]["array-location"]
        return _rows(n, m, a, b, col0, cols, cfg)

    return da.map_blocks(block, chunks=(chunks, (cols,)), dtype=np.float64,
                         meta=np.empty((0, 0)))


def write_data(cfg: dict, path: Path) -> float:
    import dask
    import dask.array as da
    import zarr

    x = data_array(cfg)
    z = zarr.create_array(str(path), shape=(cfg["n"], cfg["m"]),
                          chunks=(cfg["chunk_rows"], cfg["block"]), dtype="float64")
    t0 = time.perf_counter()
    with dask.config.set(scheduler="threads"):
        da.store(x.rechunk((cfg["chunk_rows"], cfg["block"])), z, lock=False)
    return time.perf_counter() - t0


# --------------------------------------------------------------------------- methods


def _client(workers: int):
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0")
    return cluster, Client(cluster)


def _truncate(V: np.ndarray, k: int):
    """Exact truncation of ``U V^T`` (U orthonormal) to rank k: ``U Z_k``, ``W_k S_k``."""
    W, S, Zt = np.linalg.svd(V, full_matrices=False)
    return Zt.T[:, :k], W[:, :k] * S[:k], S[:k]


def run_method(method: str, cfg: dict, path: Path, work: Path) -> dict[str, Any]:
    """Run one method (timed, memory sampled), then measure its errors (untimed)."""
    import dask
    import dask.array as da
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    import streamsvd.parallel.cluster as par

    m, k = cfg["m"], cfg["k"]
    workers = cfg.get("workers")
    cluster = client = None
    if workers:
        cluster, client = _client(workers)
    opts = {"max_rank": k + cfg["oversample"], "oversampling": 0, "sweeps": None,
            "rule": "jacobi"}
    out: dict[str, Any] = {"method": method, "workers": workers}
    x = da.from_zarr(str(path))
    sched = client if client is not None else "threads"
    result = None
    try:
        with ProcessPeaks(client_tree=True) as mem:
            t0 = time.perf_counter()
            if method == "read":
                dask.compute(x.sum(), scheduler=sched)
            elif method == "tsqr":
                u, s, v = da.linalg.svd(x.rechunk((max(cfg["chunk_rows"], m), m)))
                result = dask.compute(u[:, :k], s, v[:k], scheduler=sched)
            elif method.startswith("svd_compressed"):
                q = int(method.rsplit("=", 1)[1])
                u, s, v = da.linalg.svd_compressed(x, k, n_power_iter=q, seed=cfg["seed"])
                result = dask.compute(u, s, v, scheduler=sched)
            elif method == "streamsvd tree":
                sc = par.tree_compress(str(path), block=cfg["tree_block"],
                                       leaf_columns=cfg["leaf_columns"], client=client,
                                       **opts)
            elif method == "streamsvd tall":
                sc = par.tall_compress(str(path), block=cfg["tall_block"],
                                       store=work / "tall-store", client=client, **opts)
            else:
                raise SystemExit(f"unknown method {method!r}")
            out["seconds"] = time.perf_counter() - t0
        out["peak_rss"] = mem.client
        out["base_rss"] = mem.base
        if method in STREAM_METHODS:
            out.update(_stream_errors(method, sc, cfg, x, client))
            sc.close()
        elif result is not None:
            u, s, v = result
            out.update(_errors(np.asarray(u), np.asarray(s)[:k], np.asarray(v).T, cfg, x,
                               client))
            if method == "tsqr":
                np.save(work / "ref_s.npy", np.asarray(s))
                np.save(work / "ref_u.npy", np.asarray(u))
    finally:
        if client is not None:
            client.close()
            cluster.close()
    return out


def _stream_errors(method: str, sc: Any, cfg: dict, x: Any, client: Any) -> dict[str, Any]:
    import dask.array as da

    k = cfg["k"]
    if method == "streamsvd tall":
        U, V = sc.factors()
    else:
        e = sc.expansion
        U, V = da.from_array(e.U, chunks=(cfg["chunk_rows"], -1)), e.V
    Z, Vk, s = _truncate(V, k)
    out = _errors(U @ Z, s, Vk / s, cfg, x, client)
    out.update(rank_kept=sc.rank, error_bound=sc.error_bound)
    # continue with new snapshots: one more block (neither dask method can)
    new = _new_block(cfg, client)
    t0 = time.perf_counter()
    sc.absorb(new)
    out["update_seconds"] = time.perf_counter() - t0
    out["update_columns"] = int(new.shape[1])
    return out


def _new_block(cfg: dict, client: Any):
    import dask

    cols = cfg["tall_block"]
    x = data_array(cfg, col0=cfg["m"], cols=cols)
    if client is None:
        return np.asarray(dask.compute(x, scheduler="threads")[0])
    return np.asarray(client.compute(x).result())


def _errors(U: Any, s: np.ndarray, Vn: np.ndarray, cfg: dict, x: Any,
            client: Any) -> dict[str, Any]:
    """Errors of ``U diag(s) Vn^T`` (``Vn`` with orthonormal columns) against A and TSQR."""
    import dask
    import dask.array as da

    k = cfg["k"]
    sched = client if client is not None else "threads"
    if not isinstance(U, da.Array):
        U = da.from_array(np.asarray(U), chunks=(cfg["chunk_rows"], -1))
    U = U.rechunk((x.chunks[0], -1))
    VS = Vn * s
    resid = (x - U @ VS.T) ** 2
    work = [resid.sum(), (x**2).sum(), U.T @ U]
    ref_u = cfg.get("ref_u")
    if ref_u is not None:
        R = da.from_array(np.load(ref_u, mmap_mode="r"), chunks=(cfg["chunk_rows"], -1))
        work.append(R.rechunk((x.chunks[0], -1)).T @ U)
    vals = dask.compute(*work, scheduler=sched)
    err2, norm2, UtU = float(vals[0]), float(vals[1]), np.asarray(vals[2])
    out = {
        "error_rel": math.sqrt(max(err2, 0.0) / norm2),
        "orthogonality": float(np.linalg.norm(UtU - np.eye(UtU.shape[0]), 2)),
        "norm_A": math.sqrt(norm2),
        "s": s.tolist(),
    }
    ref_s = cfg.get("ref_s")
    if ref_s is not None:
        sr = np.load(ref_s)
        opt = math.sqrt(float(np.sum(sr[k:] ** 2)))
        out["optimal_rel"] = opt / math.sqrt(norm2)
        out["error_over_optimal"] = math.sqrt(max(err2, 0.0)) / opt
        out["sv_error"] = float(np.max(np.abs(s[:k] - sr[:k])) / sr[0])
        cosines = np.linalg.svd(np.asarray(vals[3]), compute_uv=False)
        out["max_angle_sin"] = math.sqrt(max(0.0, 1.0 - float(np.min(cosines)) ** 2))
    return out


# ------------------------------------------------------------------------------ main


def _child(method: str, cfg: dict, path: Path, work: Path, inprocess: bool) -> dict:
    if inprocess:
        return run_method(method, cfg, path, work)
    spec = json.dumps({"method": method, "cfg": cfg, "path": str(path), "work": str(work)})
    res = subprocess.run([sys.executable, __file__, "--child", spec], capture_output=True,
                         text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"{method} failed:\n{res.stderr[-4000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def parse_size(text: str) -> tuple[int, int]:
    try:
        n, m = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SystemExit(f"--size must look like 1000000x2000; got {text!r}") from None
    return n, m


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("bench_dask", argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="1000000x2000", help="n x m (rows x snapshots)")
    ap.add_argument("--k", type=int, default=20, help="rank of every method's result")
    ap.add_argument("--oversample", type=int, default=20, help="streamsvd keeps k + this")
    ap.add_argument("--signal", type=int, default=60, help="modes of the data")
    ap.add_argument("--decades", type=float, default=3.0, help="decay of the modes")
    ap.add_argument("--noise", type=float, default=1e-4, help="spectral norm of the noise")
    ap.add_argument("--chunk-rows", type=int, default=10000)
    ap.add_argument("--block", type=int, default=50, help="columns per zarr chunk")
    ap.add_argument("--tree-block", type=int, default=50)
    ap.add_argument("--tall-block", type=int, default=100)
    ap.add_argument("--leaf-columns", type=int, help="default m / 2 (a leaf per worker)")
    ap.add_argument("--workers", default="1,2", help="LocalCluster sizes for the scaling")
    ap.add_argument("--methods", help="comma-separated subset (default: all)")
    ap.add_argument("--tmpdir", help="where the data is written (default: system temp)")
    ap.add_argument("--keep", action="store_true", help="keep the data directory")
    ap.add_argument("--inprocess", action="store_true", help="no child processes (smoke)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="output directory (default bench/results)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        spec = json.loads(args.child)
        res = run_method(spec["method"], spec["cfg"], Path(spec["path"]), Path(spec["work"]))
        print(json.dumps(res))
        return res
    n, m = parse_size(args.size)
    cfg = {
        "n": n, "m": m, "k": args.k, "oversample": args.oversample, "signal": args.signal,
        "decades": args.decades, "noise": args.noise, "chunk_rows": args.chunk_rows,
        "block": args.block, "tree_block": args.tree_block, "tall_block": args.tall_block,
        "leaf_columns": args.leaf_columns or max(args.tree_block, -(-m // 2)),
        "seed": args.seed, "extra": args.tall_block,
    }
    base = ["read", "tsqr", "svd_compressed q=0", "svd_compressed q=1",
            "svd_compressed q=2", *STREAM_METHODS]
    methods = base if not args.methods else [s.strip() for s in args.methods.split(",")]
    workers = [int(w) for w in args.workers.split(",") if w.strip()]
    out = out_dir(args.out)
    tmp = Path(tempfile.mkdtemp(prefix="streamsvd-bench-", dir=args.tmpdir))
    runs: list[dict[str, Any]] = []
    try:
        path = tmp / "A.zarr"
        print(f"writing {n} x {m} float64 ({n * m * 8 / GB:.2f} GB) to {path}", flush=True)
        write_s = write_data(cfg, path)
        print(f"  written in {write_s:.1f} s", flush=True)
        for method in methods:
            cfg_run = dict(cfg)
            if method != "tsqr" and (tmp / "ref_s.npy").exists():
                cfg_run.update(ref_s=str(tmp / "ref_s.npy"), ref_u=str(tmp / "ref_u.npy"))
            res = _child(method, cfg_run, path, tmp, args.inprocess)
            runs.append(res)
            print(f"  {method:>22s}: {res['seconds']:8.2f} s, peak "
                  f"{res['peak_rss'] / GB:6.2f} GB", flush=True)
            if method == "tsqr":
                tsqr = res
                tsqr.update(_errors_vs_self(tsqr))
            shutil.rmtree(tmp / "tall-store", ignore_errors=True)
        for w in workers:
            for method in STREAM_METHODS:
                if method not in methods:
                    continue
                cfg_run = dict(cfg, workers=w)
                if (tmp / "ref_s.npy").exists():
                    cfg_run.update(ref_s=str(tmp / "ref_s.npy"), ref_u=str(tmp / "ref_u.npy"))
                res = _child(method, cfg_run, path, tmp, args.inprocess)
                runs.append(res)
                print(f"  {method:>16s} {w} worker(s): {res['seconds']:8.2f} s, peak "
                      f"{res['peak_rss'] / GB:6.2f} GB", flush=True)
                shutil.rmtree(tmp / "tall-store", ignore_errors=True)
    finally:
        if args.keep:
            print(f"data kept in {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    report = summarise(cfg, runs, write_s)
    report["machine"] = machine_info()
    report["command"] = " ".join(["python bench/bench_dask.py", *(argv or sys.argv[1:])])
    record.write(out / "bench_dask.json", report)
    plot(report, out / "bench_dask.png")
    print_table(*table(report), title=f"\nstreamsvd on dask, {n} x {m} ({n * m * 8 / GB:.2f} GB)")
    return report


def _errors_vs_self(tsqr: dict) -> dict:
    # TSQR is the reference: its truncation is the optimum
    return {"error_over_optimal": 1.0, "sv_error": 0.0, "max_angle_sin": 0.0,
            "optimal_rel": tsqr.get("error_rel")}


def summarise(cfg: dict, runs: list[dict], write_s: float) -> dict[str, Any]:
    nbytes = cfg["n"] * cfg["m"] * 8
    read = next((r for r in runs if r["method"] == "read"), None)
    read_tp = nbytes / read["seconds"] if read else None
    for r in runs:
        r["throughput"] = nbytes / r["seconds"]
        r["throughput_vs_read"] = r["throughput"] / read_tp if read_tp else None
    tsqr = next((r for r in runs if r["method"] == "tsqr"), None)
    targets: dict[str, Any] = {}
    main_stream = [r for r in runs if r["method"] in STREAM_METHODS and not r["workers"]]
    comp = [r for r in runs if r["method"].startswith("svd_compressed")]
    for r in main_stream:
        name = r["method"]
        targets[name] = {
            "peak_rss_under_2GB": r["peak_rss"] < 2 * GB,
            "throughput_at_least_half_of_read": (r["throughput_vs_read"] or 0) >= 0.5,
            "more_accurate_than_every_svd_compressed": bool(comp) and all(
                r.get("error_over_optimal", math.inf) < c.get("error_over_optimal", math.inf)
                for c in comp),
            "faster_than_tsqr": bool(tsqr) and r["seconds"] < tsqr["seconds"],
        }
    return {"config": cfg, "bytes": nbytes, "write_seconds": write_s,
            "read_throughput": read_tp, "runs": runs, "targets": targets}


def _label(r: dict) -> str:
    return r["method"] + (f" ({r['workers']}w)" if r.get("workers") else "")


def table(report: dict) -> tuple[list[str], list[list[Any]]]:
    headers = ["method", "time s", "peak GB", "MB/s", "vs read", "err/opt-1", "sv err",
               "sin angle", "orth", "update s"]
    rows = []
    for r in report["runs"]:
        rows.append([
            _label(r), r["seconds"], r["peak_rss"] / GB, r["throughput"] / 1e6,
            r["throughput_vs_read"] if r["throughput_vs_read"] is not None else math.nan,
            r.get("error_over_optimal", math.nan) - 1.0, r.get("sv_error", math.nan),
            r.get("max_angle_sin", math.nan), r.get("orthogonality", math.nan),
            r.get("update_seconds", math.nan),
        ])
    return headers, rows


def plot(report: dict, path: Path) -> None:
    plt = pyplot()
    runs = report["runs"]
    labels = [_label(r) for r in runs]
    fig, ax = plt.subplots(2, 2, figsize=(13, 8))
    y = np.arange(len(runs))
    colors = ["C2" if r["method"] in STREAM_METHODS else "C0" for r in runs]
    ax[0, 0].barh(y, [r["seconds"] for r in runs], color=colors)
    ax[0, 0].set(yticks=y, yticklabels=labels, xlabel="wall time (s)", title="time")
    ax[0, 0].invert_yaxis()
    ax[0, 1].barh(y, [r["peak_rss"] / GB for r in runs], color=colors)
    ax[0, 1].axvline(2.0, color="r", ls="--", lw=1, label="2 GB target")
    ax[0, 1].set(yticks=y, yticklabels=labels, xlabel="peak resident memory (GB)",
                 title="memory (process + workers)")
    ax[0, 1].invert_yaxis()
    ax[0, 1].legend()
    err = [(lab, r["error_over_optimal"] - 1.0) for lab, r in zip(labels, runs, strict=True)
           if "error_over_optimal" in r and r["method"] != "tsqr"]
    if err:
        ye = np.arange(len(err))
        ax[1, 0].barh(ye, [max(e, 1e-16) for _, e in err], color="C1")
        ax[1, 0].set(yticks=ye, yticklabels=[lab for lab, _ in err], xscale="log",
                     xlabel="||A - U_k V_k^T|| / optimum - 1 (TSQR reference)",
                     title="excess error over the optimal rank-k error")
        ax[1, 0].invert_yaxis()
    for method, marker in zip(STREAM_METHODS, "os", strict=True):
        pts = sorted((r["workers"], r["seconds"]) for r in runs
                     if r["method"] == method and r.get("workers"))
        if pts:
            ax[1, 1].plot(*zip(*pts, strict=True), marker=marker, label=method)
    if report.get("read_throughput"):
        ax[1, 1].axhline(report["bytes"] / report["read_throughput"], color="k", ls=":",
                         label="raw read (threads)")
    ax[1, 1].set(xlabel="LocalCluster workers (1 thread each)", ylabel="wall time (s)",
                 title="scaling on this machine")
    ax[1, 1].legend()
    cfg = report["config"]
    fig.suptitle(f"{cfg['n']} x {cfg['m']} float64, rank k = {cfg['k']} "
                 f"(streamsvd keeps {cfg['k'] + cfg['oversample']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
