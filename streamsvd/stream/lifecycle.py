"""The lifecycle of a compressor: open, copy, save, flush, close, and each update.

:class:`StoreLifecycle` is the part of the :class:`~streamsvd.StreamCompressor` facade that
creates, reopens and closes its store, and that runs every update
(:meth:`StoreLifecycle._run`: plan, commit when due, then switch to the new state); what a
commit writes, what it lets the basis delete and how a store is checked are
:mod:`streamsvd.stream.persistence`'s; what differs where the basis is out of core is the
compressor's :class:`~streamsvd.algebra.interface.Backend`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np

from streamsvd._util.threads import blas_threads
from streamsvd._util.validation import check_choice
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import Backend
from streamsvd.algebra.memory import MEMORY_KIND, MemoryBackend
from streamsvd.engine.downdate import Ledger
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.state import Plan, State, apply_plan
from streamsvd.errors import StoreError
from streamsvd.io.provenance import SourceRecord
from streamsvd.storage import open_storage
from streamsvd.stream.options import CompressorOptions
from streamsvd.stream.persistence import StreamStore, open_stream_store, restore_state

__all__ = ["StoreLifecycle"]


class StoreLifecycle:
    """Open, copy, save, flush and close a compressor's store (see the module docstring)."""

    n: int
    inner: InnerProduct
    options: CompressorOptions
    source_record: SourceRecord | None
    source_offset: int
    finalized: bool
    _state: State
    _history: list[UpdateRecord]
    _version: int
    _persistence: StreamStore | None
    _inner_data: dict[str, np.ndarray]
    _removed: np.ndarray
    _ledger: Ledger
    _restore_removals: Callable[[dict[str, Any]], None]
    _removal_attrs: Callable[[Plan | None], dict[str, Any]]
    _pending: tuple[Ledger, np.ndarray]
    threads: int | None
    finalize: Callable[..., UpdateRecord]
    _empty_copy: Callable[..., Any]
    _backend: Backend
    _built: Callable[..., Any]

    @classmethod
    def open(
        cls, path: Any, *, inner: Any = None, mode: str = "a",
        storage_options: dict[str, Any] | None = None,
    ) -> Any:
        """Reopen a compressor from its store, exactly as it was at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``StreamCompressor(..., store=path)``.
        inner : optional
            The inner product the store was written with (checked by fingerprint). When
            omitted, the one the store keeps (Euclidean if none); a store written before
            stores kept it, with another inner product than the Euclidean one, needs it.
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock); ``"r"`` reads only.
        storage_options : dict, optional
            Options of the object store of a URL ``path`` (``s3://``: ``key``,
            ``secret``, ``endpoint_url``, ...), as for :func:`streamsvd.open_storage`.
        """
        return cls._open(path, inner=inner, mode=mode, kind=MEMORY_KIND,
                         backend=lambda attrs, root: MemoryBackend(),
                         storage_options=storage_options)

    @classmethod
    def _open(cls, path: Any, *, inner: Any, mode: str, kind: str,
              backend: Callable[[dict[str, Any], Any], Backend],
              storage_options: dict[str, Any] | None = None) -> Any:
        """Open a store of ``kind`` and restore the compressor it holds.

        ``backend(basis_attrs, root)`` returns the backend of the store at ``root``.
        """
        mode = check_choice(mode, "mode", ("a", "r"))
        path = open_storage(path, storage_options=storage_options)
        st, state, ip = open_stream_store(path, kind=kind, name=cls.__name__, mode=mode,
                                          inner=inner)
        try:
            options = CompressorOptions.from_stored(state.n, state.attrs["options"])
            sc = cls._built(state.n, backend=backend(state.attrs["basis"], path),
                            inner=ip, **options.as_dict())
            sc.source_offset, sc._history = restore_state(sc._state, state.arrays,
                                                          state.attrs)
            sc._restore_removals(state.attrs)
            sc._version += 1
            sc.source_record = SourceRecord.from_attrs(state.attrs.get("source"))
            sc._persistence = StreamStore(st, commit_every=options.commit_every)
            sc._persistence.restored(
                sc._state, state.generation, state.attrs["basis"], state.arrays["history"],
                inner=all(name in state.arrays for name in sc._inner_data),
            )
        except BaseException:
            st.close()
            raise
        return sc

    def copy(self) -> Any:
        """Return an independent copy of the compressor (without its store)."""
        return self._copy_with()

    def _drop_scratch(self) -> None:
        """Free the buffers the basis keeps for its next update (they come back when needed).

        For a compressor that will not be updated soon, such as a finished leaf of a tree.
        """
        self._state.basis.drop_scratch()

    def _copy_with(self, *, backend: Any = None, **changes: Any) -> Any:
        """Return an independent copy whose options differ by ``changes``.

        Its basis is kept by ``backend`` (default: a fresh one of the same settings).
        """
        out = self._empty_copy(backend=backend, **changes)
        basis = self._backend.copied(self._state.basis, out._state.basis)
        out._state = copy.deepcopy(self._state, {id(self._state.basis): basis})
        out._history = list(self._history)
        out.source_offset = self.source_offset
        out._removed, out._ledger = self._removed, self._ledger
        return out

    def _start_store(self, path: Any, storage_options: dict[str, Any] | None) -> None:
        """Create the store at ``path`` by committing the current state to it.

        All or nothing: the store exists once its first commit, which holds the whole
        state (and the basis's attributes), switched its pointer; until then a failure
        deletes everything written under it, and a process killed meanwhile leaves the
        leftovers of an interrupted creation, which the next creation replaces.
        """
        self._persistence = StreamStore.create(
            path, n=self.n, inner_fingerprint=self.inner.fingerprint,
            storage_options=storage_options, commit_every=self.options.commit_every,
        )
        before = self._backend, self._state.basis
        try:
            # a basis that no commit refers to (a tall mode's work directory) is copied
            # into the store first
            self._backend, self._state.basis = self._backend.into_store(
                self._state.basis, self._persistence.storage)
            self._commit(None, self.source_offset)
        except BaseException:
            self._backend, self._state.basis = before
            self._persistence.close()  # deletes a creation that did not commit
            self._persistence = None
            raise
        if self._backend is not before[0]:
            before[0].close()

    def save(self, path: Any) -> None:
        """Write the compressor into a new store at ``path`` and keep committing there.

        One commit of the current state, bit for bit (no update is run). The compressor
        must not have a store already.
        """
        if self._persistence is not None:
            raise StoreError(
                f"this compressor already commits to {self._persistence.path}; `save` "
                "writes a compressor that has no store."
            )
        self._start_store(path, None)

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        if self._persistence is not None and self._persistence.uncommitted:
            self._commit(None, self.source_offset)

    def close(self, *, finalize: bool = True) -> None:
        """Finalise the expansion, commit what is pending and release the store's lock.

        Parameters
        ----------
        finalize : bool
            Run :meth:`finalize` first (default) unless :attr:`finalized`, so that the
            closed expansion is the SVD, truncated to ``max_rank``. A store opened
            read-only is never finalised, nor a basis that closing removes (a
            temporary backend's).
        """
        p = self._persistence
        writable = p is None or p.writable
        if finalize and writable and not self.finalized and not self._backend.temporary:
            self.finalize()
        if p is not None:
            if writable:
                self.flush()
            p.close()
            self._persistence = None
        self._state.basis.drop_scratch()
        self._backend.close()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        # a block that raised keeps its streamed state: what was committed stays as it was
        self.close(finalize=exc_type is None)

    @property
    def store_path(self) -> str | None:
        """Path of the store, or None."""
        return None if self._persistence is None else self._persistence.path

    def _attrs(self, plan: Plan | None) -> dict[str, Any]:
        s = self._state
        bound = s.bound if plan is None else plan.bound
        rank = s.rank if plan is None else plan.coords.shape[1]
        return {
            "kind": self._backend.kind, "options": self.options.as_dict(),
            "n_seen": s.m if plan is None else plan.m, "rank": rank,
            "source_offset": self.source_offset, "updates": len(self._history),
            "error_bound": bound.bound, "discarded_norm": bound.discarded,
            "source": None if self.source_record is None else self.source_record.to_attrs(),
            **self._removal_attrs(plan),
        }

    def _commit(self, plan: Plan | None, source_offset: int) -> None:
        """Write the current state, or the state ``plan`` leads to, as a new generation."""
        assert self._persistence is not None
        self._persistence.commit(
            self._state, plan, attrs=self._attrs(plan), history=self._history,
            inner_data=self._inner_data, source_offset=source_offset,
        )

    def _run(
        self, make_plan: Callable[[], Plan], source_offset: int, *,
        ledger: Ledger | None = None, removed: np.ndarray | None = None,
    ) -> UpdateRecord:
        """Plan an update, persist it when a commit is due, then switch to it.

        The plan runs with the BLAS limited to :attr:`threads` threads. ``ledger`` and
        ``removed`` are the error ledger and the removed indices before the update's own
        discard (default: the current ones).
        """
        # plan, then persist, then switch the in-memory state: an exception anywhere
        # before the switch leaves both the memory and the store as they were, and the
        # backend drops what the plan wrote in its workspace
        p = self._persistence
        if p is not None:
            # refused before planning: a plan may write (the tall mode's panels)
            p.check_writable()
        try:
            with blas_threads(self.threads):
                plan = make_plan()
            self._pending = (
                (self._ledger if ledger is None else ledger).appended(
                    plan.m, plan.record.discarded),
                self._removed if removed is None else removed,
            )
            self._history.append(plan.record)
            try:
                if p is not None and p.due(self._state, plan):
                    self._commit(plan, source_offset)
                elif p is not None:
                    p.uncommitted += 1
            except BaseException:
                self._history.pop()
                raise
        except BaseException:
            self._state.basis.discard_planned()
            raise
        apply_plan(self._state, plan)
        self._ledger, self._removed = self._pending
        if p is not None:
            p.tracker.settle(self._state.extents(), len(self._history))
        # what the update replaced goes, unless a recent commit still refers to it
        self._state.basis.release(() if p is None else p.recent)
        self._version += 1
        self.source_offset = source_offset
        return plan.record
