"""When an update may go through a Gram matrix: the Gram path's conditions and helpers.

The tuning constants of the path, the rounding allowance of ``Phi`` and the checks that
send an update to the exact path (:func:`skips_gram_path`, :func:`_path_applies`,
:func:`_refused_before_block`, :func:`_compaction_pays`, :func:`_room`), the choice to
keep a narrow block beside the basis (:func:`_keeps_block`, :func:`_kept_factors`) and
the products of a block with the basis (:func:`_products`). They serve
:mod:`streamsvd.engine.update_gram`, which plans the update; the method and why it is
safe are on the theory page ``docs/theory/gram-path.md``.
"""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
from scipy.linalg.blas import dnrm2
from scipy.linalg.lapack import dtrtri

from streamsvd._util.scaling import pow2_exponent
from streamsvd.algebra.interface import BasisBackend, DeferredGram
from streamsvd.engine.aside import sets_aside
from streamsvd.engine.state import Plan, State, StepOptions
from streamsvd.engine.truncation import Truncation
from streamsvd.linalg.rejection import default_reject_tol
from streamsvd.linalg.slices import slice_width

__all__ = [
    "GRAM_MEASURES", "_ALLOWANCE_SHARE", "_COMPACTION_RATIO", "_EPS", "_JOINT_MAX_SHARE",
    "_KEEP_MAX_SHARE", "_KEEP_MAX_WIDTH", "_MAX_DRIFT", "_MAX_SPREAD", "_ROUNDING_LAMBDA",
    "_SAFE_HIGH", "_SAFE_LOW", "_SMALLEST_KEPT", "_allowance", "_cancellation_energy",
    "_compaction_pays", "_declined", "_drift", "_keeps_block", "_kept_factors",
    "_path_applies", "_products", "_refused_before_block", "_refused_by_frobenius",
    "_room", "_times", "_times_left", "skips_gram_path",
]

_EPS = float(np.finfo(np.float64).eps)
# a block taken in slices skips the Gram path beside at most this many terms per column
# (skips_gram_path: pyMOR's heat example, updates of 668 columns, 9 to 20 terms at 1e-2 ..
# 1e-4)
_SKIP_GRAM_SHARE = 1 / 32
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


def _refused_before_block(state: State, trunc: Truncation, b: int, n: int,
                          width: int | None = None) -> bool:
    """Whether a target refuses the update whatever the block holds.

    The rounding allowance grows with ``||F||^2 = ||R||^2 + ||X||^2``. With ``mean_l2``
    the growth of the budget (``b (share target)^2``) does not depend on the block: when
    the energy already absorbed alone exceeds the share, the block's ``M`` product and
    Gram are not made. With ``relative`` it is ``(share target)^2 ||X||^2``, and the
    allowance at least ``c ||X||^2`` (``c = _allowance(1, k + b, n)``): when ``c`` alone
    exceeds the share of ``(share target)^2`` the block is refused whatever its energy
    (the check :func:`~streamsvd.engine.update_gram.plan_absorb_by_gram` makes after
    measuring it would refuse it). ``b`` is the number of snapshots appended, ``width``
    the block's columns (``b`` by default; a merge's basis is narrower). An
    ``absolute`` target: :func:`_refused_absolute`.
    """
    if trunc.target is None:
        return False
    if trunc.measure == "absolute":
        return _refused_absolute(state, trunc, (b if width is None else width), n)
    if trunc.measure not in GRAM_MEASURES:
        return False
    if trunc.measure == "relative":
        se = trunc.share * trunc.target
        cols = b if width is None else width
        return _allowance(1.0, state.R.shape[0] + cols, n) > _ALLOWANCE_SHARE * se * se
    if state.R.size == 0:
        return False
    e = pow2_exponent(state.R)
    if abs(e) > _MAX_SPREAD // 2:  # 4^e outside the range: left to the checks that follow
        return False
    old = float(np.linalg.norm(np.ldexp(state.R, -e))) ** 2
    room = _scaled_square(trunc.share * trunc.target, e) * b
    return _allowance(old, state.R.shape[0] + b, n) > _ALLOWANCE_SHARE * room


def _refused_by_frobenius(state: State, trunc: Truncation, X: np.ndarray, inner: Any,
                          n: int) -> bool:
    """Whether a relative target refuses ``X`` on an upper bound of its energy.

    ``||X||_M^2 <= ||M||_2 ||X||_F^2``, with ``||M||_2`` bounded by the inner product's
    ``norm_bound`` (:class:`~streamsvd.algebra.inner.MatrixInner`: its largest absolute
    row sum). With a ``relative`` target, :func:`_block_refused` refuses a block when
    ``c (||R||^2 + E) > s (share target)^2 E``, that is, when its energy ``E`` is small
    beside the energy absorbed before: a block refused at an upper bound of ``E`` is
    refused at ``E``, so the block's ``M`` product and Gram, which the check would
    otherwise measure first, are not made (``n b`` flops where they take a sparse
    product and ``n b^2``). False when the bound is unknown or does not refuse.
    """
    bound = getattr(inner, "norm_bound", None)
    if (trunc.target is None or trunc.measure != "relative" or bound is None
            or state.R.size == 0 or X.size == 0):
        return False
    x = np.ravel(X, order="K").astype(np.float64, copy=False)
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        squares = float(x @ x)
    if _SAFE_LOW < squares < _SAFE_HIGH:
        norm = math.sqrt(squares)
    else:  # squares that under- or overflow: LAPACK's scaled norm
        norm = float(dnrm2(x))
    # every sum rounds down by at most N eps of itself (N = n b terms)
    upper = math.sqrt(bound) * norm * (1.0 + x.size * _EPS)
    if not math.isfinite(upper) or upper == 0.0:
        return False
    top = max(math.frexp(upper)[1], pow2_exponent(state.R))
    if abs(top) > _MAX_SPREAD // 2:
        return False
    return _block_refused(state, trunc, math.ldexp(upper, -top) ** 2, X.shape[1], n, top)


def _refused_by_norms(state: State, trunc: Truncation, norms: np.ndarray, n: int) -> bool:
    """Whether a relative or mean-l2 target refuses a block of column norms ``norms``.

    The check :func:`~streamsvd.engine.update_gram.plan_absorb_by_gram` makes once the
    block's Gram is measured, made on its columns' norms (``n b`` flops, where the Gram
    takes ``n b^2``: Burgers, 674 columns, 0.1 s): ``||F||^2 = ||R||^2 + ||X||^2``
    against the growth of the budget.
    """
    live = norms[norms > 0]
    if trunc.target is None or trunc.measure not in GRAM_MEASURES or live.size == 0:
        return False
    e = max(pow2_exponent(live), pow2_exponent(state.R) if state.R.size else -_MAX_SPREAD)
    if abs(e) > _MAX_SPREAD // 2:  # left to the checks on the Gram
        return False
    return _block_refused(state, trunc, float(np.sum(np.ldexp(live, -e) ** 2)), norms.size,
                          n, e)


def _block_refused(state: State, trunc: Truncation, block_energy: float, b: int, n: int,
                   top: int) -> bool:
    """Whether the rounding of ``||F||^2 = ||R||^2 + ||X||^2`` exceeds its share of the room.

    ``block_energy`` is ``||X||^2`` scaled by ``4^-top`` (as :func:`_room` takes it), ``b``
    the block's columns.
    """
    old = float(np.linalg.norm(np.ldexp(state.R, -top))) ** 2 if state.R.size else 0.0
    return (_allowance(old + block_energy, state.R.shape[0] + b, n)
            > _ALLOWANCE_SHARE * _room(trunc, np.zeros(0), block_energy, b, top))


def _refused_absolute(state: State, trunc: Truncation, cols: int, n: int) -> bool:
    """Whether an ``absolute`` target refuses the update whatever the block holds.

    The update's room is the energy it cuts, at most what is left of the squared
    budget, ``(share target)^2 - b^2`` (``b`` the bound before: the bound after a cut
    ``d`` is at least ``sqrt(b^2 + d^2)``), when nothing else cuts (no ``max_rank``,
    ``eps`` or ``rtol``); the allowance is at least that of the energy absorbed before.
    """
    if (trunc.target is None or trunc.max_rank is not None or trunc.eps > 0
            or trunc.rtol is not None or state.R.size == 0):
        return False
    e = pow2_exponent(state.R)
    if abs(e) > _MAX_SPREAD // 2:
        return False
    old = float(np.linalg.norm(np.ldexp(state.R, -e))) ** 2
    room = (_scaled_square(trunc.share * trunc.target, e)
            - _scaled_square(state.bound.bound, e))
    return _allowance(old, state.R.shape[0] + cols, n) > _ALLOWANCE_SHARE * max(room, 0.0)


def _scaled_square(x: float, e: int) -> float:
    """Return ``(x 2^-e)^2``, ``inf`` past the range (a target of 1e200 has no square)."""
    mantissa, exponent = math.frexp(x)
    twice = 2 * (exponent - e)
    return math.inf if twice > 1000 else math.ldexp(mantissa * mantissa, twice)


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
            return _scaled_square(share_eps, top) * added
        return _scaled_square(share_eps, 0) * block_energy
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


def skips_gram_path(state: State, b: int, opts: StepOptions) -> bool:
    """Whether a block of ``b`` columns skips the Gram path for the exact update.

    With a budget to set aside, a block of at least two slices beside a basis narrower
    than one is extended slice by slice (:func:`~streamsvd.linalg.slices.slice_width`):
    about ``n b s + 4 n (w + r) b`` flops (``s`` the slice's width, ``w`` the basis's,
    ``r`` the directions kept), against the ``n (w + b)^2`` of the Gram of the basis and
    the whole block that the Gram path forms, and its eigendecomposition. When the stream
    so far holds at most ``b / 32`` terms, a block keeps few directions and the slices
    cost well under the Gram: such a block goes to the exact update
    (:func:`~streamsvd.engine.update.plan_absorb`) directly. The first block, of which
    nothing is known, and a stream of a higher rank try it first (Burgers with updates of
    674 columns, 24 to 78 terms: the slices took as long or longer than the Gram path,
    their rounding's share of the bound one mode more; the theory page
    ``docs/theory/gram-path.md``).
    """
    return (0 < state.rank <= _SKIP_GRAM_SHARE * b and sets_aside(opts)
            and slice_width(b, state.basis.width) is not None)
