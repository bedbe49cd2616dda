"""The tree's checkpoints: every finished leaf and merge committed beside the store.

A tree with a ``store`` writes each node it finishes (a leaf, a merge) as a basis store of
its own under ``<store>.tree/<node>`` (a directory beside a local store, a prefix beside
an ``s3://`` one), from the worker that computed it. A store's creation is atomic (its
pointer is written last, :mod:`streamsvd.store.create`): a node killed while it is
written does not exist, never half of it. The same call run again (after a crash of a
worker, of the client, or a kill) finds the plan it wrote (``plan.json``: the source's
shape and description, the columns, ``block``, the leaves' width and the options) and
builds its graph from the top: a node already committed is loaded, and nothing below
it is computed or read again. The loaded nodes are the computed ones bit for bit, so the
resumed result is the uninterrupted one. Another plan (other data, other options)
replaces the checkpoints. They are removed once the root is committed to the store.

The client is therefore not a single point of failure for the finished work: what the
workers committed stays, whoever asks for it next.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from typing import Any

from streamsvd.algebra.interface import Backend
from streamsvd.algebra.memory import MemoryBackend
from streamsvd.errors import StoreError
from streamsvd.storage import LocalStorage, ObjectStorage, open_storage
from streamsvd.store import POINTER_NAME
from streamsvd.stream.compressor import StreamCompressor

__all__ = ["Checkpoints", "checkpoints_beside", "child_storage"]

logger = logging.getLogger(__name__)

PLAN = "plan.json"
SUFFIX = ".tree"

ARGUMENTS = {"n": "`source`", "m": "`source`", "source": "`source`",
             "identity": "`source`", "start": "`source`", "stop": "`source`",
             "block": "`block`", "width": "`leaf_columns`", "chunk_rows": "`chunk_rows`",
             "options": "options (`eps`, `max_rank`, `inner`, ...)"}
"""The argument of the call that each entry of a plan comes from (named when refused)."""


def checkpoints_beside(store: LocalStorage | ObjectStorage) -> LocalStorage | ObjectStorage:
    """Return the storage of the checkpoints of a tree writing ``store``: ``<store>.tree``."""
    if isinstance(store, LocalStorage):
        return LocalStorage(store.root.with_name(store.root.name + SUFFIX))
    return open_storage(store.url + SUFFIX, storage_options=store.storage_options or None,
                        argument="store")


def child_storage(root: LocalStorage | ObjectStorage, name: str
                  ) -> LocalStorage | ObjectStorage:
    """Return the storage of ``root``'s sub-directory or prefix ``name`` (same options)."""
    if isinstance(root, LocalStorage):
        return LocalStorage(root.root / name)
    return open_storage(f"{root.url}/{name}", storage_options=root.storage_options or None,
                        argument="store")


class Checkpoints:
    """The committed nodes of one tree (see the module docstring); picklable.

    Parameters
    ----------
    root : LocalStorage or ObjectStorage
        Where the nodes live (:func:`checkpoints_beside`).
    plan : dict
        What the tree computes (JSON-serialisable): checkpoints of another plan are
        removed by :meth:`start`.
    """

    def __init__(self, root: LocalStorage | ObjectStorage, plan: dict[str, Any]) -> None:
        self.root = root
        self.plan = plan
        self.done: frozenset[str] = frozenset()

    @staticmethod
    def fingerprint(options: dict[str, Any]) -> str:
        """Return a digest of a tree's node options (the inner product by its fingerprint)."""
        described = {k: (getattr(v, "fingerprint", None) or repr(v)) if k == "inner" else v
                     for k, v in sorted(options.items())}
        return hashlib.sha256(repr(described).encode()).hexdigest()[:16]

    def start(self, *, refuse: bool = False) -> frozenset[str]:
        """Keep the nodes of this plan; return the committed ones.

        Another plan's checkpoints are removed, or with ``refuse`` a
        :class:`~streamsvd.errors.StoreError` names the arguments that differ.
        """
        wanted = json.dumps(self.plan, sort_keys=True).encode()
        try:
            found = self.root.get(PLAN)
        except (FileNotFoundError, OSError):
            found = None
        if found is not None and found != wanted:
            if refuse:
                raise StoreError(self._mismatch(found))
            logger.warning("checkpoints at %s belong to another tree: removed", self.root.url)
            self.root.delete("")
            found = None
        if found is None:
            self.root.prepare()
            self.root.put(PLAN, wanted)
            self.done = frozenset()
            return self.done
        names = [name for name in self.root.list("") if name != PLAN]
        self.done = frozenset(name for name in names
                              if POINTER_NAME in self.root.list(name))
        if self.done:
            logger.info("%d committed nodes found at %s: resumed from them",
                        len(self.done), self.root.url)
        return self.done

    def _mismatch(self, found: bytes) -> str:
        """Return the message refusing checkpoints of the plan ``found`` (JSON)."""
        try:
            theirs = json.loads(found)
        except ValueError:
            theirs = {}
        keys = sorted(k for k in {*self.plan, *theirs} if self.plan.get(k) != theirs.get(k))
        names = sorted({ARGUMENTS.get(k, f"`{k}`") for k in keys}) or ["the plan"]
        detail = "; ".join(f"{k}: checkpoints {theirs.get(k)!r}, this call {self.plan.get(k)!r}"
                           for k in keys)
        return (
            f"the checkpoints at {self.root.url} were written by a call with other "
            f"{', '.join(names)} ({detail}), so they cannot be resumed. Run the call with "
            f"the arguments that wrote them to resume, or remove {self.root.url} (or pass "
            "checkpoints=False) to start again."
        )

    def save(self, name: str, sc: StreamCompressor) -> None:
        """Commit node ``name`` (on the worker that computed it); ``sc`` is unchanged."""
        place = child_storage(self.root, name)
        place.delete("")  # what a killed writer of this node left (never a committed node)
        copy = sc._copy_with()
        try:
            copy.save(place)
        finally:
            copy.close(finalize=False)

    def load(self, name: str, *, reader: Callable[..., StreamCompressor] | None = None,
             backend: Backend | None = None) -> StreamCompressor:
        """Return the committed node ``name`` as it was computed, without a store.

        ``reader(storage, mode="r")`` opens it (:meth:`StreamCompressor.open` by default,
        a tall node's ``TallCompressor.open``); the copy's basis is kept by ``backend``
        (in memory, compacting in place, by default).
        """
        read = StreamCompressor.open if reader is None else reader
        with read(child_storage(self.root, name), mode="r") as stored:
            return stored._copy_with(
                backend=MemoryBackend(compact_in_place=True) if backend is None else backend)

    def remove(self) -> None:
        """Remove every checkpoint (the root is committed to the store)."""
        self.root.delete("")
