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

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg
import scipy.linalg.blas as blas
import scipy.linalg.lapack

from ._scaling import pow2_exponent
from ._validation import as_float_array, check_nonnegative
from .basis import BasisBackend, MemoryBasis
from .errors import ShapeMismatchError
from .expansion import Expansion
from .inner import InnerProduct, as_inner

__all__ = [
    "BasisExtension",
    "GramSchmidtResult",
    "default_reject_tol",
    "extend_basis",
    "orthonormalize",
    "orthonormalize_literal",
]

_EPS = np.finfo(np.float64).eps
_MAX_PASSES = 4  # projections on the old basis: one, plus up to three while norms collapse
_REITERATE = 0.5  # project again when a pass leaves less than this fraction of the norm
_DELTA = 1.0 / 32.0  # a residual joins a CholeskyQR batch when its Schur pivot is >= _DELTA^2
_COND_MAX = 1e4  # and the batch's factor stays this well conditioned (CholeskyQR2 is exact)


def _m_norms(X: np.ndarray, inner: InnerProduct) -> np.ndarray:
    """``M``-norms of the columns of an already scaled block."""
    MX = X if inner.is_euclidean else inner.apply(X)
    return np.sqrt(np.maximum(np.einsum("ij,ij->j", X, MX), 0.0))


def _gram(X: np.ndarray, inner: InnerProduct) -> np.ndarray:
    """``X^T M X`` (symmetric; a rank-k update for the Euclidean product)."""
    if inner.is_euclidean and X.shape[1] <= 8:  # too narrow for syrk to pay
        G = X.T @ X
        return 0.5 * (G + G.T)
    if inner.is_euclidean:
        H = blas.dsyrk(1.0, np.asfortranarray(X), trans=1)
        return np.triu(H) + np.triu(H, 1).T
    G = X.T @ inner.apply(X)
    return 0.5 * (G + G.T)


def default_reject_tol(n: int) -> float:
    """Return the default rejection threshold ``n * eps`` (relative to a column's norm)."""
    return max(n, 1) * _EPS


@dataclass(frozen=True)
class BasisExtension:
    """How a block ``X`` (``n x b``) decomposes on a basis ``Q`` extended by new directions.

    ``X = Q coeffs + Q_new R_new + Res``, where ``Q_new`` (``n x r``) sits in the basis
    backend's workspace (accepted by the caller with ``basis.accept(r)``) and ``Res`` holds
    the rejected residuals (zero in accepted columns), ``M``-orthogonal to ``Q`` and
    ``Q_new`` to working accuracy.

    Attributes
    ----------
    coeffs : ndarray, shape (q, b)
        Coefficients on the existing basis.
    R_new : ndarray, shape (r, b)
        Coefficients on the new directions.
    accepted : ndarray of bool, shape (b,)
        Whether each column brought a new direction.
    rejected_norms : ndarray, shape (b,)
        ``||res_k||_M`` of each rejected residual, zero for accepted columns.
    rejected_gram : ndarray, shape (k, k)
        ``Res_rej^T M Res_rej`` of the ``k`` rejected residuals, scaled by
        ``2^-(e_i + e_j)`` with ``e = rejected_exponents`` (overflow-safe).
    rejected_exponents : ndarray of int, shape (k,)
    block_norm : float
        ``||X||_M`` (Frobenius in ``M``) of the block, overflow-safe.
    """

    coeffs: np.ndarray
    R_new: np.ndarray
    accepted: np.ndarray
    rejected_norms: np.ndarray
    rejected_gram: np.ndarray
    rejected_exponents: np.ndarray
    block_norm: float

    @property
    def rank(self) -> int:
        """Number of new directions ``r``."""
        return int(self.R_new.shape[0])

    def rejected_norm(self, F: np.ndarray | None = None) -> float:
        """Return ``||Res_rej F^T||_F`` in the inner product ``M``, exactly and overflow-safe.

        ``F`` (``rows x k``) holds the right vectors of the rejected columns (``V_k`` of an
        increment, the core of an expansion); ``None`` stands for distinct columns of
        their own (a block of snapshots), where the norm is ``sqrt(sum ||res_k||^2)``.
        """
        e = self.rejected_exponents
        if e.size == 0:
            return 0.0
        if F is None:
            return _scaled_norm(np.sqrt(np.maximum(np.diag(self.rejected_gram), 0.0)), e)
        shift = int(e.max())
        Fs = np.ldexp(F, (e - shift)[np.newaxis, :])
        top = pow2_exponent(Fs)
        Fs = np.ldexp(Fs, -top)
        energy = float(np.sum(self.rejected_gram * (Fs.T @ Fs)))
        return math.ldexp(math.sqrt(max(energy, 0.0)), top + shift)


def extend_basis(
    basis: BasisBackend,
    G: np.ndarray | None,
    X: np.ndarray,
    *,
    inner: InnerProduct,
    reject_tol: float,
    reference: np.ndarray | None = None,
) -> BasisExtension:
    """Decompose a block on the basis ``Q G`` and orthonormalise its residual, BLAS-3.

    1. Block CGS against the basis, column subsets projected again while a pass cancels
       more than half of their norm (DGKS; Giraud et al. 2005: twice is enough).
    2. The residual block by CholeskyQR2 in batches: the Gram of the residuals normalised
       to unit ``M``-norm is factored in order, a column joining the batch only when its
       Schur pivot is at least ``_DELTA^2`` and the batch's factor keeps
       ``cond_1 <= _COND_MAX`` (LAPACK ``dtrcon``), so that two CholeskyQR passes give
       orthonormality to working accuracy; the rounding left along the old basis is
       amplified by at most that condition, which the orthogonality monitor of the
       compressor measures. The other
       columns are projected explicitly (CGS2) on the old basis and the batch, their
       norms measured directly (never from a Gram of the data), and treated in the next
       batch. A residual whose norm is ``<= reject_tol * reference_k`` is rejected, never
       normalised.
    3. The rejected residuals are projected on the new directions, so that they are
       ``M``-orthogonal to every kept direction.

    Parameters
    ----------
    basis : BasisBackend
        The stored basis; the new directions are left in its workspace.
    G : ndarray, shape (w, q), or None
        The basis is ``Q G`` (``M``-orthonormal); ``None``: the basis is ``Q``.
    X : ndarray, shape (n, b)
        Finite block; not modified.
    inner : InnerProduct
    reject_tol : float
        Relative rejection threshold.
    reference : ndarray, shape (b,), optional
        The norm each column's residual is compared with; default the column's own
        ``M``-norm. Columns with a zero reference carry nothing and are rejected.
    """
    n, b = X.shape
    q = basis.width if G is None else G.shape[1]
    peak = np.max(np.abs(X), axis=0) if n else np.zeros(b)
    exps = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0).astype(np.int64)
    Y, MY = basis.workspace(b)
    np.multiply(X, np.ldexp(1.0, -exps), out=Y)  # exact: powers of two
    nu = _m_norms(Y, inner)
    current = nu.copy()
    ref = nu if reference is None else np.ldexp(np.asarray(reference, float), -exps)
    C = np.zeros((q, b))
    if q:
        _project_old(basis, G, Y, C, current, inner)
    R_new = np.zeros((b, b))
    rejected = np.zeros(b, dtype=bool)
    order: list[np.ndarray] = []  # the accepted columns, batch after batch
    batches: list[np.ndarray] = []  # their orthonormal directions
    pending = np.arange(b)
    while pending.size:
        norms = current[pending] if pending.size == b else _m_norms(Y[:, pending], inner)
        drop = (ref[pending] == 0.0) | (norms <= reject_tol * ref[pending])
        rejected[pending[drop]] = True
        pending, norms = pending[~drop], norms[~drop]
        if not pending.size:
            break
        whole = pending.size == b
        Yp = Y if whole else Y[:, pending]
        Gz = _gram(Yp, inner) / np.outer(norms, norms)  # the Gram of the unit columns
        take, Lz = _cholesky_batch(Gz)
        cols = pending[take]
        r0 = sum(o.size for o in order)
        # the factor of the batch's own Gram is diag(norms) Lz: CholeskyQR's first pass
        # reuses it (Cholesky commutes with a diagonal scaling)
        first = norms[take][:, np.newaxis] * Lz
        if whole and take.all():
            # the common case, in place: the workspace becomes the new directions
            Qb, Rb = _cholesky_qr2(Y, inner, in_place=True, first=first)
        else:
            Qb, Rb = _cholesky_qr2(Yp[:, take], inner, in_place=True, first=first)
        R_new[r0 : r0 + cols.size, cols] = Rb
        order.append(cols)
        batches.append(Qb)
        rest = pending[~take]
        if rest.size:
            _project_on_batches(basis, G, Y, C, R_new, rest, batches, order, inner)
        pending = rest
    r = sum(o.size for o in order)
    in_place = len(batches) == 1 and np.shares_memory(batches[0], Y)
    Qnew = batches[0] if in_place else (np.hstack(batches) if batches else np.zeros((n, 0)))
    rej = np.flatnonzero(rejected)
    if rej.size and r:
        # make the rejected residuals orthogonal to every new direction (exact energies)
        Yr = Y[:, rej]
        c = inner.gram(Qnew, Yr)
        Yr -= Qnew @ c
        R_new[:r, rej] += c
        Y[:, rej] = Yr
    Yrej = Y[:, rej].copy()
    Grej = _gram(Yrej, inner) if rej.size else np.zeros((0, 0))
    rejected_norms = np.zeros(b)
    rejected_norms[rej] = np.sqrt(np.maximum(np.diag(Grej), 0.0))
    # the new directions go to the front of the workspace, in the accepted order
    if not in_place:
        Y[:, :r] = Qnew
    if not inner.is_euclidean and r:
        MY[:, :r] = inner.apply(Qnew)
    perm = np.concatenate(order) if order else np.zeros(0, dtype=np.int64)
    scale = np.ldexp(1.0, exps)
    accepted = np.zeros(b, dtype=bool)
    accepted[perm] = True
    return BasisExtension(
        coeffs=C * scale,
        R_new=R_new[:r] * scale,
        accepted=accepted,
        rejected_norms=rejected_norms * scale,
        rejected_gram=Grej,
        rejected_exponents=exps[rej],
        block_norm=_scaled_norm(nu, exps),
    )


def _scaled_norm(x: np.ndarray, exps: np.ndarray) -> float:
    """``sqrt(sum (x_k 2^e_k)^2)`` without overflow."""
    if x.size == 0:
        return 0.0
    top = int(exps.max())
    return math.ldexp(float(np.linalg.norm(np.ldexp(x, exps - top))), top)


def _project_old(
    basis: BasisBackend,
    G: np.ndarray | None,
    Y: np.ndarray,
    C: np.ndarray,
    norms: np.ndarray,
    inner: InnerProduct,
) -> None:
    """Project ``Y`` on the basis, columns again while a pass cancels; update ``norms``.

    ``norms`` holds the ``M``-norms of the columns on entry and on return.
    """
    active = np.arange(Y.shape[1])
    before = norms[active]
    for _ in range(_MAX_PASSES):
        whole = active.size == Y.shape[1]
        Ya = Y if whole else Y[:, active]
        dC = basis.project(Ya, G)
        basis.subtract(Ya, G, dC)
        if not whole:
            Y[:, active] = Ya
        C[:, active] += dC
        after = _m_norms(Ya, inner)
        norms[active] = after
        # one pass is enough unless it cancelled more than half of the norm (DGKS)
        again = after < _REITERATE * before
        active, before = active[again], after[again]
        if not active.size:
            return


def _well_conditioned(L: np.ndarray) -> bool:
    """Whether a lower-triangular factor has ``cond_1(L) <= _COND_MAX`` (LAPACK estimate)."""
    rcond, _ = scipy.linalg.lapack.dtrcon(L, norm="1", uplo="L", diag="N")
    return bool(rcond * _COND_MAX >= 1.0)


def _cholesky_batch(Gz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns (in order) of a unit-diagonal Gram that form a well-conditioned batch.

    Returns the mask of the batch's columns and the Cholesky factor of their Gram.

    A column joins when its Schur pivot is at least ``_DELTA^2`` and the factor of the
    batch keeps ``cond_1(L) <= _COND_MAX`` (pivots alone do not bound the condition: the
    growth can be exponential in the batch size), so that two CholeskyQR passes are
    accurate to working precision (their error grows as ``eps cond^2``).
    """
    c = Gz.shape[0]
    if c == 1:
        return np.ones(1, dtype=bool), np.sqrt(np.maximum(Gz, 0.0))
    try:
        L = np.linalg.cholesky(Gz)
        if float(np.min(np.diag(L))) >= _DELTA and _well_conditioned(L):
            return np.ones(c, dtype=bool), L
    except np.linalg.LinAlgError:
        pass
    take = np.zeros(c, dtype=bool)
    L = np.zeros((c, c))
    idx: list[int] = []
    for k in range(c):
        if idx:
            lk = scipy.linalg.solve_triangular(L[np.ix_(idx, idx)], Gz[idx, k], lower=True)
            piv = float(Gz[k, k] - lk @ lk)
        else:
            lk, piv = np.zeros(0), float(Gz[k, k])
        if piv < _DELTA * _DELTA:
            continue
        L[k, idx] = lk
        L[k, k] = math.sqrt(piv)
        trial = idx + [k]
        if len(trial) > 1 and not _well_conditioned(L[np.ix_(trial, trial)]):
            L[k, :] = 0.0
            continue
        idx = trial
        take[k] = True
    return take, L[np.ix_(idx, idx)]


def _cholesky_qr2(
    Z: np.ndarray,
    inner: InnerProduct,
    *,
    in_place: bool = False,
    first: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``Z = Q R`` by two CholeskyQR passes (``Z`` well conditioned).

    With ``in_place`` (and ``Z`` column-major) ``Q`` overwrites ``Z``; else it is new.
    ``first`` is the Cholesky factor of ``Z^T M Z`` when the caller has it already.
    """
    Q = Z if in_place and Z.flags.f_contiguous else np.array(Z, order="F")
    R = np.eye(Z.shape[1])
    for k in range(2):
        L = first if k == 0 and first is not None else np.linalg.cholesky(_gram(Q, inner))
        out = blas.dtrsm(1.0, L, Q, side=1, lower=1, trans_a=1, overwrite_b=1)
        if not np.shares_memory(out, Q):
            Q[...] = out
        R = L.T @ R
    return Q, R


def _project_on_batches(
    basis: BasisBackend,
    G: np.ndarray | None,
    Y: np.ndarray,
    C: np.ndarray,
    R_new: np.ndarray,
    rest: np.ndarray,
    batches: list[np.ndarray],
    order: list[np.ndarray],
    inner: InnerProduct,
) -> None:
    """CGS2 of the deferred columns on the old basis and the new directions together."""
    Qn = np.hstack(batches)
    r = Qn.shape[1]
    Yr = Y[:, rest]
    for _ in range(2):
        c = inner.gram(Qn, Yr)
        Yr -= Qn @ c
        R_new[:r, rest] += c
        if C.shape[0]:
            dC = basis.project(Yr, G)
            basis.subtract(Yr, G, dC)
            C[:, rest] += dC
    Y[:, rest] = Yr


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
        ``||Res V_rej^T||_F^2`` (in ``M``) of the rejected residuals, computed exactly from
        their Gram matrix and that of their right vectors: ``||U V^T - U_in V_in^T||_F^2``
        up to rounding.
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
    basis = MemoryBasis(n, ip, capacity=min(p, n) + min(block, p))
    R = np.zeros((min(p, n), p))
    rejected: list[int] = []
    energy = 0.0
    for start in range(0, p, block):
        stop = min(start + block, p)
        q = basis.width
        ext = extend_basis(basis, None, U[:, start:stop], inner=ip, reject_tol=tol)
        r = ext.rank
        R[:q, start:stop] = ext.coeffs
        R[q : q + r, start:stop] = ext.R_new
        basis.accept(r)
        bad = np.flatnonzero(~ext.accepted)
        rejected.extend(int(start + k) for k in bad)
        energy += ext.rejected_norm(V[:, start + bad]) ** 2
    q = basis.width
    Uo = basis.Q.copy()
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
