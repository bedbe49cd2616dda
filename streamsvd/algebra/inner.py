"""Inner products on snapshot space.

An expansion ``A = U V^T`` is kept with ``U`` orthonormal in an inner product
``(x | y)_M = x^T M y``. The paper uses the Euclidean one; a finite-element solver
usually wants its mass matrix. Three kinds are offered, all behind one small interface:

* :class:`Euclidean` -- ``M = I``;
* :class:`DiagonalInner` -- ``M = diag(w)`` with positive weights ``w``;
* :class:`MatrixInner` -- any symmetric positive-definite ``M``, dense or scipy.sparse.

Each carries a :attr:`fingerprint` (a SHA-256 of its kind and data) so that a stored basis
can refuse to be continued with another inner product. A compressor's store also keeps
the data of these three kinds (:func:`inner_arrays`, :func:`inner_from_arrays`), so that
it reopens without being given the inner product; :func:`load_inner` reads one from a
file (the command line's ``--inner FILE``).
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from streamsvd._util.threads import blas_threads
from streamsvd._util.validation import as_float_array, check_finite
from streamsvd.errors import InnerProductMismatchError, InputError, ShapeMismatchError

__all__ = [
    "DiagonalInner",
    "Euclidean",
    "InnerProduct",
    "MatrixInner",
    "as_inner",
    "check_same_inner",
    "inner_arrays",
    "inner_from_arrays",
    "load_inner",
]

logger = logging.getLogger(__name__)


@runtime_checkable
class InnerProduct(Protocol):
    """What every inner product offers."""

    @property
    def n(self) -> int | None:
        """Size of the vectors, or None when any size is accepted."""

    @property
    def is_euclidean(self) -> bool:
        """Whether ``M`` is the identity (so ``apply`` returns its argument itself)."""

    @property
    def fingerprint(self) -> str:
        """A SHA-256 hex digest identifying the kind and the data of ``M``."""

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Return ``M @ X``."""

    def gram(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Return ``X^T M Y``."""


class Euclidean:
    """The canonical inner product ``x^T y`` (the paper's choice)."""

    n: int | None = None
    is_euclidean = True
    fingerprint = hashlib.sha256(b"euclidean").hexdigest()

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Return ``X`` itself (``M = I``)."""
        return X

    def gram(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Return ``X^T Y``."""
        return X.T @ Y

    def __repr__(self) -> str:
        return "Euclidean()"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Euclidean)

    def __hash__(self) -> int:
        return hash(self.fingerprint)


class DiagonalInner:
    """The weighted inner product ``x^T diag(w) y`` with positive weights ``w``.

    Parameters
    ----------
    weights : array_like, shape (n,)
        Positive, finite weights (a lumped mass matrix, quadrature weights, ...).
    """

    is_euclidean = False

    def __init__(self, weights: Any) -> None:
        w = as_float_array(weights, "weights", ndim=1, allow_empty=False, copy=True)
        if np.any(w <= 0):
            k = int(np.argmin(w))
            raise InputError(
                f"`weights` must all be > 0 to define an inner product; got weights[{k}] = "
                f"{float(w[k])!r}. Drop the degrees of freedom that carry no weight."
            )
        w.setflags(write=False)
        self.weights = w
        self.n = w.shape[0]
        self.fingerprint = _digest(b"diagonal", w)

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Return ``diag(w) @ X``."""
        return X * self.weights.reshape((-1,) + (1,) * (X.ndim - 1))

    def gram(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Return ``X^T diag(w) Y``."""
        return X.T @ self.apply(Y)

    def __repr__(self) -> str:
        return f"DiagonalInner(n={self.n}, fingerprint={self.fingerprint[:12]})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, DiagonalInner) and other.fingerprint == self.fingerprint

    def __hash__(self) -> int:
        return hash(self.fingerprint)


class MatrixInner:
    """The inner product ``x^T M y`` of a symmetric positive-definite matrix ``M``.

    Parameters
    ----------
    M : array_like or scipy.sparse matrix, shape (n, n)
        Symmetric positive definite (for example a finite-element mass matrix), else
        :class:`~streamsvd.errors.InputError` is raised. Symmetry is checked to
        ``max(1000, w) * eps * max|M|``, ``w`` the most entries in a row (a product with
        ``M`` rounds by that much), and positivity of the diagonal always. Definiteness is
        checked by a Cholesky factorisation when ``M`` is dense; when it is sparse, on
        ``D^-1/2 M D^-1/2`` (``D`` its diagonal, so that the test does not depend on the
        scaling of the unknowns): nothing more when ``M`` is diagonal, an ``LDL^T``
        factorisation (its inertia, exact) up to ``n = 10000``, and above, a Lanczos
        estimate of the smallest eigenvalue from a fixed start (a negative or zero one
        standing apart from the rest of the spectrum is found in a few tens of products
        with ``M``; one at the end of a cluster reaching zero, as a Neumann stiffness
        matrix has, may be missed, which is logged). Zero means at most
        ``n * eps * ||D^-1/2 M D^-1/2||_inf``, singular to working precision as
        :func:`numpy.linalg.matrix_rank` counts.
    """

    is_euclidean = False

    def __init__(self, M: Any) -> None:
        if sp.issparse(M):
            mat: Any = sp.csr_array(M, dtype=np.float64)
            mat.sum_duplicates()
            mat.sort_indices()
            check_finite(mat.data, "M")
        else:
            mat = as_float_array(M, "M", ndim=2, allow_empty=False, copy=True)
        if mat.shape[0] != mat.shape[1]:
            raise ShapeMismatchError(f"`M` must be square; got shape {mat.shape}.")
        _check_symmetric(mat)
        diag = mat.diagonal()
        if np.any(diag <= 0):
            k = int(np.argmin(diag))
            raise InputError(
                f"`M` must be positive definite; got M[{k}, {k}] = {float(diag[k])!r} <= 0."
            )
        # a sparse matrix with nothing off its diagonal (a lumped mass matrix, cell
        # volumes): its positive diagonal makes it definite, and it is applied as weights
        # (the product is exact, and column-major blocks are not copied to row-major as
        # the sparse product needs)
        diagonal = sp.issparse(mat) and mat.nnz == mat.shape[0]
        if not sp.issparse(mat):
            try:
                np.linalg.cholesky(mat)
            except np.linalg.LinAlgError:
                raise InputError(
                    "`M` must be positive definite; its Cholesky factorisation failed. "
                    "Check the matrix (a singular mass matrix needs its constraints removed)."
                ) from None
            mat.setflags(write=False)
            self.fingerprint = _digest(b"dense", mat)
        else:
            if not diagonal:
                _check_sparse_definite(mat, diag)
            self.fingerprint = _digest(
                b"sparse", mat.indptr.astype(np.int64), mat.indices.astype(np.int64), mat.data
            )
        self.matrix = mat
        self.n = mat.shape[0]
        self._weights = diag.reshape(-1, 1) if diagonal else None

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Return ``M @ X``."""
        if self._weights is not None:
            return X * (self._weights if X.ndim == 2 else self._weights[:, 0])
        return np.asarray(self.matrix @ X)

    def gram(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Return ``X^T M Y``."""
        return X.T @ self.apply(Y)

    def __repr__(self) -> str:
        kind = "sparse" if sp.issparse(self.matrix) else "dense"
        return f"MatrixInner(n={self.n}, {kind}, fingerprint={self.fingerprint[:12]})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, MatrixInner) and other.fingerprint == self.fingerprint

    def __hash__(self) -> int:
        return hash(self.fingerprint)


# definiteness of a sparse M (on D^-1/2 M D^-1/2): an exact LDL^T up to this size (its
# fill, in 3-D, costs about a second there), a Lanczos estimate above
_EXACT_MAX_N = 10_000
# the Lanczos estimate: its smallest Ritz value is looked at every _LANCZOS_EVERY steps
# (a divisor of _LANCZOS_MAX_STEPS); it is taken after _LANCZOS_MIN_STEPS (by then an
# eigenvalue apart from the rest has shown) once it moves by at most _LANCZOS_RTOL of
# itself between two looks, else after _LANCZOS_MAX_STEPS, and then logged
_LANCZOS_EVERY = 10
_LANCZOS_MIN_STEPS = 30
_LANCZOS_MAX_STEPS = 150
_LANCZOS_RTOL = 1e-2


def _check_symmetric(mat: Any) -> None:
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


def _check_sparse_definite(mat: sp.csr_array, diag: np.ndarray) -> None:
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
    ``_EXACT_MAX_N``, SuperLU factors ``P S P^T = L U`` with the diagonal as pivots (a
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
    if n <= _EXACT_MAX_N:
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


def _digest(kind: bytes, *arrays: np.ndarray) -> str:
    h = hashlib.sha256(kind)
    for a in arrays:
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def as_inner(inner: Any, n: int | None = None) -> InnerProduct:
    """Normalise the ``inner=`` argument of every public function.

    Parameters
    ----------
    inner : None, InnerProduct, array_like or scipy.sparse matrix
        ``None`` for the Euclidean inner product, a 1-D array of positive weights, a 2-D
        SPD matrix (dense or sparse), or an object implementing :class:`InnerProduct`.
    n : int, optional
        The size of the vectors; checked against the inner product's own size.
    """
    if inner is None:
        out: InnerProduct = Euclidean()
    elif isinstance(inner, Euclidean | DiagonalInner | MatrixInner):
        out = inner
    elif sp.issparse(inner):
        out = MatrixInner(inner)
    elif isinstance(inner, InnerProduct):
        out = inner
    else:
        arr = np.asarray(inner)
        if arr.ndim == 1:
            out = DiagonalInner(arr)
        elif arr.ndim == 2:
            out = MatrixInner(arr)
        else:
            raise InputError(
                "`inner` must be None, a 1-D array of weights, a 2-D SPD matrix or an "
                f"InnerProduct; got an array of shape {arr.shape}."
            )
    if n is not None and out.n is not None and out.n != n:
        raise InnerProductMismatchError(
            f"`inner` acts on vectors of size {out.n}; the snapshots have size {n}. "
            "Pass the matrix that belongs to this mesh."
        )
    return out


def check_same_inner(a: InnerProduct, b: InnerProduct, what: str) -> None:
    """Raise :class:`InnerProductMismatchError` if two inner products differ."""
    if a.fingerprint != b.fingerprint:
        raise InnerProductMismatchError(
            f"`{what}` uses the inner product {b!r}; expected {a!r}, the one of the "
            "current basis. Express both in the same inner product."
        )


def inner_arrays(inner: InnerProduct) -> dict[str, np.ndarray] | None:
    """Return the arrays that rebuild ``inner`` with :func:`inner_from_arrays`.

    Weights are one array, a dense matrix one ``n x n`` array, a sparse matrix its CSR
    ``indptr``, ``indices`` and ``data`` (the indices as float64, exact below 2**53).

    Returns
    -------
    dict of str to numpy.ndarray or None
        Empty for the Euclidean inner product; None for an inner product of another
        class, whose data cannot be stored.
    """
    if isinstance(inner, Euclidean):
        return {}
    if isinstance(inner, DiagonalInner):
        return {"inner_weights": inner.weights}
    if isinstance(inner, MatrixInner):
        mat = inner.matrix
        if not sp.issparse(mat):
            return {"inner_matrix": mat}
        return {
            "inner_indptr": mat.indptr.astype(np.float64),
            "inner_indices": mat.indices.astype(np.float64),
            "inner_data": mat.data,
        }
    return None


def inner_from_arrays(arrays: Mapping[str, np.ndarray]) -> InnerProduct | None:
    """Rebuild the inner product stored by :func:`inner_arrays` (None if none is stored)."""
    if "inner_weights" in arrays:
        return DiagonalInner(arrays["inner_weights"])
    if "inner_matrix" in arrays:
        return MatrixInner(arrays["inner_matrix"])
    if "inner_indptr" in arrays:
        indptr = np.asarray(arrays["inner_indptr"]).astype(np.int64)
        indices = np.asarray(arrays["inner_indices"]).astype(np.int64)
        n = indptr.size - 1
        return MatrixInner(sp.csr_array((arrays["inner_data"], indices, indptr), shape=(n, n)))
    return None


def load_inner(path: str | os.PathLike[str]) -> InnerProduct:
    """Read an inner product from a file.

    Parameters
    ----------
    path : str or os.PathLike
        ``.npy``: a 1-D array of positive weights or a 2-D SPD matrix; ``.npz``: a
        scipy sparse matrix written by :func:`scipy.sparse.save_npz`; ``.mtx``: a Matrix
        Market file (sparse or dense).

    Returns
    -------
    InnerProduct
        Checked as :func:`as_inner` checks an array.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in (".npy", ".npz", ".mtx"):
        raise InputError(
            f"`inner` must be a .npy (weights or a dense matrix), .npz (scipy.sparse."
            f"save_npz) or .mtx (Matrix Market) file; got {p.name!r}."
        )
    if not p.is_file():
        raise InputError(f"`inner` file {p} does not exist. Check the path.")
    try:
        if suffix == ".npy":
            data: Any = np.load(p, allow_pickle=False)
        elif suffix == ".npz":
            data = sp.load_npz(p)
        else:
            import scipy.io

            data = scipy.io.mmread(p)
    except (OSError, ValueError, KeyError, EOFError) as exc:  # EOFError: an empty file
        raise InputError(
            f"`inner` file {p} cannot be read as a {suffix} file ({exc}). A .npz file must "
            "hold a sparse matrix written by scipy.sparse.save_npz."
        ) from None
    return as_inner(data)
