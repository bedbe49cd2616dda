"""Inner products on snapshot space.

An expansion ``A = U V^T`` is kept with ``U`` orthonormal in an inner product
``(x | y)_M = x^T M y``. The paper uses the Euclidean one; a finite-element solver
usually wants its mass matrix. Three kinds are offered, all behind one small interface:

* :class:`Euclidean` -- ``M = I``;
* :class:`DiagonalInner` -- ``M = diag(w)`` with positive weights ``w``;
* :class:`MatrixInner` -- any symmetric positive-definite ``M``, dense or scipy.sparse.

Each carries a :attr:`fingerprint` (a SHA-256 of its kind and data) so that a stored basis
can refuse to be continued with another inner product. A compressor's store also keeps
the data of these three kinds, so that it reopens without being given the inner product,
and the command line reads one from a file (``--inner FILE``): both in
:mod:`streamsvd.io.inner_file`. A matrix is checked symmetric positive definite by
:mod:`streamsvd.algebra.spd`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from streamsvd._util.lazy import lazy_module
from streamsvd._util.validation import as_float_array, check_finite
from streamsvd.algebra.spd import (
    EXACT_MAX_N,
    check_sparse_definite,
    check_symmetric,
    proven_definite,
    remember_definite,
    row_sum_bound,
)
from streamsvd.errors import InnerProductMismatchError, InputError, ShapeMismatchError

if TYPE_CHECKING:
    import scipy.sparse as sp
else:  # imported by the first sparse inner product (0.1 s that `streamsvd info` need not pay)
    sp = lazy_module("scipy.sparse", absent={"issparse": lambda x: False})

# the dtypes of the blocks the compiled sparse product reads where they are (float32
# widened exactly, as scipy does)
_KERNEL_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))
_NO_DOTS = np.zeros(0)  # the compiled product's energies, not wanted

__all__ = [
    "DiagonalInner",
    "Euclidean",
    "InnerProduct",
    "MatrixInner",
    "as_inner",
    "check_same_inner",
]


@runtime_checkable
class InnerProduct(Protocol):
    """What every inner product offers.

    The products of this module also give ``norm_bound`` (a bound on ``||M||_2``) and
    ``entries_per_row`` (the multiply-adds of a product per entry of the result, by
    which CholeskyQR chooses between mapping ``M Z`` through its solve and applying ``M``
    again: :func:`streamsvd.linalg.blocks.cholesky_qr_in_place`); an implementation
    without them gets the choices that do not need them.
    """

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
    diagonal = None
    norm_bound = 1.0  # ||M||_2
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


@dataclass(frozen=True)
class Diagonal:
    """A diagonal ``M``: its weights, their square roots, and the weight if all are equal.

    ``X^T M X`` is then ``(W^1/2 X)^T (W^1/2 X)``, a rank-k update with half the flops of
    ``X^T (M X)`` (:func:`streamsvd.algebra.blas.gram`), without the scaled copy when
    every weight is the same (pyMOR's ``l2_product`` of a uniform grid, ``h I``).
    """

    weights: np.ndarray
    roots: np.ndarray
    uniform: float | None

    @classmethod
    def of(cls, weights: np.ndarray) -> Diagonal:
        """Return the description of ``diag(weights)`` (positive weights)."""
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        roots = np.sqrt(w).reshape(-1, 1)
        roots.setflags(write=False)
        same = bool(w.size) and float(w.min()) == float(w.max())
        return cls(weights=w, roots=roots, uniform=float(w[0]) if same else None)


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
        self.diagonal = Diagonal.of(w)
        self.norm_bound = float(np.max(w))  # ||M||_2, exactly
        self.entries_per_row = 1.0  # what a product costs per entry of the result

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
        digest = (_digest(b"sparse", mat.indptr.astype(np.int64), mat.indices.astype(np.int64),
                          mat.data) if sp.issparse(mat) else None)
        # a sparse matrix proven definite before (the same entries, by their digest) is
        # not factorised again: a compressor made per trajectory or per target reuses it
        checked = digest is not None and proven_definite(digest)
        if not checked:
            check_symmetric(mat)
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
            if not diagonal and not checked:
                check_sparse_definite(mat, diag)
            assert digest is not None
            self.fingerprint = digest
            if mat.shape[0] <= EXACT_MAX_N:  # proven definite (above: estimated, logged)
                remember_definite(digest)
        self.matrix = mat
        self.n = mat.shape[0]
        self.norm_bound = row_sum_bound(mat)
        # what a product costs per entry of the result (multiply-adds)
        self.entries_per_row = (mat.nnz if sp.issparse(mat) else mat.size) / max(self.n, 1)
        self._weights = diag.reshape(-1, 1) if diagonal else None
        self.diagonal = Diagonal.of(diag) if diagonal else None
        # the CSR arrays of a sparse M, for the compiled product with a column-major block
        self._csr = ((mat.indptr.astype(np.int64), mat.indices.astype(np.int64), mat.data)
                     if sp.issparse(mat) and not diagonal else None)

    def apply(self, X: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Return ``M @ X`` (written into ``out``, of the shape of ``X``, when given).

        A sparse ``M`` times a column-major block of two or more columns of float64 or
        float32 goes through :func:`~streamsvd.algebra.sparse_kernels.csr_times_columns`,
        which reads the columns where they are (scipy's product copies the block to
        row-major and back; float32 widened first), with the same digits.
        """
        return self._apply(X, out, _NO_DOTS)

    def apply_with_energies(self, X: np.ndarray, out: np.ndarray | None = None
                            ) -> tuple[np.ndarray, np.ndarray]:
        """Return ``M @ X`` (as :meth:`apply`) and the columns' energies ``x_c^T M x_c``.

        The compiled sparse product measures them on each group of columns right after
        writing it (5101 x 91, pyMOR's heat example: the block is not read again);
        otherwise they are summed after the product.
        """
        if self._kernel_takes(X):
            dots = np.zeros(X.shape[1])
            return self._apply(X, out, dots), dots
        MX = self._apply(X, out, _NO_DOTS)
        return MX, np.einsum("ij,ij->j", X, MX)

    def _kernel_takes(self, X: np.ndarray) -> bool:
        """Whether the compiled sparse product reads ``X`` where it is."""
        return (self._csr is not None and X.ndim == 2 and X.shape[1] >= 2
                and X.dtype in _KERNEL_DTYPES and X.flags.f_contiguous)

    def _apply(self, X: np.ndarray, out: np.ndarray | None, dots: np.ndarray) -> np.ndarray:
        """``M @ X`` into ``out``; the compiled product also fills ``dots`` (if not empty)."""
        if self._weights is not None:
            weights = self._weights if X.ndim == 2 else self._weights[:, 0]
            if out is not None and not np.shares_memory(out, X):
                return np.multiply(X, weights, out=out)
            MX = X * weights
        elif self._kernel_takes(X):
            from streamsvd.algebra.sparse_kernels import csr_times_columns

            if out is None or not out.flags.f_contiguous or np.shares_memory(out, X):
                target = np.empty(X.shape, order="F")
            else:
                target = out
            assert self._csr is not None
            indptr, indices, data = self._csr
            csr_times_columns(indptr, indices, data, X, target, dots)
            if target is out:
                return out
            MX = target
        else:
            MX = np.asarray(self.matrix @ X)
        if out is None:
            return MX
        out[...] = MX
        return out

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
