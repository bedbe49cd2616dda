"""Command line: ``streamsvd ingest | info | export | plot``.

A user mistake (missing file, locked or foreign store, bad option) prints one line
``streamsvd: error: ...`` and exits with status 2; nothing else prints a traceback
unless ``--debug`` is given.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .errors import StoreError, StreamSVDError
from .sources import open_source
from .stream import StreamCompressor

__all__ = ["main"]

logger = logging.getLogger(__name__)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="streamsvd", description="Streaming low-rank bases by rotation sweeps."
    )
    ap.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = ap.add_subparsers(dest="command", required=True)

    ing = sub.add_parser("ingest", help="absorb the columns of SOURCE into STORE")
    ing.add_argument("source", help=".npy, .h5/.hdf5 or zarr path (columns are snapshots)")
    ing.add_argument("store", help="basis store directory (zarr v3)")
    ing.add_argument("--dataset", help="dataset name inside an HDF5 file or zarr group")
    ing.add_argument("--block", type=int, default=100, help="snapshots per update")
    tol = ing.add_mutually_exclusive_group()
    tol.add_argument("--eps", type=float, default=0.0, help="absolute cut on ||v_i||")
    tol.add_argument("--rtol", type=float, help="relative cut ||v_i|| < rtol ||v_1||")
    ing.add_argument("--max-rank", type=int, help="keep at most K terms")
    ing.add_argument("--rule", choices=("paper", "jacobi"), default="paper")
    ing.add_argument("--sweeps", type=int, default=1, help="sweeps per update (0: converge)")
    ing.add_argument("--commit-every", type=int, default=1, help="updates per commit")
    ing.add_argument("--resume", action="store_true", help="continue an existing store")
    ing.add_argument("--quiet", action="store_true", help="no progress bar")
    ing.add_argument(
        "--scheduler",
        help="run on dask: 'threads', 'local' (a LocalCluster) or a scheduler address; "
        "columns are compressed in leaves merged in a tree",
    )
    ing.add_argument("--workers", type=int, help="worker processes of --scheduler local")
    ing.add_argument("--tall", action="store_true",
                     help="keep U out of core in zarr panels (snapshots too long for memory)")
    ing.add_argument("--leaf-columns", type=int, help="columns per leaf of the tree")
    ing.add_argument("--chunk-rows", type=int, help="rows per chunk of the tall panels")

    info = sub.add_parser("info", help="summarise a store")
    info.add_argument("store")
    info.add_argument("--json", action="store_true", help="print JSON")

    exp = sub.add_parser("export", help="write U, V and the amplitudes to .npz or .h5")
    exp.add_argument("store")
    exp.add_argument("out", help="output file, .npz or .h5")

    plot = sub.add_parser("plot", help="amplitudes, energy and orthogonality as PNG")
    plot.add_argument("store")
    plot.add_argument("out", help="output .png")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``streamsvd`` command; returns the exit status."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="streamsvd: %(message)s")
    if not args.debug:
        # dask.distributed sets its loggers to INFO from its config when first imported
        # (here, lazily); the config can be given by environment, which workers inherit
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    try:
        return int(_COMMANDS[args.command](args))
    except (StreamSVDError, OSError, ValueError) as err:
        if args.debug:
            raise
        print(f"streamsvd: error: {err}", file=sys.stderr)
        return 2


def _ingest(args: Any) -> int:
    if args.scheduler is not None or args.tall:
        return _ingest_dask(args)
    from tqdm import tqdm

    store = Path(args.store)
    with open_source(args.source, dataset=args.dataset) as src:
        if args.resume:
            sc = StreamCompressor.open(store)
        elif store.exists():
            raise StoreError(
                f"`store` {store} already exists; pass --resume to continue it or choose "
                "another path."
            )
        else:
            sc = StreamCompressor(
                src.n, eps=args.eps, rtol=args.rtol, max_rank=args.max_rank, rule=args.rule,
                sweeps=None if args.sweeps == 0 else args.sweeps, store=store,
                commit_every=args.commit_every,
            )
        with sc:
            if src.n != sc.n:
                raise StoreError(
                    f"`source` has snapshots of size {src.n}; the store holds a basis of "
                    f"size {sc.n}."
                )
            start = sc.source_offset
            bar = tqdm(
                total=src.m, initial=start, unit="col", disable=args.quiet,
                dynamic_ncols=True, desc="ingest",
            )
            with bar:
                for offset, block in src.blocks(block=args.block, start=start):
                    rec = sc.absorb(block, source_offset=offset + block.shape[1])
                    bar.update(block.shape[1])
                    bar.set_postfix(rank=rec.rank, bound=f"{rec.error_bound:.2e}", refresh=False)
            summary = _summary(sc)
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


def _ingest_dask(args: Any) -> int:
    from .parallel import ingest

    summary = ingest(
        args.source, args.store, dataset=args.dataset, block=args.block,
        scheduler=args.scheduler, workers=args.workers, tall=args.tall,
        leaf_columns=args.leaf_columns, chunk_rows=args.chunk_rows, resume=args.resume,
        progress=not args.quiet, eps=args.eps, rtol=args.rtol, max_rank=args.max_rank,
        rule=args.rule, sweeps=None if args.sweeps == 0 else args.sweeps,
        # a tree commits its root once; the tall mode commits every `commit_every` updates
        **({"commit_every": args.commit_every} if args.tall else {}),
    )
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


def _open(path: Any) -> Any:
    """Open the compressor of a store read-only, whichever kind wrote it."""
    from .errors import StoreMismatchError

    try:
        return StreamCompressor.open(path, mode="r")
    except StoreMismatchError:
        from .parallel import open_compressor  # a tall store: dask is needed to read it

        return open_compressor(path, mode="r")


def _summary(sc: Any) -> dict[str, Any]:
    amps = sc.amplitudes
    return {
        "store": sc.store_path, "n": sc.n, "n_seen": sc.n_seen, "rank": sc.rank,
        "source_offset": sc.source_offset, "updates": len(sc.history),
        "error_bound": sc.error_bound, "discarded_energy": sc.discarded_energy,
        "orthogonality": sc.orthogonality_error(), "options": sc._options(),
        "amplitudes_head": amps[:10].tolist(),
    }


def _info(args: Any) -> int:
    with _open(args.store) as sc:
        summary = _summary(sc)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    opts = summary["options"]
    print(f"store         {summary['store']}")
    print(f"snapshots     n = {summary['n']}, absorbed {summary['n_seen']} "
          f"(source offset {summary['source_offset']}) in {summary['updates']} updates")
    print(f"rank          {summary['rank']}  (rule {opts['rule']}, sweeps {opts['sweeps']}, "
          f"eps {opts['eps']}, rtol {opts['rtol']}, max_rank {opts['max_rank']})")
    print(f"error bound   ||A - U V^T||_F <= {summary['error_bound']:.3e}")
    print(f"orthogonality ||U^T M U - I||_2 = {summary['orthogonality']:.2e}")
    head = ", ".join(f"{a:.4g}" for a in summary["amplitudes_head"])
    print(f"amplitudes    {head}{', ...' if summary['rank'] > 10 else ''}")
    return 0


def _export(args: Any) -> int:
    out = Path(args.out)
    if out.suffix not in (".npz", ".h5", ".hdf5"):
        raise ValueError(f"`out` must end with .npz, .h5 or .hdf5; got {out.name!r}.")
    with _open(args.store) as sc:
        e = sc.expansion
        bound = sc.error_bound
    data = {"U": e.U, "V": e.V, "amplitudes": e.amplitudes, "error_bound": np.array(bound)}
    if out.suffix == ".npz":
        np.savez(out, U=e.U, V=e.V, amplitudes=e.amplitudes, error_bound=np.array(bound))
    else:
        import h5py

        with h5py.File(out, "w") as h5:
            for k, v in data.items():
                h5.create_dataset(k, data=v)
    print(f"wrote {out} (U {e.U.shape}, V {e.V.shape})")
    return 0


def _plot(args: Any) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with _open(args.store) as sc:
        amps = sc.amplitudes
        hist = sc.history
        bound = sc.error_bound
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    ax[0].semilogy(np.arange(1, amps.size + 1), amps, "k.-", ms=3)
    ax[0].set(xlabel="term i", ylabel="||v_i||", title="amplitudes")
    energy = np.cumsum(amps**2)
    total = energy[-1] + sc.discarded_energy if energy.size else 1.0
    ax[1].plot(np.arange(1, amps.size + 1), energy / total, "b.-", ms=3)
    ax[1].set(xlabel="terms kept", ylabel="fraction of energy", title=f"error bound {bound:.2e}")
    ax[1].set_ylim(0, 1.02)
    orth = [max(h.orthogonality, 1e-18) for h in hist]
    ax[2].semilogy(np.arange(1, len(orth) + 1), orth, "r-")
    ax[2].set(xlabel="update", ylabel="||U^T M U - I||_2", title="orthogonality")
    fig.tight_layout()
    fig.savefig(args.out, dpi=120)
    plt.close(fig)
    print(f"wrote {args.out}")
    return 0


_COMMANDS = {"ingest": _ingest, "info": _info, "export": _export, "plot": _plot}


if __name__ == "__main__":
    sys.exit(main())
