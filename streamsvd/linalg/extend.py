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

from streamsvd._util.scaling import scale_into, scaled_norm, top_exponent
from streamsvd.algebra.blas import apply_into as m_apply_into
from streamsvd.algebra.blas import apply_with_energies, gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisProducts
from streamsvd.linalg.blocks import (
    COND_SPLIT,
    ONE_PASS_COND,
    apply_into,
    cholesky_qr_in_place,
    column_rule,
    complement,
    eigh_desc,
    kept_clean,
    orthonormalize_in_rounds,
    place_directions,
    right_solve,
    set_aside,
)
from streamsvd.linalg.extension import BasisExtension
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
    n, b = X.shape
    w = basis.width
    q = w if G is None else G.shape[1]
    Y, MY = basis.workspace(b)
    exps, zero = scale_into(X, Y, name=name)
    C = np.zeros((q, b))
    passes = 0
    if w:
        C += basis.project(Y, G)
        basis.subtract(Y, G, C)
        passes += 2
    Z = Y
    # with a budget, the directions kept after setting the weakest aside decide first
    # whether what the projection left along the basis is measured (below)
    lazy = bool(w and b and basis_gram is not None and (aside[0] > 0 or aside[1] > 0))
    if not (lazy and sketch is not None):
        MZ = apply_into(Z, MY, inner)
    else:
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
    if w and not lazy:
        cross0, S = basis.residual_products(Z, MZ)
        passes += 1
    else:
        cross0, S = np.zeros((0, b)), gram(Z, inner, MZ)
    split = None
    skewed = False
    budget = 0.0
    Zk = None
    spectrum = None  # eigh_desc(S), once taken (S changes only with a second projection)
    if lazy:
        # the second projection is not made when the directions kept after setting the
        # weakest aside lie along the basis by at most _KEPT_LOSS_MAX (nearly collinear
        # time steps): their part along the basis is measured on them alone (a narrow
        # product), kept in cross_gram; the directions set aside keep theirs, of the
        # order of the projection's rounding (eps ||X||), which the bound does not count
        budget = _aside_budget(_norms(C, S), exps, aside)
        spectrum = eigh_desc(S) if budget > 0 else None
        split = set_aside(S, budget, n, _ROUNDING_LAMBDA, spectrum=spectrum)
        if split is not None:
            Zk = np.empty((n, split[0].shape[1]), order="F")
            np.matmul(Z, split[0], out=Zk)
            skewed = kept_clean(basis.project(Zk, G), split[1], _KEPT_LOSS_MAX)
            passes += 1
        if skewed:
            nu = _norms(C, S)
        else:
            split, Zk = None, None
            cross0 = basis.project(Z, None)
            passes += 1
    if w and not skewed:
        # what the projection left along the basis decides a second projection: not
        # made when it is below _LOSS_MAX of every column's residual
        along = cross0 if G is None else G.T @ cross0
        loss = np.sqrt(np.einsum("ij,ij->j", along, along))
        norms = np.sqrt(np.maximum(np.diag(S), 0.0))
        reproject = bool(np.any(loss > _LOSS_MAX * norms))
        if reproject:
            basis.subtract(Z, G, along)
            C += along
            passes += 1
            if basis_gram is None:
                cross0 = basis.project(Z, None)
                passes += 1
            else:
                cross0 = cross0 - basis_gram @ (along if G is None else G @ along)
            MZ = apply_into(Z, MY, inner)
            S = gram(Z, inner, MZ)
            spectrum = None
    # the columns' M-norms: the part along the (orthonormal) basis and the residual's
    if not skewed:
        nu = _norms(C, S)
    ref = nu if reference is None else np.ldexp(np.asarray(reference, float), -exps)
    if split is None and b:
        budget = _aside_budget(nu, exps, aside)
        if budget > 0 and spectrum is None:
            spectrum = eigh_desc(S)
        split = set_aside(S, budget, n, _ROUNDING_LAMBDA, spectrum=spectrum)
    if not b or split is not None:
        lam = np.zeros(0)
    else:  # the eigenvalues decide between CholeskyQR and the rounds
        lam = np.linalg.eigvalsh(S)[::-1] if spectrum is None else spectrum[0]
    well = split is None and b > 0 and lam[-1] > 0 and lam[-1] >= COND_SPLIT * lam[0]
    floor: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    pre: list[tuple[np.ndarray, np.ndarray]] = []
    apart: list[tuple[np.ndarray, np.ndarray]] = []
    if split is not None:
        # the kept combinations Z W_k go through the rounds (the tail is never formed):
        # on Z itself, whose first round forms only what it resolves, unless Z W_k was
        # formed already (the narrow product above)
        Wk, lam_k, Wt, Gt = split
        pre.append((Wt.T, Gt))
        if Zk is None:
            kept, F0, spec = Z, None, (lam_k, Wk)
        else:
            kept, F0, spec = Zk, Wk.T, (lam_k, np.eye(lam_k.size))
        parts, Rz, floor, more, mparts, apart = orthonormalize_in_rounds(
            basis, G, kept, spec, C, inner, reject_tol, ref, F0=F0,
            aside=budget - float(np.trace(Gt)))
        passes += more
    elif well:
        # the common case: Z = Q_z L^T in place, Rz = L^T triangular
        Rz, cross_z, more = cholesky_qr_in_place(basis, Z, MZ, S, lam, cross0, inner)
        passes += more
        parts, mparts = [Z], []
    else:
        parts, Rz, floor, more, mparts, apart = orthonormalize_in_rounds(
            basis, G, Z, eigh_desc(S) if spectrum is None else spectrum, C, inner,
            reject_tol, ref, aside=budget)
        passes += more
    accepted, Wacc = column_rule(Rz, ref, reject_tol)
    s, r = Rz.shape[0], Wacc.shape[1]
    keep = None if r == s else Wacc
    R_new = Rz if keep is None else Wacc.T @ Rz
    maps, grams = [], []
    if r < s:
        # the rejected part in the directions' coordinates, orthogonal to the kept ones
        maps.append(complement(Wacc, s).T @ Rz)
        grams.append(np.eye(s - r))
    for F, Gt in pre + apart:
        maps.append(F)
        grams.append(Gt)
    for T, MT, F in floor:
        maps.append(F)
        Gt = T.T @ MT
        grams.append(0.5 * (Gt + Gt.T))
    if well:
        cross = cross_z if keep is None else cross_z @ keep
        gram_new = np.eye(r)
        if keep is not None:
            place_directions(Z @ keep, Y, MY, inner, None if inner.is_euclidean else MZ @ keep)
    else:
        # the new directions (Q_z, or Q_z Wacc) written to the front of the workspace,
        # which the residual no longer needs
        Qn = Y[:, :r]
        start = 0
        for i, part in enumerate(parts):
            width = part.shape[1]
            if keep is None:
                Qn[:, start : start + width] = part
            elif i == 0:
                np.matmul(part, keep[:width], out=Qn)
            else:
                Qn += part @ keep[start : start + width]
            start += width
        if inner.is_euclidean:
            pass
        elif keep is None and len(parts) == 1:
            MY[:, :r] = mparts[0]  # the part's image, measured by the rounds
        else:
            m_apply_into(inner, Qn, MY[:, :r])
        gram_new = gram(Y[:, :r], inner, None if inner.is_euclidean else MY[:, :r])
        if r and np.max(np.abs(gram_new - np.eye(r))) > ONE_PASS_COND * r * _EPS:
            # the rounds' directions are orthonormal to a few eps each; one CholeskyQR
            # pass over all of them makes the block orthonormal as a whole
            L = np.linalg.cholesky(gram_new)
            right_solve(Qn, L)
            R_new = L.T @ R_new
            if not inner.is_euclidean:
                m_apply_into(inner, Qn, MY[:, :r])
            gram_new = np.eye(r)
        cross = basis.project(Y[:, :r], None) if w and r else np.zeros((w, r))
        passes += 1 if w and r else 0
    rejected_map = np.vstack(maps) if maps else np.zeros((0, b))
    if zero.any():
        # a zero column carries nothing: its scale 2^0 says nothing of the rounding the
        # mixing of the other (scaled) columns left in its coordinates, which would come
        # back at the size of 1 (Rz, W, and the maps are exact zeros there in exact
        # arithmetic, and the column is represented exactly by zeros)
        C[:, zero] = 0.0
        R_new[:, zero] = 0.0
        rejected_map[:, zero] = 0.0
    return BasisExtension(
        coeffs=np.ldexp(C, exps[np.newaxis, :]),
        R_new=np.ldexp(R_new, exps[np.newaxis, :]),
        accepted=accepted,
        rejected_gram=_block_diagonal(grams),
        rejected_map=rejected_map,
        exponents=exps,
        block_norm=scaled_norm(nu, exps),
        cross_gram=cross,
        gram_new=gram_new,
        passes=passes,
        skewed=skewed,
    )


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
    with np.errstate(over="ignore"):
        budget = math.ldexp(aside[0], -2 * top) + aside[1] * energy
    return budget if math.isfinite(budget) else 0.0
