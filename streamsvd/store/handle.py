"""The store handle: :class:`BasisStore` and :func:`open_store`.

A thin handle: the public face of its :class:`~streamsvd.store.session.Session`, which
checks the root and the pointer on opening (:mod:`~streamsvd.store.reading`), reads,
plans what a commit writes (:mod:`streamsvd.store.segments`) and hands it to its
:class:`~streamsvd.store.commit.Writer`, which owns the fence, the pointer switch and the
collector. The handle checks its arguments and its mode, and closes.
"""

from __future__ import annotations

import logging
import os
import weakref
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

from streamsvd.errors import StoreError
from streamsvd.storage import Storage
from streamsvd.store.format import DEFAULT_CHUNK_BYTES, StoreState, normalise_attrs
from streamsvd.store.reading import read_current
from streamsvd.store.segments import Appended, Piece
from streamsvd.store.session import Session

logger = logging.getLogger("streamsvd.store")


class BasisStore:
    """A versioned, crash-safe basis store in a zarr v3 group (a directory or an object store).

    Open one with :func:`open_store` or create one with :meth:`BasisStore.create`; see
    :mod:`streamsvd.store` for the layout and the guarantees. A store opened for writing
    holds the writer lock (the lease, on an object store) until :meth:`close` (also
    called on leaving a ``with`` block). The parameters, and the errors raised on opening,
    are those of :func:`open_store`.
    """

    def __init__(self, path: str | os.PathLike[str] | Storage, mode: Literal["r", "a"] = "r", *,
                 n: int | None = None, dtype: Any = None, inner_fingerprint: str | None = None,
                 storage_options: Mapping[str, Any] | None = None) -> None:
        self._setup(Session.open(path, mode, n=n, dtype=dtype,
                                 inner_fingerprint=inner_fingerprint,
                                 storage_options=storage_options))

    def _setup(self, session: Session) -> None:
        self._session = session
        self._lock = session.lock  # held until close (None: a reader)
        self._closed = False
        creation = session.creation
        release = (creation.close if creation is not None
                   else self._lock.release if self._lock is not None else None)
        self._finalizer = weakref.finalize(self, release) if release is not None else None

    @classmethod
    def begin(cls, path: str | os.PathLike[str] | Storage, *, n: int, dtype: Any = "float64",
              inner_fingerprint: str, chunk_bytes: int = DEFAULT_CHUNK_BYTES,
              storage_options: Mapping[str, Any] | None = None) -> BasisStore:
        """Start creating a store at ``path``; its first :meth:`commit` creates it.

        The lock is taken and the root metadata written, but no pointer: the store
        exists once the first commit (generation 0) switched the pointer to it. Until
        then the caller may write its own objects under the store (see
        :data:`~streamsvd.storage.PANELS`); a first commit that fails, or
        :meth:`close` before it, deletes everything written under the store, and a
        process killed meanwhile leaves the leftovers of an interrupted creation, which
        opening reports and the next creation replaces.

        Parameters
        ----------
        path, n, dtype, inner_fingerprint, chunk_bytes, storage_options
            As for :meth:`create`.

        Returns
        -------
        BasisStore
            The handle, opened with mode ``"a"`` (it holds the writer lock), at
            generation -1 (nothing committed).

        Raises
        ------
        StoreError
            A store or other files exist at ``path``, or writing failed (nothing is left
            behind then; the message names the step).
        StoreLockedError
            Another process is creating or writing a store at ``path``.
        """
        self = cls.__new__(cls)
        self._setup(Session.begin(path, n=n, dtype=dtype, inner_fingerprint=inner_fingerprint,
                                  chunk_bytes=chunk_bytes, storage_options=storage_options))
        return self

    @classmethod
    def create(cls, path: str | os.PathLike[str] | Storage, *, n: int, dtype: Any = "float64",
               inner_fingerprint: str, attrs: Mapping[str, Any] | None = None,
               chunk_bytes: int = DEFAULT_CHUNK_BYTES,
               storage_options: Mapping[str, Any] | None = None) -> BasisStore:
        """Create a new store at ``path`` and return it opened for writing (generation 0).

        Parameters
        ----------
        path : str, os.PathLike or Storage
            A directory, ``file://`` or ``s3://`` URL where nothing is stored yet (the
            leftovers of an interrupted creation are replaced; a store that ever committed
            never is), or a storage.
        n : int
            Snapshot size (the number of rows of ``U``).
        dtype : {"float64", "float32"}
            Dtype in which every array is stored; committed arrays are cast to it.
        inner_fingerprint : str
            Fingerprint of the inner product (``inner.fingerprint``).
        attrs : dict, optional
            JSON-able attributes of generation 0.
        chunk_bytes : int
            Target size of one uncompressed chunk.
        storage_options : dict, optional
            Options of the fsspec file system of a URL.

        Returns
        -------
        BasisStore
            The store, opened with mode ``"a"`` (it holds the writer lock).

        Raises
        ------
        StoreError
            A store or other files exist at ``path``, or writing failed (nothing is left
            behind then; the message names the step).
        StoreLockedError
            Another process is creating or writing a store at ``path``.
        """
        user_attrs = normalise_attrs(attrs)
        self = cls.begin(path, n=n, dtype=dtype, inner_fingerprint=inner_fingerprint,
                         chunk_bytes=chunk_bytes, storage_options=storage_options)
        try:
            self._write_generation(0, {}, [], user_attrs)
        except BaseException:
            self.close()  # the lock of a store whose pointer switch took effect
            raise
        logger.info("created basis store %s (n=%d, dtype=%s)", self.path, self.n, self.dtype)
        return self

    # --------------------------------------------------------------- properties

    @property
    def path(self) -> Path | str:
        """Directory of the store (a Path), or its URL on an object store."""
        return self._session.path

    @property
    def storage(self) -> Storage:
        """The storage the store lives in (what a backend writes its own arrays to)."""
        return self._session.storage

    @property
    def mode(self) -> str:
        """``"r"`` (read only) or ``"a"`` (read and commit)."""
        return self._session.mode

    @property
    def format_version(self) -> int:
        """Format version of the store layout."""
        return int(self._session.root_attrs["format_version"])

    @property
    def generation(self) -> int:
        """Number of the current generation, as last seen by this handle."""
        return self._session.generation

    @property
    def n(self) -> int:
        """Snapshot size recorded at creation."""
        return int(self._session.root_attrs["n"])

    @property
    def dtype(self) -> str:
        """Dtype of the stored arrays."""
        return str(self._session.root_attrs["dtype"])

    @property
    def inner_fingerprint(self) -> str:
        """Fingerprint of the inner product recorded at creation."""
        return str(self._session.root_attrs["inner_fingerprint"])

    @property
    def root_attrs(self) -> dict[str, Any]:
        """Root attributes (format, version, n, dtype, fingerprint, created, ...)."""
        return dict(self._session.root_attrs)

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    @property
    def last_written(self) -> dict[str, int]:
        """Elements written per array name by the last :meth:`commit` of this handle."""
        return dict(self._session.written)

    # -------------------------------------------------------------------- reading

    def read(self, *, generation: int | None = None) -> StoreState:
        """Read the current generation (or the retained previous one), checksums verified.

        A reader (mode ``"r"``) whose generation is collected during the read reads the
        new pointer's, for as long as the pointer moves; only a generation that fails to
        verify while the pointer names it is damaged.

        Raises
        ------
        StoreFormatError
            The generation is missing or damaged; the previous generation is not
            substituted silently (the message names the last readable one).
        """
        self._check_open()
        session = self._session
        if session.generation < 0:
            raise StoreError(
                f"`store` {session.path} is being created: nothing was committed yet. "
                "Commit its first generation before reading it."
            )
        state, pointer = read_current(session.storage, self._load, generation,
                                      retry=session.mode == "r")
        session.follow(pointer)
        return state

    def _load(self, k: int, attrs_sha256: str | None) -> StoreState:
        return self._session.load(k, attrs_sha256)

    # --------------------------------------------------------------------- writing

    def commit(self, arrays: Mapping[str, Any], attrs: Mapping[str, Any] | None = None, *,
               appended: Mapping[str, Appended] | None = None) -> int:
        """Write ``arrays`` and ``attrs`` as a new generation and make it current.

        The switch is atomic: a reader, or a process reopening the store after this one
        was killed at any instant, sees the previous generation or the new one, whole.
        If the commit fails, the previous generation stays current and intact.

        Parameters
        ----------
        arrays : dict of str to array_like
            Named real 1-D or 2-D arrays, written whole (cast to the store's dtype, finite).
        attrs : dict, optional
            JSON-able attributes of the generation.
        appended : dict of str to Appended, optional
            Arrays that keep the unchanged part of the current generation's and write the
            rest (:class:`~streamsvd.store.segments.Appended`).

        Returns
        -------
        int
            Number of the new generation.

        Raises
        ------
        StoreError
            The store is read-only or closed, or writing failed.
        StoreLockedError
            The lock was taken over by another writer meanwhile (nothing was written).
        """
        self._check_open()
        if self.mode != "a":
            raise StoreError(
                f"`store` {self.path} was opened read-only (mode='r'); commit needs "
                "mode='a'. Reopen it with `open_store(path, mode='a')`."
            )
        k = self.generation + 1
        records, pieces = self._session.plan(arrays, appended, k)
        user_attrs = normalise_attrs(attrs)
        self._write_generation(k, records, pieces, user_attrs)
        return k

    def _write_generation(self, k: int, records: dict[str, Any], pieces: list[Piece],
                          user_attrs: dict[str, Any]) -> None:
        creation = self._session.creation
        try:
            pointer = self._session.write(k, records, pieces, user_attrs)
        except BaseException as exc:
            if creation is None or creation.done:
                raise
            self._closed = True
            if self._finalizer is not None:
                self._finalizer.detach()  # the creation releases the lock as it undoes
            creation.abort(exc, f"writing generation {k} and its pointer")
        self._session.settle(k, pointer)

    # --------------------------------------------------------------------- closing

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(
                f"`store` {self.path} is closed. Open it again with `open_store(path)`."
            )

    def close(self) -> None:
        """Release the writer lock (if held); the handle cannot be used afterwards.

        A store begun with :meth:`begin` that has not committed yet is deleted whole.
        """
        if self._closed:
            return
        self._closed = True
        if self._finalizer is not None:
            self._finalizer()

    def __enter__(self) -> BasisStore:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"mode={self.mode!r}"
        return (
            f"BasisStore({str(self.path)!r}, {state}, generation={self.generation}, "
            f"n={self.n}, dtype={self.dtype!r})"
        )


def open_store(
    path: str | os.PathLike[str] | Storage,
    mode: Literal["r", "a"] = "r",
    *,
    n: int | None = None,
    dtype: Any = None,
    inner_fingerprint: str | None = None,
    storage_options: Mapping[str, Any] | None = None,
) -> BasisStore:
    """Open an existing basis store.

    Parameters
    ----------
    path : str, os.PathLike or Storage
        Directory of the store, a ``file://`` or ``s3://`` URL, or a storage from
        :func:`streamsvd.storage.open_storage`.
    mode : {"r", "a"}
        ``"r"`` to read only (no lock is taken), ``"a"`` to read and commit (takes the
        writer lock; leftovers of interrupted commits are deleted).
    n, dtype, inner_fingerprint : optional
        Expected snapshot size, stored dtype and inner-product fingerprint; each one
        given is checked against the store.
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...); the ``AWS_*`` environment variables apply too.

    Returns
    -------
    BasisStore
        The open store; use it as a context manager or call :meth:`BasisStore.close`.

    Raises
    ------
    StoreFormatError
        ``path`` is not a basis store, is damaged, or has another format version.
    StoreMismatchError
        An expectation differs from what the store holds.
    StoreLockedError
        ``mode="a"`` and another live writer holds the lock.
    """
    return BasisStore(
        path, mode, n=n, dtype=dtype, inner_fingerprint=inner_fingerprint,
        storage_options=storage_options,
    )
