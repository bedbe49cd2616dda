"""What a store handle holds while it is open, and how it opens, begins and commits.

A :class:`~streamsvd.store.handle.BasisStore` is the public face (its arguments, errors
and closing); its :class:`Session` is the store behind it: the storage, the root
attributes, the lock and the :class:`~streamsvd.store.commit.Writer` of a handle opened
for writing, and the generations its pointer names as last seen, with the attributes
read of them. :meth:`Session.open` opens an existing store (the root and the pointer
checked, :mod:`~streamsvd.store.reading`; leftovers of killed writers deleted),
:meth:`Session.begin` starts creating one (:mod:`~streamsvd.store.create`), and a commit
is planned (:func:`~streamsvd.store.commit.plan_commit`), written through the writer and
adopted (:meth:`Session.write`), then recorded and collected (:meth:`Session.settle`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from streamsvd.errors import InputError, StoreError
from streamsvd.storage import Storage, open_storage
from streamsvd.store import collector
from streamsvd.store.commit import Writer, plan_commit
from streamsvd.store.create import Creation, begin_store
from streamsvd.store.format import (
    DEFAULT_CHUNK_BYTES,
    StoreState,
    check_expected,
    expectations,
    lock_key,
    named,
)
from streamsvd.store.reading import current_doc, load_generation, read_root
from streamsvd.store.segments import Appended, Piece

logger = logging.getLogger("streamsvd.store")


class Session:
    """The store behind one open handle: where it is, its lock and writer, its generations.

    Parameters
    ----------
    storage : Storage
        Where the store lives.
    mode : {"r", "a"}
        Read only, or read and commit.
    root_attrs : dict
        The store's root attributes (checked).
    lock : FileLock, Lease or None
        The writer lock or lease, held in mode ``"a"``.
    generation : int
        The generation the pointer names (-1: a store being created).
    previous : int or None
        The previous generation the pointer names.
    writer : Writer or None
        What commits, in mode ``"a"``.
    creation : Creation, optional
        The creation of a store begun (:meth:`begin`), before and after its first commit.
    """

    def __init__(self, storage: Storage, mode: str, root_attrs: dict[str, Any], lock: Any,
                 generation: int, previous: int | None, writer: Writer | None,
                 creation: Creation | None = None) -> None:
        self.storage = storage
        self.path = named(storage)
        self.mode = mode
        self.root_attrs = dict(root_attrs)
        self.lock = lock
        self.writer = writer
        self.creation = creation
        self.generation = generation
        self.previous = previous
        self.docs: dict[int, dict[str, Any]] = {}  # attributes of retained generations
        self.written: dict[str, int] = {}

    @classmethod
    def open(cls, path: str | os.PathLike[str] | Storage, mode: str, *, n: Any, dtype: Any,
             inner_fingerprint: Any, storage_options: Mapping[str, Any] | None) -> Session:
        """Open the store at ``path``: see :func:`~streamsvd.store.handle.open_store`.

        The root and the pointer are checked against the expectations; in mode ``"a"``
        the lock is taken, the root and the pointer read again under it, and the
        leftovers of killed writers deleted (the lock is released if that fails).
        """
        storage = open_storage(path, storage_options=storage_options)
        if mode not in ("r", "a"):
            raise InputError(
                f"`mode` must be 'r' (read only) or 'a' (read and commit); got {mode!r}."
            )
        want = expectations(n, dtype, inner_fingerprint)
        attrs, _pointer, _tag = read_root(storage)
        check_expected(storage, attrs, want)
        lock = None
        if mode == "a":
            lock = storage.lock(lock_key(storage))
            lock.acquire()
        try:
            attrs, pointer, tag = read_root(storage)  # as it is now that the lock is held
            session = cls(storage, mode, attrs, lock, pointer["generation"],
                          pointer.get("previous"), Writer(storage, lock, attrs, tag)
                          if lock is not None else None)
            if session.writer is not None:
                keep = session.keep()
                keep.current_sha256 = pointer["attrs_sha256"]
                collector.clean_leftovers(session.writer.fence, keep)
        except BaseException:
            if lock is not None:
                lock.release()
            raise
        return session

    @classmethod
    def begin(cls, path: str | os.PathLike[str] | Storage, *, n: Any, dtype: Any,
              inner_fingerprint: Any, chunk_bytes: Any,
              storage_options: Mapping[str, Any] | None) -> Session:
        """Start creating a store at ``path``: see :meth:`~streamsvd.store.BasisStore.begin`."""
        storage = open_storage(path, storage_options=storage_options)
        creation = begin_store(storage, n=n, dtype=dtype, inner_fingerprint=inner_fingerprint,
                               chunk_bytes=chunk_bytes)
        return cls(storage, "a", creation.root_attrs, creation.lock, -1, None,
                   creation.writer, creation)

    def keep(self) -> collector.Keep:
        """Return the generations the pointer names, and the attributes read of them."""
        return collector.Keep(self.generation, self.previous, self.docs)

    # -------------------------------------------------------------------- reading

    def load(self, k: int, attrs_sha256: str | None) -> StoreState:
        """Read generation ``k`` verified; keep its attributes."""
        state, doc = load_generation(self.storage, k, attrs_sha256, self.root_attrs,
                                     previous=self.previous)
        self.docs[k] = doc
        return state

    def follow(self, pointer: dict[str, Any]) -> None:
        """Take the generations a pointer just read names."""
        self.generation = pointer["generation"]
        previous = pointer.get("previous")
        self.previous = previous if isinstance(previous, int) else None

    # -------------------------------------------------------------------- writing

    def plan(self, arrays: Mapping[str, Any], appended: Mapping[str, Appended] | None,
             k: int) -> tuple[dict[str, Any], list[Piece]]:
        """Plan generation ``k``: the segment records of every array, the pieces to write."""
        return plan_commit(
            arrays, appended, generation=k, dtype=np.dtype(str(self.root_attrs["dtype"])),
            seal_bytes=int(self.root_attrs.get("chunk_bytes", DEFAULT_CHUNK_BYTES)),
            current=lambda: self.current_doc()["streamsvd"]["arrays"],
        )

    def current_doc(self) -> dict[str, Any]:
        """Attributes of the current generation (its digest checked against the pointer)."""
        k = self.generation
        if k not in self.docs:
            self.docs[k] = current_doc(self.storage, k)
        return self.docs[k]

    def write(self, k: int, records: dict[str, Any], pieces: list[Piece],
              user_attrs: dict[str, Any]) -> dict[str, Any]:
        """Write generation ``k`` and switch the pointer to it; return that pointer.

        Once the switch took effect, ``k`` is the current generation (and a creation is
        done: the store exists).
        """
        writer = self.writer
        if writer is None:  # pragma: no cover - commit checks the mode first
            raise StoreError(f"`store` {self.path} was opened read-only (mode='r').")
        previous = self.generation if self.generation >= 0 else None
        adopted: list[dict[str, Any]] = []

        def adopt(doc: dict[str, Any], pointer: dict[str, Any], written: dict[str, int]) -> None:
            self.docs = {g: d for g, d in self.docs.items() if g == self.generation}
            self.docs[k] = doc
            self.previous, self.generation, self.written = previous, k, written
            adopted.append(pointer)
            if self.creation is not None:
                self.creation.done = True  # the pointer names it: the store exists
            logger.debug("committed generation %d of %s (%s)", k, self.path, written)

        writer.write_generation(k, records, pieces, user_attrs, previous, adopt)
        return adopted[0]

    def settle(self, k: int, pointer: dict[str, Any]) -> None:
        """After the switch to generation ``k`` (:meth:`write`): record the commit, collect."""
        assert self.writer is not None  # write() wrote through it
        self.writer.after_switch(k, pointer, self.keep())
