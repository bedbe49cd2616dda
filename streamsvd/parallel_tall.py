"""Out-of-core streaming for tall snapshots: the stream compressor over zarr row panels.

:class:`TallCompressor` is :class:`~streamsvd.StreamCompressor` with its n-sized factor in
a :class:`~streamsvd.panels.PanelBasis`: the basis lives in zarr panels chunked by rows
in the store directory (``<store>/panels/``), and every product with it runs over row
chunks with dask, on the threaded scheduler or on a ``distributed`` cluster. The update
step, the options, ``add``, ``merge``, the error bound, the history and the store are the
in-memory compressor's (one implementation), so both give the same basis to rounding.

Memory: the block being absorbed (``n x b``) and its Gram-Schmidt workspace are held in
memory, with the next block that :func:`~streamsvd.parallel.tall_compress` reads ahead
(float32 for a float32 source), plus the small matrices and the right vectors (``m x p``,
or none with ``right_vectors=False``); the basis (``n x w``) never is. At ``n = 2e5``,
``b = 100`` the process peaks at 1.0 to 1.1 GB (``bench/outofcore_benchmark.py``): the
peak grows with ``n``.

Crash safety: a plan writes its new panel (or the compacted basis) before the commit
that refers to it; a panel is deleted only when neither the state nor the last two
commits refer to it, so a process or worker killed at any instant leaves the last commit
readable; leftovers are removed when the store is reopened for writing.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from ._scaling import safe_column_norms
from ._validation import check_positive_int
from .basis import BasisBackend
from .errors import InputError, ShapeMismatchError, SourceError
from .inner import DiagonalInner, InnerProduct, as_inner
from .options import CompressorOptions
from .panels import PanelBasis
from .scheduling import check_client, execute
from .storage import LocalStorage, ObjectStorage, open_storage
from .stream import StreamCompressor, UpdateRecord

__all__ = ["DEFAULT_CHUNK_ROWS", "KIND", "TallCompressor"]

logger = logging.getLogger(__name__)

DEFAULT_CHUNK_ROWS = 16384
"""Rows per chunk of the stored panels when ``chunk_rows`` is not given."""

KIND = "streamsvd.TallCompressor"


class TallCompressor(StreamCompressor):
    """Stream snapshots into a basis kept out of core, in zarr panels chunked by rows.

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
        ``reject_tol``, ``reorth_tol``, ``right_vectors``, ``commit_every``: as for
        :class:`~streamsvd.StreamCompressor`.

    Notes
    -----
    Cost of absorbing ``b`` columns at stored width ``w``: the in-memory update's flops
    (:mod:`streamsvd.update`), each product with the basis a dask graph over the row
    chunks that reads the panels once; a new panel of ``n x r`` (or the compacted basis
    ``n x p``) is written per update.
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
        n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        ip = as_inner(inner, n)
        if not (ip.is_euclidean or isinstance(ip, DiagonalInner)):
            raise InputError(
                f"`inner` must be Euclidean or diagonal weights out of core; got {ip!r}, "
                "which couples the row chunks. Use the in-memory StreamCompressor, or "
                "lump the mass matrix into weights."
            )
        if store is not None and workdir is not None:
            raise InputError(
                f"`workdir` must be None when `store` is given (the panels live in the "
                f"store); got workdir={workdir!r}. Drop one of them."
            )
        self.chunk_rows = int(check_positive_int(  # type: ignore[arg-type]
            DEFAULT_CHUNK_ROWS if chunk_rows is None else chunk_rows, "chunk_rows"))
        self.client = check_client(client)
        self._cleanup: Any = None
        self._root: LocalStorage | ObjectStorage
        if store is not None:
            self._root = store = open_storage(store, storage_options=storage_options,
                                              argument="store")
        elif workdir is None:
            self._root = LocalStorage(Path(tempfile.mkdtemp(prefix="streamsvd-tall-")))
            self._cleanup = weakref.finalize(self, shutil.rmtree, self._root.root, True)
        else:
            self._root = open_storage(workdir, storage_options=storage_options,
                                      argument="workdir")
            self._root.prepare()
        self._commits: tuple[set[str], set[str]] = (set(), set())
        super().__init__(n, inner=ip, store=store, **options)

    def _new_basis(self) -> PanelBasis:
        return PanelBasis(self.n, self.inner, chunk_rows=self.chunk_rows, client=self.client,
                          root=self._root)

    @property
    def _panels(self) -> PanelBasis:
        basis = self._state.basis
        assert isinstance(basis, PanelBasis)
        return basis

    # --------------------------------------------------------------- persistence
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
        return cls._open(path, inner=inner, mode=mode, backend={"client": client},
                         storage_options=storage_options)

    @classmethod
    def _reopen(cls, n: int, inner: InnerProduct, attrs: dict[str, Any], path: Any, *,
                options: CompressorOptions, **backend: Any) -> Any:
        return cls(n, inner=inner, workdir=path, client=backend.get("client"),
                   chunk_rows=int(attrs["basis"]["chunk_rows"]), **options.as_dict())

    def _reopened(self, mode: str) -> None:
        self._commits = (set(self._panels.panels), set())
        if mode == "a":
            self._panels.collect(set())

    def _committed(self, basis_attrs: dict[str, Any]) -> None:
        """Keep the panels of the current and previous commits; delete the others."""
        self._commits = (set(basis_attrs["panels"]), self._commits[0])
        self._panels.collect(self._commits[0] | self._commits[1])

    def close(self, *, finalize: bool = True) -> None:
        """Finalise, commit what is pending, release the store's lock, remove a workdir.

        As :meth:`StreamCompressor.close <streamsvd.StreamCompressor.close>`; a
        temporary workdir (no store, no ``workdir``) is removed with its panels, and
        nothing is finalised then.
        """
        super().close(finalize=finalize and self._cleanup is None)
        if self._cleanup is not None:
            self._cleanup()
            self._cleanup = None

    def __enter__(self) -> TallCompressor:
        return self

    # ------------------------------------------------------------------ updates
    def absorb(self, columns: Any, *, source_offset: int | None = None) -> UpdateRecord:
        """Append a block of snapshots (``n x b``, a numpy or dask array).

        A dask array is read by row chunks (on the cluster when there is one) into
        memory first. On any error (bad input, a failing read, a lost worker) the state in
        memory and in the store is unchanged, and what the update wrote is removed.
        """
        import dask.array as da

        if isinstance(columns, da.Array):
            if columns.ndim != 2 or columns.shape[0] != self.n:
                raise ShapeMismatchError(
                    f"`columns` must have {self.n} rows; got shape {columns.shape}. Pass "
                    "snapshots as columns."
                )
            if columns.dtype.kind not in "biuf":
                raise InputError(
                    f"`columns` must hold real numbers; got dtype {columns.dtype}. "
                    "Convert it with `.astype(float)`."
                )
            if columns.shape[1] == 0:
                raise InputError(f"`columns` must not be empty; got shape {columns.shape}.")
            try:
                (columns,) = execute([columns.astype(np.float64)], client=self.client)
            except Exception as exc:
                a = self.source_offset
                kept = "" if self._persistence is None else " and the store holds its last commit"
                raise SourceError(
                    f"absorbing columns {a}:{a + columns.shape[1]} (offset {a}) failed: "
                    f"{type(exc).__name__}: {exc}. The basis is unchanged{kept}; fix the "
                    f"cause and resume from offset {a}."
                ) from exc
            columns = np.asarray(columns)
        try:
            return super().absorb(columns, source_offset=source_offset)
        except BaseException:
            self._panels.discard_planned()  # the panels a failed plan wrote
            raise

    # --------------------------------------------------------------- properties
    @property
    def stored_width(self) -> int:
        """Number of stored columns of the basis (all panels)."""
        return self._panels.width

    def factors(self) -> tuple[Any, np.ndarray]:
        """Return the expansion as ``(U, V)``: ``U`` lazy (dask, over the panels), ``V`` in memory.

        Terms are sorted by decreasing amplitude and signed as in :attr:`expansion` (the
        largest-modulus entry of each ``u_i`` positive, found by a reduction over the
        row chunks), so neither this call nor computing ``U`` chunk by chunk holds
        ``n x p``; :attr:`left_vectors` and :attr:`expansion` do gather ``U``. Needs
        ``right_vectors=True``.
        """
        s = self._state
        V = self.right_factor()
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U = self._panels.lazy(s.Gu[:, perm])
        top, bottom = execute([U.max(axis=0), U.min(axis=0)], client=self.client)
        signs = np.where(np.asarray(top) >= -np.asarray(bottom), 1.0, -1.0)
        self._exposure = (self._version, perm, signs)  # the coordinates of `add`
        return U * signs, V[:, perm] * signs

    def _empty_copy(self, **changes: Any) -> TallCompressor:
        return TallCompressor(
            self.n, chunk_rows=self.chunk_rows, client=self.client, inner=self.inner,
            source_record=self.source_record, threads=self.threads,
            **{**self.options.as_dict(), **changes},
        )

    def _copied_basis(self, blank: BasisBackend) -> BasisBackend:
        """Return the panels copied into the copy's own work directory, as one panel.

        The copy is written chunk by chunk (``O(n w)`` on disk, never in memory), so the
        copy outlives the original and its store.
        """
        assert isinstance(blank, PanelBasis)
        blank.adopt(self._panels)
        return blank

    def __repr__(self) -> str:
        return (
            f"TallCompressor(n={self.n}, n_seen={self.n_seen}, rank={self.rank}, "
            f"panels={len(self._panels.panels)}, chunk_rows={self.chunk_rows}, "
            f"rule={self.rule!r}, sweeps={self.sweeps}, eps={self.eps}, rtol={self.rtol}, "
            f"max_rank={self.max_rank})"
        )
