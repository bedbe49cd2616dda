"""Command line: ``streamsvd ingest | info | export | plot``.

Output. A command's result (the JSON summary of ``ingest``, the report of ``info``, the
``wrote ...`` line of ``export`` and ``plot``) is the only thing written to stdout;
progress bars and log messages go to stderr, and ``ingest --quiet`` silences the bar and
the summary. ``streamsvd ingest ... > summary.json`` and ``streamsvd info STORE --json``
therefore give pure JSON.

Errors. A user mistake (missing file, locked or foreign store, bad option, an option of
another mode, bad data) prints one line ``streamsvd: error: ...`` in the words of the
command line (its arguments, options and commands, never a Python call) and exits with
status 2; nothing prints a traceback unless ``--debug`` is given.

Start-up. At module level this imports only the standard library and
:mod:`streamsvd.errors`; numpy, zarr, dask, numba and matplotlib are imported by the
command that needs them, so ``streamsvd --help`` answers at once.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import re
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from . import __version__
from .errors import (
    InputError,
    NonFiniteError,
    ShapeMismatchError,
    SourceError,
    StoreError,
    StoreMismatchError,
    StreamSVDError,
)

__all__ = ["CONVERGE", "main"]

if TYPE_CHECKING:  # the storage module imports zarr: only for the annotations
    from .storage import Storage

logger = logging.getLogger(__name__)

#: The ``--sweeps`` value that sweeps every update until no pair rotates.
CONVERGE = "converge"

_DEFAULT_BLOCK = 100
_DEFAULT_RULE = "paper"
_DEFAULT_SWEEPS = 1
_DEFAULT_COMMIT_EVERY = 1
_DEFAULT_OVERSAMPLING = 10
#: The ``--final-sweeps`` values: converge the core at the end, or leave it as streamed.
_FINAL_SWEEPS = (CONVERGE, "none")

# options of the compressor that a store records at creation (``--resume`` reuses them)
_STORE_OPTIONS = (
    ("eps", "--eps"), ("rtol", "--rtol"), ("max_rank", "--max-rank"),
    ("oversampling", "--oversampling"), ("rule", "--rule"), ("sweeps", "--sweeps"),
    ("commit_every", "--commit-every"), ("target_error", "--target-error"),
    ("error_measure", "--error-measure"), ("streaming_share", "--streaming-share"),
)

_INGEST_EPILOG = """\
modes:
  in memory   (default)             the basis in memory, committed to STORE every
                                    --commit-every updates
  tree        --scheduler S         leaves of --leaf-columns columns compressed
                                    independently on dask, merged pairwise; STORE is
                                    written once, at the end
  tall        --tall [--scheduler S]
                                    U kept out of core in zarr panels of --chunk-rows
                                    rows, every product run by dask over row chunks;
                                    committed every --commit-every updates
  --leaf-columns is for the tree mode only, --chunk-rows for the tall mode only and
  --workers for --scheduler local only; an option of another mode is refused.

resume:
  with --resume, STORE is continued from its recorded source offset if it exists and
  created otherwise, so one command line starts an ingestion and restarts it after an
  interruption. STORE records its options and SOURCE (path, --dataset, shape): an option
  or a SOURCE that differs is refused, naming both values; a SOURCE that gained columns
  is the same SOURCE, continued; --source-changed-ok continues STORE from another SOURCE.
  A command that fails before its first commit of snapshots leaves no new STORE behind.

output:
  the progress bar goes to stderr; the JSON summary (as `streamsvd info --json`) goes
  to stdout; --quiet prints neither.
"""

_INNER_HELP = (
    ".npy (1-D positive weights or a 2-D SPD matrix), .npz (a scipy sparse matrix saved "
    "by scipy.sparse.save_npz) or .mtx (Matrix Market)"
)


# -------------------------------------------------------------------------- parsing


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line ``streamsvd: error: ...``."""

    def error(self, message: str) -> NoReturn:
        """Print the usage error on one line and exit with status 2."""
        self.exit(2, f"streamsvd: error: {message} (see `{self.prog} --help`).\n")


def _nonnegative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0; got {text!r}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer; got {text!r}")
    return value


def _nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0; got {text!r}")
    return value


def _threads(text: str) -> int | str:
    if text == "all":
        return text
    return _positive_int(text)


def _sweeps(text: str) -> int | str:
    if text == CONVERGE:
        return CONVERGE
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"must be a positive number of sweeps per update, or '{CONVERGE}' to sweep "
            f"until no pair rotates; got {text!r}"
        )
    return value


def _storage_option(text: str) -> tuple[str, Any]:
    """``KEY=VALUE``: VALUE as JSON when it parses (true, 3, "x"), else as the text."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or any(not part for part in key.strip().split(".")):
        raise argparse.ArgumentTypeError(
            f"must be KEY=VALUE (for example endpoint_url=http://localhost:9000 or "
            f"client_kwargs.region_name=eu-west-1); got {text!r}"
        )
    try:
        parsed: Any = json.loads(value)
    except ValueError:
        parsed = value
    return key.strip(), parsed


def _storage_options(args: Any) -> dict[str, Any] | None:
    """Return the ``--storage-option`` pairs as a dict (a dotted KEY nests), or None."""
    pairs = getattr(args, "storage_option", None)
    if not pairs:
        return None
    out: dict[str, Any] = {}
    for key, value in pairs:
        *parents, last = key.split(".")
        node = out
        for part in parents:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise InputError(
                    f"--storage-option {key} nests below {part}, which was given a value "
                    f"({child!r}); give either {part}=VALUE or {part}.KEY=VALUE."
                )
            node = child
        node[last] = value
    return out


def _add_storage_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--storage-option", metavar="KEY=VALUE", type=_storage_option, action="append",
        help="option of the object store of an s3:// (or other fsspec) URL, for SOURCE and "
        "STORE alike, such as endpoint_url=URL, key=ID, secret=S, anon=true; a dotted KEY "
        "nests (client_kwargs.region_name=R); repeatable (default: none; the AWS_* "
        "environment variables apply)",
    )


def _locate(args: Any) -> None:
    """Turn STORE into a storage and a SOURCE URL into its zarr array (with the options)."""
    from .sources import open_zarr_url
    from .storage import is_url, open_storage

    options = _storage_options(args)
    urls = [getattr(args, name) for name in ("store", "source") if hasattr(args, name)]
    if options and not any(is_url(u) for u in urls):
        raise InputError(
            "--storage-option only applies to URLs (s3://...); SOURCE and STORE are local "
            "paths. Drop --storage-option."
        )
    args.store = open_storage(
        args.store, storage_options=options if is_url(args.store) else None,
        argument="store",
    )
    if is_url(getattr(args, "source", None)):
        args.source_given = (args.source, args.dataset)  # what the store records
        args.source = open_zarr_url(
            args.source, dataset=args.dataset,
            storage_options=options,  # the same options as STORE's
        )
        args.dataset = None


def _scheduler(text: str) -> str:
    if not text.strip():
        raise argparse.ArgumentTypeError(
            "must be 'threads', 'local' or a scheduler address such as tcp://HOST:8786; "
            "got ''"
        )
    return text


def _parser() -> argparse.ArgumentParser:
    ap = _Parser(
        prog="streamsvd",
        description="Streaming low-rank bases by rotation sweeps: absorb the columns of a "
        "snapshot matrix into a basis store, then inspect, export or plot it.",
        epilog="Run `streamsvd COMMAND --help` for the arguments and options of a command.",
    )
    ap.add_argument("--version", action="version", version=f"streamsvd {__version__}")
    ap.add_argument("--debug", action="store_true",
                    help="show Python tracebacks instead of one-line errors (default: off)")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    ing = sub.add_parser(
        "ingest", help="absorb the columns of SOURCE into STORE",
        description="Absorb the columns (snapshots) of SOURCE into the basis store STORE,\n"
        "a block of columns per update: Gram-Schmidt against the basis, rotation sweeps,\n"
        "truncation (--eps, --rtol, --max-rank).",
        epilog=_INGEST_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ing.add_argument("source", metavar="SOURCE",
                     help=".npy, .h5/.hdf5/.he5 file or zarr array/group, or the URL of a "
                     "zarr array/group (s3://BUCKET/run.zarr); columns are snapshots")
    ing.add_argument("store", metavar="STORE",
                     help="basis store (zarr v3): a directory or a URL (file://, "
                     "s3://BUCKET/basis.zarr); created, or continued with --resume")
    ing.add_argument("--dataset", metavar="NAME",
                     help="dataset of an HDF5 file or array of a zarr group (default: the "
                     "only one there)")
    ing.add_argument("--block", metavar="B", type=_positive_int,
                     help=f"snapshots (columns) absorbed per update (default: {_DEFAULT_BLOCK})")
    tol = ing.add_mutually_exclusive_group()
    tol.add_argument("--eps", metavar="E", type=_nonnegative_float,
                     help="absolute cut: drop the terms with ||v_i|| < E, in the units of "
                     "the data (default: 0, no cut)")
    tol.add_argument("--rtol", metavar="R", type=_nonnegative_float,
                     help="relative cut: drop the terms with ||v_i|| < R ||v_1|| (default: "
                     "none; not with --eps)")
    tol.add_argument("--target-error", metavar="T", type=_nonnegative_float,
                     help="keep the fewest terms whose guaranteed error bound is at most T "
                     "in --error-measure (default: none; not with --eps or --rtol)")
    ing.add_argument("--error-measure", choices=("relative", "mean_l2", "absolute"),
                     help="'relative': ||A - U V^T||_F <= T ||A||_F; 'mean_l2': "
                     "sqrt(sum_j ||a_j - P a_j||^2 / m) <= T (pyMOR HAPOD's measure); "
                     "'absolute': ||A - U V^T||_F <= T; norms in --inner (default: relative)")
    ing.add_argument("--streaming-share", metavar="S", type=float,
                     help="share of the --target-error budget spent while streaming, the "
                     "rest by the final cut (default: 0.9)")
    ing.add_argument("--max-rank", metavar="K", type=_positive_int,
                     help="keep K terms in the end: K + --oversampling while streaming, "
                     "cut to K by the final sweeps (default: no limit)")
    ing.add_argument("--oversampling", metavar="P", type=_nonnegative_int,
                     help="extra terms kept while streaming with --max-rank; 0 cuts to K "
                     f"at every update (default: {_DEFAULT_OVERSAMPLING})")
    ing.add_argument("--rule", choices=("paper", "jacobi"),
                     help="rotation of a pair of terms: 'paper' turns by tan(theta) = "
                     "(v_j|v_i)/(v_j|v_j) (eq. 5, linear convergence), 'jacobi' by the angle "
                     "that zeroes the pair's coupling (one-sided Jacobi, quadratic "
                     f"convergence) (default: {_DEFAULT_RULE})")
    ing.add_argument("--sweeps", metavar=f"N|{CONVERGE}", type=_sweeps,
                     help="rotation sweeps per update: a positive integer, or "
                     f"'{CONVERGE}' to sweep until no pair rotates (an incremental SVD) "
                     f"(default: {_DEFAULT_SWEEPS})")
    ing.add_argument("--final-sweeps", choices=_FINAL_SWEEPS,
                     help=f"at the end, '{CONVERGE}': sweep the core until no pair rotates "
                     "(Jacobi rule) and cut by --eps/--rtol/--max-rank, so that STORE holds "
                     "the SVD of what was absorbed; 'none': keep the streamed expansion "
                     f"(default: {CONVERGE})")
    ing.add_argument("--threads", metavar="N", type=_threads,
                     help="BLAS threads of an update, or 'all' for the BLAS's own setting "
                     "(default: 1, never much slower, and much faster on a busy machine)")
    ing.add_argument("--commit-every", metavar="C", type=_positive_int,
                     help="updates per commit to STORE, in memory and with --tall; the "
                     f"tree mode commits once (default: {_DEFAULT_COMMIT_EVERY})")
    ing.add_argument("--inner", metavar="FILE",
                     help="inner product in which U is orthonormal (a mass matrix, "
                     f"quadrature weights): {_INNER_HELP}; STORE keeps it, so --resume, "
                     "info, export and plot need it only for a store written before "
                     "stores kept it (checked against STORE when given) (default: "
                     "Euclidean, or the one STORE keeps)")
    ing.add_argument("--resume", action="store_true",
                     help="continue STORE from its recorded source offset, with the "
                     "options it was created with (an option given again must have the "
                     "same value) and the SOURCE it was built from; create STORE when it "
                     "does not exist yet (default: off, STORE must not exist)")
    ing.add_argument("--source-changed-ok", action="store_true",
                     help="with --resume, continue STORE from a SOURCE other than the one "
                     "it records (another path or --dataset, fewer columns) (default: off, "
                     "refused)")
    ing.add_argument("--quiet", action="store_true",
                     help="no progress bar on stderr and no summary on stdout (default: off)")
    ing.add_argument("--scheduler", metavar="S", type=_scheduler,
                     help="run on dask: 'threads' (this process), 'local' (a LocalCluster "
                     "of --workers processes) or the address of a scheduler "
                     "(tcp://HOST:PORT); without --tall, the tree mode (default: no dask, "
                     "in memory; 'threads' with --tall)")
    ing.add_argument("--workers", metavar="W", type=_positive_int,
                     help="worker processes of --scheduler local (default: the number of "
                     "CPUs)")
    ing.add_argument("--tall", action="store_true",
                     help="tall mode: keep U out of core in zarr panels, for snapshots too "
                     "long for memory; on --scheduler, threads by default (default: off)")
    ing.add_argument("--leaf-columns", metavar="L", type=_positive_int,
                     help="columns per leaf, tree mode only (default: 10 blocks)")
    ing.add_argument("--chunk-rows", metavar="R", type=_positive_int,
                     help="rows per chunk of the panels, tall mode only (default: the "
                     "source's row chunks, else 16384)")
    _add_storage_option(ing)

    def reader(name: str, *, help: str, description: str) -> argparse.ArgumentParser:
        """Add a command that reads STORE (its first argument)."""
        parser = sub.add_parser(name, help=help, description=description)
        parser.add_argument("store", metavar="STORE",
                            help="basis store written by `streamsvd ingest`")
        parser.add_argument("--inner", metavar="FILE",
                            help="the inner product STORE was written with, for a store "
                            f"that does not keep it (written before stores kept it): "
                            f"{_INNER_HELP}; checked against STORE (default: the one STORE "
                            "keeps, else Euclidean)")
        _add_storage_option(parser)
        return parser

    info = reader("info", help="summarise a store",
                  description="Summarise a basis store: sizes, rank, options, error bound, "
                  "orthogonality and the leading amplitudes.")
    info.add_argument("--json", action="store_true",
                      help="print the summary as JSON (default: off, a text report)")

    exp = reader("export", help="write U, V and the amplitudes to .npz or .h5",
                 description="Write U, V, the amplitudes ||v_i|| and the error bound of a "
                 "basis store to a .npz or HDF5 file.")
    exp.add_argument("out", metavar="OUT",
                     help="output file, .npz or .h5/.hdf5 (overwritten if it exists)")

    check = sub.add_parser(
        "check", help="verify every checksum of a store",
        description="Verify every checksum of a basis store (root attributes, pointer, the "
        "current and previous generations, every segment) without changing it. Exit 0 if "
        "it is healthy, 2 if it is damaged: one line per problem, naming what is damaged "
        "and the last readable generation.")
    check.add_argument("store", metavar="STORE", help="basis store written by `streamsvd ingest`")
    _add_storage_option(check)

    plot = reader("plot", help="amplitudes, error bound against k, orthogonality as PNG",
                  description="Plot the amplitudes, the error bound against the terms "
                  "kept (log scale, with the target when there is one) and the "
                  "orthogonality history of a basis store.")
    plot.add_argument("out", metavar="OUT",
                      help="output image, .png (or .pdf, .svg); overwritten if it exists")
    return ap


# --------------------------------------------------------------------------- errors

# Advice the library gives Python callers, and what a command-line user does instead.
_REWRITES = (
    (r"Create one with `BasisStore\.create\([^`]*\)`\.",
     "Create it with `streamsvd ingest SOURCE STORE`."),
    (r"Pass the directory given to `BasisStore\.create`\.",
     "Pass a directory written by `streamsvd ingest`."),
    (r"Create it again with `BasisStore\.create`, which replaces the leftovers\.",
     "Delete it and run `streamsvd ingest` again."),
    (r"Close that writer first, open the store with mode='r' to read it without the "
     r"lock, or delete the lock file if that process is gone\.",
     "Wait for that writer (another `streamsvd ingest`) to finish, or delete the lock "
     "file if that process is gone; `streamsvd info`, `export` and `plot` can read the "
     "store meanwhile."),
    (r"Open it with `open_store\(path, mode='a'\)`, or delete it first to start afresh\.",
     "Pass --resume to continue it, or delete it first to start afresh."),
    (r"The previous generation is kept: read it with `store\.read\(generation=(\d+)\)` and "
     r"commit it again, or restore the store from a copy\.",
     r"The previous generation \1 is kept (`streamsvd check STORE` verifies it); restore "
     "the store from a copy."),
    (r"Pass dataset=<one of them>\.", "Pass --dataset with one of them."),
    (r"Use the in-memory StreamCompressor, or lump the mass matrix into weights\.",
     "Drop --tall, or lump the mass matrix into weights."),
    (r"Drop the `dataset` argument\.", "Drop --dataset."),
    (r"got dataset=('[^']*')", r"got --dataset \1"),
)

# Python argument names (as the library quotes them) -> command-line words
_NAMES = {
    "path": "STORE", "store": "STORE", "source": "SOURCE", "out": "OUT",
    "dataset": "--dataset", "block": "--block", "eps": "--eps", "rtol": "--rtol",
    "max_rank": "--max-rank", "oversampling": "--oversampling", "rule": "--rule",
    "sweeps": "--sweeps",
    "commit_every": "--commit-every", "scheduler": "--scheduler", "workers": "--workers",
    "leaf_columns": "--leaf-columns", "chunk_rows": "--chunk-rows", "resume": "--resume",
    "inner": "--inner", "storage_options": "--storage-option",
    "M": "--inner (its matrix)", "weights": "--inner (its weights)",
}

# a sentence holding Python code: a quoted call, a keyword argument, a module path
_PYTHON = re.compile(r"`[\w.]+\(|\b\w+=(?:True|False|None|'|\.\.\.)|`streamsvd\.\w|\bmode='")


def _in_cli_words(message: str) -> str:
    """Say a library message in the words of the command line, on one line.

    Known Python advice is replaced by what a command-line user does; argument names
    become the command's arguments and options; any remaining sentence that still shows
    Python code is dropped (the first sentence, the fact, is always kept).
    """
    text = " ".join(message.split())
    for pattern, replacement in _REWRITES:
        text = re.sub(pattern, replacement, text)
    text = re.sub(r"`(\w+)`", lambda m: _NAMES.get(m[1], m[0]), text)
    sentences = re.split(r"(?<=[.;])\s+(?=[A-Z`])", text)
    kept = sentences[:1] + [s for s in sentences[1:] if not _PYTHON.search(s)]
    return " ".join(kept)


def main(argv: list[str] | None = None) -> int:
    """Run the ``streamsvd`` command.

    Parameters
    ----------
    argv : list of str, optional
        The arguments after the command name; ``sys.argv[1:]`` when omitted.

    Returns
    -------
    int
        The exit status: 0 on success (and after ``--help``), 2 after a user mistake
        (reported on one line of stderr as ``streamsvd: error: ...``), 130 after Ctrl-C
        (one line saying what the store holds and the command that continues).
    """
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) or a usage error (2), already printed
        return int(exc.code or 0)
    logging.basicConfig(level=logging.WARNING, format="streamsvd: %(message)s")
    if not args.debug:
        # dask.distributed sets its loggers to INFO from its config when first imported
        # (here, lazily); the config can be given by environment, which workers inherit
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    try:
        _locate(args)
        return int(_COMMANDS[args.command](args))
    except KeyboardInterrupt:
        print(_interrupted(args, argv), file=sys.stderr)
        return 130
    except (StreamSVDError, OSError, ValueError) as err:
        if args.debug:
            raise
        print(f"streamsvd: error: {_in_cli_words(str(err))}", file=sys.stderr)
        return 2


def _interrupted(args: Any, argv: list[str]) -> str:
    """Return the line printed after Ctrl-C: what the store holds, how to continue."""
    if args.command != "ingest":
        return "streamsvd: interrupted."
    again = " ".join(shlex.quote(a) for a in argv if a != "--resume")
    try:
        from .store import open_store

        with open_store(args.store, "r") as st:
            offset = int(st.read().attrs.get("source_offset", 0))
    except (StreamSVDError, OSError, ValueError):
        return (
            f"streamsvd: interrupted; nothing was committed to STORE {args.store}; start "
            f"again with: streamsvd {again} --resume"
        )
    return (
        f"streamsvd: interrupted; STORE {args.store} holds the snapshots up to column "
        f"{offset} of SOURCE (its last commit); continue with: streamsvd {again} --resume"
    )


# --------------------------------------------------------------------------- ingest


def _mode(args: Any) -> str:
    if args.tall:
        return "tall"
    return "tree" if args.scheduler is not None else "memory"


def _check_mode_options(args: Any, mode: str) -> None:
    """Refuse the options that the chosen mode would ignore."""
    if args.leaf_columns is not None and mode != "tree":
        raise InputError(
            "--leaf-columns applies to the tree mode only (--scheduler without --tall); "
            + ("drop it with --tall." if mode == "tall" else
               "add --scheduler threads|local|ADDRESS, or drop it.")
        )
    if args.chunk_rows is not None and mode != "tall":
        raise InputError("--chunk-rows applies to the tall mode only; add --tall, or drop it.")
    if args.threads is not None and mode != "memory":
        raise InputError(
            "--threads applies to the in-memory mode; the dask modes give each task its "
            "share of the cores. Drop --threads, or drop --scheduler/--tall."
        )
    if args.streaming_share is not None and args.target_error is None and not args.resume:
        raise InputError(
            "--streaming-share splits the budget of --target-error; add --target-error T, "
            "or drop --streaming-share."
        )
    if args.workers is not None and args.scheduler != "local":
        where = ("without --scheduler" if args.scheduler is None else
                 f"with --scheduler {args.scheduler}")
        raise InputError(
            f"--workers sizes a LocalCluster and applies to --scheduler local only; got it "
            f"{where}. Add --scheduler local, or drop --workers (a remote cluster is sized "
            "where it runs)."
        )
    if args.source_changed_ok and not args.resume:
        raise InputError(
            "--source-changed-ok applies to --resume only (a new STORE records its SOURCE); "
            "add --resume, or drop it."
        )
    if args.commit_every is not None and mode == "tree":
        raise InputError(
            "--commit-every does not apply to the tree mode (--scheduler without --tall), "
            "which commits STORE once, when the tree is merged; drop it, or add --tall."
        )


def _compressor_options(args: Any, mode: str, *, resume: bool, inner: Any
                        ) -> dict[str, Any]:
    """Return the options of a new store, with the command's defaults (to resume: inner)."""
    if resume:
        return {} if inner is None else {"inner": inner}
    sweeps = _DEFAULT_SWEEPS if args.sweeps is None else args.sweeps
    options: dict[str, Any] = {
        "inner": inner, "eps": 0.0 if args.eps is None else args.eps, "rtol": args.rtol,
        "max_rank": args.max_rank, "rule": args.rule or _DEFAULT_RULE,
        "sweeps": None if sweeps == CONVERGE else sweeps,
        "oversampling": (_DEFAULT_OVERSAMPLING if args.oversampling is None
                         else args.oversampling),
        "target_error": args.target_error,
        "error_measure": args.error_measure or "relative",
        "streaming_share": 0.9 if args.streaming_share is None else args.streaming_share,
    }
    if mode != "tree":
        options["commit_every"] = args.commit_every or _DEFAULT_COMMIT_EVERY
    return options


def _show(name: str, value: Any) -> str:
    if value is None:
        return CONVERGE if name == "sweeps" else "none"
    return str(value)


def _check_resume_options(args: Any, recorded: dict[str, Any]) -> None:
    """Refuse an option given with --resume that differs from the one STORE records.

    A store keeps the options it was created with; giving the same value again (the
    first command line with --resume added) is accepted, another value is refused rather
    than silently ignored.
    """
    differ = []
    for name, flag in (*_STORE_OPTIONS, ("chunk_rows", "--chunk-rows")):
        value = getattr(args, name)
        if value is None or name not in recorded:
            continue
        wanted = None if value == CONVERGE else value
        if wanted != recorded[name]:
            differ.append(f"{flag} {_show(name, wanted)} (STORE has {_show(name, recorded[name])})")
    if differ:
        raise InputError(
            f"{', '.join(differ)}: --resume continues STORE with the options it was created "
            "with (`streamsvd info STORE` shows them). Drop the option, or give the store's "
            "value."
        )


# how a difference of SourceRecord.differences is named on the command line
_SOURCE_PARTS = {"path": "SOURCE", "dataset": "--dataset", "shape": "SOURCE of shape"}


def _check_resume(args: Any, sc: Any, record: Any) -> None:
    """Refuse to continue the compressor ``sc`` with other options or another SOURCE.

    ``record`` describes SOURCE as given. Its snapshot size must be the store's; its
    path, dataset and number of columns are checked against the source the store
    records (a store written before stores recorded it is not checked), unless
    --source-changed-ok is given. On success the store will record ``record``.
    """
    recorded = sc._options()
    if hasattr(sc, "chunk_rows"):  # a tall store keeps the row chunks of its panels
        recorded["chunk_rows"] = sc.chunk_rows
    _check_resume_options(args, recorded)
    n = record.shape[0]
    if n != sc.n:
        raise ShapeMismatchError(
            f"SOURCE has snapshots of size {n}; STORE {args.store} holds a basis of size "
            f"{sc.n}. Pass the source the store was built from."
        )
    source = sc.source_record
    differ = [] if source is None else source.differences(record)
    if differ and not args.source_changed_ok:
        said = ", ".join(f"{_SOURCE_PARTS[what]} {given} (STORE has {had})"
                         for what, given, had in differ)
        raise InputError(
            f"{said}: STORE {args.store} was built from another source. Pass the SOURCE "
            "(and --dataset) it was built from, or add --source-changed-ok to continue it "
            "from this one."
        )
    if differ:
        logger.warning("continuing STORE %s from another source (%s)", args.store,
                       ", ".join(f"{what} {had} -> {given}" for what, given, had in differ))
    sc.source_record = record


def _source_record(args: Any) -> Any:
    """Open SOURCE (checking it) and return its record."""
    from .provenance import SourceRecord
    from .sources import open_source

    source, dataset = getattr(args, "source_given", (args.source, args.dataset))
    with open_source(args.source, dataset=args.dataset) as src:
        if src.shape[0] < 1:
            raise SourceError(f"SOURCE {source} holds snapshots of size {src.shape[0]} "
                              f"(shape {src.shape}); a snapshot needs at least one entry.")
        return SourceRecord.of(source, dataset=dataset, shape=src.shape,
                               description=src.description)


def _load_inner(args: Any) -> Any:
    if args.inner is None:
        return None
    from .inner import load_inner

    return load_inner(args.inner)


def _ingest(args: Any) -> int:
    mode = _mode(args)
    _check_mode_options(args, mode)
    from .policy import removed_on_failure, resuming

    store = args.store  # a storage (see _locate)
    resume = resuming(store, resume=args.resume)
    if args.oversampling is not None and args.max_rank is None and not resume:
        raise InputError(
            "--oversampling adds terms to --max-rank while streaming; add --max-rank K, or "
            "drop --oversampling."
        )
    options = _compressor_options(args, mode, resume=resume, inner=_load_inner(args))
    block = args.block or _DEFAULT_BLOCK
    record = _source_record(args)
    with removed_on_failure(store, new=not resume):
        try:
            if mode == "memory":
                summary = _ingest_memory(args, store, block, options, resume=resume,
                                         record=record)
            else:
                summary = _ingest_dask(args, mode, store, block, options, resume=resume,
                                       record=record)
        except StoreMismatchError:
            if resume:
                _check_store_kind(store, tall=mode == "tall")
            raise
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


def _final(args: Any) -> bool:
    """Whether the command ends with the final sweeps (``--final-sweeps``)."""
    return args.final_sweeps in (None, CONVERGE)


def _ingest_memory(args: Any, store: Storage, block: int, options: dict[str, Any], *,
                   resume: bool, record: Any) -> dict[str, Any]:
    from tqdm import tqdm

    from .sources import open_source
    from .stream import StreamCompressor, summary_of

    with open_source(args.source, dataset=args.dataset) as src:
        if resume:
            sc = StreamCompressor.open(store, **options)
        else:
            sc = StreamCompressor(src.n, store=store, source_record=record, **options)
        sc.threads = {None: 1, "all": None}.get(args.threads, args.threads)
        try:
            if resume:
                _check_resume(args, sc, record)
            start = sc.source_offset
            bar = tqdm(total=src.m, initial=start, unit="col", disable=args.quiet,
                       dynamic_ncols=True, desc="ingest", file=sys.stderr)
            with bar:
                for offset, X in src.blocks(block=block, start=start):
                    rec = sc.absorb(X, source_offset=offset + X.shape[1])
                    # the postfix first, so that the redraw of update() shows this update
                    bar.set_postfix(rank=rec.rank, bound=f"{rec.error_bound:.2e}",
                                    refresh=False)
                    bar.update(X.shape[1])
            if _final(args) and not sc.finalized:
                sc.finalize()
            return summary_of(sc)
        finally:
            sc.close(finalize=False)


def _ingest_dask(args: Any, mode: str, store: Storage, block: int, options: dict[str, Any], *,
                 resume: bool, record: Any) -> dict[str, Any]:
    from .parallel import ingest

    if resume:  # the engine takes no option with resume: check here
        with _open(store, inner=options.get("inner")) as sc:
            _check_resume(args, sc, record)
    # dask's progress bars (ProgressBar, distributed.progress) write to stdout, which
    # belongs to the command's output: send whatever the engine prints to stderr
    try:
        with contextlib.redirect_stdout(sys.stderr):
            return ingest(
                args.source, store, dataset=args.dataset, block=block,
                scheduler=args.scheduler, workers=args.workers, tall=mode == "tall",
                leaf_columns=args.leaf_columns, chunk_rows=args.chunk_rows,
                resume=resume, progress=not args.quiet, finalize=_final(args),
                **options,
            )
    except NonFiniteError:
        if mode == "tall":  # the tall engine counts the bad entries but cannot place them
            _locate_non_finite(args, store, block)
        raise


def _locate_non_finite(args: Any, store: Storage, block: int) -> None:
    """Re-read the source after the last commit; raise its error naming the bad entry.

    Every block before the store's recorded source offset was absorbed, so the first
    NaN or infinite entry after it is the one the tall update refused. Returns without
    raising when it finds none (the caller re-raises the update's error).
    """
    from .parallel import open_compressor
    from .sources import open_source

    try:
        with open_compressor(store, mode="r") as sc:
            start = sc.source_offset
    except (StoreError, ValueError):
        start = 0
    with open_source(args.source, dataset=args.dataset) as src:
        for _ in src.blocks(block=block, start=min(start, src.m)):
            pass  # Source checks every block it reads and raises NonFiniteError


def _check_store_kind(store: Storage, *, tall: bool) -> None:
    """Raise a command-line error when STORE was written in the other mode."""
    from .store import open_store

    try:
        with open_store(store, "r") as st:
            kind = st.read().attrs.get("kind")
    except (StoreError, ValueError):
        return
    if tall and kind == "streamsvd.StreamCompressor":
        raise StoreMismatchError(
            f"STORE {store} was written without --tall (in memory or by a tree); resume "
            "it without --tall."
        )
    if not tall and kind == "streamsvd.TallCompressor":
        raise StoreMismatchError(f"STORE {store} was written with --tall; resume it with --tall.")


# ------------------------------------------------------------------- info, export, plot


def _open(path: Any, *, inner: Any = None) -> Any:
    """Open the compressor of a store read-only, whichever kind wrote it.

    ``inner``: the inner product, needed only for a store that does not keep its own.
    """
    from .storage import open_storage

    if open_storage(path).is_file():
        raise StoreError(
            f"STORE {path} is a file; a basis store is a directory written by "
            "`streamsvd ingest`."
        )
    from .stream import StreamCompressor

    try:
        return StreamCompressor.open(path, mode="r", inner=inner)
    except StoreMismatchError:
        from .parallel import open_compressor  # a tall store: dask is needed to read it

        return open_compressor(path, mode="r", inner=inner)


def _info(args: Any) -> int:
    from .stream import summary_of

    with _open(args.store, inner=_load_inner(args)) as sc:
        summary = summary_of(sc)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    opts = summary["options"]
    sweeps = CONVERGE if opts["sweeps"] is None else opts["sweeps"]
    print(f"store         {summary['store']}")
    source = summary["source"]
    if source is not None:
        n, m = source["shape"]
        where = "" if source["resolved"] in (None, source["path"]) else f", {source['resolved']}"
        print(f"source        {source['description']} ({n} x {m}){where}")
    print(f"inner product {summary['inner']}")
    print(f"snapshots     n = {summary['n']}, absorbed {summary['n_seen']} "
          f"(source offset {summary['source_offset']}) in {summary['updates']} "
          f"update{'' if summary['updates'] == 1 else 's'}")
    print(f"rank          {summary['rank']}  (rule {opts['rule']}, sweeps {sweeps}, "
          f"eps {opts['eps']}, rtol {opts['rtol']}, max_rank {opts['max_rank']}, "
          f"oversampling {opts['oversampling']})")
    print("final sweeps  " + (
        "converged: the expansion is the SVD of what was absorbed" if summary["finalized"]
        else "not run: the expansion is as streamed (`streamsvd ingest --resume` without "
        "--final-sweeps none converges it)"))
    print(f"error bound   ||A - U V^T||_F <= {summary['error_bound']:.3e}")
    if opts.get("target_error") is not None:
        met = "met" if summary["target_met"] else "NOT met (--max-rank cuts more)"
        print(f"target error  {opts['target_error']:.3e} ({opts['error_measure']}): bound "
              f"{summary['error_in_measure']:.3e} in that measure, {met}")
    print(f"orthogonality ||U^T M U - I||_2 = {summary['orthogonality']:.2e}")
    head = ", ".join(f"{a:.4g}" for a in summary["amplitudes_head"])
    print(f"amplitudes    {head}{', ...' if summary['rank'] > 10 else ''}")
    return 0


def _export(args: Any) -> int:
    out = Path(args.out)
    if out.suffix not in (".npz", ".h5", ".hdf5"):
        raise InputError(f"OUT must end with .npz, .h5 or .hdf5; got {out.name!r}.")
    import numpy as np

    with _open(args.store, inner=_load_inner(args)) as sc:
        e = sc.expansion
        bound = sc.error_bound
    data = {"U": e.U, "V": e.V, "amplitudes": e.amplitudes, "error_bound": np.array(bound)}
    if out.suffix == ".npz":
        np.savez(out, **data)
    else:
        import h5py

        with h5py.File(out, "w") as h5:
            for k, v in data.items():
                h5.create_dataset(k, data=v)
    print(f"wrote {out} (U {e.U.shape}, V {e.V.shape})")
    return 0


def _figure(sc: Any, *, name: str) -> Any:
    """Draw the amplitudes, the error bound against k and the orthogonality history.

    Parameters
    ----------
    sc : StreamCompressor or TallCompressor
        An open compressor.
    name : str
        How the store is named in the title.

    Returns
    -------
    matplotlib.figure.Figure
        Three panels; every x axis counts terms or updates and has integer ticks.
    """
    import numpy as np
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    amps = np.asarray(sc.amplitudes)
    hist = sc.history
    terms = np.arange(1, amps.size + 1)
    fig = Figure(figsize=(14, 4.4))
    ax = fig.subplots(1, 3)
    fig.suptitle(
        f"{name}: n = {sc.n}, rank {sc.rank}, {sc.n_seen} snapshots in {len(hist)} "
        f"update{'' if len(hist) == 1 else 's'}, ||A - U V^T||_F <= {sc.error_bound:.2e}"
    )
    ax[0].semilogy(terms, amps, "k.-", ms=4)
    ax[0].set(xlabel="term i", ylabel="amplitude ||v_i|| (units of the data)",
              title="amplitudes")
    # the bound after cutting to k terms (the terms are orthogonal at convergence):
    # hypot(bound, ||amplitudes k+1 ...||), in the measure of the target
    scale = float(amps.max()) if amps.size else 1.0
    a = amps / scale if scale > 0 else amps
    tail = np.sqrt(np.append(np.cumsum((a**2)[::-1])[::-1], 0.0))[1:] * scale
    bound_k = np.hypot(sc.error_bound, tail)
    measure = sc.error_measure if sc.target_error is not None else "relative"
    if measure == "mean_l2":
        shown, label = bound_k / np.sqrt(max(sc.n_seen, 1)), "bound on the mean l2 error"
    elif measure == "absolute":
        shown, label = bound_k, "bound on ||A - U_k V_k^T||_F"
    else:
        kept = np.sqrt(np.cumsum(a**2)) * scale
        with np.errstate(divide="ignore", invalid="ignore"):
            shown = np.where(kept > bound_k, bound_k / (kept - bound_k), np.inf)
        label = "bound on ||A - U_k V_k^T||_F / ||A||_F"
    ax[1].semilogy(terms, np.maximum(shown, 1e-300), "b.-", ms=4, label="cut to k terms")
    if sc.target_error is not None:
        ax[1].axhline(sc.target_error, color="0.3", ls="--", lw=1,
                      label=f"target {sc.target_error:.1e}")
    ax[1].set(xlabel="terms kept k", ylabel=f"{label} (dimensionless)" if measure != "absolute"
              else f"{label} (units of the data)", title="error bound against k")
    if amps.size:
        ax[1].legend(loc="best", fontsize="small")
    updates = np.arange(1, len(hist) + 1)
    orth = [max(h.orthogonality, 1e-18) for h in hist]
    ax[2].semilogy(updates, orth, "r.-", ms=8, label="after each update")
    reorth = sc._options().get("reorth_tol")
    if reorth:
        ax[2].axhline(reorth, color="0.5", ls="--", lw=1, label="re-orthonormalisation threshold")
    ax[2].set(xlabel="update", ylabel="||U^T M U - I||_2 (dimensionless)",
              title="orthogonality of U")
    if hist:
        ax[2].legend(loc="best", fontsize="small")
    for a, count, what in ((ax[0], amps.size, "no terms"), (ax[1], amps.size, "no terms"),
                           (ax[2], len(hist), "no updates")):
        # counts: integer ticks, and limits wide enough for them even with one point
        a.set_xlim(0.5, max(count, 1) + 0.5)
        a.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
        if not count:
            a.text(0.5, 0.5, what, transform=a.transAxes, ha="center", va="center")
    fig.tight_layout()
    return fig


def _plot(args: Any) -> int:
    out = Path(args.out)
    with _open(args.store, inner=_load_inner(args)) as sc:
        fig = _figure(sc, name=Path(str(args.store).rstrip("/")).name)
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")
    return 0


def _check(args: Any) -> int:
    """Verify every checksum of STORE: one line per problem (exit 2), or what verified (0)."""
    from .storage import open_storage
    from .store import check_store

    report = check_store(open_storage(args.store))
    for problem in report.problems:
        print(f"damaged: {_in_cli_words(problem)}")
    if report.problems:
        return 2
    for line in report.verified:
        print(f"STORE {report.store}: {line}")
    return 0


_COMMANDS = {"ingest": _ingest, "info": _info, "export": _export, "plot": _plot,
             "check": _check}


if __name__ == "__main__":
    sys.exit(main())
