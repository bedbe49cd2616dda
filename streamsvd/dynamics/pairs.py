"""The snapshot pairs of a stream and their small triangular factor.

DMD fits ``x_(j+1) ~ A x_j`` over the *pairs* of consecutive snapshots of one trajectory.
In a stream the snapshots are the columns of the expansion ``U V^T`` (``U`` orthonormal
in ``M``), so snapshot ``j`` has the coordinates ``z_j = v_j`` (row ``j`` of ``V``) on
``U``. A pair is two consecutive rows of ``V`` whose snapshots were absorbed one after
the other (no removal between them) and in the same trajectory
(:func:`pair_positions`).

Everything a DMD query needs is the triangular factor ``T`` (``2k x 2k``) of the
``q x 2k`` matrix ``[Zx^T, Zy^T]`` of the ``q`` pairs (``Zx``: the coordinates of the
first snapshot of each pair, ``Zy``: of the second): ``[Zx^T, Zy^T] = Q T`` with ``Q``
orthonormal, so ``Zx = T_x^T Q^T``, ``Zy = T_y^T Q^T`` with ``T = [T_x, T_y]``
(:class:`PairFactor`). It is formed by a Householder QR, not by the Gram matrices
``Zx Zx^T``, whose conditioning is the square of the data's (docs: theory, DMD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PairFactor", "pair_factor", "pair_positions"]


def pair_positions(absorbed: np.ndarray, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the positions ``(first, second)`` of the snapshot pairs among the live ones.

    Parameters
    ----------
    absorbed : ndarray of int, shape (m,)
        The absorption index of each live snapshot, increasing (row ``i`` of ``V`` holds
        the snapshot absorbed ``absorbed[i]``-th).
    starts : ndarray of int
        Absorption indices at which a new trajectory starts.

    Returns
    -------
    first, second : ndarray of int
        Rows ``i`` and ``i + 1`` of ``V`` form a pair when ``absorbed[i + 1] ==
        absorbed[i] + 1`` (nothing removed between them) and ``absorbed[i + 1]`` does not
        start a trajectory.
    """
    absorbed = np.asarray(absorbed, dtype=np.int64)
    if absorbed.size < 2:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    nxt = absorbed[1:]
    ok = (nxt == absorbed[:-1] + 1) & ~np.isin(nxt, np.asarray(starts, dtype=np.int64))
    first = np.flatnonzero(ok)
    return first, first + 1


@dataclass(frozen=True, eq=False)
class PairFactor:
    """The triangular factor of the snapshot pairs, and the last snapshot's coordinates.

    Attributes
    ----------
    T : ndarray, shape (2k, 2k) or (q, 2k) when q < 2k
        Upper triangular (trapezoidal) with ``[Zx^T, Zy^T] = Q T``.
    pairs : int
        Number ``q`` of pairs.
    last : ndarray, shape (k,)
        Coordinates of the last live snapshot (the start of a forecast).
    """

    T: np.ndarray
    pairs: int
    last: np.ndarray

    @property
    def k(self) -> int:
        """Number of coordinates (the rank of the basis)."""
        return int(self.last.shape[0])

    @property
    def Tx(self) -> np.ndarray:
        """``T_x``: ``Zx = T_x^T Q^T``."""
        return self.T[:, : self.k]

    @property
    def Ty(self) -> np.ndarray:
        """``T_y``: ``Zy = T_y^T Q^T``."""
        return self.T[:, self.k:]


def pair_factor(V: np.ndarray, first: np.ndarray, second: np.ndarray) -> PairFactor:
    """Return the :class:`PairFactor` of the pairs ``(V[first], V[second])``.

    Parameters
    ----------
    V : ndarray, shape (m, k)
        The right vectors: row ``j`` holds the coordinates of snapshot ``j`` on ``U``.
    first, second : ndarray of int
        Rows of the pairs (:func:`pair_positions`).

    Notes
    -----
    Costs ``O(q k^2)`` for ``q`` pairs: one Householder QR of ``q x 2k``.
    """
    V = np.asarray(V, dtype=np.float64)
    k = V.shape[1]
    last = V[-1].copy() if V.shape[0] else np.zeros(k)
    if first.size == 0:
        return PairFactor(np.zeros((0, 2 * k)), 0, last)
    X = np.concatenate([V[first], V[second]], axis=1)
    T = np.linalg.qr(X, mode="r")
    return PairFactor(np.asarray(T), int(first.size), last)
