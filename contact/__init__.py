"""contact: space-time LATIN solvers for quasi-static frictional contact.

The application of the paper "An efficient quasi-optimal space-time PGD application to
frictional contact mechanics": an elastic billet pushed into, then pulled out of, a rigid
conical die (Signorini contact, Coulomb friction), solved over the whole time interval by
the LATIN method in three variants (full field, space-time separated P3, and P3 kept
quasi-optimal by :class:`streamsvd.StreamCompressor`), validated against an independent
step-by-step semi-smooth Newton solver.
"""

from __future__ import annotations

import logging

from .errors import ContactError, ConvergenceError, ProblemError, SolverOptionError
from .globalstage import default_search_direction, indicator
from .latin import METHODS, solve
from .local import local_stage
from .mesh import Mesh
from .pgd import indicator_metric
from .post import LawCheck, SVDModes, check_laws, mac, optimal_rank, svd_modes
from .problem import Problem, billet, block
from .reference import ReferenceResult, reference_solve
from .result import IterationState, LatinResult

logging.getLogger(__name__).addHandler(logging.NullHandler())


def __getattr__(name: str) -> object:
    # the study draws figures: import matplotlib only when it is asked for
    if name == "billet_study":
        from .study import billet_study

        return billet_study
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "METHODS",
    "ContactError",
    "ConvergenceError",
    "IterationState",
    "LatinResult",
    "LawCheck",
    "Mesh",
    "Problem",
    "ProblemError",
    "ReferenceResult",
    "SVDModes",
    "SolverOptionError",
    "billet",
    "billet_study",
    "block",
    "check_laws",
    "default_search_direction",
    "indicator",
    "indicator_metric",
    "local_stage",
    "mac",
    "optimal_rank",
    "reference_solve",
    "solve",
    "svd_modes",
]
