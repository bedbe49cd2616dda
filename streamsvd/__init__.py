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
import importlib.abc
import importlib.machinery
import logging
import sys
import types
from typing import TYPE_CHECKING, Any

from streamsvd.errors import (
    BrokenStateError,
    ConvergenceError,
    FloatRangeError,
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
    from streamsvd.algebra.inner import (
        DiagonalInner,
        Euclidean,
        InnerProduct,
        MatrixInner,
        as_inner,
    )
    from streamsvd.dynamics import DMDResult
    from streamsvd.linalg.compress import CompressResult, SweepState, compress
    from streamsvd.linalg.expansion import Expansion
    from streamsvd.linalg.gram_schmidt import (
        GramSchmidtResult,
        orthonormalize,
        orthonormalize_literal,
    )
    from streamsvd.linalg.rotations import PairDynamics, PairRotation, pair_dynamics, rotate_pair
    from streamsvd.storage import open_storage
    from streamsvd.store import BasisStore, open_store
    from streamsvd.stream.compressor import StreamCompressor, UpdateRecord
    from streamsvd.stream.dynamics import dmd

from streamsvd._version import __version__

logging.getLogger(__name__).addHandler(logging.NullHandler())

# public name -> submodule that defines it
_LAZY = {
    "CompressResult": "linalg.compress",
    "SweepState": "linalg.compress",
    "compress": "linalg.compress",
    "Expansion": "linalg.expansion",
    "GramSchmidtResult": "linalg.gram_schmidt",
    "orthonormalize": "linalg.gram_schmidt",
    "orthonormalize_literal": "linalg.gram_schmidt",
    "DiagonalInner": "algebra.inner",
    "Euclidean": "algebra.inner",
    "InnerProduct": "algebra.inner",
    "MatrixInner": "algebra.inner",
    "as_inner": "algebra.inner",
    "PairDynamics": "linalg.rotations",
    "PairRotation": "linalg.rotations",
    "pair_dynamics": "linalg.rotations",
    "rotate_pair": "linalg.rotations",
    "StreamCompressor": "stream.compressor",
    "dmd": "stream.dynamics",
    "DMDResult": "dynamics",
    "BasisStore": "store",
    "open_store": "store",
    "open_storage": "storage",
    "UpdateRecord": "stream.compressor",
}

# the layers, reachable as attributes (``streamsvd.store``) without importing them first
_SUBPACKAGES = frozenset({
    "algebra", "cli", "dynamics", "engine", "errors", "io", "linalg", "parallel", "plotting",
    "sklearn", "storage", "store", "stream", "testing",
})

# module paths of the flat layout before the layers, kept for one release as aliases of
# their new homes (``import streamsvd.sources`` reads ``streamsvd.io.sources``); a module
# split in the move names its homes in order, and its alias reads each name from the
# first home that has it
_MOVED: dict[str, str | tuple[str, ...]] = {
    "basis": ("algebra.memory", "algebra.interface", "algebra.buffer"),
    "bound": "engine.bound", "estimator": "sklearn.estimator",
    "expansion": "linalg.expansion",
    "gram_schmidt": ("linalg.gram_schmidt", "linalg.extend", "linalg.rejection"),
    "inner": ("algebra.inner", "io.inner_file", "algebra.spd"),
    "locks": ("storage.lockfile", "storage.lease"),
    "panels": "algebra.panels.basis",
    "parallel_tall": ("parallel.tall", "algebra.panels.backend"),
    "parallel_tree": ("parallel.tree", "parallel.spec"),
    "provenance": "io.provenance", "rotations": "linalg.rotations", "rows": "engine.rows",
    "sources": ("io.sources", "io.open", "algebra.panels.lazy", "io.formats"),
    "update": ("engine.update", "engine.state"),
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Import an old module path (:data:`_MOVED`) as a stand-in for its new home.

    The stand-in reads every attribute from the module at the new home, which is left
    as it is (its name, its spec).
    """

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        prefix, _, name = fullname.rpartition(".")
        if prefix != __name__ or name not in _MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: Any) -> None:
        """Use the default module."""

    def exec_module(self, module: types.ModuleType) -> None:
        homes = [importlib.import_module(f"{__name__}.{path}")
                 for path in _homes(module.__name__.rpartition(".")[2])]

        def read(name: str) -> Any:
            for home in homes:
                if hasattr(home, name):
                    return getattr(home, name)
            raise AttributeError(f"module {module.__name__!r} has no attribute {name!r}")

        names = [name for home in homes for name in getattr(home, "__all__", ())]
        vars(module).update(
            __doc__="Moved to " + ", ".join(f":mod:`{home.__name__}`" for home in homes) + ".",
            __all__=list(dict.fromkeys(names)),
            __getattr__=read,
        )


def _homes(old: str) -> tuple[str, ...]:
    """Return the new homes of an old module path (one, or several for a split module)."""
    homes = _MOVED[old]
    return (homes,) if isinstance(homes, str) else homes


sys.meta_path.insert(0, _MovedModules())


def __getattr__(name: str) -> Any:
    """Import a public name (or a layer) of streamsvd on first access."""
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(f".{module}", __name__), name)
        globals()[name] = value  # later look-ups do not come here again
        return value
    if name in _MOVED:  # the new home, or the alias of a module split in the move
        homes = _homes(name)
        return importlib.import_module(f".{homes[0] if len(homes) == 1 else name}", __name__)
    if name in _SUBPACKAGES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | _SUBPACKAGES)


__all__ = [
    "BasisStore",
    "BrokenStateError",
    "CompressResult",
    "DMDResult",
    "ConvergenceError",
    "DiagonalInner",
    "Euclidean",
    "Expansion",
    "FloatRangeError",
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
    "dmd",
    "orthonormalize",
    "open_store",
    "open_storage",
    "orthonormalize_literal",
    "pair_dynamics",
    "rotate_pair",
]
