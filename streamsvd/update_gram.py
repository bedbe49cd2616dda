"""Absorb a block through the Gram matrix of the snapshots, when the cut allows it.

The exact path (:func:`streamsvd.update.plan_absorb`) orthonormalises the block's residual
to working accuracy, which takes several passes when the snapshots are nearly collinear
(time steps), and then cuts most of what it orthonormalised. When the update cuts (a
target error, or a rank cap), the directions far below the cut carry nothing the user
needs, and the update can be the method of snapshots, as pyMOR's HAPOD does:

* the expansion and the block are ``F = [Q, X] Z`` (``Z`` holds ``coords R^T`` and the
  block's scaling); one product ``[M Q, M X]^T X`` gives the Gram ``B`` of ``[Q, X]`` (the
  stored ``H = Q^T M Q`` completes it), and ``Phi = Z^T B Z = F^T M F`` is decomposed,
  ``Phi = W Lambda W^T`` (``O((k + b)^3)``);
* the truncation rule picks the fewest leading terms (the target's streaming share);
  the kept left vectors ``[Q, X] Z W_k Lambda_k^(-1/2)`` are written as the new basis in
  one product (the backend's compaction, which measures their Gram ``H'``), and their
  loss of orthogonality, about ``eps lambda_1 / lambda_k``, is absorbed in the small
  factor ``coords = L^(-T)`` (``H' = L L^T``), so ``U = Q' coords`` is orthonormal to working
  accuracy without another pass; the right factor becomes ``blockdiag(Y, I) W_k``
  (orthonormal) with the core ``R = Lambda_k^(1/2) L``.

Cost: about ``2 n (w + b) b + 2 n (w + b) k`` flops and one ``M X``: two passes over the
basis and the block, whatever the conditioning of the block.

Accuracy, and what the bound counts. What is discarded is ``F W_r W_r^T``, ``W_r`` the
eigenvectors not kept: it is orthogonal to the kept terms on the right, as a cut of the
converged core, so the bound grows by the Pythagorean rule (:mod:`streamsvd.bound`). Its
energy is ``sum(lambda_r)`` up to the rounding of ``Phi``, at most
``4 (sqrt((k + b) n) + (k + b)) eps trace(Phi)`` in the probabilistic rounding model of
Higham and Mary (2019) with ``lambda = 4``; this allowance is added to the discarded
energy, so the bound still holds. The path is taken only when the allowance is below 1%
of the growth of the error budget in this update (the bound then stays within 0.5% of
the exact path's), when the smallest kept eigenvalue is above 64 times the rounding of
``Phi`` (``4 (sqrt(n) + k + b) eps trace(Phi)``, Weyl's bound), and when the kept
vectors' Gram is within 1/4 of the identity. "The growth of the budget" is, for a
``relative`` or ``mean_l2`` target, what this update adds to the squared streaming
budget; for an ``absolute`` target or a rank cap, the energy this update cuts (the
allowance then adds at most 0.5% to the discarded norm). Otherwise the exact path runs:
for updates that cut nothing, for ``eps`` and ``rtol`` alone (they act after the rule's
sweeps, as in the paper's Algorithm 3), for blocks so narrow that writing a new basis
costs more than four times the flops of the exact path's products (the exact path reads
the basis three or four times per block, so at equal flops it is slower: blocks of 10
columns at rank 70 run 20% faster through the Gram), and for ``add`` and ``merge``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from scipy.linalg.lapack import dtrtri

from ._blocks import scale_into
from ._core import Truncation, UpdateRecord
from ._scaling import pow2_exponent
from .basis import BasisBackend
from .update import Plan, State, StepOptions, Writes, gram_orthogonality, plan_rows

__all__ = ["plan_absorb_by_gram"]

_EPS = float(np.finfo(np.float64).eps)
GRAM_MEASURES = ("relative", "mean_l2")
_ALLOWANCE_SHARE = 0.01  # of the growth of the (squared) budget in this update
_ROUNDING_LAMBDA = 4.0  # Higham and Mary's constant of the probabilistic model
_SMALLEST_KEPT = 64.0  # kept eigenvalues above this many times their rounding
_MAX_DRIFT = 0.25  # largest ||H' - I|| of the new basis
_MAX_SPREAD = 900  # largest spread of the block's binary exponents
_COMPACTION_RATIO = 4.0  # largest compaction flops over the exact path's products
# squared column norms within which the block is used unscaled (no product of its
# entries can overflow or lose digits to underflow in the Gram)
_SAFE_LOW, _SAFE_HIGH = 2.0**-600, 2.0**600


def _allowance(energy: float, size: int, n: int) -> float:
    """Return the bound on the rounding of ``trace(Phi) = energy`` (``Phi`` of order ``size``)."""
    return _ROUNDING_LAMBDA * (math.sqrt(size * n) + size) * _EPS * energy


def _drift(H: np.ndarray) -> float:
    """Return ``||H - I||_2``, or its upper bound ``||H - I||_F`` when that is small."""
    E = H - np.eye(H.shape[0])
    frobenius = float(np.linalg.norm(E))
    if frobenius <= _MAX_DRIFT:
        return frobenius
    return float(np.max(np.abs(np.linalg.eigvalsh(E))))


def _refused_before_block(state: State, trunc: Truncation, b: int, n: int) -> bool:
    """Whether a ``mean_l2`` target refuses the update whatever the block holds.

    The rounding allowance grows with ``||F||^2 >= ||R||^2`` while the growth of the
    budget (``b (share target)^2``) does not depend on the block: when the energy already
    absorbed alone exceeds the share, the block's ``M`` product and Gram are not made.
    """
    if trunc.target is None or trunc.measure != "mean_l2" or state.R.size == 0:
        return False
    e = pow2_exponent(state.R)
    if abs(e) > _MAX_SPREAD // 2:  # 4^e outside the range: left to the checks that follow
        return False
    old = float(np.linalg.norm(np.ldexp(state.R, -e))) ** 2
    room = (trunc.share * trunc.target) ** 2 * math.ldexp(float(b), -2 * e)
    return _allowance(old, state.R.shape[0] + b, n) > _ALLOWANCE_SHARE * room


def _declined(basis: BasisBackend) -> None:
    """Drop what the basis staged for this path; None sends the update to the exact path."""
    basis.discard_planned()
    return None


def _compaction_pays(w: int, b: int, keep: int) -> bool:
    """Whether writing ``keep`` columns from ``w + b`` costs at most 4x the exact path.

    The exact path's products cost about ``3 w b + 2 b^2`` per row; a narrow block takes
    it, appending its directions and compacting only when that pays.
    """
    return (w + b) * keep <= _COMPACTION_RATIO * (3 * w * b + 2 * b * b)


def _room(
    trunc: Truncation, cut: np.ndarray, S: np.ndarray, exps: np.ndarray, top: int, b: int
) -> float:
    """Return the energy (scaled by ``4^-top``) the rounding allowance is measured against.

    With a ``relative`` or ``mean_l2`` target: the growth of the squared streaming budget
    in this update (the block's energy, or ``b``, times ``(share target)^2``); otherwise
    the energy this update cuts (``cut``: the eigenvalues not kept).
    """
    if trunc.target is not None and trunc.measure in GRAM_MEASURES:
        share_eps = trunc.share * trunc.target
        if trunc.measure == "mean_l2":
            return share_eps**2 * math.ldexp(float(b), -2 * top)
        block = float(np.sum(np.diag(S) * np.ldexp(1.0, 2 * (exps - top))))
        return share_eps**2 * block
    return float(np.sum(cut))


def plan_absorb_by_gram(
    state: State, X: Any, opts: StepOptions, *, t0: float
) -> Plan | None:
    """Plan the absorption of ``X`` (``n x b``) by its Gram matrix; None when not allowed.

    ``X`` is an array, or a block the basis reads by row chunks
    (:class:`~streamsvd.sources.LazyBlock`, the tall mode), which this path reads once.
    See the module docstring for the method and the conditions; None leaves the state
    and the basis as they were (the caller then plans the exact update).
    """
    trunc = opts.truncation
    if trunc.target is None and trunc.max_rank is None:
        # nothing is cut but by eps and rtol, which act after the rule's sweeps (the
        # paper's Algorithm 3), or nothing at all: every digit is the user's
        return None
    n, b = X.shape
    basis = state.basis
    w = basis.width
    k = state.R.shape[0]
    if not _compaction_pays(w, b, state.rank):
        return None
    if _refused_before_block(state, trunc, b, n):
        return None
    # with a relative or mean-l2 target the block's Gram alone can refuse the update:
    # the projection waits for that check (a backend reading the block in one pass
    # computes both anyway)
    measured_first = trunc.target is not None and trunc.measure in GRAM_MEASURES
    # column-major, as the workspace of the exact path: the same BLAS kernels, so a
    # block scaled by powers of two below gives the same digits, scaled
    Y = np.asfortranarray(X) if isinstance(X, np.ndarray) else X
    exps = np.zeros(b, dtype=np.int64)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        S, C = basis.block_products(Y, project=not measured_first)
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
        if zero.any():
            return _declined(basis)  # an empty or zero column: the exact path counts it
        S, C = basis.block_products(Y, project=not measured_first)
        norms2 = np.diag(S)
    top = max(int(exps.max()), pow2_exponent(state.R) if state.R.size else int(exps.max()))
    if top - int(exps.min()) > _MAX_SPREAD or abs(top) > _MAX_SPREAD:
        return _declined(basis)
    size = k + b
    if measured_first:
        # the budget's growth is known before the projection: with ||F||^2 = ||R||^2 +
        # ||X||^2 (U orthonormal), a target the rounding cannot meet skips it
        energy = (float(np.linalg.norm(np.ldexp(state.R, -top))) ** 2
                  + float(np.sum(norms2 * np.ldexp(1.0, 2 * (exps - top)))))
        if _allowance(energy, size, n) > _ALLOWANCE_SHARE * _room(
                trunc, np.zeros(0), S, exps, top, b):
            return _declined(basis)
    if C is None:
        C = basis.project(Y, None) if w else np.zeros((0, b))
    # F = [Q, Y] Z 2^top with Z = blockdiag(Zq, diag(d)), every entry at most about 1;
    # Phi = Z^T B Z, B = [[H, C], [C^T, S]] the Gram of [Q, Y], formed by blocks
    Zq = np.ldexp(state.coords @ state.R.T, -top)
    d = np.ldexp(1.0, exps - top)
    ZC = (Zq.T @ C) * d
    Phi = np.empty((size, size))
    Phi[:k, :k] = Zq.T @ state.gram @ Zq
    Phi[:k, k:] = ZC
    Phi[k:, :k] = ZC.T
    Phi[k:, k:] = (d[:, np.newaxis] * S) * d
    lam, W = np.linalg.eigh(0.5 * (Phi + Phi.T))
    lam, W = np.maximum(lam[::-1], 0.0), W[:, ::-1]
    total = float(np.sum(lam))
    if total <= 0.0:
        return _declined(basis)
    allowance = _allowance(total, size, n)
    amps = np.ldexp(np.sqrt(lam), top)
    spent = math.hypot(state.bound.bound, math.ldexp(math.sqrt(allowance), top))
    m = state.m + b
    keep = trunc.keep_count(amps, spent=spent, m=m)
    # Weyl: every eigenvalue of the computed Phi is within ||E||_F of the exact one
    perturbation = _ROUNDING_LAMBDA * (math.sqrt(n) + size) * _EPS * total
    if (keep == 0 or lam[keep - 1] < _SMALLEST_KEPT * perturbation
            or allowance > _ALLOWANCE_SHARE * _room(trunc, lam[keep:], S, exps, top, b)
            or not _compaction_pays(w, b, keep)):
        return _declined(basis)
    Wk = W[:, :keep] / np.sqrt(lam[:keep])
    G = np.empty((w + b, keep))
    G[:w] = Zq @ Wk[:k]
    G[w:] = d[:, np.newaxis] * Wk[k:]
    H = basis.compact_with_block(G)
    if _drift(H) > _MAX_DRIFT:
        return _declined(basis)
    L = np.linalg.cholesky(H)
    coords = dtrtri(L, lower=1)[0].T  # L^{-T}
    R = amps[:keep, np.newaxis] * L
    rows = None if state.rows is None else plan_rows(state, W[:, :keep], None)
    discarded = math.ldexp(math.sqrt(float(np.sum(lam[keep:])) + allowance), top)
    bound = state.bound.step(discarded, 0.0, overlapping=False)
    orth = gram_orthogonality(coords, H)
    record = UpdateRecord(
        kind="absorb", columns=b, rank=keep, new_directions=b, rejected=0,
        cut=size - keep, discarded=discarded, sweeps=0, max_cosine=0.0,
        orthogonality=orth, error_bound=bound.bound, seconds=time.perf_counter() - t0,
        passes=2,
    )
    return Plan(coords=coords, gram=H, R=R, m=m, wasted_flops=0.0, bound=bound, record=record,
                writes=Writes(compacted=True, rows=rows))
