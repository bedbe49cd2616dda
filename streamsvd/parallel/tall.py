"""Out-of-core streaming for tall snapshots: the stream compressor over zarr row panels.

:class:`~streamsvd.algebra.panels.backend.PanelBackend` is the backend
(:class:`~streamsvd.algebra.interface.Backend`) that keeps a compressor's n-sized factor in a
:class:`~streamsvd.algebra.panels.basis.PanelBasis`, and :class:`TallCompressor` is
:class:`~streamsvd.StreamCompressor` built with it (a constructor and nothing else): the
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

import logging
from typing import Any, cast

import numpy as np

from streamsvd._util.scaling import safe_column_norms
from streamsvd._util.scheduling import check_client, execute
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.panels.backend import KIND, PanelBackend
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.stream.compressor import StreamCompressor

__all__ = ["TallCompressor"]

logger = logging.getLogger(__name__)

class TallCompressor(StreamCompressor):
    """Stream snapshots into a basis kept out of core, in panels chunked by rows.

    A :class:`~streamsvd.StreamCompressor` whose backend is a
    :class:`~streamsvd.algebra.panels.backend.PanelBackend`: this class only builds it
    from the arguments below.

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
    **options
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

    def __init__(
        self,
        n: int,
        *,
        store: Any = None,
        workdir: Any = None,
        chunk_rows: int | None = None,
        client: Any = None,
        inner: Any = None,
        storage_options: dict[str, Any] | None = None,
        **options: Any,
    ) -> None:
        check_positive_int(n, "n")
        backend = PanelBackend.create(store=store, workdir=workdir, chunk_rows=chunk_rows,
                                      client=client, storage_options=storage_options)
        super().__init__(n, inner=inner, store=None if store is None else backend.root,
                         backend=backend, **options)

    @classmethod
    def open(
        cls, path: Any, *, inner: Any = None, mode: str = "a", client: Any = None,
        storage_options: dict[str, Any] | None = None,
    ) -> TallCompressor:
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
        return cls._open(
            path, inner=inner, mode=mode, kind=KIND,
            backend=lambda attrs, root: PanelBackend.for_store(attrs, root, client=client),
            storage_options=storage_options,
        )

    @property
    def chunk_rows(self) -> int:
        """Rows per chunk of the panels."""
        return self._panel_backend.chunk_rows

    @property
    def client(self) -> Any:
        """The cluster the row-chunk products run on (None: the threaded scheduler)."""
        return self._panel_backend.client

    @property
    def _panel_backend(self) -> PanelBackend:
        backend = self._backend
        assert isinstance(backend, PanelBackend)
        return backend

    def expect(self, columns: Any) -> None:
        """Name the block that will follow the one the coming :meth:`absorb` is given.

        A block read from its source (a :class:`~streamsvd.algebra.panels.lazy.LazyBlock`, as
        :func:`~streamsvd.stream.ingest.ingest` hands them out) is then read by the coming
        update's last pass over the panels, which writes its scratch copy and forms its
        products with the new basis: its own update then makes one pass over the panels
        instead of two (``bench/README.md``). The results are the same to the last bit
        (tested); should the call after the coming one get another block, or the coming
        update take another path, the block is read as usual.
        """
        cast(PanelBasis, self._state.basis).expect(columns)

    @property
    def stored_width(self) -> int:
        """Number of stored columns of the basis (all panels)."""
        return self._state.basis.width

    def factors(self) -> tuple[Any, np.ndarray]:
        """Return the expansion as ``(U, V)``: ``U`` lazy (dask, over the panels), ``V`` in memory.

        Terms are sorted by decreasing amplitude and signed as in :attr:`expansion` (the
        largest-modulus entry of each ``u_i`` positive, found by a reduction over the
        row chunks), so neither this call nor computing ``U`` chunk by chunk holds
        ``n x p``; :attr:`left_vectors` and :attr:`expansion` do gather ``U``. Needs
        ``right_vectors=True``.
        """
        s = self._state
        basis = s.basis
        assert isinstance(basis, PanelBasis)
        V = self.right_factor()
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U = basis.lazy(s.settled()[0][:, perm])
        top, bottom = execute([U.max(axis=0), U.min(axis=0)], client=self.client,
                              overlap_io=True)
        signs = np.where(np.asarray(top) >= -np.asarray(bottom), 1.0, -1.0)
        self._exposure = (self._version, perm, signs)  # the coordinates of `add`
        return U * signs, V[:, perm] * signs
