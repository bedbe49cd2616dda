"""The n-sized algebra: inner products and the basis, in memory and out of core.

The backend interface (the Protocols an update needs of the basis) lives in
:mod:`~streamsvd.algebra.interface`; its in-memory implementation in
:mod:`~streamsvd.algebra.memory`, on the growable buffer of :mod:`~streamsvd.algebra.buffer`
(its compactions' columns and images written by :mod:`~streamsvd.algebra.compaction`);
the out-of-core one in :mod:`~streamsvd.algebra.panels`. Inner products are in
:mod:`~streamsvd.algebra.inner` (the checks that a matrix is symmetric positive definite in
:mod:`~streamsvd.algebra.spd`), the Gram products in :mod:`~streamsvd.algebra.blas`.
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
    "Backend": "interface",
    "BasisAlgebra": "interface",
    "BasisBackend": "interface",
    "BasisStaging": "interface",
    "DeferredGram": "interface",
    "BasisBuffer": "buffer",
    "MEMORY_KIND": "memory",
    "MemoryBackend": "memory",
    "MemoryBasis": "memory",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
