"""Test kit for users and backends: hard matrices, hypothesis strategies, SVD contract.

``assert_svd_contract`` checks an expansion against LAPACK with LAPACK's own test ratios
(``xGESVD`` tests, ``dchkbd``): every ratio must stay below ``threshold`` (50 by default).
"""

from .contract import assert_svd_contract, svd_ratios
from .matrices import hard_matrices, with_spectrum
from .strategies import low_rank_matrices, rank2_expansions

__all__ = [
    "assert_svd_contract",
    "hard_matrices",
    "low_rank_matrices",
    "rank2_expansions",
    "svd_ratios",
    "with_spectrum",
]
