"""A commit: the pack of a new generation written through the fence, then the pointer switch.

A commit (:meth:`Writer.write_generation`) writes the generation's pack (its
``zarr.json`` first, then its chunks, each object created anew, never overwriting one,
each file ``fsync``-ed, then the directory), confirms that the writer still holds its
lock or lease, and switches the pointer: an atomic replace locally, a conditional
``PUT`` (``If-Match`` the ETag this writer last saw) in an object store. After the switch
it writes the commit record (``committed.json``, a copy of the pointer) into the
generation, which tells a committed generation from the leftovers of an interrupted
commit for ever after, and runs the collector (:mod:`streamsvd.store.collector`).

If anything fails or is interrupted before the switch took effect, the generation is
deleted again, if this writer still holds the lock and no pointer can name it; once the
switch took effect the commit stands (only what follows it failed) and is recorded.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Any

import numpy as np

from streamsvd.errors import InputError, StoreError, StoreLockedError
from streamsvd.storage import Storage, remote_errors
from streamsvd.store import collector
from streamsvd.store import fence as _fence
from streamsvd.store.fence import Fence
from streamsvd.store.format import (
    DEFAULT_CHUNK_BYTES,
    FORMAT,
    FORMAT_VERSION,
    MARKER_NAME,
    NAME_RE,
    POINTER_NAME,
    attrs_digest,
    gen_key,
    now,
    prepare_arrays,
    root_record,
    unreadable,
)
from streamsvd.store.pack import Packed, encode_pack, pack
from streamsvd.store.segments import Appended, Piece, plan_appended, plan_whole

logger = logging.getLogger(__name__)


#: The threads that write a pack's chunks, each written and ``fsync``-ed: the writes wait
#: outside the GIL (a 107 MiB commit in 0.28 s against 0.60 s with one thread and the
#: copies before, ``bench/studies/commit-benchmark.md``).
WRITE_THREADS = 2


def _write_pack(
    fence: Fence, path: str, data: np.ndarray | Packed, doc: dict[str, Any], chunk_bytes: int
) -> None:
    """Create the pack ``path`` (a flat zarr array with attributes ``doc``), fenced, durably.

    Its ``zarr.json`` first (it claims the generation), then the chunks, on
    :data:`WRITE_THREADS` threads (a local file's write and ``fsync`` and a ``PUT`` wait
    outside the GIL): every write has ended, written or failed, when this returns or
    raises, so that a failed commit deletes all it wrote.
    """
    objects = iter(encode_pack(data, doc, chunk_bytes).items())
    name, blob = next(objects)
    fence.create(f"{path}/{name}", blob)
    _fence.crash_point("pack-started")
    with ThreadPoolExecutor(WRITE_THREADS, thread_name_prefix="streamsvd-commit") as pool:
        futures = [pool.submit(fence.create, f"{path}/{name}", blob) for name, blob in objects]
        try:
            for future in futures:
                future.result()
        except BaseException:
            for future in futures:
                future.cancel()
            wait(futures)
            raise
    fence.storage.sync_dir(path)


def plan_commit(
    arrays: Mapping[str, Any],
    appended: Mapping[str, Appended] | None,
    *,
    generation: int,
    dtype: np.dtype,
    seal_bytes: int,
    current: Callable[[], dict[str, Any]],
) -> tuple[dict[str, Any], list[Piece]]:
    """Plan generation ``generation``: the segment records of every array, the pieces to write.

    ``current()`` returns the segment records of the current generation (read only when
    an appended array keeps a part of it).
    """
    prepared = prepare_arrays(arrays, dtype)
    records: dict[str, Any] = {}
    pieces: list[Piece] = []
    for name, arr in prepared.items():
        records[name], new = plan_whole(arr, generation=generation)
        pieces += new
    if not appended:
        return records, pieces
    if not isinstance(appended, Mapping):
        raise InputError(
            f"`appended` must be a dict mapping names to Appended; got "
            f"{type(appended).__name__}."
        )
    kept = current() if any(getattr(v, "unchanged", 0) for v in appended.values()) else {}
    for name, value in appended.items():
        if not isinstance(name, str) or not NAME_RE.match(name) or name in records:
            raise InputError(
                f"`appended` keys must be identifiers not used in `arrays`; got "
                f"{name!r}. Rename the array."
            )
        records[name], new = plan_appended(
            name, value, kept.get(name), generation=generation, dtype=dtype,
            seal_bytes=seal_bytes,
        )
        pieces += new
    return records, pieces


class Writer:
    """The writing side of a store handle: its fence, its view of the pointer, its commits.

    Parameters
    ----------
    storage : Storage
        Where the store lives.
    lock : FileLock or Lease
        The writer's lock or lease, held.
    root_attrs : dict
        The store's root attributes.
    pointer_tag : str or None
        The pointer's version as this writer last saw it (None: no pointer yet).
    """

    def __init__(
        self, storage: Storage, lock: Any, root_attrs: dict[str, Any], pointer_tag: str | None
    ) -> None:
        from streamsvd.store.format import named

        self.storage = storage
        self.lock = lock
        self.path = named(storage)
        self.root_attrs = root_attrs
        self.pointer_tag = pointer_tag
        self.fence = Fence(storage, lock, self.path)
        self.switched = False  # whether a commit of this writer took effect
        self.failures: tuple[type[BaseException], ...] = (OSError, *remote_errors())

    def write_generation(
        self,
        k: int,
        records: dict[str, Any],
        pieces: list[Piece],
        user_attrs: dict[str, Any],
        previous: int | None,
        adopt: Callable[[dict[str, Any], dict[str, Any], dict[str, int]], None],
    ) -> None:
        """Write generation ``k``, switch the pointer to it and call ``adopt``.

        ``adopt(doc, pointer, written)`` receives the generation's attributes, the pointer
        and the elements written per array once the pointer names the generation (also
        when an interrupt came after the switch, which then propagates). Raises, with
        nothing persisted changed, if the switch did not take effect.
        """
        gkey = gen_key(k)
        self.check_pointer_unchanged(k)
        self.fence.check(f"starting generation {k}")
        if gkey.rsplit("/", 1)[1] in self.storage.list(gkey.rsplit("/", 1)[0]):
            logger.warning("removing %s/%s, left by an interrupted commit", self.path, gkey)
            self.fence.delete(gkey)
        dtype = np.dtype(str(self.root_attrs["dtype"]))
        data = pack(pieces, dtype)
        written: dict[str, int] = {}
        for name, info in records.items():
            for seg in info["segments"]:
                if seg["generation"] == k:
                    written[name] = written.get(name, 0) + int(np.prod(seg["shape"]))
        doc = {
            "streamsvd": {"generation": k, "committed": now(), "arrays": records},
            "attrs": user_attrs,
        }
        doc = json.loads(json.dumps(doc))
        pointer = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "generation": k,
            "previous": previous,
            "attrs_sha256": attrs_digest(doc),
            "committed": doc["streamsvd"]["committed"],
            "root": root_record(self.root_attrs),
            "writer": getattr(self.lock, "token", None),
        }
        try:
            from streamsvd.store import commit as this  # the pack writer, looked up at call time

            this._write_pack(
                self.fence, gkey, data, doc,
                int(self.root_attrs.get("chunk_bytes", DEFAULT_CHUNK_BYTES)),
            )
            _fence.crash_point("pack-written")
            if not self.lock.owned():
                raise StoreLockedError(
                    f"`store` {self.path} lost its writer lock to {self.lock.holder()}; "
                    f"generation {k} was not committed. Make sure a single writer opens the "
                    "store."
                )
            _fence.crash_point("before-switch")
            self.switch(pointer, k)
        except BaseException as exc:
            if not self.pointer_is(pointer):
                if self.not_named(k):
                    self.fence.delete(gkey)
                if isinstance(exc, self.failures) and not isinstance(exc, StoreError):
                    kept = (
                        "the store was not created" if previous is None
                        else f"the current generation {previous} is unchanged"
                    )
                    raise StoreError(
                        f"`store` {self.path}: writing generation {k} failed ({exc}); "
                        f"{kept}. Fix the cause and commit again."
                    ) from exc
                raise
            # The pointer names this commit: the switch took effect and only what follows
            # it (the directory's fsync, the reply) failed or was interrupted. The commit
            # stands and is never undone; an interrupt still propagates once it is recorded
            # (and the caller reports the commit: the command line names its last column).
            self.switched = True
            adopt(doc, pointer, written)
            if not isinstance(exc, self.failures):
                logger.info("generation %d of %s was committed before the interrupt",
                            k, self.path)
                raise
            logger.warning(
                "generation %d of %s was committed; the step after its pointer switch "
                "failed (%s)", k, self.path, type(exc).__name__,
            )
            return
        self.switched = True
        adopt(doc, pointer, written)

    def after_switch(self, k: int, pointer: dict[str, Any], keep: collector.Keep) -> None:
        """Record the commit in generation ``k`` and collect what no pointer can reach.

        A failure here leaves the commit standing; it is logged.
        """
        try:
            _fence.crash_point("switched")
            self.fence.create(
                f"{gen_key(k)}/{MARKER_NAME}", json.dumps(pointer, indent=2).encode()
            )
            _fence.crash_point("marked")
            if self.pointer_is(pointer):
                collector.collect(self.fence, keep)
            _fence.crash_point("collected")
        except self.failures as exc:  # FileExistsError is an OSError
            logger.warning(
                "generation %d of %s was committed; recording it or collecting older "
                "generations failed (%s)", k, self.path, exc,
            )

    def pointer_is(self, pointer: dict[str, Any]) -> bool:
        """Whether the stored pointer is ``pointer`` (then its version tag is recorded).

        Asked after a commit failed or was interrupted, to tell whether its switch took
        effect; a pointer that cannot be read counts as not switched.
        """
        try:
            seen = self.storage.get_tagged(POINTER_NAME)
            if seen is None or json.loads(seen[0]) != pointer:
                return False
        except unreadable():
            return False
        if self.storage.conditional:
            self.pointer_tag = seen[1]
        return True

    def not_named(self, k: int) -> bool:
        """Whether no pointer can name generation ``k`` (so deleting it loses nothing).

        True when the store has no pointer yet (its creation) or a readable pointer names
        an older generation; a pointer that cannot be read keeps ``k``.
        """
        try:
            seen = self.storage.get_tagged(POINTER_NAME)
            if seen is None:
                return True
            named = json.loads(seen[0]).get("generation")
        except unreadable():
            return False
        return isinstance(named, int) and named < k

    def pointer_changed(self, k: int) -> StoreLockedError:
        """Return the error of a commit that found the pointer changed under it."""
        mine = self.fence.holds()
        who = (
            "although this writer still holds the lease: the store was changed by hand, "
            "or by a writer that ignored the lease"
            if mine
            else f"by another writer ({self.lock.holder()})".replace(
                "(nobody)", "(which has closed the store since)")
        )
        return StoreLockedError(
            f"`store` {self.path}: the pointer {POINTER_NAME} was changed {who} since this "
            f"writer last committed; generation {k} was not committed. Make sure a single "
            "writer opens the store."
        )

    def check_pointer_unchanged(self, k: int) -> None:
        """On an object store, refuse to start a commit if another writer committed since.

        Nothing is written or deleted then (generation ``k`` may be the other writer's).
        """
        if not self.storage.conditional or self.pointer_tag is None:
            return
        seen = self.storage.get_tagged(POINTER_NAME)
        if seen is None or seen[1] != self.pointer_tag:
            raise self.pointer_changed(k)

    def switch(self, pointer: dict[str, Any], k: int) -> None:
        """Make ``pointer`` current: an atomic replace locally, a conditional PUT remotely.

        On an object store the pointer is replaced only if it is still the version this
        writer last wrote or read (``If-Match`` its ETag; ``If-None-Match`` at creation),
        so a writer that lost its lease can never overwrite another writer's commit. A
        refusal after a failed attempt whose write did take effect (an HTTP 500 on a
        ``PUT`` the server applied, then retried) is recognised as this commit.
        """
        data = json.dumps(pointer, indent=2).encode()
        storage = self.storage
        self.fence.check(f"switching the pointer to generation {k}")
        if not storage.conditional:
            storage.put(POINTER_NAME, data)
            return
        tag = (
            storage.put_if_absent(POINTER_NAME, data)
            if self.pointer_tag is None
            else storage.put_if_match(POINTER_NAME, data, self.pointer_tag)
        )
        if tag is None:
            if self.pointer_is(pointer):
                return
            raise self.pointer_changed(k)
        self.pointer_tag = tag

