r"""The LATIN global stage shared by the three variants, and the error indicator.

The global stage finds an admissible state ``s = (u, lam)`` -- ``(K u)_f = (C^T L lam)_f``
with the prescribed displacements -- on the descent search direction

.. math:: \lambda - \hat\lambda = -k\,(w - \hat w), \qquad w = C u \qquad (E^-).

Eliminating ``lam`` gives, at every instant, the linear problem

.. math:: A\,u = C^T L (\hat\lambda + k \hat w), \qquad A = K + k\,C^T L C,

with one operator ``A`` for every instant and every iteration: it is factorised once.
Displacements are split as ``u = u_lift + y``: the lift ``u_lift`` is the elastic response
to the prescribed displacements without contact (``(K u_lift)_f = 0``), kept in separated
form, and ``y`` vanishes on the prescribed dofs. Then ``A_ff y_f = G Z`` with
``G = (C^T)_f L`` and ``Z = lam_hat + k w_hat - k w_lift``, ``w_lift = C u_lift``.

Default search direction: ``k = E / h`` with ``h`` the mean depth of the body behind the
contact zone (:func:`default_search_direction`); the effect of this choice is measured by
``bench/bench_contact_scale.py --study k``.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from .errors import ProblemError
from .problem import Problem

__all__ = [
    "BandedCholesky", "GlobalStage", "default_search_direction", "indicator", "indicator_parts",
]


class BandedCholesky:
    """Cholesky factorisation of a sparse SPD matrix in banded storage.

    The rows are renumbered by reverse Cuthill-McKee, then LAPACK's banded Cholesky
    (``pbtrf``) factorises the profile once; each solve is a banded triangular solve
    (``pbtrs``) for all right-hand sides at once. For the structured meshes of this
    package the half-bandwidth is ``2 (nx + 2)``, so this is both exact and much faster
    than a general sparse LU with many right-hand sides.

    Parameters
    ----------
    A : sparse matrix, shape (n, n)
        Symmetric positive definite.
    """

    def __init__(self, A: sp.spmatrix) -> None:
        A = sp.csr_matrix(A)
        self.perm = csgraph.reverse_cuthill_mckee(A, symmetric_mode=True)
        Ap = A[self.perm][:, self.perm].tocoo()
        n = A.shape[0]
        upper = Ap.row <= Ap.col
        bw = int(np.max(Ap.col[upper] - Ap.row[upper])) if n else 0
        ab = np.zeros((bw + 1, n))
        ab[bw + Ap.row[upper] - Ap.col[upper], Ap.col[upper]] = Ap.data[upper]
        try:
            self.cb = sla.cholesky_banded(ab)
        except np.linalg.LinAlgError as exc:
            raise ProblemError(
                "the global operator K + k C^T L C is not positive definite on the free "
                "dofs; check that the prescribed displacements remove every rigid motion."
            ) from exc
        self.bandwidth = bw
        self.nbytes = int(self.cb.nbytes)

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Return ``A^{-1} B`` for a vector or a matrix ``B``."""
        X = np.empty_like(B, dtype=float)
        X[self.perm] = sla.cho_solve_banded((self.cb, False), B[self.perm])
        return X


def default_search_direction(problem: Problem) -> float:
    """Return the default search direction ``k = E / h``.

    ``h = |Omega| / |Gamma_c|`` is the mean depth of the body behind its candidate
    contact zone: the area of the mesh (in its own plane) divided by the length of the
    polyline of the contact nodes. ``E / h`` is the order of magnitude of the stiffness
    of the body seen from the contact zone, the classical LATIN choice. For the billet
    (``h`` about 8.7 mm, close to its mean radius of 8 mm) it is near the best constant
    direction measured (see ``contact/README.md``).
    """
    X = problem.mesh.coords[problem.mesh.quads]
    x, y = X[:, :, 0], X[:, :, 1]
    area = 0.5 * float(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y))
    coords = problem.mesh.coords[problem.contact_nodes]
    length = float(np.sum(np.linalg.norm(np.diff(coords, axis=0), axis=1)))
    if length <= 0.0 or area <= 0.0:
        return problem.E
    return problem.E * length / area


class GlobalStage:
    """Factorised global operator, lift and contact restrictions of one problem.

    Parameters
    ----------
    problem : Problem
    k : float
        Search direction.

    Attributes
    ----------
    bandwidth : int
        Half-bandwidth of the factorised operator after reverse Cuthill-McKee.
    """

    def __init__(self, problem: Problem, k: float) -> None:
        P = problem
        self.problem = P
        self.k = float(k)
        self.free = P.free_dofs
        fixed = P.dirichlet_dofs
        K = P.K.tocsr()
        Kf = K[self.free]
        self.Cf = P.C[:, self.free].tocsr()
        self.Lw = P.L
        self.G = (self.Cf.T @ sp.diags(self.Lw)).tocsr()
        A = Kf[:, self.free] + self.k * (self.G @ self.Cf)
        self.A = A.tocsr()
        self._factor = BandedCholesky(A)
        self.bandwidth = self._factor.bandwidth
        # lift: elastic extension of the separated Dirichlet data (a thin SVD of the data)
        Ud, s, Vdt = np.linalg.svd(P.dirichlet_values, full_matrices=False)
        r = int(np.sum(s > 1e-13 * s[0])) if s.size and s[0] > 0 else 0
        space = np.zeros((P.n, r))
        space[fixed] = Ud[:, :r]
        if r:
            space[self.free] = spla.spsolve(
                Kf[:, self.free].tocsc(), -(Kf[:, fixed] @ Ud[:, :r])
            ).reshape(len(self.free), r)
        Q, Rq = np.linalg.qr(space)
        self.lift_space = Q
        self.lift_time = Vdt[:r].T * s[:r] @ Rq.T
        self.w_lift = (P.C @ self.lift_space) @ self.lift_time.T

    def solve(self, B: np.ndarray) -> np.ndarray:
        """Return ``A_ff^{-1} B`` with the one factorisation."""
        return self._factor.solve(np.asarray(B, dtype=float))

    def rhs_data(self, w_hat: np.ndarray, lam_hat: np.ndarray) -> np.ndarray:
        """Return ``Z = lam_hat + k w_hat - k w_lift`` (2 nc x m); the right side is ``G Z``."""
        return lam_hat + self.k * (w_hat - self.w_lift)

    def tractions(self, w: np.ndarray, w_hat: np.ndarray, lam_hat: np.ndarray) -> np.ndarray:
        """Return ``lam = lam_hat - k (w - w_hat)`` (the direction E^-)."""
        return lam_hat - self.k * (w - w_hat)

    def lift(self) -> np.ndarray:
        """Return the dense lift ``u_lift`` (n x m)."""
        return self.lift_space @ self.lift_time.T


def indicator(
    w: np.ndarray, lam: np.ndarray, w_hat: np.ndarray, lam_hat: np.ndarray,
    L: np.ndarray, k: float,
) -> float:
    r"""Return the LATIN error indicator between ``s = (w, lam)`` and ``s_hat``.

    .. math::

        \eta = \frac{\| s - \hat s \|_k}{\| (s + \hat s) / 2 \|_k}, \qquad
        \| (w, \lambda) \|_k^2 = \sum_{t} \sum_{i} L_i \left( k\, |w_i(t)|^2
        + k^{-1} |\lambda_i(t)|^2 \right),

    an energy-like norm over the contact nodes (normal and tangential components) and the
    instants, with the tributary measures ``L_i``.
    """
    Lc = L[:, None]
    num = np.sum(Lc * (k * (w - w_hat) ** 2 + (lam - lam_hat) ** 2 / k))
    den = np.sum(Lc * (k * (w + w_hat) ** 2 + (lam + lam_hat) ** 2 / k)) / 4.0
    return float(np.sqrt(num / den)) if den > 0 else float(np.sqrt(num))



def indicator_parts(
    w: np.ndarray, lam: np.ndarray, w_hat: np.ndarray, lam_hat: np.ndarray,
    L: np.ndarray, k: float,
) -> tuple[float, float]:
    """Return the indicator ``eta`` of :func:`indicator` and its denominator ``D``.

    ``D = ||(s + s_hat) / 2||_k``; LATIN-PGD's enrichment rule compares the departure of
    its reduced global stage, ``||d||_{M_c} / D``, with ``eta``.
    """
    Lc = L[:, None]
    num = np.sum(Lc * (k * (w - w_hat) ** 2 + (lam - lam_hat) ** 2 / k))
    den = np.sum(Lc * (k * (w + w_hat) ** 2 + (lam + lam_hat) ** 2 / k)) / 4.0
    eta = float(np.sqrt(num / den)) if den > 0 else float(np.sqrt(num))
    return eta, float(np.sqrt(den))
