"""Extend a basis by a wide block in slices: each slice's Gram, not the whole block's.

:func:`~streamsvd.linalg.extend.extend_basis` measures the residual's Gram of the whole
block (``n b^2`` flops) and, for a block far from the basis (the first block of a
stream), orthonormalises its nearly collinear columns in rounds, each with the Gram of
what the round before left. A block of ``b`` columns taken in slices of ``s`` costs about
``n b s`` instead: :func:`extend_in_slices` extends the basis by each slice in turn with
:func:`~streamsvd.linalg.extend.extend_basis`, the directions the slices before found
standing beside the basis (:class:`_Beside`, so that its projections, their second pass
and the rounds' re-projections cover them), each slice with its share of the budget that
may be set aside. Then it decomposes the whole block once on the basis and on the
directions found, a slice at a time (the block is never held whole; the basis's
workspace receives the new directions alone): what is left is the rejected part,
orthogonal to every kept direction and measured on the vectors, column by column
(``BasisExtension.column_energies``), so that its norm is exact whatever the slices set
aside. A compressor with a target (a
budget to set aside) takes blocks of at least two slices this way while its basis is
narrower than a slice (:func:`slice_width`).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

from streamsvd._util.scaling import block_exponents, scale_by
from streamsvd.algebra.blas import gram, subtract_product
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisProducts
from streamsvd.linalg.blocks import ONE_PASS_COND, apply_into, place_directions, right_solve
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.extension import BasisExtension
from streamsvd.linalg.sketch import Sketch

__all__ = ["SLICE", "extend_block", "extend_in_slices", "slice_width"]

# the width of a slice (pyMOR's heat example, updates of 668 snapshots at 1e-4 .. 1e-6:
# 64 and 96 alike, 128 and 192 5 to 15% slower)
SLICE = 96


def slice_width(b: int, w: int) -> int | None:
    """Return the width of the slices a block of ``b`` columns is taken in, or None (whole).

    A block of at least two slices is sliced while the basis (``w`` columns) is narrower
    than a slice: past that, a slice's projections on the basis cost more than the Gram
    it saves (Burgers, a basis of 100 to 180 terms: 1.39 s sliced against 1.39 s whole
    at mean_l2 1e-5, 2.23 s against 1.89 s at relative 1e-6 in float32; heat, a basis of
    20 to 40: 0.55 s against 0.95 s).
    """
    return SLICE if b >= 2 * SLICE and w < SLICE else None


def extend_block(
    basis: BasisProducts,
    G: np.ndarray | None,
    X: np.ndarray,
    *,
    inner: InnerProduct,
    reject_tol: float,
    basis_gram: np.ndarray | None,
    aside: tuple[float, float],
    sketch: Sketch | None = None,
    name: str | None = None,
) -> BasisExtension:
    """Extend the basis by a block of snapshots: whole, or in slices when it pays.

    The parameters are :func:`~streamsvd.linalg.extend.extend_basis`'s. A block is taken
    in slices (:func:`extend_in_slices`) when something may be set aside (``aside``) and
    :func:`slice_width` says so; ``sketch`` serves a whole block.
    """
    width = slice_width(X.shape[1], basis.width) if aside != (0.0, 0.0) else None
    if width is None:
        return extend_basis(basis, G, X, inner=inner, reject_tol=reject_tol,
                            basis_gram=basis_gram, aside=aside, sketch=sketch, name=name)
    return extend_in_slices(basis, G, X, inner=inner, reject_tol=reject_tol,
                            basis_gram=basis_gram, aside=aside, width=width, name=name)


class _Beside:
    """The basis ``Q`` with orthonormal directions ``P`` beside it: ``[Q, P]``.

    ``P`` is ``M``-orthogonal to ``Q``; the coordinates ``G`` of the basis ``[Q, P] G``
    are ``blockdiag(G_Q, I)`` (:func:`_coordinates`). The workspace is the slices' own
    ``(Y, MY)``: a basis may make a new one at every call (the panels do), and the
    block's new directions go to the basis's own workspace once, at the end.
    """

    def __init__(self, basis: BasisProducts, P: np.ndarray, MP: np.ndarray,
                 Y: np.ndarray, MY: np.ndarray) -> None:
        self.basis, self.P, self.MP, self.Y, self.MY = basis, P, MP, Y, MY

    @property
    def width(self) -> int:
        return self.basis.width + self.P.shape[1]

    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        K = np.vstack([self.basis.project(X, None), self.MP.T @ X])
        return K if G is None else G.T @ K

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        K = C if G is None else G @ C
        w = self.basis.width
        self.basis.subtract(X, None, K[:w])
        subtract_product(X, self.P, K[w:])

    def residual_products(self, Z: np.ndarray, MZ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cross, S = self.basis.residual_products(Z, MZ)
        return np.vstack([cross, self.MP.T @ Z]), S

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        return self.Y[:, :b], self.MY[:, :b]


class _Directions:
    """The directions the slices found and their images, in buffers that double when full.

    ``P`` and ``MP`` are column-major views of the first columns (``MP`` is ``P`` with
    the Euclidean product); appending copies only the new columns, where stacking copied
    every column found before at each slice.
    """

    def __init__(self, n: int, capacity: int, euclidean: bool) -> None:
        self._euclidean = euclidean
        self._P = np.empty((n, capacity), order="F")
        self._MP = self._P if euclidean else np.empty((n, capacity), order="F")
        self._r = 0

    @property
    def P(self) -> np.ndarray:
        return self._P[:, :self._r]

    @property
    def MP(self) -> np.ndarray:
        return self._MP[:, :self._r]

    def append(self, Q: np.ndarray, MQ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Append the directions ``Q`` (images ``MQ``); return the new ``(P, MP)``."""
        r, k = self._r, Q.shape[1]
        if r + k > self._P.shape[1]:
            size = max(2 * self._P.shape[1], r + k)
            self._P = _widened(self._P, r, size)
            self._MP = self._P if self._euclidean else _widened(self._MP, r, size)
        self._P[:, r:r + k] = Q
        if not self._euclidean:
            self._MP[:, r:r + k] = MQ
        self._r = r + k
        return self.P, self.MP


def _widened(A: np.ndarray, used: int, size: int) -> np.ndarray:
    """Return a column-major buffer of ``size`` columns holding ``A``'s first ``used``."""
    out = np.empty((A.shape[0], size), order="F")
    out[:, :used] = A[:, :used]
    return out


def _coordinates(G: np.ndarray | None, r: int) -> np.ndarray | None:
    """Return the coordinates of the basis ``[Q, P]`` (``P`` of ``r`` columns) from ``Q``'s."""
    return None if G is None else scipy.linalg.block_diag(G, np.eye(r))


def extend_in_slices(
    basis: BasisProducts,
    G: np.ndarray | None,
    X: np.ndarray,
    *,
    inner: InnerProduct,
    reject_tol: float,
    basis_gram: np.ndarray | None,
    aside: tuple[float, float],
    width: int,
    name: str | None = None,
) -> BasisExtension:
    """Decompose a wide block on the basis ``Q G`` and on new directions found by slices.

    Returns the :class:`~streamsvd.linalg.extension.BasisExtension` of the whole block,
    ``X = Q G coeffs + Q_new R_new + Res``: ``Q_new`` orthonormal and orthogonal to the
    basis, ``coeffs`` and ``R_new`` the block's projections on the basis and on
    ``Q_new``, ``Res`` what is left, known by its columns' energies, measured.

    Parameters
    ----------
    basis, G, inner, reject_tol, basis_gram, name
        As for :func:`~streamsvd.linalg.extend.extend_basis`.
    X : ndarray, shape (n, b)
    aside : (float, float)
        The whole block's ``(e0, e1)``; a slice of ``b_i`` columns gets ``(e0 b_i / b, e1)``.
    width : int
        The slices' width.
    """
    n, b = X.shape
    Y = np.empty((n, width), order="F")
    MY = Y if inner.is_euclidean else np.empty((n, width), order="F")
    exps, zero = block_exponents(X, name=name)
    found = _Directions(n, width, inner.is_euclidean)
    P, MP = found.P, found.MP
    accepted: list[np.ndarray] = []
    passes = 0
    for start in range(0, b, width):
        part = X[:, start:start + width]  # unscaled: the budget is in X's units
        r = P.shape[1]
        beside = _Beside(basis, P, MP, Y, MY)
        gram_beside = None if basis_gram is None else scipy.linalg.block_diag(
            basis_gram, np.eye(r))
        if gram_beside is not None and basis.width and r:
            cross = basis.project(P, None)
            gram_beside[:basis.width, basis.width:] = cross
            gram_beside[basis.width:, :basis.width] = cross.T
        G_beside = _coordinates(G, r)
        ext = extend_basis(beside, G_beside, part, inner=inner, reject_tol=reject_tol,
                           basis_gram=gram_beside, aside=(aside[0] * part.shape[1] / b,
                                                          aside[1]))
        accepted.append(ext.accepted)
        passes += ext.passes
        if ext.rank:
            Qi = np.array(Y[:, :ext.rank], order="F")
            Qi, MQi, more = _orthonormal_beside(beside, G_beside, Qi, inner)
            passes += more
            P, MP = found.append(Qi, MQi)
    r = P.shape[1]
    # the whole block on the basis, then on the new directions, a slice at a time in the
    # slices' workspace: what is left is rejected, measured (the basis's workspace holds
    # the new directions alone, not the block)
    w = basis.width
    C = np.zeros((w if G is None else G.shape[1], b))
    R_new = np.zeros((r, b))
    energies = np.zeros(b)
    passes += 2 if w else 0  # the block's projection on the basis and its subtraction
    for start in range(0, b, width):
        cols = slice(start, min(start + width, b))
        Z = Y[:, :cols.stop - start]
        scale_by(X[:, cols], exps[cols], Z)
        if w:
            C[:, cols] = basis.project(Z, G)
            basis.subtract(Z, G, C[:, cols])
        R_new[:, cols] = MP.T @ Z
        subtract_product(Z, P, R_new[:, cols])
        MZ = apply_into(Z, MY[:, :Z.shape[1]], inner)
        energies[cols] = np.maximum(np.einsum("ij,ij->j", Z, MZ), 0.0)
    nu = np.sqrt(np.einsum("ij,ij->j", C, C) + np.einsum("ij,ij->j", R_new, R_new)
                 + energies)
    place_directions(P, *basis.workspace(r), inner, MP)
    cross = basis.project(P, None) if w and r else np.zeros((w, r))
    passes += 1 if w and r else 0
    return BasisExtension.from_scaled(
        C, R_new, exponents=exps, zero=zero, nu=nu, accepted=np.concatenate(accepted),
        cross_gram=cross, gram_new=np.eye(r), passes=passes, column_energies=energies)


def _orthonormal_beside(
    basis: BasisProducts, G: np.ndarray | None, Q: np.ndarray, inner: InnerProduct,
) -> tuple[np.ndarray, np.ndarray, int]:
    """Make a slice's directions ``Q`` orthogonal to the basis ``[Q_b, P] G`` and orthonormal.

    :func:`~streamsvd.linalg.extend.extend_basis` leaves them along the basis by what a
    single projection leaves (up to ``2^-10`` of their norm, measured): they are
    projected twice more, then CholeskyQR, twice when the first Gram's condition exceeds
    ``ONE_PASS_COND`` (CholeskyQR2). Returns ``Q``, ``M Q`` and the passes made.
    """
    passes = 0
    if basis.width:
        for _ in range(2):
            basis.subtract(Q, G, basis.project(Q, G))
            passes += 2
    for _ in range(2):
        MQ = Q if inner.is_euclidean else np.asfortranarray(inner.apply(Q))
        H = gram(Q, inner, None if inner.is_euclidean else MQ)
        right_solve(Q, np.linalg.cholesky(H))
        lam = np.linalg.eigvalsh(H)
        if lam[-1] <= ONE_PASS_COND * lam[0]:
            break
    MQ = Q if inner.is_euclidean else np.asfortranarray(inner.apply(Q))
    return Q, MQ, passes
