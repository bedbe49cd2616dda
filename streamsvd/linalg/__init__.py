"""The paper's algorithms over arrays.

Expansions, Algorithm 1 (Gram-Schmidt), the pair rotation F (eqs 5-14) and its
sweeps, Algorithms 2-3 (compression).
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "Expansion": "expansion",
    "BasisExtension": "extend",
    "default_reject_tol": "rejection",
    "extend_basis": "extend",
    "GramSchmidtResult": "gram_schmidt",
    "orthonormalize": "gram_schmidt",
    "orthonormalize_literal": "gram_schmidt",
    "PairDynamics": "rotations",
    "PairRotation": "rotations",
    "SweepStats": "rotations",
    "pair_dynamics": "rotations",
    "rotate_pair": "rotations",
    "sweep_until": "rotations",
    "sweep_literal": "rotations",
    "CompressResult": "compress",
    "SweepState": "compress",
    "fix_signs": "compress",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
