"""Snapshots and a mass matrix the tests of the block kernels share."""

import numpy as np
import scipy.sparse as sp


def pulse(n, m):
    """Snapshots of a pulse that drifts and widens: nearly collinear columns."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 1.0, m)[np.newaxis, :]
    return np.exp(-((x - 0.2 - 0.6 * t) / (0.05 + 0.05 * t)) ** 2)


def mass(n):
    """The P1 mass matrix of n nodes on [0, 1] (tridiagonal, symmetric positive definite)."""
    h = 1.0 / n
    return sp.diags([np.full(n - 1, h / 6), np.full(n, 2 * h / 3), np.full(n - 1, h / 6)],
                    [-1, 0, 1], format="csr")
