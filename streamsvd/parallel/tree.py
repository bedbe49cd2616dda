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
the leaves' width, never on the scheduler; every task is a deterministic function of its
inputs. The default width gives every thread of a cluster a leaf
(:func:`~streamsvd.parallel.spec.default_leaf_columns`), so it depends on the number of
workers: pass ``leaf_columns`` for a result that does not. With a given width the result
is the same with the threaded scheduler, on a :class:`distributed.LocalCluster` or on a
remote cluster (tested bit for bit on isolated workers), up to the rounding differences
of the BLAS (each task's BLAS threads are its worker's cores over the threads of the
workers on its host: :mod:`streamsvd.parallel.workers`).

Checkpoints. With a store, every finished node is committed beside it and a run killed
midway resumes from them (:mod:`streamsvd.parallel.checkpoints`).

Error bound. Leaves cover disjoint columns, so when a merge appends the right operand
``B ~ K_B`` to the left one ``A ~ K_A``, the errors ``E_A`` and ``E_B`` occupy disjoint
columns and ``||[E_A, E_B]||_F^2 = ||E_A||^2 + ||E_B||^2``; the merge's own truncation
and rejection then enter through the recursion of the
:class:`~streamsvd.StreamCompressor` notes. The root's :attr:`error_bound` is a
guaranteed bound on ``||A - U V^T||_F`` over every column compressed.
"""

from __future__ import annotations

import logging
from typing import Any, cast

from streamsvd._util.malloc import keep_freed_memory
from streamsvd._util.scheduling import check_client
from streamsvd._util.validation import check_positive_int
from streamsvd.errors import FloatRangeError, InputError, ShapeMismatchError, StoreError
from streamsvd.io.provenance import SourceRecord
from streamsvd.parallel.checkpoints import checkpoints_beside, open_checkpoints
from streamsvd.parallel.spec import SourceSpec, check_options, options_of
from streamsvd.parallel.tree_graph import run_tree
from streamsvd.parallel.workers import check_workers_see, source_places
from streamsvd.storage import open_storage
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.options import TREE_OPTIONS as COMPRESSOR_OPTIONS

__all__ = ["COMPRESSOR_OPTIONS", "tree_compress"]

logger = logging.getLogger(__name__)


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
    finalize: bool = False,
    checkpoints: bool = True,
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
        Columns per leaf; default ``10 * block``, cut down to whole blocks so that every
        thread of ``client``'s cluster gets a leaf (never fewer than ``block``). The
        result depends on it (each merge is an update with its own truncation), never on
        the scheduler: pass it for a result that does not depend on the workers.
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
    finalize : bool
        ``True``: converge the root and cut it to ``max_rank`` (and the other truncation
        rules) before returning it, committed with ``store``
        (:meth:`~streamsvd.StreamCompressor.finalize`): at most ``max_rank`` terms.
        ``False`` (default): the root is handed back uncut, with the
        ``max_rank + 2 oversampling`` terms its nodes keep, and ``finalized`` False, to go
        on absorbing; its :attr:`~streamsvd.StreamCompressor.amplitudes` and ``factors``
        then have more than ``max_rank`` terms until :meth:`finalize` or :meth:`close`.
    checkpoints : bool
        With ``store``: commit every finished leaf and merge beside it (``<store>.tree``,
        removed once the root is committed), so that the same call run again after a
        crash resumes from them (:mod:`streamsvd.parallel.checkpoints`); skipped, with a
        warning, when the workers of ``client`` cannot reach that location.
    **options
        Options of every :class:`~streamsvd.StreamCompressor` of the tree: ``inner``,
        ``eps``, ``rtol``, ``max_rank``, ``oversampling``, ``rule``, ``sweeps``,
        ``reject_tol``, ``reorth_tol``, ``target_error``, ``error_measure``,
        ``streaming_share``. Every level of the tree cuts to the rank cap, so its leaves
        and merges keep ``max_rank + 2 oversampling`` terms (on a spectrum decaying
        slowly through the cap the tree then cuts within 1e-5 of the optimal error,
        against 2e-4 with the compressor's own oversampling); the root is handed back
        with the compressor's options, cut to ``max_rank`` by ``finalize=True``, by its
        :meth:`~streamsvd.StreamCompressor.finalize` or by closing it.

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
        check_workers_see(client, **source_places(spec))
        saved = (None if path is None or not checkpoints else
                 open_checkpoints(checkpoints_beside(path), spec, client, tree="tree",
                                  where="the checkpoints of `store`"))
        root = run_tree(spec, start, block, leaf_columns, opts, client, progress, saved)
        if target is None and path is None:
            out = root if root is not None else StreamCompressor(spec.n, **opts)
            if finalize and not out.finalized:
                out.finalize()
            return out
        if target is None:
            # a new store: the root is written as it is (one commit, no further update)
            target = root if root is not None else StreamCompressor(spec.n, **opts)
            target.source_record = record
            target.save(path)
        elif root is not None:
            target.source_record = record
            target.merge(root, spend_target=False)
        if saved is not None:  # the root is committed: its parts are not needed
            saved.remove()
        if finalize and not target.finalized:
            target.finalize()
    except FloatRangeError as exc:  # a leaf's block or a merge: the caller's `source`
        if target is not None:
            target.close(finalize=False)
        raise exc.naming("`source`") from exc
    except BaseException:
        if target is not None:
            target.close(finalize=False)
        raise
    return target
