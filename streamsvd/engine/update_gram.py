"""Absorb a block, or merge an expansion, through a Gram matrix, when the cut allows it.

When an update cuts (a target error, or a rank cap), it can be the method of snapshots,
as pyMOR's HAPOD does: one product gives the Gram ``Phi = F^T M F`` of the expansion and
the block, whose eigenvectors give the kept terms, written as the new basis in one more
product (:func:`plan_absorb_by_gram`; a merge, :func:`plan_merge_by_gram`, takes the
other expansion's basis as the block). The method, its cost, what the bound counts and
when the exact path (:func:`streamsvd.engine.update.plan_absorb`) runs instead are
derived on the theory page ``docs/theory/gram-path.md`` (The Gram path); the conditions
and the helpers are in :mod:`streamsvd.engine.gram_path`.
"""

from __future__ import annotations

import math
import time
from typing import Any, cast

import numpy as np
from scipy.linalg.lapack import dtrtri

from streamsvd._util.scaling import pow2_exponent, safe_m_norms, scale_into
from streamsvd.algebra.interface import DeferredGram
from streamsvd.engine.bound import Bound
from streamsvd.engine.gram_path import (
    _ALLOWANCE_SHARE,
    _EPS,
    _MAX_DRIFT,
    _MAX_SPREAD,
    _ROUNDING_LAMBDA,
    _SAFE_HIGH,
    _SAFE_LOW,
    _SMALLEST_KEPT,
    GRAM_MEASURES,
    _allowance,
    _block_refused,
    _cancellation_energy,
    _compaction_pays,
    _declined,
    _drift,
    _keeps_block,
    _kept_factors,
    _path_applies,
    _products,
    _refused_before_block,
    _refused_by_frobenius,
    _refused_by_norms,
    _room,
    _times,
    _times_left,
)
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.state import Plan, State, StepOptions, Writes, gram_orthogonality
from streamsvd.engine.truncation import Before
from streamsvd.engine.update import COMPACT_PER_COLUMN, plan_rows

__all__ = ["plan_absorb_by_gram", "plan_merge_by_gram"]


# a block at least this wide is measured by its norms before its Gram when they are
# cheap (n b flops against the Gram's n b^2: the Euclidean product, or weights); with a
# sparse M they would cost a product with M that the Gram makes again (pyMOR's heat
# example, updates of 668 snapshots at mean_l2 1e-2 .. 1e-4: 1.08-1.24x HAPOD's time
# against 0.91-1.04x without the check)
_NORMS_FIRST = 256


def plan_absorb_by_gram(
    state: State, X: Any, opts: StepOptions, *, t0: float
) -> Plan | None:
    """Plan the absorption of ``X`` (``n x b``) by its Gram matrix; None when not allowed.

    ``X`` is an array, or a block the basis reads by row chunks
    (:class:`~streamsvd.algebra.panels.lazy.LazyBlock`, the tall mode), which this path
    reads once. See the theory page ``docs/theory/gram-path.md`` for the method and the
    conditions; None leaves the state
    and the basis as they were (the caller then plans the exact update).
    """
    trunc = opts.truncation
    n, b = X.shape
    if not _path_applies(opts, n):
        return None
    basis = state.basis
    if not (_compaction_pays(basis.width, b, state.rank)
            or basis.defers_gram and _keeps_block(basis.width, b, state.rank)):
        return None
    if _refused_before_block(state, trunc, b, n):
        return None
    if isinstance(X, np.ndarray) and _refused_by_frobenius(state, trunc, X, opts.inner, n):
        return None  # refused on an upper bound of the block's energy, before its products
    if (isinstance(X, np.ndarray) and b >= _NORMS_FIRST
            and (opts.inner.is_euclidean or getattr(opts.inner, "diagonal", None) is not None)
            and _refused_by_norms(state, trunc, safe_m_norms(X, opts.inner), n)):
        return None  # refused on the block's norms, before its Gram
    # with a relative or mean-l2 target the block's Gram alone can refuse the update:
    # the projection waits for that check (a backend reading the block in one pass
    # computes both anyway)
    measured_first = trunc.target is not None and trunc.measure in GRAM_MEASURES
    # column-major, as the workspace of the exact path: the same BLAS kernels, so a
    # block scaled by powers of two below gives the same digits, scaled
    Y = np.asfortranarray(X) if isinstance(X, np.ndarray) else X
    exps = np.zeros(b, dtype=np.int64)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        S, C, H = _products(state, Y, project=not measured_first)
    norms2 = np.diag(S)
    # a finite diagonal of the Gram means a finite block (each entry of column j enters
    # S_jj, and BLAS propagates NaN and infinities): the block is checked here for free
    if not np.all((norms2 >= _SAFE_LOW) & (norms2 <= _SAFE_HIGH)):
        # squares near the ends of the range (or a zero column): scale each column by a
        # power of two first, exactly, and measure again; a block read by row chunks,
        # or one holding NaN or infinities, is left to the exact path, which loads and
        # checks it
        if not isinstance(X, np.ndarray) or not np.isfinite(X).all():
            return _declined(basis)
        Y = np.empty(X.shape, order="F")
        exps, zero = scale_into(X, Y)
        if zero.all():
            return _declined(basis)  # nothing but zero columns: the exact path counts them
        S, C, H = _products(state, Y, project=not measured_first)
        norms2 = np.diag(S)
    else:
        zero = np.zeros(b, dtype=bool)
    # a zero column (the first snapshot of a trajectory, often) adds nothing: its
    # coefficient is 0, so it enters neither Phi nor the kept vectors
    live = exps[~zero]
    top = max(int(live.max()), pow2_exponent(state.R) if state.R.size else int(live.max()))
    if top - int(live.min()) > _MAX_SPREAD or abs(top) > _MAX_SPREAD:
        return _declined(basis)
    # a zero column's exponent (0) may lie 2^664 above `top`: its 0 is not multiplied by
    # that power (0 * inf); the zeros stay in the sum (the same rounding of the others)
    block_energy = float(np.sum(norms2 * np.ldexp(1.0, 2 * (np.where(zero, top, exps) - top))))
    if measured_first:
        # the budget's growth is known before the projection: with ||F||^2 = ||R||^2 +
        # ||X||^2 (U orthonormal), a target the rounding cannot meet skips it
        if _block_refused(state, trunc, block_energy, b, n, top):
            return _declined(basis)
    if C is None:
        C = basis.project(Y, None) if basis.width else np.zeros((0, b))
    return _plan_by_gram(
        state, opts, S=S, C=C, H=H, Zb=np.where(zero, 0.0, np.ldexp(1.0, exps - top)),
        top=top,
        block_energy=block_energy, prior=state.bound, Y_appended=None, added=b,
        kind="absorb", t0=t0,
    )


def plan_merge_by_gram(
    state: State,
    Q_o: Any,
    Z_o: np.ndarray,
    R_o: np.ndarray,
    Y_o: np.ndarray | None,
    m_o: int,
    prior: Bound,
    opts: StepOptions,
    *,
    t0: float,
) -> Plan | None:
    """Plan appending ``m_o`` snapshots ``Q_o Z_o R_o^T Y_o^T`` by the Gram path, or None.

    ``Q_o`` is the other expansion's basis (``n x c``, in memory, or a block the basis
    reads by row chunks: :class:`~streamsvd.algebra.panels.lazy.LazyBlock`, the left
    vectors of a tall compressor, read once), ``U_o = Q_o Z_o`` its
    left vectors, ``V_o = Y_o R_o`` its right ones (``Y_o`` orthonormal, None when the
    right vectors are not kept); ``prior`` is the composed bound of both parts. As for
    a block (the theory page ``docs/theory/gram-path.md``) with
    ``F = [Q, Q_o] blockdiag(coords R^T, Z_o R_o^T)``: the Gram of ``[Q, Q_o]`` is one
    product over ``Q_o`` (``U_o`` is never formed) and the kept vectors are written in one
    more, where the exact path (:func:`streamsvd.engine.update.plan_merge`)
    orthonormalises ``U_o`` against the basis in several passes. The same conditions
    apply; None leaves the state and the basis as they were.
    """
    trunc = opts.truncation
    if not _path_applies(opts, Q_o.shape[0]):
        return None
    n, c = Q_o.shape
    basis = state.basis
    if c == 0 or R_o.size == 0 or not _compaction_pays(basis.width, c, state.rank):
        return None
    if _refused_before_block(state, trunc, m_o, n, width=c):
        return None
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        S, C, H = _products(state, np.asfortranarray(Q_o) if isinstance(Q_o, np.ndarray)
                            else Q_o, project=True)
    norms2 = np.diag(S)
    if not np.all((norms2 >= _SAFE_LOW) & (norms2 <= _SAFE_HIGH)):
        return _declined(basis)  # not the basis of an expansion: left to the exact path
    top = max(pow2_exponent(R_o), pow2_exponent(state.R) if state.R.size else -_MAX_SPREAD)
    if abs(top) > _MAX_SPREAD:
        return _declined(basis)
    Zb = np.ldexp(Z_o @ R_o.T, -top)
    block_energy = float(np.sum(Zb * (S @ Zb)))
    assert C is not None  # asked for with the block's Gram
    return _plan_by_gram(
        state, opts, S=S, C=C, H=H, Zb=Zb, top=top, block_energy=block_energy, prior=prior,
        Y_appended=Y_o, added=m_o, kind="merge", t0=t0,
    )


def _plan_by_gram(
    state: State,
    opts: StepOptions,
    *,
    S: np.ndarray,
    C: np.ndarray,
    H: np.ndarray,
    Zb: np.ndarray,
    top: int,
    block_energy: float,
    prior: Bound,
    Y_appended: np.ndarray | None,
    added: int,
    kind: str,
    t0: float,
) -> Plan | None:
    """Plan the update ``F = [Q, Y] blockdiag(Zq, Zb) 2^top`` from the Gram of ``[Q, Y]``.

    ``Y`` (``n x c``) is the block the basis staged, ``S = Y^T M Y``, ``C = MQ^T Y``,
    ``H = Q^T M Q``; ``Zb``
    (``c x k_b``, or the ``c`` entries of a diagonal) its coefficients, scaled by
    ``2^-top`` as ``Zq = coords R^T 2^-top``; ``block_energy = ||Y Zb||_M^2``. The rows
    appended are ``Y_appended`` (the identity when None), ``added`` snapshots; ``prior``
    is the bound before this update's cut.
    """
    trunc = opts.truncation
    basis = state.basis
    n, w = basis.n, basis.width
    k = state.R.shape[0]
    c = C.shape[1]
    kb = c if Zb.ndim == 1 else Zb.shape[1]
    size = k + kb
    # Phi = Z^T B Z, B = [[H, C], [C^T, S]] the Gram of [Q, Y], formed by blocks
    Zq = np.ldexp(state.coords @ state.R.T, -top)
    ZbT = Zb if Zb.ndim == 1 else Zb.T
    ZC = _times(Zq.T @ C, Zb)
    Phi = np.empty((size, size))
    Phi[:k, :k] = Zq.T @ H @ Zq
    Phi[:k, k:] = ZC
    Phi[k:, :k] = ZC.T
    Phi[k:, k:] = _times(_times_left(ZbT, S), Zb)
    Phi = 0.5 * (Phi + Phi.T)
    lam, W = np.linalg.eigh(Phi)
    lam, W = np.maximum(lam[::-1], 0.0), W[:, ::-1]
    total = float(np.sum(lam))
    if total <= 0.0:
        return _declined(basis)
    # the rounding of Phi, relative to its trace, or more when U combines stored
    # columns that cancel (a basis holding blocks, kept beside it by earlier updates)
    if w > state.rank:
        total = max(total, _cancellation_energy(H, S, Zq, Zb))
    allowance = _allowance(total, size, n)
    amps = np.ldexp(np.sqrt(lam), top)
    before = Before(prior, math.ldexp(math.sqrt(allowance), top))
    m = state.m + added
    keep = trunc.keep_count(amps, before=before, m=m)
    # a block with a zero column is not kept beside the basis (its Gram would be singular)
    keeps = (basis.defers_gram and cast(DeferredGram, basis).block_beside
             and _keeps_block(w, c, keep) and not (Zb.ndim == 1 and not Zb.all()))
    # Weyl: every eigenvalue of the computed Phi is within ||E||_F of the exact one
    perturbation = _ROUNDING_LAMBDA * (math.sqrt(n) + size) * _EPS * total
    if (keep == 0 or lam[keep - 1] < _SMALLEST_KEPT * perturbation
            or allowance > _ALLOWANCE_SHARE * _room(trunc, lam[keep:], block_energy, added,
                                                    top)
            or not (keeps or _compaction_pays(w, c, keep))):
        return _declined(basis)
    Wk = W[:, :keep] / np.sqrt(lam[:keep])
    G = np.empty((w + c, keep))
    G[:w] = Zq @ Wk[:k]
    G[w:] = _times_left(Zb, Wk[k:])
    # the block stays beside the basis when U = [Q, Y] G L^(-T) can be formed to
    # working accuracy; else the kept terms are written (a compaction)
    # the Gram of U = [Q, Y] G as the Gram B of [Q, Y] predicts it: G^T B G = Wk^T Phi Wk
    predicted = Wk.T @ Phi @ Wk
    predicted = 0.5 * (predicted + predicted.T)
    kept = (_kept_factors(G, predicted, np.block([[H, C], [C.T, S]]), tol=opts.reorth_tol)
            if keeps else None)
    if kept is None and not _compaction_pays(w, c, keep):
        return _declined(basis)
    wasted_flops = 0.0
    gram: np.ndarray | None
    if kept is not None:
        coords, L, gram, orth = kept
        R = amps[:keep, np.newaxis] * L
        # the exact path counts the compaction saved here as wasted (update.py)
        wasted_flops = COMPACT_PER_COLUMN * (w + c) * keep
    else:
        # the new basis drifts from orthonormal by about the rounding of Phi over the
        # smallest kept eigenvalue, below 1/64 by the check above: declining here means
        # the rounding model failed (never observed); a basis that compacts in place is
        # then broken
        if basis.defers_gram:
            # the new basis's Gram as predicted (its actual Gram, with the compaction's
            # rounding, is measured with the next block): U = Q' until then, of this
            # orthogonality; written once checked
            gram, drift = None, _drift(predicted)
        else:
            gram = basis.compact_with_block(G)
            assert gram is not None
            drift = _drift(gram)
        if drift > _MAX_DRIFT:
            return _declined(basis)
        if gram is None:
            basis.compact_with_block(G)
            coords, R, orth = np.eye(keep), np.diag(amps[:keep]), drift
        else:
            L = np.linalg.cholesky(gram)
            coords = dtrtri(L, lower=1)[0].T  # L^{-T}
            R = amps[:keep, np.newaxis] * L
            orth = gram_orthogonality(coords, gram)
    rows = None if state.rows is None else plan_rows(state, W[:, :keep], Y_appended)
    discarded = math.ldexp(math.sqrt(float(np.sum(lam[keep:])) + allowance), top)
    bound = prior.step(discarded, 0.0, overlapping=False)
    record = UpdateRecord(
        kind=kind, columns=added, rank=keep, new_directions=c, rejected=0,
        cut=size - keep, discarded=discarded, sweeps=0, max_cosine=0.0,
        orthogonality=orth, error_bound=bound.bound, seconds=time.perf_counter() - t0,
        passes=2 if kept is None else 1,
    )
    writes = Writes(compacted=True, rows=rows) if kept is None else Writes(columns=c, rows=rows)
    return Plan(coords=coords, gram=gram, R=R, m=m, wasted_flops=wasted_flops, bound=bound,
                record=record, writes=writes)
