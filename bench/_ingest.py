"""The ``ingest`` case of ``tight_targets.py``: out of core against the same computation in memory.

A 200000 x 500 float64 zarr array (``outofcore_benchmark.py``'s: chunks 10000 x 50,
zarr's default zstd codec; and the same array stored uncompressed), rank 60, blocks of
100. Every contender runs in its own process, the contenders interleaved (round ``r``
of each before round ``r + 1`` of any), medians of ``--repeat``; ``os.getloadavg()`` is
recorded before every run. Wall and CPU seconds (all threads):

* ``read``: the raw read, ``z[:, j:j + 100].sum()`` by blocks of 100 columns (zarr's
  own threads decode);
* ``read-src``: the read as ``ingest`` does it, :meth:`Source.blocks
  <streamsvd.io.sources.Source.blocks>` (the reader thread, one block ahead), summed;
* ``memory``: the in-memory API on the array already loaded (``StreamCompressor(n,
  max_rank=60)``, ``absorb`` by blocks of 100, ``finalize``), the reference;
* ``driver``: :func:`streamsvd.stream.ingest.ingest` from the zarr array into the same
  compressor without a store, finalised, in the process (imports excluded);
  ``driver-serial``: the same without read-ahead (each block read, then absorbed);
* ``cli``: ``streamsvd ingest A S --max-rank 60 --block 100 --quiet``, the whole process
  (interpreter start, imports, store creation and commits included); ``cli@REV`` the
  same command on revision ``REV`` (``--against``, a git worktree);
* ``tall``: :func:`streamsvd.parallel.tall_compress` (``block=100, max_rank=60``) and
  ``finalize``, in the process (dask's import excluded).

Start-up (the rows of store ``start-up``, processes, wall and CPU seconds): ``streamsvd
--help``; ``streamsvd ingest`` of a 500 x 40 ``.npy`` file (``--max-rank 10``); ``streamsvd
info`` of the store it wrote.

Every command runs on compiled bytecode, as an installed package does (pip compiles a
wheel's modules when it installs it): the trees measured are compiled first
(``compileall``). Without it, where ``PYTHONDONTWRITEBYTECODE`` is set (this machine's
environment), every run compiled the package's modules again, 0.14 s of the start-up.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

CONTENDERS = ("read", "read-src", "memory", "driver", "driver-serial", "cli", "tall")
STARTUP = ("help", "small ingest", "info")  # the rows of store "start-up"
RANK, BLOCK = 60, 100


def arrays(data: Path, quick: bool = False) -> dict[str, Path]:
    """The zstd array (written by ``outofcore_benchmark.py``'s code) and its uncompressed copy.

    ``quick``: 3000 x 250 instead of 200000 x 500 (a smoke test).
    """
    import zarr
    from outofcore_benchmark import write_data

    n, m = (3000, 250) if quick else (200000, 500)
    data.mkdir(parents=True, exist_ok=True)
    zstd, raw = data / f"A{n}x{m}.zarr", data / f"A{n}x{m}-raw.zarr"
    if not zstd.exists():
        write_data(zstd, n, m, "float64")
    if not raw.exists():
        src = zarr.open_array(str(zstd), mode="r")
        dst = zarr.create_array(str(raw) + ".tmp", shape=src.shape, chunks=src.chunks,
                                dtype=src.dtype, compressors=None, overwrite=True)
        for a in range(0, src.shape[0], src.chunks[0]):
            dst[a : a + src.chunks[0]] = src[a : a + src.chunks[0]]
        os.replace(str(raw) + ".tmp", raw)
    return {"zstd": zstd, "raw": raw}


def child(what: str, path: str) -> None:
    """``--child WHAT PATH``: one contender in this process; prints its times as JSON."""
    import zarr

    z = zarr.open_array(path, mode="r")
    if what == "read":
        t0, c0 = time.perf_counter(), time.process_time()
        total = 0.0
        for j in range(0, z.shape[1], BLOCK):
            total += float(z[:, j : j + BLOCK].sum())
    elif what == "read-src":
        from streamsvd.io.open import open_source

        t0, c0 = time.perf_counter(), time.process_time()
        with open_source(path) as src:
            total = sum(float(X.sum()) for _, X in src.blocks(BLOCK))
    elif what == "memory":
        import streamsvd as ss

        A = np.asfortranarray(z[:])
        t0, c0 = time.perf_counter(), time.process_time()
        sc = ss.StreamCompressor(A.shape[0], max_rank=RANK)
        for j in range(0, A.shape[1], BLOCK):
            sc.absorb(A[:, j : j + BLOCK])
        sc.finalize()
    elif what in ("driver", "driver-serial"):
        import streamsvd as ss
        from streamsvd.io.open import open_source
        from streamsvd.stream.ingest import ingest

        t0, c0 = time.perf_counter(), time.process_time()
        with open_source(path) as src:
            sc = ss.StreamCompressor(src.n, max_rank=RANK)
            ingest(src, sc, block=BLOCK, prefetch=what == "driver")
        sc.finalize()
    elif what == "tall":
        # imports are not the mode's time (dask.array imports xarray and pandas when they
        # are installed, 0.4-0.9 s here, and the modes read through it)
        import dask.array  # noqa: F401

        from streamsvd.parallel.cluster import tall_compress

        t0, c0 = time.perf_counter(), time.process_time()
        tc = tall_compress(path, block=BLOCK, max_rank=RANK)
        tc.finalize()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        tc.close(finalize=False)
        print(json.dumps({"wall": wall, "cpu": cpu}))
        return
    else:
        raise SystemExit(f"unknown contender {what!r}")
    print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0}))


def compile_tree(tree: Path) -> None:
    """Compile the package of ``tree`` to bytecode, as installing it would."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "streamsvd")],
                   check=True, stdout=subprocess.DEVNULL)


def _command(args: list[str], tree: Path, cwd: str) -> dict[str, float]:
    """Wall and CPU seconds of ``python -m streamsvd ARGS`` on the package of ``tree``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.perf_counter()
    r0 = os.times()
    subprocess.run([sys.executable, "-m", "streamsvd", *args], check=True, env=env, cwd=cwd,
                   stdout=subprocess.DEVNULL)
    wall, r1 = time.perf_counter() - t0, os.times()
    return {"wall": wall,
            "cpu": (r1.children_user - r0.children_user)
            + (r1.children_system - r0.children_system)}


def _cli(path: Path, tree: Path) -> dict[str, float]:
    # run from an empty directory: `python -m` puts the working directory first on the
    # path, which from a checkout would import the checkout's package whatever `tree` is
    with tempfile.TemporaryDirectory() as tmp:  # the store's removal is not the command's
        return _command(["ingest", str(path), str(Path(tmp) / "S.svd"), "--max-rank",
                         str(RANK), "--block", str(BLOCK), "--quiet"], tree, tmp)


def _startup(tree: Path) -> dict[str, dict[str, float]]:
    """``--help``, a small file's ingest and ``info`` of its store, each a process."""
    with tempfile.TemporaryDirectory() as tmp:
        small = Path(tmp) / "small.npy"
        np.save(small, np.random.default_rng(0).standard_normal((500, 40)))
        store = str(Path(tmp) / "S.svd")
        args = {"help": ["--help"],
                "small ingest": ["ingest", str(small), store, "--max-rank", "10", "--quiet"],
                "info": ["info", store]}
        return {what: _command(args[what], tree, tmp) for what in STARTUP}


def rows(paths: dict[str, Path], repeat: int, repo: Path, script: Path,
         against: tuple[str, Path] | None = None,
         contenders: tuple[str, ...] = CONTENDERS) -> list[dict[str, Any]]:
    """Every contender on every array, interleaved; one row per (array, contender)."""
    env = dict(os.environ, PYTHONPATH=str(repo))
    names = list(contenders) + ([f"cli@{against[0]}"] if against else [])
    for tree in (repo, *([against[1]] if against else [])):
        compile_tree(tree)
    runs: dict[tuple[str, str], list[dict[str, float]]] = {}
    for _ in range(repeat):
        for what, t in _startup(repo).items():
            t["load"] = os.getloadavg()[0]
            runs.setdefault(("start-up", what), []).append(t)
            print(f"  start-up {what:12s} wall {t['wall']:.2f} s, CPU {t['cpu']:.2f} s",
                  flush=True)
        for store, path in paths.items():
            for what in names:
                load = os.getloadavg()[0]
                if what == "cli":
                    t = _cli(path, repo)
                elif what.startswith("cli@") and against:
                    t = _cli(path, against[1])
                else:
                    out = subprocess.run([sys.executable, str(script), "--child", what,
                                          str(path)], check=True, capture_output=True,
                                         text=True, env=env)
                    t = json.loads(out.stdout.strip().splitlines()[-1])
                t["load"] = load
                runs.setdefault((store, what), []).append(t)
                print(f"  {store:4s} {what:14s} wall {t['wall']:.2f} s, CPU {t['cpu']:.2f} s,"
                      f" load {load:.1f}", flush=True)
    out_rows = []
    for (store, what), rs in runs.items():
        out_rows.append({"store": store, "contender": what,
                         "wall": statistics.median(r["wall"] for r in rs),
                         "cpu": statistics.median(r["cpu"] for r in rs),
                         "load": statistics.median(r["load"] for r in rs),
                         "load_min": min(r["load"] for r in rs),
                         "load_max": max(r["load"] for r in rs), "runs": rs})
    for row in out_rows:
        mem = next((r for r in out_rows if r["store"] == row["store"]
                    and r["contender"] == "memory"), None)
        row["wall_over_memory"] = None if mem is None else row["wall"] / mem["wall"]
        row["cpu_over_memory"] = None if mem is None else row["cpu"] / mem["cpu"]
    return out_rows


def figure(rows_: list[dict[str, Any]], path: Path) -> None:
    """Wall and CPU seconds of every contender, one group of bars per store."""
    from _common import pyplot

    plt = pyplot()
    stores = sorted({r["store"] for r in rows_})
    fig, axes = plt.subplots(1, len(stores), figsize=(6 * len(stores), 4), squeeze=False)
    for ax, store in zip(axes[0], stores, strict=True):
        rs = [r for r in rows_ if r["store"] == store]
        x = np.arange(len(rs))
        ax.bar(x - 0.2, [r["wall"] for r in rs], 0.4, label="wall")
        ax.bar(x + 0.2, [r["cpu"] for r in rs], 0.4, label="CPU (all threads)")
        mem = next((r for r in rs if r["contender"] == "memory"), None)
        if mem is not None:
            ax.axhline(1.2 * mem["wall"], color="k", lw=0.8, ls="--",
                       label="1.2 x in-memory wall")
        ax.set_xticks(x, [r["contender"] for r in rs], rotation=30, fontsize=7)
        ax.set_ylabel("seconds")
        what = "start-up (a 500 x 40 file)" if store == "start-up" else store
        ax.set_title(f"{what}: load {min(r['load_min'] for r in rs):.1f}-"
                     f"{max(r['load_max'] for r in rs):.1f}", fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle("200000 x 500 float64, rank 60, blocks of 100 (medians)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
