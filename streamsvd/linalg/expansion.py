"""The low-rank expansion ``A = U V^T = sum_i u_i v_i^T`` of eq. (1)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from streamsvd._util.scaling import safe_column_norms
from streamsvd._util.validation import as_float_array
from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.errors import ShapeMismatchError

__all__ = ["Expansion"]


@dataclass(frozen=True, eq=False)
class Expansion:
    """A rank-``p`` expansion ``A = U V^T`` (eq. 1) of an ``n x m`` snapshot matrix.

    Columns of ``A`` are snapshots. ``U`` (``n x p``) is meant to be orthonormal in the
    inner product ``inner`` (``U^T M U = I``), as produced by
    :func:`streamsvd.orthonormalize`; ``V`` (``m x p``) carries the amplitudes, so that
    ``||v_i|| -> sigma_i`` once ``V^T V`` is diagonal (eq. 15). The arrays are stored
    read-only.

    Parameters
    ----------
    U : array_like, shape (n, p)
        Left vectors (the basis).
    V : array_like, shape (m, p)
        Right vectors (coordinates of the snapshots, scaled by the amplitudes).
    inner : None, array_like, sparse matrix or InnerProduct
        The inner product in which ``U`` is orthonormal; Euclidean by default.
    """

    U: np.ndarray
    V: np.ndarray
    inner: InnerProduct = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        U = as_float_array(self.U, "U", ndim=2)
        V = as_float_array(self.V, "V", ndim=2)
        if U.shape[1] != V.shape[1]:
            raise ShapeMismatchError(
                f"`U` and `V` must have the same number of columns (the rank p); got "
                f"U {U.shape} and V {V.shape}."
            )
        U = U.view()
        V = V.view()
        U.setflags(write=False)
        V.setflags(write=False)
        object.__setattr__(self, "U", U)
        object.__setattr__(self, "V", V)
        object.__setattr__(self, "inner", as_inner(self.inner, U.shape[0]))

    @property
    def n(self) -> int:
        """Size of one snapshot (rows of ``A``)."""
        return int(self.U.shape[0])

    @property
    def m(self) -> int:
        """Number of snapshots (columns of ``A``)."""
        return int(self.V.shape[0])

    @property
    def rank(self) -> int:
        """Number of terms ``p`` of the expansion."""
        return int(self.U.shape[1])

    @cached_property
    def amplitudes(self) -> np.ndarray:
        """The norms ``||v_i||`` (the singular values once ``V^T V`` is diagonal)."""
        return safe_column_norms(self.V)

    def to_dense(self) -> np.ndarray:
        """Return the ``n x m`` matrix ``U V^T``."""
        return self.U @ self.V.T

    def orthogonality_error(self) -> float:
        """Return ``||U^T M U - I||_2``, the loss of orthonormality of the basis."""
        if self.rank == 0:
            return 0.0
        G = self.inner.gram(self.U, self.U)
        return float(np.linalg.norm(G - np.eye(self.rank), 2))

    def coupling(self) -> float:
        """Return ``max_{i != j} |v_i^T v_j| / (||v_i|| ||v_j||)``, zero at the SVD (eq. 15)."""
        if self.rank < 2:
            return 0.0
        amps = self.amplitudes
        nz = amps > 0
        Vn = self.V[:, nz] / amps[nz]
        C = np.abs(Vn.T @ Vn)
        np.fill_diagonal(C, 0.0)
        return float(C.max()) if C.size else 0.0

    def truncate(self, rank: int) -> Expansion:
        """Return the expansion made of the first ``rank`` terms."""
        return Expansion(self.U[:, :rank], self.V[:, :rank], inner=self.inner)

    def __repr__(self) -> str:
        return f"Expansion(n={self.n}, m={self.m}, rank={self.rank}, inner={self.inner!r})"

    @classmethod
    def canonical(cls, A: Any) -> Expansion:
        """Return the canonical expansion ``U = I_n, V = A^T`` of a matrix (section 2)."""
        A = as_float_array(A, "A", ndim=2)
        return cls(np.eye(A.shape[0]), A.T.copy())
