"""Extend an orthonormal basis by a block: block CGS2 with rejection, one update's step.

:func:`extend_basis` projects a block of columns onto the basis twice (or more, DGKS),
orthonormalises the residual (CholeskyQR, or rounds of SVQB for a nearly collinear one)
and rejects the columns whose residual is negligible
(:mod:`streamsvd.linalg.rejection`); the new directions and their measurements are
returned as a :class:`~streamsvd.linalg.extension.BasisExtension`. The rejection rule is
the one of :mod:`streamsvd.linalg.gram_schmidt`.
"""

from __future__ import annotations

import math

import numpy as np

from streamsvd._util.scaling import scale_into, top_exponent
from streamsvd.algebra.blas import apply_with_energies, gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisProducts
from streamsvd.linalg.blocks import (
    apply_into,
    column_rule,
    complement,
    eigh_desc,
    kept_clean,
    place_directions,
    set_aside,
)
from streamsvd.linalg.extension import BasisExtension
from streamsvd.linalg.residual import (
    ResidualDirections,
    orthonormalize_residual,
    write_directions,
)
from streamsvd.linalg.sketch import Sketch, extend_by_sketch

__all__ = ["extend_basis"]

_EPS = np.finfo(np.float64).eps
# a residual that kept more than this of its component along the basis (relative to its
# own norm) is projected a second time; a smaller one is measured and kept in the basis
# Gram, where the compressor's orthogonality check accounts for it
_LOSS_MAX = 2.0**-26
# after a single projection, the directions a block keeps (its weakest set aside) may lie
# along the basis by this much (relative to their norm): measured in the basis Gram and
# removed in the small factors before the truncation (streamsvd.engine.update)
_KEPT_LOSS_MAX = 2.0**-10
# Higham and Mary's constant of the probabilistic rounding model (as the Gram path's)
_ROUNDING_LAMBDA = 4.0


def extend_basis(
    basis: BasisProducts,
    G: np.ndarray | None,
    X: np.ndarray,
    *,
    inner: InnerProduct,
    reject_tol: float,
    reference: np.ndarray | None = None,
    basis_gram: np.ndarray | None = None,
    aside: tuple[float, float] = (0.0, 0.0),
    sketch: Sketch | None = None,
    name: str | None = None,
) -> BasisExtension:
    """Decompose a block on the basis ``Q G`` and orthonormalise its residual, BLAS-3.

    The columns are first scaled by exact powers of two (entries from the subnormal range
    to 1e308 neither overflow nor underflow). Then:

    1. **One projection** on the basis, ``Z = Y - Q G (G^T Q^T M Y)``, and one product
       ``(M Q)^T Z`` over every stored column, which measures what the projection left
       along the basis. It is subtracted (a second pass; Giraud et al. 2005: twice is
       enough) only where it exceeds ``_LOSS_MAX`` of a column's residual; otherwise it
       is returned in ``cross_gram``, the new block of the basis Gram, where the compressor's
       orthogonality check (``coords^T gram coords = I``, :mod:`streamsvd.engine.update`) accounts
       for it. With an ``aside`` budget and ``basis_gram`` the second pass is not made
       either when the directions kept after setting the weakest aside (step 2) lie along
       the basis by at most ``_KEPT_LOSS_MAX`` of their norm (nearly collinear time steps:
       the block is mostly along the basis, its residual small), which is measured on
       the kept directions alone (``MQ^T Z W_k``, a narrow product, before the whole
       block's): the directions set aside keep their part along the basis (the
       projection's rounding, of the order of ``eps ||X||``, which the bound leaves
       out), the kept ones keep theirs, measured in ``cross_gram`` (``skewed``), and the
       caller truncates in the coordinates of the extended basis made orthonormal
       (:func:`~streamsvd.linalg.blocks.skew_factor`).
    2. **The residual's Gram** ``S = Z^T M Z`` and its eigenvalues. When they lie within
       ``COND_SPLIT`` of the largest (the common case), ``Z = Q_new L^T`` by CholeskyQR
       in place, twice when ``cond(S) > ONE_PASS_COND`` (CholeskyQR2: orthonormal to
       working accuracy for ``cond(Z) <= 2^20``). Otherwise (nearly collinear snapshots,
       the common case of time steps) the well-conditioned top of the spectrum is
       orthonormalised as ``Z W Lambda^(-1/2)`` and one CholeskyQR pass (SVQB,
       Stathopoulos and Wu 2002), and the rest ``Z W_t`` is measured again on the
       vectors, projected twice on the basis and on the directions found, and treated in
       a further round (each round resolves six more decades of the spectrum). A
       direction too small to bring any column to the rejection threshold (below
       ``reject_tol * ref_k / (2 sqrt(b))`` in every column ``k``) is set aside as
       rejected without a further round.
    3. **The rejection rule, column by column**, on the small coefficients ``Rz`` of the
       residual on its orthonormal directions: in column order, a column is accepted
       when its residual after the directions of the columns accepted before it exceeds
       ``reject_tol * ref_k`` (``ref_k`` its ``M``-norm, or ``reference``), so nothing
       below the threshold is ever normalised. The rejected part is orthogonal to the
       kept directions in those coordinates, and its energy (with that of the directions
       set aside, from the Gram of the measured vectors) is exact.

    Parameters
    ----------
    basis : BasisProducts
        The stored basis; the new directions are left in its workspace.
    G : ndarray, shape (w, q), or None
        The basis is ``Q G`` (``M``-orthonormal); ``None``: the basis is ``Q``.
    X : ndarray, shape (n, b)
        Finite block (checked when ``name`` is given); not modified.
    inner : InnerProduct
    reject_tol : float
        Relative rejection threshold.
    reference : ndarray, shape (b,), optional
        The norm each column's residual is compared with; default the column's own
        ``M``-norm. Columns with a zero reference carry nothing and are rejected.
    basis_gram : ndarray, shape (w, w), optional
        ``Q^T M Q``, when the caller keeps it (saves measuring ``cross_gram`` again after
        a second projection).
    aside : (float, float)
        ``(e0, e1)``: an energy ``e0 + e1 ||X||_M^2`` the caller lets this block discard
        on the residual's Gram alone, before any ``n``-sized orthonormalisation
        (:func:`~streamsvd.linalg.blocks.set_aside`, rounding counted): the directions of
        smallest energy within it are rejected (``rejected_gram``, ``rejected_map``), the
        rest orthonormalised. A compressor with a target error passes a small share of
        the budget's growth in this update; ``(0, 0)`` (the default) sets nothing aside.
        What the residual's Gram cannot set aside (its rounding allowance, relative to
        the residual's energy, exceeds the budget: a first block, or one far from the
        basis) the rounds of step 2 set aside on the Gram of a later round's unresolved
        part, whose trace is that part's energy alone
        (:func:`~streamsvd.linalg.blocks.orthonormalize_in_rounds`).
    sketch : Sketch, optional
        With a budget (``aside``), a sketch that finds the directions to keep without
        the residual's Gram (:func:`~streamsvd.linalg.sketch.extend_by_sketch`; the
        rejected part is then known by its columns' energies); None (the default): the
        Gram.
    name : str, optional
        ``X``'s name in the caller's words: ``X`` is then checked finite from its
        columns' peaks, which the scaling takes anyway (a NaN or infinite entry raises
        :class:`~streamsvd.errors.NonFiniteError` naming it, before any other work).
    """
    b = X.shape[1]
    w = basis.width
    Z, MY = basis.workspace(b)  # the scaled block, then its residual, in place
    exps, zero = scale_into(X, Z, name=name)
    C = np.zeros((w if G is None else G.shape[1], b))
    passes = 0
    if w:
        C += basis.project(Z, G)
        basis.subtract(Z, G, C)
        passes += 2
    # with a budget, the directions kept after setting the weakest aside decide first
    # whether what the projection left along the basis is measured (_split_on_kept)
    lazy = bool(w and b and basis_gram is not None and (aside[0] > 0 or aside[1] > 0))
    if lazy and sketch is not None:
        # the directions to keep found from a sketch of the columns, the rest measured
        # and rejected, without the residual's Gram (streamsvd.linalg.sketch)
        MZ, energies = apply_with_energies(inner, Z, MY)
        energies = np.maximum(energies, 0.0)
        nu = np.sqrt(np.einsum("ij,ij->j", C, C) + energies)
        ext = extend_by_sketch(
            basis, G, Z, MZ, C, energies=energies, nu=nu,
            ref=nu if reference is None else np.ldexp(np.asarray(reference, float), -exps),
            exps=exps, zero=zero, budget=_aside_budget(nu, exps, aside),
            reject_tol=reject_tol, inner=inner, sketch=sketch, passes=passes,
            kept_loss=_KEPT_LOSS_MAX)
        if ext is not None:
            return ext
    else:
        MZ = apply_into(Z, MY, inner)
    if w and not lazy:
        cross, S = basis.residual_products(Z, MZ)
        passes += 1
    else:
        cross, S = np.zeros((0, b)), gram(Z, inner, MZ)
    split = kept = spectrum = None  # spectrum: eigh_desc(S), once taken
    budget = 0.0
    if lazy:
        split, kept, budget, spectrum, more = _split_on_kept(basis, G, Z, C, S, exps, aside)
        passes += more
        if split is None:
            cross = basis.project(Z, None)
            passes += 1
    skewed = split is not None
    if w and not skewed:
        cross, MZ, S, more = _project_again_if_lost(basis, G, Z, MY, MZ, C, cross, S,
                                                    basis_gram, inner)
        passes += more
        spectrum = None if more else spectrum  # S changes only with a second projection
    # the columns' M-norms: the part along the (orthonormal) basis and the residual's
    nu = _norms(C, S)
    ref = nu if reference is None else np.ldexp(np.asarray(reference, float), -exps)
    if split is None and b:
        budget = _aside_budget(nu, exps, aside)
        if budget > 0 and spectrum is None:
            spectrum = eigh_desc(S)
        split = set_aside(S, budget, Z.shape[0], _ROUNDING_LAMBDA, spectrum=spectrum)
    found = orthonormalize_residual(basis, G, Z, MZ, S, cross, C, split=split, kept=kept,
                                   spectrum=spectrum, budget=budget, inner=inner,
                                   reject_tol=reject_tol, ref=ref)
    accepted, R_new, rejected, cross, gram_new, more = _accept_columns(
        basis, found, Z, MY, MZ, ref=ref, reject_tol=reject_tol, inner=inner)
    return BasisExtension.from_scaled(
        C, R_new, exponents=exps, zero=zero, nu=nu, accepted=accepted, cross_gram=cross,
        gram_new=gram_new, passes=passes + found.passes + more,
        rejected_map=np.vstack([F for F, _ in rejected]) if rejected else None,
        rejected_gram=_block_diagonal([Gt for _, Gt in rejected]), skewed=skewed)


def _accept_columns(
    basis: BasisProducts, found: ResidualDirections, Z: np.ndarray, MY: np.ndarray,
    MZ: np.ndarray, *, ref: np.ndarray, reject_tol: float, inner: InnerProduct,
) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]], np.ndarray,
           np.ndarray, int]:
    """Apply the rejection rule (step 3 of :func:`extend_basis`) and place the directions kept.

    Returns whether each column was accepted, the coefficients ``R_new`` on the new
    directions (at the front of the workspace ``Z``, images in ``MY``), the ``(map,
    Gram)`` of every rejected part in order, the cross block ``(M Q)^T Q_new``, the new
    directions' Gram and the passes made over the basis.
    """
    w = basis.width
    accepted, Wacc = column_rule(found.Rz, ref, reject_tol)
    s, r = found.Rz.shape[0], Wacc.shape[1]
    keep = None if r == s else Wacc
    R_new = found.Rz if keep is None else Wacc.T @ found.Rz
    rejected = found.rejected
    if r < s:
        # the rejected part in the directions' coordinates, orthogonal to the kept ones
        rejected = [(complement(Wacc, s).T @ found.Rz, np.eye(s - r)), *rejected]
    if found.cross is not None:  # CholeskyQR: the directions are Z itself, in place
        cross = found.cross if keep is None else found.cross @ keep
        if keep is not None:
            place_directions(Z @ keep, Z, MY, inner, None if inner.is_euclidean else MZ @ keep)
        return accepted, R_new, rejected, cross, np.eye(r), 0
    # the new directions (Q_z, or Q_z Wacc) written to the front of the workspace, which
    # the residual no longer needs
    R_new, gram_new = write_directions(found, keep, R_new, Z, MY, inner)
    if not (w and r):
        return accepted, R_new, rejected, np.zeros((w, r)), gram_new, 0
    return accepted, R_new, rejected, basis.project(Z[:, :r], None), gram_new, 1


def _split_on_kept(
    basis: BasisProducts, G: np.ndarray | None, Z: np.ndarray, C: np.ndarray, S: np.ndarray,
    exps: np.ndarray, aside: tuple[float, float],
) -> tuple[tuple[np.ndarray, ...] | None, np.ndarray | None, float,
           tuple[np.ndarray, np.ndarray] | None, int]:
    """Set the weakest directions aside first, then measure the kept ones along the basis.

    The second projection is not made when the directions kept after setting the weakest
    aside lie along the basis by at most ``_KEPT_LOSS_MAX`` (nearly collinear time
    steps): their part along the basis is measured on them alone (a narrow product) and
    kept in ``cross_gram``; the directions set aside keep theirs, of the order of the
    projection's rounding (``eps ||X||``), which the bound does not count. Returns the
    split and ``Z W_k`` (both None when the kept directions are not clean enough, or
    nothing is set aside), the budget, the spectrum of ``S`` (when taken) and the passes.
    """
    budget = _aside_budget(_norms(C, S), exps, aside)
    spectrum = eigh_desc(S) if budget > 0 else None
    split = set_aside(S, budget, Z.shape[0], _ROUNDING_LAMBDA, spectrum=spectrum)
    if split is None:
        return None, None, budget, spectrum, 0
    kept = np.empty((Z.shape[0], split[0].shape[1]), order="F")
    np.matmul(Z, split[0], out=kept)
    if kept_clean(basis.project(kept, G), split[1], _KEPT_LOSS_MAX):
        return split, kept, budget, spectrum, 1
    return None, None, budget, spectrum, 1


def _project_again_if_lost(
    basis: BasisProducts, G: np.ndarray | None, Z: np.ndarray, MY: np.ndarray,
    MZ: np.ndarray, C: np.ndarray, cross: np.ndarray, S: np.ndarray,
    basis_gram: np.ndarray | None, inner: InnerProduct,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Project the residual a second time when the first left too much along the basis.

    What the projection left along the basis (``cross = (M Q)^T Z``) decides: no second
    projection when it is below ``_LOSS_MAX`` of every column's residual. Otherwise ``Z``
    and ``C`` are updated in place and ``cross``, ``M Z`` and ``S`` measured again.
    Returns them with the passes made (0: nothing changed).
    """
    along = cross if G is None else G.T @ cross
    loss = np.sqrt(np.einsum("ij,ij->j", along, along))
    norms = np.sqrt(np.maximum(np.diag(S), 0.0))
    if not np.any(loss > _LOSS_MAX * norms):
        return cross, MZ, S, 0
    basis.subtract(Z, G, along)
    C += along
    if basis_gram is None:
        cross, passes = basis.project(Z, None), 2
    else:
        cross, passes = cross - basis_gram @ (along if G is None else G @ along), 1
    MZ = apply_into(Z, MY, inner)
    return cross, MZ, gram(Z, inner, MZ), passes


def _block_diagonal(blocks: list[np.ndarray]) -> np.ndarray:
    """Return the block-diagonal matrix of square ``blocks`` (scipy's checks cost more)."""
    out = np.zeros((sum(B.shape[0] for B in blocks),) * 2)
    start = 0
    for B in blocks:
        stop = start + B.shape[0]
        out[start:stop, start:stop] = B
        start = stop
    return out


def _norms(C: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Return the columns' ``M``-norms: their part along the basis and the residual's."""
    return np.sqrt(np.einsum("ij,ij->j", C, C) + np.maximum(np.diag(S), 0.0))


def _aside_budget(nu: np.ndarray, exps: np.ndarray, aside: tuple[float, float]) -> float:
    """Return the energy ``aside`` lets the block set aside, in its scaled units (0: none).

    The columns were scaled by ``2^-e``: an energy ``E`` of the scaled residual is at
    most ``4^max(e) E`` of the block's (the maximum over the nonzero columns: a zero
    column has no residual), so the budget is scaled by ``4^-max(e)``.
    """
    live = nu > 0
    top = top_exponent(exps, live)
    if top is None or not (aside[0] > 0 or aside[1] > 0):
        return 0.0
    energy = float(np.sum(nu[live] ** 2 * np.ldexp(1.0, 2 * (exps[live] - top))))
    try:
        return math.ldexp(aside[0], -2 * top) + aside[1] * energy
    except OverflowError:  # past the range in the block's units (data near 1e-180 and
        return 0.0  # below, a target far above them): nothing is set aside, the safe side
