"""The one ingest driver: read a source block by block and absorb every block.

:func:`ingest` is the loop that the command line (``streamsvd ingest``), the tall mode
(:func:`streamsvd.parallel.tall_compress`), the leaves of the tree mode
(:func:`streamsvd.parallel.tree_compress`) and :meth:`streamsvd.StreamingSVD.fit` run:
the blocks come from the source's prefetching reader
(:meth:`streamsvd.io.sources.Source.blocks`, a background thread reading ahead through a
bounded queue, each block read once), and each is handed to ``compressor.absorb`` with
the source offset just after it, so that a store records where to resume.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from typing import Any

from streamsvd.errors import FloatRangeError
from streamsvd.io.sources import Source
from streamsvd.linalg.rotations import load_kernels_in_background

__all__ = ["IngestResult", "ingest"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class IngestResult:
    """What :func:`ingest` did.

    Attributes
    ----------
    start, stop : int
        The columns absorbed, ``start:stop``.
    blocks : int
        Number of updates (blocks absorbed).
    seconds : float
        Wall time of the loop.
    waiting : float
        Part of it spent waiting for the reader (0 when every read was hidden behind
        the updates).
    """

    start: int
    stop: int
    blocks: int
    seconds: float
    waiting: float


def ingest(
    source: Source,
    compressor: Any,
    *,
    start: int | None = None,
    stop: int | None = None,
    block: int = 100,
    depth: int = 1,
    prefetch: bool = True,
    min_last: int = 0,
    rows: int | None = None,
    progress: bool = False,
    desc: str = "ingest",
    preload_sweeps: bool = True,
) -> IngestResult:
    """Absorb columns ``start:stop`` of ``source`` into ``compressor``, block by block.

    The compiled kernels of the final sweeps load in the background
    (:func:`streamsvd.linalg.rotations.load_kernels_in_background`) while the last block is
    absorbed, once every read is done and the reader's core is free, unless
    ``preload_sweeps`` is False (with ``rows``, where the updates read their blocks, from
    the start). Beside the first reads, the load delayed them: ``streamsvd ingest`` of a
    200000 x 500 array in blocks of 100 started its updates later and waited longer for
    its second block (``bench/studies/tight-targets.md``, "Latest for ingest").

    Parameters
    ----------
    source : Source
        The snapshots (see :func:`streamsvd.io.open.open_source`).
    compressor : StreamCompressor or TallCompressor
        Anything with ``absorb(X, source_offset=...)`` and ``source_offset``.
    start : int, optional
        First column; default ``compressor.source_offset`` (where the store resumes).
    stop : int, optional
        End of the range; default ``source.m``.
    block : int
        Columns per update.
    depth : int
        Blocks the reader keeps ahead of the update (at most ``depth + 1`` blocks in
        memory).
    prefetch : bool
        Read ahead in a background thread (False: each block is read when the previous
        one is absorbed, one block in memory; for callers that keep the cores busy
        otherwise, such as the leaves of a tree).
    min_last : int
        A last block shorter than this joins the one before it (:meth:`Source.blocks
        <streamsvd.io.sources.Source.blocks>`).
    rows : int, optional
        Hand each block to the compressor unread, as a
        :class:`~streamsvd.algebra.panels.lazy.LazyBlock` of chunks of this many rows (the
        tall mode, whose update reads it chunk by chunk); ``depth`` then does not apply, and a
        compressor with an ``expect`` method is given each block one update ahead
        (:meth:`TallCompressor.expect <streamsvd.parallel.TallCompressor.expect>`).
    progress : bool
        Show a progress bar over the columns (tqdm, on stderr) with the rank and the
        error bound.
    desc : str
        The progress bar's label.
    preload_sweeps : bool
        Load the sweep kernels while the last block is absorbed (0.2-0.4 s once per
        process, and 46 MB): for a caller that finalises in this process.

    Returns
    -------
    IngestResult

    Raises
    ------
    SourceError, NonFiniteError, FloatRangeError
        A block cannot be read, holds NaN or infinite entries, or would take the
        expansion's norm beyond the float64 range; every block before it was absorbed
        (and committed as the compressor's ``commit_every`` says).
    """
    first = int(compressor.source_offset if start is None else start)
    last = source.m if stop is None else int(stop)
    t0 = time.perf_counter()
    waiting = 0.0
    count = 0
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=last, initial=first, unit="col", dynamic_ncols=True, desc=desc,
                   file=sys.stderr)
    blocks = source.blocks(block, start=first, stop=last, depth=depth, min_last=min_last,
                           rows=rows, prefetch=prefetch)
    if preload_sweeps and rows is not None:  # lazy blocks are read inside their updates
        load_kernels_in_background()
    # unread blocks are named one update ahead to a compressor that reads them sooner
    expect = getattr(compressor, "expect", None) if rows is not None else None
    following = None
    try:
        while True:
            t = time.perf_counter()
            item = following if following is not None else next(blocks, None)
            if item is not None and expect is not None:
                following = next(blocks, None)
                if following is not None:
                    expect(following[1])
            waiting += time.perf_counter() - t
            if item is None:
                break
            offset, X = item
            if preload_sweeps and offset + X.shape[1] >= last:
                load_kernels_in_background()  # the reads are over: their core loads them
            try:
                rec = compressor.absorb(X, source_offset=offset + X.shape[1])
            except FloatRangeError as exc:
                raise exc.naming(f"`source` (its columns {offset}:{offset + X.shape[1]})"
                                 ) from exc
            count += 1
            if bar is not None:  # the postfix first: the redraw shows this update
                bar.set_postfix(rank=rec.rank, bound=f"{rec.error_bound:.2e}", refresh=False)
                bar.update(X.shape[1])
            del X, item
    finally:
        blocks.close()  # stops the reader thread now, also on an error
        if bar is not None:
            bar.close()
    result = IngestResult(first, last, count, time.perf_counter() - t0, waiting)
    logger.info("absorbed columns %d:%d of %s in %d blocks, %.2f s (%.2f s waiting for "
                "reads)", first, last, source.description, count, result.seconds, waiting)
    return result
