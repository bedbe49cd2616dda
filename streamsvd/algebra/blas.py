"""Gram matrices and ``M``-norms of a block of columns, the two products every layer shares.

The algebra (:class:`~streamsvd.algebra.memory.MemoryBasis`) and the BLAS-3 passes of
block Gram-Schmidt (:mod:`streamsvd.linalg.blocks`) both measure blocks with them.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import blas

from streamsvd.algebra.inner import InnerProduct, MatrixInner

__all__ = ["apply_into", "apply_with_energies", "gram", "m_norms", "subtract_product"]

# with a diagonal M, blocks at least this wide take the rank-k update (half the flops of
# X^T (M X)); a narrower block's weighted copy would cost about what the update saves
_WEIGHTED_RANK_K = 16


def apply_into(inner: InnerProduct, X: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Write ``M X`` into ``out`` and return it (a sparse ``M`` without a temporary block)."""
    if isinstance(inner, MatrixInner):
        return inner.apply(X, out=out)
    out[...] = inner.apply(X)
    return out


def apply_with_energies(inner: InnerProduct, X: np.ndarray, out: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Return ``M X`` (in ``out``; ``X`` itself for the Euclidean product) and ``x_c^T M x_c``.

    A sparse ``M`` measures the columns' energies within its product
    (:meth:`~streamsvd.algebra.inner.MatrixInner.apply_with_energies`).
    """
    if inner.is_euclidean:
        return X, np.einsum("ij,ij->j", X, X)
    if isinstance(inner, MatrixInner):
        return inner.apply_with_energies(X, out=out)
    MX = apply_into(inner, X, out)
    return MX, np.einsum("ij,ij->j", X, MX)


def subtract_product(X: np.ndarray, A: np.ndarray, K: np.ndarray) -> None:
    """``X -= A K`` in place: one gemm into ``X`` when it is column-major float64.

    Otherwise (another layout or dtype) the product is formed, then subtracted.
    """
    if X.size == 0 or A.shape[1] == 0:
        return
    if X.flags.f_contiguous and X.dtype == np.float64:
        out = blas.dgemm(-1.0, A, K, beta=1.0, c=X, overwrite_c=1)
        if np.shares_memory(out, X):
            return
    X -= A @ K


def m_norms(X: np.ndarray, inner: InnerProduct, MX: np.ndarray | None = None) -> np.ndarray:
    """``M``-norms of the columns of an already scaled block (``MX``: ``M X``, when known)."""
    if MX is None:
        MX = X if inner.is_euclidean else inner.apply(X)
    return np.sqrt(np.maximum(np.einsum("ij,ij->j", X, MX), 0.0))


def gram(X: np.ndarray, inner: InnerProduct, MX: np.ndarray | None = None) -> np.ndarray:
    """``X^T M X`` (symmetric; a rank-k update for the Euclidean product).

    ``MX`` is ``M X`` when the caller has it already.
    """
    if inner.is_euclidean:
        # numpy makes X^T X a rank-k update (syrk) and fills in the lower triangle
        Xf = np.asfortranarray(X)
        G = Xf.T @ Xf
        return 0.5 * (G + G.T)
    diagonal = getattr(inner, "diagonal", None)
    if diagonal is not None and X.shape[1] >= _WEIGHTED_RANK_K:
        # a diagonal M: (W^1/2 X)^T (W^1/2 X), a rank-k update (half of X^T (M X)'s
        # flops); the scaled copy is not made when every weight is the same
        if diagonal.uniform is not None:
            Xf = np.asfortranarray(X)
            G = diagonal.uniform * (Xf.T @ Xf)
        else:
            Xs = np.multiply(X, diagonal.roots, order="F")
            G = Xs.T @ Xs
        return 0.5 * (G + G.T)
    G = X.T @ (inner.apply(X) if MX is None else MX)
    return 0.5 * (G + G.T)
