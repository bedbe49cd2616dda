"""The lifecycle of a compressor: its state, each update, its store.

:class:`Lifecycle` is the part of the :class:`~streamsvd.StreamCompressor` facade that
owns everything an update changes: the state (:class:`~streamsvd.engine.state.State`),
the history, the source offset, the removed snapshots and their error ledger. It runs
every update (:meth:`Lifecycle.run`: plan, commit when due, then switch to the new state)
and creates, reopens, copies and closes the store. What a commit writes, what it lets
the basis delete and how a store is checked are :mod:`streamsvd.stream.persistence`'s;
what differs where the basis is out of core is the
:class:`~streamsvd.algebra.interface.Backend`'s. The other parts of the facade (the window
and the view) read this one and never write it but through :meth:`Lifecycle.run`.
"""

from __future__ import annotations

import copy
import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from streamsvd._util.scaling import safe_norm
from streamsvd._util.threads import blas_threads
from streamsvd._util.validation import check_choice
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import Backend
from streamsvd.engine.downdate import Ledger
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.rows import RowFactor
from streamsvd.engine.state import Plan, State, apply_plan
from streamsvd.errors import FloatRangeError, StoreError
from streamsvd.io.inner_file import inner_arrays
from streamsvd.io.provenance import SourceRecord
from streamsvd.storage import open_storage
from streamsvd.stream.options import CompressorOptions
from streamsvd.stream.persistence import (
    LAYOUT,
    LAYOUT_WITH_REMOVALS,
    StreamStore,
    open_stream_store,
    restore_state,
)

__all__ = ["Lifecycle"]


class Lifecycle:
    """A compressor's state, its updates and its store (see the module docstring).

    Parameters
    ----------
    n : int
        Size of one snapshot.
    inner : InnerProduct
        The inner product of the basis.
    options : CompressorOptions
        The compressor's validated options.
    backend : Backend
        Where the n-sized factor lives.
    threads : int or None
        BLAS threads of an update.
    source_record : SourceRecord or None
        Where the snapshots come from.
    """

    def __init__(
        self, n: int, *, inner: InnerProduct, options: CompressorOptions, backend: Backend,
        threads: int | None, source_record: SourceRecord | None,
    ) -> None:
        self.n, self.inner, self.options = n, inner, options
        self.opts = options.step_options(inner)
        self.backend = backend
        self.threads = threads
        self.source_record = source_record
        self.state = State(basis=backend.new_basis(n, inner),
                           rows=RowFactor() if options.right_vectors else None)
        self.history: list[UpdateRecord] = []
        self.version = 0  # increases with every state change (for the view's caches)
        self.source_offset = 0
        # the removed snapshots ([start, stop) rows in absorption order), the error ledger
        # of the discards that still lie on the current columns, and both as the planned
        # update leaves them (committed with it)
        self.removed = np.zeros((0, 2), dtype=np.int64)
        self.ledger = Ledger.start(0, 0.0)
        self._pending = (self.ledger, self.removed)
        # absorption indices at which a trajectory other than the first starts (DMD pairs
        # never cross them: streamsvd.stream.dynamics)
        self.trajectory_starts = np.zeros(0, dtype=np.int64)
        self.persistence: StreamStore | None = None

    @functools.cached_property
    def inner_data(self) -> dict[str, np.ndarray]:
        """The inner product's arrays that the store keeps (none for an unknown class)."""
        return inner_arrays(self.inner) or {}

    @property
    def kind(self) -> str:
        """The kind of compressor a store records (the backend's)."""
        return self.backend.kind

    # ------------------------------------------------------------ the store
    @classmethod
    def open(cls, path: Any, *, inner: Any, mode: str, kind: str, name: str,
             backend: Callable[[dict[str, Any], Any], Backend],
             storage_options: dict[str, Any] | None = None) -> Lifecycle:
        """Open a store of ``kind`` and restore the lifecycle it holds.

        ``backend(basis_attrs, root)`` returns the backend of the store at ``root``;
        ``name`` is the facade's, for the messages.
        """
        mode = check_choice(mode, "mode", ("a", "r"))
        path = open_storage(path, storage_options=storage_options)
        st, state, ip = open_stream_store(path, kind=kind, name=name, mode=mode, inner=inner)
        try:
            options = CompressorOptions.from_stored(state.n, state.attrs["options"])
            life = cls(state.n, inner=ip, options=options, threads=1,
                       backend=backend(state.attrs["basis"], path),
                       source_record=SourceRecord.from_attrs(state.attrs.get("source")))
            life.source_offset, life.history = restore_state(life.state, state.arrays,
                                                             state.attrs)
            life._restore_removals(state.attrs)
            life.version += 1
            life.persistence = StreamStore(st, commit_every=options.commit_every)
            life.persistence.restored(
                life.state, state.generation, state.attrs["basis"], state.arrays["history"],
                inner=all(name in state.arrays for name in life.inner_data),
            )
        except BaseException:
            st.close()
            raise
        return life

    def _restore_removals(self, attrs: dict[str, Any]) -> None:
        """Read the removed indices and the ledger a store's commit recorded."""
        self.removed = np.array(attrs.get("removed", []), dtype=np.int64).reshape(-1, 2)
        self.trajectory_starts = np.array(attrs.get("trajectory_starts", []), dtype=np.int64)
        self.ledger = (
            Ledger(np.array(attrs["ledger"], dtype=np.float64).reshape(-1, 2))
            if "ledger" in attrs else Ledger.start(self.state.m, self.state.bound.bound)
        )
        self._pending = (self.ledger, self.removed)

    def copied(self, *, backend: Backend | None = None, **changes: Any) -> Lifecycle:
        """Return an independent copy, without the store, whose options differ by ``changes``.

        Its basis is kept by ``backend`` (default: a fresh one of the same settings).
        """
        options = CompressorOptions.validated(self.n, **{**self.options.as_dict(), **changes})
        out = Lifecycle(self.n, inner=self.inner, options=options, threads=self.threads,
                        backend=self.backend.fresh() if backend is None else backend,
                        source_record=self.source_record)
        basis = self.backend.copied(self.state.basis, out.state.basis)
        out.state = copy.deepcopy(self.state, {id(self.state.basis): basis})
        out.history = list(self.history)
        out.source_offset = self.source_offset
        out.removed, out.ledger = self.removed, self.ledger
        out.trajectory_starts = self.trajectory_starts.copy()
        out._pending = (out.ledger, out.removed)
        return out

    def start_store(self, path: Any, storage_options: dict[str, Any] | None) -> None:
        """Create the store at ``path`` by committing the current state to it.

        All or nothing: the store exists once its first commit, which holds the whole
        state (and the basis's attributes), switched its pointer; until then a failure
        deletes everything written under it, and a process killed meanwhile leaves the
        leftovers of an interrupted creation, which the next creation replaces.
        """
        if self.persistence is not None:
            raise StoreError(
                f"this compressor already commits to {self.persistence.path}; `save` "
                "writes a compressor that has no store."
            )
        self.persistence = StreamStore.create(
            path, n=self.n, inner_fingerprint=self.inner.fingerprint,
            storage_options=storage_options, commit_every=self.options.commit_every,
        )
        before = self.backend, self.state.basis
        try:
            # a basis that no commit refers to (a tall mode's work directory) is copied
            # into the store first
            self.backend, self.state.basis = self.backend.into_store(
                self.state.basis, self.persistence.storage)
            self._commit(None, self.source_offset)
        except BaseException:
            self.backend, self.state.basis = before
            self.persistence.close()  # deletes a creation that did not commit
            self.persistence = None
            raise
        if self.backend is not before[0]:
            before[0].close()

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        if self.persistence is not None and self.persistence.uncommitted:
            self._commit(None, self.source_offset)

    @property
    def writable(self) -> bool:
        """Whether updates may be committed (no store, or one opened for writing)."""
        return self.persistence is None or self.persistence.writable

    def close(self) -> None:
        """Commit what is pending, release the store's lock and the backend's resources."""
        p = self.persistence
        if p is not None:
            if p.writable:
                self.flush()
            p.close()
            self.persistence = None
        self.state.basis.drop_scratch()
        self.backend.close()

    def attrs(self, plan: Plan | None) -> dict[str, Any]:
        """Return the attributes a commit of the current state, or of ``plan``'s, records.

        A store with snapshots removed has the layout :data:`~streamsvd.stream.persistence.
        LAYOUT_WITH_REMOVALS`, which a version that knows no removals refuses.
        """
        s = self.state
        bound = s.bound if plan is None else plan.bound
        ledger, removed = (self.ledger, self.removed) if plan is None else self._pending
        return {
            "kind": self.backend.kind, "options": self.options.as_dict(),
            "n_seen": s.m if plan is None else plan.m,
            "rank": s.rank if plan is None else plan.coords.shape[1],
            "source_offset": self.source_offset, "updates": len(self.history),
            "error_bound": bound.bound, "discarded_norm": bound.discarded,
            "source": None if self.source_record is None else self.source_record.to_attrs(),
            "removed": removed.tolist(), "ledger": ledger.entries.tolist(),
            "layout": LAYOUT_WITH_REMOVALS if removed.size else LAYOUT,
            "trajectory_starts": self.trajectory_starts.tolist(),
        }

    def _commit(self, plan: Plan | None, source_offset: int) -> None:
        """Write the current state, or the state ``plan`` leads to, as a new generation."""
        assert self.persistence is not None
        self.persistence.commit(
            self.state, plan, attrs=self.attrs(plan), history=self.history,
            inner_data=self.inner_data, source_offset=source_offset,
        )

    # ------------------------------------------------------------ updates
    def run(
        self, make_plan: Callable[[], Plan], source_offset: int, *,
        ledger: Ledger | None = None, removed: np.ndarray | None = None,
        name: str = "the update",
    ) -> UpdateRecord:
        """Plan an update, persist it when a commit is due, then switch to it.

        The plan runs with the BLAS limited to :attr:`threads` threads. ``ledger`` and
        ``removed`` are the error ledger and the removed indices before the update's own
        discard (default: the current ones). ``name`` is the argument the update came
        from, for the message of a result beyond the float64 range
        (:class:`~streamsvd.errors.FloatRangeError`, the state left as it was).
        """
        # plan, then persist, then switch the in-memory state: an exception anywhere
        # before the switch leaves both the memory and the store as they were, and the
        # backend drops what the plan wrote in its workspace
        p = self.persistence
        if p is not None:
            # refused before planning: a plan may write (the tall mode's panels)
            p.check_writable()
        try:
            with blas_threads(self.threads):
                try:
                    plan = make_plan()
                except FloatRangeError as exc:  # the engine's, named here
                    raise exc.naming(name, self._norm()) from exc
            self._pending = (
                (self.ledger if ledger is None else ledger).appended(
                    plan.m, plan.record.discarded),
                self.removed if removed is None else removed,
            )
            self.history.append(plan.record)
            try:
                if p is not None and p.due(self.state, plan):
                    self._commit(plan, source_offset)
                elif p is not None:
                    p.uncommitted += 1
            except BaseException:
                self.history.pop()
                raise
        except BaseException:
            self.state.basis.discard_planned()
            raise
        apply_plan(self.state, plan)
        self.ledger, self.removed = self._pending
        if p is not None:
            p.tracker.settle(self.state.extents(), len(self.history))
        # what the update replaced goes, unless a recent commit still refers to it
        self.state.basis.release(() if p is None else p.recent)
        self.version += 1
        self.source_offset = source_offset
        return plan.record

    def _norm(self) -> float:
        """Return the norm of the expansion, ``||R||_F`` (0 when it is empty)."""
        return safe_norm(self.state.R)
