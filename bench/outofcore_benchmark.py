"""Out of core at disk speed: every streamsvd mode against the raw read and dask's SVDs.

```
python bench/outofcore_benchmark.py [--sizes 200000x1000,200000x500] [--dtype float64]
       [--methods read,cli,...] [--data DIR] [--out DIR] [--big] [--repeat R]
```

A zarr v3 array ``A = U diag(s) V^T`` (rank 200, ``s`` from 1 to 1e-10 log-spaced,
``U``, ``V`` orthonormal; chunks 10000 x 50, zarr's default zstd codec) is written once
into ``--data`` (kept for the next run). Every contender runs in its own process; its
peak resident memory is that process's high-water mark since its ``exec`` (``VmHWM``),
taken when the compression ends (before the result is gathered for the error; for the
command line, when it exits). Before each contender
the raw read (``da.from_zarr(A).sum()``) is timed again, and the contender's time is
reported as a multiple of that adjacent read, so that the load of the shared machine
cancels out of the ratios. Two ratios: "x read" divides the time measured inside each
process (after its interpreter started and imported dask; the command line is only
timed as a whole process, so its time includes that start) by the read's; "x read
(processes)" divides the wall times of the two processes, interpreter start and imports
included on both sides. The error is ``||A - U_k V_k^T||_F`` over the optimum
``sqrt(sum_{i>k} s_i^2)``, ``k = 60``, measured in a separate pass over the array (for a
float32 array, the optimum of the stored rounded values, from the float64 eigenvalues of
``A^T A``: the float64 SVD of the rounded data).

CPU time: ``cpu_seconds`` is the CPU time of the process (all its threads, user and
system) over the timed part (the whole process for the command line), "cores" that
over the time, and "floor x read" the least "x read" that this CPU time allows on the
machine's cores (``cpu_seconds / cores / read time``): a mode whose floor is near a
target cannot meet it by overlapping better, only by doing less work.

Contenders (block 100, rank 60):

* ``read``: ``da.from_zarr(A).sum()``;
* ``cli``: ``streamsvd ingest A S --max-rank 60`` (the default ``--commit-every auto``:
  commits timed to take about a tenth of the time); ``cli-c1``: the same with
  ``--commit-every 1`` (one commit per update); ``cli-c100``: with ``--commit-every 100``
  (one commit at the end); ``cli-o20``: with ``--oversampling 20`` (80 terms kept while
  streaming instead of 70: more accurate, more flops);
* ``tall``: :func:`streamsvd.parallel.tall_compress` (``U`` in zarr panels), finalised;
  ``tall-o20``: with ``oversampling=20``;
* ``tree``: :func:`streamsvd.parallel.tree_compress` with two leaves on the two cores;
* ``svdc-q{0,1,2}-{power,QR}``: ``dask.array.linalg.svd_compressed(A, 60,
  n_power_iter=q, iterator=...)``;
* ``tsqr``: ``dask.array.linalg.svd`` (TSQR) of ``A`` rechunked to full rows.

``--repeat R`` runs every contender ``R`` times, the repeats interleaved (each with its
adjacent read); the table and the figure show the medians, the JSON every run.

``--big`` adds a 2,000,000 x 2,000 float32 array (16 GB; this machine has 23 GB of
memory) for the raw read and the streamsvd modes, timed without the error (its ``U`` is
Gaussian, not orthonormal, so the optimum is not known in closed form).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot

# the cores this process may run on (its affinity), which the floor divides by
CPU_COUNT = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
    os.cpu_count() or 1)

RANK, SIGNAL, BLOCK, CHUNK = 60, 200, 100, (10000, 50)
METHODS = ("read", "cli", "cli-c1", "cli-c100", "cli-o20", "tall", "tall-o20", "tree",
           "svdc-q0-power", "svdc-q1-power", "svdc-q1-QR", "svdc-q2-power", "svdc-q2-QR",
           "tsqr")
STREAMSVD = ("cli", "cli-c1", "cli-c100", "cli-o20", "tall", "tall-o20", "tree")
REPO = Path(__file__).resolve().parents[1]


def spectrum() -> np.ndarray:
    """The singular values of the test array."""
    return np.logspace(0, -10, SIGNAL)


def write_data(path: Path, n: int, m: int, dtype: str, seed: int = 0) -> float:
    """Write ``A = U diag(s) V^T`` to a zarr array at ``path`` by row chunks; return seconds."""
    import zarr

    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    V, _ = np.linalg.qr(rng.standard_normal((m, SIGNAL)))
    SV = spectrum()[:, None] * V.T
    z = zarr.create_array(str(path) + ".tmp", shape=(n, m), chunks=CHUNK, dtype=dtype,
                          overwrite=True)
    if n <= 400000:  # U orthonormal exactly: the optimum is known
        U, _ = np.linalg.qr(rng.standard_normal((n, SIGNAL)))
        rows = lambda a, b: U[a:b]  # noqa: E731
    else:  # too tall to orthonormalise in memory: Gaussian rows, nearly orthonormal
        rows = lambda a, b: rng.standard_normal((b - a, SIGNAL)) / np.sqrt(n)  # noqa: E731
    for a in range(0, n, CHUNK[0]):
        b = min(a + CHUNK[0], n)
        z[a:b] = (rows(a, b) @ SV).astype(dtype)
    os.replace(str(path) + ".tmp", path)
    return time.perf_counter() - t0


# ------------------------------------------------------------------------ children


def _peak_mb() -> float:
    """This process's peak resident memory since its ``exec`` (``VmHWM``), in MB.

    Not ``ru_maxrss``: Linux counts in it the memory of the process before ``exec``,
    which for a child is its parent's (the residuals computed between two contenders
    grow the parent to about 1 GB).
    """
    with open("/proc/self/status") as f:
        kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    return kb / 1024.0


# the command line, run so that its peak memory is written to the file $PEAK_FILE on exit
_CLI = ("import atexit, os, runpy, sys\n"
        "def peak():\n"
        "    with open('/proc/self/status') as f:\n"
        "        kb = next(int(x.split()[1]) for x in f if x.startswith('VmHWM:'))\n"
        "    with open(os.environ['PEAK_FILE'], 'w') as f:\n"
        "        f.write(str(kb / 1024.0))\n"
        "atexit.register(peak)\n"
        "sys.argv[0] = 'streamsvd'\n"
        "runpy.run_module('streamsvd', run_name='__main__', alter_sys=True)\n")


def run_child(method: str, path: str, work: str) -> dict[str, Any]:
    """Run one contender in this process; save its factors to ``work``/factors.npy files."""
    import dask
    import dask.array as da

    out: dict[str, Any] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    U = V = None
    if method == "read":
        dask.compute(da.from_zarr(path).sum(), scheduler="threads")
    elif method in ("tall", "tall-o20", "tree"):
        from streamsvd.parallel.cluster import tall_compress, tree_compress

        if method.startswith("tall"):
            extra = {"oversampling": 20} if method == "tall-o20" else {}
            sc = tall_compress(path, block=BLOCK, max_rank=RANK, **extra)
        else:
            import zarr

            m = zarr.open_array(path, mode="r").shape[1]
            sc = tree_compress(path, block=BLOCK, max_rank=RANK, leaf_columns=-(-m // 2))
        sc.finalize()
        out["seconds"] = time.perf_counter() - t0
        out["cpu_seconds"] = time.process_time() - c0
        out["peak_rss_mb"] = _peak_mb()
        e = sc.expansion
        U, V = e.U, e.V
        sc.close(finalize=False)
    elif method.startswith("svdc") or method == "tsqr":
        x = da.from_zarr(path)
        if method == "tsqr":
            u, s, v = da.linalg.svd(x.rechunk({1: -1}))
        else:
            _, q, it = method.split("-")
            u, s, v = da.linalg.svd_compressed(x, RANK, n_power_iter=int(q[1:]),
                                               iterator=it, seed=0)
        u, s, v = dask.compute(u[:, :RANK], s[:RANK], v[:RANK], scheduler="threads")
        U, V = u, (s[:, None] * v).T
    out.setdefault("seconds", time.perf_counter() - t0)
    out.setdefault("cpu_seconds", time.process_time() - c0)
    out.setdefault("peak_rss_mb", _peak_mb())
    if U is not None:
        np.save(Path(work) / "U.npy", U)
        np.save(Path(work) / "V.npy", V)
    return out


def _cli_factors(store: Path, work: Path) -> None:
    from streamsvd.cli.reading import open_readonly

    with open_readonly(store) as sc:
        e = sc.expansion
    np.save(work / "U.npy", e.U)
    np.save(work / "V.npy", e.V)


def measure(method: str, path: Path, work: Path, errors: bool = True) -> dict[str, Any]:
    """Run ``method`` in its own process; return its time, peak RSS and (``errors``) error."""
    env = dict(os.environ, PYTHONPATH=str(REPO), PEAK_FILE=str(work / "peak.txt"))
    if method.startswith("cli"):
        store = work / "S"
        cmd = [sys.executable, "-c", _CLI, "ingest", str(path), str(store),
               "--max-rank", str(RANK), "--block", str(BLOCK), "--quiet"]
        if method.startswith("cli-c"):
            cmd += ["--commit-every", method[len("cli-c"):]]
        if method == "cli-o20":
            cmd += ["--oversampling", "20"]
    else:
        cmd = [sys.executable, __file__, "--child", method, "--path", str(path),
               "--work", str(work)]
    t0 = time.perf_counter()
    with open(work / "stdout.txt", "wb") as out:
        proc = subprocess.Popen(cmd, env=env, stdout=out)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    stdout = (work / "stdout.txt").read_bytes()
    if status != 0:
        raise RuntimeError(f"{method} failed with status {status}")
    if method.startswith("cli"):
        from streamsvd.store import open_store

        with open_store(work / "S", "r") as st:  # generations from 0, the creation's commit
            commits = st.generation + 1
        result = {"seconds": wall, "peak_rss_mb": float((work / "peak.txt").read_text()),
                  "commits": commits, "cpu_seconds": usage.ru_utime + usage.ru_stime}
        if errors:
            _cli_factors(work / "S", work)
    else:
        result = json.loads(stdout.decode().strip().splitlines()[-1])
    result["process_seconds"] = wall
    result["process_cpu_seconds"] = usage.ru_utime + usage.ru_stime
    if errors and (work / "U.npy").exists():
        result["error"] = residual(path, np.load(work / "U.npy"), np.load(work / "V.npy"))
    return result


def residual(path: Path, U: np.ndarray, V: np.ndarray) -> float:
    """Return ``||A - U V^T||_F``, column block by column block."""
    import zarr

    z = zarr.open_array(str(path), mode="r")
    total = 0.0
    for a in range(0, z.shape[1], 200):
        X = np.asarray(z[:, a:a + 200], dtype=np.float64)
        X -= U @ V[a:a + 200].T
        total += float(np.sum(X * X))
    return float(np.sqrt(total))


def rounded_optimum(path: Path) -> float:
    """Return the optimal rank-60 error of the stored (rounded) data, in float64.

    ``||A||_F^2`` minus the 60 largest eigenvalues of ``A^T A``, both summed in float64
    from the float32 values by slabs of rows: the float64 SVD of the rounded data,
    without the cancellation of summing the tail eigenvalues.
    """
    import zarr

    z = zarr.open_array(str(path), mode="r")
    G = np.zeros((z.shape[1], z.shape[1]))
    total = 0.0
    for a in range(0, z.shape[0], 20000):
        X = np.asarray(z[a:a + 20000], dtype=np.float64)
        G += X.T @ X
        total += float(np.sum(X * X))
    lam = np.linalg.eigvalsh(G)[::-1]
    return float(np.sqrt(max(total - float(np.sum(lam[:RANK])), 0.0)))


# ------------------------------------------------------------------------ the run


def run_size(n: int, m: int, dtype: str, methods: list[str], data: Path,
             repeat: int = 1) -> dict[str, Any]:
    path = data / f"A_{n}x{m}_{dtype}.zarr"
    write_s = None
    if not path.exists():
        print(f"writing {path} ...", file=sys.stderr)
        write_s = write_data(path, n, m, dtype)
    exact = n <= 400000  # the arrays whose optimum (and error) is measured
    optimum = None
    if exact:
        optimum = rounded_optimum(path) if dtype == "float32" else float(
            np.sqrt(np.sum(spectrum()[RANK:] ** 2)))
    runs = []
    for method in [x for _ in range(repeat) for x in methods]:  # the repeats interleaved
        with tempfile.TemporaryDirectory(dir=data) as w1, \
                tempfile.TemporaryDirectory(dir=data) as w2:
            load0 = os.getloadavg()[0]
            read = measure("read", path, Path(w1))
            r = read if method == "read" else measure(method, path, Path(w2), exact)
            r.update(method=method, read_seconds=read["seconds"],
                     vs_read=r["seconds"] / read["seconds"],
                     read_process_seconds=read["process_seconds"],
                     vs_read_process=r["process_seconds"] / read["process_seconds"],
                     cores=r["cpu_seconds"] / r["seconds"],
                     floor_vs_read=r["cpu_seconds"] / CPU_COUNT / read["seconds"],
                     load_before=load0, load_after=os.getloadavg()[0])
            if "error" in r and optimum is not None:
                r["error_over_optimum"] = r["error"] / optimum
            runs.append(r)
            print(f"{n}x{m} {method}: {r['seconds']:.2f} s ({r['vs_read']:.2f} x read), "
                  f"{r['peak_rss_mb']:.0f} MB, err/opt {r.get('error_over_optimum', '-')}",
                  file=sys.stderr)
    mb = n * m * np.dtype(dtype).itemsize / 1e6
    return {"n": n, "m": m, "dtype": dtype, "megabytes": mb, "optimum": optimum,
            "write_seconds": write_s, "runs": runs, "medians": medians(runs)}


def medians(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Return, per method, the medians of its runs (the error is the same in each)."""
    keys = ("seconds", "vs_read", "vs_read_process", "peak_rss_mb", "load_before",
            "cpu_seconds", "cores", "floor_vs_read")
    out = []
    for method in dict.fromkeys(r["method"] for r in runs):
        mine = [r for r in runs if r["method"] == method]
        row = {"method": method, "runs": len(mine),
               **{k: float(np.median([r[k] for r in mine])) for k in keys}}
        if "error_over_optimum" in mine[0]:
            row["error_over_optimum"] = mine[0]["error_over_optimum"]
        out.append(row)
    return out


def plot(report: dict[str, Any], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5))
    markers = dict(zip(METHODS, "o1^v<>23sDpPX*", strict=True))
    for i, case in enumerate(report["cases"]):
        for r in case["medians"]:
            if "error_over_optimum" not in r:
                continue
            excess = max(r["error_over_optimum"] - 1.0, 1e-16)
            dask_svd = r["method"] not in STREAMSVD
            ax.scatter(r["vs_read"], excess, marker=markers[r["method"]], s=45,
                       color=f"C{i}", label=f"{'dask ' if dask_svd else ''}{r['method']}, "
                       f"{case['n']} x {case['m']}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time / time of the raw read (da.from_zarr(A).sum()), adjacent run")
    ax.set_ylabel("error / optimal rank-60 error - 1  (floored at 1e-16)")
    ax.set_title("Out of core, rank 60: a marker per method, a colour per array")
    ax.legend(fontsize=7, ncol=2, loc="best")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("outofcore_benchmark", argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="200000x1000,200000x500")
    p.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "streamsvd-ooc"))
    p.add_argument("--out", default=None)
    p.add_argument("--big", action="store_true")
    p.add_argument("--repeat", type=int, default=1,
                   help="runs of every contender, interleaved; the table shows medians")
    p.add_argument("--child", help=argparse.SUPPRESS)
    p.add_argument("--path", help=argparse.SUPPRESS)
    p.add_argument("--work", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(run_child(args.child, args.path, args.work)))
        return {}
    methods = [x for x in args.methods.split(",") if x]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        p.error(f"--methods: unknown {unknown}; choose among {METHODS}")
    data = Path(args.data)
    data.mkdir(parents=True, exist_ok=True)
    plan = [(int(n), int(m), args.dtype, methods) for n, m in
            (s.split("x") for s in args.sizes.split(",") if s)]
    if args.big:
        plan.append((2_000_000, 2000, "float32", [x for x in methods if x in STREAMSVD]))
    report: dict[str, Any] = {"machine": machine_info(), "rank": RANK, "block": BLOCK,
                              "chunks": CHUNK, "cores": CPU_COUNT, "cases": []}
    out = out_dir(args.out)
    for n, m, dtype, which in plan:  # the report is written after each array
        report["cases"].append(run_size(n, m, dtype, which, data, args.repeat))
        record.write(out / "outofcore_benchmark.json", report)
        plot(report, out / "outofcore_benchmark.png")
    cases = report["cases"]
    rows = [[f"{c['n']}x{c['m']} {c['dtype']}", r["method"], f"{r['seconds']:.2f}",
             f"{r['vs_read']:.2f}", f"{r['vs_read_process']:.2f}", f"{r['peak_rss_mb']:.0f}",
             f"{r['cpu_seconds']:.2f}", f"{r['cores']:.2f}", f"{r['floor_vs_read']:.2f}",
             f"{r['error_over_optimum']:.6f}" if "error_over_optimum" in r else "-",
             f"{r['load_before']:.1f}"]
            for c in cases for r in c["medians"]]
    print_table(["array", "method", "s", "x read", "x read (processes)", "peak RSS MB",
                 "CPU s", "cores", "floor x read", "err/opt", "load"], rows,
                title=f"out of core, rank 60, block 100, medians of {args.repeat}")
    return report


if __name__ == "__main__":
    main()
