"""Absorb a block, or merge an expansion, through a Gram matrix, when the cut allows it.

The exact path (:func:`streamsvd.engine.update.plan_absorb`) orthonormalises the block's residual
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
* an in-memory basis (:attr:`~streamsvd.algebra.memory.MemoryBasis.defers_gram`) measures ``H'``
  one update later instead: the state keeps ``coords = I``, ``R = Lambda_k^(1/2)`` and a
  pending Gram (:class:`~streamsvd.engine.state.State`); a next block at most half as wide as
  the basis is copied beside ``Q'`` and the Gram of ``[Q', X]``, ``H'`` with it, is one
  product, the compaction one more (on the synthetic stream of
  ``bench/hapod_benchmark.py``: 14 to 17% less time at blocks of 10, the same digits); a
  wider one is staged as it is and ``H'`` measured alone (:func:`_products`). Whatever
  reads the state
  before measures ``H'`` aside (:meth:`~streamsvd.engine.state.State.settled`), so the digits
  of the stream do not depend on it. The update's recorded orthogonality is then the one
  the Gram of ``[Q, X]`` predicts for ``U = Q'``, ``||W_k^T Phi W_k Lambda_k^(-1) - I||``
  (its Frobenius norm, an upper bound of the 2-norm, when below 1/4; the compaction's
  own rounding is measured with the next block).
* a narrow block is *kept* beside an in-memory basis instead (:func:`_keeps_block`: at
  most a quarter as wide as the ``k`` kept terms, the stored width within ``2 k``):
  copied after the stored columns, its products are one product ``[M Q, M X]^T X``
  (:meth:`~streamsvd.algebra.memory.MemoryBasis.products_beside`), nothing is written, and the
  state becomes ``U = [Q, X] G L^(-T)`` with the Gram ``B`` of ``[Q, X]`` as the stored
  basis's Gram (measured: the block's columns are stored as they are) and ``G^T B G =
  W_k^T Phi W_k Lambda_k^(-1) = L L^T``. Writing ``k`` columns from ``w + b`` costs ``2
  n (w + b) k`` flops where the block's products cost ``2 n (w + b) b``: at blocks of 10
  on 70 terms one update in eight compacts instead of every one, for a third of the
  flops (``bench/README.md``). Kept only while ``U`` can be formed to the exact path's
  ``reorth_tol`` (:func:`_kept_factors`): forming ``U`` from columns that cancel rounds
  by about ``eps sum_i ||q_i|| |coords_ik|``, and ``L`` carries the rounding of ``Phi``,
  about ``eps lambda_1 / lambda_k``, which a compaction's measured Gram would remove;
  the rounding allowance of ``Phi`` is then relative to ``sum_i B_ii ||Z_i||^2`` where
  that exceeds ``trace(Phi)`` (:func:`_cancellation_energy`). The next update that
  compacts (this path's when the width would pass ``2 k``, or the exact path's, which
  counts the compaction's cost as already wasted, ``wasted_flops``) writes the kept
  blocks into the new basis.

Cost: about ``2 n (w + b) b + 2 n (w + b) k`` flops and one ``M X``: two passes over the
basis and the block, whatever the conditioning of the block; one pass, ``2 n (w + b) b``
flops, for a block kept beside the basis.

A merge (:func:`plan_merge_by_gram`) is the same update with the other expansion's basis
``Q_o`` as the block and ``Z_o R_o^T`` as its coefficients (``U_o = Q_o Z_o``, ``V_o = Y_o
R_o``): the Gram of ``[Q, Q_o]`` needs one product over ``Q_o`` (``U_o`` is never formed),
and the appended rows are ``Y_o`` instead of the identity. Where the exact merge
(:func:`streamsvd.engine.update.plan_merge`) orthonormalises ``U_o`` against the basis in up to
seven passes and converges the core by sweeps, this path makes two passes and no sweep
(two leaves of 80 terms, n = 200000: 0.35 s against 1.39 s, the same error, measured by
``bench/merge_benchmark.py``).

Accuracy, and what the bound counts. What is discarded is ``F W_r W_r^T``, ``W_r`` the
eigenvectors not kept: it is orthogonal to the kept terms on the right, as a cut of the
converged core, so the bound grows by the Pythagorean rule (:mod:`streamsvd.engine.bound`). Its
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
sweeps, as in the paper's Algorithm 3), with a ``reject_tol`` above its default ``n eps``
(residuals that weak are then rejected one by one, as asked), for blocks so narrow that
writing a new basis costs more than four times the flops of the exact path's products
(the exact path reads the basis three or four times per block, so at equal flops it is
slower: blocks of 10 columns at rank 70 run 20% faster through the Gram), for an
expansion whose basis is not in memory, and for ``add``.
"""

from __future__ import annotations

import math
import time
from typing import Any, cast

import numpy as np
from scipy.linalg.lapack import dtrtri

from streamsvd._util.scaling import pow2_exponent
from streamsvd.algebra.memory import BasisBackend, DeferredGram
from streamsvd.engine.bound import Bound
from streamsvd.engine.core import Before, Truncation
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.state import Plan, State, StepOptions, Writes, gram_orthogonality
from streamsvd.engine.update import COMPACT_PER_COLUMN, plan_rows
from streamsvd.linalg.blocks import scale_into
from streamsvd.linalg.gram_schmidt import default_reject_tol

__all__ = ["plan_absorb_by_gram", "plan_merge_by_gram"]

_EPS = float(np.finfo(np.float64).eps)
GRAM_MEASURES = ("relative", "mean_l2")
_ALLOWANCE_SHARE = 0.01  # of the growth of the (squared) budget in this update
_ROUNDING_LAMBDA = 4.0  # Higham and Mary's constant of the probabilistic model
_SMALLEST_KEPT = 64.0  # kept eigenvalues above this many times their rounding
_MAX_DRIFT = 0.25  # largest ||H' - I|| of the new basis
_MAX_SPREAD = 900  # largest spread of the block's binary exponents
_COMPACTION_RATIO = 4.0  # largest compaction flops over the exact path's products
_JOINT_MAX_SHARE = 0.5  # widest block, over the basis's width, copied beside a pending one
_KEEP_MAX_SHARE = 4  # a block kept beside the basis is at most 1/4 as wide as the terms
_KEEP_MAX_WIDTH = 2  # and the stored width stays within twice the terms
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


def _path_applies(opts: StepOptions, n: int) -> bool:
    """Whether the options let an update take this path at all.

    Not when nothing is cut but by ``eps`` and ``rtol``, which act after the rule's
    sweeps (the paper's Algorithm 3), or nothing at all (every digit is the user's), and
    not with a ``reject_tol`` above the default ``n eps``: residuals that weak are
    rejected one by one on the exact path, as the user asked, where this path would
    keep a term the rule keeps.
    """
    trunc = opts.truncation
    if trunc.target is None and trunc.max_rank is None:
        return False
    return opts.reject_tol <= default_reject_tol(n)


def _declined(basis: BasisBackend) -> Plan | None:
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
    trunc: Truncation, cut: np.ndarray, block_energy: float, added: int, top: int
) -> float:
    """Return the energy (scaled by ``4^-top``) the rounding allowance is measured against.

    With a ``relative`` or ``mean_l2`` target: the growth of the squared streaming budget
    in this update (the energy appended, ``block_energy``, or the number of snapshots
    appended, ``added``, times ``(share target)^2``); otherwise the energy this update
    cuts (``cut``: the eigenvalues not kept).
    """
    if trunc.target is not None and trunc.measure in GRAM_MEASURES:
        share_eps = trunc.share * trunc.target
        if trunc.measure == "mean_l2":
            return share_eps**2 * math.ldexp(float(added), -2 * top)
        return share_eps**2 * block_energy
    return float(np.sum(cut))


def _keeps_block(w: int, b: int, keep: int) -> bool:
    """Whether an update may store a block of ``b`` columns instead of compacting.

    For a block at most a quarter as wide as the ``keep`` terms, while the stored width
    stays within twice ``keep``: writing ``keep`` columns from ``w + b`` then costs more
    than the wider projections the stored block adds until the next compaction.
    """
    return _KEEP_MAX_SHARE * b <= keep and w + b <= _KEEP_MAX_WIDTH * keep


def _kept_factors(G: np.ndarray, predicted: np.ndarray, B: np.ndarray, *, tol: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Return ``(coords, L, B, orthogonality)`` for a block kept beside the basis, or None.

    ``U = [Q, Y] G`` has the Gram ``G^T B G = Wk^T Phi Wk``, ``predicted`` here
    (symmetric), ``B`` the Gram of ``[Q, Y]`` (measured: the block's columns are stored
    as they are); with ``predicted = L L^T``, ``U = [Q, Y] coords``, ``coords = G
    L^(-T)``. Forming ``U``
    rounds each column ``u_k`` by about ``lambda sqrt(w) eps sum_i ||q_i|| |coords_ik|``
    (``q_i`` the stored columns, ``w`` of them), more than ``eps`` when the columns
    cancel, and ``L`` carries the rounding of ``predicted`` (about ``eps lambda_1 /
    lambda_k``, which a compaction's measured Gram would remove): None when either
    exceeds ``tol`` (``reorth_tol``), so that ``U`` is orthonormal to the tolerance the
    exact path keeps.
    """
    drift = _drift(predicted)
    if drift > tol:
        return None
    L = np.linalg.cholesky(predicted)
    coords = G @ dtrtri(L, lower=1)[0].T  # G L^{-T}
    norms = np.sqrt(np.maximum(np.diag(B), 0.0))
    rounding = (_ROUNDING_LAMBDA * math.sqrt(B.shape[0]) * _EPS
                * float(np.max(norms @ np.abs(coords))))
    orthogonality = drift + 2.0 * rounding
    if orthogonality > tol:
        return None
    return coords, L, B, orthogonality


def _cancellation_energy(H: np.ndarray, S: np.ndarray, Zq: np.ndarray,
                         Zb: np.ndarray) -> float:
    """Return ``sum_i B_ii ||Z_i||^2``, ``B`` the Gram of ``[Q, Y]``, ``Z_i`` the rows of ``Z``.

    The rounding of ``B`` is relative to its diagonal (``|dB_ij| <~ gamma sqrt(B_ii
    B_jj)``), so that of ``Phi = Z^T B Z`` is relative to this sum. It is ``trace(Phi)``
    when ``[Q, Y] Z`` has orthonormal columns ``Q`` and a block of orthogonal columns, and
    larger when ``Z`` combines stored columns that cancel (blocks kept beside the basis).
    """
    zb2 = Zb * Zb if Zb.ndim == 1 else np.sum(Zb * Zb, axis=1)
    return float(np.diag(H) @ np.sum(Zq * Zq, axis=1) + np.diag(S) @ zb2)


def _times(A: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """Return ``A Z``, ``Z`` a matrix or a diagonal given by its entries (1-D)."""
    return A * Z if Z.ndim == 1 else A @ Z


def _times_left(Z: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Return ``Z A``, ``Z`` a matrix or a diagonal given by its entries (1-D)."""
    return Z[:, np.newaxis] * A if Z.ndim == 1 else Z @ A


def plan_absorb_by_gram(
    state: State, X: Any, opts: StepOptions, *, t0: float
) -> Plan | None:
    """Plan the absorption of ``X`` (``n x b``) by its Gram matrix; None when not allowed.

    ``X`` is an array, or a block the basis reads by row chunks
    (:class:`~streamsvd.io.sources.LazyBlock`, the tall mode), which this path reads once.
    See the module docstring for the method and the conditions; None leaves the state
    and the basis as they were (the caller then plans the exact update).
    """
    trunc = opts.truncation
    n, b = X.shape
    if not _path_applies(opts, n):
        return None
    basis = state.basis
    k = state.R.shape[0]
    if not (_compaction_pays(basis.width, b, state.rank)
            or basis.defers_gram and _keeps_block(basis.width, b, state.rank)):
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
        if zero.any():
            return _declined(basis)  # an empty or zero column: the exact path counts it
        S, C, H = _products(state, Y, project=not measured_first)
        norms2 = np.diag(S)
    top = max(int(exps.max()), pow2_exponent(state.R) if state.R.size else int(exps.max()))
    if top - int(exps.min()) > _MAX_SPREAD or abs(top) > _MAX_SPREAD:
        return _declined(basis)
    block_energy = float(np.sum(norms2 * np.ldexp(1.0, 2 * (exps - top))))
    if measured_first:
        # the budget's growth is known before the projection: with ||F||^2 = ||R||^2 +
        # ||X||^2 (U orthonormal), a target the rounding cannot meet skips it
        energy = float(np.linalg.norm(np.ldexp(state.R, -top))) ** 2 + block_energy
        if _allowance(energy, k + b, n) > _ALLOWANCE_SHARE * _room(
                trunc, np.zeros(0), block_energy, b, top):
            return _declined(basis)
    if C is None:
        C = basis.project(Y, None) if basis.width else np.zeros((0, b))
    return _plan_by_gram(
        state, opts, S=S, C=C, H=H, Zb=np.ldexp(1.0, exps - top), top=top,
        block_energy=block_energy, prior=state.bound, Y_appended=None, added=b,
        kind="absorb", t0=t0,
    )


def plan_merge_by_gram(
    state: State,
    Q_o: np.ndarray,
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

    ``Q_o`` is the other expansion's basis (``n x c``, in memory), ``U_o = Q_o Z_o`` its
    left vectors, ``V_o = Y_o R_o`` its right ones (``Y_o`` orthonormal, None when the
    right vectors are not kept); ``prior`` is the composed bound of both parts. As for
    a block (the module docstring) with ``F = [Q, Q_o] blockdiag(coords R^T, Z_o R_o^T)``:
    the Gram of ``[Q, Q_o]`` is one product over ``Q_o`` (``U_o`` is never formed) and the
    kept vectors are written in one more, where the exact path (:func:`streamsvd.engine.update.
    plan_merge`) orthonormalises ``U_o`` against the basis in several passes. The same
    conditions apply; None leaves the state and the basis as they were.
    """
    trunc = opts.truncation
    if not isinstance(Q_o, np.ndarray) or not _path_applies(opts, Q_o.shape[0]):
        return None
    n, c = Q_o.shape
    basis = state.basis
    if c == 0 or R_o.size == 0 or not _compaction_pays(basis.width, c, state.rank):
        return None
    if _refused_before_block(state, trunc, m_o, n):
        return None
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        S, C, H = _products(state, np.asfortranarray(Q_o), project=True)
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


def _products(state: State, Y: Any, *, project: bool
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Stage the block ``Y``; return ``Y^T M Y``, ``MQ^T Y`` and the basis's Gram ``H``.

    A pending Gram (:class:`~streamsvd.engine.state.State`) is measured here: for a block at
    most half as wide as the basis in one product with it
    (:meth:`~streamsvd.algebra.memory.MemoryBasis.joint_products`), which holds the block beside
    the basis in both of its buffers (``2 n b`` more numbers: 32 MB for 10 columns at
    n = 200000); a wider block, where the product gains less (5 to 7% at 100 columns on
    a basis of 70, against 14 to 17% at 10) for more memory (320 MB at n = 200000), is
    staged as it is and the Gram measured alone. Otherwise the Gram is the state's, and
    ``MQ^T Y`` is None unless ``project``.
    """
    basis = cast(DeferredGram, state.basis)
    if state.gram is not None:
        if (basis.defers_gram and isinstance(Y, np.ndarray)
                and _keeps_block(basis.width, Y.shape[1], state.rank)):
            return (*basis.products_beside(Y), state.gram)
        S, C = basis.block_products(Y, project=project)
        return S, C, state.gram
    if Y.shape[1] <= _JOINT_MAX_SHARE * basis.width:
        return basis.joint_products(Y)
    H = basis.measure_gram()
    S, C = basis.block_products(Y, project=project)
    return S, C, H


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
    keeps = (basis.defers_gram and cast(DeferredGram, basis).block_beside
             and _keeps_block(w, c, keep))
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
