"""Windows and forgetting: the snapshots a compressor removes, and their error ledger.

:class:`Window` is the part of the :class:`~streamsvd.StreamCompressor` facade that
removes absorbed snapshots (:meth:`Window.remove`, Brand's downdate of
:mod:`streamsvd.engine.downdate`), keeps the ``window`` most recent ones and weights them by
``forget``. The indices removed (disjoint ``[start, stop)`` rows, in absorption order)
and the error ledger of the discards that still lie on the current columns are state:
the :class:`~streamsvd.stream.lifecycle.Lifecycle` keeps them, carries them into the
state an update leads to and commits them; this part computes what a removal changes.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any

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
from streamsvd.engine.state import State
from streamsvd.errors import InputError

if TYPE_CHECKING:
    from streamsvd.stream.lifecycle import Lifecycle

__all__ = ["Window"]


class Window:
    """Remove snapshots, keep a window, forget (see the module docstring).

    Parameters
    ----------
    life : Lifecycle
        The compressor's lifecycle, whose removed indices and ledger this part reads and
        whose :meth:`~streamsvd.stream.lifecycle.Lifecycle.run` runs the removals.
    """

    def __init__(self, life: Lifecycle) -> None:
        self._life = life

    @property
    def n_absorbed(self) -> int:
        """Number of snapshots absorbed, removed ones included (the next one's index)."""
        removed = self._life.removed
        return self._life.state.m + int(np.sum(removed[:, 1] - removed[:, 0]))

    @property
    def removed(self) -> np.ndarray:
        """Indices (in absorption order) of the snapshots removed, as ``[start, stop)`` rows."""
        return self._life.removed.copy()

    def remove(self, columns: Any) -> UpdateRecord:
        """Remove absorbed snapshots exactly: the result is as if they were never absorbed.

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

        Parameters
        ----------
        columns : int or sequence of int
            Indices of the snapshots in the order they were absorbed (0 is the first one
            ever absorbed; :attr:`n_absorbed` the next), unchanged by earlier removals.

        Raises
        ------
        InputError
            Without right vectors, or when an index is not an integer, out of range,
            repeated or already removed; the state, in memory and in the store, is then
            unchanged.
        """
        if self._life.state.rows is None:
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
        gone = g[intervals_contain(self._life.removed, g)]
        if gone.size:
            raise InputError(
                f"`columns` must name snapshots still in the expansion; got "
                f"{gone[:5].tolist()}, already removed (see `removed`)."
            )
        return self.remove_positions(
            values - intervals_count_below(self._life.removed, values))

    def remove_positions(self, positions: np.ndarray) -> UpdateRecord:
        """Remove the current columns at ``positions`` (sorted, distinct, valid)."""
        t0 = time.perf_counter()
        life = self._life
        ledger = life.ledger.removed(positions)
        prior = bound_after_removal(life.state.bound, ledger)
        removed = intervals_add(life.removed, intervals_skip(life.removed, positions))
        return life.run(
            lambda: plan_remove(life.state, positions, life.opts, prior=prior, t0=t0),
            life.source_offset, ledger=ledger, removed=removed,
        )

    def windowed(self, B: Any) -> tuple[Any, State, Ledger, np.ndarray]:
        """Prepare the absorption of the block ``B``: the window's removal, the weights.

        With ``window``, the oldest snapshots that fall out leave first (an update of their
        own), and a block wider than the window enters by its last ``window`` columns only;
        with ``forget``, the block's columns are weighted and the state the update starts
        from is scaled. Returns the block, that state, the ledger and the removed indices
        the update starts from.
        """
        life = self._life
        window, forget = life.options.window, life.options.forget
        if window is not None or forget < 1.0:
            B = life.backend.in_memory(B)
        skipped = 0
        if window is not None:
            skipped = max(B.shape[1] - window, 0)
            out = life.state.m + B.shape[1] - skipped - window
            if out > 0:
                self.remove_positions(np.arange(out))
            B = B[:, skipped:]
        # read after the removal above, which moved them
        removed = (intervals_add(life.removed, self.n_absorbed + np.arange(skipped))
                   if skipped else life.removed)
        state, ledger = life.state, life.ledger
        if forget < 1.0:
            b = B.shape[1]
            B = B * forget ** np.arange(b - 1, -1, -1, dtype=np.float64)
            scale = forget**b
            state = dataclasses.replace(
                state, R=state.R * scale, bound=Bound.from_array(state.bound.to_array() * scale)
            )
            ledger = ledger.scaled(scale)
        return B, state, ledger, removed
