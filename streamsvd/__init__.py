"""streamsvd: streaming low-rank basis updates by pairwise rotations.

The method compresses a low-rank expansion ``A = U V^T`` with orthonormal ``U`` towards
its singular value decomposition by sweeps of plane rotations (the function F of the
paper "An efficient quasi-optimal space-time PGD application to frictional contact
mechanics", eqs 5-11, Algorithms 1-3), and absorbs new snapshots into the expansion.

The public names below are imported on first use (PEP 562 module ``__getattr__``), so
that ``import streamsvd`` and the command line's ``--help`` do not load numpy, numba,
zarr or dask before they are needed. The exception classes are light and imported at
once.
"""

from __future__ import annotations

import importlib
import logging
import sys
import types
from typing import TYPE_CHECKING, Any

from .errors import (
    BrokenStateError,
    ConvergenceError,
    InnerProductMismatchError,
    InputError,
    NonFiniteError,
    OptionalDependencyError,
    ShapeMismatchError,
    SourceError,
    SparseInputError,
    StoreError,
    StoreFormatError,
    StoreLockedError,
    StoreMismatchError,
    StreamSVDError,
)

if TYPE_CHECKING:
    from .compress import CompressResult, SweepState, compress
    from .expansion import Expansion
    from .gram_schmidt import GramSchmidtResult, orthonormalize, orthonormalize_literal
    from .inner import DiagonalInner, Euclidean, InnerProduct, MatrixInner, as_inner
    from .rotations import PairDynamics, PairRotation, pair_dynamics, rotate_pair
    from .storage import open_storage
    from .store import BasisStore, open_store
    from .stream import StreamCompressor, UpdateRecord

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

# public name -> submodule that defines it
_LAZY = {
    "CompressResult": "compress",
    "SweepState": "compress",
    "compress": "compress",
    "Expansion": "expansion",
    "GramSchmidtResult": "gram_schmidt",
    "orthonormalize": "gram_schmidt",
    "orthonormalize_literal": "gram_schmidt",
    "DiagonalInner": "inner",
    "Euclidean": "inner",
    "InnerProduct": "inner",
    "MatrixInner": "inner",
    "as_inner": "inner",
    "PairDynamics": "rotations",
    "PairRotation": "rotations",
    "pair_dynamics": "rotations",
    "rotate_pair": "rotations",
    "StreamCompressor": "stream",
    "BasisStore": "store",
    "open_store": "store",
    "open_storage": "storage",
    "UpdateRecord": "stream",
}

# submodules reachable as attributes (``streamsvd.store``) without importing them first
_SUBMODULES = frozenset({
    "basis", "bound", "cli", "compress", "errors", "estimator", "expansion",
    "gram_schmidt", "inner", "locks", "panels", "parallel", "parallel_tall",
    "parallel_tree", "plotting", "provenance", "rotations", "rows", "sources", "storage",
    "store", "stream", "testing", "update",
})


def __getattr__(name: str) -> Any:
    """Import a public name (or a submodule) of streamsvd on first access."""
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(f".{module}", __name__), name)
        globals()[name] = value  # later look-ups do not come here again
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | _SUBMODULES)


class _Package(types.ModuleType):
    """The package's module type: keeps a public function named like its submodule.

    Importing the submodule ``streamsvd.compress`` (which any module using it does)
    binds the module on the package as ``compress``; the public name ``compress`` is the
    function, as it was when the package imported it eagerly, so the function is bound
    instead.
    """

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, types.ModuleType) and _LAZY.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ = [
    "BasisStore",
    "BrokenStateError",
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
    "OptionalDependencyError",
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
    "open_store",
    "open_storage",
    "orthonormalize_literal",
    "pair_dynamics",
    "rotate_pair",
]
