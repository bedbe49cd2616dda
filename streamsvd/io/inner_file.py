"""An inner product read from a file: the command line's ``--inner FILE``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.errors import InputError

__all__ = ["load_inner"]


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
