"""Scale-out on dask: out-of-core products over row chunks, tree merges on a cluster.

Three ways to run the same compression beyond one in-memory stream, all built on dask
(``dask.array``, ``dask.delayed``, ``dask.distributed``):

* :func:`tree_compress` -- many snapshots: column ranges (leaves) are compressed
  independently on workers and merged pairwise in a tree with
  :meth:`StreamCompressor.merge`, the error bounds composed (pyMOR's distributed HAPOD);
* :class:`TallCompressor` and :func:`tall_compress` -- tall snapshots: the stored factor
  ``U`` lives in panels chunked by rows and every product an update needs runs over
  row chunks with ``map_blocks`` and ``da.reduction``;
* :func:`ingest` -- what ``streamsvd ingest --scheduler ... [--tall]`` runs.

The compressor a store holds is reopened by the class of the kind it records
(:func:`compressor_class`, :func:`open_compressor`), and :func:`check_store` verifies a
store and then opens it (``streamsvd check``).

Scheduler. Every function takes ``client=``: ``None`` runs on dask's threaded scheduler
in this process; a :class:`distributed.Client` runs the same task graphs on its cluster
(:func:`connect` opens a :class:`~distributed.LocalCluster` or connects to a scheduler
address). Results do not depend on the scheduler, nor on the chunking of the source,
beyond rounding.

Sources. A numpy array, a ``.npy``/HDF5/zarr path, an h5py dataset, a zarr array or any
dask array (see :func:`~streamsvd.io.open.open_source`). The tall mode reads its blocks
in this process, the tree's leaves where they run, both through the one block reader
(:meth:`~streamsvd.io.sources.Source.blocks`: the next block read in a background thread
while the current one is absorbed, each block once) driven by
:func:`streamsvd.stream.ingest.ingest`. On a cluster, paths must be visible to every worker.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator
from typing import Any, cast

from streamsvd._util.scheduling import execute
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.memory import MEMORY_KIND
from streamsvd.algebra.panels.backend import KIND
from streamsvd.errors import InputError, StoreMismatchError
from streamsvd.parallel.tall import TallCompressor, tall_compress
from streamsvd.parallel.tree import COMPRESSOR_OPTIONS, tree_compress
from streamsvd.storage import Storage, open_storage
from streamsvd.store import CheckReport, open_store
from streamsvd.store import check_store as check_checksums
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.summary import summary_of

__all__ = [
    "COMPRESSOR_OPTIONS",
    "TallCompressor",
    "check_opens",
    "check_store",
    "compressor_class",
    "connect",
    "execute",
    "ingest",
    "open_compressor",
    "stored_kind",
    "tall_compress",
    "tree_compress",
]

logger = logging.getLogger(__name__)


@contextlib.contextmanager
def connect(scheduler: str | None = None, *, workers: int | None = None) -> Iterator[Any]:
    """Yield the ``client=`` argument for a scheduler named as on the command line.

    Parameters
    ----------
    scheduler : {None, "threads", "local"} or str
        ``None`` or ``"threads"``: dask's threaded scheduler (yields ``None``);
        ``"local"``: start a :class:`distributed.LocalCluster` of ``workers`` processes
        with one thread each, closed on exit; anything else is the address of a running
        scheduler (``tcp://host:8786``), connected to and disconnected from on exit.
    workers : int, optional
        Number of worker processes of a local cluster (default: the number of CPUs).

    Yields
    ------
    distributed.Client or None
    """
    if scheduler is None or scheduler == "threads":
        yield None
        return
    if not isinstance(scheduler, str) or not scheduler:
        raise InputError(
            f"`scheduler` must be 'threads', 'local' or a scheduler address such as "
            f"'tcp://host:8786'; got {scheduler!r}."
        )
    from distributed import Client, LocalCluster

    if scheduler == "local":
        nw = cast(int, check_positive_int(workers if workers is not None else
                                          (os.cpu_count() or 1), "workers"))
        with LocalCluster(n_workers=nw, threads_per_worker=1, processes=True,
                          dashboard_address=":0") as cluster, Client(cluster) as client:
            logger.info("started a local cluster of %d worker processes", nw)
            yield client
        return
    if workers is not None:
        raise InputError(
            f"`workers` only applies to scheduler='local'; got workers={workers!r} with "
            f"the address {scheduler!r}. Size the remote cluster where it runs."
        )
    try:
        client = Client(scheduler, timeout="20s")
    except OSError as exc:
        raise InputError(
            f"`scheduler` {scheduler!r} cannot be reached ({exc}). Check the address "
            "(tcp://host:port) and that the scheduler is running."
        ) from exc
    with client:
        yield client


def compressor_class(kind: Any) -> type[StreamCompressor] | type[TallCompressor] | None:
    """Return the class whose stores record ``kind`` (None for any other kind)."""
    classes: dict[str, type[StreamCompressor] | type[TallCompressor]] = {
        MEMORY_KIND: StreamCompressor, KIND: TallCompressor}
    return classes.get(kind)


def stored_kind(path: Any, *, storage_options: dict[str, Any] | None = None) -> Any:
    """Return the kind a basis store records (which compressor wrote it)."""
    with open_store(open_storage(path, storage_options=storage_options), "r") as st:
        return st.read().attrs.get("kind")


def open_compressor(path: Any, *, mode: str = "r", client: Any = None, inner: Any = None,
                    storage_options: dict[str, Any] | None = None,
                    ) -> StreamCompressor:
    """Reopen the compressor of a store, in memory or tall, whichever wrote it.

    Both kinds offer ``n``, ``n_seen``, ``rank``, ``amplitudes``, ``error_bound``,
    ``discarded_energy``, ``history``, ``orthogonality_error()``, ``expansion``,
    ``source_offset``, ``source_record``, ``store_path`` and ``close()``. ``inner`` is
    needed only for a store that does not keep its inner product (see
    :meth:`StreamCompressor.open`); ``storage_options`` for a URL ``path`` that needs them.
    """
    storage = open_storage(path, storage_options=storage_options)
    kind = stored_kind(storage)
    cls = compressor_class(kind)
    if cls is TallCompressor:
        return TallCompressor.open(storage, mode=mode, client=client, inner=inner)
    if cls is StreamCompressor:
        return StreamCompressor.open(storage, mode=mode, inner=inner)
    raise StoreMismatchError(
        f"`path` {path!s} holds a basis store of kind {kind!r}; expected a StreamCompressor "
        "or TallCompressor store."
    )


def check_opens(storage: Storage, kind: Any) -> str | None:
    """Open the compressor a store of ``kind`` holds, read-only, and close it.

    Returns the name of its class (None for a kind that holds no compressor: nothing is
    opened) and raises what opening it raises (:meth:`StreamCompressor.open`): the
    ``opens`` of :func:`streamsvd.store.check_store`.
    """
    cls = compressor_class(kind)
    if cls is None:
        return None
    with cls.open(storage, mode="r"):
        pass
    return cls.__name__


def check_store(storage: Storage) -> CheckReport:
    """Verify every checksum of a store, then open the compressor it holds: ``streamsvd check``.

    :func:`streamsvd.store.check_store` with ``opens=``:func:`check_opens`: a store that
    verifies is opened read-only as ``streamsvd info`` and ``--resume`` open it, so that a
    store called healthy opens; a store that needs its inner product given to open (an
    earlier version's that does not keep it) is no problem. Nothing is written or deleted.

    Parameters
    ----------
    storage : Storage
        Where the store lives (:func:`streamsvd.storage.open_storage`).

    Returns
    -------
    streamsvd.store.CheckReport
        One line per problem, or what verified.
    """
    return check_checksums(storage, opens=check_opens)


# --------------------------------------------------------------------------------- CLI


def ingest(
    source: Any,
    store: Any,
    *,
    dataset: str | None = None,
    block: int = 100,
    scheduler: str | None = None,
    workers: int | None = None,
    tall: bool = False,
    leaf_columns: int | None = None,
    chunk_rows: int | None = None,
    resume: bool = False,
    progress: bool = True,
    finalize: bool = True,
    **options: Any,
) -> dict[str, Any]:
    """Compress a source into a store on dask: what ``streamsvd ingest`` runs.

    Parameters
    ----------
    source, dataset, block
        As for :func:`tree_compress`.
    store : str or path-like
        The basis store (created; continued with ``resume=True``).
    scheduler : {None, "threads", "local"} or str
        See :func:`connect`.
    workers : int, optional
        Worker processes of a local cluster.
    tall : bool
        Keep ``U`` out of core (:func:`tall_compress`); otherwise a tree of in-memory
        leaves (:func:`tree_compress`).
    leaf_columns : int, optional
        Columns per leaf of the tree (ignored with ``tall``).
    chunk_rows : int, optional
        Rows per chunk of the tall panels (ignored without ``tall``).
    resume : bool
        Continue the store from its recorded source offset.
    progress : bool
        Show a progress bar (dask's for the tree, per column for the tall mode).
    finalize : bool
        Converge the core at the end and cut to ``max_rank``
        (:meth:`~streamsvd.StreamCompressor.finalize`, committed), unless the store
        already is (default).
    **options
        Compressor options (``eps``, ``rtol``, ``max_rank``, ``oversampling``, ``rule``,
        ``sweeps``, ...).

    Returns
    -------
    dict
        The summary ``streamsvd info --json`` prints, plus ``mode``, ``scheduler`` and
        ``seconds``.
    """
    t0 = time.perf_counter()
    with connect(scheduler, workers=workers) as client:
        sc: StreamCompressor
        if tall:
            if leaf_columns is not None:
                raise InputError(
                    f"`leaf_columns` does not apply to the tall mode; got {leaf_columns!r}. "
                    "Drop it, or drop `tall` to compress by a tree of leaves."
                )
            sc = tall_compress(source, block=block, dataset=dataset, store=store,
                               resume=resume, chunk_rows=chunk_rows, client=client,
                               progress=progress, finalize=False, **options)
        else:
            if chunk_rows is not None:
                raise InputError(
                    f"`chunk_rows` only applies to the tall mode; got {chunk_rows!r}. Pass "
                    "`tall=True` (--tall) or drop it."
                )
            sc = tree_compress(source, block=block, leaf_columns=leaf_columns,
                               dataset=dataset, client=client, store=store, resume=resume,
                               progress=progress, finalize=False, **options)
        try:
            if finalize and not sc.finalized:
                sc.finalize(progress=progress)
            summary = summary_of(sc)
            summary.update(mode="tall" if tall else "tree", scheduler=scheduler or "threads")
        finally:
            sc.close(finalize=False)
    summary["seconds"] = time.perf_counter() - t0
    return summary
