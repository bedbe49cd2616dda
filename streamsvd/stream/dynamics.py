"""The dynamics of a stream: trajectories and the DMD query of a compressor.

:class:`Dynamics` is the part of the :class:`~streamsvd.StreamCompressor` facade that
answers :meth:`Dynamics.dmd`. The snapshot pairs come from the right vectors ``V = V0 Vp R``
(:mod:`streamsvd.engine.rows`): the triangular factor of the pairs of the stored rows
``V0``, which only grow between two rewrites, is extended by the rows stored since the
last query and multiplied by ``Vp R`` (:class:`_StoredPairs`: nothing in the number of
snapshots); after a removal the pairs are read from ``V`` (``O(m k^2)``). Either way
they are reduced to their ``2k x 2k`` triangular factor
(:mod:`streamsvd.dynamics.pairs`), then solved and certified in ``O(k^3)``
(:mod:`streamsvd.dynamics.solve`). The trajectories are the
:class:`~streamsvd.stream.lifecycle.Lifecycle`'s (the absorption indices where one
starts, committed with every update); a removal between two snapshots breaks their pair,
so ``remove()`` of a middle column splits a trajectory in two.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from streamsvd._util.threads import blas_threads
from streamsvd.dynamics import (
    DMDResult,
    PairFactor,
    dmd_from_pairs,
    pair_factor,
    pair_positions,
)
from streamsvd.engine.downdate import intervals_skip
from streamsvd.errors import InputError

if TYPE_CHECKING:
    from streamsvd.engine.rows import RightFactor
    from streamsvd.stream.lifecycle import Lifecycle
    from streamsvd.stream.view import ExpansionView

__all__ = ["Dynamics", "dmd"]

_CHUNK = 2048  # stored rows factored at once


class Dynamics:
    """Trajectories and DMD (see the module docstring).

    Parameters
    ----------
    life : Lifecycle
        The compressor's lifecycle (its state, removals and trajectories).
    view : ExpansionView
        The compressor's view (the right vectors, the bound).
    """

    def __init__(self, life: Lifecycle, view: ExpansionView) -> None:
        self._life, self._view = life, view
        self._stored: _StoredPairs | None = None

    @property
    def trajectory_starts(self) -> np.ndarray:
        """Absorption indices at which a trajectory starts (0 included once absorbed)."""
        starts = self._life.trajectory_starts
        return np.concatenate([[0], starts]).astype(np.int64) if self._life.state.m or \
            starts.size else np.zeros(0, dtype=np.int64)

    def pairs(self) -> PairFactor:
        """Return the pair factor of the snapshots in the expansion (module docstring).

        Without removals, from the factor of the stored rows' pairs, kept up to date here
        (:class:`_StoredPairs`); after a removal, from ``V`` (``O(m k^2)``).
        """
        life = self._life
        rows = life.state.rows
        assert rows is not None
        if rows.dead.size or life.removed.size:
            self._stored = None
            V = self._view.right_factor()
            first, second = pair_positions(self.absorbed_indices(), life.trajectory_starts)
            return pair_factor(V, first, second)
        stored = self._stored
        if stored is None or not stored.valid(rows, life.trajectory_starts):
            stored = self._stored = _StoredPairs(rows.rewrites)
        stored.extend(rows, life.trajectory_starts)
        return stored.factor(rows, life.state.settled()[2])

    def absorbed_indices(self) -> np.ndarray:
        """Return the absorption index of each snapshot in the expansion (row of ``V``)."""
        life = self._life
        return intervals_skip(life.removed, np.arange(life.state.m, dtype=np.int64))

    def dmd(
        self, *, rank: int | None = None, rtol: float | None = None,
        model_error: float = 0.0, dt: float | None = None, modes: bool = True,
    ) -> DMDResult:
        """Return the DMD of the snapshots in the expansion, each eigenvalue certified.

        Parameters
        ----------
        rank : int, optional
            Keep at most ``rank`` singular directions of the pairs' first snapshots.
        rtol : float, optional
            Keep the directions with ``s_i > rtol * s_1`` (default: the numerical rank).
        model_error : float
            ``delta``: the certificate holds for every operator ``A`` with ``||A X_0 -
            X_1||_(F,M) <= delta`` over the pairs (0: the data follow a linear map
            exactly; measurement noise belongs here).
        dt : float, optional
            Time step between snapshots (for ``continuous_eigenvalues``).
        modes : bool
            Form ``U`` for the modes and forecasts (``O(n w k)``); ``False`` keeps the
            query in ``O(m k^2)`` with nothing n-sized.

        Returns
        -------
        DMDResult
            See :class:`~streamsvd.dynamics.result.DMDResult`. The eigenvalues are those
            of the DMD of the compressed snapshots ``U V^T``, whose distance to the
            snapshots is the certified :attr:`error_bound`; the residual bounds account
            for it (docs: theory, DMD). With ``forget`` the eigenvalues are rescaled by
            the factor.

        Raises
        ------
        InputError
            Without right vectors, or with no pair of consecutive snapshots.
        """
        life = self._life
        if life.state.rows is None:
            raise InputError(
                "`dmd` reads the snapshot pairs from the right vectors, and this "
                "StreamCompressor keeps none (`right_vectors=False`); create it with "
                "`dynamics=True` (or `right_vectors=True`)."
            )
        with blas_threads(life.threads):  # as an update runs (default: 1 thread)
            pairs = self.pairs()
            basis = None
            if modes and life.state.rank:
                coords = life.state.settled()[0]
                basis = np.asarray(life.state.basis.lincomb(coords))
            return dmd_from_pairs(
                pairs, rank=rank, rtol=rtol,
                error_bound=self._view.error_bound, model_error=model_error,
                orthogonality=life.state.orthogonality(), forget=life.options.forget, dt=dt,
                basis=basis,
            )

class _StoredPairs:
    """The triangular factor of the pairs of *stored* rows ``[V0_first, V0_second]``.

    ``V = V0 Vp R`` and the stored rows ``V0`` only grow between two rewrites (a rebase or
    a replacement, :mod:`streamsvd.engine.rows`), new columns being zero in old rows. So
    the factor of the pairs of stored rows is extended by the rows appended since the last
    query (``O(b w^2)``), and the pair factor of ``V`` is that of ``T0 blockdiag(Vp R,
    Vp R)`` (``O(w^2 k)``): nothing in the number of snapshots. Valid while no snapshot
    was removed (then stored row ``i`` is snapshot ``i``).
    """

    def __init__(self, rewrites: int) -> None:
        self.rewrites, self.done, self.width = rewrites, 0, 0
        self.T0 = np.zeros((0, 0))
        self.pairs = 0
        self.starts_seen = 0

    def valid(self, rows: RightFactor, starts: np.ndarray) -> bool:
        """Whether the factor still describes the stored rows (no rewrite, no late start)."""
        late = starts[self.starts_seen:]
        return (rows.rewrites == self.rewrites and rows.m >= self.done
                and not np.any(late < self.done))

    def extend(self, rows: RightFactor, starts: np.ndarray) -> None:
        """Add the pairs that end in the rows stored since the last call."""
        V0 = rows.V0
        m, w = V0.shape
        if w > self.width:  # new columns: zero in the rows already factored
            half = self.width
            pad = np.zeros((self.T0.shape[0], w - half))
            self.T0 = np.hstack([self.T0[:, :half], pad, self.T0[:, half:], pad])
            self.width = w
        ends = np.arange(max(self.done, 1), m)
        ends = ends[~np.isin(ends, starts)]
        for c in range(0, ends.size, _CHUNK):  # in chunks: the memory stays O(chunk w)
            part = ends[c:c + _CHUNK]
            new = np.hstack([V0[part - 1], V0[part]])
            self.T0 = np.asarray(np.linalg.qr(np.vstack([self.T0, new]), mode="r"))
            self.pairs += int(part.size)
        self.done, self.starts_seen = m, int(starts.size)

    def factor(self, rows: RightFactor, R: np.ndarray) -> PairFactor:
        """Return the pair factor of ``V = V0 Vp R``."""
        F = rows.Vp @ R
        k, w = F.shape[1], self.width
        last = rows.V0[-1] @ F if rows.m else np.zeros(k)
        if self.pairs == 0:
            return PairFactor(np.zeros((0, 2 * k)), 0, last)
        T = np.asarray(np.linalg.qr(np.hstack([self.T0[:, :w] @ F, self.T0[:, w:] @ F]),
                                    mode="r"))
        return PairFactor(T, self.pairs, last)


def dmd(source: Any, *, rank: int | None = None, rtol: float | None = None,
        model_error: float = 0.0, dt: float | None = None, modes: bool = True,
        error_bound: float = 0.0, storage_options: dict[str, Any] | None = None,
        ) -> DMDResult:
    """Return the certified DMD of a compressor, a finished store or an expansion.

    Parameters
    ----------
    source : StreamCompressor, Expansion, str or path-like
        A compressor (its :meth:`~streamsvd.StreamCompressor.dmd`), the path or URL of
        a store written with right vectors (opened read-only), or an
        :class:`~streamsvd.Expansion` ``U V^T`` of consecutive snapshots (one trajectory).
    rank, rtol, model_error, dt, modes
        As for :meth:`~streamsvd.StreamCompressor.dmd`.
    error_bound : float
        For an expansion only: a bound on ``||X - U V^T||_(F,M)`` (default 0, the
        expansion taken as the data).
    storage_options : dict, optional
        Options of the object store of a URL ``source``.

    Raises
    ------
    InputError
        A store or compressor without right vectors (name the option
        ``right_vectors``/``dynamics``), or fewer than two snapshots.
    """
    options: dict[str, Any] = {"rank": rank, "rtol": rtol, "model_error": model_error,
                               "dt": dt}
    if hasattr(source, "dmd"):
        return source.dmd(modes=modes, **options)
    if hasattr(source, "U") and hasattr(source, "V"):
        V = np.asarray(source.V)
        m = V.shape[0]
        first = np.arange(max(m - 1, 0), dtype=np.int64)
        return dmd_from_pairs(
            pair_factor(V, first, first + 1), error_bound=error_bound,
            basis=np.asarray(source.U) if modes else None, **options,
        )
    from streamsvd.stream.compressor import StreamCompressor

    with StreamCompressor.open(source, mode="r", storage_options=storage_options) as sc:
        return sc.dmd(modes=modes, **options)
