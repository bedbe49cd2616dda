"""The plan of ``streamsvd ingest``, decided once from its command line.

:func:`plan_ingest` checks the options against each other and against SOURCE (opened
once by the caller), asks :mod:`streamsvd.cli.policy` once what to do with STORE, and
returns an :class:`IngestPlan`: the mode, the store, whether it is continued, the
compressor options with the command's defaults, the block width and SOURCE's record.
:mod:`streamsvd.cli.ingest` runs the plan and nothing on the command line is read again.

Only the standard library is imported at module level (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from streamsvd.cli.parsing import (
    DEFAULT_BLOCK,
    DEFAULT_OVERSAMPLING,
    DEFAULT_RULE,
    DEFAULT_SWEEPS,
    diagonal_as_weights,
    load_inner,
)
from streamsvd.cli.types import CONVERGE, DEFAULT_COMMIT_EVERY
from streamsvd.errors import InputError, ShapeMismatchError, SourceError

if TYPE_CHECKING:  # these modules import numpy and zarr: only for the annotations
    from streamsvd.io.provenance import SourceRecord
    from streamsvd.io.sources import Source
    from streamsvd.storage import Storage

__all__ = ["IngestPlan", "check_orientation", "plan_ingest"]

Mode = Literal["memory", "tree", "tall"]


@dataclass(frozen=True)
class IngestPlan:
    """What one ``streamsvd ingest`` does.

    Attributes
    ----------
    mode : {"memory", "tree", "tall"}
        In memory (default), a tree of leaves on dask (``--scheduler``) or the tall
        mode (``--tall``).
    store : Storage
        Where STORE lives.
    resume : bool
        Whether STORE holds a store that the command continues.
    options : Mapping
        The compressor options: those of a new store with the command's defaults, or
        only ``inner`` to continue one.
    block : int
        Columns per update (``--block``).
    record : SourceRecord
        SOURCE's path, dataset, shape and description.
    finalize : bool
        Whether the command ends with the final sweeps (``--final-sweeps``).
    progress : bool
        Whether progress is shown on stderr (not ``--quiet``).
    source, dataset : str
        SOURCE and ``--dataset``, as the readers open them (the dask modes open SOURCE
        again on their workers).
    threads : int or None
        BLAS threads of the in-memory mode (``--threads``; None: all cores).
    dask : Mapping
        ``scheduler``, ``workers``, ``leaf_columns`` and ``chunk_rows`` of the dask modes.
    given : Mapping
        The options given on the command line, which a continued STORE must match.
    source_changed_ok : bool
        Continue STORE from a SOURCE that differs from its record
        (``--source-changed-ok``).
    """

    mode: Mode
    store: Storage
    resume: bool
    options: Mapping[str, Any]
    block: int
    record: SourceRecord
    finalize: bool
    progress: bool
    source: str
    dataset: str | None
    threads: int | None
    dask: Mapping[str, Any]
    given: Mapping[str, Any]
    source_changed_ok: bool


def plan_ingest(args: Any, source: Source) -> IngestPlan:
    """Check the command line of ``streamsvd ingest`` once and return its plan.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line (STORE already located as a storage).
    source : Source
        SOURCE, opened once by the caller.

    Raises
    ------
    InputError
        An option of another mode, or options that contradict each other.
    SourceError, ShapeMismatchError
        SOURCE holds empty snapshots, or looks saved with one snapshot per row.
    StoreError
        STORE exists and ``--resume`` was not given.
    """
    from streamsvd.cli.policy import resuming

    mode = _mode(args)
    _check_mode_options(args, mode)
    resume = resuming(args.store, resume=args.resume)
    if args.oversampling is not None and args.max_rank is None and not resume:
        raise InputError(
            "--oversampling adds terms to --max-rank while streaming; add --max-rank K, or "
            "drop --oversampling."
        )
    inner = load_inner(args)
    if mode == "tall":
        inner = _tall_inner(inner, args.inner)
    record = _source_record(args, source)
    if inner is not None and inner.n is not None:
        check_orientation(record, inner.n, "--inner")
    return IngestPlan(
        mode=mode, store=args.store, resume=resume,
        options=_compressor_options(args, mode, resume=resume, inner=inner),
        block=args.block or DEFAULT_BLOCK, record=record,
        finalize=args.final_sweeps in (None, CONVERGE), progress=not args.quiet,
        source=args.source, dataset=args.dataset,
        threads={None: 1, "all": None}.get(args.threads, args.threads),
        dask={"scheduler": args.scheduler, "workers": args.workers,
              "leaf_columns": args.leaf_columns, "chunk_rows": args.chunk_rows},
        given=_given(args), source_changed_ok=args.source_changed_ok,
    )


def _given(args: Any) -> dict[str, Any]:
    """Return the options given on the command line (``--sweeps converge`` as None)."""
    given = {name: value for name, value in vars(args).items() if value is not None}
    if given.get("sweeps") == CONVERGE:
        given["sweeps"] = None
    return given


def _mode(args: Any) -> Mode:
    if args.tall:
        return "tall"
    return "tree" if args.scheduler is not None else "memory"


def _check_mode_options(args: Any, mode: Mode) -> None:
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
    for given, flag, cannot in (
        (args.window, "--window", "drop or weight the oldest snapshots"),
        (args.forget, "--forget", "drop or weight the oldest snapshots"),
        (args.dynamics, "--dynamics", "record trajectories (a tree store keeps its right "
         "vectors in order, which `streamsvd dmd STORE` reads without it)"),
    ):
        if given is not None and mode == "tree":
            raise InputError(
                f"{flag} applies to the in-memory and tall modes only; the tree mode "
                f"(--scheduler without --tall) compresses its leaves apart and cannot "
                f"{cannot}. Drop {flag}, or drop --scheduler (or add --tall)."
            )
    if args.commit_every is not None and mode == "tree":
        raise InputError(
            "--commit-every does not apply to the tree mode (--scheduler without --tall), "
            "which commits STORE once, when the tree is merged; drop it, or add --tall."
        )


def _compressor_options(args: Any, mode: Mode, *, resume: bool, inner: Any
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
    if args.dynamics:
        options["dynamics"] = True
    if mode != "tree":
        options["commit_every"] = args.commit_every or DEFAULT_COMMIT_EVERY
    return options


def _source_record(args: Any, src: Source) -> SourceRecord:
    """Check the opened SOURCE and return its record."""
    from streamsvd.io.provenance import SourceRecord

    source, dataset = getattr(args, "source_given", (args.source, args.dataset))
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


def check_orientation(record: Any, size: int, what: str) -> None:
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
