"""Matrices that are known to be hard for SVD algorithms (LAPACK's and Demmel's lists)."""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = ["hard_matrices", "with_spectrum"]

_EPS = np.finfo(np.float64).eps


def with_spectrum(
    s: np.ndarray, n: int, m: int, rng: np.random.Generator
) -> np.ndarray:
    """Return ``Q1 diag(s) Q2^T`` (``n x m``) with Haar-random orthonormal ``Q1, Q2``."""
    k = len(s)
    Q1 = np.linalg.qr(rng.standard_normal((n, k)))[0]
    Q2 = np.linalg.qr(rng.standard_normal((m, k)))[0]
    return (Q1 * s) @ Q2.T


def _kahan(n: int, theta: float = 1.2) -> np.ndarray:
    s, c = np.sin(theta), np.cos(theta)
    R = np.eye(n) - c * np.triu(np.ones((n, n)), 1)
    return np.diag(s ** np.arange(n)) @ R


def hard_matrices(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Return a named collection of hard test matrices (small, dense, float64)."""
    n = 40
    out: dict[str, np.ndarray] = {
        "zero": np.zeros((12, 7)),
        "one_column": rng.standard_normal((15, 1)),
        "one_row": rng.standard_normal((1, 9)),
        "zero_columns": np.zeros((8, 0)),
        "identity": np.eye(n),
        "repeated": with_spectrum(np.array([3.0] * 5 + [1.0] * 5 + [0.5] * 5), 30, 25, rng),
        "arithmetic": with_spectrum(np.linspace(1.0, _EPS, n), 50, n, rng),
        "geometric": with_spectrum(np.logspace(0, -15.5, n), n, 45, rng),
        "cluster_at_eps": with_spectrum(
            np.r_[np.logspace(0, -3, 10), np.full(20, _EPS)], 35, 30, rng
        ),
        "scaled_up": with_spectrum(np.logspace(0, -6, 20), 25, 20, rng) * 1e300,
        "scaled_down": with_spectrum(np.logspace(0, -6, 20), 25, 20, rng) * 1e-300,
        "graded_two_sided": np.diag(np.logspace(0, -8, 30))
        @ rng.standard_normal((30, 30))
        @ np.diag(np.logspace(0, -8, 30)),
        "kahan": _kahan(n),
        "lauchli": np.vstack([np.ones((1, 20)), np.sqrt(_EPS) * np.eye(20)]),
        "hilbert": scipy.linalg.hilbert(n),
        "vandermonde": np.vander(np.linspace(0.0, 1.0, n), 20, increasing=True),
        "rank_deficient_product": rng.standard_normal((45, 6)) @ rng.standard_normal((6, 35)),
        "wide": rng.standard_normal((10, 60)),
        "tall": rng.standard_normal((80, 12)),
    }
    return out
