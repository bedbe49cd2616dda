"""Left-orthonormalisation of an expansion: Algorithm 1 and block CGS2.

Two implementations:

* :func:`orthonormalize_literal` is Algorithm 1 transcribed loop by loop (modified
  Gram-Schmidt order, one pass), kept as the reference;
* :func:`orthonormalize` (the fast path) runs classical Gram-Schmidt twice
  ("twice is enough", Giraud et al. 2005) block by block, and *rejects* a new direction
  whose residual is negligible instead of normalising rounding noise. "Twice is enough"
  assumes the second pass does not cancel much; a column whose norm a pass reduces by
  more than half is projected again (the Kahan-Parlett / DGKS criterion), up to four
  passes, so that a small accepted residual is orthogonal to working accuracy.

Both extend the basis block by block with :func:`~streamsvd.linalg.extend.extend_basis`
(module :mod:`streamsvd.linalg.extend`), the step every update of a compressor takes.

Rejection rule: after both passes, the column ``x_k`` (``M``-norm ``nu_k`` before
projection) leaves the residual ``r_k``; the direction is kept when

    ||r_k||_M > reject_tol * nu_k,     reject_tol = n * eps by default,

and otherwise dropped, its coefficients on the current basis being kept. The product
``U V^T`` changes by ``r_k v_k^T``, whose energy ``||r_k||_M^2 ||v_k||^2`` is reported as
discarded. Columns are scaled by exact powers of two before any inner product, so
entries from 1e-300 to 1e300 neither overflow nor underflow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from streamsvd._util.scaling import pow2_exponent
from streamsvd._util.validation import as_float_array, check_nonnegative, check_positive_int
from streamsvd.algebra.blas import gram
from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.algebra.memory import MemoryBasis
from streamsvd.errors import ShapeMismatchError
from streamsvd.linalg.expansion import Expansion
from streamsvd.linalg.extend import extend_basis
from streamsvd.linalg.rejection import default_reject_tol

__all__ = [
    "GramSchmidtResult",
    "orthonormalize",
    "orthonormalize_literal",
]

_EPS = np.finfo(np.float64).eps
# a basis whose Gram departs from the identity by more than this times n eps is
# orthonormalised by its Cholesky factor (as the compressors' reorth_tol)
_REORTH = 10.0


@dataclass(frozen=True)
class GramSchmidtResult:
    """Result of :func:`orthonormalize`.

    Attributes
    ----------
    expansion : Expansion
        ``U`` ``M``-orthonormal, ``V`` such that ``U V^T`` equals the input product up to
        rounding and the rejected residuals.
    rejected : tuple of int
        Indices of the input columns whose new direction was rejected.
    discarded_energy : float
        ``||Res V_L^T||_F^2`` (in ``M``) of what the columns ``L`` keep outside the basis:
        the residuals of the rejected columns, and the small parts of accepted columns
        that the column rule left out of a block's span. Computed from those columns
        themselves (their residuals' Gram matrix and that of their right vectors), it is
        ``||U V^T - U_in V_in^T||_F^2`` up to rounding.
    """

    expansion: Expansion
    rejected: tuple[int, ...]
    discarded_energy: float


def _check_pair(U: Any, V: Any) -> tuple[np.ndarray, np.ndarray]:
    U = as_float_array(U, "U", ndim=2)
    V = as_float_array(V, "V", ndim=2)
    if U.shape[1] != V.shape[1]:
        raise ShapeMismatchError(
            f"`U` and `V` must have the same number of columns (the rank p); got U {U.shape} "
            f"and V {V.shape}."
        )
    return U, V


def orthonormalize(
    U: Any,
    V: Any,
    *,
    inner: Any = None,
    reject_tol: float | None = None,
    block: int = 64,
) -> GramSchmidtResult:
    """Left-orthonormalise ``U V^T`` (Algorithm 1) by block CGS2 with rejection.

    Parameters
    ----------
    U : array_like, shape (n, p)
        Left vectors, in any inner product.
    V : array_like, shape (m, p)
        Right vectors.
    inner : None, array_like, sparse matrix or InnerProduct
        The inner product ``M`` of the result's orthonormality (Euclidean by default).
    reject_tol : float, optional
        A direction is rejected when ``||r_k||_M <= reject_tol * ||u_k||_M``; default
        ``n * eps``.
    block : int
        Number of columns extended together (:func:`extend_basis`).

    Returns
    -------
    GramSchmidtResult
    """
    U, V = _check_pair(U, V)
    n, p = U.shape
    ip = as_inner(inner, n)
    tol = (
        default_reject_tol(n)
        if reject_tol is None
        else check_nonnegative(reject_tol, "reject_tol")
    )
    block = int(check_positive_int(block, "block"))  # type: ignore[arg-type]
    basis = MemoryBasis(n, ip, capacity=min(p, n) + min(block, p))
    R = np.zeros((min(p, n), p))
    # the basis Gram Q^T M Q, from what each extension measured: a direction keeps the
    # component along the basis a first projection left when it is tiny (`cross_gram`)
    H = np.zeros((min(p, n), min(p, n)))
    rejected: list[int] = []
    lossy: list[int] = []  # columns that keep a part outside the basis, rejected or not
    for start in range(0, p, block):
        stop = min(start + block, p)
        q = basis.width
        ext = extend_basis(basis, None, U[:, start:stop], inner=ip, reject_tol=tol,
                           basis_gram=H[:q, :q])
        r = ext.rank
        R[:q, start:stop] = ext.coeffs
        R[q : q + r, start:stop] = ext.R_new
        H[:q, q : q + r] = ext.cross_gram
        H[q : q + r, :q] = ext.cross_gram.T
        H[q : q + r, q : q + r] = ext.gram_new
        basis.accept(r)
        rejected.extend(int(start + k) for k in np.flatnonzero(~ext.accepted))
        if ext.rejected_map.size:
            lossy.extend(int(start + k) for k in np.flatnonzero(np.any(ext.rejected_map, 0)))
    q = basis.width
    Uo = basis.Q.copy()
    Rq = R[:q]
    if q and _gram_departure(H[:q, :q]) > _REORTH * n * _EPS:
        # Q = Qo L^T with Qo = Q L^(-T) orthonormal (Q^T M Q = L L^T): Q R = Qo (L^T R)
        L = np.linalg.cholesky(H[:q, :q])
        Uo = scipy.linalg.solve_triangular(L, Uo.T, lower=True).T
        Rq = L.T @ Rq
    Vo = V @ Rq.T
    # the discarded part is what the columns keep outside the basis: the rejected ones,
    # and the accepted ones whose small coefficients the column rule left out (the kept
    # direction is the span of the accepted columns, not each column itself); taken
    # from the columns themselves, its energy is exact even where the residuals of
    # different blocks combine
    lost = np.asarray(lossy, dtype=np.int64)
    res = U[:, lost] - Uo @ Rq[:, lost]
    energy = _residual_norm(res, V[:, lost], ip) ** 2
    return GramSchmidtResult(Expansion(Uo, Vo, inner=ip), tuple(rejected), energy)


def _gram_departure(H: np.ndarray) -> float:
    """``||H - I||_2`` of a symmetric Gram matrix."""
    E = H - np.eye(H.shape[0])
    return float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (E + E.T)))))


def _residual_norm(res: np.ndarray, V: np.ndarray, inner: InnerProduct) -> float:
    """``||res V^T||_F`` in ``M``, from the two Gram matrices, overflow-safe."""
    if res.size == 0 or V.size == 0:
        return 0.0
    er, ev = pow2_exponent(res), pow2_exponent(V)
    Rs, Vs = np.ldexp(res, -er), np.ldexp(V, -ev)
    energy = float(np.sum(gram(Rs, inner) * (Vs.T @ Vs)))
    return math.ldexp(math.sqrt(max(energy, 0.0)), er + ev)


def orthonormalize_literal(U: Any, V: Any, *, inner: Any = None) -> Expansion:
    """Algorithm 1 of the paper, transcribed loop by loop (the reference).

    Each ``u_k`` is projected on the previous ``u~_i`` one at a time (modified
    Gram-Schmidt order), the right vectors are updated with the projections, and the
    residual is normalised. A residual of exactly zero norm is dropped (Algorithm 1
    divides by it); no other rejection is made.
    """
    U, V = _check_pair(U, V)
    ip = as_inner(inner, U.shape[0])

    def ip_norm(x: np.ndarray) -> float:
        return float(np.sqrt(float(x @ ip.apply(x))))

    us: list[np.ndarray] = []
    vs: list[np.ndarray] = []
    for k in range(U.shape[1]):
        uk = U[:, k].copy()
        vk = V[:, k].copy()
        for i in range(len(us)):
            alpha = float(us[i] @ ip.apply(uk))  # projection
            vs[i] = vs[i] + alpha * vk  # update right modes
            uk = uk - alpha * us[i]  # subtract projected component
        nrm = ip_norm(uk)
        if nrm == 0.0:
            continue
        us.append(uk / nrm)  # new left vector
        vs.append(nrm * vk)  # new right vector
    n, m = U.shape[0], V.shape[0]
    Uo = np.column_stack(us) if us else np.zeros((n, 0))
    Vo = np.column_stack(vs) if vs else np.zeros((m, 0))
    return Expansion(Uo, Vo, inner=ip)
