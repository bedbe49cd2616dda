"""An inner product in files and in stores.

:func:`load_inner` reads one from a file (the command line's ``--inner FILE``);
:func:`inner_arrays` and :func:`inner_from_arrays` turn the three kinds of
:mod:`streamsvd.algebra.inner` into the arrays a compressor's store keeps and back, so
that a store reopens without being given its inner product.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from streamsvd._util.lazy import lazy_module
from streamsvd.algebra.inner import (
    DiagonalInner,
    Euclidean,
    InnerProduct,
    MatrixInner,
    as_inner,
)
from streamsvd.errors import InputError

if TYPE_CHECKING:
    import scipy.sparse as sp
else:  # a store without a sparse inner product never imports it (0.1 s)
    sp = lazy_module("scipy.sparse", absent={"issparse": lambda x: False})

__all__ = ["inner_arrays", "inner_from_arrays", "load_inner"]


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
