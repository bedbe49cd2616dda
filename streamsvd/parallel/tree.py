"""Tree compression on dask: column ranges compressed on workers, merged pairwise.

The columns of a source are split into *leaves* of ``leaf_columns`` columns. Each leaf is
compressed by its own :class:`~streamsvd.StreamCompressor` in one dask task, which opens
the source where it runs and reads its own column range one block at a time (so the
data never travels through the scheduler, and a block is never read twice). The leaves
are then merged pairwise in a balanced binary tree, left then right, with
:meth:`StreamCompressor.merge`, which appends the right operand's columns after the left
one's and composes the error bounds. This is the hierarchical approximate POD (HAPOD) of
Himpe, Leibner and Rave (2018), as pyMOR distributes it.

Determinism. The tree depends only on the number of columns, ``start``, ``block`` and
``leaf_columns``, never on the scheduler or on the number of workers; every task is a
deterministic function of its inputs. The result is therefore the same with the threaded
scheduler, on a :class:`distributed.LocalCluster` or on a remote cluster, up to the
rounding differences of the BLAS (a worker process may use a different number of BLAS
threads than the client process).

Error bound. Leaves cover disjoint columns, so when a merge appends the right operand
``B ~ K_B`` to the left one ``A ~ K_A``, the errors ``E_A`` and ``E_B`` occupy disjoint
columns and ``||[E_A, E_B]||_F^2 = ||E_A||^2 + ||E_B||^2``; the merge's own truncation
and rejection then enter through the recursion of the
:class:`~streamsvd.StreamCompressor` notes. The root's :attr:`error_bound` is a
guaranteed bound on ``||A - U V^T||_F`` over every column compressed.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any, cast

from threadpoolctl import threadpool_limits

from streamsvd._util.malloc import keep_freed_memory
from streamsvd._util.scheduling import blas_threads_per_task, check_client, execute
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.memory import MemoryBackend
from streamsvd.errors import BrokenStateError, InputError, ShapeMismatchError, StoreError
from streamsvd.io.provenance import SourceRecord
from streamsvd.linalg.rotations import load_kernels_in_background
from streamsvd.parallel.spec import (
    _NODE_CHANGES,
    SourceSpec,
    _node_options,
    check_options,
    default_leaf_columns,
    leaf_ranges,
    options_of,
)
from streamsvd.storage import open_storage
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest
from streamsvd.stream.options import TREE_OPTIONS as COMPRESSOR_OPTIONS

__all__ = ["COMPRESSOR_OPTIONS", "tree_compress"]

logger = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- tasks


def _compress_leaf(
    spec: SourceSpec,
    start: int,
    stop: int,
    block: int,
    options: dict[str, Any],
    blas_threads: int,
    in_place: bool = True,
) -> StreamCompressor:
    """Compress columns ``start:stop`` of the source (runs on a worker).

    The leaf compacts in place (one ``n x k`` buffer less); should an update leave its
    basis broken (:class:`~streamsvd.errors.BrokenStateError`), the leaf is compressed
    again with compactions written aside (``in_place=False``).
    """
    sc = StreamCompressor(spec.n, backend=MemoryBackend(compact_in_place=in_place), **options)
    try:
        with threadpool_limits(limits=blas_threads, user_api="blas"), spec.open() as src:
            # the other leaves keep the cores busy: no read-ahead, one block per leaf; the
            # root is finalised by the caller, maybe in another process: no kernels here
            ingest(src, sc, start=start, stop=stop, block=block, prefetch=False,
                   preload_sweeps=False)
    except BrokenStateError:
        if not in_place:
            raise
        logger.warning("leaf %d:%d compressed again, compacting aside", start, stop)
        return _compress_leaf(spec, start, stop, block, options, blas_threads, False)
    sc._drop_scratch()  # it waits for its merge: its compaction buffer is not needed
    logger.info("leaf %d:%d compressed to rank %d (bound %.3e)", start, stop, sc.rank,
                sc.error_bound)
    return sc


def _merge_pair(
    left: StreamCompressor, right: StreamCompressor, blas_threads: int,
    preload_sweeps: bool = False,
) -> StreamCompressor:
    """Return a new compressor: ``left`` with ``right``'s columns appended (on a worker).

    Neither input is modified (a task's inputs may be shared with the threaded scheduler
    or re-used when a task is retried after a crash), so a merge that fails or is re-run
    starts again from the same inputs: the copy compacts in place, and is made again
    compacting aside should the merge leave it broken. With ``preload_sweeps`` (the root's
    merge, run in the caller's process) the compiled sweep kernels that the root's
    ``finalize`` needs load in the background meanwhile, on the core the leaves left.
    """
    if preload_sweeps:
        load_kernels_in_background()
    with threadpool_limits(limits=blas_threads, user_api="blas"):
        try:
            out = left._copy_with(backend=MemoryBackend(compact_in_place=True))
            out.merge(right, spend_target=False)
        except BrokenStateError:
            logger.warning("merge up to column %d made again, compacting aside",
                           right.source_offset)
            out = left._copy_with(backend=MemoryBackend())
            out.merge(right, spend_target=False)
    out._drop_scratch()
    logger.info("merged columns up to %d: rank %d (bound %.3e)", out.source_offset,
                out.rank, out.error_bound)
    return out


# ----------------------------------------------------------------------------- API


def tree_compress(
    source: Any,
    *,
    block: int = 100,
    leaf_columns: int | None = None,
    dataset: str | None = None,
    client: Any = None,
    store: Any = None,
    resume: bool = False,
    progress: bool = False,
    storage_options: dict[str, Any] | None = None,
    **options: Any,
) -> StreamCompressor:
    """Compress the columns of a source on dask: leaves on workers, merged in a tree.

    Parameters
    ----------
    source : array_like, str, os.PathLike, h5py.Dataset, zarr.Array or dask array
        An ``n x m`` snapshot matrix (columns are snapshots), as accepted by
        :func:`~streamsvd.io.open.open_source`. Each leaf reads its own columns, one block
        at a time, where it runs: paths are reopened by every task (on a cluster they must
        be visible to the workers), dask arrays are computed block by block.
    block : int
        Columns absorbed per update inside a leaf.
    leaf_columns : int, optional
        Columns per leaf; default ``10 * block`` (never fewer than ``block``). The result
        depends on it (each merge is an update with its own truncation), never on the
        scheduler or on the number of workers.
    dataset : str, optional
        Dataset of an HDF5 file or array of a zarr group (see ``open_source``).
    client : distributed.Client, optional
        Run on this cluster; the threaded scheduler of this process when omitted.
    store : str or path-like, optional
        Write the result to a basis store there. A new store is created only once the
        whole tree is computed, and the root is written into it as it is (one commit, no
        further update: the stored basis is the tree's). With ``resume=True``
        the store's compressor is reopened first (taking its writer lock), the columns
        from its recorded source offset on are compressed, and the root is merged into
        it (one commit). A failure anywhere before that commit leaves an existing store
        as it was. The source is recorded in the store
        (:attr:`~streamsvd.StreamCompressor.source_record`).
    resume : bool
        Continue the existing store at ``store`` (its options and inner product are
        used; ``inner``, if passed, is checked against the store's).
    progress : bool
        Show dask's progress bar.
    storage_options : dict, optional
        Options of the object store of a URL ``store``.
    **options
        Options of every :class:`~streamsvd.StreamCompressor` of the tree: ``inner``,
        ``eps``, ``rtol``, ``max_rank``, ``oversampling``, ``rule``, ``sweeps``,
        ``reject_tol``, ``reorth_tol``, ``target_error``, ``error_measure``,
        ``streaming_share``. Every level of the tree cuts to the rank cap, so its leaves
        and merges keep ``max_rank + 2 oversampling`` terms (on a spectrum decaying
        slowly through the cap the tree then cuts within 1e-5 of the optimal error,
        against 2e-4 with the compressor's own oversampling); the root is handed back
        with the compressor's options, and closing it (or
        :meth:`~streamsvd.StreamCompressor.finalize`) cuts to ``max_rank``.

    Returns
    -------
    StreamCompressor
        The compressor of every column (``source_offset = m``). With ``store`` it holds
        the store's writer lock: close it (or use it in a ``with`` block) when done; it
        can go on absorbing new snapshots.

    Raises
    ------
    InputError
        Bad options, ``client`` or sizes.
    StoreError
        ``store`` exists and ``resume`` is false, or cannot be continued.
    SourceError
        A read failed on a worker (the store is then unchanged).

    Notes
    -----
    Cost. With ``L`` leaves of ``c`` columns and rank ``p``, each leaf costs
    ``O(n c (p + block))`` and each merge ``O(n p^2 + c p^2)``; the ``L - 1`` merges form
    ``ceil(log2 L)`` levels, so with ``W`` workers the wall time is about
    ``(L / W) t_leaf + log2(L) t_merge``. Peak memory per worker is one leaf's basis
    (``n x p``: the leaves and merges write their compactions over it, see
    :class:`~streamsvd.algebra.memory.MemoryBasis`) plus its block, and the merge of two ``n x p``
    factors; the returned compressor compacts aside again.

    Memory. As :func:`~streamsvd.parallel.tall_compress`, this process's allocator keeps
    freed memory for the next arrays from the first call on (glibc).
    """
    client = check_client(client)
    block = cast(int, check_positive_int(block, "block"))
    keep_freed_memory()
    if leaf_columns is not None:
        leaf_columns = cast(int, check_positive_int(leaf_columns, "leaf_columns"))
    spec = SourceSpec.of(source, dataset=dataset)
    record = SourceRecord.of(source, dataset=dataset, shape=(spec.n, spec.m),
                             description=spec.description)
    target: StreamCompressor | None = None
    path = (None if store is None else
            open_storage(store, storage_options=storage_options, argument="store"))
    if resume:
        if path is None:
            raise InputError(
                "`resume` needs `store`: got resume=True and store=None. Pass the store to "
                "continue."
            )
        inner = options.pop("inner", None)
        if options:
            raise InputError(
                f"`options` must be empty with resume=True (the store's options are used; "
                f"only `inner` is passed to check it); got {sorted(options)}. Drop them."
            )
        target = StreamCompressor.open(path, inner=inner)
        try:
            if target.n != spec.n:
                raise ShapeMismatchError(
                    f"`source` must have snapshots of size {target.n} (the store's n); got "
                    f"{spec.n} from {spec.description}. Pass the source the store was "
                    "built from."
                )
            opts = options_of(target)
            start = target.source_offset
        except BaseException:
            target.close(finalize=False)
            raise
    else:
        opts = check_options(options, spec.n)
        start = 0
        if path is not None and path.exists():
            raise StoreError(
                f"`store` {path} already exists; pass resume=True to continue it or choose "
                "another path."
            )
    try:
        root = _run_tree(spec, start, block, leaf_columns, opts, client, progress)
        if target is None and path is None:
            return root if root is not None else StreamCompressor(spec.n, **opts)
        if target is None:
            # a new store: the root is written as it is (one commit, no further update)
            target = root if root is not None else StreamCompressor(spec.n, **opts)
            target.source_record = record
            target.save(path)
        elif root is not None:
            target.source_record = record
            target.merge(root, spend_target=False)
    except BaseException:
        if target is not None:
            target.close(finalize=False)
        raise
    return target


def _run_tree(
    spec: SourceSpec,
    start: int,
    block: int,
    leaf_columns: int | None,
    opts: dict[str, Any],
    client: Any,
    progress: bool,
) -> StreamCompressor | None:
    import dask

    stop = spec.m
    if start >= stop:
        logger.info("nothing to compress: the source offset %d is the end of %s", start,
                    spec.description)
        return None
    width = leaf_columns if leaf_columns is not None else default_leaf_columns(stop - start,
                                                                               block)
    ranges = leaf_ranges(start, stop, width)
    tag = uuid.uuid4().hex[:12]
    blas = blas_threads_per_task(client)
    node_opts = opts if len(ranges) == 1 else _node_options(opts, columns=stop)
    nodes = [
        dask.delayed(_compress_leaf, pure=False)(
            spec.window(a, b), a, b, block, node_opts, blas,
            dask_key_name=f"streamsvd-leaf-{a}-{b}-{tag}",
        )
        for a, b in ranges
    ]
    spans = list(ranges)
    level = 0
    while len(nodes) > 1:
        level += 1
        merged, merged_spans = [], []
        for i in range(0, len(nodes) - 1, 2):
            a, b = spans[i][0], spans[i + 1][1]
            merged.append(dask.delayed(_merge_pair, pure=False)(
                nodes[i], nodes[i + 1], blas, len(nodes) == 2 and client is None,
                dask_key_name=f"streamsvd-merge-{a}-{b}-{tag}",
            ))
            merged_spans.append((a, b))
        if len(nodes) % 2:
            merged.append(nodes[-1])
            merged_spans.append(spans[-1])
        nodes, spans = merged, merged_spans
    logger.info(
        "tree of %d leaves of %d columns (%d levels) over columns %d:%d of %s on %s",
        len(ranges), width, level, start, stop, spec.description,
        "the threaded scheduler" if client is None else client,
    )
    (root,) = execute(nodes, client=client, progress=progress)
    # the user's copy compacts aside again: an interrupted update leaves it as it was
    return cast(StreamCompressor, root)._copy_with(
        backend=MemoryBackend(), **{name: opts[name] for name in _NODE_CHANGES})
