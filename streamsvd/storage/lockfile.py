"""Keeping a second writer out of a basis store: a lock file locally, a lease in an object store.

:class:`FileLock` (a local directory). A writer creates ``writer.lock`` with
``O_CREAT | O_EXCL``; it holds the writer's pid, host name and start time, and the writer
keeps an advisory ``flock`` on it while the store is open. A lock whose holder is on this
host and no longer runs (its pid is gone, or its ``flock`` is released, which also covers
a reused pid) is stale and is taken over with a logged warning.

:class:`Lease` (an object store, which has neither ``O_EXCL`` nor ``flock``). A writer
creates the object ``writer.lease`` by a conditional ``PUT`` (``If-None-Match: *``:
refused when it exists); it holds a random holder id, the writer's pid, host, process
start time and an expiry time (:data:`LEASE_SECONDS` ahead). While the store is open a
background thread renews it every third of that time, each renewal a conditional ``PUT``
(``If-Match`` the ETag of the writer's last version: refused if anybody else wrote it).
Another writer finds a live lease and is refused; it takes over a lease that has
expired (its holder stopped renewing it: killed, or cut off for longer than the expiry)
or whose holder is on the same host and no longer runs, again by ``If-Match`` on the
ETag it read, so of two writers racing for a dead writer's lease exactly one wins and
the other gets :class:`~streamsvd.errors.StoreLockedError`. Expiry compares the holder's
clock with the reader's: clocks must agree to well within :data:`LEASE_SECONDS`.

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
import threading
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from streamsvd.errors import StoreError, StoreLockedError

__all__ = ["LEASE_SECONDS", "FileLock", "Lease"]

logger = logging.getLogger(__name__)

LEASE_SECONDS = 60.0
"""Lifetime of an object-store lease that is not renewed (seconds)."""

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



# ------------------------------------------------------------------------ lease


def _process_started(pid: int) -> float | None:
    """Start time of process ``pid`` (seconds since the epoch), None if it does not run."""
    import psutil

    try:
        return float(psutil.Process(pid).create_time())
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return None
    except psutil.Error:
        return -1.0  # exists but cannot be inspected: taken as running


def _describe_lease(info: dict[str, Any] | None) -> str:
    if info is None:
        return "a writer whose lease cannot be read"
    expires = info.get("expires")
    until = (
        datetime.fromtimestamp(float(expires), UTC).isoformat(timespec="seconds")
        if isinstance(expires, int | float)
        else "?"
    )
    return (
        f"pid {info.get('pid')} on host {info.get('host')!r} since {info.get('since')} "
        f"(lease valid until {until} unless renewed)"
    )


class Lease:
    """The ``writer.lease`` object of a store in an object store (see the module docstring).

    Parameters
    ----------
    storage : ObjectStorage
        Where the lease object lives (it must offer conditional writes).
    key : str
        Key of the lease object.
    seconds : float
        Lifetime of the lease without renewal; renewed every ``seconds / 3``.
    """

    def __init__(self, storage: Any, key: str, *, seconds: float = LEASE_SECONDS) -> None:
        self.storage = storage
        self.key = key
        self.seconds = float(seconds)
        self.where = f"{storage.url}/{key}"
        self.holder_id = uuid.uuid4().hex
        self.owner_pid = os.getpid()
        self.tag: str | None = None
        self.token = 1  # the fencing token: one more than the lease taken over
        self.lost = False
        self._mutex = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._since = _now()

    def _document(self) -> bytes:
        pid = os.getpid()
        return json.dumps({
            "holder": self.holder_id,
            "pid": pid,
            "host": socket.gethostname(),
            "started": _process_started(pid),
            "since": self._since,
            "token": self.token,
            "expires": time.time() + self.seconds,
        }).encode()

    def _read(self) -> tuple[dict[str, Any] | None, str] | None:
        seen = self.storage.get_tagged(self.key)
        if seen is None:
            return None
        raw, tag = seen
        try:
            info = json.loads(raw)
        except ValueError:
            info = None
        if not isinstance(info, dict) or not isinstance(info.get("expires"), int | float):
            info = None
        return info, tag

    @staticmethod
    def _stale_reason(info: dict[str, Any] | None) -> str | None:
        """Why the lease ``info`` is dead, or None if it may be live."""
        if info is None:
            return "its content cannot be read (a damaged lease)"
        late = time.time() - float(info["expires"])
        if late > 0:
            return f"it expired {late:.0f} s ago (its holder stopped renewing it)"
        pid = info.get("pid")
        if info.get("host") == socket.gethostname() and isinstance(pid, int):
            started = _process_started(pid)
            if started is None:
                return f"process {pid} on this host is no longer running"
            recorded = info.get("started")
            if isinstance(recorded, int | float) and started >= 0 and (
                abs(started - float(recorded)) > 1.0
            ):
                return f"process {pid} on this host is another process than its holder"
        return None

    def acquire(self) -> None:
        """Create the lease, taking over a dead writer's; raise if a live writer holds it."""
        for _attempt in range(8):
            tag = self.storage.put_if_absent(self.key, self._document())
            if tag is not None:
                self._held(tag)
                return
            seen = self._read()
            if seen is None:
                continue  # released meanwhile
            info, old = seen
            reason = self._stale_reason(info)
            if reason is None:
                raise StoreLockedError(
                    f"`path` {self.storage.url} is locked by another writer: "
                    f"{_describe_lease(info)} (lease object {self.where}). Close that "
                    "writer first, or open the store with mode='r' to read it without the "
                    f"lease; a dead writer's lease is taken over once it expires (at most "
                    f"{self.seconds:.0f} s after its last renewal)."
                )
            previous = info.get("token") if isinstance(info, dict) else None
            self.token = previous + 1 if isinstance(previous, int) else 2
            tag = self.storage.put_if_match(self.key, self._document(), old)
            if tag is None:
                raise StoreLockedError(
                    f"`path` {self.storage.url}: another writer took over the dead lease "
                    f"{self.where} first (a conditional write lost the race). Make sure a "
                    "single writer opens the store, then retry."
                )
            logger.warning(
                "taking over the lease %s held by %s: %s", self.where,
                _describe_lease(info), reason,
            )
            self._held(tag)
            return
        raise StoreLockedError(
            f"`path` {self.storage.url} could not be leased: the lease object {self.where} "
            "kept changing hands. Make sure a single writer opens the store, then retry."
        )

    def _held(self, tag: str) -> None:
        self.tag = tag
        self.owner_pid = os.getpid()
        self._thread = threading.Thread(
            target=self._heartbeat, name="streamsvd-lease", daemon=True
        )
        self._thread.start()

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.seconds / 3):
            try:
                if not self.renew():
                    return
            except OSError as exc:  # a transient failure: try again at the next beat
                logger.warning("could not renew the lease %s: %s", self.where, exc)

    def renew(self) -> bool:
        """Extend the lease by ``seconds`` if it is still ours; return whether it is."""
        with self._mutex:
            if self.tag is None or self.lost:
                return False
            tag = self.storage.put_if_match(self.key, self._document(), self.tag)
            if tag is None:
                self.lost = True
                logger.error("the lease %s was taken over by another writer", self.where)
                return False
            self.tag = tag
            return True

    def owned(self) -> bool:
        """Renew the lease now; whether it is still ours (checked before a pointer switch)."""
        return os.getpid() == self.owner_pid and self.renew()

    def held(self) -> bool:
        """Whether the lease object is still the version this writer last wrote.

        One ``GET``, checked before every write and delete of the writer (its fence): a
        writer whose lease was taken over changes nothing.
        """
        with self._mutex:  # not during a renewal, which changes the tag
            if self.tag is None or self.lost or os.getpid() != self.owner_pid:
                return False
            seen = self.storage.get_tagged(self.key)
            if seen is None or seen[1] != self.tag:
                self.lost = True
                return False
            return True

    def holder(self) -> str:
        """Describe the current holder of the lease."""
        seen = self._read()
        return "nobody" if seen is None else _describe_lease(seen[0])

    def release(self) -> None:
        """Stop renewing; delete the lease object if it is still ours."""
        if self.tag is None or os.getpid() != self.owner_pid:
            return
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        with self._mutex:
            try:
                seen = self.storage.get_tagged(self.key)
                if seen is not None and seen[1] == self.tag and not self.lost:
                    self.storage.delete(self.key)
                elif not self.lost:
                    logger.warning(
                        "the lease %s was taken over by %s; leaving it in place",
                        self.where, self.holder(),
                    )
            except OSError as exc:
                logger.warning(
                    "could not delete the lease %s (%s); it expires in %.0f s",
                    self.where, exc, self.seconds,
                )
            finally:
                self.tag = None
