"""The ``streamsvd`` command's arguments: the parser, the option types and the defaults.

:func:`build_parser` describes every command and option (the ``--help`` texts), an
option that several commands take once (:func:`add_json`, :func:`add_rtol`); the option
types turn a word of the command line into a value or a one-line usage error.
An option left out parses as None, so that a command can tell an option given from its
default (``--resume`` refuses an option that differs from the store's). :func:`locate`
and :func:`load_inner` turn STORE, a SOURCE URL and ``--inner`` into the objects the
commands use.

Only the standard library is imported here (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import argparse
import re
from typing import Any, NoReturn

from streamsvd._version import __version__
from streamsvd.cli.types import (
    CONVERGE,
    DEFAULT_COMMIT_EVERY,
    commit_every,
    forget,
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
    scheduler,
    storage_option,
    sweeps,
    threads,
)
from streamsvd.errors import InputError

__all__ = [
    "DEFAULT_BLOCK",
    "DEFAULT_OVERSAMPLING",
    "DEFAULT_RULE",
    "DEFAULT_SWEEPS",
    "add_json",
    "add_rtol",
    "build_parser",
    "diagonal_as_weights",
    "load_inner",
    "locate",
]

# the defaults of `streamsvd ingest` (an option left out parses as None)
DEFAULT_BLOCK = 100
DEFAULT_RULE = "paper"
DEFAULT_SWEEPS = 1
DEFAULT_OVERSAMPLING = 10
#: The ``--final-sweeps`` values: converge the core at the end, or leave it as streamed.
_FINAL_SWEEPS = (CONVERGE, "none")

_INGEST_EPILOG = """\
modes:
  in memory   (default)             the basis in memory, committed to STORE as
                                    --commit-every says
  tree        --scheduler S         leaves of --leaf-columns columns compressed
                                    independently on dask, merged pairwise; STORE is
                                    written once, at the end
  tall        --tall [--scheduler S]
                                    U kept out of core in panels of --chunk-rows
                                    rows, every product run by dask over row chunks;
                                    committed as --commit-every says
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

# a word that Python reads as a negative float (-1, -.5, -1e-3, -inf): argparse's own
# pattern misses the exponent and the infinities, and takes such a word for an option
_NEGATIVE_NUMBER = re.compile(
    r"^-(\d[\d_]*\.?[\d_]*|\.\d[\d_]*)(e[+-]?\d[\d_]*)?$|^-(inf|infinity|nan)$", re.IGNORECASE
)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line ``streamsvd: error: ...``.

    A negative number after an option is that option's value, whatever its notation, so
    that ``--target-error -1e-3`` is refused by the option's type, in the same words as
    ``--target-error=-1e-3``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str) -> NoReturn:
        """Print the usage error on one line and exit with status 2."""
        self.exit(2, f"streamsvd: error: {message} (see `{self.prog} --help`).\n")


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


def add_json(parser: Any, *, what: str, otherwise: str) -> None:
    """Add ``--json`` to ``parser``: print ``what`` as JSON instead of ``otherwise``."""
    parser.add_argument("--json", action="store_true",
                        help=f"print {what} as JSON (default: off, {otherwise})")


def add_rtol(parser: Any, *, help: str) -> None:
    """Add ``--rtol R`` (a number >= 0) to ``parser`` or to one of its groups."""
    parser.add_argument("--rtol", metavar="R", type=nonnegative_float, help=help)


def _add_store(parser: Any, *, help: str = "basis store written by `streamsvd ingest`"
               ) -> None:
    """Add the argument STORE, which ``help`` describes."""
    parser.add_argument("store", metavar="STORE", help=help)


def _add_inner(parser: Any, *, what: str, then: str) -> None:
    """Add ``--inner FILE``, whose help is ``what``, the file formats, then ``then``."""
    parser.add_argument(
        "--inner", metavar="FILE",
        help=f"{what}: .npy (1-D positive weights or a 2-D SPD matrix), .npz (a scipy "
        f"sparse matrix saved by scipy.sparse.save_npz) or .mtx (Matrix Market); {then}",
    )


def _add_storage_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--storage-option", metavar="KEY=VALUE", type=storage_option, action="append",
        help="option of the object store of an s3:// (or other fsspec) URL, for SOURCE and "
        "STORE alike, such as endpoint_url=URL, key=ID, secret=S, anon=true; a dotted KEY "
        "nests (client_kwargs.region_name=R); repeatable (default: none; the AWS_* "
        "environment variables apply)",
    )


def locate(args: Any) -> None:
    """Turn STORE into a storage and a SOURCE URL into its zarr array (with the options)."""
    from streamsvd.io.formats import open_zarr_url
    from streamsvd.storage import is_url, open_storage

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


def load_inner(args: Any) -> Any:
    """Return the inner product of ``--inner`` (loaded from its file), or None."""
    if args.inner is None:
        return None
    from streamsvd.io.inner_file import load_inner as load

    return load(args.inner)


def diagonal_as_weights(inner: Any) -> Any:
    """Return a matrix inner product with nothing off its diagonal as its weights.

    The tall mode keeps ``U`` in row panels and takes weights only; a diagonal mass
    matrix (pyMOR's finite-volume ``l2_product`` saved by ``scipy.sparse.save_npz``) is
    such weights. Any other inner product (or None) is returned as it is.
    """
    import numpy as np
    import scipy.sparse as sp

    from streamsvd.algebra.inner import DiagonalInner, MatrixInner

    if not isinstance(inner, MatrixInner):
        return inner
    mat = inner.matrix  # its diagonal is positive (checked): n entries are not zero
    nonzero = mat.count_nonzero() if sp.issparse(mat) else np.count_nonzero(mat)
    return DiagonalInner(mat.diagonal()) if nonzero == inner.n else inner


def build_parser() -> argparse.ArgumentParser:
    """Return the parser of the ``streamsvd`` command and its six commands."""
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
    _add_store(ing, help="basis store (zarr v3): a directory or a URL (file://, "
               "s3://BUCKET/basis.zarr); created, or continued with --resume")
    ing.add_argument("--dataset", metavar="NAME",
                     help="dataset of an HDF5 file or array of a zarr group (default: the "
                     "only one there)")
    ing.add_argument("--block", metavar="B", type=positive_int,
                     help=f"snapshots (columns) absorbed per update (default: {DEFAULT_BLOCK})")
    tol = ing.add_mutually_exclusive_group()
    tol.add_argument("--eps", metavar="E", type=nonnegative_float,
                     help="absolute cut: drop the terms with ||v_i|| < E, in the units of "
                     "the data (default: 0, no cut)")
    add_rtol(tol, help="relative cut: drop the terms with ||v_i|| < R ||v_1|| (default: "
             "none; not with --eps)")
    tol.add_argument("--target-error", metavar="T", type=positive_float,
                     help="keep the fewest terms whose guaranteed error bound is at most T, "
                     "a positive number, in --error-measure (default: none; not with --eps "
                     "or --rtol)")
    ing.add_argument("--error-measure", choices=("relative", "mean_l2", "absolute"),
                     help="'relative': ||A - U V^T||_F <= T ||A||_F; 'mean_l2': "
                     "sqrt(sum_j ||a_j - P a_j||^2 / m) <= T (pyMOR HAPOD's measure); "
                     "'absolute': ||A - U V^T||_F <= T; norms in --inner (default: relative)")
    ing.add_argument("--streaming-share", metavar="S", type=float,
                     help="share of the --target-error budget spent while streaming, the "
                     "rest by the final cut (default: 0.436 = sqrt(1 - 0.9^2), pyMOR "
                     "HAPOD's split at omega = 0.9)")
    ing.add_argument("--max-rank", metavar="K", type=positive_int,
                     help="keep K terms in the end: K + --oversampling while streaming, "
                     "cut to K by the final sweeps (default: no limit)")
    ing.add_argument("--window", metavar="W", type=positive_int,
                     help="keep the W most recent snapshots: each block removes exactly "
                     "those that fall out, in memory and --tall; the tree mode refuses it "
                     "(default: keep all)")
    ing.add_argument("--forget", metavar="G", type=forget,
                     help="forgetting factor in (0, 1]: each snapshot is weighted by G to "
                     "the number absorbed after it, in memory and --tall (default: 1, none)")
    ing.add_argument("--dynamics", action="store_true", default=None,
                     help="record the stream for `streamsvd dmd` (keeps the right vectors, "
                     "which hold the snapshot pairs), in memory and --tall (default: off)")
    ing.add_argument("--oversampling", metavar="P", type=nonnegative_int,
                     help="extra terms kept while streaming with --max-rank; 0 cuts to K "
                     f"at every update (default: {DEFAULT_OVERSAMPLING})")
    ing.add_argument("--rule", choices=("paper", "jacobi"),
                     help="rotation of a pair of terms: 'paper' turns by tan(theta) = "
                     "(v_j|v_i)/(v_j|v_j) (eq. 5, linear convergence), 'jacobi' by the angle "
                     "that zeroes the pair's coupling (one-sided Jacobi, quadratic "
                     f"convergence) (default: {DEFAULT_RULE})")
    ing.add_argument("--sweeps", metavar=f"N|{CONVERGE}", type=sweeps,
                     help="rotation sweeps per update: a positive integer, or "
                     f"'{CONVERGE}' to sweep until no pair rotates (an incremental SVD) "
                     f"(default: {DEFAULT_SWEEPS})")
    ing.add_argument("--final-sweeps", choices=_FINAL_SWEEPS,
                     help=f"at the end, '{CONVERGE}': sweep the core until no pair rotates "
                     "(Jacobi rule) and cut by --eps/--rtol/--max-rank, so that STORE holds "
                     "the SVD of what was absorbed; 'none': keep the streamed expansion "
                     f"(default: {CONVERGE})")
    ing.add_argument("--threads", metavar="N", type=threads,
                     help="BLAS threads of an update, or 'all' for the BLAS's own setting "
                     "(default: 1, never much slower, and much faster on a busy machine)")
    ing.add_argument("--commit-every", metavar=f"C|{DEFAULT_COMMIT_EVERY}", type=commit_every,
                     help="when the updates are committed to STORE, in memory and with "
                     f"--tall: every C updates, or with '{DEFAULT_COMMIT_EVERY}' whenever "
                     "the commits so far plus one more as long as the last take at most a "
                     "tenth of the time since the start; "
                     "then a commit comes about 10 times as long as the last one took "
                     "after it, which bounds what a kill loses; the end and Ctrl-C commit "
                     "what is pending; the tree mode commits once (default: "
                     f"{DEFAULT_COMMIT_EVERY})")
    _add_inner(ing, what="inner product in which U is orthonormal (a mass matrix, "
               "quadrature weights)", then="with --tall, weights only (a matrix with "
               "nothing off its diagonal is read as its weights); STORE keeps it, so "
               "--resume, info, export and plot need it only for a store written before "
               "stores kept it (checked against STORE when given) (default: Euclidean, or "
               "the one STORE keeps)")
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
    ing.add_argument("--scheduler", metavar="S", type=scheduler,
                     help="run on dask: 'threads' (this process), 'local' (a LocalCluster "
                     "of --workers processes) or the address of a scheduler "
                     "(tcp://HOST:PORT); without --tall, the tree mode (default: no dask, "
                     "in memory; 'threads' with --tall)")
    ing.add_argument("--workers", metavar="W", type=positive_int,
                     help="worker processes of --scheduler local (default: the number of "
                     "CPUs)")
    ing.add_argument("--tall", action="store_true",
                     help="tall mode: keep U out of core in panels on disk, for snapshots too "
                     "long for memory; on --scheduler, threads by default (default: off)")
    ing.add_argument("--leaf-columns", metavar="L", type=positive_int,
                     help="columns per leaf, tree mode only (default: 10 blocks, fewer so "
                     "that every worker thread gets a leaf)")
    ing.add_argument("--chunk-rows", metavar="R", type=positive_int,
                     help="rows per chunk of the panels, tall mode only (default: the "
                     "source's row chunks, else 16384)")
    _add_storage_option(ing)

    def reader(name: str, *, help: str, description: str) -> argparse.ArgumentParser:
        """Add a command that reads STORE (its first argument)."""
        parser = sub.add_parser(name, help=help, description=description)
        _add_store(parser)
        _add_inner(parser, what="the inner product STORE was written with, for a store "
                   "that does not keep it (written before stores kept it)",
                   then="checked against STORE (default: the one STORE keeps, else "
                   "Euclidean)")
        _add_storage_option(parser)
        return parser

    info = reader("info", help="summarise a store",
                  description="Summarise a basis store: sizes, rank, options, error bound, "
                  "orthogonality and the leading amplitudes.")
    add_json(info, what="the summary", otherwise="a text report")

    exp = reader("export", help="write U, V and the amplitudes to .npz or .h5",
                 description="Write U, V, the amplitudes ||v_i|| and the error bound of a "
                 "basis store to a .npz or HDF5 file.")
    exp.add_argument("out", metavar="OUT",
                     help="output file, .npz or .h5/.hdf5 (overwritten if it exists)")

    from streamsvd.cli import dmd

    dmd.add_arguments(reader(
        "dmd", help="certified DMD: eigenvalues with residual bounds, modes, forecast",
        description="Dynamic mode decomposition of the snapshots of STORE (written by "
        "`ingest --dynamics`, or any store with right vectors): eigenvalues, a residual "
        "bound eta per eigenvalue (docs: theory, DMD), modes and forecasts."))

    check = sub.add_parser(
        "check", help="verify every checksum of a store",
        description="Verify every checksum of a basis store (root attributes, pointer, the "
        "current and previous generations, every segment) without changing it. Exit 0 if "
        "it is healthy, 2 if it is damaged: one line per problem, naming what is damaged "
        "and the last readable generation.")
    _add_store(check)
    _add_storage_option(check)

    plot = reader("plot", help="amplitudes, error bound against k, orthogonality as PNG",
                  description="Plot the amplitudes, the error bound against the terms "
                  "kept (log scale, with the target when there is one) and the "
                  "orthogonality history of a basis store.")
    plot.add_argument("out", metavar="OUT",
                      help="output image, .png (or .pdf, .svg); overwritten if it exists")
    return ap

