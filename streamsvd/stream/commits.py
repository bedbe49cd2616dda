"""What a compressor's commit writes: only what changed since its previous commit.

A :class:`~streamsvd.StreamCompressor` commits its state to a
:class:`~streamsvd.store.BasisStore` as appended arrays
(:class:`~streamsvd.store.segments.Appended`), each keeping the segments of the previous
commit that are unchanged:

* ``Q`` (and ``MQ`` for a non-Euclidean inner product), by columns: the columns of the
  previous commit are unchanged unless the basis was compacted since
  (the compactions counted in :class:`~streamsvd.engine.state.Extents` moved, or the plan
  compacts), when it is written anew;
* ``V0``, by rows: the rows of the previous commit are unchanged unless the factor was
  rebased or replaced since (the rewrites of the extents moved, or the plan replaces it); the
  columns added since are zero in those rows;
* ``history``, one row per update, only appended;
* the inner product's data (``inner_weights``, ``inner_matrix`` or the CSR arrays
  ``inner_indptr``, ``inner_indices``, ``inner_data``;
  :func:`streamsvd.io.inner_file.inner_arrays`),
  written by the first commit and kept unchanged by every later one.

The small state (``coords``, ``H``, ``R``, ``Vp``, the scalars) is written whole by the
compressor. :class:`CommitTracker` remembers those extents for the generation a commit
wrote, once the compressor switched to the committed state; a commit to any other
generation (after a failed commit, say) writes every array anew.

:class:`CommitSchedule` decides which updates are committed: every ``commit_every``
updates, or with ``commit_every="auto"`` once the time since the previous commit is a
multiple of what that commit cost, so that commits take a bounded share of the time.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from streamsvd.engine.record import HISTORY_FIELDS, UpdateRecord, history_array
from streamsvd.engine.state import Extents
from streamsvd.store.segments import Appended

__all__ = ["ASSUMED_RATE", "AUTO", "COMMIT_OVERHEAD", "CommitSchedule", "CommitTracker"]

#: The ``commit_every`` value that schedules commits by their cost (:class:`CommitSchedule`).
AUTO = "auto"
#: The share of the time the commits may take with :data:`AUTO`.
COMMIT_OVERHEAD = 0.1
#: The rate (bytes per second) at which :data:`AUTO` expects a commit to write its basis
#: until one is measured writing faster (a local disk here writes a 112 MB basis at
#: 150 to 250 MB/s, fsync included: ``bench/commit_benchmark.py``).
ASSUMED_RATE = 100e6


class CommitSchedule:
    """Which updates are committed: every ``every`` updates, or by cost with ``"auto"``.

    With an integer ``every``, an update is committed when it is the ``every``-th since
    the previous commit. With ``every="auto"``, an update is committed when the commits
    made since the schedule started, plus this one, take at most ``overhead`` of the time
    since it started::

        spent + max(last, nbytes / rate) <= overhead * (now - start)

    (``now`` once the update is planned): this commit is expected to cost as much as the
    last one, or as its ``nbytes`` (the basis it writes) at the fastest rate measured so
    far (at least :data:`ASSUMED_RATE`) when that is more. Committing then takes at most
    about ``overhead`` of the wall time (a tenth by default) whatever the store (a local
    disk, an object store) and the size of what a commit writes. Once the commits have
    spent their share, the time between two commits is about ``last / overhead``: a
    process killed between two commits loses the updates of at most that long, plus
    one. The commit that creates a new store is counted in ``spent``, but it writes no
    basis: the first update that writes one (112 MB at n = 200000 and 70 terms) is
    committed once ``nbytes / rate / overhead`` (11 s) have passed. On a reopened store,
    nothing is spent yet and the first update is committed.

    Parameters
    ----------
    every : int or "auto"
        Updates per commit, or :data:`AUTO`.
    overhead : float
        With :data:`AUTO`, the share of the time the commits may take.
    clock : callable, optional
        Returns the time in seconds (default :func:`time.monotonic`).
    """

    def __init__(self, every: int | str, *, overhead: float = COMMIT_OVERHEAD,
                 clock: Callable[[], float] | None = None) -> None:
        self.every = every
        self.overhead = overhead
        self._clock = time.monotonic if clock is None else clock
        self._start = self._clock()
        self._spent = 0.0  # seconds spent committing since the start
        self._last = 0.0  # how long the last commit took
        self._rate = ASSUMED_RATE  # the fastest bytes per second a commit wrote

    def due(self, uncommitted: int, nbytes: int = 0) -> bool:
        """Whether the update planned now, after ``uncommitted`` uncommitted ones, is committed.

        ``nbytes``: what its commit would write of the basis.
        """
        if self.every == AUTO:
            elapsed = self._clock() - self._start
            expected = max(self._last, nbytes / self._rate)
            return self._spent + expected <= self.overhead * elapsed
        return uncommitted + 1 >= int(self.every)

    @contextlib.contextmanager
    def timed(self, nbytes: int = 0) -> Iterator[None]:
        """Time a commit writing ``nbytes`` of the basis (one that raises is not counted)."""
        start = self._clock()
        yield
        self._last = self._clock() - start
        self._spent += self._last
        if self._last > 0.0:
            self._rate = max(self._rate, nbytes / self._last)


@dataclass(frozen=True)
class _Mark:
    """Extents of the arrays a generation holds, and the epochs they belong to."""

    generation: int
    extents: Extents
    records: int
    inner: bool  # whether the generation holds the inner product's data


class CommitTracker:
    """Remember what the last commit wrote (see the module docstring)."""

    def __init__(self) -> None:
        self._mark: _Mark | None = None
        self._pending: int | None = None
        self._inner_pending = True  # whether the pending generation holds the inner data
        # rows [0, _valid) of _rows encode the committed records (they never change)
        self._rows = np.zeros((0, len(HISTORY_FIELDS)))
        self._valid = 0

    def appended(
        self,
        generation: int,
        extents: Extents,
        *,
        basis: dict[str, np.ndarray],
        compact: bool,
        V0: np.ndarray | None,
        replaced: bool,
        history: list[UpdateRecord],
        inner: dict[str, np.ndarray],
    ) -> dict[str, Appended]:
        """Return the appended arrays of a commit on top of generation ``generation``.

        ``extents`` are the current state's (:meth:`streamsvd.engine.state.State.extents`);
        ``basis`` holds the planned basis arrays (``Q``, ``MQ``), ``compact`` whether
        the plan compacts it; ``V0`` the planned rows, ``replaced`` whether the plan
        replaces them; ``history`` the records including the planned one; ``inner`` the
        inner product's arrays (the same at every commit).
        """
        mark = self._mark
        if mark is not None and mark.generation != generation:
            mark = None
        columns = rows = records = 0
        if mark is not None:
            if not compact and extents.compactions == mark.extents.compactions:
                columns = mark.extents.columns
            if not replaced and V0 is not None and extents.rewrites == mark.extents.rewrites:
                rows = mark.extents.rows
            records = min(mark.records, self._valid)
        out = {
            name: Appended(a, axis=1, unchanged=min(columns, a.shape[1]))
            for name, a in basis.items()
        }
        if V0 is not None:
            out["V0"] = Appended(V0, axis=0, unchanged=min(rows, V0.shape[0]))
        out["history"] = Appended(self._history(history, records), axis=0, unchanged=records)
        kept = mark is not None and mark.inner
        for name, a in inner.items():
            out[name] = Appended(a, axis=0, unchanged=a.shape[0] if kept else 0)
        return out

    def _history(self, history: list[UpdateRecord], keep: int) -> np.ndarray:
        """Return the encoded history (a view), re-encoding the records from ``keep`` on."""
        count = len(history)
        if self._rows.shape[0] < count:
            grown = np.zeros((max(count, 2 * self._rows.shape[0], 64), len(HISTORY_FIELDS)))
            grown[:keep] = self._rows[:keep]
            self._rows = grown
        self._rows[keep:count] = history_array(history[keep:count])
        return self._rows[:count]

    def committed(self, generation: int) -> None:
        """Record that ``generation`` was committed; :meth:`settle` follows the switch."""
        self._pending = generation

    def settle(self, extents: Extents, records: int) -> None:
        """Remember the extents of the committed state (the compressor switched to it)."""
        if self._pending is None:
            return
        self._mark = _Mark(generation=self._pending, extents=extents, records=records,
                           inner=self._inner_pending)
        self._valid = records
        self._pending = None
        self._inner_pending = True

    def restored(
        self, generation: int, extents: Extents, history: np.ndarray, *, inner: bool
    ) -> None:
        """Remember the extents of a state restored from ``generation``.

        ``inner``: whether that generation holds the inner product's data (a store
        written before it was kept does not; the next commit then writes it).
        """
        self._rows = np.array(history, dtype=np.float64).reshape(-1, len(HISTORY_FIELDS))
        self._valid = self._rows.shape[0]
        self._pending = generation
        self._inner_pending = inner
        self.settle(extents, self._valid)
