"""The tall mode at narrow blocks: its time against the in-memory stream, by block width.

```
python bench/tall_narrow_blocks.py [--n 200000] [--m 60] [--blocks 1,5,20] [--repeat 1]
                                   [--against REV] [--out DIR]
```

A random ``n x m`` matrix in memory (full rank: nothing is cut, so only a full buffer or
the panels' count makes the basis compact) is streamed in blocks of ``b`` columns by
:func:`streamsvd.parallel.tall_compress` (panels on a local scratch directory, row
chunks of 16384, the threaded scheduler) and by the in-memory
:class:`~streamsvd.StreamCompressor`, one BLAS thread. Each update that does not compact
adds a panel to the tall mode's basis and every pass reads each panel in tasks of its
own: the table gives the wall times (best of ``--repeat``), their ratio, the tall mode's
compactions and ``||A - U V^T||_F / ||A||_F``. ``--against REV`` runs the same rows on a
git revision (a worktree on ``PYTHONPATH``, in a child process) right after.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    Run,
    library_warnings_silenced,
    load_average,
    out_dir,
    print_table,
    pyplot,
    rows_of_revision,
)


def _row(A: np.ndarray, block: int, repeat: int) -> dict[str, Any]:
    """Time the tall mode and the in-memory stream on ``A`` in blocks of ``block``."""
    import streamsvd as ss
    from streamsvd.parallel import tall_compress

    n, m = A.shape
    tall, memory = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        tc = tall_compress(A, block=block, chunk_rows=16384)
        tall.append(time.perf_counter() - t0)
        compactions = tc._life.state.basis.compactions
        U, V = tc.factors()
        error = float(np.linalg.norm(A - np.asarray(U) @ V.T) / np.linalg.norm(A))
        tc.close()
        t0 = time.perf_counter()
        sc = ss.StreamCompressor(n)
        for j in range(0, m, block):
            sc.absorb(A[:, j:j + block])
        memory.append(time.perf_counter() - t0)
    return {"block": block, "tall": min(tall), "memory": min(memory),
            "ratio": min(tall) / min(memory), "compactions": compactions, "error": error,
            "load": load_average()[0] if load_average() else None}


def _rows(n: int, m: int, blocks: list[int], repeat: int) -> list[dict[str, Any]]:
    A = np.random.default_rng(0).standard_normal((n, m))
    with library_warnings_silenced():
        _row(A[:, :4], 1, 1)  # the compiled kernels and dask load once, untimed
        return [_row(A, b, repeat) for b in blocks]


def _plot(rows: list[dict[str, Any]], before: list[dict[str, Any]] | None, path: Path,
          title: str) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    b = [r["block"] for r in rows]
    ax.plot(b, [r["tall"] for r in rows], "o-", label="tall mode, this version")
    if before:
        ax.plot(b, [r["tall"] for r in before], "s--", label="tall mode, before")
    ax.plot(b, [r["memory"] for r in rows], "^-", label="in memory")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("block width b (columns per update)")
    ax.set_ylabel("wall time of the stream (s)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("tall_narrow_blocks", argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--n", type=int, default=200_000)
    p.add_argument("--m", type=int, default=60)
    p.add_argument("--blocks", default="1,5,20")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--against", default=None, help="a git revision to run the rows on too")
    p.add_argument("--out", default=None)
    p.add_argument("--rows-only", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    blocks = [int(x) for x in args.blocks.split(",") if x]
    rows = _rows(args.n, args.m, blocks, args.repeat)
    if args.rows_only:
        Path(args.rows_only).write_text(json.dumps(rows))
        return {}
    before = (rows_of_revision(args.against, __file__, [
        "--n", str(args.n), "--m", str(args.m), "--blocks", args.blocks,
        "--repeat", str(args.repeat)]) if args.against else None)
    report = {"n": args.n, "m": args.m, "against": args.against, "rows": rows,
              "before": before}
    out = out_dir(args.out)
    record.write(out / "tall_narrow_blocks.json", report)
    title = f"tall mode vs in memory, {args.n} x {args.m}, nothing cut"
    _plot(rows, before, out / "tall_narrow_blocks.png", title)
    table = [[r["block"], f"{r['tall']:.2f}", "-" if not before else f"{before[i]['tall']:.2f}",
              f"{r['memory']:.2f}", f"{r['ratio']:.1f}", r["compactions"],
              "-" if not before else before[i]["compactions"], f"{r['error']:.1e}",
              f"{r['load']:.1f}"]
             for i, r in enumerate(rows)]
    print_table(["b", "tall s", "tall s before", "memory s", "tall / memory", "compactions",
                 "before", "error", "load"], table, title=title)
    return report


if __name__ == "__main__":
    main()
