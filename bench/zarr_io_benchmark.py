"""zarr from dask's threads: zarr's shared event loop against one loop per core
(streamsvd.algebra.panels.zarr_io).

Usage::

    python bench/zarr_io_benchmark.py [--source A.zarr] [--repeat 4] [--rows 10000]
                                      [--ops 40] [--out DIR]

Two measurements, each route in its own process, interleaved, medians of ``--repeat``:

* ``tall_compress(source, block=100, max_rank=60, store=..., commit_every=1)`` and
  ``finalize()`` on a zarr array (default: the 200000 x 1000 float64 array of
  ``bench/outofcore_benchmark.py``, made there), with :mod:`streamsvd.algebra.panels.zarr_io`'s
  loops and with zarr's own (the module's store check patched to refuse every store, in the child
  only). The passes use raw panels; each commit writes the zarr copy of the new panel,
  which is what the routes differ in (before raw panels, the passes read and wrote zarr
  panels, and this ran without a store);
* reads and writes alone: ``--ops`` row chunks of ``--rows`` x 100 float64 (``bytes`` +
  ``crc32c``, the tall mode's panels) from 1 and 2 threads that do nothing else, in ms
  per chunk (wall time over chunks).

Prints both tables, saves ``zarr_io_benchmark.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, Run, machine_info, out_dir, print_table, pyplot  # noqa: E402

logger = logging.getLogger("zarr_io_benchmark")
ROUTES = ("loops", "zarr")
DEFAULT_SOURCE = Path(tempfile.gettempdir()) / "streamsvd-ooc" / "A_200000x1000_float64.zarr"


def _route(route: str) -> None:
    """In this (child) process, send every zarr read and write through zarr's own loop."""
    if route == "zarr":
        from streamsvd.algebra.panels import zarr_io

        zarr_io._parallel = lambda array: False  # type: ignore[assignment]


def child_tall(source: str, route: str) -> dict[str, float]:
    """Run the tall mode on ``source``; return its time and peak RSS."""
    import resource

    _route(route)
    from streamsvd.parallel.cluster import tall_compress

    with tempfile.TemporaryDirectory() as work:
        t0 = time.perf_counter()
        tc = tall_compress(source, block=100, max_rank=60, store=Path(work) / "s.zarr",
                           commit_every=1)
        tc.finalize()
        seconds = time.perf_counter() - t0
        tc.close(finalize=False)
    return {"seconds": seconds,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def child_ops(route: str, threads: int, rows: int, ops: int, cols: int = 100
              ) -> dict[str, float]:
    """Write then read ``ops`` row chunks from ``threads`` threads; return ms per chunk."""
    import zarr
    from threadpoolctl import threadpool_limits
    from zarr.codecs import Crc32cCodec

    _route(route)
    from streamsvd.algebra.panels import zarr_io

    X = np.random.default_rng(0).standard_normal((rows, cols))
    out = {}
    with tempfile.TemporaryDirectory(prefix="zarr-io-bench-") as d, threadpool_limits(1):
        z = zarr.create_array(store=d, name="p", shape=(rows * ops, cols),
                              chunks=(rows, cols), dtype="float64", fill_value=0.0,
                              compressors=[Crc32cCodec()], config={"write_empty_chunks": True})

        def region(i: int) -> tuple[slice, slice]:
            return slice(i * rows, (i + 1) * rows), slice(None)

        work = {"write": lambda i: zarr_io.write(z, region(i), X),
                "read": lambda i: zarr_io.read(z, region(i))}
        with ThreadPoolExecutor(threads) as pool:
            for kind, op in work.items():
                t0 = time.perf_counter()
                list(pool.map(op, range(ops)))
                out[kind] = 1e3 * (time.perf_counter() - t0) / ops
    return out


def _run_child(*args: str) -> dict[str, float]:
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    done = subprocess.run([sys.executable, __file__, "--child", *args], env=env,
                          capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    record = Run("zarr_io_benchmark", argv)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", default=str(DEFAULT_SOURCE))
    p.add_argument("--repeat", type=int, default=4)
    p.add_argument("--rows", type=int, default=10000)
    p.add_argument("--ops", type=int, default=40)
    p.add_argument("--out", default=None)
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        kind, *rest = args.child
        result = (child_tall(rest[0], rest[1]) if kind == "tall"
                  else child_ops(rest[0], *map(int, rest[1:])))
        print(json.dumps(result))
        return 0
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stderr)
    if not Path(args.source).exists():
        p.error(f"--source {args.source} does not exist; make it with "
                "bench/outofcore_benchmark.py --methods read, or pass a zarr array")
    tall: dict[str, list[dict[str, float]]] = {r: [] for r in ROUTES}
    ops: dict[str, list[dict[str, float]]] = {f"{r}@{t}": [] for t in (1, 2) for r in ROUTES}
    for rep in range(args.repeat):
        for route in ROUTES:
            logger.info("run %d/%d: tall mode, %s", rep + 1, args.repeat, route)
            tall[route].append(_run_child("tall", args.source, route))
        for key in ops:
            route, threads = key.split("@")
            ops[key].append(_run_child("ops", route, threads, str(args.rows), str(args.ops)))
    tall_med = {r: float(np.median([x["seconds"] for x in v])) for r, v in tall.items()}
    ops_med = {k: {kind: float(np.median([x[kind] for x in v])) for kind in ("write", "read")}
               for k, v in ops.items()}
    load = os.getloadavg()[0]
    print_table(["route", "tall mode s", "runs s", "peak RSS MB"],
                [[r, tall_med[r], " ".join(f"{x['seconds']:.1f}" for x in tall[r]),
                  max(x["peak_rss_mb"] for x in tall[r])] for r in ROUTES],
                title=f"tall_compress({Path(args.source).name}), medians of {args.repeat} "
                      f"(load {load:.1f})")
    print_table(["route", "threads", "write ms/chunk", "read ms/chunk"],
                [[k.split("@")[0], k.split("@")[1], m["write"], m["read"]]
                 for k, m in ops_med.items()],
                title=f"{args.rows} x 100 float64 chunks alone")
    out = out_dir(args.out)
    record.write(out / "zarr_io_benchmark.json",
                 {"machine": machine_info(), "source": args.source, "rows": args.rows,
                  "ops_count": args.ops, "tall": tall,
                  "tall_medians": tall_med, "ops": ops, "ops_medians": ops_med,
                  "load_after": os.getloadavg()})
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 3.8))
    labels = {"loops": "one loop per core (zarr_io)", "zarr": "zarr's own loop"}
    for i, r in enumerate(ROUTES):
        a1.scatter([i] * len(tall[r]), [x["seconds"] for x in tall[r]], label=labels[r])
        a1.hlines(tall_med[r], i - 0.2, i + 0.2, color="k")
    a1.set_xticks(range(len(ROUTES)), [labels[r] for r in ROUTES])
    a1.set_ylabel("tall_compress + finalize (s)")
    a1.set_title(f"tall mode, {Path(args.source).name}")
    a1.grid(alpha=0.3)
    for r, marker in zip(ROUTES, "so", strict=True):
        for kind, style in (("write", "-"), ("read", "--")):
            a2.plot([1, 2], [ops_med[f"{r}@{t}"][kind] for t in (1, 2)], style,
                    marker=marker, label=f"{kind}, {labels[r]}")
    a2.set_xticks([1, 2])
    a2.set_xlabel("threads")
    a2.set_ylabel("wall time per chunk (ms)")
    a2.set_title(f"{args.rows} x 100 float64 chunks alone")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "zarr_io_benchmark.png", dpi=120)
    logger.info("wrote %s", out / "zarr_io_benchmark.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
