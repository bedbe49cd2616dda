"""Brand's incremental SVD (block version), the baseline of the streaming benchmark.

M. Brand, "Fast low-rank modifications of the thin singular value decomposition",
Linear Algebra Appl. 415 (2006) 20-30. The state is a thin SVD ``A_k ~ U diag(s) V^T``
of the snapshots seen so far (columns of ``A``), truncated to ``rank`` terms. Absorbing a
block ``B`` (``n x b``):

1. block CGS2 against ``U`` ("twice is enough"): ``C = U^T B``, ``B1 = B - U C``,
   ``C2 = U^T B1``, ``Bp = B1 - U C2``, ``C <- C + C2``;
2. Householder QR of the residual, ``Bp = Q R`` (LAPACK ``dgeqrf`` + ``dorgqr`` through
   ``scipy.linalg.qr``; robust when the residual is rank deficient: a zero residual gives
   a zero row of ``R`` and some orthonormal ``Q``);
3. LAPACK SVD (``dgesdd``) of the ``(p + b) x (p + b)`` core
   ``K = [[diag(s), C], [0, R]]``, ``K = Uk diag(sk) Vk^T``;
4. ``U <- [U, Q] Uk[:, :r]``, ``V <- blockdiag(V, I_b) Vk[:, :r]``, ``s <- sk[:r]`` with
   ``r = min(rank, p + b)``: the exact SVD of the current (already truncated) expansion
   plus the block, truncated to ``rank`` terms.

Every truncation happens at the exact SVD of the expansion, so the discarded parts are
mutually orthogonal and ``||A - U diag(s) V^T||_F = sqrt(sum of discarded s_i^2)`` (the
error bound reported), up to rounding.

Cost per block at rank ``p``: ``4 n p b`` (CGS2) ``+ O(n b^2)`` (QR) ``+ O((p + b)^3)``
(core SVD) ``+ 2 n (p + b) p`` (the new ``U``) ``+ 2 m (p + b) p`` (the new ``V``, which
grows with the number ``m`` of snapshots seen; small next to the ``n`` terms for
``m << n``). ``U``, ``V`` and the work arrays live in buffers preallocated at their
largest size (``U`` in two buffers used in turn, ``V`` for ``m_max`` rows), so an update
allocates only the LAPACK outputs and the ``n x b`` residual.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla

_EPS = np.finfo(np.float64).eps


class BrandSVD:
    """Truncated incremental SVD of a stream of column blocks (Brand 2006).

    Parameters
    ----------
    n : int
        Size of one snapshot.
    rank : int
        Number of terms kept after each update.
    max_columns : int
        Largest number of snapshots the stream will bring (size of the ``V`` buffer).
    max_block : int
        Largest block width (size of the work buffers).
    """

    def __init__(self, n: int, *, rank: int, max_columns: int, max_block: int) -> None:
        self.n = int(n)
        self.rank = int(rank)
        self.max_columns = int(max_columns)
        self.max_block = int(max_block)
        w = self.rank + self.max_block
        self._U = [np.empty((self.n, self.rank), order="F"),
                   np.empty((self.n, self.rank), order="F")]
        self._cur = 0
        self._V = [np.empty((self.max_columns, self.rank)),
                   np.empty((self.max_columns, self.rank))]
        self._C = np.empty((self.rank, self.max_block))
        self._C2 = np.empty((self.rank, self.max_block))
        self._K = np.zeros((w, w), order="F")
        self.p = 0
        self.m = 0
        self.s = np.empty(0)
        self.discarded = 0.0
        self.seconds: list[float] = []

    @property
    def U(self) -> np.ndarray:
        """Left singular vectors (``n x p``, a view of the internal buffer)."""
        return self._U[self._cur][:, : self.p]

    @property
    def V(self) -> np.ndarray:
        """Right singular vectors (``m x p``, a view of the internal buffer)."""
        return self._V[self._cur][: self.m, : self.p]

    @property
    def error_bound(self) -> float:
        """``sqrt`` of the discarded energy: ``||A - U diag(s) V^T||_F`` up to rounding."""
        return math.sqrt(self.discarded)

    def absorb(self, B: np.ndarray) -> None:
        """Absorb the columns of ``B`` (``n x b``, ``b <= max_block``)."""
        b = B.shape[1]
        if b > self.max_block or self.m + b > self.max_columns or B.shape[0] != self.n:
            raise ValueError(
                f"`B` must be {self.n} x b with b <= {self.max_block} and at most "
                f"{self.max_columns - self.m} more columns; got {B.shape}."
            )
        p = self.p
        U = self._U[self._cur][:, :p]
        X = np.array(B, dtype=np.float64, order="F")
        C = self._project(U, X)  # 1. block CGS2 against U
        # 2. Householder QR of the residual (overwrites X)
        Q, R = sla.qr(X, mode="economic", overwrite_a=True, check_finite=False)
        Uk, r, Vk = self._core_svd(C, R)  # 3. SVD of the small core
        # 4. rotate and truncate: U <- U Uk[:p, :r] + Q Uk[p:, :r] into the other buffer
        Unew = self._U[1 - self._cur][:, :r]
        if p:
            np.matmul(U, Uk[:p, :r], out=Unew)
            Unew += Q @ Uk[p:, :r]
        else:
            np.matmul(Q, Uk[p:, :r], out=Unew)
        self._finish(Vk, r, b)

    def _project(self, U: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Block CGS2 of ``X`` against ``U`` in place; return the coefficients."""
        p, b = U.shape[1], X.shape[1]
        C = self._C[:p, :b]
        if p:
            np.matmul(U.T, X, out=C)
            X -= U @ C
            C2 = self._C2[:p, :b]
            np.matmul(U.T, X, out=C2)
            X -= U @ C2
            C += C2
        return C

    def _core_svd(self, C: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
        """SVD of ``[[diag(s), C], [0, R]]``; the kept rank and right factor."""
        p, b = C.shape
        w = p + b
        K = self._K[:w, :w]
        K[:] = 0.0
        K[np.arange(p), np.arange(p)] = self.s
        K[:p, p:] = C
        K[p:, p:] = R
        Uk, sk, Vkt = sla.svd(K, full_matrices=False, lapack_driver="gesdd",
                              check_finite=False)
        r = min(self.rank, w)
        self.discarded += float(np.sum(sk[r:] ** 2))
        self._s_next = sk[:r].copy()
        return Uk, r, Vkt[:r].T

    def _finish(self, Vk: np.ndarray, r: int, b: int) -> None:
        """``V <- blockdiag(V, I) Vk`` into the other buffer; switch the buffers."""
        p, m = self.p, self.m
        nxt = 1 - self._cur
        Vold = self._V[self._cur][:m, :p]
        Vnew = self._V[nxt]
        if p:
            np.matmul(Vold, Vk[:p], out=Vnew[:m, :r])
        Vnew[m : m + b, :r] = Vk[p:]
        self._cur = nxt
        self.s = self._s_next
        self.p, self.m = r, m + b


class TunedBrandSVD(BrandSVD):
    """Brand's incremental SVD with the n-sized work at BLAS-3 speed (the tuned baseline).

    Differs from :class:`BrandSVD` in two places only: the residual is orthonormalised by
    shifted CholeskyQR3 (three Gram matrices and triangular solves, all BLAS-3, instead of
    Householder QR; the shift of the first pass makes it succeed on a rank-deficient
    residual, the two plain passes restore orthogonality), and ``U`` lives with the new
    directions in one buffer ``[U, Q]`` so that the rotation ``U <- [U, Q] Uk`` is a
    single gemm.
    """

    def __init__(self, n: int, *, rank: int, max_columns: int, max_block: int) -> None:
        super().__init__(n, rank=rank, max_columns=max_columns, max_block=max_block)
        w = self.rank + self.max_block
        self._W = [np.empty((self.n, w), order="F"), np.empty((self.n, w), order="F")]

    @property
    def U(self) -> np.ndarray:
        """Left singular vectors (``n x p``, a view of the internal buffer)."""
        return self._W[self._cur][:, : self.p]

    def absorb(self, B: np.ndarray) -> None:
        """Absorb the columns of ``B`` (``n x b``, ``b <= max_block``)."""
        b = B.shape[1]
        p = self.p
        W = self._W[self._cur]
        X = W[:, p : p + b]
        X[:] = B
        C = self._project(W[:, :p], X)
        R = np.eye(b)
        for k in range(3):  # shifted CholeskyQR3 (Fukaya et al. 2020): robust, BLAS-3
            G = sla.blas.dsyrk(1.0, X, trans=1)
            G = np.triu(G) + np.triu(G, 1).T
            if k == 0:  # the shift makes the first factorisation succeed on any residual
                G[np.diag_indices(b)] += 11.0 * (self.n * b + b * (b + 1)) * _EPS * np.trace(G)
            L = np.linalg.cholesky(G)
            Y = sla.blas.dtrsm(1.0, L, X, side=1, lower=1, trans_a=1, overwrite_b=1)
            if not np.shares_memory(Y, X):
                X[:] = Y
            R = L.T @ R
        Uk, r, Vk = self._core_svd(C, R)
        np.matmul(W[:, : p + b], Uk[:, :r], out=self._W[1 - self._cur][:, :r])  # one gemm
        self._finish(Vk, r, b)
