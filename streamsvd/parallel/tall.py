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
(``bench/outofcore_benchmark.py``). An update that takes the exact path (no cut, ``eps``
or ``rtol`` alone, ``window``, ``forget``, a block the Gram path declines) reads its block
into memory first (``n x b``) and orthonormalises it there.

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

from typing import Any

from streamsvd._util.scheduling import check_client
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.panels.backend import KIND, PanelBackend
from streamsvd.stream.compressor import StreamCompressor

__all__ = ["TallCompressor"]


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
