"""streamsvd: streaming low-rank basis updates by pairwise rotations.

The method compresses a low-rank expansion ``A = U V^T`` with orthonormal ``U`` towards
its singular value decomposition by sweeps of plane rotations (the function F of the
paper "An efficient quasi-optimal space-time PGD application to frictional contact
mechanics", eqs 5-11, Algorithms 1-3), and absorbs new snapshots into the expansion.
"""

from __future__ import annotations

import logging

from .compress import CompressResult, SweepState, compress
from .errors import (
    ConvergenceError,
    InnerProductMismatchError,
    InputError,
    NonFiniteError,
    ShapeMismatchError,
    SourceError,
    SparseInputError,
    StoreError,
    StoreFormatError,
    StoreLockedError,
    StoreMismatchError,
    StreamSVDError,
)
from .expansion import Expansion
from .gram_schmidt import GramSchmidtResult, orthonormalize, orthonormalize_literal
from .inner import DiagonalInner, Euclidean, InnerProduct, MatrixInner, as_inner
from .rotations import PairDynamics, PairRotation, pair_dynamics, rotate_pair
from .stream import StreamCompressor, UpdateRecord

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "CompressResult",
    "ConvergenceError",
    "DiagonalInner",
    "Euclidean",
    "Expansion",
    "GramSchmidtResult",
    "InnerProduct",
    "InnerProductMismatchError",
    "InputError",
    "MatrixInner",
    "NonFiniteError",
    "PairDynamics",
    "PairRotation",
    "ShapeMismatchError",
    "SourceError",
    "SparseInputError",
    "StoreError",
    "StoreFormatError",
    "StoreLockedError",
    "StoreMismatchError",
    "StreamCompressor",
    "StreamSVDError",
    "SweepState",
    "UpdateRecord",
    "__version__",
    "as_inner",
    "compress",
    "orthonormalize",
    "orthonormalize_literal",
    "pair_dynamics",
    "rotate_pair",
]
