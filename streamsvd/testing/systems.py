"""Linear systems with known eigenvalues, and a batch DMD to compare a stream with.

:func:`normal_system` builds ``x_(j+1) = A x_j`` with ``A = Q D Q^T`` normal, ``D``
block diagonal (2 x 2 rotations scaled by a decay, and real decays), embedded in
``R^n`` by a random orthonormal ``Q``; :func:`batch_dmd` is Schmid's (projected) DMD of
a snapshot matrix computed with numpy, the reference of the tests and benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LinearSystem", "batch_dmd", "match_eigenvalues", "normal_system"]


@dataclass(frozen=True, eq=False)
class LinearSystem:
    """A normal linear system: its operator's eigenvalues, basis and small matrix."""

    eigenvalues: np.ndarray  # (k,) complex, those of D
    Q: np.ndarray  # (n, k) orthonormal
    D: np.ndarray  # (k, k) real, normal

    def trajectory(self, x0_coords: np.ndarray, m: int, *, noise: float = 0.0,
                   rng: np.random.Generator | None = None) -> np.ndarray:
        """Return ``m`` snapshots ``Q D^j z0`` (``n x m``), plus noise of that std."""
        k = self.D.shape[0]
        Z = np.empty((k, m))
        z = np.asarray(x0_coords, dtype=np.float64)
        for j in range(m):
            Z[:, j] = z
            z = self.D @ z
        X = self.Q @ Z
        if noise:
            assert rng is not None
            X = X + noise * rng.standard_normal(X.shape)
        return X

    def apply(self, X: np.ndarray) -> np.ndarray:
        """Return ``A X`` with ``A = Q D Q^T``."""
        return self.Q @ (self.D @ (self.Q.T @ X))


def normal_system(n: int, radii: np.ndarray, angles: np.ndarray,
                  rng: np.random.Generator, *, real: np.ndarray | None = None) -> LinearSystem:
    """Return a normal system with eigenvalues ``r e^(+-i theta)`` and ``real`` ones."""
    blocks, lam = [], []
    for r, t in zip(radii, angles, strict=True):
        c, s = np.cos(t), np.sin(t)
        blocks.append(r * np.array([[c, -s], [s, c]]))
        lam += [r * np.exp(1j * t), r * np.exp(-1j * t)]
    for x in () if real is None else real:
        blocks.append(np.array([[x]]))
        lam.append(complex(x))
    k = sum(b.shape[0] for b in blocks)
    D = np.zeros((k, k))
    i = 0
    for b in blocks:
        D[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    Q, _ = np.linalg.qr(rng.standard_normal((n, k)))
    return LinearSystem(np.array(lam), Q, D)


def batch_dmd(X: np.ndarray, *, rank: int | None = None, Y: np.ndarray | None = None
              ) -> np.ndarray:
    """Return the eigenvalues of Schmid's DMD of ``x_(j+1) ~ A x_j`` over ``X``'s columns.

    ``Y`` (optional) holds the second snapshots of the pairs, ``X`` then the first ones.
    ``rank``: the SVD of the first snapshots is cut to it (default: numerical rank).
    """
    X0, X1 = (X[:, :-1], X[:, 1:]) if Y is None else (X, Y)
    U, s, Wt = np.linalg.svd(X0, full_matrices=False)
    r = int(np.count_nonzero(s > max(X0.shape) * np.finfo(float).eps * s[0]))
    if rank is not None:
        r = min(r, rank)
    A = U[:, :r].T @ X1 @ Wt[:r].T / s[:r]
    return np.linalg.eigvals(A)


def match_eigenvalues(found: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Return, for each found eigenvalue, the distance to the nearest true one."""
    found, true = np.asarray(found, dtype=complex), np.asarray(true, dtype=complex)
    return np.min(np.abs(found[:, None] - true[None, :]), axis=1)
