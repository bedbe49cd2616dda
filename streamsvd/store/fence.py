"""The fence of a writer: every write and delete checked against its lock or lease.

A writer's every write and delete goes through its :class:`Fence`, which first checks
that the writer still holds its lock (locally: the lock file is still the one it
created) or its lease (in an object store: the lease object is still the version it last
wrote, one ``GET``). Objects are only ever *created* (``O_EXCL`` locally,
``If-None-Match: *`` in an object store), never overwritten, so a writer paused between
the check and its write (a zombie woken after a takeover) can at most add an object
that nobody names; it can neither replace another writer's object nor, through the
conditional pointer switch, its commit.

:func:`crash_point` marks the named steps of a commit; it does nothing, and the fault
tests replace it to interrupt a commit at each step.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from streamsvd.errors import StoreLockedError
from streamsvd.storage import Storage, remote_errors

logger = logging.getLogger(__name__)

CRASH_POINTS = (
    "pack-started",  # the generation's first object is written
    "pack-written",  # every object of the pack is written and durable
    "before-switch",  # the lock or lease was confirmed; the pointer is next
    "switched",  # the pointer names the new generation
    "marked",  # the commit record is written into the generation
    "collected",  # unused generations were deleted
)
"""The named steps of a commit, in order (see :func:`crash_point`)."""


def crash_point(name: str) -> None:
    """Mark the step ``name`` of a commit (one of :data:`CRASH_POINTS`); does nothing."""


class Fence:
    """Checks, before each write and delete, that the writer still holds its lock or lease.

    Parameters
    ----------
    storage : Storage
        Where the store lives.
    lock : FileLock or Lease or None
        The writer's lock or lease (None: a read-only handle, which writes nothing).
    path : pathlib.Path or str
        How the store is named in messages.
    """

    def __init__(self, storage: Storage, lock: Any, path: Path | str) -> None:
        self.storage = storage
        self.lock = lock
        self.path = path
        self.unreachable: tuple[type[BaseException], ...] = (OSError, *remote_errors())

    def holds(self) -> bool:
        """Whether the writer still holds its lock or lease."""
        return self.lock is not None and bool(self.lock.held())

    def check(self, doing: str) -> None:
        """Raise :class:`StoreLockedError` unless the writer still holds its lock or lease."""
        if not self.holds():
            holder = self.lock.holder() if self.lock is not None else "nobody"
            raise StoreLockedError(
                f"`store` {self.path} lost its writer lock to "
                f"{'a writer that has closed the store since' if holder == 'nobody' else holder}"
                "; nothing was "
                f"written or deleted ({doing}). Make sure a single writer opens the store."
            )

    def create(self, key: str, data: bytes) -> None:
        """Create the object ``key`` (never overwriting one) if the writer still holds the lock."""
        self.check(f"creating {key}")
        self.storage.create(key, data)

    def delete(self, key: str) -> bool:
        """Delete ``key`` if the writer still holds the lock; return whether it did.

        A lock or lease that cannot be checked (the object store unreachable) counts as
        lost: nothing is deleted.
        """
        try:
            held = self.holds()
        except self.unreachable as exc:
            logger.warning("not deleting %s/%s: the lock cannot be checked (%s)",
                           self.path, key, exc)
            return False
        if not held:
            logger.warning(
                "not deleting %s/%s: this writer no longer holds the lock of the store",
                self.path, key,
            )
            return False
        self.storage.delete(key)
        return True
