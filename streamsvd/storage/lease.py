"""Keeping a second writer out of a basis store in an object store: the writer's lease.

:class:`Lease` keeps a second writer out of an object store, which has neither ``O_EXCL``
nor ``flock``. A writer creates the object ``writer.lease`` by a conditional ``PUT``
(``If-None-Match: *``: refused when it exists); it holds a random holder id, the writer's
pid, host, process start time and an expiry time (:data:`LEASE_SECONDS` ahead). While the
store is open a background thread renews it every third of that time, each renewal a
conditional ``PUT`` (``If-Match`` the ETag of the writer's last version: refused if
anybody else wrote it). Another writer finds a live lease and is refused; it takes over a
lease that has expired (its holder stopped renewing it: killed, or cut off for longer
than the expiry) or whose holder is on the same host and no longer runs, again by
``If-Match`` on the ETag it read, so of two writers racing for a dead writer's lease
exactly one wins and the other gets :class:`~streamsvd.errors.StoreLockedError`. Expiry
compares the holder's clock with the reader's: clocks must agree to well within
:data:`LEASE_SECONDS`.

Like :class:`~streamsvd.storage.lockfile.FileLock`, it raises
:class:`~streamsvd.errors.StoreLockedError` naming the holder, and offers ``acquire``,
``owned`` (checked before every pointer switch; the lease renews itself there),
``holder`` and ``release``.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
import uuid
from datetime import UTC, datetime
from typing import Any

from streamsvd.errors import StoreLockedError
from streamsvd.storage.lockfile import _now

__all__ = ["LEASE_SECONDS", "Lease"]

# the writer lock's logger: what the lease logs is named as before the move
logger = logging.getLogger("streamsvd.storage.lockfile")

LEASE_SECONDS = 60.0
"""Lifetime of an object-store lease that is not renewed (seconds)."""


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
