"""The cost of committing and reading a large basis, with and without chunk compression.

```
python bench/commit_benchmark.py [--n 200000] [--k 70] [--repeat 5] [--dir DIR] [--out DIR]
```

A :class:`streamsvd.store.BasisStore` in ``--dir`` (a temporary directory on the file
system of ``/tmp`` by default) commits a basis ``Q`` (``n x k``, Gaussian, as a basis is
to a compressor: floating-point noise) ``--repeat`` times, each commit a new generation
written whole (``fsync`` included), and reads it back as many times. Two layouts are
timed side by side in one process: the store's (chunks stored as they are) and chunks
compressed with zstd at level 3 (the layout before; set for this measurement only).
Reported: the median commit and read times, the commit's processor time (every thread of
the process: encoding, copies, checksums), the throughput, and the bytes on disk per
generation.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zarr.codecs
from _common import Run, machine_info, out_dir, print_table, pyplot

from streamsvd.store import BasisStore
from streamsvd.store import pack as pack_module

FP = "commit-benchmark"


def generation_bytes(path: Path) -> int:
    """Return the bytes of the current generation's files."""
    gens = sorted(p for p in (path / "generations").iterdir() if p.is_dir())
    return sum(f.stat().st_size for f in gens[-1].iterdir())


def measure(Q: np.ndarray, root: Path, layout: str, repeat: int) -> dict[str, Any]:
    """Commit and read ``Q`` ``repeat`` times in a new store under ``root``."""
    store_path = root / ("store-" + layout.replace(" ", "-"))
    commits, reads, cpu = [], [], []
    with BasisStore.create(store_path, n=Q.shape[0], inner_fingerprint=FP) as st:
        for _ in range(repeat):
            t0, c0 = time.perf_counter(), time.process_time()
            st.commit({"Q": Q})
            commits.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            t0 = time.perf_counter()
            back = st.read().arrays["Q"]
            reads.append(time.perf_counter() - t0)
            assert np.array_equal(back, Q)
        size = generation_bytes(store_path)
    mb = Q.nbytes / 2**20
    return {"layout": layout, "commit_s": statistics.median(commits), "read_s":
            statistics.median(reads), "commit_cpu_s": statistics.median(cpu),
            "commits": commits, "reads": reads, "commit_cpu": cpu,
            "commit_mb_s": mb / statistics.median(commits),
            "read_mb_s": mb / statistics.median(reads), "bytes": size,
            "bytes_over_data": size / Q.nbytes, "load": os.getloadavg()[0]}


def run(n: int, k: int, repeat: int, directory: str | None) -> dict[str, Any]:
    """Time both layouts; return the report."""
    Q = np.asfortranarray(np.random.default_rng(0).standard_normal((n, k)))
    rows = []
    default = pack_module.PACK_COMPRESSORS
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        for layout in ("stored as is", "zstd level 3"):
            pack_module.PACK_COMPRESSORS = (
                default if layout == "stored as is"
                else (zarr.codecs.ZstdCodec(level=3, checksum=False),))
            try:
                rows.append(measure(Q, Path(tmp), layout, repeat))
            finally:
                pack_module.PACK_COMPRESSORS = default
    return {"n": n, "k": k, "megabytes": Q.nbytes / 2**20, "rows": rows,
            "machine": machine_info()}


def plot(report: dict[str, Any], path: Path) -> None:
    """Draw the commit and read times of each layout."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    rows = report["rows"]
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r["commit_s"] for r in rows], 0.4, label="commit (fsync included)")
    ax.bar(x + 0.2, [r["read_s"] for r in rows], 0.4, label="read (checksums verified)")
    ax.set_xticks(x, [f"{r['layout']}\n{r['bytes_over_data']:.3f} of the data" for r in rows])
    ax.set_ylabel("time (s, median)")
    ax.set_xlabel("chunk layout")
    ax.set_title(f"one generation: a {report['n']} x {report['k']} float64 basis "
                 f"({report['megabytes']:.0f} MB)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("commit_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200000)
    ap.add_argument("--k", type=int, default=70)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--dir", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.n, args.k, args.repeat = 5000, 10, 1
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("streamsvd").setLevel(logging.WARNING)
    report = run(args.n, args.k, args.repeat, args.dir)
    print_table(["layout", "commit s", "MB/s", "commit CPU s", "read s", "MB/s",
                 "bytes / data", "load"],
                [[r["layout"], f"{r['commit_s']:.3f}", f"{r['commit_mb_s']:.0f}",
                  f"{r['commit_cpu_s']:.3f}",
                  f"{r['read_s']:.3f}", f"{r['read_mb_s']:.0f}", f"{r['bytes_over_data']:.3f}",
                  f"{r['load']:.1f}"] for r in report["rows"]],
                title=f"commit of a {args.n} x {args.k} basis")
    out = out_dir(args.out)
    record.write(out / "commit_benchmark.json", report)
    plot(report, out / "commit_benchmark.png")
    return report


if __name__ == "__main__":
    main()
