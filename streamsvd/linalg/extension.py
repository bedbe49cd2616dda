"""The result of extending a basis by a block: :class:`BasisExtension`.

Made by :func:`~streamsvd.linalg.extend.extend_basis` (and, for a wide block, by
:func:`~streamsvd.linalg.slices.extend_in_slices`), read by the update step
(:mod:`streamsvd.engine.update`): how the block decomposes on the basis and on the new
directions, and the exact norm of what was rejected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from streamsvd._util.scaling import pow2_exponent, scaled_norm, top_exponent
from streamsvd.errors import FloatRangeError

__all__ = ["BasisExtension"]


@dataclass(frozen=True)
class BasisExtension:
    """How a block ``X`` (``n x b``) decomposes on a basis ``Q G`` extended by new directions.

    ``X = Q G coeffs + Q_new R_new + Res``, where ``Q_new`` (``n x r``) sits in the basis
    backend's workspace (accepted by the caller with ``basis.accept(r)``) and ``Res`` is
    the rejected part, ``M``-orthogonal to ``Q_new``: ``Res = T F D`` with
    ``D = diag(2^e)`` the columns' scalings, ``F = rejected_map`` and ``T`` (never
    formed) of Gram ``T^T M T = rejected_gram``.

    Attributes
    ----------
    coeffs : ndarray, shape (q, b)
        Coefficients on the existing basis ``Q G``.
    R_new : ndarray, shape (r, b)
        Coefficients on the new directions.
    accepted : ndarray of bool, shape (b,)
        Whether each column brought a new direction (the rule of :func:`extend_basis`).
    rejected_gram : ndarray, shape (k, k)
    rejected_map : ndarray, shape (k, b)
    exponents : ndarray of int, shape (b,)
        The columns' power-of-two scalings ``e``.
    block_norm : float
        ``||X||_M`` (Frobenius in ``M``) of the block, overflow-safe.
    cross_gram : ndarray, shape (w, r)
        ``(M Q)^T Q_new`` over every stored column: the new block of the basis Gram.
    gram_new : ndarray, shape (r, r)
        ``Q_new^T M Q_new``.
    passes : int
        Products of an ``n``-sized block with the stored basis (projections and
        subtractions): what an update costs.
    skewed : bool
        Whether the residual was projected once, its new directions along the basis by
        at most ``_KEPT_LOSS_MAX`` (measured in ``cross_gram``): the caller truncates in
        the coordinates of the extended basis made orthonormal.
    column_energies : ndarray, shape (b,), or None
        ``||Res e_j||_M^2`` of the scaled columns, when the rejected part is known by its
        columns alone (:func:`~streamsvd.linalg.slices.extend_in_slices`; ``rejected_map``
        and ``rejected_gram`` are then empty): its norm is known for a block of snapshots,
        not for an increment or a merge.
    """

    coeffs: np.ndarray
    R_new: np.ndarray
    accepted: np.ndarray
    rejected_gram: np.ndarray
    rejected_map: np.ndarray
    exponents: np.ndarray
    block_norm: float
    cross_gram: np.ndarray
    gram_new: np.ndarray
    passes: int = 0
    skewed: bool = False
    column_energies: np.ndarray | None = None

    @classmethod
    def empty(cls, q: int, w: int) -> BasisExtension:
        """Return the extension by a block of no column."""
        return cls(
            coeffs=np.zeros((q, 0)), R_new=np.zeros((0, 0)), accepted=np.zeros(0, dtype=bool),
            rejected_gram=np.zeros((0, 0)), rejected_map=np.zeros((0, 0)),
            exponents=np.zeros(0, dtype=np.int64), block_norm=0.0, cross_gram=np.zeros((w, 0)),
            gram_new=np.zeros((0, 0)),
        )

    @classmethod
    def from_scaled(
        cls,
        C: np.ndarray,
        R_new: np.ndarray,
        *,
        exponents: np.ndarray,
        zero: np.ndarray,
        nu: np.ndarray,
        accepted: np.ndarray,
        cross_gram: np.ndarray,
        gram_new: np.ndarray,
        passes: int,
        rejected_map: np.ndarray | None = None,
        rejected_gram: np.ndarray | None = None,
        column_energies: np.ndarray | None = None,
        skewed: bool = False,
    ) -> BasisExtension:
        """Return the extension of a block whose columns were scaled by ``2^-exponents``.

        ``C``, ``R_new``, the columns of ``rejected_map`` and ``column_energies`` are the
        scaled columns'; ``nu`` their ``M``-norms. The columns in ``zero`` carry nothing:
        they are set to exact zeros in those arrays (in place), since their scale ``2^0``
        says nothing of the rounding the mixing of the other (scaled) columns left in
        their coordinates, which would come back at the size of 1 (in exact arithmetic
        they are zeros, and the column is represented exactly by zeros). The scaling is
        then undone on the coefficients; the rejected part stays in the scaled units,
        with ``exponents`` (:meth:`rejected_norm`). Omitted, ``rejected_map`` and
        ``rejected_gram`` are empty (nothing rejected beyond ``column_energies``).
        """
        b = exponents.size
        rejected_map = np.zeros((0, b)) if rejected_map is None else rejected_map
        if zero.any():
            C[:, zero] = 0.0
            R_new[:, zero] = 0.0
            rejected_map[:, zero] = 0.0
            if column_energies is not None:
                column_energies[zero] = 0.0
        # a column whose norm lies beyond the float64 range (finite entries near 1e308)
        # scales back to infinities: _block_norm refuses the update
        with np.errstate(over="ignore"):
            coeffs = np.ldexp(C, exponents[np.newaxis, :])
            R_new = np.ldexp(R_new, exponents[np.newaxis, :])
        return cls(
            coeffs=coeffs,
            R_new=R_new,
            accepted=accepted,
            rejected_gram=np.zeros((0, 0)) if rejected_gram is None else rejected_gram,
            rejected_map=rejected_map,
            exponents=exponents,
            block_norm=_block_norm(nu, exponents),
            cross_gram=cross_gram,
            gram_new=gram_new,
            passes=passes,
            skewed=skewed,
            column_energies=column_energies,
        )

    @property
    def rank(self) -> int:
        """Number of new directions ``r``."""
        return int(self.R_new.shape[0])

    @property
    def rejected(self) -> int:
        """Number of columns that brought no new direction."""
        return int(np.count_nonzero(~self.accepted))

    def rejected_norm(self, V: np.ndarray | None = None) -> float:
        """Return ``||Res V^T||_F`` in the inner product ``M``, exactly and overflow-safe.

        ``V`` (``rows x b``) holds the right vectors of the block's columns (``V_k`` of an
        increment, the core of an expansion); ``None`` stands for distinct columns of
        their own (a block of snapshots), where the norm is ``||Res||_F``.
        """
        if self.column_energies is not None:
            if V is not None:
                raise ValueError("the rejected part is known by its columns' energies "
                                 "alone: its norm against right vectors is not")
            return scaled_norm(np.sqrt(self.column_energies), self.exponents)
        F = self.rejected_map
        if F.size == 0:
            return 0.0
        e = self.exponents
        shift = top_exponent(e, np.any(F != 0, axis=0))
        if shift is None:
            return 0.0
        DF = np.ldexp(F, (e - shift)[np.newaxis, :]).T  # (b, k): D F^T, scaled
        if V is not None:
            ev = pow2_exponent(V)
            DF = np.ldexp(V, -ev) @ DF
            shift += ev
        top = pow2_exponent(DF)
        DF = np.ldexp(DF, -top)
        energy = float(np.sum(self.rejected_gram * (DF.T @ DF)))
        return math.ldexp(math.sqrt(max(energy, 0.0)), shift + top)


def _block_norm(nu: np.ndarray, exponents: np.ndarray) -> float:
    """Return the block's norm, ``sqrt(sum (nu_k 2^e_k)^2)``.

    Raises :class:`~streamsvd.errors.FloatRangeError` when it lies beyond the float64
    range (columns of finite entries near 1e308).
    """
    try:
        return scaled_norm(nu, exponents)
    except OverflowError as exc:
        raise FloatRangeError("the update") from exc
