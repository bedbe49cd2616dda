"""Dynamic mode decomposition of a stream, with a residual certificate per eigenvalue.

Plain functions over small arrays: :func:`~streamsvd.dynamics.pairs.pair_positions` and
:func:`~streamsvd.dynamics.pairs.pair_factor` turn the right vectors of an expansion into
the triangular factor of its snapshot pairs; :func:`~streamsvd.dynamics.solve.
dmd_from_pairs` solves the DMD from it in ``O(k^3)`` and certifies each eigenvalue;
:class:`~streamsvd.dynamics.result.DMDResult` holds the answer and forecasts. The facade's
``StreamCompressor.dmd`` and :func:`streamsvd.dmd` call them (docs: theory, DMD).
"""

from streamsvd.dynamics.pairs import PairFactor, pair_factor, pair_positions
from streamsvd.dynamics.result import DMDResult
from streamsvd.dynamics.solve import dmd_from_pairs

__all__ = ["DMDResult", "PairFactor", "dmd_from_pairs", "pair_factor", "pair_positions"]
