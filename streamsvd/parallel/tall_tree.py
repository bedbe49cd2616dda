"""A tree whose leaves are tall compressors: tall data, parallel across blocks.

:func:`tall_tree_compress` cuts the columns into leaves as :func:`tree_compress` does,
but each leaf is a :class:`~streamsvd.parallel.tall.TallCompressor` run inside one dask
task: its basis lives in row panels under ``workdir`` (a prefix every worker reaches,
``s3://...`` on a cluster), and the row-chunk products of its updates run on the task's
own worker (the threaded scheduler there), so a worker holds a few row chunks, the
small matrices and one block's row chunk at a time, independent of ``n``. The leaves run
in parallel; the merges (:meth:`~streamsvd.StreamCompressor.merge`, pairwise, left then
right) read both operands' panels from ``workdir`` (the right operand's left vectors by
row chunks, in the merge's pass: no ``n``-sized array on the merging worker) and write
the merged basis there. The root comes back to the client as its small matrices and the
names of its panels; its panels are copied into ``store`` (one commit) or left in
``workdir``, and that copy and ``finalize`` run on the cluster, not in the client.

What it does not do (yet): checkpoints (a killed run starts again), resuming a store.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any, cast

from threadpoolctl import threadpool_limits

from streamsvd._util.scheduling import check_client, execute
from streamsvd._util.validation import check_positive_int
from streamsvd.errors import InputError
from streamsvd.io.provenance import SourceRecord
from streamsvd.parallel.checkpoints import child_storage
from streamsvd.parallel.spec import (
    SourceSpec,
    _node_options,
    check_options,
    default_leaf_columns,
    leaf_ranges,
)
from streamsvd.parallel.tall import TallCompressor
from streamsvd.parallel.workers import (
    blas_here,
    blas_plan,
    check_workers_see,
    source_places,
    worker_threads,
)
from streamsvd.storage import open_storage
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest

__all__ = ["tall_tree_compress"]

logger = logging.getLogger(__name__)


def _tall_leaf(spec: SourceSpec, start: int, stop: int, block: int, chunk_rows: int,
               options: dict[str, Any], place: Any, blas: int | dict[str, int]
               ) -> StreamCompressor:
    """Compress columns ``start:stop`` into panels at ``place`` (on a worker)."""
    tc = TallCompressor(spec.n, workdir=place, chunk_rows=chunk_rows, **options)
    with threadpool_limits(limits=blas_here(blas), user_api="blas"), spec.open() as src:
        ingest(src, tc, start=start, stop=stop, block=block, rows=chunk_rows,
               prefetch=False, preload_sweeps=False)
    logger.info("tall leaf %d:%d: rank %d (bound %.3e)", start, stop, tc.rank,
                tc.error_bound)
    return tc


def _tall_merge(left: StreamCompressor, right: StreamCompressor,
                blas: int | dict[str, int]) -> StreamCompressor:
    """Append ``right``'s columns to ``left`` (on a worker); ``left`` is the result."""
    with threadpool_limits(limits=blas_here(blas), user_api="blas"):
        left.merge(right, spend_target=False)
    return left


def tall_tree_compress(
    source: Any,
    *,
    workdir: Any,
    block: int = 100,
    leaf_columns: int | None = None,
    chunk_rows: int = 16384,
    dataset: str | None = None,
    client: Any = None,
    store: Any = None,
    finalize: bool = False,
    storage_options: dict[str, Any] | None = None,
    **options: Any,
) -> StreamCompressor:
    """Compress tall snapshots by a tree of tall leaves (see the module docstring).

    Parameters
    ----------
    source, block, leaf_columns, dataset, client, finalize
        As for :func:`~streamsvd.parallel.tree.tree_compress`.
    workdir : str or path-like
        Where every leaf and merge keeps its panels: a prefix every worker reaches
        (``s3://bucket/scratch`` on a cluster; a local directory with the threaded
        scheduler). Not removed: the panels of the root are there without ``store``.
    chunk_rows : int
        Rows per chunk of the panels.
    store : str or path-like, optional
        A new store that receives the root (its panels copied, one commit).
    storage_options : dict, optional
        Options of the object store of a URL ``workdir`` or ``store``.
    **options
        Compressor options (``inner`` Euclidean or diagonal, ``eps``, ``max_rank``, ...).

    Returns
    -------
    StreamCompressor
        A tall compressor (its panels in ``workdir``, or in ``store``).

    Notes
    -----
    The root keeps the options of the tree's nodes (twice the oversampling, an absolute
    target spent as a mean-l2 one: :func:`~streamsvd.parallel.spec._node_options`);
    ``finalize`` cuts to ``max_rank`` all the same. A merge appends to its left operand
    in place (a retried merge task would see it merged already).
    """
    client = check_client(client)
    block = cast(int, check_positive_int(block, "block"))
    chunk_rows = cast(int, check_positive_int(chunk_rows, "chunk_rows"))
    if workdir is None:
        raise InputError("`workdir` must be a directory or URL every worker reaches; got "
                         "None. Pass workdir='s3://bucket/scratch' on a cluster.")
    spec = SourceSpec.of(source, dataset=dataset)
    opts = check_options(options, spec.n)
    root_dir = open_storage(workdir, storage_options=storage_options, argument="workdir")
    root_dir.prepare()
    check_workers_see(client, paths=source_places(spec)["paths"],
                      storages=[*source_places(spec)["storages"], ("`workdir`", root_dir)])
    width = (leaf_columns if leaf_columns is not None else
             default_leaf_columns(spec.m, block, tasks=worker_threads(client)))
    ranges = leaf_ranges(0, spec.m, width)
    node_opts = opts if len(ranges) == 1 else _node_options(opts, columns=spec.m)
    blas = blas_plan(client)
    tag = uuid.uuid4().hex[:12]
    import dask

    nodes = [dask.delayed(_tall_leaf, pure=False)(
        spec.window(a, b), a, b, block, chunk_rows, node_opts,
        child_storage(root_dir, f"{tag}/leaf-{a}-{b}"), blas,
        dask_key_name=f"streamsvd-tall-leaf-{a}-{b}-{tag}") for a, b in ranges]
    while len(nodes) > 1:
        merged = [dask.delayed(_tall_merge, pure=False)(nodes[i], nodes[i + 1], blas)
                  for i in range(0, len(nodes) - 1, 2)]
        nodes = merged + nodes[len(merged) * 2:]
    (root,) = execute(nodes, client=client)
    root = cast(StreamCompressor, root)  # with the nodes' options (see the notes)
    if client is not None:  # its copy into `store` and its finalisation run on the workers
        root._life.backend.use_client(root._life.state.basis, client)  # type: ignore[attr-defined]
    root.source_record = SourceRecord.of(source, dataset=dataset, shape=(spec.n, spec.m),
                                         description=spec.description)
    if store is not None:
        root.save(open_storage(store, storage_options=storage_options, argument="store"))
    if finalize and not root.finalized:
        root.finalize()
    return root
