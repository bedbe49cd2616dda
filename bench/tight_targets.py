"""Tight targets, a rank cap and a full SVD: streamsvd against pyMOR's HAPOD and LAPACK.

```
python bench/tight_targets.py [--cases heat,burgers,cap,rbs480a,ingest] [--repeat 3]
       [--blocks traj,10,1000] [--dtypes float64,float32]
       [--ingest ZARR] [--ingest-data DIR] [--against REV] [--products] [--out DIR]
       [--quick]
```

One process, one BLAS thread, CPU time (``time.process_time``: the machine is shared),
the contenders interleaved (repeat ``r`` of each before repeat ``r + 1`` of any), medians
of ``--repeat``; ``os.getloadavg()`` recorded with every row.

* ``heat``: pyMOR's ``heat_equation_example(grid_intervals=50, nt=90)`` (5101 dofs),
  22 trajectories of 91 snapshots at ``parameters.space(1, 100).sample_randomly(22)``,
  its ``l2_product``; one trajectory per update. ``burgers``: the snapshots of
  ``hapod_benchmark.py`` (7200 x 2020, 20 trajectories of 101). At each target
  1e-2 .. 1e-6 in the ``mean_l2`` and ``relative`` measures: streamsvd (the Jacobi rule
  converged, ``right_vectors=False``, ``finalize()``) against
  ``inc_vectorarray_hapod(steps, U, eps, 0.9, product=l2)`` with ``eps`` the target
  (``mean_l2``) or ``target ||A||_M / sqrt(m)`` (``relative``, the same budget). Reported:
  CPU seconds, their ratio, the modes, the true error over the target (the
  ``M``-orthogonal projection on the modes) and streamsvd's certified bound over it.
  ``--blocks``: the updates' widths (``traj``, one trajectory, the default; or a number
  of columns: both contenders take the slices ``inc_vectorarray_hapod`` makes of
  ``ceil(m / width)`` steps); ``--dtypes``: the snapshots as given (``float64``) or
  rounded once to ``float32``, the same array for both.
* ``cap``: the synthetic stream of ``hapod_benchmark.py`` (n 20000, m 2000, blocks of
  100, ``max_rank=60``): streamsvd with its default oversampling and with 20, pyMOR's
  incremental HAPOD tree with ``pod(modes=60)`` and with 70 modes per step; the largest
  relative error of the 60 leading singular values of ``Q^T A`` (``sv_err``).
* ``rbs480a``: ``compress(Expansion.canonical(A), rule="jacobi")`` with and without
  ``precondition=True`` against ``scipy.linalg.svd(A, lapack_driver="gesdd")``, and the
  LAPACK test ratios of the result.
* ``ingest`` (or ``--ingest ZARR`` for one given array): out of core against the same
  computation in memory, on a 200000 x 500 float64 zarr array (zstd, and the same
  uncompressed), written once into ``--ingest-data``; the contenders are
  ``_ingest.py``'s (the raw read, the read as ``ingest`` does it, the in-memory API, the
  ingest driver with and without read-ahead, ``streamsvd ingest`` as a process, the tall
  mode), each in its own process, wall and CPU time; and the command's start-up
  (``--help``, a small file's ``ingest`` and ``info``), on compiled bytecode as an
  installed package runs.

``--against REV`` runs the same rows on revision ``REV`` (a git worktree, a child
process, after this version's rows) and prints its ratios beside these; for ``ingest``
it adds ``cli@REV``, the command of revision ``REV``, interleaved with the others.
``--products`` runs each contender of a ``heat`` or ``burgers`` row once more, untimed,
with its ``n``-sized products counted (``_products.py``): Mflop and columns of ``M``
per update, and the ratio of the flops beside the ratio of the times.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _ingest  # noqa: E402
import _products  # noqa: E402
from _common import (  # noqa: E402
    REPO_ROOT,
    Run,
    library_warnings_silenced,
    load_rbs480a,
    machine_info,
    out_dir,
    print_table,
    pyplot,
    rows_of_revision,
)
from hapod_benchmark import DEFAULT_CACHE, _projection_error2, generate  # noqa: E402

TARGETS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
MEASURES = ("mean_l2", "relative")
OMEGA = 0.9


# ------------------------------------------------------------------------------ data
def heat_snapshots(cache: Path, quick: bool) -> dict[str, Path]:
    """pyMOR's heat example, 22 trajectories of 91 snapshots (written once to ``cache``)."""
    grid, nt, k = (8, 10, 4) if quick else (50, 90, 22)
    tag = f"heat_g{grid}_nt{nt}_k{k}"
    names = {"X": cache / f"{tag}_X.npy", "M": cache / f"{tag}_M.npz",
             "meta": cache / f"{tag}_len.npy"}
    if all(p.is_file() for p in names.values()):
        return names
    from pymor.core.logger import set_log_levels
    from pymor.models.examples import heat_equation_example

    set_log_levels({"pymor": "WARN"})
    cache.mkdir(parents=True, exist_ok=True)
    fom = heat_equation_example(grid_intervals=grid, nt=nt)
    U = fom.solution_space.empty()
    lengths = []
    for mu in fom.parameters.space(1, 100).sample_randomly(k):
        Ui = fom.solve(mu)
        lengths.append(len(Ui))
        U.append(Ui)
    X = U.to_numpy()
    X = X if X.shape[1] == sum(lengths) else X.T
    np.save(names["X"], np.asfortranarray(X))
    sp.save_npz(names["M"], sp.csr_matrix(fom.l2_product.matrix))
    np.save(names["meta"], np.array(lengths))
    return names


def _load_case(case: str, cache: Path, quick: bool) -> tuple[np.ndarray, Any, np.ndarray]:
    names = heat_snapshots(cache, quick) if case == "heat" else {
        k: Path(v) for k, v in generate(case, cache, quick).items()}
    X = np.asfortranarray(np.load(names["X"]))
    return X, sp.load_npz(names["M"]).tocsr(), np.load(names["meta"])


# ------------------------------------------------------------------------ contenders
def _streamsvd_target(X: np.ndarray, M: Any, lengths: np.ndarray, target: float,
                      measure: str) -> tuple[float, np.ndarray, float]:
    import streamsvd as ss

    starts = np.concatenate([[0], np.cumsum(lengths)])
    c0 = time.process_time()
    sc = ss.StreamCompressor(X.shape[0], target_error=target, error_measure=measure,
                             inner=M, rule="jacobi", sweeps=None, right_vectors=False)
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        sc.absorb(X[:, a:b])
    sc.finalize()
    return time.process_time() - c0, sc.left_vectors, sc.error_bound


def _hapod_target(U: Any, prod: Any, steps: int, eps: float) -> tuple[float, np.ndarray]:
    from pymor.algorithms.hapod import inc_vectorarray_hapod

    c0 = time.process_time()
    modes = inc_vectorarray_hapod(steps, U, eps, OMEGA, product=prod)[0]
    return time.process_time() - c0, modes.to_numpy()


def _chunks(lengths: np.ndarray, block: str) -> tuple[np.ndarray, int]:
    """The widths of the updates and HAPOD's ``steps``: one trajectory, or ``block`` columns.

    ``inc_vectorarray_hapod(steps, ...)`` slices the snapshots by ``ceil(m / steps)``
    columns; streamsvd absorbs the same slices.
    """
    m = int(np.sum(lengths))
    steps = len(lengths) if block == "traj" else math.ceil(m / int(block))
    size = math.ceil(m / steps)
    widths = np.diff(np.append(np.arange(0, m, size), m))
    return widths, len(widths)


def target_rows(case: str, cache: Path, repeat: int, quick: bool, *,
                blocks: tuple[str, ...] = ("traj",),
                dtypes: tuple[str, ...] = ("float64",),
                products: bool = False) -> list[dict[str, Any]]:
    """Every measure and target of ``case``: streamsvd and HAPOD interleaved.

    For each block width (``"traj"``: one trajectory per update) and each dtype of the
    snapshots (``float32``: rounded once, both contenders read the same array); the
    errors are measured against the snapshots in that dtype. ``products``: each row also
    counts both contenders' products in one more run each (``_products``).
    """
    from pymor.core.logger import set_log_levels
    from pymor.operators.numpy import NumpyMatrixOperator
    from pymor.vectorarrays.numpy import NumpyVectorSpace

    set_log_levels({"pymor": "WARN"})
    X64, M, lengths = _load_case(case, cache, quick)
    n, m = X64.shape
    prod = NumpyMatrixOperator(M)
    rows = []
    for dtype in dtypes:
        X = np.asfortranarray(X64.astype(dtype))
        U = NumpyVectorSpace(n).from_numpy(X)
        Xe = X.astype(np.float64)
        norm = math.sqrt(float(np.sum(_projection_error2(Xe, np.zeros((n, 0)), M))))
        _streamsvd_target(X[:, :20], M, np.array([10, 10]), 1e-3, "mean_l2")  # warm-up
        _hapod_target(U[:20], prod, 2, 1e-3)
        for block in blocks:
            widths, steps = _chunks(lengths, block)
            rows += _block_rows(case, dtype, block, X, U, Xe, M, prod, widths, steps, norm,
                                repeat, products)
    return rows


def _block_rows(case: str, dtype: str, block: str, X: np.ndarray, U: Any, Xe: np.ndarray,
                M: Any, prod: Any, widths: np.ndarray, steps: int, norm: float,
                repeat: int, products: bool) -> list[dict[str, Any]]:
    """The rows of one case, dtype and block width (every measure and target)."""
    n, m = X.shape
    rows = []
    for measure in MEASURES:
        scale = math.sqrt(m) if measure == "mean_l2" else norm
        for target in TARGETS:
            eps = target if measure == "mean_l2" else target * norm / math.sqrt(m)
            ts, th = [], []
            for _ in range(repeat):
                t, Q, bound = _streamsvd_target(X, M, widths, target, measure)
                ts.append(t)
                t, H = _hapod_target(U, prod, steps, eps)
                th.append(t)
            err_s = math.sqrt(float(np.sum(_projection_error2(Xe, Q, M)))) / scale
            err_h = math.sqrt(float(np.sum(_projection_error2(Xe, H, M)))) / scale
            row = {"case": case, "dtype": dtype, "block": block,
                   "width": int(widths[0]), "measure": measure, "target": target,
                   "streamsvd_cpu": statistics.median(ts), "hapod_cpu": statistics.median(th),
                   "streamsvd_modes": int(Q.shape[1]), "hapod_modes": int(H.shape[1]),
                   "streamsvd_error": err_s / target, "hapod_error": err_h / target,
                   "bound": bound / scale / target, "load": os.getloadavg()[0],
                   "streamsvd_runs": ts, "hapod_runs": th}
            row["ratio"] = row["streamsvd_cpu"] / row["hapod_cpu"]
            if products:
                row["streamsvd_products"] = _products.streamsvd_products(
                    partial(_streamsvd_target, X, M, widths, target, measure), len(widths))
                row["hapod_products"] = _products.hapod_products(
                    partial(_hapod_target, U, prod, steps, eps), len(widths))
                row["flop_ratio"] = (row["streamsvd_products"]["total"]
                                     / row["hapod_products"]["total"])
            rows.append(row)
            print(f"{case} {dtype} block {block} {measure} {target:g}: ratio "
                  f"{row['ratio']:.2f}, modes {row['streamsvd_modes']}/{row['hapod_modes']}, "
                  f"bound/target {row['bound']:.3f}", file=sys.stderr, flush=True)
    return rows


def cap_rows(cache: Path, repeat: int, quick: bool) -> list[dict[str, Any]]:
    """The rank cap: streamsvd (default and 20 extra terms) and HAPOD (0 and 10 extra)."""
    from hapod_benchmark import _pymor_capped_hapod, _pymor_space

    import streamsvd as ss

    names = generate("synthetic", cache, quick)
    X = np.asfortranarray(np.load(names["X"]))
    s = np.load(names["s"])
    n, m = X.shape
    cap, block = (10, 20) if quick else (60, 100)
    cols = [slice(j, min(j + block, m)) for j in range(0, m, block)]

    def streamsvd_run(extra: int | None) -> tuple[float, np.ndarray]:
        kw = {} if extra is None else {"oversampling": extra}
        c0 = time.process_time()
        sc = ss.StreamCompressor(n, max_rank=cap, rule="jacobi", sweeps=None,
                                 right_vectors=False, **kw)
        for c in cols:
            sc.absorb(X[:, c])
        sc.finalize()
        return time.process_time() - c0, sc.left_vectors

    U, _ = _pymor_space(X, None)

    def hapod_run(extra: int) -> tuple[float, np.ndarray]:
        blocks = [U[c] for c in cols]
        c0 = time.process_time()
        modes = _pymor_capped_hapod(blocks, cap + extra)[:cap]
        return time.process_time() - c0, modes.to_numpy()

    contenders = {"streamsvd (default)": lambda: streamsvd_run(None),
                  "streamsvd oversampling=20": lambda: streamsvd_run(20),
                  "HAPOD pod(modes=k)": lambda: hapod_run(0),
                  "HAPOD pod(modes=k+10)": lambda: hapod_run(10)}
    times: dict[str, list[float]] = {k: [] for k in contenders}
    last: dict[str, np.ndarray] = {}
    streamsvd_run(None)  # warm-up (numba's cache)
    for _ in range(repeat):
        for name, fn in contenders.items():
            t, Q = fn()
            times[name].append(t)
            last[name] = Q
    rows = []
    for name, Q in last.items():
        C = Q.T @ X
        amps = np.linalg.svd(C, compute_uv=False)[:cap]
        err = float(np.linalg.norm(X - Q @ C))
        rows.append({"contender": name, "cpu": statistics.median(times[name]),
                     "sv_err": float(np.max(np.abs(amps - s[:cap]) / s[:cap])),
                     "err_opt": err / float(np.linalg.norm(s[cap:])), "runs": times[name],
                     "load": os.getloadavg()[0]})
    return rows


def rbs480a_rows(repeat: int, quick: bool) -> list[dict[str, Any]]:
    """The full SVD of rbs480a: plain and preconditioned sweeps against gesdd."""
    import scipy.linalg

    import streamsvd as ss
    from streamsvd.testing.contract import svd_ratios

    A = load_rbs480a(None)
    if quick:
        A = A[:60, :60]
    e = ss.Expansion.canonical(A)
    runs: dict[str, Any] = {
        "gesdd": lambda: scipy.linalg.svd(A, lapack_driver="gesdd"),
        "compress (jacobi)": lambda: ss.compress(e, rule="jacobi", max_sweeps=60),
        "compress (jacobi, precondition)": lambda: ss.compress(
            e, rule="jacobi", max_sweeps=60, precondition=True),
    }
    for fn in runs.values():
        fn()  # warm-up
    times: dict[str, list[float]] = {k: [] for k in runs}
    out: dict[str, Any] = {}
    for _ in range(repeat):
        for name, fn in runs.items():
            c0 = time.process_time()
            out[name] = fn()
            times[name].append(time.process_time() - c0)
    base = statistics.median(times["gesdd"])
    rows = []
    for name in runs:
        row: dict[str, Any] = {"method": name, "cpu": statistics.median(times[name]),
                               "runs": times[name], "load": os.getloadavg()[0]}
        row["over_gesdd"] = row["cpu"] / base
        if name != "gesdd":
            r = out[name]
            ratios = svd_ratios(A, r.expansion)
            row.update(sweeps=r.sweeps, residual=float(ratios.residual),
                       orthogonality_u=float(ratios.orthogonality_u),
                       orthogonality_v=float(ratios.orthogonality_v),
                       singular_values=float(ratios.singular_values))
        rows.append(row)
    return rows


# ------------------------------------------------------------------------ driver
def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every case of ``args``, with the library's warnings silenced only while it runs."""
    with library_warnings_silenced():
        return _measure(args)


def _measure(args: argparse.Namespace) -> dict[str, Any]:
    cases = args.cases.split(",")
    cache = Path(args.cache)
    data: dict[str, Any] = {"targets": [], "cap": [], "rbs480a": [], "ingest": []}
    for case in cases:
        if case in ("heat", "burgers"):
            data["targets"] += target_rows(case, cache, args.repeat, args.quick,
                                           blocks=tuple(args.blocks.split(",")),
                                           dtypes=tuple(args.dtypes.split(",")),
                                           products=args.products)
        elif case == "cap":
            data["cap"] = cap_rows(cache, args.repeat, args.quick)
        elif case == "rbs480a":
            data["rbs480a"] = rbs480a_rows(args.repeat, args.quick)
    if args.ingest or "ingest" in cases:
        paths = ({"given": Path(args.ingest)} if args.ingest
                 else _ingest.arrays(Path(args.ingest_data), args.quick))
        against = None
        if args.against:
            against = (args.against, _worktree(args.against, Path(args.ingest_data)))
        data["ingest"] = _ingest.rows(paths, args.repeat, REPO_ROOT, Path(__file__),
                                      against=against)
    return data


def _worktree(rev: str, where: Path) -> Path:
    """A git worktree of ``rev`` under ``where`` (made once, kept for the next run)."""
    tree = where / f"tree-{rev}"
    if not tree.exists():
        subprocess.run(["git", "-C", str(REPO_ROOT), "worktree", "add", "--detach", "-q",
                        str(tree), rev], check=True)
    return tree


def _against(rev: str, args: argparse.Namespace) -> dict[str, Any]:
    """The rows of revision ``rev``, measured in a child process over a git worktree."""
    cases = ",".join(c for c in args.cases.split(",") if c in ("heat", "burgers"))
    return dict(rows_of_revision(rev, __file__, [
        "--cases", cases, "--cache", args.cache, "--repeat", str(args.repeat),
        "--blocks", args.blocks, "--dtypes", args.dtypes,
        *(["--quick"] if args.quick else [])]))


def _key(row: dict[str, Any]) -> tuple[Any, ...]:
    """A target row's case, dtype, block, measure and target (rows without: float64, traj)."""
    return (row["case"], row.get("dtype", "float64"), row.get("block", "traj"),
            row["measure"], row["target"])


def _print(data: dict[str, Any], before: dict[str, Any] | None) -> None:
    old = {_key(r): r for r in (before or {}).get("targets", [])}
    rows = []
    for r in data["targets"]:
        o = old.get(_key(r))
        rows.append([r["case"], r.get("dtype", "float64"), r.get("width", ""), r["measure"],
                     f"{r['target']:g}", f"{r['streamsvd_cpu']:.3f}",
                     f"{r['hapod_cpu']:.3f}", f"{r['ratio']:.2f}",
                     "" if o is None else f"{o['ratio']:.2f}",
                     f"{r['streamsvd_modes']}/{r['hapod_modes']}",
                     f"{r['streamsvd_error']:.3f}/{r['hapod_error']:.3f}", f"{r['bound']:.3f}",
                     f"{r['load']:.1f}", *_products_cells(r)])
    if rows:
        counted = any("flop_ratio" in r for r in data["targets"])
        print_table(["case", "dtype", "block", "measure", "target", "streamsvd CPU s",
                     "HAPOD CPU s", "ratio",
                     "ratio before", "modes s/H", "true err/target s/H", "bound/target",
                     "load", *(["Mflop/update s/H", "flop ratio", "M columns/update s/H"]
                               if counted else [])],
                    rows, title="\ntargets: streamsvd against inc_vectorarray_hapod")
    if data["cap"]:
        print_table(["contender", "CPU s", "sv_err", "err/opt", "load"],
                    [[r["contender"], f"{r['cpu']:.2f}", f"{r['sv_err']:.1e}",
                      f"{r['err_opt']:.7f}", f"{r['load']:.1f}"] for r in data["cap"]],
                    title="\nrank cap 60, blocks of 100")
    if data["rbs480a"]:
        print_table(["method", "CPU s", "x gesdd", "sweeps", "LAPACK ratios (res/U/V/s)", "load"],
                    [[r["method"], f"{r['cpu']:.3f}", f"{r['over_gesdd']:.2f}",
                      r.get("sweeps", ""),
                      "" if "residual" not in r else
                      f"{r['residual']:.2f}/{r['orthogonality_u']:.2f}/"
                      f"{r['orthogonality_v']:.2f}/{r['singular_values']:.2f}",
                      f"{r['load']:.1f}"] for r in data["rbs480a"]],
                    title="\nrbs480a: the full SVD")
    if data["ingest"]:
        print_table(["store", "contender", "wall s", "CPU s", "wall / memory", "CPU / memory",
                     "load (min-max)"],
                    [[r.get("store", ""), r["contender"], f"{r['wall']:.2f}", f"{r['cpu']:.2f}",
                      *(("", "") if r["wall_over_memory"] is None else
                        (f"{r['wall_over_memory']:.2f}", f"{r['cpu_over_memory']:.2f}")),
                      f"{r['load']:.1f} ({r.get('load_min', r['load']):.1f}-"
                      f"{r.get('load_max', r['load']):.1f})"] for r in data["ingest"]],
                    title="\ningest 200000 x 500 (--max-rank 60 --block 100)")


def _figure(data: dict[str, Any], before: dict[str, Any] | None, path: Path) -> None:
    plt = pyplot()
    dtypes = sorted({r.get("dtype", "float64") for r in data["targets"]}, reverse=True) or [""]
    counted = any("flop_ratio" in r for r in data["targets"])  # --products: a second row
    panels = len(dtypes) + (1 if data["rbs480a"] else 0)
    fig, grid = plt.subplots(2 if counted else 1, panels, figsize=(5.5 * panels,
                             4.2 * (2 if counted else 1)), squeeze=False)
    axes = grid[0]
    old = {_key(r): r for r in (before or {}).get("targets", [])}
    for col, dtype in enumerate(dtypes):
        rows = [r for r in data["targets"] if r.get("dtype", "float64") == dtype]
        _ratio_panel(axes[col], rows, "ratio", old, "CPU time streamsvd / HAPOD",
                     f"{dtype} snapshots" + (" (dotted: before)" if old else ""))
        if counted:
            _ratio_panel(grid[1][col], rows, "flop_ratio", {},
                         "flops streamsvd / HAPOD (counted)",
                         f"{dtype} snapshots: the products of an update")
    if counted and data["rbs480a"]:
        grid[1][-1].axis("off")
    if data["rbs480a"]:
        ax = axes[-1]
        names = [r["method"] for r in data["rbs480a"]]
        ax.bar(range(len(names)), [r["cpu"] for r in data["rbs480a"]])
        ax.set_xticks(range(len(names)), [n.replace(" (", "\n(") for n in names], fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("CPU time (s)")
        ax.set_title("rbs480a: full SVD")
    loads = [r["load"] for key in ("targets", "cap", "rbs480a") for r in data[key]]
    if loads:
        fig.suptitle(f"1 BLAS thread, CPU time; load {min(loads):.1f}-{max(loads):.1f}",
                     fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _ratio_panel(ax: Any, rows: list[dict[str, Any]], key: str, old: dict[Any, Any],
                 ylabel: str, title: str) -> None:
    """Plot ``row[key]`` against the target, a line per case, measure and block width."""
    styles = ("-", "--", "-.", (0, (3, 1, 1, 1)))
    blocks = list(dict.fromkeys(r.get("block", "traj") for r in rows))
    for case in sorted({r["case"] for r in rows}):
        for measure, mk in zip(MEASURES, ("o", "s"), strict=True):
            for block, ls in zip(blocks, styles, strict=False):
                sel = [r for r in rows if r["case"] == case and r["measure"] == measure
                       and r.get("block", "traj") == block]
                if not sel:
                    continue
                label = f"{case} {measure}, blocks of {sel[0].get('width', block)}"
                line, = ax.plot([r["target"] for r in sel], [r[key] for r in sel],
                                marker=mk, ls=ls, label=label)
                prev = [old[_key(r)] for r in sel if _key(r) in old]
                if prev:
                    ax.plot([r["target"] for r in prev], [r[key] for r in prev],
                            marker=mk, ls=":", color=line.get_color(), alpha=0.5)
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("target error (mean_l2 or relative)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=6)
    ax.grid(True, which="both", alpha=0.3)


def _products_cells(row: dict[str, Any]) -> list[str]:
    """The counted products of a row (``--products``), or no cells."""
    if "flop_ratio" not in row:
        return []
    s, h = row["streamsvd_products"], row["hapod_products"]
    return [f"{s['total']:.1f}/{h['total']:.1f}", f"{row['flop_ratio']:.2f}",
            f"{s['m_columns']:.0f}/{h['m_columns']:.0f}"]


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("tight_targets", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="heat,burgers,cap,rbs480a")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--blocks", default="traj",
                    help="update widths of heat and burgers: traj (a trajectory) or columns,"
                         " comma-separated (e.g. traj,10,1000)")
    ap.add_argument("--dtypes", default="float64", help="float64, float32 or both")
    ap.add_argument("--cache", default=str(DEFAULT_CACHE), help="snapshot cache directory")
    ap.add_argument("--ingest", default=None, help="a 200000 x 500 zarr array")
    ap.add_argument("--ingest-data", default=str(Path(tempfile.gettempdir()) / "streamsvd-ooc"),
                    help="where --cases ingest writes its arrays (kept)")
    ap.add_argument("--against", default=None, help="git revision to compare with")
    ap.add_argument("--products", action="store_true",
                    help="also count each contender's products per update (one more run)")
    ap.add_argument("--out", default=None, help="directory for the PNG and JSON")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--rows-only", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        _ingest.child(*args.child)
        return {}
    data = measure(args)
    if args.rows_only:
        Path(args.rows_only).write_text(json.dumps(data))
        return data
    targets = any(c in ("heat", "burgers") for c in args.cases.split(","))
    before = _against(args.against, args) if args.against and targets else None
    _print(data, before)
    out = out_dir(args.out)
    name = "tight_targets" + ("_quick" if args.quick else "")
    payload = {"machine": machine_info(), "load": os.getloadavg(), "against": args.against,
               **data, "before": before}
    if data["targets"] or data["cap"] or data["rbs480a"]:
        record.write(out / f"{name}.json", payload)
        _figure(data, before, out / f"{name}.png")
        print(f"wrote {out / name}.json and .png")
    if data["ingest"]:  # a file of its own: `--cases ingest` alone keeps the others
        record.write(out / f"{name}_ingest.json", {"machine": machine_info(),
                                                   "ingest": data["ingest"]})
        _ingest.figure(data["ingest"], out / f"{name}_ingest.png")
        print(f"wrote {out / name}_ingest.json and .png")
    return payload


if __name__ == "__main__":
    main()
