"""Creating a store: all of it, or nothing.

:func:`create_store` takes the writer lock or lease, writes the root metadata and
generation 0 (each object created anew, through the writer's fence) and switches the
pointer to it. If any step fails (a full disk, a lost connection, Ctrl-C), everything
it wrote is deleted again, the lock released and a root directory it made removed, and
the error says which store and which step failed. Only an empty location, or the
leftovers of an interrupted creation (root metadata, a lock, an uncommitted generation
0, never a pointer nor a committed generation), is created over.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping
from typing import Any

import zarr
from zarr.storage import MemoryStore

from ..errors import StoreError, StoreLockedError
from ..storage import Storage, remote_errors
from .commit import Writer
from .format import (
    FORMAT,
    FORMAT_VERSION,
    GENERATIONS,
    POINTER_NAME,
    check_dtype,
    check_fingerprint,
    history,
    library_version,
    lock_key,
    named,
    normalise_attrs,
    now,
    positive_int,
)

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


def create_store(
    storage: Storage,
    *,
    n: Any,
    dtype: Any,
    inner_fingerprint: Any,
    attrs: Mapping[str, Any] | None,
    chunk_bytes: Any,
    opened: Any,
) -> Any:
    """Create the store in ``storage`` and return ``opened(storage, root_attrs, lock, writer)``.

    ``opened`` builds the handle and writes generation 0 through the writer; see
    :meth:`streamsvd.store.BasisStore.create` for the arguments and errors.
    """
    root = named(storage)
    n = positive_int(n, "n")
    dtype_name = check_dtype(dtype)
    fingerprint = check_fingerprint(inner_fingerprint)
    chunk_bytes = positive_int(chunk_bytes, "chunk_bytes")
    user_attrs = normalise_attrs(attrs)
    check_creatable(storage)
    existed = storage.exists()
    step = "creating its directory"
    lock = None
    written: list[str] = []
    writer = None
    try:
        storage.prepare()
        step = f"writing its lock {lock_key(storage)}"
        lock = storage.lock(lock_key(storage))
        lock.acquire()
        check_creatable(storage)
        root_attrs = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "n": n,
            "dtype": dtype_name,
            "inner_fingerprint": fingerprint,
            "created": now(),
            "library_version": library_version(),
            "chunk_bytes": chunk_bytes,
        }
        writer = Writer(storage, lock, root_attrs, None)
        for entry in storage.list():
            if entry != lock_key(storage):
                logger.warning(
                    "removing %s/%s, left by an interrupted store creation", root, entry
                )
                writer.fence.delete(entry)
        written.append(GENERATIONS)
        for key, blob in _root_documents(root_attrs).items():
            step = f"writing {key}"
            written.append(key)
            writer.fence.create(key, blob)
        storage.sync_dir(GENERATIONS)
        step = "writing generation 0 and its pointer"
        return opened(storage, root_attrs, lock, writer, user_attrs)
    except BaseException as exc:
        if writer is not None and writer.switched:  # an interrupt after the switch: it stands
            if lock is not None:
                lock.release()
            raise
        _undo(writer, written)
        if lock is not None:
            lock.release()
        if not existed:
            with contextlib.suppress(OSError, *remote_errors()):
                storage.delete("") if not storage.list() else None
        if isinstance(exc, StoreLockedError) or not isinstance(exc, (OSError, *remote_errors())):
            raise
        cause = exc.__cause__ if isinstance(exc, StoreError) and exc.__cause__ else exc
        raise StoreError(
            f"`path` {root}: creating the store failed while {step} ({cause}); "
            "nothing was left behind. Fix the cause and run the command again."
        ) from exc


def _undo(writer: Writer | None, written: list[str]) -> None:
    """Delete what a failed creation wrote (only while it still holds the lock)."""
    if writer is None:
        return
    for key in reversed(written):
        with contextlib.suppress(OSError, *remote_errors()):
            writer.fence.delete(key)

