"""A basis store's storage in a local directory (see :mod:`streamsvd.storage`).

An overwrite is a temporary file, ``fsync``, :func:`os.replace` (atomic on POSIX) and an
``fsync`` of the directory; :meth:`LocalStorage.flush` makes what zarr wrote durable
(zarr never calls ``fsync``); the writer lock is a file with an advisory ``flock``
(:class:`streamsvd.storage.lockfile.FileLock`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

from streamsvd.errors import StoreError

__all__ = ["LocalStorage"]

logger = logging.getLogger(__name__)


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
        """Return the :class:`~streamsvd.storage.lockfile.FileLock` of the file ``key``."""
        from streamsvd.storage.lockfile import FileLock

        return FileLock(self._path(key))
