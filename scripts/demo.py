"""The main job: stream rbs480a (or a generated matrix) into a local zarr basis store.

Run with ``bash scripts/demo.sh [--data PATH] [--out DIR] [--quiet]`` (or
``python scripts/demo.py ...`` where streamsvd is installed). The columns
of the matrix are absorbed block by block into ``OUT/basis.zarr`` (one rotation sweep per
block, then sweeps to convergence at the end), and the result is compared with LAPACK:
spectrum, error, error bound and orthogonality go to ``OUT/summary.json`` and
``OUT/spectrum.png``.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import scipy.io
import scipy.linalg

from streamsvd import Expansion, StreamCompressor
from streamsvd.testing.matrices import with_spectrum

logger = logging.getLogger(__name__)

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "rbs480a.mtx"


def _load(path: Path) -> tuple[str, np.ndarray]:
    if path.exists():
        return path.name, scipy.io.mmread(path).toarray()
    logger.warning(
        "%s not found (RBS480A is published by the Matrix Market, Harwell-Boeing "
        "collection); using a generated 480 x 480 matrix with a geometric spectrum",
        path,
    )
    return "generated", with_spectrum(np.logspace(0, -12, 480), 480, 480, np.random.default_rng(0))


def main(argv: list[str] | None = None) -> int:
    """Run the main job; return the process exit code."""
    ap = argparse.ArgumentParser(prog="scripts/demo.sh", description=__doc__)
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="Matrix Market file")
    ap.add_argument("--out", type=Path, default=Path("out/demo"), help="output directory")
    ap.add_argument("--block", type=int, default=40, help="snapshots per update")
    ap.add_argument("--rule", choices=("paper", "jacobi"), default="jacobi")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    from tqdm import tqdm

    name, A = _load(args.data)
    args.out.mkdir(parents=True, exist_ok=True)
    store = args.out / "basis.zarr"
    if store.exists():
        shutil.rmtree(store)
    t0 = time.perf_counter()
    with StreamCompressor(A.shape[0], rule=args.rule, sweeps=1, store=store) as sc:
        for j in tqdm(range(0, A.shape[1], args.block), disable=args.quiet, desc="absorb"):
            sc.absorb(A[:, j : j + args.block])
        t_stream = time.perf_counter() - t0
        streamed = sc.expansion
        history = sc.history
        record = sc.finalize()  # what close() does: converge the core, commit the SVD
        final = sc.expansion
        bound = sc.error_bound
    elapsed = time.perf_counter() - t0
    s_ref = scipy.linalg.svdvals(A)

    def rel_sv(e: Expansion) -> float:
        k = min(e.rank, s_ref.size)
        return float(np.max(np.abs(e.amplitudes[:k] - s_ref[:k])) / s_ref[0])

    summary = {
        "matrix": name, "shape": list(A.shape), "rule": args.rule, "block": args.block,
        "store": str(store), "stream_seconds": t_stream, "total_seconds": elapsed,
        "stream_max_rel_singular_value_error": rel_sv(streamed),
        "final_sweeps": record.sweeps, "final_max_cosine": record.max_cosine,
        "final_max_rel_singular_value_error": rel_sv(final),
        "relative_residual": float(np.linalg.norm(A - final.to_dense()) / np.linalg.norm(A)),
        "error_bound": bound, "orthogonality": final.orthogonality_error(),
        "sigma_head": final.amplitudes[:10].tolist(),
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    ax[0].semilogy(s_ref, "k-", lw=2, label="LAPACK")
    ax[0].semilogy(streamed.amplitudes, "c.", ms=3, label="streamed (1 sweep / block)")
    ax[0].semilogy(final.amplitudes, "r.", ms=2, label="after final sweeps")
    ax[0].set(xlabel="mode", ylabel="singular value", title=name)
    ax[0].legend()
    tiny = np.finfo(np.float64).tiny
    for e, style, label in ((streamed, "c.", "streamed"), (final, "r.", "final")):
        k = min(e.rank, s_ref.size)
        err = np.abs(e.amplitudes[:k] - s_ref[:k]) / s_ref[0]
        ax[1].semilogy(np.arange(1, k + 1), np.maximum(err, tiny), style, ms=3, label=label)
    ax[1].set(xlabel="mode", ylabel="|sigma_i - sigma_i(LAPACK)| / sigma_1",
              title=f"singular values, rule {args.rule}")
    ax[1].legend()
    ax[2].semilogy([max(h.orthogonality, 1e-18) for h in history], "r.-")
    ax[2].set(xlabel="update", ylabel="||U^T U - I||_2", title="orthogonality")
    fig.tight_layout()
    fig.savefig(args.out / "spectrum.png", dpi=120)
    plt.close(fig)
    print(json.dumps(summary, indent=2))
    print(f"wrote {args.out / 'summary.json'}, {args.out / 'spectrum.png'} and {store}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
