"""Where a basis store lives: a local directory or an object store, as keys and bytes.

A basis store (:mod:`streamsvd.store`) and the row panels of the tall mode
(:mod:`streamsvd.panels`) speak to a *storage*: a root under which ``/``-separated keys
name small objects (the pointer, the lock or lease, JSON metadata) and zarr arrays
(opened through :meth:`LocalStorage.zarr_store` / :meth:`ObjectStorage.zarr_store`, a
zarr v3 store over the same root). :func:`open_storage` turns what the user passed into
one:

* a path or a ``file://`` URL: :class:`LocalStorage`, a directory. An overwrite is a
  temporary file, ``fsync``, :func:`os.replace` (atomic on POSIX) and an ``fsync`` of the
  directory; :meth:`LocalStorage.flush` makes what zarr wrote durable (zarr never calls
  ``fsync``); the writer lock is a file with an advisory ``flock``
  (:class:`streamsvd.locks.FileLock`).
* any other fsspec URL (``s3://bucket/prefix``, with ``storage_options`` passed to the
  file system, and the usual ``AWS_*`` environment variables): :class:`ObjectStorage`.
  An object store has no rename: an overwrite is a single ``PUT``, which S3 and
  S3-compatible servers apply atomically (a reader gets the old or the new object whole,
  and, on S3 since 2020, every read after the ``PUT`` returned gets the new one). Writing
  needs *conditional* writes (``If-None-Match: *`` to create an object only if absent,
  ``If-Match: <ETag>`` to replace it only if unchanged), which the writer lease
  (:class:`streamsvd.locks.Lease`) and the pointer switch use; they are implemented for
  ``s3://`` (through s3fs); other fsspec protocols can be read but not written.

An object store needs the optional packages of the ``s3`` extra
(``pip install 'streamsvd[s3]'``); a missing one is reported by name.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import shutil
import uuid
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, Protocol, TypeVar, cast

from .errors import InputError, OptionalDependencyError, StoreError

__all__ = ["LocalStorage", "ObjectStorage", "Storage", "open_storage"]

logger = logging.getLogger(__name__)

_EXTRA_HINT = "Install the object-store extra: pip install 'streamsvd[s3]'."


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


# ------------------------------------------------------------------------ local


def _write_new_file(path: Path, data: bytes) -> None:
    """Create ``path`` (``O_EXCL``), write all of ``data`` and ``fsync`` it."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_path(path: Path, *, directory: bool = False) -> None:
    flags = os.O_RDONLY | (os.O_DIRECTORY if directory else 0)
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class LocalStorage:
    """A local directory (see the module docstring).

    Parameters
    ----------
    root : pathlib.Path
        The directory (it may not exist yet).
    """

    conditional = False

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.url = str(self.root)

    def __repr__(self) -> str:
        return f"LocalStorage({self.url!r})"

    def __str__(self) -> str:
        return self.url

    def _path(self, key: str) -> Path:
        return self.root / key if key else self.root

    def exists(self) -> bool:
        """Whether the directory (or a file of that name) exists."""
        return self.root.exists()

    def is_file(self) -> bool:
        """Whether the root is a file."""
        return self.root.exists() and not self.root.is_dir()

    def get(self, key: str) -> bytes:
        """Return the bytes of the file ``key``."""
        return self._path(key).read_bytes()

    def get_tagged(self, key: str) -> tuple[bytes, str] | None:
        """Return the bytes of ``key`` and ``"<inode>:<mtime_ns>"``, or None if absent."""
        path = self._path(key)
        try:
            st = path.stat()
            return path.read_bytes(), f"{st.st_ino}:{st.st_mtime_ns}"
        except FileNotFoundError:
            return None

    def put(self, key: str, data: bytes) -> None:
        """Replace ``key`` atomically: temporary file, fsync, rename, fsync of the directory."""
        path = self._path(key)
        tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.tmp")
        try:
            _write_new_file(tmp, data)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise
        _fsync_path(path.parent, directory=True)

    def create(self, key: str, data: bytes) -> None:
        """Create the file ``key`` (``O_EXCL``) holding ``data`` and ``fsync`` it.

        A partly written file is removed when writing fails (a full disk), so a failed
        call leaves nothing behind; :class:`FileExistsError` if ``key`` exists.
        """
        path = self._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            _write_new_file(path, data)
        except BaseException:
            with contextlib.suppress(OSError):
                path.unlink()
            raise

    def sync_dir(self, key: str) -> None:
        """``fsync`` the directory ``key`` and the directory holding it."""
        path = self._path(key)
        _fsync_path(path, directory=True)
        _fsync_path(path.parent, directory=True)

    def put_if_absent(self, key: str, data: bytes) -> str | None:
        """Not used locally (the file lock keeps writers out); raises StoreError."""
        raise StoreError(f"`store` {self.url}: a local directory has no conditional writes.")

    def put_if_match(self, key: str, data: bytes, tag: str) -> str | None:
        """Not used locally (the file lock keeps writers out); raises StoreError."""
        raise StoreError(f"`store` {self.url}: a local directory has no conditional writes.")

    def list(self, prefix: str = "") -> list[str]:
        """Return the entries of the directory ``prefix``."""
        try:
            return sorted(entry.name for entry in self._path(prefix).iterdir())
        except (FileNotFoundError, NotADirectoryError):
            return []

    def delete(self, key: str) -> None:
        """Delete the file or directory tree ``key`` (a failure is logged, not raised)."""
        path = self._path(key)
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            logger.warning("could not delete %s: %s", path, exc)

    def flush(self, key: str) -> None:
        """Flush every file and directory below ``key`` and the directory holding it."""
        top = self._path(key)
        for dirpath, _dirnames, filenames in os.walk(top):
            for name in filenames:
                _fsync_path(Path(dirpath) / name)
            _fsync_path(Path(dirpath), directory=True)
        _fsync_path(top.parent, directory=True)

    def prepare(self) -> None:
        """Create the directory (and its parents)."""
        self.root.mkdir(parents=True, exist_ok=True)

    def zarr_store(self, *, read_only: bool) -> Any:
        """Return a :class:`zarr.storage.LocalStore` on the directory."""
        from zarr.storage import LocalStore

        return LocalStore(self.root, read_only=read_only)

    def lock(self, key: str) -> Any:
        """Return the :class:`~streamsvd.locks.FileLock` of the file ``key``."""
        from .locks import FileLock

        return FileLock(self._path(key))


# ----------------------------------------------------------------------- object


def remote_errors() -> tuple[type[BaseException], ...]:
    """Exceptions an object-store client raises besides :class:`OSError` (botocore's)."""
    try:
        from botocore.exceptions import BotoCoreError
    except ImportError:
        return ()
    return (BotoCoreError,)


@contextlib.contextmanager
def _reaching(named: str) -> Iterator[None]:
    """Report a failure to reach the object store as a StoreError naming it."""
    errors = remote_errors()
    try:
        yield
    except errors as exc:
        raise StoreError(
            f"{named} cannot be reached ({type(exc).__name__}: {exc}). Check the "
            "endpoint, the network and the credentials (AWS_* variables, "
            "`storage_options`)."
        ) from exc


_F = TypeVar("_F", bound=Callable[..., Any])


def _reached(method: _F) -> _F:
    """Run an :class:`ObjectStorage` method under :func:`_reaching`."""

    @functools.wraps(method)
    def wrapper(self: ObjectStorage, *args: Any, **kwargs: Any) -> Any:
        with _reaching(self.named):
            return method(self, *args, **kwargs)

    return cast(_F, wrapper)


def _precondition_failed(exc: BaseException) -> bool:
    """Whether ``exc`` (as s3fs translates it) is an HTTP 412 or 409 refusal."""
    text = str(exc)
    return isinstance(exc, FileExistsError) or any(
        word in text
        for word in ("PreconditionFailed", "pre-conditions", "precondition",
                     "ConditionalRequestConflict")
    )


class ObjectStorage:
    """A prefix in an object store reached through fsspec (see the module docstring).

    Parameters
    ----------
    url : str
        ``protocol://bucket/prefix``.
    storage_options : dict
        Passed to the fsspec file system (for s3fs: ``key``, ``secret``,
        ``endpoint_url``, ``client_kwargs``, ...).
    argument : str
        How the location is named in messages (``"store"``, ``"source"``, ...).
    """

    def __init__(
        self, url: str, storage_options: Mapping[str, Any], *, argument: str = "store"
    ) -> None:
        import fsspec

        self.url = url.rstrip("/")
        self.storage_options = dict(storage_options)
        self.argument = argument
        self.named = f"`{argument}` {self.url}"
        try:
            fs, path = fsspec.url_to_fs(self.url, **self.storage_options)
        except ImportError as exc:
            raise OptionalDependencyError(
                f"`{argument}` {url} needs a package that is not installed ({exc}). {_EXTRA_HINT}"
            ) from None
        except (ValueError, TypeError) as exc:
            raise InputError(
                f"`{argument}` {url!r} is not a URL fsspec can open ({exc}). Pass a local path "
                "or a URL such as s3://bucket/basis.zarr, and valid `storage_options`."
            ) from None
        self.fs = fs
        self.path = str(path).rstrip("/")
        protocols = fs.protocol if isinstance(fs.protocol, tuple | list) else (fs.protocol,)
        self.conditional = "s3" in protocols

    def __repr__(self) -> str:
        return f"ObjectStorage({self.url!r})"

    def __str__(self) -> str:
        return self.url

    def __reduce__(self) -> Any:
        return (_rebuild, (self.url, self.storage_options, self.argument))

    def _full(self, key: str) -> str:
        return f"{self.path}/{key}" if key else self.path

    def _bucket_key(self, key: str) -> tuple[str, str]:
        bucket, _, rest = self._full(key).partition("/")
        return bucket, rest

    @_reached
    def exists(self) -> bool:
        """Whether an object exists below the prefix (or the prefix is an object)."""
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.exists(self.path))

    @_reached
    def is_file(self) -> bool:
        """Whether the prefix names an object."""
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.isfile(self.path))

    @_reached
    def get(self, key: str) -> bytes:
        """Return the bytes of the object ``key``."""
        return cast(bytes, self.fs.cat_file(self._full(key)))

    @_reached
    def get_tagged(self, key: str) -> tuple[bytes, str] | None:
        """Return the bytes of ``key`` and its ETag from one ``GET``, or None if absent."""
        from fsspec.asyn import sync

        bucket, name = self._bucket_key(key)

        async def fetch() -> tuple[bytes, str]:
            out = await self.fs._call_s3("get_object", Bucket=bucket, Key=name)
            body = out["Body"]
            try:
                data = await body.read()
            finally:
                body.close()
            return data, str(out["ETag"])

        try:
            return sync(self.fs.loop, fetch)
        except FileNotFoundError:
            return None

    @_reached
    def put(self, key: str, data: bytes) -> None:
        """Write the object ``key`` with one ``PUT``."""
        self.fs.pipe_file(self._full(key), data)

    @_reached
    def _conditional_put(self, key: str, data: bytes, condition: dict[str, str]) -> str | None:
        if not self.conditional:
            raise StoreError(
                f"{self.named}: writing needs conditional writes (If-None-Match, "
                "If-Match), which streamsvd implements for s3:// only. Write to an s3:// "
                "URL or a local directory; other URLs can be read."
            )
        bucket, name = self._bucket_key(key)
        try:
            out = self.fs.call_s3(
                "put_object", Bucket=bucket, Key=name, Body=data, **condition
            )
        except OSError as exc:
            if _precondition_failed(exc):
                return None
            if isinstance(exc, FileNotFoundError) and "IfMatch" in condition:
                return None  # If-Match on an object deleted meanwhile: not matched either
            raise
        return str(out["ETag"])

    def create(self, key: str, data: bytes) -> None:
        """``PUT`` with ``If-None-Match: *``; :class:`FileExistsError` if ``key`` exists."""
        if self.put_if_absent(key, data) is None:
            raise FileExistsError(f"{self.url}/{key} exists already")

    def sync_dir(self, key: str) -> None:
        """Nothing to do: an object is durable when its ``PUT`` returns."""

    def put_if_absent(self, key: str, data: bytes) -> str | None:
        """``PUT`` with ``If-None-Match: *``; None when the object already exists."""
        return self._conditional_put(key, data, {"IfNoneMatch": "*"})

    def put_if_match(self, key: str, data: bytes, tag: str) -> str | None:
        """``PUT`` with ``If-Match: tag``; None when the object changed or is gone."""
        return self._conditional_put(key, data, {"IfMatch": tag})

    @_reached
    def list(self, prefix: str = "") -> list[str]:
        """Return the names directly below ``prefix``."""
        full = self._full(prefix)
        self.fs.invalidate_cache(full)
        try:
            entries = self.fs.ls(full, detail=False)
        except FileNotFoundError:
            return []
        return sorted({str(e).rstrip("/").rsplit("/", 1)[-1] for e in entries} - {""})

    @_reached
    def delete(self, key: str) -> None:
        """Delete the object ``key`` and every object below ``key/``."""
        full = self._full(key)
        self.fs.invalidate_cache(full)
        try:
            self.fs.rm(full, recursive=True)  # one listing, then a batched delete
        except FileNotFoundError:
            pass
        except OSError as exc:
            logger.warning("could not delete %s: %s", full, exc)
        self.fs.invalidate_cache(full)

    def flush(self, key: str) -> None:
        """Nothing to do: an object is durable when its ``PUT`` returns."""

    def prepare(self) -> None:
        """Nothing to do: prefixes need not be created."""

    def zarr_store(self, *, read_only: bool) -> Any:
        """Return a :class:`zarr.storage.FsspecStore` on the prefix."""
        from zarr.storage import FsspecStore

        return FsspecStore.from_url(
            self.url, storage_options=dict(self.storage_options), read_only=read_only
        )

    def lock(self, key: str) -> Any:
        """Return the :class:`~streamsvd.locks.Lease` of the object ``key``."""
        from .locks import Lease

        return Lease(self, key)


def _rebuild(url: str, storage_options: dict[str, Any], argument: str) -> ObjectStorage:
    """Unpickle an :class:`ObjectStorage` (its file system is opened anew)."""
    return ObjectStorage(url, storage_options, argument=argument)


# ------------------------------------------------------------------------ entry


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
