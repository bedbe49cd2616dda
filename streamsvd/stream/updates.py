"""The updates of a stream that bring snapshots in: absorb, add, merge, finalize.

:class:`Updates` is the part of the :class:`~streamsvd.StreamCompressor` facade that
checks what an update is given and plans it with :mod:`streamsvd.engine.update` (or the
Gram path of :mod:`streamsvd.engine.update_gram`); the
:class:`~streamsvd.stream.lifecycle.Lifecycle` runs the plan (commit when due, then the
switch to the new state). Removals are the :class:`~streamsvd.stream.window.Window`'s.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.engine.aside import UNIT_FLOAT64
from streamsvd.engine.gram_path import skips_gram_path
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.update import (
    plan_absorb,
    plan_add,
    plan_finalize,
    plan_merge,
)
from streamsvd.engine.update_gram import plan_absorb_by_gram, plan_merge_by_gram
from streamsvd.stream.operands import _final_options, _increment, _merge_operand, _merge_options
from streamsvd.stream.summary import _sweep_bar

if TYPE_CHECKING:
    from streamsvd.engine.state import Plan
    from streamsvd.stream.lifecycle import Lifecycle
    from streamsvd.stream.view import ExpansionView
    from streamsvd.stream.window import Window

__all__ = ["Updates"]


class Updates:
    """Absorb, add, merge and finalize (see the module docstring).

    Parameters
    ----------
    life : Lifecycle
        The compressor's lifecycle, which runs the updates.
    window : Window
        The compressor's window (its removals before a block, its weights).
    view : ExpansionView
        The compressor's view (the coordinates of the terms it last exposed).
    """

    def __init__(self, life: Lifecycle, window: Window, view: ExpansionView) -> None:
        self._life, self._window, self._view = life, window, view

    def absorb(self, columns: Any, *, source_offset: int | None = None,
               new_trajectory: bool = False) -> UpdateRecord:
        """Append a block of snapshots (the columns of ``columns``, ``n x b``, ``b >= 1``).

        With ``window``, the oldest snapshots that would fall out are removed first
        (:meth:`remove`, an update of its own in :attr:`history`); with ``forget``, the
        expansion is scaled by ``forget^b`` and the block's columns weighted
        ``forget^(b-1), ..., 1`` (``b`` the block's width).

        On bad input an :class:`~streamsvd.errors.InputError` is raised and the state,
        in memory and in the store, is unchanged.

        Parameters
        ----------
        columns : array_like, shape (n, b)
            The new snapshots.
        source_offset : int, optional
            Position in the source just after this block, recorded in the store so that
            an interrupted ingestion resumes there; default: the previous offset + ``b``.
        new_trajectory : bool
            The block's first column starts a new trajectory: no DMD pair joins it to the
            snapshot before (:meth:`dmd`); default False, the block continues the last
            trajectory.
        """
        t0 = time.perf_counter()
        life = self._life
        B = life.backend.load(columns, rows=life.n, first=life.source_offset)
        offset = life.source_offset + B.shape[1] if source_offset is None else int(source_offset)
        first = self._window.n_absorbed
        B, state, ledger, removed = self._window.windowed(B)
        starts = life.trajectory_starts
        if new_trajectory and first > 0:
            life.trajectory_starts = np.append(starts, np.int64(first))

        def exact() -> Plan:
            return plan_absorb(state, life.backend.in_memory(B, check=False), life.opts,
                               t0=t0, name="columns",
                               previous=life.history[-1] if life.history else None,
                               unit=_unit_roundoff(columns))

        # a block in memory that the exact update takes in slices, beside few terms,
        # skips the Gram path
        skip = isinstance(B, np.ndarray) and skips_gram_path(state, B.shape[1], life.opts)
        try:
            return life.run(
                exact if skip
                else lambda: plan_absorb_by_gram(state, B, life.opts, t0=t0) or exact(),
                offset, ledger=ledger, removed=removed, name="`columns`",
            )
        except BaseException:
            life.trajectory_starts = starts
            raise

    def add(self, U_k: Any, V_k: Any, *, coefficients: Any = None) -> UpdateRecord:
        """Add the low-rank increment ``U dV^T + U_k V_k^T`` to the current matrix.

        A term whose residual carries ``||r_j||_M ||v_j|| <= reject_tol * max_i
        ||u_i||_M ||v_i||`` is rejected; the rejected residuals share the same columns, so
        their norm ``||Res V_rej^T||`` is computed exactly from two small Gram matrices.
        Needs ``right_vectors=True``.

        Parameters
        ----------
        U_k : array_like, shape (n, k)
            Left vectors of the increment (any, not necessarily orthonormal); ``k`` may
            be 0 when ``coefficients`` is given.
        V_k : array_like, shape (m, k)
            Right vectors; ``m`` must equal :attr:`n_seen` (or fixes it when the
            compressor is empty).
        coefficients : array_like, shape (m, p), optional
            ``dV``: an increment *inside* the current basis, in the coordinates of the
            ``U`` last returned by :attr:`expansion` (its column ``i`` is the change of
            ``v_i``). It costs ``O(m p^2)`` instead of a Gram-Schmidt of ``U`` against
            itself. This is how a PGD solver updates its time functions.
        """
        t0 = time.perf_counter()
        life = self._life
        s = life.state
        Uk, Vk, dV = _increment(s, U_k, V_k, coefficients, n=life.n)
        dV_int = None if dV is None else self._view.internal_coefficients(dV)
        return life.run(
            lambda: plan_add(s, Uk, Vk, dV_int, life.opts, t0=t0), life.source_offset,
            name="the increment (`U_k`, `V_k`, `coefficients`)",
        )

    def merge(self, other: Any, *, spend_target: bool = True) -> UpdateRecord:
        """Append the snapshots represented by ``other`` (they come after the current ones).

        ``other`` is a :class:`~streamsvd.StreamCompressor` fed with later columns (for
        instance on another worker) or an expansion of them; it is not modified. Its left
        vectors are decomposed on the basis, and its right vectors enter the small core
        through their core ``R_o``, so the cost is ``O(n w p_o + p_o^2 (p + p_o))`` (plus
        ``O(m_o p_o p)`` for the new rows of ``V`` when they are kept), never ``O(n m_o)``.
        A term of ``other`` is rejected relative to the energy of ``other``, and a term of
        the merged core below
        ``reject_tol`` times the largest amplitude of the smaller expansion is cut as
        rounding noise, its norm counted in the bound (see
        :func:`streamsvd.engine.update.plan_merge`).
        Error bounds compose: the two parts cover disjoint columns, so before the merge's
        own truncation the bound is ``sqrt(b_self^2 + b_other^2)``, as in the hierarchical
        POD of Himpe, Leibner and Rave (2018).

        With ``spend_target=False`` the merge cuts nothing for the target error (``eps``,
        ``rtol`` and the rank cap still apply): the tree of :func:`streamsvd.parallel.
        tree_compress` merges so, and the budget its leaves left is spent by one optimal
        cut in the root's :meth:`finalize`, as pyMOR's ``dist_vectorarray_hapod`` does.
        """
        t0 = time.perf_counter()
        life = self._life
        s = life.state
        op = _merge_operand(other, n=life.n, inner=life.inner, keep_rows=s.rows is not None,
                            by_rows=isinstance(s.basis, PanelBasis))
        prior = s.bound.combine(op.bound)
        opts = _merge_options(life.opts, spend_target=spend_target)
        return life.run(
            lambda: plan_merge_by_gram(s, op.Q, op.coordinates(), op.R, op.Y, op.m, prior,
                                       opts, t0=t0)
            or plan_merge(s, op.left_vectors(life.backend.in_memory), op.R, op.Y, op.m,
                          prior, opts, t0=t0),
            life.source_offset + op.m,
            ledger=life.ledger.appended(s.m + op.m, prior.bound), name="`other`",
        )

    def finalize(
        self, *, rule: str = "jacobi", max_rank: int | None = None, progress: bool = False
    ) -> UpdateRecord:
        """Converge the small core to the SVD of the current expansion, then truncate.

        Rotation sweeps of ``rule`` (``"jacobi"`` by default: quadratic convergence) run
        on the core until a sweep rotates nothing (at most 200), and the truncation rules
        (``eps``, ``rtol``, and ``max_rank``, or the compressor's own when omitted, without
        the oversampling) are applied to the converged amplitudes: the optimal
        (Eckart-Young) truncation of the expansion. Costs one compaction of the basis at
        most, nothing in the number of snapshots; recorded in :attr:`history` (kind
        ``"finalize"``) and committed like any update. :meth:`close` calls it. The stream
        may continue afterwards (with the compressor's options). ``progress=True`` shows
        the sweeps on stderr (tqdm). An interrupt (Ctrl-C) or an error during the sweeps
        leaves the compressor and its store at the last commit: calling ``finalize``
        again starts the sweeps over from it.
        """
        t0 = time.perf_counter()
        life = self._life
        opts = _final_options(life.opts, life.options, rule=rule, max_rank=max_rank)
        with _sweep_bar(life.state.rank, progress) as on_sweep:
            record = life.run(
                lambda: plan_finalize(life.state, opts, t0=t0, on_sweep=on_sweep),
                life.source_offset,
            )
        self._view.warn_if_target_missed()
        return record

    def expect(self, columns: Any) -> None:
        """Name the block that will follow the one the coming :meth:`absorb` is given.

        Used by the tall mode (a no-op in memory): a block read from its source (a
        :class:`~streamsvd.algebra.panels.lazy.LazyBlock`, as
        :func:`~streamsvd.stream.ingest.ingest` hands them out) is then read by the
        coming update's last pass over the panels, which writes its scratch copy and
        forms its products with the new basis: its own update then makes one pass over
        the panels instead of two (``bench/README.md``). The results are the same to the
        last bit (tested); should the call after the coming one get another block, or the
        coming update take another path, the block is read as usual.
        """
        expect = getattr(self._life.state.basis, "expect", None)
        if expect is not None:
            expect(columns)


def _unit_roundoff(columns: Any) -> float:
    """Return the unit roundoff of the snapshots' own dtype (float64's unless coarser).

    The block is converted to float64; float32 snapshots keep their rounding, which
    decides whether a sketch can set their weakest directions aside
    (:class:`~streamsvd.linalg.sketch.Sketch`).
    """
    dtype = getattr(columns, "dtype", None)
    unit = UNIT_FLOAT64
    if dtype is not None and np.issubdtype(dtype, np.floating):
        unit = max(unit, float(np.finfo(dtype).eps) / 2)
    return unit
