"""The SVD by default: what ``streamsvd ingest`` stores, against LAPACK, in every mode.

    python bench/final_benchmark.py                     # n = 5000, m = 400, k = 20
    python bench/final_benchmark.py --n 1000 --m 200 --oversampling 0,10 --quick

Setup
-----
Snapshot matrices ``A = Q1 diag(s) Q2^T`` (``n x m``, ``Q1``, ``Q2`` Haar-orthonormal) with
three spectra:

* ``gap``: 20 singular values log-spaced from 1 to 0.1, the others log-spaced from 1e-3
  to 1e-6 (a rank-20 signal in noise, the case of a POD basis that has converged);
* ``log3``: log-spaced from 1 to 1e-3 over all ``m`` (slow decay: sigma_30/sigma_20 = 0.96);
* ``log8``: log-spaced from 1 to 1e-8.

Each is saved as ``.npy`` and ingested by the command line, ``streamsvd.cli.main``,
with its defaults (rule ``paper``, one sweep per update, ``--final-sweeps converge``)
and ``--max-rank k``, at ``--block`` 100 (the default) and 20, in the three modes: in
memory, ``--tall`` (zarr panels, threaded dask scheduler) and the tree (``--scheduler
threads``, leaves of 10 blocks),
for each ``--oversampling`` in the list (10 is the default). One run per spectrum and mode
adds ``--final-sweeps none`` (oversampling 10), and one has no ``--max-rank`` at all.

Measures
--------
From ``streamsvd export`` of the store: ``err/opt = ||A - U V^T||_F / ||A - A_k||_F``
(``A_k`` the LAPACK rank-k truncation; 1 is optimal); ``sv_err``: the largest
``|sigma_i - sigma_i(LAPACK)| / sigma_1`` over the kept terms; ``kept_err``: the largest
``|sigma_i - sigma_i(U V^T)|`` over the kept terms, in units of ``eps * sigma_1``
(``sigma_i(U V^T)`` the LAPACK singular values of the stored expansion: the amplitudes
are those of the expansion kept, to this accuracy); ``angle``: the largest principal
angle between the stored ``U[:, :k]`` and LAPACK's top-k left singular subspace, in
degrees; the wall time of the command.

Writes ``final_benchmark.json`` and ``final_benchmark.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

from _common import Run, machine_info, out_dir, print_table, pyplot  # noqa: E402

from streamsvd.cli import main as cli  # noqa: E402

_EPS = np.finfo(np.float64).eps
_MODES = {"memory": [], "tall": ["--tall"], "tree": ["--scheduler", "threads"]}


def spectrum(name: str, m: int) -> np.ndarray:
    """Return the singular values of the test matrix ``name`` (see the module docstring)."""
    if name == "gap":
        return np.r_[np.logspace(0, -1, 20), np.logspace(-3, -6, m - 20)]
    if name == "log3":
        return np.logspace(0, -3, m)
    if name == "log8":
        return np.logspace(0, -8, m)
    raise ValueError(f"unknown spectrum {name!r}")


def matrix(s: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Return ``Q1 diag(s) Q2^T`` with Haar-orthonormal factors."""
    m = s.size
    Q1 = np.linalg.qr(rng.standard_normal((n, m)))[0]
    Q2 = np.linalg.qr(rng.standard_normal((m, m)))[0]
    return (Q1 * s) @ Q2.T


def run(source: Path, store: Path, options: list[str]) -> tuple[dict[str, np.ndarray], float]:
    """Ingest ``source`` into ``store`` with the CLI; return the exported factors, seconds."""
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        cli(["ingest", str(source), str(store), "--quiet", *options])
    seconds = time.perf_counter() - t0
    out = store.with_suffix(".npz")
    with contextlib.redirect_stdout(io.StringIO()):
        cli(["export", str(store), str(out)])
    with np.load(out) as f:
        return {k: f[k] for k in ("U", "V", "amplitudes")}, seconds


def measure(A: np.ndarray, ref: tuple[np.ndarray, np.ndarray], k: int,
            e: dict[str, np.ndarray]) -> dict[str, float]:
    """Return the figures of one stored expansion (see the module docstring)."""
    U_ref, s_ref = ref
    U, V, amps = e["U"], e["V"], e["amplitudes"]
    r = amps.size
    kk = min(k, r)
    opt = float(np.sqrt(np.sum(s_ref[k:] ** 2)))
    err = float(np.linalg.norm(A - U @ V.T))
    s_kept = np.linalg.svd(U @ V.T, compute_uv=False)[:r]
    cos = np.linalg.svd(U_ref[:, :kk].T @ U[:, :kk], compute_uv=False)
    return {
        "rank": r, "err_over_opt": err / opt if opt > 0 else float("nan"),
        "sv_err": float(np.max(np.abs(amps[:kk] - s_ref[:kk])) / s_ref[0]),
        "kept_err_eps": float(np.max(np.abs(amps - s_kept)) / (_EPS * s_ref[0])),
        "angle_deg": float(np.degrees(np.arccos(np.clip(cos.min(), -1.0, 1.0)))),
    }


def main(argv: Sequence[str] | None = None) -> int:
    record = Run("final_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5000)
    ap.add_argument("--m", type=int, default=400)
    ap.add_argument("--k", type=int, default=20, help="--max-rank")
    ap.add_argument("--oversampling", default="0,10,20,40")
    ap.add_argument("--spectra", default="gap,log3,log8")
    ap.add_argument("--modes", default="memory,tall,tree")
    ap.add_argument("--blocks", default="100,20",
                    help="--block values (100 is the command line's default)")
    ap.add_argument("--quick", action="store_true", help="skip the extra runs")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = out_dir(args.out)
    rng = np.random.default_rng(20261201)
    overs = [int(x) for x in args.oversampling.split(",")]
    rows: list[dict[str, Any]] = []
    spectra, modes = args.spectra.split(","), args.modes.split(",")
    blocks = [int(b) for b in args.blocks.split(",")]
    total = len(spectra) * len(modes) * len(blocks) * (len(overs) + (0 if args.quick else 2))
    with tempfile.TemporaryDirectory(prefix="streamsvd-final-") as tmp, \
            tqdm(total=total, unit="run", file=sys.stderr) as bar:
        for name in spectra:
            A = matrix(spectrum(name, args.m), args.n, rng)
            source = Path(tmp) / f"{name}.npy"
            np.save(source, A)
            U_ref, s_ref, _ = np.linalg.svd(A, full_matrices=False)
            cases: list[tuple[str, list[str]]] = [
                (f"os {o}", ["--max-rank", str(args.k), "--oversampling", str(o)])
                for o in overs
            ]
            if not args.quick:
                cases += [("os 10, final none",
                           ["--max-rank", str(args.k), "--final-sweeps", "none"]),
                          ("no max-rank", [])]
            for block in blocks:
                for mode in modes:
                    for label, options in cases:
                        store = Path(tmp) / f"{name}-{mode}-{len(rows)}.zarr"
                        e, seconds = run(source, store,
                                         ["--block", str(block), *_MODES[mode], *options])
                        row = {"spectrum": name, "block": block, "mode": mode, "case": label,
                               "oversampling": _oversampling(options), "seconds": seconds,
                               **measure(A, (U_ref, s_ref), args.k, e)}
                        rows.append(row)
                        bar.update()
    print_table([c for c, _ in _COLUMNS],
                [[f.format(r[c]) for c, f in _COLUMNS] for r in rows],
                title=f"n = {args.n}, m = {args.m}, k = {args.k} (CLI defaults)")
    record.write(out / "final_benchmark.json", {
        "n": args.n, "m": args.m, "k": args.k, "blocks": blocks, "rows": rows,
        "machine": machine_info(),
    })
    _figure(rows, args.k, out / "final_benchmark.png")
    return 0


_COLUMNS = (
    ("spectrum", "{}"), ("block", "{}"), ("mode", "{}"), ("case", "{}"), ("rank", "{}"),
    ("err_over_opt", "{:.6f}"), ("sv_err", "{:.1e}"), ("kept_err_eps", "{:.1f}"),
    ("angle_deg", "{:.2e}"), ("seconds", "{:.2f}"),
)


def _oversampling(options: list[str]) -> int | None:
    if "--max-rank" not in options:
        return None
    return int(options[options.index("--oversampling") + 1]) if "--oversampling" in options \
        else 10


def _figure(rows: list[dict[str, Any]], k: int, path: Path) -> None:
    plt = pyplot()
    spectra = sorted({r["spectrum"] for r in rows}, key=[r["spectrum"] for r in rows].index)
    fig, axes = plt.subplots(1, len(spectra), figsize=(5 * len(spectra), 4), squeeze=False)
    for ax, name in zip(axes[0], spectra, strict=True):
        blocks = sorted({r["block"] for r in rows}, reverse=True)
        for block, fill in zip(blocks, ("full", "none"), strict=False):
            for mode, style in (("memory", "ko-"), ("tall", "bs--"), ("tree", "r^-")):
                pts = [(r["oversampling"], r["err_over_opt"] - 1) for r in rows
                       if r["spectrum"] == name and r["mode"] == mode and r["block"] == block
                       and r["case"].startswith("os") and "final" not in r["case"]]
                if pts:
                    x, y = zip(*pts, strict=True)
                    ax.semilogy(x, np.maximum(y, 1e-16), style, fillstyle=fill,
                                label=f"{mode}, block {block}")
        ax.axhline(1e-4, color="0.5", ls=":", label="target 1.0001")
        ax.set(xlabel="--oversampling (terms kept above k while streaming)",
               ylabel="||A - U V^T||_F / ||A - A_k||_F - 1",
               title=f"spectrum {name}, k = {k}")
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
