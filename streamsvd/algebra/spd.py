"""The checks that a matrix defines an inner product: symmetric, and positive definite.

:class:`~streamsvd.algebra.inner.MatrixInner` calls :func:`check_symmetric` on every
matrix and :func:`check_sparse_definite` on a sparse one that is not diagonal: on
``D^-1/2 M D^-1/2`` (``D`` its diagonal), an ``LDL^T`` factorisation (its inertia, exact)
up to ``n = 10000``, and above, a Lanczos estimate of the smallest eigenvalue from a fixed
start. (A dense matrix is checked by its Cholesky factorisation, in ``MatrixInner``.)
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.linalg

from streamsvd._util.lazy import lazy_module
from streamsvd._util.threads import blas_threads
from streamsvd.errors import InputError

if TYPE_CHECKING:
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
else:  # imported by the first sparse matrix checked
    sp = lazy_module("scipy.sparse", absent={"issparse": lambda x: False})
    spla = lazy_module("scipy.sparse.linalg")

__all__ = [
    "EXACT_MAX_N", "check_sparse_definite", "check_symmetric", "proven_definite",
    "remember_definite", "row_sum_bound",
]

logger = logging.getLogger(__name__)

# definiteness of a sparse M (on D^-1/2 M D^-1/2): an exact LDL^T up to this size (its
# fill, in 3-D, costs about a second there), a Lanczos estimate above
EXACT_MAX_N = 10_000
# the Lanczos estimate: its smallest Ritz value is looked at every _LANCZOS_EVERY steps
# (a divisor of _LANCZOS_MAX_STEPS); it is taken after _LANCZOS_MIN_STEPS (by then an
# eigenvalue apart from the rest has shown) once it moves by at most _LANCZOS_RTOL of
# itself between two looks, else after _LANCZOS_MAX_STEPS, and then logged
_LANCZOS_EVERY = 10
_LANCZOS_MIN_STEPS = 30
_LANCZOS_MAX_STEPS = 150
_LANCZOS_RTOL = 1e-2


def check_symmetric(mat: Any) -> None:
    """Raise :class:`InputError` unless ``mat`` is symmetric to the rounding of ``mat @ x``.

    The tolerance is ``max(1000, w) * eps * max|M|``, ``w`` the most entries in a row
    (``n`` for a dense matrix): a product with ``M`` rounds by up to ``w * eps * |M| |x|``,
    so that an asymmetry below it cannot be told from rounding.
    """
    if sp.issparse(mat):
        asym = abs(mat - mat.T).max() if mat.nnz else 0.0
        scale = abs(mat).max() if mat.nnz else 0.0
        width = int(np.diff(mat.indptr).max(initial=0))
    else:
        asym = float(np.max(np.abs(mat - mat.T)))
        scale = float(np.max(np.abs(mat)))
        width = mat.shape[0]
    if asym > max(1e3, width) * np.finfo(float).eps * scale:
        raise InputError(
            f"`M` must be symmetric; got max |M - M^T| = {asym:.3e} for max |M| = "
            f"{scale:.3e}. Symmetrise it with `(M + M.T) / 2`."
        )


def check_sparse_definite(mat: sp.csr_array, diag: np.ndarray) -> None:
    """Raise :class:`InputError` unless the sparse symmetric ``mat`` is positive definite.

    Parameters
    ----------
    mat : scipy.sparse.csr_array, shape (n, n)
        Symmetric, with the positive diagonal ``diag``.
    diag : numpy.ndarray, shape (n,)
        Its diagonal.

    Notes
    -----
    The test is on ``S = D^-1/2 M D^-1/2`` (unit diagonal, ``||S||_2 <= ||S||_inf``). An
    eigenvalue at most ``tol = n * eps * ||S||_inf`` counts as zero. Up to
    ``EXACT_MAX_N``, SuperLU factors ``P S P^T = L U`` with the diagonal as pivots (a
    symmetric ordering and a zero pivot threshold): then ``U = D L^T``, and by Sylvester's
    law of inertia ``S`` has as many negative eigenvalues as ``D`` negative entries; each
    pivot is at least the smallest eigenvalue, so a pivot within ``tol`` of zero makes
    ``S`` singular to working precision. Above, the smallest Ritz value of a Lanczos run
    is at least the smallest eigenvalue: at most ``tol`` refuses ``M``.
    """
    n = mat.shape[0]
    s = 1.0 / np.sqrt(diag)
    norm = float(np.max(s * (abs(mat) @ s)))
    tol = n * np.finfo(float).eps * norm
    scaled = "D^-1/2 M D^-1/2 (D its diagonal)"
    if n <= EXACT_MAX_N:
        how = f"the LDL^T factorisation of {scaled}"
        pivots = _ldlt_pivots(sp.diags_array(s) @ mat @ sp.diags_array(s))
        negative = 0 if pivots is None else int(np.count_nonzero(pivots < -tol))
        if pivots is None:
            found = f"it is singular or indefinite: {how} meets a zero pivot"
        elif negative:
            plural = "s" if negative > 1 else ""
            found = (
                f"it is indefinite: {how} has {negative} negative pivot{plural} (the "
                f"smallest {float(pivots.min()):.3e}), so M has {negative} negative "
                f"eigenvalue{plural}"
            )
        elif pivots.min() <= tol:
            found = (
                f"it is singular to working precision: {how} has a pivot of "
                f"{float(pivots.min()):.3e}, within {tol:.1e} of zero"
            )
        else:
            return
    else:
        theta, settled, steps = _lanczos_smallest(lambda x: s * (mat @ (s * x)), n, tol)
        if theta > tol:
            if not settled:
                logger.warning(
                    "the sparse inner-product matrix (n = %d) is taken as positive definite "
                    "without proof: after %d Lanczos steps the smallest eigenvalue estimate "
                    "of %s is %.3e and still moving (M is ill-conditioned, or singular)",
                    n, steps, scaled, theta,
                )
            return
        how = f"a Lanczos estimate of the smallest eigenvalue of {scaled} is {theta:.3e}"
        found = (
            f"it is indefinite: {how}, negative" if theta < -tol else
            f"it is singular to working precision: {how}, within {tol:.1e} of zero"
        )
    raise InputError(
        f"`M` must be symmetric positive definite to define an inner product; {found}. "
        "Check the matrix: a mass matrix is positive definite unless it is assembled "
        "wrongly or keeps degrees of freedom that no element carries."
    )


def _ldlt_pivots(S: sp.csr_array) -> np.ndarray | None:
    """Return the pivots ``D`` of ``P S P^T = L D L^T``, ``S`` symmetric (SuperLU, no pivoting).

    Returns
    -------
    numpy.ndarray or None
        The pivots; None when one is exactly zero (SuperLU then finds ``S`` exactly
        singular, or takes a pivot off the diagonal).
    """
    try:
        lu = spla.splu(
            S.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # "Factor is exactly singular"
        return None
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    return lu.U.diagonal()


def _lanczos_smallest(
    apply: Callable[[np.ndarray], np.ndarray], n: int, tol: float
) -> tuple[float, bool, int]:
    """Estimate the smallest eigenvalue of a symmetric operator by the Lanczos process.

    Plain Lanczos (no reorthogonalisation: its extreme Ritz values stay right) from a
    fixed random start, so that the same matrix always gets the same answer. The
    smallest Ritz value decreases towards the smallest eigenvalue: an eigenvalue standing
    apart below the rest shows within a few tens of steps, the bottom of a cluster is
    approached slowly.

    Parameters
    ----------
    apply : callable
        ``x -> S @ x`` for a symmetric ``S`` of size ``n``.
    n : int
        The size.
    tol : float
        Stop as soon as the estimate is at most ``tol``.

    Returns
    -------
    theta : float
        The smallest Ritz value, at least the smallest eigenvalue (up to rounding).
    settled : bool
        Whether ``theta`` moved by at most ``_LANCZOS_RTOL * |theta|`` over the last
        ``_LANCZOS_EVERY`` steps (or the Krylov space is invariant, when it is exact).
    steps : int
        The products with ``S`` made.
    """
    v = np.random.default_rng(0).standard_normal(n)
    v /= np.linalg.norm(v)
    v_prev = np.zeros(n)
    alphas: list[float] = []
    betas: list[float] = []
    beta = 0.0
    previous = np.inf
    with blas_threads(1):  # spinning BLAS threads make these vector products slower
        for step in range(1, _LANCZOS_MAX_STEPS + 1):
            w = apply(v)
            alpha = float(v @ w)
            w -= alpha * v
            w -= beta * v_prev
            beta = float(np.linalg.norm(w))
            alphas.append(alpha)
            betas.append(beta)
            # an invariant Krylov space (a breakdown) shows no more of S than it has shown
            invariant = bool(beta <= np.finfo(float).eps * abs(alpha))
            if invariant or step % _LANCZOS_EVERY == 0:
                theta = float(scipy.linalg.eigvalsh_tridiagonal(
                    alphas, betas[:-1], select="i", select_range=(0, 0)
                )[0])
                settled = invariant or previous - theta <= _LANCZOS_RTOL * abs(theta)
                if invariant or theta <= tol or (settled and step >= _LANCZOS_MIN_STEPS):
                    break
                previous = theta
            v_prev, v = v, w / beta
    return theta, settled, step


def row_sum_bound(mat: Any) -> float:
    """Return an upper bound of ``||M||_2``: its largest absolute row sum (Gershgorin).

    Each sum of ``k`` terms is rounded down by at most ``k eps`` of itself; the bound is
    raised by twice that, so that it bounds the exact sums (about 1.37x the largest
    eigenvalue of pyMOR's heat example's mass matrix, which its snapshots' Rayleigh
    quotients reach to 0.74 of the bound). Every row holds its positive diagonal entry.
    """
    if sp.issparse(mat):
        sums = np.add.reduceat(np.abs(mat.data), mat.indptr[:-1])
        width = int(np.max(np.diff(mat.indptr)))
    else:
        sums = np.sum(np.abs(mat), axis=1)
        width = mat.shape[1]
    return float(np.max(sums)) * (1.0 + 2.0 * width * float(np.finfo(np.float64).eps))


# the digests of the last sparse matrices found symmetric positive definite
_CHECKED: dict[str, None] = {}
_CHECKED_MAX = 8


def proven_definite(digest: str) -> bool:
    """Whether a sparse matrix of this digest was found symmetric positive definite."""
    return digest in _CHECKED


def remember_definite(digest: str) -> None:
    """Record a sparse matrix found symmetric positive definite (the last few are kept)."""
    _CHECKED.pop(digest, None)
    _CHECKED[digest] = None
    while len(_CHECKED) > _CHECKED_MAX:
        del _CHECKED[next(iter(_CHECKED))]
