"""The tree's graph and its tasks: leaves, pairwise merges, committed nodes loaded.

:func:`run_tree` builds the graph of :func:`~streamsvd.parallel.tree.tree_compress` (its
shape depends on the columns, ``start``, ``block`` and the leaves' width only) and
computes it; the tasks run on the workers (see :mod:`streamsvd.parallel.tree` for the
algorithm and :mod:`streamsvd.parallel.checkpoints` for the nodes a run commits).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable
from typing import Any, Optional, cast

from threadpoolctl import threadpool_limits

from streamsvd._util.scheduling import execute
from streamsvd.algebra.memory import MemoryBackend
from streamsvd.errors import BrokenStateError
from streamsvd.linalg.rotations import load_kernels_in_background
from streamsvd.parallel.checkpoints import Checkpoints
from streamsvd.parallel.spec import (
    _NODE_CHANGES,
    SourceSpec,
    _node_options,
    default_leaf_columns,
    leaf_ranges,
)
from streamsvd.parallel.workers import blas_here, blas_plan, worker_threads
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest

__all__ = ["begin", "node_graph", "run_tree"]

logger = logging.getLogger(__name__)

_Node = tuple[str, int, int, Optional["_Node"], Optional["_Node"]]
"""``(kind, first column, stop column, left, right)`` of a leaf or a merge."""


# ---------------------------------------------------------------------------- tasks


def _compress_leaf(
    spec: SourceSpec,
    start: int,
    stop: int,
    block: int,
    options: dict[str, Any],
    blas_threads: int | dict[str, int],
    checkpoints: Checkpoints | None = None,
    in_place: bool = True,
) -> StreamCompressor:
    """Compress columns ``start:stop`` of the source (runs on a worker).

    The leaf compacts in place (one ``n x k`` buffer less); should an update leave its
    basis broken (:class:`~streamsvd.errors.BrokenStateError`), the leaf is compressed
    again with compactions written aside (``in_place=False``). With ``checkpoints`` the
    finished leaf is committed there.
    """
    sc = StreamCompressor(spec.n, backend=MemoryBackend(compact_in_place=in_place), **options)
    try:
        with threadpool_limits(limits=blas_here(blas_threads), user_api="blas"), \
                spec.open() as src:
            # the other leaves keep the cores busy: no read-ahead, one block per leaf; the
            # root is finalised by the caller, maybe in another process: no kernels here
            ingest(src, sc, start=start, stop=stop, block=block, prefetch=False,
                   preload_sweeps=False)
    except BrokenStateError:
        if not in_place:
            raise
        logger.warning("leaf %d:%d compressed again, compacting aside", start, stop)
        return _compress_leaf(spec, start, stop, block, options, blas_threads, checkpoints,
                              False)
    if checkpoints is not None:
        checkpoints.save(f"leaf-{start}-{stop}", sc)
    sc._drop_scratch()  # it waits for its merge: its compaction buffer is not needed
    logger.info("leaf %d:%d compressed to rank %d (bound %.3e)", start, stop, sc.rank,
                sc.error_bound)
    return sc


def _merge_pair(
    left: StreamCompressor, right: StreamCompressor, blas_threads: int | dict[str, int],
    preload_sweeps: bool = False, checkpoints: Checkpoints | None = None, name: str = "",
) -> StreamCompressor:
    """Return a new compressor: ``left`` with ``right``'s columns appended (on a worker).

    Neither input is modified (a task's inputs may be shared with the threaded scheduler
    or re-used when a task is retried after a crash), so a merge that fails or is re-run
    starts again from the same inputs: the copy compacts in place, and is made again
    compacting aside should the merge leave it broken. With ``preload_sweeps`` (the root's
    merge, run in the caller's process) the compiled sweep kernels that the root's
    ``finalize`` needs load in the background meanwhile, on the core the leaves left.
    With ``checkpoints`` the merge is committed there as ``name``.
    """
    if preload_sweeps:
        load_kernels_in_background()
    with threadpool_limits(limits=blas_here(blas_threads), user_api="blas"):
        try:
            out = left._copy_with(backend=MemoryBackend(compact_in_place=True))
            out.merge(right, spend_target=False)
        except BrokenStateError:
            logger.warning("merge up to column %d made again, compacting aside",
                           right.source_offset)
            out = left._copy_with(backend=MemoryBackend())
            out.merge(right, spend_target=False)
    if checkpoints is not None:
        checkpoints.save(name, out)
    out._drop_scratch()
    logger.info("merged columns up to %d: rank %d (bound %.3e)", out.source_offset,
                out.rank, out.error_bound)
    return out


def _load_node(checkpoints: Checkpoints, name: str) -> StreamCompressor:
    """Return the committed node ``name`` (on a worker): nothing below it is recomputed."""
    sc = checkpoints.load(name)
    logger.info("%s loaded from %s: rank %d (bound %.3e)", name, checkpoints.root.url,
                sc.rank, sc.error_bound)
    return sc


# ----------------------------------------------------------------------------- graph


def begin(checkpoints: Checkpoints | None, *, start: int, stop: int, block: int,
          width: int, options: dict[str, Any], refuse: bool = False, **plan: Any
          ) -> frozenset[str]:
    """Record a tree's plan in ``checkpoints``; return the nodes committed (none without).

    The plan is what the tree's nodes depend on: its columns, ``block``, the leaves'
    width, the nodes' options (by :meth:`Checkpoints.fingerprint`) and ``plan``'s other
    entries. Checkpoints of another plan are replaced, or with ``refuse`` refused
    (:meth:`Checkpoints.start`).
    """
    if checkpoints is None:
        return frozenset()
    checkpoints.plan.update(start=start, stop=stop, block=block, width=width,
                            options=Checkpoints.fingerprint(options), **plan)
    return checkpoints.start(refuse=refuse)


def node_graph(
    ranges: list[tuple[int, int]],
    done: frozenset[str],
    key: str,
    *,
    leaf: Callable[[int, int, str, str], Any],
    merge: Callable[[Any, Any, str, str, bool], Any],
    load: Callable[[str, str], Any],
) -> tuple[Any, int]:
    """Return a tree's graph over the leaves ``ranges`` (its root task) and its levels.

    The shape, bottom up: the leaves, then pairs left to right (an odd one moves up).
    The graph is built top down: a node in ``done`` (committed) is ``load(name, key)``
    and nothing below it is in the graph; else ``leaf(a, b, name, key)`` or
    ``merge(left, right, name, key, is_root)``. ``name`` is ``leaf-a-b`` or
    ``merge-a-b`` (the node's checkpoint), ``key`` is ``key`` formatted with it.
    """
    nodes: list[_Node] = [("leaf", a, b, None, None) for a, b in ranges]
    level = 0
    while len(nodes) > 1:
        level += 1
        merged: list[_Node] = [("merge", nodes[i][1], nodes[i + 1][2], nodes[i], nodes[i + 1])
                               for i in range(0, len(nodes) - 1, 2)]
        nodes = merged + nodes[len(merged) * 2:]

    def task(node: _Node, root: bool) -> Any:
        kind, a, b, left, right = node
        name = f"{kind}-{a}-{b}"
        if name in done:
            return load(name, key.format(name))
        if left is None or right is None:
            return leaf(a, b, name, key.format(name))
        return merge(task(left, False), task(right, False), name, key.format(name), root)

    return task(nodes[0], True), level


def run_tree(
    spec: SourceSpec,
    start: int,
    block: int,
    leaf_columns: int | None,
    opts: dict[str, Any],
    client: Any,
    progress: bool,
    checkpoints: Checkpoints | None = None,
) -> StreamCompressor | None:
    """Compute the tree over columns ``start:`` of ``spec``; return its root (None if empty).

    With ``checkpoints``, nodes committed by an earlier run of the same plan are loaded
    and nothing below them runs; every node computed is committed.
    """
    import dask

    stop = spec.m
    if start >= stop:
        logger.info("nothing to compress: the source offset %d is the end of %s", start,
                    spec.description)
        return None
    width = (leaf_columns if leaf_columns is not None else
             default_leaf_columns(stop - start, block, tasks=worker_threads(client)))
    ranges = leaf_ranges(start, stop, width)
    tag = uuid.uuid4().hex[:12]
    blas = blas_plan(client)
    node_opts = opts if len(ranges) == 1 else _node_options(opts, columns=stop)
    done = begin(checkpoints, start=start, stop=stop, block=block, width=width,
                 options=node_opts)

    def leaf(a: int, b: int, name: str, key: str) -> Any:
        return dask.delayed(_compress_leaf, pure=False)(
            spec.window(a, b), a, b, block, node_opts, blas, checkpoints, dask_key_name=key)

    def merge(left: Any, right: Any, name: str, key: str, root: bool) -> Any:
        return dask.delayed(_merge_pair, pure=False)(
            left, right, blas, root and client is None, checkpoints, name,
            dask_key_name=key)

    def load(name: str, key: str) -> Any:
        return dask.delayed(_load_node, pure=False)(checkpoints, name, dask_key_name=key)

    graph, level = node_graph(ranges, done, f"streamsvd-{{}}-{tag}", leaf=leaf, merge=merge,
                              load=load)
    logger.info(
        "tree of %d leaves of %d columns (%d levels) over columns %d:%d of %s on %s",
        len(ranges), width, level, start, stop, spec.description,
        "the threaded scheduler" if client is None else client,
    )
    (root,) = execute([graph], client=client, progress=progress)
    # the user's copy compacts aside again: an interrupted update leaves it as it was
    return cast(StreamCompressor, root)._copy_with(
        backend=MemoryBackend(), **{name: opts[name] for name in _NODE_CHANGES})
