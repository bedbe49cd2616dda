"""Windows and forgetting: the snapshots a compressor removes, and their error ledger.

:class:`Removals` is the part of the :class:`~streamsvd.StreamCompressor` facade that
removes absorbed snapshots (:meth:`Removals.remove`, Brand's downdate of
:mod:`streamsvd.engine.downdate`), keeps the ``window`` most recent ones and weights them by
``forget``. It keeps the indices removed (disjoint ``[start, stop)`` rows, in absorption
order) and the error ledger of the discards that still lie on the current columns; the
facade's update loop carries both into the state an update leads to (``_pending``) and
the store records them.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from streamsvd.engine.bound import Bound
from streamsvd.engine.downdate import (
    Ledger,
    bound_after_removal,
    intervals_add,
    intervals_contain,
    intervals_count_below,
    intervals_skip,
    plan_remove,
)
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.state import Plan, State, StepOptions
from streamsvd.errors import InputError
from streamsvd.stream.options import CompressorOptions
from streamsvd.stream.persistence import LAYOUT, LAYOUT_WITH_REMOVALS

__all__ = ["Removals"]


class Removals:
    """Remove snapshots, keep a window, forget (see the module docstring)."""

    options: CompressorOptions
    source_offset: int
    n_seen: int
    _state: State
    _opts: StepOptions
    _removed: np.ndarray
    _ledger: Ledger
    _pending: tuple[Ledger, np.ndarray]
    _run: Callable[..., UpdateRecord]

    def _start_removals(self) -> None:
        """Nothing removed, an empty ledger."""
        self._removed = np.zeros((0, 2), dtype=np.int64)
        self._ledger = Ledger.start(0, 0.0)
        self._pending = (self._ledger, self._removed)

    def _restore_removals(self, attrs: dict[str, Any]) -> None:
        """Read the removed indices and the ledger a store's commit recorded."""
        self._removed = np.array(attrs.get("removed", []), dtype=np.int64).reshape(-1, 2)
        self._ledger = (
            Ledger(np.array(attrs["ledger"], dtype=np.float64).reshape(-1, 2))
            if "ledger" in attrs else Ledger.start(self._state.m, self._state.bound.bound)
        )

    def _removal_attrs(self, plan: Plan | None) -> dict[str, Any]:
        """Return what a commit records of the removals (of the state ``plan`` leads to).

        A store with snapshots removed has the layout :data:`~streamsvd.stream.persistence.
        LAYOUT_WITH_REMOVALS`, which a version that knows no removals refuses.
        """
        ledger, removed = (self._ledger, self._removed) if plan is None else self._pending
        return {"removed": removed.tolist(), "ledger": ledger.entries.tolist(),
                "layout": LAYOUT_WITH_REMOVALS if removed.size else LAYOUT}

    @property
    def n_absorbed(self) -> int:
        """Number of snapshots absorbed, removed ones included (the next one's index)."""
        return self._state.m + int(np.sum(self._removed[:, 1] - self._removed[:, 0]))

    @property
    def removed(self) -> np.ndarray:
        """Indices (in absorption order) of the snapshots removed, as ``[start, stop)`` rows."""
        return self._removed.copy()

    def remove(self, columns: Any) -> UpdateRecord:
        """Remove absorbed snapshots exactly: the result is as if they were never absorbed.

        Parameters
        ----------
        columns : int or sequence of int
            Indices of the snapshots in the order they were absorbed (0 is the first one
            ever absorbed; :attr:`n_absorbed` the next), unchanged by earlier removals.

        Brand's downdate (:mod:`streamsvd.engine.downdate`): the removed rows of the orthonormal
        right factor ``Y`` are read, and the small core is downdated, swept and truncated
        like any update. ``U`` is unchanged. Cost ``O(r w k + (r + k)^3 + k^2 p)`` for
        ``r`` columns, nothing in the number of snapshots absorbed, while every right
        direction keeps at least half its support on the remaining columns; otherwise
        (and once the removed rows outnumber the others) the remaining rows of ``Y``
        are orthonormalised again, ``O(m w k)`` with ``m`` the snapshots kept (the
        window's size with ``window``).

        Guarantee: the new expansion is, to rounding, ``U V^T`` with the removed columns
        deleted (then swept and truncated by the compressor's rules). Without truncation
        so far it is the expansion of the remaining snapshots; with truncation, that of
        the remaining columns of the truncated expansion, and
        ``||A_rest - U V^T||_F <= error_bound`` still holds (module
        :mod:`streamsvd.engine.downdate`: the bound is kept, or lowered to the ledger's sum of
        the discards that still lie on remaining columns). Needs ``right_vectors=True``.

        Raises
        ------
        InputError
            Without right vectors, or when an index is not an integer, out of range,
            repeated or already removed; the state, in memory and in the store, is then
            unchanged.
        """
        if self._state.rows is None:
            raise InputError(
                "`remove` needs the right vectors, and this StreamCompressor keeps none "
                "(`right_vectors=False`); create it with `right_vectors=True`."
            )
        g = np.asarray(columns)
        if g.ndim == 0:
            g = g.reshape(1)
        if g.ndim != 1 or g.size == 0 or g.dtype.kind not in "iu":
            raise InputError(
                "`columns` must be a non-empty sequence of integer snapshot indices; got "
                + f"{columns!r}"[:120] + "."
            )
        g = g.astype(np.int64)
        total = self.n_absorbed
        bad = g[(g < 0) | (g >= total)]
        if bad.size:
            raise InputError(
                f"`columns` must be indices of absorbed snapshots, 0 <= index < {total} "
                f"(the snapshots absorbed so far); got {bad[:5].tolist()}."
            )
        values, counts = np.unique(g, return_counts=True)
        if np.any(counts > 1):
            raise InputError(
                f"`columns` must name each snapshot once; got "
                f"{values[counts > 1][:5].tolist()} more than once."
            )
        gone = g[intervals_contain(self._removed, g)]
        if gone.size:
            raise InputError(
                f"`columns` must name snapshots still in the expansion; got "
                f"{gone[:5].tolist()}, already removed (see `removed`)."
            )
        return self._remove_positions(values - intervals_count_below(self._removed, values))

    def _remove_positions(self, positions: np.ndarray) -> UpdateRecord:
        """Remove the current columns at ``positions`` (sorted, distinct, valid)."""
        t0 = time.perf_counter()
        ledger = self._ledger.removed(positions)
        prior = bound_after_removal(self._state.bound, ledger)
        removed = intervals_add(self._removed, intervals_skip(self._removed, positions))
        return self._run(
            lambda: plan_remove(self._state, positions, self._opts, prior=prior, t0=t0),
            self.source_offset, ledger=ledger, removed=removed,
        )

    def _windowed(self, B: Any) -> tuple[Any, State, Ledger, np.ndarray]:
        """Prepare the absorption of the block ``B``: the window's removal, the weights.

        With ``window``, the oldest snapshots that fall out leave first (an update of their
        own), and a block wider than the window enters by its last ``window`` columns only;
        with ``forget``, the block's columns are weighted and the state the update starts
        from is scaled. Returns the block, that state, the ledger and the removed indices
        the update starts from.
        """
        window, forget = self.options.window, self.options.forget
        if window is not None or forget < 1.0:
            B = self._backend.in_memory(B)
        skipped = 0
        if window is not None:
            skipped = max(B.shape[1] - window, 0)
            out = self.n_seen + B.shape[1] - skipped - window
            if out > 0:
                self._remove_positions(np.arange(out))
            B = B[:, skipped:]
        # read after the removal above, which moved them
        removed = (intervals_add(self._removed, self.n_absorbed + np.arange(skipped))
                   if skipped else self._removed)
        state, ledger = self._state, self._ledger
        if forget < 1.0:
            b = B.shape[1]
            B = B * forget ** np.arange(b - 1, -1, -1, dtype=np.float64)
            scale = forget**b
            state = dataclasses.replace(
                state, R=state.R * scale, bound=Bound.from_array(state.bound.to_array() * scale)
            )
            ledger = ledger.scaled(scale)
        return B, state, ledger, removed
