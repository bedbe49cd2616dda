"""Test kit for users and backends: hard matrices, hypothesis strategies, SVD contract.

``assert_svd_contract`` checks an expansion against LAPACK with LAPACK's own test ratios
(``xGESVD`` tests, ``dchkbd``): every ratio must stay below ``threshold`` (50 by default).
The hypothesis strategies (``low_rank_matrices``, ``rank2_expansions``) need the test
extra ``hypothesis``; they are imported on first use, so the rest of the kit works without
it.
"""

from typing import Any

from streamsvd.testing.contract import assert_svd_contract, svd_ratios
from streamsvd.testing.matrices import hard_matrices, with_spectrum

__all__ = [
    "assert_svd_contract",
    "hard_matrices",
    "low_rank_matrices",
    "rank2_expansions",
    "svd_ratios",
    "with_spectrum",
]

_STRATEGIES = ("low_rank_matrices", "rank2_expansions")


def __getattr__(name: str) -> Any:
    if name in _STRATEGIES:
        from streamsvd.testing import strategies

        return getattr(strategies, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
