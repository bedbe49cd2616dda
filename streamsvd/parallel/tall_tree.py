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

Checkpoints. Every finished leaf and merge is committed, from the worker that computed
it, as a store of its own (its panels copied into one, and its small state) under
``<store>.tree/<node>``, or ``<workdir>/checkpoints/<node>`` without a store, with
:class:`~streamsvd.parallel.checkpoints.Checkpoints` and the graph of
:func:`~streamsvd.parallel.tree_graph.node_graph`, as the in-memory tree does. The same
call run again after a kill (of a worker, of the client) loads the committed nodes and
computes nothing below them. A node is handed on to its merge as it is loaded back, in
the run that computed it as in the one that resumes, so the resumed result is the
uninterrupted one bit for bit (``tests/slow/faults/test_tall_tree_checkpoints.py``).
Checkpoints written with other arguments (source, ``block``, ``leaf_columns``,
``chunk_rows``, options) are refused with an error naming them. They are removed once
the root is committed to ``store`` (or handed back without one). What they add: each
node's panels are written twice more (a local copy, the checkpoint) and read back once
(``O(n p)`` per node against the ``O(n c (p + block))`` of a leaf): 14% more CPU time
at ``n = 50000``, four leaves of 100 columns (``bench/studies/tall-tree-checkpoints.md``).

What it does not do (yet): resuming (appending to) an existing store.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any, cast

from threadpoolctl import threadpool_limits

from streamsvd._util.scheduling import check_client, execute
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.panels.backend import PanelBackend
from streamsvd.errors import InputError, StoreError
from streamsvd.io.provenance import SourceRecord
from streamsvd.parallel.checkpoints import (
    Checkpoints,
    checkpoints_beside,
    child_storage,
    open_checkpoints,
)
from streamsvd.parallel.spec import (
    SourceSpec,
    _node_options,
    check_options,
    default_leaf_columns,
    leaf_ranges,
)
from streamsvd.parallel.tall import TallCompressor
from streamsvd.parallel.tree_graph import begin, node_graph
from streamsvd.parallel.workers import (
    blas_here,
    blas_plan,
    check_workers_see,
    source_places,
    worker_threads,
)
from streamsvd.storage import open_storage
from streamsvd.store import POINTER_NAME
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest

__all__ = ["tall_tree_compress"]

logger = logging.getLogger(__name__)

CHECKPOINTS = "checkpoints"
"""The checkpoints' prefix under ``workdir`` when there is no ``store``."""


def _tall_leaf(spec: SourceSpec, start: int, stop: int, block: int, chunk_rows: int,
               options: dict[str, Any], place: Any, blas: int | dict[str, int],
               checkpoints: Checkpoints | None = None, name: str = "") -> StreamCompressor:
    """Compress columns ``start:stop`` into panels at ``place`` (on a worker).

    With ``checkpoints`` the leaf is committed there as ``name`` and handed on as it is
    loaded back (:func:`_committed`).
    """
    tc = TallCompressor(spec.n, workdir=place, chunk_rows=chunk_rows, **options)
    with threadpool_limits(limits=blas_here(blas), user_api="blas"), spec.open() as src:
        ingest(src, tc, start=start, stop=stop, block=block, rows=chunk_rows,
               prefetch=False, preload_sweeps=False)
    logger.info("tall leaf %d:%d: rank %d (bound %.3e)", start, stop, tc.rank,
                tc.error_bound)
    return tc if checkpoints is None else _committed(tc, checkpoints, name, place)


def _tall_merge(left: StreamCompressor, right: StreamCompressor,
                blas: int | dict[str, int], checkpoints: Checkpoints | None = None,
                name: str = "", place: Any = None) -> StreamCompressor:
    """Append ``right``'s columns to ``left`` (on a worker); ``left`` is the result.

    With ``checkpoints`` the merge is committed there as ``name``, handed on as it is
    loaded back into ``place``, and both operands' work panels are removed once it is
    committed.
    """
    with threadpool_limits(limits=blas_here(blas), user_api="blas"):
        left.merge(right, spend_target=False)
    if checkpoints is None:
        return left
    out = _committed(left, checkpoints, name, place)
    _discard(right)
    return out


def _committed(sc: StreamCompressor, checkpoints: Checkpoints, name: str, place: Any
               ) -> StreamCompressor:
    """Commit node ``name``, remove its work panels and return it loaded into ``place``.

    The node handed on is the committed one read back (its panels copied into one), both
    in a run that computed it and in one that resumes from it: the two runs then compute
    the same products, and give the same result bit for bit.
    """
    checkpoints.save(name, sc)
    rows = cast(int, sc.chunk_rows)
    _discard(sc)
    return _load(checkpoints, name, place, rows)


def _load(checkpoints: Checkpoints, name: str, place: Any, chunk_rows: int
          ) -> StreamCompressor:
    """Return the committed node ``name`` with its panels copied to ``place`` (a worker)."""
    place.prepare()
    sc = checkpoints.load(name, reader=TallCompressor.open, backend=PanelBackend(
        place, chunk_rows=chunk_rows, client=None, committed=False))
    logger.info("%s loaded from %s: rank %d (bound %.3e)", name, checkpoints.root.url,
                sc.rank, sc.error_bound)
    return sc


def _discard(sc: StreamCompressor) -> Any:
    """Close a work-directory node and remove its panels; return where they were."""
    place = cast(PanelBackend, sc._life.backend).root
    sc.close(finalize=False)
    place.delete("")
    return place


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
    checkpoints: bool = True,
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
    checkpoints : bool
        Commit every finished leaf and merge (``<store>.tree``, or
        ``<workdir>/checkpoints`` without ``store``; see the module docstring) so that the
        same call run again resumes from them; skipped, with a warning, when the workers
        cannot reach that location.
    **options
        Compressor options (``inner`` Euclidean or diagonal, ``eps``, ``max_rank``, ...).

    Returns
    -------
    StreamCompressor
        A tall compressor (its panels in ``workdir``, or in ``store``).

    Raises
    ------
    StoreError
        ``store`` exists already, or the checkpoints found were written by a call with
        other arguments (the error names them).

    Notes
    -----
    The root keeps the options of the tree's nodes (twice the oversampling, an absolute
    target spent as a mean-l2 one: :func:`~streamsvd.parallel.spec._node_options`);
    ``finalize`` cuts to ``max_rank`` all the same. A merge appends to its left operand
    in place (a retried merge task would see it merged already). With checkpoints, the
    result differs from the one without them by rounding only (a node handed on as
    loaded back holds its panels as one).
    """
    client = check_client(client)
    block = cast(int, check_positive_int(block, "block"))
    chunk_rows = cast(int, check_positive_int(chunk_rows, "chunk_rows"))
    if leaf_columns is not None:
        leaf_columns = cast(int, check_positive_int(leaf_columns, "leaf_columns"))
    if workdir is None:
        raise InputError("`workdir` must be a directory or URL every worker reaches; got "
                         "None. Pass workdir='s3://bucket/scratch' on a cluster.")
    spec = SourceSpec.of(source, dataset=dataset)
    opts = check_options(options, spec.n)
    root_dir = open_storage(workdir, storage_options=storage_options, argument="workdir")
    target = (None if store is None else
              open_storage(store, storage_options=storage_options, argument="store"))
    if target is not None and target.exists() and POINTER_NAME in target.list(""):
        raise StoreError(f"`store` {target} already exists; choose another path (the tall "
                         "tree writes a new store).")
    root_dir.prepare()
    places = source_places(spec)
    check_workers_see(client, paths=places["paths"],
                      storages=[*places["storages"], ("`workdir`", root_dir)])
    width = (leaf_columns if leaf_columns is not None else
             default_leaf_columns(spec.m, block, tasks=worker_threads(client)))
    ranges = leaf_ranges(0, spec.m, width)
    node_opts = opts if len(ranges) == 1 else _node_options(opts, columns=spec.m)
    saved = (None if not checkpoints else
             _checkpoints(root_dir if target is None else target, target is None, spec,
                          client))
    done = begin(saved, start=0, stop=spec.m, block=block, width=width, options=node_opts,
                 refuse=True, chunk_rows=chunk_rows)
    blas = blas_plan(client)
    tag = uuid.uuid4().hex[:12]
    import dask

    def place(name: str) -> Any:
        return child_storage(root_dir, f"{tag}/{name}")

    def leaf(a: int, b: int, name: str, key: str) -> Any:
        return dask.delayed(_tall_leaf, pure=False)(
            spec.window(a, b), a, b, block, chunk_rows, node_opts, place(name), blas, saved,
            name, dask_key_name=key)

    def merge(left: Any, right: Any, name: str, key: str, root: bool) -> Any:
        return dask.delayed(_tall_merge, pure=False)(left, right, blas, saved, name,
                                                      place(name), dask_key_name=key)

    def load(name: str, key: str) -> Any:
        return dask.delayed(_load, pure=False)(saved, name, place(name), chunk_rows,
                                               dask_key_name=key)

    graph, _ = node_graph(ranges, done, f"streamsvd-tall-{{}}-{tag}", leaf=leaf,
                          merge=merge, load=load)
    (root,) = execute([graph], client=client)
    root = cast(StreamCompressor, root)  # with the nodes' options (see the notes)
    if client is not None:  # its copy into `store` and its finalisation run on the workers
        root._life.backend.use_client(root._life.state.basis, client)  # type: ignore[attr-defined]
    root.source_record = SourceRecord.of(source, dataset=dataset, shape=(spec.n, spec.m),
                                         description=spec.description)
    if target is not None:
        root.save(target)
        place("").delete("")  # the root's panels are in the store: the work panels go
    if saved is not None:  # the root is committed (or handed back): its parts go
        saved.remove()
    if finalize and not root.finalized:
        root.finalize()
    return root


def _checkpoints(where: Any, in_workdir: bool, spec: SourceSpec, client: Any
                 ) -> Checkpoints | None:
    """Return where the tall tree commits its nodes (None if the workers cannot reach it).

    Beside ``store`` (``<store>.tree``), or in ``<workdir>/checkpoints`` without one.
    """
    root = child_storage(where, CHECKPOINTS) if in_workdir else checkpoints_beside(where)
    return open_checkpoints(root, spec, client, tree="tall tree", where="the checkpoints")
