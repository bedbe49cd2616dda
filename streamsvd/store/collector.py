"""The collector: deleting generations that no pointer can reach, and nothing else.

Run only by the writer that holds the lock or lease, every delete through its
:class:`~streamsvd.store.fence.Fence`. After a commit it deletes the generations *older*
than the current one that neither the current nor the previous generation uses (a
segment of theirs); it never deletes a generation newer than the one its pointer names,
which may be another writer's. When a writer opens a store it also deletes the
leftovers of interrupted commits: generations newer than the pointer that were never
committed (they hold no commit record). A generation newer than the pointer that *was*
committed means that the pointer was replaced by an older copy: the store is damaged,
and nothing is deleted.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from streamsvd.errors import StoreFormatError
from streamsvd.storage.lockfile import LOCK_NAME
from streamsvd.store.fence import Fence
from streamsvd.store.format import (
    MARKER_NAME,
    POINTER_NAME,
    attrs_digest,
    gen_key,
    gen_name,
    generations,
    read_generation_doc,
    read_marker,
    sources,
)

logger = logging.getLogger(__name__)


@dataclass
class Keep:
    """The generations the pointer names, and the attributes of those already read."""

    current: int
    previous: int | None
    docs: dict[int, dict[str, Any]] = field(default_factory=dict)
    current_sha256: str | None = None  # the pointer's checksum of the current attributes


def retained(fence: Fence, keep: Keep) -> set[int] | None:
    """Return the generations the current and previous ones use (None: one is unreadable)."""
    out: set[int] = {keep.current} | ({keep.previous} if keep.previous is not None else set())
    for g in (keep.current, keep.previous):
        if g is None:
            continue
        doc = keep.docs.get(g)
        if doc is None:
            doc = read_generation_doc(fence.storage, g)
            marker = read_marker(fence.storage, g) or {}
            want = keep.current_sha256 if g == keep.current else marker.get("attrs_sha256")
            if doc is not None and want is not None and attrs_digest(doc) != want:
                doc = None  # damaged attributes: their segment lists cannot be trusted
        if doc is None:
            logger.warning(
                "generation %d of %s cannot be read; keeping every older generation",
                g, fence.path,
            )
            return None
        out |= sources(doc)
    return out


def collect(fence: Fence, keep: Keep) -> list[int]:
    """Delete the generations older than the current one that no retained one uses."""
    used = retained(fence, keep)
    if used is None:
        return []
    deleted = []
    for g in generations(fence.storage):
        if g < keep.current and g not in used:
            logger.debug("removing generation %s of %s", gen_name(g), fence.path)
            if not fence.delete(gen_key(g)):
                break
            deleted.append(g)
    return deleted


def clean_leftovers(fence: Fence, keep: Keep) -> None:
    """At a writer's open: refuse a rolled-back pointer, then delete what killed writers left."""
    newer = [g for g in generations(fence.storage) if g > keep.current]
    committed = [g for g in newer if read_marker(fence.storage, g) is not None]
    if committed:
        g = committed[-1]
        raise StoreFormatError(
            f"`path` {fence.path} is damaged: {POINTER_NAME} names generation "
            f"{keep.current}, but generation {g} was committed after it "
            f"({fence.path}/{gen_key(g)}/{MARKER_NAME}): {POINTER_NAME} was replaced by an "
            f"older copy. Nothing was deleted. Copy {fence.path}/{gen_key(g)}/{MARKER_NAME} "
            f"to {fence.path}/{POINTER_NAME} to make generation {g} current again, or "
            "restore the store from a copy."
        )
    for g in newer:
        logger.warning(
            "removing %s/%s, left by an interrupted commit", fence.path, gen_key(g)
        )
        fence.delete(gen_key(g))
    collect(fence, keep)
    for entry in fence.storage.list():
        if entry.startswith((f"{POINTER_NAME}.", f"{LOCK_NAME}.stale-")):
            logger.info("removing %s/%s, left by an interrupted writer", fence.path, entry)
            fence.delete(entry)


__all__ = ["Keep", "clean_leftovers", "collect"]
