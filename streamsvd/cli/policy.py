"""What ``streamsvd ingest`` does with STORE: create, continue or refuse it; undo a failed start.

* :func:`resuming`: with ``--resume``, a STORE that holds a store (it has a pointer, or
  has ever committed: a committed generation, even with its pointer missing) is continued
  (opening a damaged one reports the damage); nothing, an empty directory or the
  leftovers of an interrupted creation gets a new store. Without ``--resume`` an
  existing STORE is refused.
* :func:`removed_on_failure`: a STORE that this command created is removed again if the
  command fails before committing a snapshot; a STORE that existed before, or holds
  committed snapshots, never is.
* :func:`check_resume`: a STORE is continued with the options it was created with and
  from the SOURCE it was built from (:class:`~streamsvd.io.provenance.SourceRecord`); an
  option given again with another value, or another SOURCE, is refused.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Iterator, Mapping
from datetime import datetime
from typing import Any

from streamsvd.errors import InputError, ShapeMismatchError, StoreError, StreamSVDError
from streamsvd.stream.options import CompressorOptions

__all__ = ["check_resume", "removed_on_failure", "resuming"]

logger = logging.getLogger(__name__)

# the options a store records at creation (``--resume`` reuses them), with their flags
# the options a store records that the command line sets, by option name
_RECORDED_OPTIONS = tuple(
    name for name in CompressorOptions.names()
    if name not in ("reject_tol", "reorth_tol", "right_vectors")
) + ("chunk_rows",)


# how a difference of SourceRecord.differences is named on the command line
_SOURCE_PARTS = {"path": "SOURCE", "dataset": "--dataset", "shape": "SOURCE of shape"}


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
    from streamsvd.store import history

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
    from streamsvd.store import LEASE_NAME, LOCK_NAME, history, open_store

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


def check_resume(compressor: Any, record: Any, *, given: Mapping[str, Any],
                 source_changed_ok: bool, store: Any) -> None:
    """Refuse to continue ``compressor`` with other options or from another SOURCE.

    A store keeps the options it was created with; giving the same value again (the
    first command line with --resume added) is accepted, another value is refused rather
    than silently ignored. SOURCE's snapshot size must be the store's; its path, dataset
    and number of columns are checked against the source the store records (a store
    written before stores recorded it is not checked), unless ``source_changed_ok``. On
    success the store will record ``record``.

    Parameters
    ----------
    compressor : StreamCompressor or TallCompressor
        The store's compressor, open for writing.
    record : SourceRecord
        SOURCE as given.
    given : mapping
        The options given on the command line, by option name, in the compressor's
        values (``--sweeps converge`` is ``sweeps=None``); an option not given is absent.
    source_changed_ok : bool
        Whether ``--source-changed-ok`` was given.
    store : Storage
        STORE, as named in messages.

    Raises
    ------
    InputError
        An option differs from the store's, or SOURCE differs from the recorded one.
    ShapeMismatchError
        SOURCE's snapshots are not of the store's size.
    """
    recorded = compressor.options.as_dict()
    if hasattr(compressor, "chunk_rows"):  # a tall store keeps the row chunks of its panels
        recorded["chunk_rows"] = compressor.chunk_rows
    _check_options(given, recorded)
    n = record.shape[0]
    if n != compressor.n:
        raise ShapeMismatchError(
            f"SOURCE has snapshots of size {n}; STORE {store} holds a basis of size "
            f"{compressor.n}. Pass the source the store was built from."
        )
    source = compressor.source_record
    differ = [] if source is None else source.differences(record)
    if differ and not source_changed_ok:
        said = ", ".join(f"{_SOURCE_PARTS[what]} {new} (STORE has {had})"
                         for what, new, had in differ)
        raise InputError(
            f"{said}: STORE {store} was built from another source. Pass the SOURCE "
            "(and --dataset) it was built from, or add --source-changed-ok to continue it "
            "from this one."
        )
    if differ:
        logger.warning("continuing STORE %s from another source (%s)", store,
                       ", ".join(f"{what} {had} -> {new}" for what, new, had in differ))
    compressor.source_record = record


def _check_options(given: Mapping[str, Any], recorded: dict[str, Any]) -> None:
    """Refuse an option of ``given`` that differs from the one the store records."""
    differ = []
    for name in _RECORDED_OPTIONS:
        flag = CompressorOptions.flag(name)
        if name not in given or name not in recorded:
            continue
        if given[name] != recorded[name]:
            differ.append(f"{flag} {_shown(name, given[name])} "
                          f"(STORE has {_shown(name, recorded[name])})")
    if differ:
        raise InputError(
            f"{', '.join(differ)}: --resume continues STORE with the options it was created "
            "with (`streamsvd info STORE` shows them). Drop the option, or give the store's "
            "value."
        )


def _shown(name: str, value: Any) -> str:
    """Say an option's value as the command line spells it (``sweeps=None`` is converge)."""
    if value is None:
        return "converge" if name == "sweeps" else "none"
    return str(value)
