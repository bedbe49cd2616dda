"""Creating a store: all of it, or nothing.

A store exists once its pointer names its first generation: the pointer is written
last. :func:`begin_store` takes the writer lock or lease and writes the root metadata
(each object created anew, through the writer's fence), and returns the
:class:`Creation`; the handle's first commit (generation 0) writes the generation and
switches the pointer to it. Until that switch, the caller may write its own objects
under the store (a tall compressor's panels, :data:`~streamsvd.storage.PANELS`),
and if any step fails or the handle is closed first (a full disk, a lost connection,
Ctrl-C), everything written under the store is deleted again, the lock released and a
root directory it made removed, and the error says which store and which step failed.
A process killed meanwhile leaves no pointer: opening the store reports an interrupted
creation, and the next creation replaces its leftovers. Only an empty location, or the
leftovers of an interrupted creation (root metadata, a lock, an uncommitted generation
0, panels, never a pointer nor a committed generation), is created over.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any, NoReturn

import zarr
from zarr.storage import MemoryStore

from streamsvd.errors import StoreError, StoreLockedError
from streamsvd.storage import Storage, remote_errors
from streamsvd.store.commit import Writer
from streamsvd.store.format import (
    FORMAT,
    FORMAT_VERSION,
    GENERATIONS,
    POINTER_NAME,
    check_dtype,
    check_fingerprint,
    library_version,
    lock_key,
    named,
    now,
    positive_int,
)
from streamsvd.store.reading import history

logger = logging.getLogger(__name__)


def check_creatable(storage: Storage) -> None:
    """Raise :class:`StoreError` unless ``storage`` is empty or holds creation leftovers."""
    root = named(storage)
    if storage.is_file():
        raise StoreError(
            f"`path` must be a directory to create a store in; {root} is a file. "
            "Choose another path."
        )
    kind = history(storage)
    if kind == "store":
        extra = (
            "" if POINTER_NAME in storage.list()
            else " (its pointer is missing: it is damaged, and it is never replaced)"
        )
        raise StoreError(
            f"`path` {root} already holds a basis store{extra}. Open it with "
            "`open_store(path, mode='a')`, or delete it first to start afresh."
        )
    if kind == "other":
        raise StoreError(
            f"`path` must be a new or empty directory to create a store in; {root} "
            "holds other files. Choose another path."
        )


def _root_documents(root_attrs: dict[str, Any]) -> dict[str, bytes]:
    """Return the zarr metadata of the root group and of the ``generations`` group."""
    memory: dict[str, Any] = {}
    group = zarr.create_group(store=MemoryStore(memory), zarr_format=3,
                              attributes=dict(root_attrs))
    group.create_group(GENERATIONS)
    return {key: memory[key].to_bytes() for key in ("zarr.json", f"{GENERATIONS}/zarr.json")}


class Creation:
    """A store being created: its lock held, its root written, its pointer not yet.

    Parameters
    ----------
    storage : Storage
        Where the store is created.
    existed : bool
        Whether the location existed before (else :meth:`undo` removes it).
    """

    def __init__(self, storage: Storage, *, existed: bool) -> None:
        self.storage = storage
        self.existed = existed
        self.root_attrs: dict[str, Any] = {}
        self.lock: Any = None
        self.writer: Writer | None = None
        self.done = False  # the pointer names generation 0: the store exists

    def close(self) -> None:
        """Release the lock of a created store; undo a creation that did not commit."""
        if self.done:
            if self.lock is not None:
                self.lock.release()
        else:
            self.undo()

    def undo(self) -> None:
        """Delete everything written under the store (the lock last), if the lock is held.

        Under the lock the location held nothing but the leftovers of interrupted
        creations (deleted first), so all that is there was written by this creation.
        """
        failures: tuple[type[BaseException], ...] = (OSError, *remote_errors())
        if self.writer is not None:
            with contextlib.suppress(*failures):
                for entry in self.storage.list():
                    if entry != lock_key(self.storage):
                        with contextlib.suppress(*failures):
                            self.writer.fence.delete(entry)
        if self.lock is not None:
            self.lock.release()
        if not self.existed:
            with contextlib.suppress(*failures):
                if not self.storage.list():
                    self.storage.delete("")

    def abort(self, exc: BaseException, step: str) -> NoReturn:
        """Undo the creation, interrupted by ``exc`` while ``step``; raise what to report.

        A storage failure becomes a :class:`StoreError` naming the store and the step;
        anything else (an interrupt, a lost lock, a bad argument) propagates as it is.
        """
        self.undo()
        if isinstance(exc, StoreLockedError) or not isinstance(exc, (OSError, *remote_errors())):
            raise exc
        cause = exc.__cause__ if isinstance(exc, StoreError) and exc.__cause__ else exc
        raise StoreError(
            f"`path` {named(self.storage)}: creating the store failed while {step} "
            f"({cause}); nothing was left behind. Fix the cause and run the command again."
        ) from exc


def begin_store(
    storage: Storage, *, n: Any, dtype: Any, inner_fingerprint: Any, chunk_bytes: Any
) -> Creation:
    """Lock ``storage`` and write the root of a new store in it; return the creation.

    Nothing that makes the store exist is written: the first commit of the handle does
    that. See :meth:`streamsvd.store.BasisStore.begin` for the arguments and errors.
    """
    n = positive_int(n, "n")
    dtype_name = check_dtype(dtype)
    fingerprint = check_fingerprint(inner_fingerprint)
    chunk_bytes = positive_int(chunk_bytes, "chunk_bytes")
    check_creatable(storage)
    creation = Creation(storage, existed=storage.exists())
    root = named(storage)
    step = "creating its directory"
    try:
        storage.prepare()
        step = f"writing its lock {lock_key(storage)}"
        creation.lock = storage.lock(lock_key(storage))
        creation.lock.acquire()
        check_creatable(storage)
        creation.root_attrs = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "n": n,
            "dtype": dtype_name,
            "inner_fingerprint": fingerprint,
            "created": now(),
            "library_version": library_version(),
            "chunk_bytes": chunk_bytes,
        }
        writer = creation.writer = Writer(storage, creation.lock, creation.root_attrs, None)
        for entry in storage.list():
            if entry != lock_key(storage):
                logger.warning(
                    "removing %s/%s, left by an interrupted store creation", root, entry
                )
                writer.fence.delete(entry)
        for key, blob in _root_documents(creation.root_attrs).items():
            step = f"writing {key}"
            writer.fence.create(key, blob)
        storage.sync_dir(GENERATIONS)
    except BaseException as exc:
        creation.abort(exc, step)
    return creation
