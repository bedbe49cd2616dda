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
        """SVD of ``[[diag(s), C], [0, R]]`` (``R`` is ``k x b``, ``k <= b``).

        Returns the left factor (``(p + k) x min``), the kept rank and the right factor
        (``(p + b) x r``).
        """
        p, b = C.shape
        k = R.shape[0]
        K = self._K[: p + k, : p + b]
        K[:] = 0.0
        K[np.arange(p), np.arange(p)] = self.s
        K[:p, p:] = C
        K[p:, p:] = R
        Uk, sk, Vkt = sla.svd(K, full_matrices=False, lapack_driver="gesdd",
                              check_finite=False)
        r = min(self.rank, sk.size)
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
    three Gram passes, all BLAS-3 (:meth:`_orthonormalise`, instead of Householder QR),
    and ``U`` lives with the new directions in one buffer ``[U, Q]`` so that the rotation
    ``U <- [U, Q] Uk`` is a single gemm.
    """

    def __init__(self, n: int, *, rank: int, max_columns: int, max_block: int) -> None:
        super().__init__(n, rank=rank, max_columns=max_columns, max_block=max_block)
        w = self.rank + self.max_block
        self._W = [np.empty((self.n, w), order="F"), np.empty((self.n, w), order="F")]
        self.dropped = 0  # null directions of the residuals dropped so far

    @property
    def U(self) -> np.ndarray:
        """Left singular vectors (``n x p``, a view of the internal buffer)."""
        return self._W[self._cur][:, : self.p]

    def absorb(self, B: np.ndarray) -> None:
        """Absorb the columns of ``B`` (``n x b``, ``b <= max_block``)."""
        b = B.shape[1]
        if b > self.max_block or self.m + b > self.max_columns or B.shape[0] != self.n:
            raise ValueError(
                f"`B` must be {self.n} x b with b <= {self.max_block} and at most "
                f"{self.max_columns - self.m} more columns; got {B.shape}."
            )
        p = self.p
        W = self._W[self._cur]
        X = W[:, p : p + b]
        X[:] = B
        C = self._project(W[:, :p], X)
        R = self._orthonormalise(X)  # the k new directions are now W[:, p : p + k]
        k = R.shape[0]
        Uk, r, Vk = self._core_svd(C, R)
        np.matmul(W[:, : p + k], Uk[:, :r], out=self._W[1 - self._cur][:, :r])  # one gemm
        self._finish(Vk, r, b)

    def _orthonormalise(self, X: np.ndarray) -> np.ndarray:
        """Orthonormalise the residual ``X`` (``n x b``) in place; return ``R`` (``k x b``).

        On return ``X[:, :k]`` holds ``Q`` with ``X_in = Q R`` up to rounding and
        ``||Q^T Q - I|| = O(eps)``, ``k <= b`` (``k < b`` when the residual is rank
        deficient). Three Gram passes, each one ``syrk`` and one ``trsm`` or ``gemm``:

        1. shifted CholeskyQR (Fukaya et al. 2020): ``G + s I = L L^T`` with
           ``s = 11 (n b + b (b + 1)) eps tr(G)`` always factors, and ``Y = X L^{-T}``
           has condition number ``O(sqrt(cond(X) / sqrt(s)))``, so singular values down to
           ``~1e-12 ||X||`` survive the pass;
        2. an eigen-decomposition of ``Y^T Y = W diag(lam) W^T`` (SVQB): the directions
           with ``lam <= n eps max(lam)`` are the residual's numerical null space (the
           Gram cannot tell them from rounding; where a cap or an earlier update left the
           residual rank deficient, CholeskyQR would stop on them with "not positive
           definite"). They are dropped, their energy ``||diag(lam_d)^{1/2} W_d^T L^T||_F^2``
           is added to :attr:`discarded`, and ``Q2 = Y W_k diag(lam_k)^{-1/2}``;
        3. CholeskyQR of ``Q2`` (well conditioned now) restores orthogonality to rounding.
        """
        n, b = X.shape
        G = sla.blas.dsyrk(1.0, X, trans=1)
        G = np.triu(G) + np.triu(G, 1).T
        tr = float(np.trace(G))
        if not tr > 0.0:  # a zero residual: no new direction
            return np.zeros((0, b))
        G[np.diag_indices(b)] += 11.0 * (n * b + b * (b + 1)) * _EPS * tr
        L = np.linalg.cholesky(G)
        Y = sla.blas.dtrsm(1.0, L, X, side=1, lower=1, trans_a=1, overwrite_b=1)
        if not np.shares_memory(Y, X):
            X[:] = Y
        R = L.T
        G = sla.blas.dsyrk(1.0, X, trans=1)
        G = np.triu(G) + np.triu(G, 1).T
        lam, Wg = np.linalg.eigh(G)
        keep = lam > max(n, b) * _EPS * lam[-1]
        if not keep.all():
            Rd = np.sqrt(np.maximum(lam[~keep], 0.0))[:, None] * (Wg[:, ~keep].T @ R)
            self.discarded += float(np.sum(Rd**2))
            self.dropped += int(b - keep.sum())
        lam, Wg = lam[keep][::-1], Wg[:, keep][:, ::-1]
        k = lam.size
        sq = np.sqrt(lam)
        Q = X @ (Wg / sq)
        X[:, :k] = Q
        R = (sq[:, None] * Wg.T) @ R
        Q = X[:, :k]
        G = sla.blas.dsyrk(1.0, Q, trans=1)
        G = np.triu(G) + np.triu(G, 1).T
        L = np.linalg.cholesky(G)
        Y = sla.blas.dtrsm(1.0, L, Q, side=1, lower=1, trans_a=1, overwrite_b=1)
        if not np.shares_memory(Y, Q):
            Q[:] = Y
        return L.T @ R
