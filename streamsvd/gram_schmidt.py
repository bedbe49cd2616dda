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

Rejection rule: after both passes, the column ``x_k`` (``M``-norm ``nu_k`` before
projection) leaves the residual ``r_k``; the direction is kept when

    ||r_k||_M > reject_tol * nu_k,     reject_tol = n * eps by default,

and otherwise dropped, its coefficients on the current basis being kept. The product
``U V^T`` changes by ``r_k v_k^T``, whose energy ``||r_k||_M^2 ||v_k||^2`` is reported as
discarded. Columns are scaled by exact powers of two before any inner product, so
entries from 1e-300 to 1e300 neither overflow nor underflow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ._scaling import safe_column_norms
from ._validation import as_float_array, check_nonnegative
from .errors import ShapeMismatchError
from .expansion import Expansion
from .inner import InnerProduct, as_inner

__all__ = [
    "BasisExtension",
    "GramSchmidtResult",
    "cgs2_extend",
    "default_reject_tol",
    "orthonormalize",
    "orthonormalize_literal",
]

_EPS = np.finfo(np.float64).eps
_MAX_PASSES = 4  # projections per column: two, plus up to two more while norms collapse
_REITERATE = 0.5  # project again when a pass leaves less than this fraction of the norm


def _m_norms(X: np.ndarray, inner: InnerProduct) -> np.ndarray:
    """``M``-norms of the columns of an already scaled block."""
    MX = X if inner.is_euclidean else inner.apply(X)
    return np.sqrt(np.maximum(np.einsum("ij,ij->j", X, MX), 0.0))


def default_reject_tol(n: int) -> float:
    """Return the default rejection threshold ``n * eps`` (relative to a column's norm)."""
    return max(n, 1) * _EPS


@dataclass(frozen=True)
class BasisExtension:
    """How a block ``X`` (``n x b``) decomposes on a basis ``Q`` extended by new directions.

    ``X = Q @ coeffs + Q_new @ R_new + residual``, where the residual gathers the rejected
    directions (each of ``M``-norm at most ``reject_tol`` times its column's norm).

    Attributes
    ----------
    coeffs : ndarray, shape (q, b)
        Coefficients on the existing basis.
    Q_new : ndarray, shape (n, r)
        New directions, ``M``-orthonormal and ``M``-orthogonal to ``Q``.
    MQ_new : ndarray, shape (n, r)
        ``M @ Q_new`` (the same array as ``Q_new`` for the Euclidean inner product).
    R_new : ndarray, shape (r, b)
        Coefficients on the new directions (upper trapezoidal in the accepted order).
    accepted : ndarray of bool, shape (b,)
        Whether each column brought a new direction.
    rejected_norms : ndarray, shape (b,)
        ``||r_k||_M`` of each rejected residual, zero for accepted columns.
    """

    coeffs: np.ndarray
    Q_new: np.ndarray
    MQ_new: np.ndarray
    R_new: np.ndarray
    accepted: np.ndarray
    rejected_norms: np.ndarray


def cgs2_extend(
    Q: np.ndarray,
    MQ: np.ndarray,
    X: np.ndarray,
    *,
    inner: InnerProduct,
    reject_tol: float,
    G: np.ndarray | None = None,
) -> BasisExtension:
    """Decompose a block on an ``M``-orthonormal basis and extend the basis by CGS2.

    Parameters
    ----------
    Q : ndarray, shape (n, w)
        Stored basis factor.
    MQ : ndarray, shape (n, w)
        ``M @ Q`` (``Q`` itself for the Euclidean inner product).
    X : ndarray, shape (n, b)
        Finite block; not modified.
    inner : InnerProduct
    reject_tol : float
        Relative threshold of the rejection rule (module docstring).
    G : ndarray, shape (w, q), optional
        When given, the basis is the lazy product ``Q @ G`` (``M``-orthonormal), and the
        products with it are formed as ``G^T (MQ^T X)`` and ``Q (G C)`` so that ``Q @ G``
        is never built.
    """
    n, b = X.shape
    peak = np.max(np.abs(X), axis=0) if n else np.zeros(b)
    exps = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0)
    Xs = np.ldexp(X, -exps[np.newaxis, :])
    MXs = inner.apply(Xs)
    nu = np.sqrt(np.maximum(np.einsum("ij,ij->j", Xs, MXs), 0.0))
    q = Q.shape[1] if G is None else G.shape[1]
    C = np.zeros((q, b))
    if q:
        active = np.arange(b)
        before = nu
        for npass in range(_MAX_PASSES):
            Xa = Xs[:, active]
            if G is None:
                dC = MQ.T @ Xa
                Xa -= Q @ dC
            else:
                dC = G.T @ (MQ.T @ Xa)
                Xa -= Q @ (G @ dC)
            Xs[:, active] = Xa
            C[:, active] += dC
            after = _m_norms(Xa, inner)
            # twice is enough unless a pass cancelled more than half of the norm
            again = (after < _REITERATE * before) if npass else np.ones(active.size, bool)
            active, before = active[again], after[again]
            if not active.size:
                break
    Q_new = np.empty((n, b))
    MQ_new = Q_new if inner.is_euclidean else np.empty((n, b))
    R_new = np.zeros((b, b))
    rejected = np.zeros(b)
    accepted = np.zeros(b, dtype=bool)
    r = 0
    for k in range(b):
        x = Xs[:, k]
        mx = x if inner.is_euclidean else inner.apply(x)
        nrm = float(np.sqrt(max(float(x @ mx), 0.0)))
        # DGKS on the whole basis: the first pass is against the block's new directions
        # (the old basis was handled above); whenever a pass cancels more than half of the
        # norm, the next one projects against the old basis and the new directions both,
        # since the rounding of a cancelling pass leaves components along either
        for npass in range(_MAX_PASSES if r or q else 0):
            if npass and q:
                if G is None:
                    c_old = MQ.T @ x
                    x -= Q @ c_old
                else:
                    c_old = G.T @ (MQ.T @ x)
                    x -= Q @ (G @ c_old)
                C[:, k] += c_old
            if r:
                c = MQ_new[:, :r].T @ x
                x -= Q_new[:, :r] @ c
                R_new[:r, k] += c
            mx = x if inner.is_euclidean else inner.apply(x)
            prev, nrm = nrm, float(np.sqrt(max(float(x @ mx), 0.0)))
            if nrm >= _REITERATE * prev:
                break
        if nu[k] == 0.0 or nrm <= reject_tol * nu[k]:
            rejected[k] = nrm
            continue
        Q_new[:, r] = x / nrm
        if not inner.is_euclidean:
            MQ_new[:, r] = mx / nrm
        R_new[r, k] = nrm
        accepted[k] = True
        r += 1
    scale = np.ldexp(1.0, exps)
    return BasisExtension(
        coeffs=C * scale,
        Q_new=Q_new[:, :r].copy(),
        MQ_new=Q_new[:, :r].copy() if inner.is_euclidean else MQ_new[:, :r].copy(),
        R_new=R_new[:r] * scale,
        accepted=accepted,
        rejected_norms=rejected * scale,
    )


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
        ``sum_k ||r_k||_M^2 ||v_k||^2`` over the rejected columns: an upper bound of
        ``||U V^T - U_in V_in^T||_F^2`` up to rounding when ``M = I``.
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
        Number of columns projected together (BLAS-3) before the column-wise pass.

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
    Qbuf = np.empty((n, min(p, n)))
    MQbuf = Qbuf if ip.is_euclidean else np.empty_like(Qbuf)
    R = np.zeros((min(p, n), p))
    q = 0
    rejected: list[int] = []
    energy = 0.0
    vnorms = safe_column_norms(V)
    for start in range(0, p, block):
        stop = min(start + block, p)
        ext = cgs2_extend(Qbuf[:, :q], MQbuf[:, :q], U[:, start:stop], inner=ip, reject_tol=tol)
        r = ext.Q_new.shape[1]
        R[:q, start:stop] = ext.coeffs
        R[q : q + r, start:stop] = ext.R_new
        Qbuf[:, q : q + r] = ext.Q_new
        if not ip.is_euclidean:
            MQbuf[:, q : q + r] = ext.MQ_new
        q += r
        bad = np.flatnonzero(~ext.accepted)
        rejected.extend(int(start + k) for k in bad)
        energy += float(np.sum((ext.rejected_norms[bad] * vnorms[start + bad]) ** 2))
    Uo = Qbuf[:, :q].copy()
    Vo = V @ R[:q].T
    return GramSchmidtResult(Expansion(Uo, Vo, inner=ip), tuple(rejected), energy)


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
