"""Hypothesis strategies for expansions and low-rank matrices."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from streamsvd.linalg.expansion import Expansion
from streamsvd.testing.matrices import with_spectrum

__all__ = ["low_rank_matrices", "rank2_expansions"]


@st.composite
def low_rank_matrices(
    draw: st.DrawFn, *, max_n: int = 40, max_m: int = 30, max_rank: int = 10
) -> np.ndarray:
    """Matrices ``n x m`` of a drawn rank with a drawn geometric or random spectrum."""
    n = draw(st.integers(1, max_n))
    m = draw(st.integers(1, max_m))
    k = draw(st.integers(1, min(n, m, max_rank)))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    decay = draw(st.floats(0.0, 12.0))
    s = np.logspace(0, -decay, k) * draw(st.sampled_from([1.0, 1e-100, 1e100]))
    return with_spectrum(s, n, m, rng)


@st.composite
def rank2_expansions(draw: st.DrawFn, *, max_n: int = 20, max_m: int = 20) -> Expansion:
    """Rank-2 expansions meeting conditions (3): orthonormal u's, ||v1|| >= ||v2|| > 0."""
    n = draw(st.integers(2, max_n))
    m = draw(st.integers(2, max_m))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    U = np.linalg.qr(rng.standard_normal((n, 2)))[0]
    V = rng.standard_normal((m, 2))
    V[:, 1] *= draw(st.floats(1e-3, 1.0))
    norms = np.linalg.norm(V, axis=0)
    if norms[1] > norms[0]:
        V = V[:, ::-1].copy()
    return Expansion(U, V)
