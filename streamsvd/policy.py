"""What ``streamsvd ingest`` does with STORE: create, continue or refuse it; undo a failed start.

* :func:`resuming`: with ``--resume``, a STORE that holds a store (it has a pointer, or
  has ever committed: a generation above 0, even with its pointer missing) is continued
  (opening a damaged one reports the damage); nothing, an empty directory or the
  leftovers of an interrupted creation gets a new store. Without ``--resume`` an
  existing STORE is refused.
* :func:`removed_on_failure`: a STORE that this command created is removed again if the
  command fails before committing a snapshot; a STORE that existed before, or holds
  committed snapshots, never is.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Iterator
from datetime import datetime
from typing import Any

from .errors import StoreError, StreamSVDError

__all__ = ["removed_on_failure", "resuming"]

logger = logging.getLogger(__name__)


def resuming(store: Any, *, resume: bool) -> bool:
    """Whether the command continues STORE (``--resume`` and STORE holds a store).

    Parameters
    ----------
    store : Storage
        Where STORE lives.
    resume : bool
        Whether ``--resume`` was given.

    Raises
    ------
    StoreError
        STORE exists and ``--resume`` was not given.
    """
    from .store import history

    kind = history(store)
    if not resume and store.exists():
        raise StoreError(
            f"STORE {store} already exists; pass --resume to continue it, or choose "
            "another path."
        )
    if resume and kind != "store":
        logger.info("STORE %s does not exist yet: --resume creates it", store)
    return bool(resume and kind == "store")


@contextlib.contextmanager
def removed_on_failure(store: Any, *, new: bool) -> Iterator[None]:
    """Remove STORE if this command created it (``new``) and fails before committing a snapshot."""
    started = math.floor(time.time())
    try:
        yield
    except BaseException:
        if new:
            _remove_new_store(store, since=started)
        raise


def _remove_new_store(store: Any, *, since: float) -> None:
    """Delete STORE if it holds no snapshot, no writer has it and it was created since."""
    from .store import LEASE_NAME, LOCK_NAME, history, open_store

    try:
        with open_store(store, "a") as st:  # the writer lock: no other writer is at work
            created = datetime.fromisoformat(st.root_attrs["created"]).timestamp()
            state = st.read()  # generation 0 (no arrays) or a commit of no snapshot
            empty = not state.arrays or int(state.attrs.get("source_offset", 0)) == 0
            if not (empty and created >= since):
                return
            logger.info("removing STORE %s: the command failed before its first commit", store)
            for entry in store.list():  # while the lock is held; the lock goes last
                if entry not in (LOCK_NAME, LEASE_NAME):
                    store.delete(entry)
    except (StreamSVDError, OSError, ValueError, KeyError):
        return  # not a store this command made, or one another writer holds
    if history(store) == "empty":
        with contextlib.suppress(OSError):
            store.delete("")
