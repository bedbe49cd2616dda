"""Keeping a second writer out of a basis store: a lock file locally, a lease in an object store.

:class:`FileLock` (a local directory). A writer creates ``writer.lock`` with
``O_CREAT | O_EXCL``; it holds the writer's pid, host name and start time, and the writer
keeps an advisory ``flock`` on it while the store is open. A lock whose holder is on this
host and no longer runs (its pid is gone, or its ``flock`` is released, which also covers
a reused pid) is stale and is taken over with a logged warning.

:class:`~streamsvd.storage.lease.Lease` (an object store, which has neither ``O_EXCL``
nor ``flock``): a conditional ``PUT`` of ``writer.lease``, renewed while the store is
open (:mod:`streamsvd.storage.lease`).

Both raise :class:`~streamsvd.errors.StoreLockedError` naming the holder, and both offer
``acquire``, ``owned`` (checked before every pointer switch; the lease renews itself
there), ``holder`` and ``release``.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import socket
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from streamsvd.errors import StoreError, StoreLockedError

__all__ = ["FileLock"]

logger = logging.getLogger(__name__)

LOCK_NAME = "writer.lock"
# A lock file without content is given this long (seconds) to be filled by its creator.
_LOCK_FILL_GRACE = 0.2


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OverflowError:
        return False
    return True


def _flock_free(path: Path) -> bool | None:
    """Whether nobody holds an advisory lock on ``path`` (None if it cannot be told)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return None
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return True
    finally:
        os.close(fd)


def _describe_holder(info: dict[str, Any] | None) -> str:
    if info is None:
        return "a writer that has not yet written its pid into the lock file"
    return f"pid {info.get('pid')} on host {info.get('host')!r} since {info.get('since')}"


class FileLock:
    """The ``writer.lock`` file of a local store (see the module docstring)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd: int | None = None
        self.owner_pid = os.getpid()

    def acquire(self) -> None:
        """Create the lock file, taking over a stale one; raise if a live writer holds it."""
        if self.path.is_dir():
            raise StoreError(
                f"`path` {self.path.parent} cannot be locked: its lock {self.path} is a "
                "directory, not the lock file streamsvd writes. Move that directory away "
                "(no streamsvd writer made it), then retry."
            )
        for _attempt in range(8):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                seen = self._read()
                if seen is None:
                    continue  # released meanwhile
                info, raw, ident = seen
                reason = self._stale_reason(info)
                if reason is None:
                    again = self._read()
                    if again is None or again[2] != ident:
                        continue  # replaced meanwhile
                    raise StoreLockedError(
                        f"`path` {self.path.parent} is locked by another writer: "
                        f"{_describe_holder(info)} (lock file {self.path}). Close that "
                        "writer first, open the store with mode='r' to read it without the "
                        "lock, or delete the lock file if that process is gone."
                    ) from None
                self._take_over(info, raw, ident, reason)
            else:
                try:
                    self._fill(fd)
                except BaseException:  # a full disk: leave no empty lock file behind
                    os.close(fd)
                    with contextlib.suppress(OSError):
                        os.unlink(self.path)
                    self.fd = None
                    raise
                return
        raise StoreLockedError(
            f"`path` {self.path.parent} could not be locked: the lock file {self.path} kept "
            "changing hands. Make sure a single writer opens the store, then retry."
        )

    def _fill(self, fd: int) -> None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            flocked = True
        except OSError:
            flocked = False
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": _now(),
            "flock": flocked,
        }
        os.write(fd, json.dumps(info).encode())
        os.fsync(fd)
        self.fd = fd
        self.owner_pid = os.getpid()

    def _read(self) -> tuple[dict[str, Any] | None, bytes, tuple[int, int]] | None:
        """Return (parsed content or None, raw bytes, (device, inode)), or None if absent."""
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except FileNotFoundError:
            return None
        try:
            st = os.fstat(fd)
            raw = os.read(fd, 65536)
        finally:
            os.close(fd)
        info: dict[str, Any] | None
        try:
            info = json.loads(raw)
        except ValueError:
            info = None
        if not isinstance(info, dict) or not isinstance(info.get("pid"), int):
            info = None
        return info, raw, (st.st_dev, st.st_ino)

    def _stale_reason(self, info: dict[str, Any] | None) -> str | None:
        """Why the lock described by ``info`` is stale, or None if it is (maybe) live."""
        if info is None:
            if _flock_free(self.path):
                time.sleep(_LOCK_FILL_GRACE)
                again = self._read()
                if again is not None and again[0] is None and _flock_free(self.path):
                    return "its holder stopped before writing into it (the file is empty)"
            return None
        if info.get("host") != socket.gethostname():
            return None
        pid = int(info["pid"])
        if not _pid_alive(pid):
            return f"process {pid} is no longer running"
        if info.get("flock") and _flock_free(self.path):
            return f"its holder released it (pid {pid} now belongs to another process)"
        return None

    def _take_over(
        self, info: dict[str, Any] | None, raw: bytes, ident: tuple[int, int], reason: str
    ) -> None:
        """Move the stale lock file away, unless another writer replaced it meanwhile."""
        moved = self.path.with_name(f"{LOCK_NAME}.stale-{uuid.uuid4().hex}")
        try:
            os.rename(self.path, moved)
        except FileNotFoundError:
            return
        st = os.stat(moved)
        if (st.st_dev, st.st_ino) != ident or moved.read_bytes() != raw:
            # Another writer replaced the stale lock in between: put its lock back.
            with contextlib.suppress(FileExistsError):
                os.link(moved, self.path)
            moved.unlink()
            return
        moved.unlink()
        logger.warning(
            "taking over the stale lock %s held by %s: %s",
            self.path,
            _describe_holder(info),
            reason,
        )

    def owned(self) -> bool:
        """Whether the lock file is still the one this object created."""
        if self.fd is None:
            return False
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return False
        mine = os.fstat(self.fd)
        return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)

    def held(self) -> bool:
        """Whether this process still holds the lock (checked before every write and delete)."""
        return os.getpid() == self.owner_pid and self.owned()

    def holder(self) -> str:
        """Describe the current holder of the lock file."""
        seen = self._read()
        return "nobody" if seen is None else _describe_holder(seen[0])

    def release(self) -> None:
        """Delete the lock file if it is still ours; close its descriptor."""
        if self.fd is None or os.getpid() != self.owner_pid:
            return
        try:
            if self.owned():
                os.unlink(self.path)
            else:
                logger.warning(
                    "the lock %s was taken over by %s; leaving it in place",
                    self.path,
                    self.holder(),
                )
        finally:
            os.close(self.fd)
            self.fd = None
