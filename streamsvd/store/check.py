"""Checking a store: every checksum of every retained generation, nothing written.

:func:`check_store` verifies what reading verifies (the root attributes, the pointer, the
current and the previous generation with every segment) and what only a pass over the
whole store finds: a generation committed after the one the pointer names (the pointer
was replaced by an older copy). The store knows no compressor: a caller that does passes
``opens``, which opens the compressor a store holds, so that a store called healthy also
opens (:func:`streamsvd.parallel.cluster.check_store` passes the one that opens either
kind; ``streamsvd check`` runs it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from streamsvd.errors import StoreFormatError, StoreMismatchError, StreamSVDError
from streamsvd.storage import Storage
from streamsvd.store.format import POINTER_NAME, gen_key, generations, named, read_marker
from streamsvd.store.reading import last_readable_hint, load_generation, read_root

Opener = Callable[[Storage, Any], str | None]
"""``opens(storage, kind)``: open the compressor a store of ``kind`` holds, read-only, and
close it; return the name of its class (None: a store of ``kind`` holds no compressor)."""


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


def check_store(storage: Storage, *, opens: Opener | None = None) -> CheckReport:
    """Verify every checksum of a store: root attributes, pointer, every retained generation.

    Every generation that a pointer names (the current and the previous one) is read
    with its segments verified; every other generation directory holding a commit record
    is checked against it. Nothing is written or deleted.

    Parameters
    ----------
    storage : Storage
        Where the store lives (:func:`streamsvd.storage.open_storage`).
    opens : callable, optional
        ``opens(storage, kind)`` (:data:`Opener`): called when every checksum verified,
        with the ``kind`` the current generation records, to open the compressor the
        store holds read-only, as ``streamsvd info`` and ``--resume`` open it, so that a
        store called healthy opens. Without it, only the checksums are verified.

    Returns
    -------
    CheckReport
        The problems found (each naming the last readable generation, unless the
        compressor does not open), or what verified.
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
    elif opens is not None:
        _check_opens(storage, kind, report, opens)
    return report


def _check_opens(storage: Storage, kind: Any, report: CheckReport, opens: Opener) -> None:
    """Open the compressor of ``kind`` a store holds, through ``opens``; report why it does not.

    The compressor's own checks (what it commits, its options, its basis) are the ones
    of opening it (a store of another kind holds no compressor, and only its checksums
    are verified). A store that needs its inner product given to open (an earlier
    version's that does not keep it) is no problem.
    """
    try:
        name = opens(storage, kind)
    except StoreMismatchError:
        return
    except StreamSVDError as exc:
        report.problems.append(str(exc).strip())
        return
    if name is not None:
        report.verified.append(f"the {name} it holds opens")


__all__ = ["CheckReport", "Opener", "check_store"]
