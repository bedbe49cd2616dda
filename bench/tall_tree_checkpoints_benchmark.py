"""Tall-tree checkpoints benchmark: what committing every node costs, and what resuming saves.

    python bench/tall_tree_checkpoints_benchmark.py          # n = 50000, m = 400
    python bench/tall_tree_checkpoints_benchmark.py --n 5000 --m 80 --repeats 1

Setup
-----
An ``n x m`` matrix (``--n`` 50000, ``--m`` 400, a spectrum decaying from 1 to 1e-9
over 40 values) in a ``.npy`` file, compressed by
:func:`streamsvd.parallel.tall_tree_compress` on the threaded scheduler of this process
(``block`` 20, ``leaf_columns`` 100: 4 leaves and 3 merges, ``chunk_rows`` 8192,
``max_rank`` 10), with a new local store and its work directory in a temporary directory
each time. Three contenders, run interleaved ``--repeats`` times (3): ``checkpoints=False``;
``checkpoints=True`` (the default: every leaf and merge committed beside the store and
loaded back); and a *resume*: the same call after a run whose checkpoints were kept up
to the last merge (the root's), so that it loads the two merges below the root and runs
the root's merge only. One untimed call first loads what the first call would (imports,
compiled kernels).

Measures
--------
Wall and CPU time (``time.process_time``, every thread of this process) of each call,
medians over the repeats; the bytes written under the store's checkpoints are not
counted. Writes ``tall_tree_checkpoints_benchmark.json`` and ``.png`` to ``--out``.
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

from streamsvd.parallel import tall_tree_compress  # noqa: E402
from streamsvd.parallel.checkpoints import Checkpoints  # noqa: E402
from streamsvd.testing import with_spectrum  # noqa: E402

CONTENDERS = ("without checkpoints", "with checkpoints", "resumed below the root")


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=None, help="output directory (default bench/results)")
    p.add_argument("--n", type=int, default=50_000, help="rows")
    p.add_argument("--m", type=int, default=400, help="columns")
    p.add_argument("--repeats", type=int, default=3, help="interleaved runs per contender")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def _call(npy: Path, root: Path, label: str, m: int, **extra: Any) -> dict[str, float]:
    """Run the tall tree once into ``root``; return its wall and CPU seconds."""
    kw = dict(block=20, leaf_columns=max(20, m // 4), chunk_rows=8192, max_rank=10)
    w, c = time.perf_counter(), time.process_time()
    tall_tree_compress(str(npy), workdir=root / "work", store=root / "basis.zarr",
                       **kw, **extra).close(finalize=False)
    return {"wall": time.perf_counter() - w, "cpu": time.process_time() - c}


def _resume(npy: Path, root: Path, m: int) -> dict[str, float]:
    """Time a call that resumes from every node but the root (prepared untimed)."""
    prep = root / "prep"
    keep = Checkpoints.remove
    Checkpoints.remove = lambda self: None  # type: ignore[method-assign]
    try:
        _call(npy, prep, "prepare", m)
    finally:
        Checkpoints.remove = keep  # type: ignore[method-assign]
    parts = prep / "basis.zarr.tree"
    roots = sorted(p for p in parts.iterdir() if p.name == f"merge-0-{m}")
    for p in roots:  # the root's checkpoint goes: its merge runs again
        shutil.rmtree(p)
    parts.rename(root / "basis.zarr.tree")
    return _call(npy, root, "resume", m)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the benchmark; return the report (also written as JSON, with a PNG)."""
    record = Run("tall_tree_checkpoints_benchmark", argv)
    args = _parse(argv)
    out = out_dir(args.out)
    machine = machine_info()
    tmp = Path(tempfile.mkdtemp(prefix="streamsvd-tall-ck-"))
    try:
        A = with_spectrum(np.logspace(0, -9, 40), args.n, args.m,
                          np.random.default_rng(args.seed))
        npy = tmp / "a.npy"
        np.save(npy, A)
        (tmp / "warm").mkdir()
        _call(npy, tmp / "warm", "warm-up (imports, compiled kernels)", args.m)  # untimed
        runs: dict[str, list[dict[str, Any]]] = {c: [] for c in CONTENDERS}
        for rep in range(args.repeats):
            for label in CONTENDERS:
                root = tmp / f"{rep}-{label.replace(' ', '-')}"
                root.mkdir()
                if label == "resumed below the root":
                    r = _resume(npy, root, args.m)
                else:
                    r = _call(npy, root, label, args.m,
                              checkpoints=label == "with checkpoints")
                r["load_average"] = round(os.getloadavg()[0], 2)
                runs[label].append(r)
                shutil.rmtree(root)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    machine["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    results = [{"contender": c, "n": args.n, "m": args.m, "repeats": args.repeats,
                "wall_seconds": float(np.median([r["wall"] for r in rs])),
                "cpu_seconds": float(np.median([r["cpu"] for r in rs])),
                "runs": rs} for c, rs in runs.items()]
    report = {"machine": machine, "options": vars(args), "results": results}
    record.write(out / "tall_tree_checkpoints_benchmark.json", report)
    load = (f"load average {machine['load_average'][0]:.1f} before, "
            f"{machine['load_average_after'][0]:.1f} after")
    _plot(results, out / "tall_tree_checkpoints_benchmark.png", load)
    print_table(["contender", "wall s (median)", "CPU s (median)"],
                [[r["contender"], f"{r['wall_seconds']:.2f}", f"{r['cpu_seconds']:.2f}"]
                 for r in results],
                title=f"tall tree {args.n} x {args.m}, medians of {args.repeats} "
                f"interleaved runs ({load})")
    return report


def _plot(results: list[dict[str, Any]], path: Path, load: str) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    x = np.arange(len(results))
    ax.bar(x - 0.2, [r["wall_seconds"] for r in results], 0.4, label="wall")
    ax.bar(x + 0.2, [r["cpu_seconds"] for r in results], 0.4, label="CPU (this process)")
    ax.set_xticks(x, [r["contender"] for r in results], fontsize=8)
    ax.set_ylabel("seconds (median over the repeats)")
    ax.set_xlabel("tall_tree_compress with a local store")
    ax.set_title(f"n = {results[0]['n']}, m = {results[0]['m']}: 4 leaves, 3 merges "
                 f"({load})", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
