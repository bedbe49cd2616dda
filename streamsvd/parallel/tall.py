"""Out-of-core streaming for tall snapshots: the stream compressor over zarr row panels.

:class:`~streamsvd.algebra.panels.backend.PanelBackend` is the backend
(:class:`~streamsvd.algebra.interface.Backend`) that keeps a compressor's n-sized factor in a
:class:`~streamsvd.algebra.panels.basis.PanelBasis`, and :class:`TallCompressor` is the
factory of a :class:`~streamsvd.StreamCompressor` built with it (nothing else): the
basis lives in panels chunked by rows in the store directory (``<store>/panels/``), and
every product with it runs over row chunks with dask, on the threaded scheduler or on a
``distributed`` cluster. The update step, the options, ``add``, ``merge``, the error
bound, the history and the store are the in-memory compressor's (one implementation), so
both give the same basis to rounding.

Memory: when the update cuts (``max_rank`` or ``target_error``: the Gram path of
:mod:`streamsvd.engine.update_gram`), a block from :func:`~streamsvd.parallel.tall_compress` or a
dask block is read by row chunks in the update's own pass over the panels, each chunk
written to a scratch copy as it enters the products, so neither the block nor the basis
is ever in memory: one row chunk of each input per dask thread (each pass is one task
per row chunk: :mod:`streamsvd.algebra.panels.basis`), the small matrices and the right vectors
(``m x p``, or none with ``right_vectors=False``). At ``b = 100``, rank 60, the process
peaked at 317 to 333 MB at ``n = 2e5`` and 327 MB at ``n = 2e6`` without a store
(``bench/outofcore_benchmark.py``); on two fresh ``dask worker`` processes with
``client=``, each worker peaked at 285 to 293 MB from ``n = 2e5`` to ``2e6`` (``m = 400``,
chunks of 20000 rows) and the client at 264 MB, the row chunks of every pass split
evenly between the workers (``bench/cluster_memory.py``). An update that takes the exact
path (no cut, ``eps`` or ``rtol`` alone, ``window``, ``forget``, a block the Gram path
declines) reads its block into memory first (``n x b``) and orthonormalises it there.

Crash safety: an update writes its new panel (or the compacted basis) before the commit
that refers to it; a panel is deleted only when neither the state nor the last two
commits refer to it, so a process or worker killed at any instant leaves the last commit
readable; leftovers are removed when the store is reopened for writing. A store is
created by its first commit, which holds the whole state and the basis's attributes
(``chunk_rows``, the panels): killed before it, the store does not exist (its leftovers,
panels included, are replaced by the next creation), never half of it
(:mod:`streamsvd.store.create`).
"""

from __future__ import annotations

import os
from typing import Any, cast

from streamsvd._util.malloc import keep_freed_memory
from streamsvd._util.scheduling import check_client
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.panels.backend import KIND, PanelBackend
from streamsvd.errors import InputError, ShapeMismatchError
from streamsvd.io.provenance import SourceRecord
from streamsvd.parallel.spec import SourceSpec
from streamsvd.parallel.workers import check_workers_see, source_places
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.ingest import ingest as ingest_blocks

__all__ = ["TallCompressor", "tall_compress"]


class _TallMode(type):
    """The type of :class:`TallCompressor`: its instances are the tall-mode compressors."""

    def __instancecheck__(cls, instance: object) -> bool:
        return isinstance(instance, StreamCompressor) and instance._life.kind == KIND


class TallCompressor(metaclass=_TallMode):
    """Stream snapshots into a basis kept out of core, in panels chunked by rows.

    A factory: ``TallCompressor(n, ...)`` returns a :class:`~streamsvd.StreamCompressor`
    whose backend is a :class:`~streamsvd.algebra.panels.backend.PanelBackend`, built
    from the arguments below, and ``isinstance(sc, TallCompressor)`` tells whether a
    compressor is one. Its tall-mode attributes (:attr:`~streamsvd.StreamCompressor.
    chunk_rows`, :attr:`~streamsvd.StreamCompressor.client`,
    :meth:`~streamsvd.StreamCompressor.factors`, whose ``U`` is lazy here, and
    :meth:`~streamsvd.StreamCompressor.expect`) are the compressor's.

    Parameters
    ----------
    n : int
        Size of one snapshot.
    store : str, path-like or Storage, optional
        Create a basis store there (a directory, a ``file://`` or ``s3://`` URL, or a
        storage from :func:`streamsvd.storage.open_storage`, which carries
        ``storage_options``); the panels live in its ``panels/`` prefix and the small
        state is committed every ``commit_every`` updates. Continue an existing one
        with :meth:`TallCompressor.open`.
    workdir : str, path-like or Storage, optional
        Without ``store``: directory (or object-store URL) for the panels (a temporary
        directory, removed by :meth:`close`, by default). On a remote cluster it must be
        visible to every worker.
    chunk_rows : int, optional
        Rows per chunk of the panels (default 16384).
    client : distributed.Client, optional
        Run the row-chunk products on this cluster; the threaded scheduler by default.
    inner : None, array of weights or DiagonalInner
        Euclidean or diagonal weights (a matrix inner product couples the row chunks and
        is not offered out of core).
    storage_options : dict, optional
        Options of the object store of a URL ``store`` or ``workdir`` (``s3://``:
        ``key``, ``secret``, ``endpoint_url``, ...).
    **options : Any
        ``eps``, ``rtol``, ``max_rank``, ``oversampling``, ``rule``, ``sweeps``,
        ``reject_tol``, ``reorth_tol``, ``right_vectors``, ``commit_every``, ...: as for
        :class:`~streamsvd.StreamCompressor`.

    Notes
    -----
    Cost of absorbing ``b`` columns at stored width ``w``: the in-memory update's flops
    (:mod:`streamsvd.engine.update`), each product with the basis a dask graph over the row
    chunks that reads the panels once; a new panel of ``n x r`` (or the compacted basis
    ``n x p``) is written per update. A dask block is read by row chunks (on the cluster
    when there is one): within the update's pass when the update cuts (see the module
    docstring), into memory first otherwise; on any error (bad input, a failing read, a
    lost worker) the state in memory and in the store is unchanged, and what the update
    wrote is removed. Without ``store`` or ``workdir``, :meth:`close` removes the panels and
    finalises nothing.
    """

    KIND = KIND

    def __new__(  # type: ignore[misc]
        cls,
        n: int,
        *,
        store: Any = None,
        workdir: Any = None,
        chunk_rows: int | None = None,
        client: Any = None,
        inner: Any = None,
        storage_options: dict[str, Any] | None = None,
        **options: Any,
    ) -> StreamCompressor:
        """Return a :class:`~streamsvd.StreamCompressor` over panels (see the class)."""
        check_positive_int(n, "n")
        backend = PanelBackend.create(store=store, workdir=workdir, chunk_rows=chunk_rows,
                                      client=client, storage_options=storage_options)
        return StreamCompressor(n, inner=inner, store=None if store is None else backend.root,
                                backend=backend, **options)

    @classmethod
    def open(
        cls, path: Any, *, inner: Any = None, mode: str = "a", client: Any = None,
        storage_options: dict[str, Any] | None = None,
    ) -> StreamCompressor:
        """Reopen a tall compressor from its store, exactly as at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``TallCompressor(..., store=path)``.
        inner : optional
            The weights the store was written with (checked by fingerprint).
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock and removes panels left
            by an interrupted update); ``"r"`` reads only.
        client : distributed.Client, optional
            Cluster for the row-chunk products.
        storage_options : dict, optional
            Options of the object store of a URL ``path``.
        """
        client = check_client(client)
        return StreamCompressor._open(
            path, inner=inner, mode=mode, kind=KIND,
            backend=lambda attrs, root: PanelBackend.for_store(attrs, root, client=client),
            storage_options=storage_options,
        )


# ------------------------------------------------------------------------- tall driver


def tall_compress(
    source: Any,
    *,
    block: int = 100,
    dataset: str | None = None,
    store: Any = None,
    resume: bool = False,
    chunk_rows: int | None = None,
    client: Any = None,
    progress: bool = False,
    storage_options: dict[str, Any] | None = None,
    finalize: bool = False,
    **options: Any,
) -> StreamCompressor:
    """Stream every column of a source into a :class:`TallCompressor`, block by block.

    Parameters
    ----------
    source : array_like, str, os.PathLike, h5py.Dataset, zarr.Array or dask array
        The ``n x m`` snapshot matrix, absorbed block by block by
        :func:`streamsvd.stream.ingest.ingest`; each block is handed over unread
        (:meth:`~streamsvd.io.sources.Source.lazy`) and read once, by chunks of
        ``chunk_rows`` rows, in the update's pass over the panels (into memory first when
        the update takes the exact path: see :class:`TallCompressor`).
    block : int
        Columns per update.
    dataset : str, optional
        Dataset of an HDF5 file or array of a zarr group.
    store : str or path-like, optional
        Store of the basis: created, or continued from its recorded source offset with
        ``resume=True``. Updates are committed as ``commit_every`` says (every update
        by default); a failure leaves the store at its last commit. The source is
        recorded in the store (:attr:`~streamsvd.StreamCompressor.source_record`).
    resume : bool
        Continue the existing store (its options and weights are used; ``inner``, if
        passed, is checked against them).
    chunk_rows : int, optional
        Rows per chunk of the panels: by default the source's row chunks when it is a
        dask, zarr or HDF5 array chunked uniformly by rows, else 16384.
    client : distributed.Client, optional
        Run the row-chunk products on this cluster.
    progress : bool
        Show a progress bar over the columns (tqdm, on stderr).
    storage_options : dict, optional
        Options of the object store of a URL ``store``.
    finalize : bool
        ``True``: converge the core and cut to ``max_rank`` (and the other truncation
        rules) before returning, committed with ``store``
        (:meth:`~streamsvd.StreamCompressor.finalize`): at most ``max_rank`` terms.
        ``False`` (default): the streamed state is handed back uncut, with its
        oversampling (``max_rank + oversampling`` terms) and ``finalized`` False, until
        :meth:`~streamsvd.StreamCompressor.finalize` or :meth:`close`.
    **options
        :class:`TallCompressor` options (``inner``, ``eps``, ``rtol``, ``max_rank``,
        ``rule``, ``sweeps``, ``reject_tol``, ``reorth_tol``,
        ``commit_every``, and ``workdir`` without a store).

    Returns
    -------
    TallCompressor
        It holds the store's writer lock when ``store`` is given: close it when done.

    Notes
    -----
    Memory. From the first call on, this process's allocator keeps freed memory for the
    next arrays (on Linux with glibc: its mmap threshold fixed at 32 MiB and its trim
    threshold at 256 MiB, unless ``MALLOC_*_`` variables or ``GLIBC_TUNABLES`` tune
    malloc already): the row chunks allocated and freed at every update were otherwise
    zeroed again by the kernel, 400000 page faults on a 200000 x 1000 array, about 10%
    of the wall time (``bench/README.md``).
    """
    block = cast(int, check_positive_int(block, "block"))
    keep_freed_memory()
    spec = SourceSpec.of(source, dataset=dataset)
    record = SourceRecord.of(source, dataset=dataset, shape=(spec.n, spec.m),
                             description=spec.description)
    if resume:
        inner = options.pop("inner", None)
        if store is None or options:
            raise InputError(
                f"`resume` needs `store` and no options but `inner` (the store's are used); "
                f"got store={store!r} and options {sorted(options)}. Pass only the store."
            )
    with spec.open() as src:
        if resume:
            tc = TallCompressor.open(store, inner=inner, client=client,
                                     storage_options=storage_options)
            if tc.n != spec.n:
                tc.close(finalize=False)
                raise ShapeMismatchError(
                    f"`source` must have snapshots of size {tc.n} (the store's n); got "
                    f"{spec.n} from {spec.description}. Pass the source the store was "
                    "built from."
                )
            tc.source_record = record
        else:
            rows = chunk_rows if chunk_rows is not None else src.row_chunks
            tc = TallCompressor(spec.n, store=store, storage_options=storage_options,
                                chunk_rows=rows, client=client, source_record=record,
                                **options)
        try:
            _check_tall_workers(tc, spec, client, store)
            ingest_blocks(src, tc, block=block, rows=tc.chunk_rows, progress=progress,
                          desc="tall")
            tc.flush()
            if finalize and not tc.finalized:
                tc.finalize(progress=progress)
        except BaseException:
            tc.close(finalize=False)
            raise
    return tc


def _check_tall_workers(tc: StreamCompressor, spec: SourceSpec, client: Any,
                        store: Any) -> None:
    """Check that the workers see the panels and the source they read (see ``workers``).

    The workers read and write the panels; they read a zarr source (a local directory or
    a URL) by row chunks themselves. An ``.npy`` or HDF5 source is read here.
    """
    if client is None:
        return
    places = source_places(spec)
    path = spec.local_path()
    if path is not None and not os.path.isdir(path):
        places["paths"] = []
    backend = cast(PanelBackend, tc._life.backend)
    root = backend.root
    root.prepare()
    name = ("`store`" if store is not None else "`workdir`" if not backend.temporary else
            "the panels' temporary directory (no `store` or `workdir` given)")
    check_workers_see(client, paths=places["paths"],
                      storages=[*places["storages"], (name, root)])
