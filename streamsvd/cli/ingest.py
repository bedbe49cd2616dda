"""``streamsvd ingest``: absorb the columns of SOURCE into STORE, in one of three modes.

The command line becomes one :class:`~streamsvd.cli.plan.IngestPlan` (SOURCE opened
once, STORE's policy asked once), which the one ingest driver runs: in memory,
:func:`streamsvd.stream.ingest.ingest` here, over the SOURCE the plan was made from; on
dask, :func:`streamsvd.parallel.cluster.ingest`, whose workers read SOURCE themselves.
What is done with an existing STORE (create, continue, refuse, undo a failed start) is
:mod:`streamsvd.cli.policy`'s.

Only the standard library is imported at module level (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import contextlib
import json
import sys
from typing import TYPE_CHECKING, Any

from streamsvd.cli.plan import IngestPlan, check_orientation, plan_ingest
from streamsvd.cli.reading import open_readonly
from streamsvd.errors import NonFiniteError, StoreError, StoreMismatchError

if TYPE_CHECKING:  # the sources import numpy: only for the annotations
    from streamsvd.io.sources import Source

__all__ = ["run"]


def run(args: Any) -> int:
    """Run ``streamsvd ingest``; print the JSON summary unless ``--quiet``."""
    from streamsvd._util.malloc import keep_freed_memory
    from streamsvd.cli.policy import removed_on_failure
    from streamsvd.io.open import open_source

    keep_freed_memory()
    with contextlib.ExitStack() as opened:
        source = opened.enter_context(open_source(args.source, dataset=args.dataset))
        plan = plan_ingest(args, source)
        if plan.mode != "memory":
            opened.close()  # the dask modes read SOURCE on their workers
        elif not plan.resume:  # the first block is read while the update step is imported
            source.read_early(0, min(plan.block, source.m))
        with removed_on_failure(plan.store, new=not plan.resume):
            try:
                summary = (_ingest_memory(plan, source) if plan.mode == "memory"
                           else _ingest_dask(plan))
            except StoreMismatchError:
                if plan.resume:
                    _check_store_kind(plan)
                raise
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


def _ingest_memory(plan: IngestPlan, source: Source) -> dict[str, Any]:
    from streamsvd.stream.compressor import StreamCompressor
    from streamsvd.stream.ingest import ingest
    from streamsvd.stream.summary import summary_of

    if plan.resume:
        sc = StreamCompressor.open(plan.store, **plan.options)
    else:
        sc = StreamCompressor(source.n, store=plan.store, source_record=plan.record,
                              **plan.options)
    sc.threads = plan.threads
    try:
        if plan.resume:
            _check_resume(plan, sc)
        ingest(source, sc, block=plan.block, progress=plan.progress)
        if plan.finalize and not sc.finalized:
            sc.finalize(progress=plan.progress)
        return summary_of(sc)
    finally:
        sc.close(finalize=False)


def _ingest_dask(plan: IngestPlan) -> dict[str, Any]:
    from streamsvd.parallel.cluster import ingest as ingest_on_dask

    if plan.resume:  # the engine takes no option with resume: check here
        with open_readonly(plan.store, inner=plan.options.get("inner")) as sc:
            _check_resume(plan, sc)
    # dask's progress bars (ProgressBar, distributed.progress) write to stdout, which
    # belongs to the command's output: send whatever the engine prints to stderr
    try:
        with contextlib.redirect_stdout(sys.stderr):
            return ingest_on_dask(
                plan.source, plan.store, dataset=plan.dataset, block=plan.block,
                tall=plan.mode == "tall", resume=plan.resume, progress=plan.progress,
                finalize=plan.finalize, **plan.dask, **plan.options,
            )
    except NonFiniteError:
        if plan.mode == "tall":  # row chunks are read in parallel: the first may not be named
            _locate_non_finite(plan)
        raise


def _locate_non_finite(plan: IngestPlan) -> None:
    """Re-read the source after the last commit; raise its error naming the bad entry.

    Every block before the store's recorded source offset was absorbed, so the first
    NaN or infinite entry after it is the one the tall update refused. Returns without
    raising when it finds none (the caller re-raises the update's error).
    """
    from streamsvd.io.open import open_source
    from streamsvd.parallel.cluster import open_compressor

    try:
        with open_compressor(plan.store, mode="r") as sc:
            start = sc.source_offset
    except (StoreError, ValueError):
        start = 0
    with open_source(plan.source, dataset=plan.dataset) as src:
        for _ in src.blocks(block=plan.block, start=min(start, src.m)):
            pass  # Source checks every block it reads and raises NonFiniteError


def _check_store_kind(plan: IngestPlan) -> None:
    """Raise a command-line error when STORE was written in the other mode."""
    from streamsvd.parallel.cluster import TallCompressor, compressor_class, stored_kind

    tall = plan.mode == "tall"
    try:
        cls = compressor_class(stored_kind(plan.store))
    except (StoreError, ValueError):
        return
    if cls is None or tall == (cls is TallCompressor):
        return
    if tall:
        raise StoreMismatchError(
            f"STORE {plan.store} was written without --tall (in memory or by a tree); "
            "resume it without --tall."
        )
    raise StoreMismatchError(
        f"STORE {plan.store} was written with --tall; resume it with --tall.")


def _check_resume(plan: IngestPlan, sc: Any) -> None:
    """Refuse to continue ``sc`` with the options and SOURCE of this command line if they differ."""
    from streamsvd.cli.policy import check_resume

    check_orientation(plan.record, sc.n, f"the basis in STORE {plan.store}")
    check_resume(sc, plan.record, given=plan.given, source_changed_ok=plan.source_changed_ok,
                 store=plan.store)
