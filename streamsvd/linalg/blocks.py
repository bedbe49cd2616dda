"""The BLAS-3 kernels of block Gram-Schmidt (:func:`streamsvd.linalg.extend.extend_basis`).

``M``-products (the Gram matrices and ``M``-norms come
from :mod:`streamsvd.algebra.blas`), CholeskyQR in place,
the rounds that orthonormalise a nearly collinear residual (SVQB with re-measured
tails), and the column-by-column rejection rule on the residual's small coefficients.
Every function works on arrays; the basis is reached only through
:class:`~streamsvd.algebra.interface.BasisProducts`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg.blas as blas

from streamsvd.algebra.blas import apply_into as m_apply_into
from streamsvd.algebra.blas import gram, m_norms, subtract_product
from streamsvd.algebra.inner import InnerProduct

if TYPE_CHECKING:
    from streamsvd.algebra.interface import BasisProducts

_EPS = np.finfo(np.float64).eps
# Higham and Mary's constant of the probabilistic rounding model
_ROUNDING_LAMBDA = 4.0
# A residual whose Gram has its eigenvalues within COND_SPLIT of the largest is
# orthonormalised in one go (condition number at most 2^20, so that a second CholeskyQR
# pass restores orthogonality to working accuracy); the smaller directions are measured
# again on the vectors themselves and treated in a further round.
COND_SPLIT = 2.0**-40
# one CholeskyQR pass leaves an orthogonality error of about eps * cond(S): below this
# condition of the residual's Gram one pass is enough
ONE_PASS_COND = 16.0
# a projection that leaves less than this share of a column's norm is made again (DGKS)
_REPROJECT = 0.5


def apply_into(Z: np.ndarray, MY: np.ndarray, inner: InnerProduct) -> np.ndarray:
    """``M Z`` written into ``MY`` (``Z`` itself for the Euclidean product)."""
    if inner.is_euclidean:
        return Z
    return m_apply_into(inner, Z, MY)


def place_directions(
    Qn: np.ndarray, Y: np.ndarray, MY: np.ndarray, inner: InnerProduct, MQn: np.ndarray | None
) -> None:
    """Write the new directions (and their ``M`` image) to the front of the workspace."""
    r = Qn.shape[1]
    Y[:, :r] = Qn
    if not inner.is_euclidean:
        if MQn is None:
            m_apply_into(inner, Qn, MY[:, :r])
        else:
            MY[:, :r] = MQn


def eigh_desc(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (decreasing) and eigenvectors of a small symmetric matrix: its spectrum.

    One decomposition serves every decision taken on a Gram (:func:`set_aside`, the
    rounds of :func:`orthonormalize_in_rounds`, the conditioning that picks CholeskyQR).
    """
    if S.shape[0] == 0:
        return np.zeros(0), np.zeros((0, 0))
    lam, W = np.linalg.eigh(S)
    return lam[::-1].copy(), np.asfortranarray(W[:, ::-1])


def _mapped(A: np.ndarray, F: np.ndarray | None) -> np.ndarray:
    """Return ``A F`` (``F`` None: the identity, ``A`` itself)."""
    return A if F is None else A @ F


def _image(Z: np.ndarray, inner: InnerProduct) -> np.ndarray:
    """``M Z``, column-major (``Z`` itself for the Euclidean product)."""
    return Z if inner.is_euclidean else np.asfortranarray(inner.apply(Z))


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Return ``A @ B`` as a new column-major array (for in-place triangular solves)."""
    out = np.empty((A.shape[0], B.shape[1]), order="F")
    np.matmul(A, B, out=out)
    return out


def right_solve(A: np.ndarray, L: np.ndarray) -> np.ndarray:
    """Return ``A L^{-T}``, in place when ``A`` is column-major (``L`` lower triangular)."""
    if A.shape[0] == 0 or A.shape[1] == 0:
        return A
    out = blas.dtrsm(1.0, L, A, side=1, lower=1, trans_a=1, overwrite_b=1)
    if not np.shares_memory(out, A):
        A[...] = out
    return A


def cholesky_qr_in_place(
    basis: BasisProducts,
    Z: np.ndarray,
    MZ: np.ndarray,
    S: np.ndarray,
    lam: np.ndarray,
    cross: np.ndarray,
    inner: InnerProduct,
) -> tuple[np.ndarray, np.ndarray, int]:
    """``Z = Q L^T`` in place (``Z`` becomes ``Q``, ``MZ`` its image).

    ``S = Z^T M Z`` is positive definite with eigenvalues ``lam`` (decreasing) and
    ``cross = (M Q_basis)^T Z``. Returns ``L^T``, the cross block of the result and the
    passes made over the basis. When ``cond(S) > ONE_PASS_COND`` a second pass is made
    (CholeskyQR2): the triangular solve by an ill-conditioned ``L`` errs by about
    ``eps cond(L)`` in every direction, so the cross block is measured again on the
    result of the first pass (one product with the basis) rather than transformed, and
    ``M Z`` applied again. A solve by a well-conditioned factor (``cond(L) <= 4``: one
    pass, or the second) maps the cross block with ``Z``, and the image ``M Z`` when that
    costs less than applying ``M`` again (:func:`_maps_image`), within the same few
    ``eps`` as the product itself (as the rounds map theirs,
    :func:`orthonormalize_in_rounds`).
    """
    L = np.linalg.cholesky(S)
    right_solve(Z, L)
    R = L.T.copy()
    maps = _maps_image(inner, Z.shape[1])
    if lam[0] <= ONE_PASS_COND * lam[-1]:
        if maps:
            right_solve(MZ, L)
        else:
            apply_into(Z, MZ, inner)
        return R, right_solve(np.array(cross, order="F"), L), 0
    L2 = np.linalg.cholesky(gram(Z, inner, apply_into(Z, MZ, inner)))
    measured = basis.project(Z, None) if basis.width else np.zeros((0, Z.shape[1]))
    right_solve(Z, L2)
    if maps:
        right_solve(MZ, L2)
    else:
        apply_into(Z, MZ, inner)
    cross = right_solve(np.array(measured, order="F"), L2)
    return L2.T @ R, cross, 1 if basis.width else 0


def _maps_image(inner: InnerProduct, b: int) -> bool:
    """Whether a triangular solve maps ``M Z`` (``n x b``) for less than ``M`` applied again.

    The solve costs ``n b^2`` flops, the product ``2 n b`` per entry in a row of ``M``
    (``entries_per_row``; an inner product that does not give it is applied again).
    """
    per_row = getattr(inner, "entries_per_row", None)
    return not inner.is_euclidean and per_row is not None and b < 2.0 * per_row


def orthonormalize_in_rounds(
    basis: BasisProducts,
    G: np.ndarray | None,
    Z: np.ndarray,
    spectrum: tuple[np.ndarray, np.ndarray],
    C: np.ndarray,
    inner: InnerProduct,
    reject_tol: float,
    ref: np.ndarray,
    F0: np.ndarray | None = None,
    aside: float = 0.0,
) -> tuple[list[np.ndarray], np.ndarray, list[tuple[np.ndarray, np.ndarray, np.ndarray]], int,
           list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """Orthonormalise an ill-conditioned residual round by round (see :func:`extend_basis`).

    Returns the orthonormal parts, the coefficients ``Rz`` of the residual on them, the
    directions set aside below the floor ``(T, M T, F)``, the passes made, the parts'
    ``M`` images and the directions set aside within ``aside``. ``C`` (the
    coefficients on the basis) receives what the re-projections of later rounds find.
    ``spectrum`` is ``(lam, W)`` of the first round: ``Z^T M Z W = W diag(lam)``, ``lam``
    decreasing, ``W`` (``s x k``) orthonormal columns; the first round resolves
    ``Z W`` alone (``k < s``: the directions :func:`set_aside` kept, never formed as a
    block of their own). ``F0`` (``s x b``), when given, says that ``Z`` holds ``s``
    combinations of the ``b`` columns (``Z = Z_columns F0^T``). ``aside``
    is an energy (in the block's scaled units) the rounds may set aside: the Gram of each
    later round's unresolved part, measured after its re-projection, has the trace of
    that part alone, so its weakest directions are rejected by :func:`set_aside` within
    what is left of ``aside`` even when the first Gram's rounding allowance exceeded it;
    they are returned last, as ``(F, G_t)`` (their map to the columns and their Gram).
    """
    b = C.shape[1]
    parts: list[np.ndarray] = []
    mparts: list[np.ndarray] = []
    rows: list[np.ndarray] = []
    floor: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    apart: list[tuple[np.ndarray, np.ndarray]] = []
    # Fc maps Zc's columns to the block's; None: the identity (the first round's, unless F0)
    Zc, Fc, spec = Z, F0, spectrum
    MZc: np.ndarray | None = None  # M Zc, once measured
    passes = 0
    # a direction t with coefficients f (over the columns) adds |f_k| ||t|| to column k:
    # directions are set aside (smallest first) while, in every column k, what they add
    # up to stays within reject_tol * ref_k / 2, so they cannot change a decision
    weight = np.where(ref > 0, 1.0 / np.where(ref > 0, ref, 1.0), 0.0)
    half_tol = 0.5 * reject_tol
    used = np.zeros(b)  # (what the directions set aside add to column k / ref_k)^2
    while True:
        if parts:
            # the unresolved part is small next to the block: its rounding along the
            # basis and the directions found is projected out, a second time when the
            # first pass cancelled more than half of a column (DGKS)
            before = m_norms(Zc, inner, MZc)
            for _ in range(2):
                if basis.width:
                    P = basis.project(Zc, G)
                    basis.subtract(Zc, G, P)
                    C += _mapped(P, Fc)
                    passes += 2
                for i, (Qp, MQp) in enumerate(zip(parts, mparts, strict=True)):
                    c = MQp.T @ Zc
                    subtract_product(Zc, Qp, c)
                    rows[i] += _mapped(c, Fc)
                MZc = _image(Zc, inner)
                after = m_norms(Zc, inner, MZc)
                if np.all(after >= _REPROJECT * before):
                    break
                before = after
            Sc = gram(Zc, inner, MZc)
            spec = eigh_desc(Sc)
            split = set_aside(Sc, aside, Zc.shape[0], _ROUNDING_LAMBDA, spectrum=spec)
            if split is not None:
                # the unresolved part's Gram has the trace of this part alone: what the
                # first Gram could not set aside under its rounding fits now
                Wk, lam_k, Wt, Gt = split
                apart.append((_mapped(Wt.T, Fc), Gt))
                aside -= float(np.trace(Gt))
                if lam_k.size == 0:
                    break
                Zc, Fc = _mm(Zc, Wk), _mapped(Wk.T, Fc)
                spec = eigh_desc(gram(Zc, inner))
        lam, W = spec
        if lam.size == 0 or lam[0] <= 0.0:
            break
        WF = _mapped(W.T, Fc)  # the directions' coefficients over the block's columns
        sizes = np.sqrt(np.maximum(lam, 0.0)) * np.max(np.abs(WF) * weight, axis=1)
        big = (lam >= COND_SPLIT * lam[0]) & (sizes > half_tol)
        # every round resolves at least its largest direction (the column rule rejects it
        # if it is too small), so the rounds end
        big[0] = True
        if big.any():
            Qb = _mm(Zc, W[:, big] / np.sqrt(lam[big]))
            MQb = _image(Qb, inner)  # M applied once: the solve below maps the image too
            L2 = np.linalg.cholesky(gram(Qb, inner, None if inner.is_euclidean else MQb))
            right_solve(Qb, L2)
            if MQb is not Qb:
                right_solve(MQb, L2)
            parts.append(Qb)
            mparts.append(MQb)
            rows.append(L2.T @ (np.sqrt(lam[big])[:, np.newaxis] * WF[big]))
        rest = ~big
        if not rest.any():
            break
        Tt = _mm(Zc, W[:, rest])
        MTt = _image(Tt, inner)
        Ft = WF[rest]
        norms = np.sqrt(np.maximum(np.einsum("ij,ij->j", Tt, MTt), 0.0))
        adds = (norms[:, np.newaxis] * np.abs(Ft) * weight) ** 2
        order = np.argsort(np.max(adds, axis=1), kind="stable")
        fits = np.max(used + np.cumsum(adds[order], axis=0), axis=1) <= half_tol**2
        cut = int(np.argmin(fits)) if not fits.all() else fits.size
        low = np.zeros(norms.size, dtype=bool)
        low[order[:cut]] = True
        used += adds[low].sum(axis=0)
        if low.any():
            floor.append((Tt[:, low], MTt[:, low], Ft[low]))
        if low.all():
            break
        Zc, MZc, Fc = np.asfortranarray(Tt[:, ~low]), np.asfortranarray(MTt[:, ~low]), Ft[~low]
    Rz = np.vstack(rows) if rows else np.zeros((0, b))
    return parts, Rz, floor, passes, mparts, apart


def column_rule(
    Rz: np.ndarray, ref: np.ndarray, reject_tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Accept columns in order on their small coefficients ``Rz`` (``s x b``).

    Returns the mask of the accepted columns and an orthonormal basis ``Wacc``
    (``s x r``) of their span, column ``j`` the direction column ``j`` brought.
    """
    s, b = Rz.shape
    thresh = reject_tol * ref
    if s == b and b and np.all(ref > 0) and not np.any(np.tril(Rz, -1)):
        d = np.abs(np.diag(Rz))
        if np.all(d > thresh):  # triangular: the residual of column k is |R_kk|
            return np.ones(b, dtype=bool), np.eye(s)
    # each column's smallest coefficients, which together stay within half of its own
    # threshold, are left out of the decision: they cannot change it, and the rounding
    # they carry would otherwise tilt the span of the accepted columns (the kept
    # directions and the rejected part are then taken from Rz itself, in full)
    mags = Rz * Rz
    order = np.argsort(mags, axis=0, kind="stable")
    small = np.cumsum(np.take_along_axis(mags, order, axis=0), axis=0) <= (0.5 * thresh) ** 2
    clean = Rz.copy()
    np.put_along_axis(clean, order, np.where(small, 0.0, np.take_along_axis(Rz, order, 0)), 0)
    accepted = np.zeros(b, dtype=bool)
    B = np.zeros((s, min(s, b)))
    r = 0
    for k in range(b):
        if ref[k] <= 0 or r == s:
            continue
        v = clean[:, k].copy()
        for _ in range(2):
            v -= B[:, :r] @ (B[:, :r].T @ v)
        rho = float(np.linalg.norm(v))
        if rho > thresh[k]:
            B[:, r] = v / rho
            accepted[k] = True
            r += 1
    return accepted, B[:, :r]


def complement(Wacc: np.ndarray, s: int) -> np.ndarray:
    """Return an orthonormal basis of the orthogonal complement of ``Wacc`` in ``R^s``."""
    r = Wacc.shape[1]
    if r == 0:
        return np.eye(s)
    Qf = np.linalg.qr(Wacc, mode="complete")[0]
    return Qf[:, r:]


def set_aside(
    S: np.ndarray, budget: float, n: int, lam_factor: float,
    *, spectrum: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Split a residual's Gram ``S`` (``b x b``) into kept and set-aside directions.

    The residual ``Z`` (``Z^T M Z = S``) is ``Z W_k W_k^T + Z W_t W_t^T`` with ``W`` the
    eigenvectors of ``S``; the tail ``Z W_t`` of smallest eigenvalues is rejected on the
    Gram alone (never formed, never orthonormalised) while its energy stays within
    ``budget`` (those below ``COND_SPLIT`` of the largest would otherwise need rounds of
    their own; the core keeps fewer columns). The energy is counted with the rounding
    of ``S``: a direction ``w`` of the tail carries ``w^T S w + w^T dS w`` with
    ``|dS_ij| <~ lam_factor sqrt(n) eps sqrt(S_ii S_jj)`` (the probabilistic model of
    Higham and Mary), so ``d`` directions carry at most ``sum lam_t + a``, with
    ``a = lam_factor (sqrt(d n) + d) eps trace(S)``: this update's residual energy, not
    the energy absorbed before it.

    Returns ``(W_k, lam_k, W_t, G_t)`` with ``G_t = diag(lam_t) + (a / d) I`` the Gram the
    tail is accounted with (``trace(D W_t G_t W_t^T D) >= sum_j ||z_j' d_j||^2`` for any
    column scaling ``D`` of norm at most one), or None when nothing fits. ``spectrum``:
    :func:`eigh_desc` of ``S``, when the caller has it.
    """
    b = S.shape[0]
    if b == 0 or not budget > 0.0:
        return None
    lam, W = eigh_desc(S) if spectrum is None else spectrum
    lam = np.maximum(lam, 0.0)
    trace = float(np.sum(np.maximum(np.diag(S), 0.0)))
    if not math.isfinite(trace):
        return None
    d = np.arange(1, b + 1, dtype=np.float64)
    tails = np.cumsum(lam[::-1])  # tails[d - 1]: energy of the d smallest
    allow = lam_factor * (np.sqrt(d * n) + d) * _EPS * trace
    fits = np.flatnonzero(tails + allow <= budget)
    if fits.size == 0:
        return None
    t = int(fits[-1]) + 1
    k = b - t
    G_t = np.diag(lam[k:]) + (float(allow[t - 1]) / t) * np.eye(t)
    return W[:, :k], lam[:k], W[:, k:], G_t


def kept_clean(along_kept: np.ndarray, lam_k: np.ndarray, limit: float) -> bool:
    """Whether the kept directions ``Z W_k`` lie along the basis by at most ``limit``.

    ``along_kept`` (``q x k``) is what the kept directions hold along the basis,
    measured (``MQ^T Z W_k``); a kept direction ``Z w_i`` has the norm ``sqrt(lam_i)``.
    The directions set aside (:func:`set_aside`) are discarded whole, so only the kept
    ones decide a second projection (:func:`streamsvd.linalg.extend.extend_basis`).
    """
    if lam_k.size == 0:
        return True
    if lam_k[-1] <= 0.0:
        return False
    A = along_kept
    return bool(np.all(np.sqrt(np.einsum("ij,ij->j", A, A)) <= limit * np.sqrt(lam_k)))


def skew_factor(coords: np.ndarray, gram: np.ndarray, cross: np.ndarray,
                gram_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(L, L^(-T))``, ``L L^T`` the Gram of ``[Q coords, Q_new]``, measured.

    ``gram`` is ``Q^T M Q``, ``cross`` ``(M Q)^T Q_new`` and ``gram_new`` ``Q_new^T M Q_new``:
    ``[Q coords, Q_new] L^(-T)`` is orthonormal, and a core ``K`` on ``[Q coords, Q_new]``
    is ``K L`` on it.
    """
    p = coords.shape[1]
    top = coords.T @ cross
    G = np.empty((p + top.shape[1],) * 2)  # the blocks in place (np.block's checks cost more)
    G[:p, :p] = coords.T @ gram @ coords
    G[:p, p:] = top
    G[p:, :p] = top.T
    G[p:, p:] = gram_new
    L = np.linalg.cholesky(0.5 * (G + G.T))
    return L, blas.dtrsm(1.0, L, np.eye(L.shape[0]), lower=1).T
