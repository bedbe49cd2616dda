"""What the guarantees cost: modes, bound and time at each target, this version against another.

On pyMOR's Burgers and heat snapshots (the cases of ``hapod_benchmark.py``, with their
mass matrices), at targets 1e-2 .. 1e-6 in the ``mean_l2`` and ``relative`` measures:

* ``stream``: one trajectory per update, converged cores (``rule="jacobi"``,
  ``sweeps=None``), then ``finalize``;
* ``tree``: ``tree_compress`` with one trajectory per leaf and the target ``absolute``
  (``mean_l2 sqrt(m)``), the measure whose leaves once overspent;
* ``window``: the stream with ``window`` = half the snapshots, the target in the measure
  (removals once made every later cut overspend).

Each row gives the modes kept, the optimum (the fewest modes of the exact POD in the
same inner product whose error meets the target), the certified error and the true
error in the measure, both over the target, and the CPU seconds. With ``--against REV``
the same runs are made on the code of git revision ``REV`` (a worktree, in a child
process) and the table sets the two side by side: the extra modes the guarantees cost.

Run: ``python bench/guarantee_cost.py --against 11e65d8`` (pyMOR, from the ``bench``
extra, generates the snapshots once into ``bench/data/hapod``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    Run,
    library_warnings_silenced,
    machine_info,
    out_dir,
    print_table,
    pyplot,
    rows_of_revision,
)
from hapod_benchmark import DEFAULT_CACHE, _projection_error2, generate  # noqa: E402

TARGETS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
MEASURES = ("mean_l2", "relative")
KINDS = ("stream", "window", "tree")


def _optimal_modes(X: np.ndarray, M: Any, budget: float) -> int:
    """The fewest modes of the exact POD (in ``M``) whose error is at most ``budget``."""
    G = X.T @ (M @ X)
    lam = np.clip(np.linalg.eigvalsh(0.5 * (G + G.T))[::-1], 0.0, None)
    tail = np.append(np.cumsum(lam[::-1])[::-1], 0.0)
    return int(np.argmax(np.sqrt(tail) <= budget))


def _in_measure(err: float, measure: str, m: int, norm: float) -> float:
    return err / math.sqrt(m) if measure == "mean_l2" else err / norm


def run_one(X: np.ndarray, M: Any, lengths: np.ndarray, kind: str, measure: str,
            target: float) -> dict[str, Any]:
    """One contender at one target; the error is measured on the snapshots it covers."""
    import streamsvd as ss
    from streamsvd.parallel.cluster import tree_compress

    starts = np.concatenate([[0], np.cumsum(lengths)])
    m = X.shape[1]
    kw: dict[str, Any] = {"inner": M, "rule": "jacobi", "sweeps": None}
    t0 = time.process_time()
    if kind == "tree":
        # the absolute target that is this mean_l2 / relative target on all snapshots
        norm = math.sqrt(float(np.sum(_projection_error2(X, np.zeros((X.shape[0], 0)), M))))
        absolute = target * (math.sqrt(m) if measure == "mean_l2" else norm)
        sc = tree_compress(X, block=int(lengths[0]), leaf_columns=int(lengths[0]),
                           target_error=absolute, error_measure="absolute", **kw)
        covered = X
    else:
        window = None if kind == "stream" else m // 2
        sc = ss.StreamCompressor(X.shape[0], target_error=target, error_measure=measure,
                                 window=window, **kw)
        for a, b in zip(starts[:-1], starts[1:], strict=True):
            sc.absorb(X[:, a:b])
        covered = X[:, -sc.n_seen:]
    sc.finalize()
    seconds = time.process_time() - t0
    Q = sc.expansion.U
    err = math.sqrt(float(np.sum(_projection_error2(covered, Q, M))))
    mc = covered.shape[1]
    norm = math.sqrt(float(np.sum(_projection_error2(covered, np.zeros((X.shape[0], 0)), M))))
    budget = target * (math.sqrt(mc) if measure == "mean_l2" else norm)
    return {
        "kind": kind, "measure": measure, "target": target, "modes": sc.rank,
        "optimal": _optimal_modes(covered, M, budget),
        "certified_over_target": _in_measure(sc.error_bound, measure, mc, norm) / target,
        "true_over_target": _in_measure(err, measure, mc, norm) / target,
        "seconds": seconds,
    }


def measure_all(cases: list[str], cache: Path, quick: bool) -> list[dict[str, Any]]:
    """Every case, kind, measure and target on the code importable as ``streamsvd``."""
    with library_warnings_silenced():  # the warnings of missed targets, counted instead
        return _measure_all(cases, cache, quick)


def _measure_all(cases: list[str], cache: Path, quick: bool) -> list[dict[str, Any]]:
    rows = []
    for case in cases:
        names = generate(case, cache, quick)
        X = np.asfortranarray(np.load(names["X"]))
        M = sp.load_npz(names["M"]).tocsr()
        lengths = np.load(names["meta"])
        for kind in KINDS:
            for measure in MEASURES:
                for target in TARGETS:
                    row = run_one(X, M, lengths, kind, measure, target)
                    row["case"] = case
                    rows.append(row)
                    print(f"{case} {kind} {measure} {target:g}: {row['modes']} modes "
                          f"(optimum {row['optimal']}), certified/target "
                          f"{row['certified_over_target']:.3f}", file=sys.stderr, flush=True)
    return rows


def _against(rev: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    """Run :func:`measure_all` on revision ``rev`` in a child process (a git worktree)."""
    return list(rows_of_revision(rev, __file__, [
        "--cases", args.cases, "--cache", args.cache, *(["--quick"] if args.quick else [])]))


def _figure(rows: list[dict[str, Any]], before: list[dict[str, Any]] | None, path: Path,
            rev: str | None) -> None:
    plt = pyplot()
    cases = sorted({r["case"] for r in rows})
    fig, axes = plt.subplots(len(cases), len(KINDS), figsize=(4.2 * len(KINDS),
                                                               3.4 * len(cases)),
                             squeeze=False)
    for i, case in enumerate(cases):
        for j, kind in enumerate(KINDS):
            ax = axes[i][j]
            for measure, style in zip(MEASURES, ("o", "s"), strict=True):
                sel = [r for r in rows if r["case"] == case and r["kind"] == kind
                       and r["measure"] == measure]
                t = [r["target"] for r in sel]
                ax.plot(t, [r["modes"] for r in sel], style + "-",
                        label=f"{measure}: this version")
                ax.plot(t, [r["optimal"] for r in sel], style + ":", color="gray",
                        label=f"{measure}: optimum")
                if before:
                    old = [r for r in before if r["case"] == case and r["kind"] == kind
                           and r["measure"] == measure]
                    ax.plot([r["target"] for r in old], [r["modes"] for r in old],
                            style + "--", alpha=0.6, label=f"{measure}: {rev}")
            ax.set_xscale("log")
            ax.invert_xaxis()
            ax.set_xlabel("target error (in its measure)")
            ax.set_ylabel("modes kept")
            ax.set_title(f"{case}: {kind}")
            ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("guarantee_cost", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="directory for the PNG and JSON")
    ap.add_argument("--cache", default=str(DEFAULT_CACHE), help="snapshot cache directory")
    ap.add_argument("--cases", default="burgers,heat")
    ap.add_argument("--against", default=None, help="git revision to compare with")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--rows-only", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    cases = args.cases.split(",")
    rows = measure_all(cases, Path(args.cache), args.quick)
    if args.rows_only:
        Path(args.rows_only).write_text(json.dumps(rows))
        return {"rows": rows}
    before = _against(args.against, args) if args.against else None
    table = []
    for r in rows:
        old = next((b for b in before or [] if all(b[k] == r[k] for k in
                                                   ("case", "kind", "measure", "target"))),
                   None)
        table.append([r["case"], r["kind"], r["measure"], f"{r['target']:g}", r["optimal"],
                      r["modes"], "" if old is None else old["modes"],
                      f"{r['certified_over_target']:.3f}",
                      "" if old is None else f"{old['certified_over_target']:.3f}",
                      f"{r['true_over_target']:.3f}", f"{r['seconds']:.2f}",
                      "" if old is None else f"{old['seconds']:.2f}"])
    rev = args.against or "-"
    print_table(["case", "kind", "measure", "target", "optimum", "modes", f"modes {rev}",
                 "certified/target", f"certified/target {rev}", "true/target", "CPU s",
                 f"CPU s {rev}"], table, title="\nwhat the guarantees cost")
    out = out_dir(args.out)
    name = "guarantee_cost" + ("_quick" if args.quick else "")
    data = {"machine": machine_info(), "load": os.getloadavg(), "against": args.against,
            "rows": rows, "before": before}
    record.write(out / f"{name}.json", data)
    _figure(rows, before, out / f"{name}.png", args.against)
    print(f"wrote {out / name}.json and .png")
    return data


if __name__ == "__main__":
    main()
