"""Reading a generation with every checksum verified, retrying while the pointer moves.

The chain pointer -> generation attributes -> segment bytes is verified on every read:
the pointer records the SHA-256 of the generation's attributes, which record the
SHA-256 of every segment. A reader racing a writer may find the generation it was told
to read collected meanwhile; it then reads the pointer again and starts over, for as long
as the pointer moves. Only a generation that fails to verify while the pointer still
names it is reported as damaged (:func:`read_current`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
import zarr

from streamsvd.errors import InputError, StoreFormatError, StoreMismatchError, StreamSVDError
from streamsvd.storage import Storage
from streamsvd.store.format import (
    POINTER_NAME,
    READ_ERRORS,
    StoreState,
    attrs_digest,
    gen_key,
    generations,
    last_readable_hint,
    named,
    read_generation_doc,
    read_marker,
    read_pointer,
    read_root,
    read_root_attrs,
)
from streamsvd.store.segments import assemble, digest

logger = logging.getLogger(__name__)

MAX_MOVES = 10_000
"""A reader gives up after the pointer moved this many times during one read."""


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


# ---------------------------------------------------------------------- checking


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


@dataclass
class CheckReport:
    """What :func:`check_store` found: one line per problem, and what verified."""

    store: str
    problems: list[str] = field(default_factory=list)
    verified: list[str] = field(default_factory=list)

    @property
    def healthy(self) -> bool:
        """Whether no problem was found."""
        return not self.problems


def check_store(storage: Storage) -> CheckReport:
    """Verify every checksum of a store: root attributes, pointer, every retained generation.

    Every generation that a pointer names (the current and the previous one) is read
    with its segments verified; every other generation directory holding a commit record
    is checked against it. A store that verifies and holds a compressor is then opened
    read-only as ``streamsvd info`` and ``--resume`` open it (:func:`_check_opens`), so
    that a store called healthy opens. Nothing is written or deleted.
    """
    path = named(storage)
    report = CheckReport(str(path))
    try:
        root, pointer, _tag = read_root(storage)
    except StoreFormatError as exc:
        report.problems.append(str(exc))
        return report
    current = pointer["generation"]
    previous = pointer.get("previous")
    kind = None
    for k, sha in ((current, pointer["attrs_sha256"]), (previous, None)):
        if not isinstance(k, int):
            continue
        if sha is None:
            marker = read_marker(storage, k)
            sha = marker.get("attrs_sha256") if marker else None
        try:
            state, _doc = load_generation(storage, k, sha, root, hint="")
        except StoreFormatError as exc:
            report.problems.append(str(exc).strip())
            continue
        if k == current:
            kind = state.attrs.get("kind")
        role = "current" if k == current else "previous"
        report.verified.append(
            f"generation {k} ({role}): {len(state.arrays)} arrays, every checksum verified"
        )
    newer = [g for g in generations(storage) if g > current and read_marker(storage, g)]
    if newer:
        report.problems.append(
            f"`path` {path} is damaged: {POINTER_NAME} names generation {current}, but "
            f"generation {newer[-1]} was committed after it ({path}/{gen_key(newer[-1])}): "
            f"{POINTER_NAME} was replaced by an older copy. Copy {path}/{gen_key(newer[-1])}/"
            f"committed.json to {path}/{POINTER_NAME} to make it current."
        )
    if report.problems:
        hint = last_readable_hint(storage)
        report.problems = [p if hint in p else f"{p} {hint}".strip() for p in report.problems]
    else:
        _check_opens(storage, kind, report)
    return report


def _check_opens(storage: Storage, kind: Any, report: CheckReport) -> None:
    """Open the compressor of ``kind`` a store holds, read-only; report why it does not open.

    The compressor's own checks (what it commits, its options, its basis) are the ones
    of opening it: the compressor classes open it (a store of another kind holds no
    compressor, and only its checksums are verified). A store that needs its inner
    product given to open (an earlier version's that does not keep it) is no problem.
    """
    from streamsvd.parallel.cluster import (
        compressor_class,  # the compressors are built on the store
    )

    cls = compressor_class(kind)
    if cls is None:
        return
    try:
        with cls.open(storage, mode="r"):
            pass
    except StoreMismatchError:
        return
    except StreamSVDError as exc:
        report.problems.append(str(exc).strip())
        return
    report.verified.append(f"the {cls.__name__} it holds opens")
