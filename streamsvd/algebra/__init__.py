"""The n-sized algebra: inner products and the basis, in memory and out of core.

The basis interface and its in-memory implementation live in :mod:`~streamsvd.algebra.memory`,
the out-of-core one in :mod:`~streamsvd.algebra.panels`.
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "DiagonalInner": "inner",
    "Euclidean": "inner",
    "InnerProduct": "inner",
    "MatrixInner": "inner",
    "as_inner": "inner",
    "check_same_inner": "inner",
    "load_inner": "inner",
    "Backend": "memory",
    "BasisAlgebra": "memory",
    "BasisBackend": "memory",
    "BasisStaging": "memory",
    "DeferredGram": "memory",
    "MEMORY_KIND": "memory",
    "MemoryBackend": "memory",
    "MemoryBasis": "memory",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
