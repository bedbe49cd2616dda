"""``streamsvd ingest``: absorb the columns of SOURCE into STORE, in one of three modes.

The mode follows from the options (in memory by default, the tree mode with
``--scheduler``, the tall mode with ``--tall``); an option of another mode is refused.
The in-memory mode runs the one ingest driver (:func:`streamsvd.stream.ingest.ingest`) here; the
dask modes run :func:`streamsvd.parallel.cluster`, which runs it too.
What is done with an existing STORE (create, continue, refuse, undo a failed start) is
:mod:`streamsvd.cli.policy`'s.

Only the standard library is imported at module level (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import contextlib
import json
import sys
from typing import TYPE_CHECKING, Any

from streamsvd.cli.parsing import (
    DEFAULT_BLOCK,
    DEFAULT_OVERSAMPLING,
    DEFAULT_RULE,
    DEFAULT_SWEEPS,
    diagonal_as_weights,
    load_inner,
)
from streamsvd.cli.reading import open_readonly
from streamsvd.cli.types import CONVERGE, DEFAULT_COMMIT_EVERY
from streamsvd.errors import (
    InputError,
    NonFiniteError,
    ShapeMismatchError,
    SourceError,
    StoreError,
    StoreMismatchError,
)

if TYPE_CHECKING:  # the storage module imports zarr: only for the annotations
    from streamsvd.storage import Storage

__all__ = ["run"]


def run(args: Any) -> int:
    """Run ``streamsvd ingest``; print the JSON summary unless ``--quiet``."""
    mode = _mode(args)
    _check_mode_options(args, mode)
    from streamsvd._util.malloc import keep_freed_memory
    from streamsvd.cli.policy import removed_on_failure, resuming

    keep_freed_memory()

    store = args.store  # a storage (see parsing.locate)
    resume = resuming(store, resume=args.resume)
    if args.oversampling is not None and args.max_rank is None and not resume:
        raise InputError(
            "--oversampling adds terms to --max-rank while streaming; add --max-rank K, or "
            "drop --oversampling."
        )
    inner = load_inner(args)
    if mode == "tall":
        inner = _tall_inner(inner, args.inner)
    options = _compressor_options(args, mode, resume=resume, inner=inner)
    block = args.block or DEFAULT_BLOCK
    record = _source_record(args)
    if inner is not None and inner.n is not None:
        _check_orientation(record, inner.n, "--inner")
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
    from streamsvd.io.open import open_source
    from streamsvd.stream.compressor import StreamCompressor
    from streamsvd.stream.ingest import ingest
    from streamsvd.stream.summary import summary_of

    with open_source(args.source, dataset=args.dataset) as src:
        if resume:
            sc = StreamCompressor.open(store, **options)
        else:
            sc = StreamCompressor(src.n, store=store, source_record=record, **options)
        sc.threads = {None: 1, "all": None}.get(args.threads, args.threads)
        try:
            if resume:
                _check_resume(args, sc, record)
            ingest(src, sc, block=block, progress=not args.quiet)
            if _final(args) and not sc.finalized:
                sc.finalize(progress=not args.quiet)
            return summary_of(sc)
        finally:
            sc.close(finalize=False)


def _ingest_dask(args: Any, mode: str, store: Storage, block: int, options: dict[str, Any], *,
                 resume: bool, record: Any) -> dict[str, Any]:
    from streamsvd.parallel.cluster import ingest as ingest_on_dask

    if resume:  # the engine takes no option with resume: check here
        with open_readonly(store, inner=options.get("inner")) as sc:
            _check_resume(args, sc, record)
    # dask's progress bars (ProgressBar, distributed.progress) write to stdout, which
    # belongs to the command's output: send whatever the engine prints to stderr
    try:
        with contextlib.redirect_stdout(sys.stderr):
            return ingest_on_dask(
                args.source, store, dataset=args.dataset, block=block,
                scheduler=args.scheduler, workers=args.workers, tall=mode == "tall",
                leaf_columns=args.leaf_columns, chunk_rows=args.chunk_rows,
                resume=resume, progress=not args.quiet, finalize=_final(args),
                **options,
            )
    except NonFiniteError:
        if mode == "tall":  # row chunks are read in parallel: the first may not be named
            _locate_non_finite(args, store, block)
        raise


def _locate_non_finite(args: Any, store: Storage, block: int) -> None:
    """Re-read the source after the last commit; raise its error naming the bad entry.

    Every block before the store's recorded source offset was absorbed, so the first
    NaN or infinite entry after it is the one the tall update refused. Returns without
    raising when it finds none (the caller re-raises the update's error).
    """
    from streamsvd.io.open import open_source
    from streamsvd.parallel.cluster import open_compressor

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
    from streamsvd.parallel.cluster import TallCompressor, compressor_class, stored_kind

    try:
        cls = compressor_class(stored_kind(store))
    except (StoreError, ValueError):
        return
    if cls is None or tall == (cls is TallCompressor):
        return
    if tall:
        raise StoreMismatchError(
            f"STORE {store} was written without --tall (in memory or by a tree); resume "
            "it without --tall."
        )
    raise StoreMismatchError(f"STORE {store} was written with --tall; resume it with --tall.")


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
    for given, flag in ((args.window, "--window"), (args.forget, "--forget")):
        if given is not None and mode == "tree":
            raise InputError(
                f"{flag} applies to the in-memory and tall modes only; the tree mode "
                "(--scheduler without --tall) compresses its leaves apart and cannot "
                f"drop or weight the oldest snapshots. Drop {flag}, or drop --scheduler "
                "(or add --tall)."
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
    from streamsvd.stream.options import STREAMING_SHARE

    sweeps = DEFAULT_SWEEPS if args.sweeps is None else args.sweeps
    options: dict[str, Any] = {
        "inner": inner, "eps": 0.0 if args.eps is None else args.eps, "rtol": args.rtol,
        "max_rank": args.max_rank, "rule": args.rule or DEFAULT_RULE,
        "sweeps": None if sweeps == CONVERGE else sweeps,
        "oversampling": (DEFAULT_OVERSAMPLING if args.oversampling is None
                         else args.oversampling),
        "target_error": args.target_error,
        "error_measure": args.error_measure or "relative",
        "streaming_share": (STREAMING_SHARE if args.streaming_share is None
                            else args.streaming_share),
    }
    if args.window is not None:
        options["window"] = args.window
    if args.forget is not None:
        options["forget"] = args.forget
    if mode != "tree":
        options["commit_every"] = args.commit_every or DEFAULT_COMMIT_EVERY
    return options


def _source_record(args: Any) -> Any:
    """Open SOURCE (checking it) and return its record."""
    from streamsvd.io.open import open_source
    from streamsvd.io.provenance import SourceRecord

    source, dataset = getattr(args, "source_given", (args.source, args.dataset))
    with open_source(args.source, dataset=args.dataset) as src:
        if src.shape[0] < 1:
            raise SourceError(f"SOURCE {source} holds snapshots of size {src.shape[0]} "
                              f"(shape {src.shape}); a snapshot needs at least one entry.")
        return SourceRecord.of(source, dataset=dataset, shape=src.shape,
                               description=src.description)


def _tall_inner(inner: Any, path: str) -> Any:
    """Return the inner product of ``--tall``: weights, or a matrix with only a diagonal as such.

    Raises
    ------
    InputError
        When the ``--inner`` matrix at ``path`` has entries off its diagonal.
    """
    from streamsvd.algebra.inner import DiagonalInner

    inner = diagonal_as_weights(inner)
    if inner is None or isinstance(inner, DiagonalInner):
        return inner
    raise InputError(
        f"--inner with --tall must be weights: a 1-D .npy of positive weights, or a "
        f"matrix with nothing off its diagonal; got {path}, a {inner.n} x {inner.n} matrix "
        "with entries off its diagonal, which couples the row panels of --tall. Drop "
        "--tall, or lump the mass matrix into weights."
    )


def _check_orientation(record: Any, size: int, what: str) -> None:
    """Refuse a SOURCE saved with one snapshot per row, which ``what`` of ``size`` reveals.

    Only when SOURCE's number of columns, not its snapshot size, is ``size``; any other
    mismatch is the library's to report.
    """
    n, m = record.shape
    if n != size and m == size:
        raise ShapeMismatchError(
            f"SOURCE {record.path} ({n} x {m}) looks saved with one snapshot per row: its "
            f"rows have size {size}, the size of {what}, while its columns, read as "
            f"snapshots, have size {n}. Save its transpose ({m} x {n}, one snapshot per "
            "column) and pass that as SOURCE."
        )


def _check_resume(args: Any, sc: Any, record: Any) -> None:
    """Refuse to continue ``sc`` with the options and SOURCE of this command line if they differ."""
    from streamsvd.cli.policy import check_resume

    _check_orientation(record, sc.n, f"the basis in STORE {args.store}")
    given = {name: value for name, value in vars(args).items() if value is not None}
    if given.get("sweeps") == CONVERGE:
        given["sweeps"] = None
    check_resume(sc, record, given=given, source_changed_ok=args.source_changed_ok,
                 store=args.store)
