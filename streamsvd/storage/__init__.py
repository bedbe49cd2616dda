"""Where a basis store lives: a local directory or an object store, as keys and bytes.

A basis store (:mod:`streamsvd.store`) and the row panels of the tall mode
(:mod:`streamsvd.algebra.panels.basis`) speak to a *storage*: a root under which ``/``-separated
keys name small objects (the pointer, the lock or lease, JSON metadata) and zarr arrays
(opened through :meth:`LocalStorage.zarr_store` / :meth:`ObjectStorage.zarr_store`, a
zarr v3 store over the same root). :func:`open_storage` turns what the user passed into
one:

* a path or a ``file://`` URL: :class:`LocalStorage`, a directory. An overwrite is a
  temporary file, ``fsync``, :func:`os.replace` (atomic on POSIX) and an ``fsync`` of the
  directory; :meth:`LocalStorage.flush` makes what zarr wrote durable (zarr never calls
  ``fsync``); the writer lock is a file with an advisory ``flock``
  (:class:`streamsvd.storage.lockfile.FileLock`).
* any other fsspec URL (``s3://bucket/prefix``, with ``storage_options`` passed to the
  file system, and the usual ``AWS_*`` environment variables): :class:`ObjectStorage`.
  An object store has no rename: an overwrite is a single ``PUT``, which S3 and
  S3-compatible servers apply atomically (a reader gets the old or the new object whole,
  and, on S3 since 2020, every read after the ``PUT`` returned gets the new one). Writing
  needs *conditional* writes (``If-None-Match: *`` to create an object only if absent,
  ``If-Match: <ETag>`` to replace it only if unchanged), which the writer lease
  (:class:`streamsvd.storage.lease.Lease`) and the pointer switch use; they are implemented
  for ``s3://`` (through s3fs); other fsspec protocols can be read but not written.

A storage pickles without the secrets of its ``storage_options`` (``key``, ``secret``,
``token``, ...: :func:`without_secrets`): what dask sends to workers through the
scheduler carries no credentials, and a worker reaches the store with its own.

An object store needs the optional packages of the ``s3`` extra
(``pip install 'streamsvd[s3]'``); a missing one is reported by name.

The storages live in :mod:`streamsvd.storage.local` and :mod:`streamsvd.storage.objects`;
this module holds their protocol and :func:`open_storage`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

from streamsvd.errors import InputError
from streamsvd.storage.local import LocalStorage
from streamsvd.storage.objects import ObjectStorage, remote_errors, without_secrets

__all__ = [
    "PANELS",
    "LocalStorage",
    "ObjectStorage",
    "Storage",
    "is_url",
    "open_storage",
    "remote_errors",
    "without_secrets",
]

PANELS = "panels"
"""The directory under a store's root where a tall compressor keeps its basis, beside the
generations (:mod:`streamsvd.algebra.panels.files` writes it, before the commits that list
it, also before the first one: a store's creation; :mod:`streamsvd.store` knows it as its
own)."""


class Storage(Protocol):
    """The operations a basis store needs from where it lives (keys are ``a/b/c``)."""

    url: str
    """How the root is named in messages (a path or a URL)."""
    conditional: bool
    """Whether :meth:`put_if_absent` and :meth:`put_if_match` are available."""

    def exists(self) -> bool:
        """Whether the root exists (a directory, or a prefix holding objects)."""

    def is_file(self) -> bool:
        """Whether the root names a file or an object (not a directory)."""

    def get(self, key: str) -> bytes:
        """Return the bytes of ``key``; raise :class:`FileNotFoundError` if absent."""

    def get_tagged(self, key: str) -> tuple[bytes, str] | None:
        """Return the bytes of ``key`` and their version tag, or None if absent."""

    def put(self, key: str, data: bytes) -> None:
        """Replace ``key`` by ``data`` atomically and durably."""

    def put_if_absent(self, key: str, data: bytes) -> str | None:
        """Create ``key`` unless it exists; return its tag, or None if it existed."""

    def put_if_match(self, key: str, data: bytes, tag: str) -> str | None:
        """Replace ``key`` if its tag is ``tag``; return the new tag, or None if not."""

    def create(self, key: str, data: bytes) -> None:
        """Create ``key`` holding ``data`` durably; :class:`FileExistsError` if it exists."""

    def sync_dir(self, key: str) -> None:
        """Make the entries of the directory ``key`` (and ``key`` in its parent) durable."""

    def list(self, prefix: str = "") -> list[str]:
        """Return the names directly below ``prefix`` (sorted; empty if absent)."""

    def delete(self, key: str) -> None:
        """Delete ``key`` and everything below it (nothing if absent)."""

    def flush(self, key: str) -> None:
        """Make what was written below ``key`` durable."""

    def prepare(self) -> None:
        """Create the root if it must exist before keys are written below it."""

    def zarr_store(self, *, read_only: bool) -> Any:
        """Return a zarr v3 store rooted at the root."""

    def lock(self, key: str) -> Any:
        """Return the (not yet acquired) writer lock or lease of the object ``key``."""


def is_url(location: Any) -> bool:
    """Whether ``location`` is a string with a ``scheme://``."""
    return isinstance(location, str) and "://" in location


def open_storage(
    location: Any,
    *,
    storage_options: Mapping[str, Any] | None = None,
    argument: str = "path",
) -> LocalStorage | ObjectStorage:
    """Return the storage that ``location`` names.

    Parameters
    ----------
    location : str, os.PathLike, LocalStorage or ObjectStorage
        A local path, a ``file://`` URL, an fsspec URL (``s3://bucket/prefix``), or a
        storage (returned as is).
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...); not accepted with a local path.
    argument : str
        How the location is named in messages.

    Raises
    ------
    InputError
        ``location`` is of another type, or ``storage_options`` is given with a local
        path or is not a dict with string keys.
    OptionalDependencyError
        The URL needs a package of the ``s3`` extra that is not installed.
    """
    if storage_options is not None and (
        not isinstance(storage_options, Mapping)
        or not all(isinstance(k, str) for k in storage_options)
    ):
        raise InputError(
            f"`storage_options` must be a dict with string keys; got "
            f"{type(storage_options).__name__} {storage_options!r}."
        )
    if isinstance(location, LocalStorage | ObjectStorage):
        if storage_options:
            raise InputError(
                f"`storage_options` must be None when `{argument}` is a storage already; "
                f"got {dict(storage_options)!r}. Pass them to `open_storage`."
            )
        return location
    if is_url(location):
        scheme = location.split("://", 1)[0].lower()
        if scheme in ("file", "local"):
            if storage_options:
                raise InputError(
                    f"`storage_options` only apply to object-store URLs; got "
                    f"{dict(storage_options)!r} with `{argument}` {location!r}. Drop them."
                )
            return LocalStorage(Path(location.split("://", 1)[1]))
        return ObjectStorage(location, storage_options or {}, argument=argument)
    if isinstance(location, str | os.PathLike):
        if storage_options:
            raise InputError(
                f"`storage_options` only apply to object-store URLs; got "
                f"{dict(storage_options)!r} with the local `{argument}` {location!s}. Drop "
                "them, or pass a URL such as s3://bucket/basis.zarr."
            )
        return LocalStorage(Path(location))
    raise InputError(
        f"`{argument}` must be a local path (str or os.PathLike) or a URL such as "
        f"s3://bucket/basis.zarr; got {type(location).__name__} {location!r}."
    )
