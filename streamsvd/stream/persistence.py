"""The store of a stream: what a :class:`~streamsvd.StreamCompressor` commits and reads back.

A compressor with a store holds a :class:`StreamStore`: the store's handle
(:class:`~streamsvd.store.BasisStore`), the :class:`~streamsvd.stream.commits.CommitTracker` that
makes a commit write only what changed, and the count of updates not committed yet. A
commit writes

* the basis and the right factor *this update leads to* (the backend's planned arrays:
  the state in memory switches only after the commit succeeded),
* the small state packed into one array ``small`` (``coords``, ``H``, ``R``, ``Vp`` when the
  right vectors are kept, and the scalars: the bound's three norms, the source offset,
  the number of snapshots, the basis's wasted width), whose shapes are recorded in the
  attribute ``small_layout``,
* the attributes the facade gives (options, provenance, counts, the removed snapshots),
  and the stored rows of the right factor that removals left dead (``rows_dead``).

:func:`open_stream_store` checks what a store holds (the kind of compressor, the layout
version :data:`LAYOUT`, or :data:`LAYOUT_WITH_REMOVALS` once snapshots were removed; the
inner product) before anything is restored from it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, cast

import numpy as np

from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.engine.bound import Bound
from streamsvd.engine.downdate import intervals_add
from streamsvd.engine.record import UpdateRecord, record_from_row
from streamsvd.engine.state import Plan, State, stage_plan
from streamsvd.errors import StoreError, StoreFormatError, StoreMismatchError
from streamsvd.io.inner_file import inner_from_arrays
from streamsvd.store import BasisStore, open_store
from streamsvd.store.format import StoreState
from streamsvd.stream.commits import CommitSchedule, CommitTracker

__all__ = [
    "LAYOUT", "LAYOUT_WITH_REMOVALS", "StreamStore", "open_stream_store",
    "restore_state",
]


# version of the arrays a StreamCompressor commits (3: Q, V0, history appended; 4: V0 Vp
# is the orthonormal factor Y of V = Y R; 5: as 4, with snapshots removed, whose rows of
# V0 are dead: a version that reads 4 only would take them for live ones)
LAYOUT = 4
LAYOUT_WITH_REMOVALS = 5
# added to either when the small state's Gram is pending (streamsvd.engine.state.State: its
# coords the identity, its Gram not stored): a version that reads 4 and 5 only would take
# the basis for orthonormal, where it is so only to about eps lambda_1 / lambda_k
PENDING_GRAM = 2
READABLE_LAYOUTS = (LAYOUT, LAYOUT_WITH_REMOVALS, LAYOUT + PENDING_GRAM,
                    LAYOUT_WITH_REMOVALS + PENDING_GRAM)


@dataclass(frozen=True)
class _Small:
    """The small state, as one commit writes it."""

    coords: np.ndarray
    gram: np.ndarray | None  # None: pending, stored as an empty piece
    R: np.ndarray
    Vp: np.ndarray | None
    bound: Bound
    source_offset: int
    m: int
    wasted_flops: float

    def pack(self) -> tuple[np.ndarray, list[list[int]]]:
        """Return the flat array and the shapes of its pieces."""
        # the bound's norms are >= 0; an infinite one (the coupling after `add`) is stored
        # as -1, since a store holds finite numbers only; the parts of the bound stores
        # before kept no record of come last, where those stores' readers do not look
        account = self.bound.to_array()
        norms = np.where(np.isinf(account), -1.0, account)
        scalars = np.concatenate([norms[:3], [float(self.source_offset), float(self.m),
                                              self.wasted_flops], norms[3:]])
        gram = np.zeros((0, 0)) if self.gram is None else self.gram
        pieces = [self.coords, gram, self.R, scalars]
        if self.Vp is not None:
            pieces.insert(3, self.Vp)
        return (np.concatenate([a.ravel() for a in pieces]),
                [list(a.shape) for a in pieces])

    @classmethod
    def unpack(cls, flat: np.ndarray, layout: list[list[int]], *, pending: bool) -> _Small:
        """Read the pieces back (``Vp`` is there when the layout has five pieces)."""
        pieces, start = [], 0
        for shape in layout:
            size = int(np.prod(shape))
            pieces.append(flat[start : start + size].reshape(shape))
            start += size
        scalars = pieces[-1]
        account = np.concatenate([scalars[:3], scalars[6:8]])  # 3 floats in older stores
        return cls(
            coords=pieces[0], gram=None if pending else pieces[1], R=pieces[2],
            Vp=pieces[3] if len(pieces) == 5 else None,
            bound=Bound.from_array(np.where(account < 0, np.inf, account)),
            source_offset=int(scalars[3]), m=int(scalars[4]),
            wasted_flops=float(scalars[5]),
        )


def basis_bytes(state: State, plan: Plan) -> int:
    """Return the bytes of ``Q`` a commit of ``plan`` writes (all, or the appended columns)."""
    w = plan.writes
    columns = plan.coords.shape[0] if w.compacted else w.columns
    return 8 * state.basis.n * int(columns)


def _committed_parts(state: State, plan: Plan | None, source_offset: int) -> tuple:
    """Return what a commit of ``state`` (or of the state ``plan`` leads to) writes.

    The basis's arrays and attributes, the rows of ``Y`` (``(V0, Vp)`` or None), whether
    the basis was compacted and ``Y`` replaced, and the small state. Staging the plan
    writes its new columns and rows (:func:`streamsvd.engine.state.stage_plan`).
    """
    if plan is None:
        basis, basis_attrs = state.basis.commit_arrays(0, compacted=False)
        rows = None if state.rows is None else (state.rows.V0, state.rows.Vp)
        small = _Small(state.coords, state.gram, state.R, None if rows is None else rows[1],
                       state.bound, source_offset, state.m, state.wasted_flops)
        return basis, basis_attrs, rows, False, False, small
    stage_plan(state, plan)
    w = plan.writes
    basis, basis_attrs = state.basis.commit_arrays(w.columns, compacted=w.compacted)
    rows = _planned_rows(state, plan)
    small = _Small(plan.coords, plan.gram, plan.R, None if rows is None else rows[1],
                   plan.bound, source_offset, plan.m, plan.wasted_flops)
    return basis, basis_attrs, rows, w.compacted, w.rows_replaced is not None, small


class StreamStore:
    """A compressor's store: its handle, what the last commit wrote, what waits for one."""

    def __init__(self, handle: BasisStore, *, commit_every: int | str) -> None:
        self.handle = handle
        self.commit_every = commit_every
        self.schedule = CommitSchedule(commit_every)
        self.tracker = CommitTracker()
        self.uncommitted = 0
        self._recent: tuple[dict[str, Any], ...] = ()  # the basis of the last two commits

    @classmethod
    def create(cls, path: Any, *, n: int, inner_fingerprint: str,
               storage_options: dict[str, Any] | None, commit_every: int | str
               ) -> StreamStore:
        """Begin a new store at ``path``: its first :meth:`commit` creates it.

        Until that commit the store does not exist (it has no pointer);
        :meth:`close` before it deletes everything written under it
        (:meth:`~streamsvd.store.BasisStore.begin`).
        """
        handle = BasisStore.begin(
            path, n=n, dtype="float64", inner_fingerprint=inner_fingerprint,
            storage_options=storage_options,
        )
        return cls(handle, commit_every=commit_every)

    @property
    def path(self) -> str:
        """Where the store is."""
        return str(self.handle.path)

    @property
    def storage(self) -> Any:
        """The store's :class:`~streamsvd.storage.Storage`."""
        return self.handle.storage

    @property
    def writable(self) -> bool:
        """Whether the store was opened to continue the stream (mode ``"a"``)."""
        return self.handle.mode == "a"

    def check_writable(self) -> None:
        """Raise :class:`~streamsvd.errors.StoreError` when the store is open read-only."""
        if not self.writable:
            raise StoreError(
                f"the store {self.path} is open read-only; reopen it with "
                "`StreamCompressor.open(path, mode='a')` to continue the stream."
            )

    @property
    def recent(self) -> tuple[dict[str, Any], ...]:
        """The basis attributes of the last two commits (what readers may still use)."""
        return self._recent

    def due(self, state: State, plan: Plan) -> bool:
        """Whether ``plan`` is committed (``commit_every``: :class:`CommitSchedule`)."""
        return self.schedule.due(self.uncommitted, basis_bytes(state, plan))

    def commit(self, state: State, plan: Plan | None, *, attrs: dict[str, Any],
               history: list[UpdateRecord], inner_data: dict[str, np.ndarray],
               source_offset: int) -> None:
        """Write ``state``, or the state ``plan`` leads to, as a new generation.

        Raises :class:`~streamsvd.errors.StoreError` on a store opened read-only.
        """
        self.check_writable()
        # the basis's own writes (a tall mode's zarr copies of its panels) count as the
        # commit's time
        with self.schedule.timed(0 if plan is None else basis_bytes(state, plan)):
            basis, basis_attrs, rows, compact, replaced, small = _committed_parts(
                state, plan, source_offset)
            # only what changed since the previous commit is written (streamsvd.stream.commits)
            appended = self.tracker.appended(
                self.handle.generation, state.extents(), basis=dict(basis), compact=compact,
                V0=None if rows is None else rows[0], replaced=replaced, history=history,
                inner=inner_data,
            )
            flat, layout = small.pack()
            attrs = {
                **attrs, "source_offset": int(source_offset), "updates": len(history),
                "layout": attrs.get("layout", LAYOUT) + (PENDING_GRAM if small.gram is None
                                                         else 0),
                "small_layout": layout, "basis": basis_attrs,
                "rows_capacity": None if state.rows is None else list(state.rows.capacity),
                "rows_dead": None if state.rows is None else intervals_add(
                    np.zeros((0, 2)), _planned_dead(state.rows.dead, plan)).tolist(),
            }
            k = self.handle.commit({"small": flat}, attrs=attrs, appended=appended)
        self.tracker.committed(k)
        self.uncommitted = 0
        if plan is None:
            self.tracker.settle(state.extents(), len(history))
        # what neither the state nor the last two commits use may go (a reader may
        # still be on the previous generation)
        self._recent = (basis_attrs, *self._recent[:1])
        state.basis.collect(self._recent)

    def restored(self, state: State, generation: int, basis_attrs: dict[str, Any],
                 history: Any, *, inner: bool) -> None:
        """Take up the commit ``state`` was restored from (see :meth:`CommitTracker.restored`).

        Opened for writing, the basis deletes what an interrupted update left.
        """
        self.tracker.restored(generation, state.extents(), history, inner=inner)
        self._recent = (basis_attrs,)
        if self.writable:
            state.basis.collect(self._recent)

    def close(self) -> None:
        """Release the store (and its writer lock)."""
        self.handle.close()


def _planned_rows(state: State, plan: Plan) -> tuple[np.ndarray, np.ndarray] | None:
    """Return ``(V0, Vp)`` the plan leads to (views, for a commit); None without rows."""
    if state.rows is None:
        return None
    w = plan.writes
    if w.rows_replaced is not None:
        return w.rows_replaced, np.eye(w.rows_replaced.shape[1])
    assert w.rows is not None
    return state.rows.stage(w.rows), w.rows.Vp


def _planned_dead(dead: np.ndarray, plan: Plan | None) -> np.ndarray:
    """Return the dead stored rows of the right factor once ``plan`` is applied."""
    if plan is None:
        return dead
    if plan.writes.rows_replaced is not None:
        return np.zeros(0, dtype=np.int64)
    return dead if plan.writes.dead_rows is None else plan.writes.dead_rows


def open_stream_store(path: Any, *, kind: str, name: str, mode: str, inner: Any
                      ) -> tuple[BasisStore, StoreState, InnerProduct]:
    """Open a compressor's store and check its kind, layout, commit, then inner product.

    ``name`` is the class the user called (for the messages). Returns the handle, the
    state read and the inner product to use; the handle is closed on any error.
    """
    st = open_store(path, cast(Literal["r", "a"], mode))
    try:
        state = st.read()
        attrs = state.attrs
        if attrs.get("kind") != kind:
            raise StoreMismatchError(
                f"`path` {path!s} holds a basis store that was not written by a "
                f"{name} (its kind is {attrs.get('kind')!r}); open any compressor's store "
                "with `streamsvd.parallel.open_compressor`, any other with "
                "`streamsvd.store.open_store`."
            )
        if attrs.get("layout") not in READABLE_LAYOUTS:
            raise StoreFormatError(
                f"`path` {path!s} holds a StreamCompressor of layout "
                f"{attrs.get('layout', 1)!r}, written by another version of streamsvd; "
                f"this version reads layouts {min(READABLE_LAYOUTS)} to "
                f"{max(READABLE_LAYOUTS)}. "
                "Ingest the "
                "snapshots again into a "
                "new store."
            )
        _check_committed(path, state, name)
        ip = _inner_of(path, state, inner)
    except BaseException:
        st.close()
        raise
    return st, state, ip


# what every commit of a compressor holds (StreamStore.commit)
COMMITTED_ARRAYS = ("small", "history")
COMMITTED_ATTRS = {"options": dict, "small_layout": list, "basis": dict}


def _check_committed(path: Any, state: StoreState, name: str) -> None:
    """Raise :class:`StoreFormatError` unless ``state`` is a whole commit of a compressor.

    A store that an earlier version of streamsvd created in two commits, and that was
    killed between them, holds only the first one: no arrays and none of the state.
    """
    if not state.arrays and "small_layout" not in state.attrs:
        raise StoreFormatError(
            f"`path` {path!s} is an incomplete store: its creation by a {name} was "
            f"interrupted before its first commit (generation {state.generation} holds "
            "none of its state), so nothing was absorbed. Delete it and ingest the "
            "snapshots again."
        )
    missing = [f"array {a!r}" for a in COMMITTED_ARRAYS if a not in state.arrays] + [
        f"attribute {a!r}" for a, kind in COMMITTED_ATTRS.items()
        if not isinstance(state.attrs.get(a), kind)
    ]
    if missing:
        raise StoreFormatError(
            f"`path` {path!s} is damaged: generation {state.generation} lacks "
            f"{', '.join(missing)} of the state a {name} commits. Restore the store from "
            "a copy."
        )


def _inner_of(path: Any, state: StoreState, inner: Any) -> InnerProduct:
    """Return the inner product to continue with: the one given, else the store's."""
    if inner is not None:
        ip = as_inner(inner, state.n)
    else:
        stored = inner_from_arrays(state.arrays)
        if stored is not None and stored.fingerprint != state.inner_fingerprint:
            raise StoreFormatError(
                f"`path` {path!s} is damaged: the inner product it keeps does not match "
                f"its fingerprint {state.inner_fingerprint[:12]}... Restore the store from "
                "a copy."
            )
        ip = as_inner(None) if stored is None else stored
        if ip.fingerprint != state.inner_fingerprint:
            raise StoreMismatchError(
                f"`inner` must be given: the store {path!s} was written with an inner "
                f"product (fingerprint {state.inner_fingerprint[:12]}...) that it does not "
                "keep (an earlier version of streamsvd, or an inner product of another "
                "class). Pass the same matrix or weights."
            )
    if ip.fingerprint != state.inner_fingerprint:
        raise StoreMismatchError(
            f"`inner` must be the inner product the store {path!s} was written with "
            f"(fingerprint {state.inner_fingerprint[:12]}...); got {ip!r}. Pass the "
            "same matrix or weights."
        )
    return ip


def restore_state(state: State, arrays: dict[str, Any], attrs: dict[str, Any]
                  ) -> tuple[int, list[UpdateRecord]]:
    """Load a commit into ``state``; return the source offset and the history."""
    a = {k: np.array(v, dtype=np.float64) for k, v in arrays.items()
         if not k.startswith("inner_")}
    small = _Small.unpack(a["small"], attrs["small_layout"],
                          pending=attrs.get("layout", LAYOUT) - PENDING_GRAM in (
                              LAYOUT, LAYOUT_WITH_REMOVALS))
    state.basis.restore(a, attrs["basis"])
    if state.rows is not None:
        assert small.Vp is not None
        dead = [np.arange(a0, b0) for a0, b0 in attrs.get("rows_dead") or []]
        state.rows.restore(a["V0"], small.Vp, capacity=tuple(attrs["rows_capacity"]),
                           dead=np.concatenate(dead + [np.zeros(0, dtype=np.int64)]))
    state.coords, state.gram, state.R = small.coords, small.gram, small.R
    state.bound, state.m, state.wasted_flops = small.bound, small.m, small.wasted_flops
    state._settled = None
    return small.source_offset, [record_from_row(row) for row in a["history"]]
