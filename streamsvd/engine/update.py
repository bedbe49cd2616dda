"""The one update step of a compressor (absorb, add, merge), over a basis backend.

The state it updates (``U = Q coords``, ``V = Y R``), the plan and its deferred writes
live in :mod:`streamsvd.engine.state`.

Every update is planned first (:func:`plan_absorb`, :func:`plan_add`,
:func:`plan_merge`, :func:`plan_finalize`): the new directions are orthonormalised in the
backend's workspace, the small core ``K`` is rotated, sorted and truncated
(:func:`streamsvd.engine.core.core_step`), and when a compaction ``Q <- [Q, Q_new] coords`` pays it
is computed into the workspace too, so that its Gram is measured from the columns
themselves. A plan is small matrices and a list of deferred
:class:`~streamsvd.engine.state.Writes` (the columns that become stored, the new rows of
``Y``); it writes nothing that the state or a store refers to.
:func:`~streamsvd.engine.state.stage_plan` makes those writes durable for a commit (the
persistence adapter calls it) and :func:`~streamsvd.engine.state.apply_plan` switches to
them, so an exception anywhere in the planning, or in a commit between the two, leaves
the state exactly as it was.

Cost of absorbing ``b`` columns at rank ``p`` (stored width ``w``): one or two block
projections (``4 n w b`` flops each, the second only for the columns the first cancelled),
CholeskyQR2 of the residual (``~4 n b^2``), the small core step (``O((p + b)^3)``), a
compaction when it pays (``2 n (w + r) p``) and ``b`` new rows of ``V`` (``O(b w p)``).
Nothing depends on the number ``m`` of snapshots already absorbed (except the rare rebase
of :mod:`streamsvd.engine.rows`). ``add`` costs ``O(m p^2)`` more (its increment spans every row).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import scipy.linalg

from streamsvd._util.scaling import safe_column_norms, safe_m_norms, safe_norm
from streamsvd.engine.aside import UNIT_FLOAT64, set_aside_budget
from streamsvd.engine.bound import Bound
from streamsvd.engine.core import core_qr, core_step, qr_factors
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.rows import RowAppend
from streamsvd.engine.state import Plan, State, StepOptions, Writes, gram_orthogonality
from streamsvd.engine.truncation import Before, Truncation
from streamsvd.errors import FloatRangeError
from streamsvd.linalg.blocks import skew_factor
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.extension import BasisExtension
from streamsvd.linalg.rejection import term_reference, top_energy
from streamsvd.linalg.sketch import plan_sketch
from streamsvd.linalg.slices import extend_block

__all__ = [
    "COMPACT_PER_COLUMN", "cutting_rounding", "plan_absorb", "plan_add", "plan_finalize",
    "plan_merge", "plan_rows",
]

logger = logging.getLogger(__name__)

# Compaction pays when the projections wasted on the extra width since the last one
# (about 4 flops per extra column, per snapshot, per row) reach its own cost
# (2 flops per stored column, per kept term, per row; a Gram-path update that keeps its
# block beside the basis records that cost as already wasted).
_WASTE_PER_COLUMN = 4.0
COMPACT_PER_COLUMN = 2.0
# and when the basis is stored in this many pieces (the panels out of core, one per
# update that does not compact): every pass reads each in tasks of its own, so without
# cuts the passes grew with the updates (blocks of 1 at n = 2e5: 35.4 s for 60 columns,
# 8.4 s compacting at 8 panels; bench/studies/outofcore-benchmark.md)
_MAX_PIECES = 8


# ---------------------------------------------------------------------------- planning
def plan_absorb(state: State, X: np.ndarray, opts: StepOptions, *, t0: float,
                name: str | None = None, previous: UpdateRecord | None = None,
                unit: float = UNIT_FLOAT64) -> Plan:
    """Plan the absorption of a block of snapshots ``X`` (``n x b``).

    ``name``: ``X``'s name in the caller's words; given, ``X`` is checked finite by
    :func:`~streamsvd.linalg.extend.extend_basis` (a NaN or infinite entry raises
    :class:`~streamsvd.errors.NonFiniteError` naming it), else it must be finite.
    ``previous``: the record of the update before (a stream's history, stored with it):
    when it was an absorb that kept few directions, a block with something to set aside
    finds its own from a sketch (:func:`~streamsvd.linalg.sketch.plan_sketch`). ``unit``:
    the unit roundoff of the block's source (``X`` itself is float64), which a sketch
    cannot set aside below, and above float64's lets the block set more aside
    (:func:`~streamsvd.engine.aside.set_aside_budget`).

    The right factor grows to ``blockdiag(Y, I_b) K`` with the core
    ``K = [[R, 0], [C^T, R_new^T]]`` (``C`` the block's coefficients on the basis,
    ``R_new`` its residual's triangular factor).
    """
    state = state.as_settled()
    b = X.shape[1]
    before = (previous.new_directions
              if previous is not None and previous.kind == "absorb" else None)
    ext = extend_block(
        state.basis, state.coords, X, inner=opts.inner, reject_tol=opts.reject_tol,
        basis_gram=state.gram, aside=set_aside_budget(opts, b, unit=unit, state=state, X=X),
        sketch=plan_sketch(before, b, unit), name=name,
    )
    k, p = state.R.shape
    K = np.zeros((k + b, p + ext.rank))
    K[:k, :p] = state.R
    K[k:, :p] = ext.coeffs.T
    K[k:, p:] = ext.R_new.T
    d_rej = ext.rejected_norm()
    block_norm = ext.block_norm
    return _plan(
        state, ext, K, opts, kind="absorb", columns=b, m=state.m + b, t0=t0, d_rej=d_rej,
        rejection_root=math.sqrt(d_rej) * math.sqrt(block_norm), prior=state.bound,
        old_rows=k,
    )


def plan_add(
    state: State,
    U_k: np.ndarray,
    V_k: np.ndarray,
    dV: np.ndarray | None,
    opts: StepOptions,
    *,
    t0: float,
) -> Plan:
    """Plan the increment ``U dV^T + U_k V_k^T`` (``dV`` in the internal term order).

    The increment spans every row, so the right factor is formed whole (``O(m p^2)``)
    and replaced by its Householder QR.
    """
    state = state.as_settled()
    assert state.rows is not None
    ref = term_reference(safe_m_norms(U_k, opts.inner), safe_column_norms(V_k))
    ext = extend_basis(
        state.basis, state.coords, U_k, inner=opts.inner, reject_tol=opts.reject_tol,
        reference=ref, basis_gram=state.gram,
    )
    V_old = (state.rows.value() @ state.R if state.rank
             else np.zeros((V_k.shape[0], 0)))
    if dV is not None:
        V_old = V_old + dV
    with np.errstate(over="ignore"):  # entries beyond the range are refused below
        V_new = np.concatenate([V_old + V_k @ ext.coeffs.T, V_k @ ext.R_new.T], axis=1)
    if not np.isfinite(V_new).all():
        raise FloatRangeError("the update")
    Y_new, K = qr_factors(V_new)
    return _plan(
        state, ext, K, opts, kind="add", columns=U_k.shape[1], m=V_k.shape[0],
        t0=t0, Y_replace=Y_new, d_rej=ext.rejected_norm(V_k), rejection_root=0.0,
        prior=state.bound, overlapping=True,
    )


def plan_merge(
    state: State,
    U_o: np.ndarray,
    R_o: np.ndarray,
    Y_o: np.ndarray | None,
    m_o: int,
    prior: Bound,
    opts: StepOptions,
    *,
    t0: float,
) -> Plan:
    """Plan appending ``m_o`` later snapshots represented by ``U_o V_o^T``.

    ``V_o = Y_o R_o`` with ``Y_o`` orthonormal (``m_o x k_o``); ``Y_o`` itself is needed
    only when the right vectors are kept. A term is rejected when its residual carries
    ``||r_j||_M ||v_j|| <= reject_tol * max_i ||u_i||_M ||v_i||``: relative to the energy
    of the expansion merged, as a snapshot's residual is relative to the snapshot.

    The residuals of several terms can be large one by one and cancel in the merged core
    (the weak left vectors of two expansions of the same data differ by their rounding):
    so a term of the merged core whose amplitude is at most ``reject_tol`` times the
    largest amplitude of the smaller of the two expansions is rounding noise of the
    merge as well, and is cut like a term below ``eps`` (its norm counted in the bound).
    With a target error this cut is not made: the target's cut (in this merge, or in the
    final one when the merge does not spend the target, as in
    :mod:`streamsvd.parallel.tree`) takes such terms within the budget.
    """
    state = state.as_settled()
    u_norms, v_norms = safe_m_norms(U_o, opts.inner), safe_column_norms(R_o)
    ref = term_reference(u_norms, v_norms)
    tops = [top_energy(u_norms, v_norms)]
    if state.rank:
        tops.append(float(np.max(safe_column_norms(state.R))))
    opts = cutting_rounding(opts, opts.reject_tol * min(tops))
    ext = extend_basis(
        state.basis, state.coords, U_o, inner=opts.inner, reject_tol=opts.reject_tol,
        reference=ref, basis_gram=state.gram,
    )
    k, p = state.R.shape
    ko = R_o.shape[0]
    K = np.zeros((k + ko, p + ext.rank))
    K[:k, :p] = state.R
    K[k:, :p] = R_o @ ext.coeffs.T
    K[k:, p:] = R_o @ ext.R_new.T
    assert state.rows is None or Y_o is not None
    d_rej = ext.rejected_norm(R_o)
    # the merged columns are new ones, as an absorbed block's: their rejected part meets
    # later cuts only through their own data, of norm ||R_o|| (module bound.py)
    return _plan(
        state, ext, K, opts, kind="merge", columns=m_o, m=state.m + m_o, t0=t0,
        Y_appended=Y_o, d_rej=d_rej,
        rejection_root=math.sqrt(d_rej) * math.sqrt(safe_norm(R_o)), prior=prior,
    )


def cutting_rounding(opts: StepOptions, floor: float) -> StepOptions:
    """Return ``opts`` cutting the terms below ``floor`` as ``eps`` does, their norms in the bound.

    For the terms an update leaves at the rounding of what it combined (a merge, a
    removal); a target error's own cut takes such terms within its budget instead.
    """
    if opts.truncation.target is None and floor > opts.truncation.eps:
        return replace(opts, truncation=replace(opts.truncation, eps=floor))
    return opts


def plan_finalize(
    state: State,
    opts: StepOptions,
    *,
    t0: float,
    on_sweep: Callable[[int, float], None] | None = None,
) -> Plan:
    """Plan sweeps of the core to convergence and the truncation (no new snapshot).

    ``opts`` carries the rule and ``sweeps=None``; the result is the SVD of the current
    expansion, truncated by the compressor's rules (Eckart-Young: what is cut is
    orthogonal to what is kept, so the bound grows by the Pythagorean rule).
    ``on_sweep`` is called after every sweep (:func:`streamsvd.engine.core.core_step`).
    """
    state = state.as_settled()
    p = state.rank
    ext = BasisExtension.empty(p, state.basis.width)
    return _plan(
        state, ext, state.R, opts, kind="finalize", columns=0, m=state.m, t0=t0,
        d_rej=0.0, rejection_root=0.0, prior=state.bound, on_sweep=on_sweep,
    )


def _plan(
    state: State,
    ext: BasisExtension,
    K: np.ndarray,
    opts: StepOptions,
    *,
    kind: str,
    columns: int,
    m: int,
    t0: float,
    d_rej: float,
    rejection_root: float,
    prior: Bound,
    Y_appended: np.ndarray | None = None,
    Y_replace: np.ndarray | None = None,
    overlapping: bool = False,
    on_sweep: Callable[[int, float], None] | None = None,
    Y_map: np.ndarray | None = None,
    dead: np.ndarray | None = None,
    old_rows: int | None = None,
) -> Plan:
    """Rotate and truncate the core ``K`` and plan the new factors.

    The right factor is ``blockdiag(Y, Y_appended) K`` (``Y_appended`` the identity for an
    absorbed block, absent after ``finalize``), or ``Y_replace K`` after ``add``; after a
    removal (:mod:`streamsvd.engine.downdate`) ``Y`` stands for ``Y_live Y_map``, ``dead``
    being the stored rows no longer live. ``old_rows``: for an absorbed block, the rows of
    ``K`` that ``Y`` multiplies (the columns received before): the cut is then sized and
    counted with its norm in those columns, the block's rejected residuals lying in its
    own (:mod:`streamsvd.engine.bound`).
    """
    keep_rows = state.rows is not None
    p, r = state.rank, ext.rank
    Lt_inv = None  # the new basis [Q coords, Q_new] L^(-T) (skew_factor)
    if ext.skewed and state.gram is not None:  # new directions along the basis: K L cut
        L, Lt_inv = skew_factor(state.coords, state.gram, ext.cross_gram, ext.gram_new)
        K = K @ L
    K_before = None if old_rows is None else K[:old_rows]
    Q_K, K = core_qr(K, want_q=keep_rows)
    step = core_step(
        K, rule=opts.rule, sweeps=opts.sweeps, m=m, truncation=opts.truncation, kind=kind,
        before=Before(prior, d_rej, overlapping, decided_new=old_rows is not None),
        on_sweep=on_sweep, rows_before=K_before,
    )
    Q_R, R = core_qr(step.R, want_q=keep_rows)
    sweeps = step.sweeps
    w = state.basis.width
    T = step.T
    p_new = T.shape[1]
    # the basis [Q, Q_new] with Gu_ext = blockdiag(coords, I_r); compact when it pays, or
    # when the next block of this width would not fit in a buffer that holds two bases
    # and a block (a compaction is then cheaper than growing it); a smaller buffer grows
    # (geometrically, when the next block's workspace is taken), else a tight buffer
    # would compact at every update
    wasted_flops = (state.wasted_flops
                    + _WASTE_PER_COLUMN * (w + r - p_new) * max(columns, 1))
    capacity, block = state.basis.capacity, ext.accepted.size
    compact = (
        wasted_flops >= COMPACT_PER_COLUMN * (w + r) * max(p_new, 1)
        or p_new == 0
        or (w + r + block > capacity and capacity >= 2 * p_new + block)
        or state.basis.pieces >= _MAX_PIECES
    )
    T = T if Lt_inv is None else Lt_inv @ T
    coords = np.vstack([state.coords @ T[:p], T[p:]])
    if compact:
        H = state.basis.compact_planned(coords, r)
        coords, wasted_flops = np.eye(p_new), 0.0
    else:
        H = _extended_gram(state, ext)
    orth = gram_orthogonality(coords, H)
    if orth > opts.reorth_tol:
        # U <- U L^{-T}, V <- V L with U^T M U = L L^T: U V^T is unchanged (V = Y R, so
        # only R changes)
        G = coords.T @ H @ coords
        L = np.linalg.cholesky(0.5 * (G + G.T))
        coords = scipy.linalg.solve_triangular(L, coords.T, lower=True).T
        R = R @ L
        orth = gram_orthogonality(coords, H)
        if opts.sweeps is None:
            # L mixes the terms of the converged core by U's loss of orthogonality (a term
            # of 1e-13 beside terms of order 1 was left at cosines of 1e-12 with them):
            # the caller asked for the SVD at every update, so the core converges again
            again = core_step(R, rule=opts.rule, sweeps=None, m=m, truncation=Truncation(),
                              kind=kind)
            coords, R, sweeps = coords @ again.T, again.R, sweeps + again.sweeps
            orth = gram_orthogonality(coords, H)
    rows = Y_full = None
    if state.rows is not None:
        # Y <- blockdiag(Y, Y_appended) P, P = Q_K Q_R orthonormal
        P = np.eye(K.shape[0]) if Q_K is None else Q_K
        if Q_R is not None:
            P = P @ Q_R
        if Y_replace is not None:
            Y_full = Y_replace @ P
        else:
            rows = plan_rows(state, P, Y_appended, Y_map=Y_map)
    discarded = math.hypot(step.cut_norm, d_rej)  # orthogonal parts (bound.py)
    bound = prior.step(
        discarded, step.coupling_root, overlapping=overlapping,
        rejection_root=rejection_root, rejected=d_rej, discarded_before=step.cut_before,
    )
    record = UpdateRecord(
        kind=kind, columns=columns, rank=p_new, new_directions=ext.rank,
        rejected=ext.rejected, cut=step.cut, discarded=discarded,
        sweeps=sweeps, max_cosine=step.max_cosine, orthogonality=orth,
        error_bound=bound.bound, seconds=time.perf_counter() - t0,
        passes=ext.passes + int(compact),
    )
    logger.debug(
        "%s of %d columns: %d passes over the basis, %d sweeps, rank %d", kind, columns,
        ext.passes, sweeps, p_new,
    )
    writes = Writes(
        columns=0 if compact else r, compacted=compact, rows=rows, rows_replaced=Y_full,
        dead_rows=dead,
    )
    return Plan(coords=coords, gram=H, R=R, m=m, wasted_flops=wasted_flops, bound=bound,
                record=record, writes=writes)


def plan_rows(
    state: State, P: np.ndarray, Y_appended: np.ndarray | None,
    *, Y_map: np.ndarray | None = None,
) -> RowAppend:
    """Plan ``Y <- blockdiag(Y, Y_appended) P``: the new rows and the new ``Vp``.

    ``P`` (``(k + k_a) x k_new``) is orthonormal; ``Y_appended`` (the identity when None)
    holds the new rows' own orthonormal factor; ``Y_map`` (``k x k'``), when given, maps
    ``Y`` first (``Y <- Y Y_map``: a removal). When the stored factor is too wide
    (:attr:`~streamsvd.engine.rows.RowFactor.wide`) the plan is made in the coordinates after a
    rebase, which staging writes.
    """
    rows = state.rows
    assert rows is not None
    k = state.R.shape[0] if Y_map is None else Y_map.shape[1]
    rebase = rows.wide
    Vp = np.eye(rows.Vp.shape[1]) if rebase else rows.Vp
    if Y_map is not None:
        Vp = Vp @ Y_map
    N = P[k:] if Y_appended is None else Y_appended @ P[k:]
    return rows.plan_append(Vp @ P[:k], N, rebase=rebase)


# ---------------------------------------------------------------------------- helpers
def _extended_gram(state: State, ext: BasisExtension) -> np.ndarray:
    """``H`` of ``[Q, Q_new]`` from the blocks Gram-Schmidt measured (:class:`BasisExtension`)."""
    w, r = state.basis.width, ext.rank
    H = np.zeros((w + r, w + r))
    H[:w, :w] = state.gram
    H[:w, w:] = ext.cross_gram
    H[w:, :w] = ext.cross_gram.T
    H[w:, w:] = ext.gram_new
    return H
