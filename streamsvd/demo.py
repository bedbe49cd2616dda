"""The main job: compress rbs480a (or a generated matrix) and report spectrum and error.

Run with ``python -m streamsvd.demo [--data PATH] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import scipy.io
import scipy.linalg

from . import Expansion, compress
from .testing import with_spectrum

logger = logging.getLogger(__name__)

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rbs480a.mtx"


def _load(path: Path) -> tuple[str, np.ndarray]:
    if path.exists():
        return path.name, scipy.io.mmread(path).toarray()
    logger.warning(
        "%s not found (RBS480A is published by the Matrix Market, Harwell-Boeing collection); "
        "using a generated 480 x 480 matrix with a geometric spectrum",
        path,
    )
    return "generated", with_spectrum(np.logspace(0, -12, 480), 480, 480, np.random.default_rng(0))


def main(argv: list[str] | None = None) -> int:
    """Run the demonstration; return the process exit code."""
    ap = argparse.ArgumentParser(prog="python -m streamsvd.demo", description=__doc__)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="Matrix Market file")
    ap.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    ap.add_argument("--rule", choices=("paper", "jacobi"), default="jacobi")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    name, A = _load(args.data)
    t0 = time.perf_counter()
    res = compress(Expansion.canonical(A), rule=args.rule, max_sweeps=200)
    elapsed = time.perf_counter() - t0
    s_ref = scipy.linalg.svdvals(A)
    amps = res.expansion.amplitudes
    k = min(len(amps), len(s_ref))
    rel_sv = float(np.max(np.abs(amps[:k] - s_ref[:k])) / s_ref[0])
    rel_res = float(np.linalg.norm(A - res.expansion.to_dense()) / np.linalg.norm(A))
    summary = {
        "matrix": name, "shape": list(A.shape), "rule": args.rule, "sweeps": res.sweeps,
        "converged": res.converged, "seconds": elapsed, "max_rel_singular_value_error": rel_sv,
        "relative_residual": rel_res, "orthogonality": res.expansion.orthogonality_error(),
        "sigma": amps[:10].tolist(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].semilogy(s_ref, "k-", label="LAPACK")
    ax[0].semilogy(amps, "r.", ms=3, label="streamsvd")
    ax[0].set(xlabel="mode", ylabel="singular value", title=name)
    ax[0].legend()
    ax[1].semilogy(np.arange(1, res.sweeps + 1), res.indicator, "b-")
    ax[1].set(xlabel="sweep", ylabel="indicator I", title=f"rule = {args.rule}")
    fig.tight_layout()
    fig.savefig(args.out / "spectrum.png", dpi=120)
    logger.info(json.dumps(summary, indent=2))
    logger.info("wrote %s and %s", args.out / "summary.json", args.out / "spectrum.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
