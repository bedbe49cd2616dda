"""Reading a store: what a location holds, its pointer, and its generations verified.

:func:`history` tells a store that has ever committed from the leftovers of an
interrupted creation (only those may be replaced). :func:`read_root` reads the pointer
and checks the root attributes against the copy it records; a pointer that is missing or
damaged is reported with the last readable generation (:func:`last_readable_hint`), and
how to make it current again.

The chain pointer -> generation attributes -> segment bytes is verified on every read:
the pointer records the SHA-256 of the generation's attributes, which record the
SHA-256 of every segment. A reader racing a writer may find the generation it was told
to read collected meanwhile; it then reads the pointer again and starts over, for as long
as the pointer moves. Only a generation that fails to verify while the pointer still
names it is reported as damaged (:func:`read_current`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any, cast

import numpy as np
import zarr

from streamsvd.errors import InputError, StoreFormatError
from streamsvd.storage import PANELS, Storage
from streamsvd.storage.lockfile import LOCK_NAME
from streamsvd.store.format import (
    FORMAT,
    FORMAT_VERSION,
    GENERATIONS,
    LEASE_NAME,
    MARKER_NAME,
    POINTER_NAME,
    READ_ERRORS,
    StoreState,
    attrs_digest,
    check_root_against_pointer,
    committed_generations,
    gen_key,
    generations,
    named,
    read_generation_doc,
    read_marker,
    read_root_attrs,
)
from streamsvd.store.segments import assemble, digest

logger = logging.getLogger(__name__)

MAX_MOVES = 10_000
"""A reader gives up after the pointer moved this many times during one read."""


# ------------------------------------------------------------ what a location holds


def history(storage: Storage) -> str:
    """Tell what ``storage`` holds: ``"empty"``, ``"creation"``, ``"store"`` or ``"other"``.

    ``"store"`` is a store that has a pointer or has ever committed (a generation above
    0, or generation 0 marked as committed): such a store is never replaced. Leftovers of
    an interrupted creation hold nothing but the root metadata, the lock or lease, an
    unmarked generation 0, the panels written after the root metadata and temporary
    files.
    """
    entries = storage.list()
    if not entries:
        return "empty"
    if POINTER_NAME in entries or committed_generations(storage):
        return "store"
    ours = {"zarr.json", GENERATIONS, LOCK_NAME, LEASE_NAME, PANELS}
    for name in entries:
        if name not in ours and not name.startswith((f"{POINTER_NAME}.", f"{LOCK_NAME}.stale-")):
            return "other"
    if "zarr.json" not in entries:  # panels come after the root metadata
        return "other" if PANELS in entries else "creation"
    try:
        doc = json.loads(storage.get("zarr.json"))
    except (OSError, ValueError):
        return "creation"
    attrs = doc.get("attributes") if isinstance(doc, dict) else None
    if not (isinstance(attrs, dict) and attrs.get("format") == FORMAT):
        return "other"
    return "creation"


# ---------------------------------------------------------------------- the pointer


def missing_pointer(storage: Storage) -> StoreFormatError:
    """Return the error for a store without a pointer: an interrupted creation, or damage."""
    path = named(storage)
    done = committed_generations(storage)
    if not done:
        return StoreFormatError(
            f"`path` {path} is an incomplete basis store: it has no {POINTER_NAME} (its "
            "creation was interrupted). Create it again with `BasisStore.create`, which "
            "replaces the leftovers."
        )
    return StoreFormatError(
        f"`path` {path} is damaged: its pointer {POINTER_NAME} is missing, but it holds "
        f"committed generations (up to {done[-1]}); nothing was deleted. "
        f"{last_readable_hint(storage)}"
    )


def last_readable_hint(storage: Storage) -> str:
    """Name the newest generation that still reads back with every checksum verified."""
    path = named(storage)
    k = last_readable(storage)
    if k is None:
        return "No generation is readable: restore the store from a copy."
    return (
        f"The last readable generation is {k}: copy {path}/{gen_key(k)}/{MARKER_NAME} to "
        f"{path}/{POINTER_NAME} to make it current, or restore the store from a copy."
    )


def read_pointer_tagged(storage: Storage) -> tuple[dict[str, Any], str]:
    """Return the pointer and its version tag (the ETag on an object store)."""
    path = named(storage)
    pointer = f"{path}/{POINTER_NAME}"
    try:
        seen = storage.get_tagged(POINTER_NAME)
        if seen is None:
            raise FileNotFoundError(pointer)
        raw, tag = seen
        doc = json.loads(raw)
    except FileNotFoundError:
        raise missing_pointer(storage) from None
    except (OSError, ValueError) as exc:
        raise StoreFormatError(
            f"`path` {path} is a damaged basis store: {pointer} cannot be read ({exc}). "
            f"{last_readable_hint(storage)}"
        ) from exc
    if (
        not isinstance(doc, dict)
        or doc.get("format") != FORMAT
        or not isinstance(doc.get("generation"), int)
        or not isinstance(doc.get("attrs_sha256"), str)
    ):
        raise StoreFormatError(
            f"`path` {path} is a damaged basis store: {pointer} does not name a "
            f"generation. {last_readable_hint(storage)}"
        )
    if doc.get("format_version") != FORMAT_VERSION:
        raise StoreFormatError(
            f"`path` {path} has a pointer of format version {doc.get('format_version')!r}; "
            f"this version of streamsvd reads format version {FORMAT_VERSION}. Open it with "
            "the streamsvd release that wrote it."
        )
    return doc, tag


def read_pointer(storage: Storage) -> dict[str, Any]:
    """Return the pointer of the store (checked)."""
    return read_pointer_tagged(storage)[0]


def read_root(storage: Storage) -> tuple[dict[str, Any], dict[str, Any], str]:
    """Return the root attributes, the pointer and its tag, each checked against the other."""
    attrs = read_root_attrs(storage)
    pointer, tag = read_pointer_tagged(storage)
    check_root_against_pointer(storage, attrs, pointer)
    return attrs, pointer, tag


# ------------------------------------------------------------------ the generations


def load_generation(
    storage: Storage,
    k: int,
    attrs_sha256: str | None,
    root: dict[str, Any],
    *,
    hint: str | None = None,
    previous: int | None = None,
) -> tuple[StoreState, dict[str, Any]]:
    """Read generation ``k`` and verify its attributes (against ``attrs_sha256``) and segments.

    Returns the state and the generation's attributes document; raises
    :class:`StoreFormatError` naming the store, the generation, the array and the pack,
    and how to recover: ``hint``, else the kept ``previous`` generation, else the last
    readable one.
    """
    if hint is None and previous is not None and previous != k:
        hint = (
            f"The previous generation is kept: read it with `store.read(generation="
            f"{previous})` and commit it again, or restore the store from a copy."
        )
    path = named(storage)
    where = f"{path}/{gen_key(k)}"
    dtype = str(root["dtype"])

    def tail() -> str:
        return hint if hint is not None else last_readable_hint(storage)

    zstore = storage.zarr_store(read_only=True)
    packs: dict[int, zarr.Array] = {}

    def open_pack(g: int) -> zarr.Array:
        if g not in packs:
            packs[g] = zarr.open_array(store=zstore, mode="r", path=gen_key(g), zarr_format=3)
        return packs[g]

    try:
        try:
            doc = open_pack(k).attrs.asdict()
        except READ_ERRORS as exc:
            raise StoreFormatError(
                f"`path` {path} is damaged: generation {k} ({where}) cannot be "
                f"opened ({type(exc).__name__}: {exc}). {tail()}"
            ) from exc
        meta = doc.get("streamsvd")
        if (
            not isinstance(meta, dict)
            or meta.get("generation") != k
            or not isinstance(meta.get("arrays"), dict)
            or not isinstance(doc.get("attrs"), dict)
            or (attrs_sha256 is not None and attrs_digest(doc) != attrs_sha256)
        ):
            raise StoreFormatError(
                f"`path` {path} is damaged: the attributes of generation {k} "
                f"({where}/zarr.json) do not match the checksum recorded in "
                f"{POINTER_NAME}. {tail()}"
            )
        arrays: dict[str, np.ndarray] = {}
        for name, info in meta["arrays"].items():

            def read(seg: dict[str, Any], name: str = name) -> np.ndarray:
                g = int(seg["generation"])
                shape = tuple(int(x) for x in seg["shape"])
                size = int(np.prod(shape, dtype=np.int64))
                start = int(seg["offset"])
                try:
                    flat = np.asarray(open_pack(g)[start : start + size]) if size else (
                        np.zeros(0, dtype=np.dtype(dtype))
                    )
                except READ_ERRORS as exc:
                    raise StoreFormatError(
                        f"`path` {path} is damaged: array {name!r} of generation "
                        f"{k} cannot be read from the pack of generation {g} "
                        f"({type(exc).__name__}: {exc}). {tail()}"
                    ) from exc
                if flat.size != size or digest(flat) != seg.get("sha256"):
                    raise StoreFormatError(
                        f"`path` {path} is damaged: array {name!r} of generation "
                        f"{k} does not match its recorded shape, dtype or SHA-256 "
                        f"checksum (its segment in the pack of generation {g}, "
                        f"{path}/{gen_key(g)}). {tail()}"
                    )
                return flat.reshape(shape)

            try:
                data = assemble(info, read)
            except StoreFormatError:
                raise
            except READ_ERRORS as exc:
                raise StoreFormatError(
                    f"`path` {path} is damaged: array {name!r} of generation {k} "
                    f"does not match its recorded shape, dtype or SHA-256 checksum "
                    f"({type(exc).__name__}: {exc}). {tail()}"
                ) from exc
            data.setflags(write=False)
            arrays[name] = data
    finally:
        zstore.close()
    state = StoreState(
        generation=k,
        arrays=arrays,
        attrs=cast(dict[str, Any], doc["attrs"]),
        n=int(root["n"]),
        dtype=dtype,
        inner_fingerprint=str(root["inner_fingerprint"]),
    )
    return state, doc


def current_doc(storage: Storage, k: int) -> dict[str, Any]:
    """Return the attributes of the current generation ``k``, checked against the pointer."""
    doc = read_generation_doc(storage, k)
    if doc is None or attrs_digest(doc) != read_pointer(storage)["attrs_sha256"]:
        raise StoreFormatError(
            f"`path` {named(storage)} is damaged: the attributes of the current generation "
            f"{k} ({named(storage)}/{gen_key(k)}/zarr.json) cannot be read or do not match "
            f"{POINTER_NAME}, so nothing can be appended to it. {last_readable_hint(storage)}"
        )
    return doc


Loader = Callable[[int, str | None], StoreState]


def read_current(
    storage: Storage, load: Loader, generation: int | None, *, retry: bool
) -> tuple[StoreState, dict[str, Any]]:
    """Read the current generation (or the retained ``generation``) through ``load``.

    With ``retry`` (a reader), a generation that fails to verify after the pointer moved
    is read again from the new pointer, for as long as the pointer moves; it is damaged
    only if it fails while the pointer still names it. Returns the state and the pointer.
    """
    pointer = read_pointer(storage)
    for _move in range(MAX_MOVES):
        current = pointer["generation"]
        previous = pointer.get("previous")
        retained = [current] + ([previous] if isinstance(previous, int) else [])
        wanted = current if generation is None else generation
        if wanted not in retained:
            raise InputError(
                f"`generation` must be one of the retained generations {retained}; got "
                f"{generation!r}. Older generations are deleted after each commit."
            )
        try:
            return load(wanted, pointer["attrs_sha256"] if wanted == current else None), pointer
        except StoreFormatError:
            if not retry:
                raise
            again = read_pointer(storage)
            if again == pointer:
                raise  # the pointer still names it: it is damaged
            logger.debug(
                "generation %d of %s was collected during the read; reading generation %d",
                wanted, named(storage), again["generation"],
            )
            pointer = again
    raise StoreFormatError(
        f"`path` {named(storage)}: the pointer moved {MAX_MOVES} times during one read; "
        "the writer commits faster than a read. Read when it pauses, or read a copy."
    )


def last_readable(storage: Storage, *, tries: int = 8) -> int | None:
    """Return the newest generation with a commit record that reads back verified, or None.

    Only the ``tries`` newest generations holding a commit record are tried.
    """
    try:
        root = read_root_attrs(storage)
    except StoreFormatError:
        return None
    for k in [g for g in reversed(generations(storage)) if read_marker(storage, g)][:tries]:
        marker = read_marker(storage, k) or {}
        try:
            load_generation(storage, k, marker.get("attrs_sha256"), root, hint="")
        except StoreFormatError:
            continue
        return k
    return None
