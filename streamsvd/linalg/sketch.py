"""Set a residual's weakest directions aside from a sketch of its columns, not its Gram.

With a budget to set aside, :func:`~streamsvd.linalg.extend.extend_basis` measures the
Gram ``S = Z^T M Z`` of the block's residual (``n b^2`` flops) and its eigenvalues to
keep the fewest directions whose tail fits the budget; on nearly collinear time steps it
keeps a few of ``b`` (pyMOR's heat example: 5 to 10 of 91). When the caller expects
few (``width``: the directions the update before kept, plus an oversampling),
:func:`extend_by_sketch` finds them from ``s = width`` fixed random combinations of the
columns, ``W = Z Omega`` (Halko, Martinsson and Tropp 2011, the randomized range
finder): ``W`` made ``M``-orthonormal (``Q``, SVQB then one CholeskyQR pass), the
columns' coefficients on it measured (``C = (M Q)^T Z``, ``s b n`` flops) and the
directions of ``Q`` kept from the singular values of ``C`` (Rayleigh-Ritz on the
sketch's span). What is set aside is measured on the columns: column ``j`` keeps
``||R_j||^2`` of its energy ``||z_j||_M^2`` on the kept directions, the rest,
``||z_j||_M^2 - ||R_j||^2``, is rejected (``BasisExtension.column_energies``), with the
allowance ``lambda (sqrt(b n) + b) eps ||Z||_M^2`` for the rounding of the energies and
of the coefficients (the one :func:`~streamsvd.linalg.blocks.set_aside` gives the Gram's
rounding at ``b`` directions). The sketch declines (None: the Gram is measured) when the
tail does not fit with all of ``Q``, or when the kept directions lie along the basis by
more than a single projection leaves.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg.blas import dgemm

from streamsvd.algebra.blas import gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisProducts
from streamsvd.linalg.blocks import (
    COND_SPLIT,
    _image,
    _mm,
    column_rule,
    eigh_desc,
    kept_clean,
    place_directions,
    right_solve,
)
from streamsvd.linalg.extension import BasisExtension

__all__ = ["SKETCH_OVERSAMPLING", "Sketch", "extend_by_sketch", "plan_sketch"]

_EPS = np.finfo(np.float64).eps
# Higham and Mary's constant of the probabilistic rounding model (as set_aside's)
_ROUNDING_LAMBDA = 4.0
# the random combinations beyond the directions the update before kept
SKETCH_OVERSAMPLING = 6
# a sketch is taken when the update before kept at most this share of the block's
# columns: its products (W, its image, C: about 2 s b n flops with s = that count plus the
# oversampling) then cost well under the Gram's 2 b^2 n, and a count that varies more
# from update to update than the oversampling covers (Burgers: 11 to 44 of 101) sends
# fewer sketches back to the Gram
_SKETCH_SHARE = 0.125
_SEED = 20261207  # the test matrices are the same in every process (a resumed stream
# repeats the digits of an uninterrupted one)


@dataclass(frozen=True)
class Sketch:
    """How a block's directions may be found from a sketch (:func:`extend_by_sketch`).

    Attributes
    ----------
    width : int
        The sketch's columns.
    unit : float
        The unit roundoff of the block's source (``2^-24`` for float32 snapshots): its
        rounding, about ``unit^2 ||X||_M^2 / 12`` spread over every direction of the
        block, is a tail that a sketch of a few columns captures less of than the Gram
        does, so a budget within ``unit^2 ||X||_M^2`` is left to the Gram.
    """

    width: int
    unit: float


def plan_sketch(previous_directions: int | None, b: int, unit: float) -> Sketch | None:
    """Return the sketch for a block of ``b`` columns, or None (the Gram).

    ``previous_directions`` is the number of new directions the update before kept (None
    for the first update): when that is at most an eighth of the block, the sketch takes
    as many and :data:`SKETCH_OVERSAMPLING` more. ``unit`` is :attr:`Sketch.unit`.
    """
    if previous_directions is None or previous_directions > _SKETCH_SHARE * b:
        return None
    return Sketch(previous_directions + SKETCH_OVERSAMPLING, unit)


@functools.lru_cache(maxsize=8)
def _test_matrix(b: int, s: int) -> np.ndarray:
    """Return a fixed Gaussian ``b x s`` test matrix (read-only)."""
    omega = np.asfortranarray(np.random.default_rng([_SEED, b, s]).standard_normal((b, s)))
    omega.setflags(write=False)
    return omega


def _orthonormal_range(W: np.ndarray, inner: InnerProduct
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """Return ``(Q, M Q)``, ``Q`` ``M``-orthonormal, spanning the top of ``W``'s range.

    SVQB on the directions within ``COND_SPLIT`` of the largest (``Q_0 = W V
    Lambda^(-1/2)``, orthonormal to about ``eps 2^20``), then one CholeskyQR pass on
    ``Q_0``'s measured Gram (``M`` applied to ``Q_0``, its image then transformed by the
    nearly orthogonal ``L^(-T)``): orthonormal to working accuracy. None when ``W`` is
    zero.
    """
    lam, V = eigh_desc(gram(W, inner, None if inner.is_euclidean else _image(W, inner)))
    if lam.size == 0 or not lam[0] > 0.0:
        return None
    top = lam >= COND_SPLIT * lam[0]
    Q = _mm(W, V[:, top] / np.sqrt(lam[top]))
    MQ = _image(Q, inner)
    L = np.linalg.cholesky(gram(Q, inner, None if inner.is_euclidean else MQ))
    right_solve(Q, L)
    if MQ is not Q:
        right_solve(MQ, L)
    return Q, MQ


def extend_by_sketch(
    basis: BasisProducts,
    G: np.ndarray | None,
    Z: np.ndarray,
    MZ: np.ndarray,
    C: np.ndarray,
    *,
    energies: np.ndarray,
    nu: np.ndarray,
    ref: np.ndarray,
    exps: np.ndarray,
    zero: np.ndarray,
    budget: float,
    reject_tol: float,
    inner: InnerProduct,
    sketch: Sketch,
    passes: int,
    kept_loss: float,
) -> BasisExtension | None:
    """Extend the basis by the block's residual ``Z`` from a sketch; None: the Gram is needed.

    ``Z`` (the block scaled by ``2^-exps`` and projected once on the basis ``Q G``, in the
    basis's workspace, ``MZ`` its image) has the coefficients ``C`` on the basis, the
    energies ``energies`` (``||z_j||_M^2``) and the norms ``nu``; ``ref`` are the norms
    its columns' residuals are compared with (the rejection rule, ``reject_tol``),
    ``budget`` the energy it may set aside (scaled by ``4^-max(exps)``), ``sketch`` the
    sketch's width and the unit roundoff of the block's source, ``passes`` the products
    with the basis made so far and ``kept_loss`` the share of their norm the kept
    directions may hold along the basis (they are measured, as
    :func:`~streamsvd.linalg.extend.extend_basis` measures its own). ``Z`` and the
    workspace are left as they were when it returns None.
    """
    n, b = Z.shape
    trace = float(np.sum(energies))
    allowance = _ROUNDING_LAMBDA * (math.sqrt(b * n) + b) * _EPS * trace
    if not budget > allowance or not 0.0 < trace < math.inf:
        return None  # nothing can be set aside: the Gram's rounds resolve the block
    live = nu > 0
    top = int(np.max(exps[live]))  # the budget's scale (extend_basis's _aside_budget)
    block = float(np.sum((nu * np.ldexp(1.0, exps - top))[live] ** 2))
    if budget <= sketch.unit * sketch.unit * block:
        return None  # the source's own rounding fills the budget
    found = _orthonormal_range(_mm(Z, _test_matrix(b, sketch.width)), inner)
    if found is None:
        return None
    Q, MQ = found
    coeffs = dgemm(1.0, MQ, Z, trans_a=1)  # (M Q)^T Z
    # the Ritz directions of the sketch's span, from the eigenvectors of C C^T: their
    # energies err by eps ||C||^2 <= eps trace, within the allowance, and any
    # orthonormal rotation keeps Q orthonormal, the coefficients being measured after it
    energy, U = eigh_desc(coeffs @ coeffs.T)
    # the tail with the k leading Ritz directions kept: trace - sum of their energies
    tails = trace - np.concatenate([[0.0], np.cumsum(np.maximum(energy, 0.0))])
    fits = np.flatnonzero(tails + allowance <= budget)
    if fits.size == 0:
        return None
    k = int(fits[0])
    Qk, MQk = _mm(Q, U[:, :k]), _mm(MQ, U[:, :k])
    w = basis.width
    along = basis.project(Qk, None) if w else np.zeros((0, k))
    if w and not kept_clean(along if G is None else G.T @ along, np.ones(k), kept_loss):
        return None
    R = U[:, :k].T @ coeffs  # the columns' coefficients on the kept directions
    accepted, Wacc = column_rule(R, ref, reject_tol)
    r = Wacc.shape[1]
    if r < k:
        R, Qk, MQk, along = Wacc.T @ R, _mm(Qk, Wacc), _mm(MQk, Wacc), along @ Wacc
    # what each column leaves off the kept directions is rejected: its energy measured,
    # the allowance shared in proportion to the columns' energies
    rejected = np.maximum(energies - np.einsum("ij,ij->j", R, R), 0.0)
    rejected += allowance * (energies / trace)
    Y, MY = basis.workspace(b)
    place_directions(Qk, Y, MY, inner, None if inner.is_euclidean else MQk)
    gram_new = gram(Y[:, :r], inner, None if inner.is_euclidean else MY[:, :r])
    return BasisExtension.from_scaled(
        C.copy(), R, exponents=exps, zero=zero, nu=nu, accepted=accepted, cross_gram=along,
        gram_new=gram_new, passes=passes + (1 if w else 0), column_energies=rejected,
        skewed=True)
