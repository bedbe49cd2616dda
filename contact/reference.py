r"""An independent step-by-step solver: semi-smooth Newton on the Alart-Curnier equations.

At each instant ``t_k`` the unknowns are the free displacements ``u_f`` and the contact
tractions ``lam = (lam_N, lam_T)``. With ``w = C u``, ``g = gaps - w_N``,
``dw_T = w_T - w_T(t_{k-1})`` and an augmentation ``r > 0``, the equations are

.. math::

    R_u &= (K u - C^T L \lambda)_f = 0, \\
    \Phi_N &= \lambda_N - \min(0, \lambda_N + r g) = 0, \\
    \Phi_T &= \lambda_T - \mathrm{proj}_{[-b, b]}(\lambda_T - r\, dw_T) = 0,
    \quad b = \mu \max(0, -(\lambda_N + r g)),

whose solutions are exactly the states satisfying equilibrium, Signorini and the
implicit Coulomb law of :mod:`contact.problem`. Newton's method uses a generalised
Jacobian (the active sets are read from the current iterate), one sparse LU per Newton
step, and a backtracking line search on the merit ``(||R_u||^2 + ||L Phi||^2) / 2``.

This module shares nothing with the LATIN stages except :class:`contact.problem.Problem`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ._threads import blas_threads as limit_blas_threads
from .errors import ConvergenceError, SolverOptionError
from .problem import Problem

__all__ = ["ReferenceResult", "reference_solve"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ReferenceResult:
    """Solution of :func:`reference_solve`.

    Attributes
    ----------
    u : ndarray, shape (n, m)
        Displacements at every instant.
    lam : ndarray, shape (2 nc, m)
        Contact tractions (normal rows, then tangential rows).
    w : ndarray, shape (2 nc, m)
        Contact displacements ``C u``.
    newton_iterations : ndarray of int, shape (m,)
        Newton steps taken at each instant.
    cpu_time : float
        Process time of the whole solve (s).
    """

    u: np.ndarray
    lam: np.ndarray
    w: np.ndarray
    newton_iterations: np.ndarray
    cpu_time: float


def reference_solve(
    problem: Problem,
    *,
    tol: float = 1e-12,
    max_newton: int = 60,
    augmentation: float | None = None,
    blas_threads: int | None = 1,
) -> ReferenceResult:
    """Solve the problem instant after instant by semi-smooth Newton.

    Parameters
    ----------
    problem : Problem
    tol : float
        Stop an instant when ``||R_u|| + ||L Phi|| <= tol * s``, with the force scale
        ``s = max(||K_fD u_D||, ||C_f^T L lam||)`` (the load and the contact forces).
    max_newton : int
        Newton steps allowed per instant.
    augmentation : float, optional
        ``r`` of the Alart-Curnier functions; by default ``E`` over the mean distance
        between contact nodes.
    blas_threads : int or None
        BLAS threads during the solve (None leaves the thread pool alone).

    Returns
    -------
    ReferenceResult

    Raises
    ------
    ConvergenceError
        When an instant does not converge; ``.result`` holds the instants solved so far.
    """
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise SolverOptionError(f"`tol` must be a positive number; got {tol!r}.")
    with limit_blas_threads(blas_threads):
        return _reference_solve(problem, tol, max_newton, augmentation)


def _reference_solve(
    problem: Problem, tol: float, max_newton: int, augmentation: float | None
) -> ReferenceResult:
    t0 = time.process_time()
    P = problem
    nc, m = P.nc, P.m
    free, fixed = P.free_dofs, P.dirichlet_dofs
    nf = len(free)
    K = P.K.tocsr()
    Kff = K[free][:, free].tocsc()
    KfD = K[free][:, fixed]
    Cf = P.C[:, free].tocsr()
    CD = P.C[:, fixed].tocsr()
    Lw = P.L
    CtL = (Cf.T @ sp.diags(Lw)).tocsr()
    if augmentation is None:
        coords = P.mesh.coords[P.contact_nodes]
        spacing = np.mean(np.linalg.norm(np.diff(coords, axis=0), axis=1)) if nc > 1 else 1.0
        augmentation = P.E / spacing
    r = float(augmentation)
    g0, mu = P.gaps, P.mu
    elastic = spla.splu(Kff)

    U = np.zeros((P.n, m))
    LAM = np.zeros((2 * nc, m))
    W = np.zeros((2 * nc, m))
    its = np.zeros(m, dtype=int)
    uf = np.zeros(nf)
    lam = np.zeros(2 * nc)
    wT_prev = np.zeros(nc)
    uD_prev = np.zeros(len(fixed))

    for k in range(m):
        uD = P.dirichlet_values[:, k]
        # predictor: the previous state plus the elastic response to the new data
        uf = uf - elastic.solve(KfD @ (uD - uD_prev))
        wD = CD @ uD
        fD = KfD @ uD
        scale = max(float(np.linalg.norm(fD)), float(np.linalg.norm(CtL @ lam)), 1e-300)

        step_data = _Step(Kff, CtL, Cf, nc, r, mu, g0, wD, fD, wT_prev)
        residual = step_data.residual

        for it in range(max_newton + 1):
            Ru, Phi, active, stick, y = residual(uf, lam)
            res = np.linalg.norm(Ru) + np.linalg.norm(Lw * Phi)
            scale = max(scale, float(np.linalg.norm(CtL @ lam)))
            if res <= tol * scale:
                break
            if it == max_newton:
                partial = ReferenceResult(U[:, :k], LAM[:, :k], W[:, :k], its[:k],
                                          time.process_time() - t0)
                raise ConvergenceError(
                    f"Newton did not converge at instant {k} (t = {P.times[k]:.4g}) within "
                    f"`max_newton` = {max_newton} steps: residual {res:.3e}, target "
                    f"{tol * scale:.3e}. Increase `max_newton` or `tol`.",
                    partial,
                )
            J = _jacobian(Kff, CtL, Cf, nc, r, mu, active, stick, np.sign(y))
            step = spla.splu(J.tocsc()).solve(-np.concatenate([Ru, Phi]))
            du, dl = step[:nf], step[nf:]
            merit = 0.5 * (Ru @ Ru + (Lw * Phi) @ (Lw * Phi))
            alpha = 1.0
            while True:
                Ru2, Phi2, *_ = residual(uf + alpha * du, lam + alpha * dl)
                merit2 = 0.5 * (Ru2 @ Ru2 + (Lw * Phi2) @ (Lw * Phi2))
                if merit2 <= (1 - 1e-4 * alpha) * merit or alpha < 1e-6:
                    break
                alpha *= 0.5
            uf = uf + alpha * du
            lam = lam + alpha * dl
        its[k] = it
        u = np.zeros(P.n)
        u[free] = uf
        u[fixed] = uD
        U[:, k] = u
        LAM[:, k] = lam
        W[:, k] = P.C @ u
        wT_prev = W[nc:, k]
        uD_prev = uD
    cpu = time.process_time() - t0
    log.info("reference solve: %d instants, %d Newton steps, %.3f s", m, its.sum(), cpu)
    return ReferenceResult(U, LAM, W, its, cpu)


@dataclass(frozen=True, eq=False)
class _Step:
    """Data of one instant; :meth:`residual` evaluates the Alart-Curnier equations."""

    Kff: sp.spmatrix
    CtL: sp.spmatrix
    Cf: sp.csr_matrix
    nc: int
    r: float
    mu: float
    g0: np.ndarray
    wD: np.ndarray
    fD: np.ndarray
    wT_prev: np.ndarray

    def residual(self, uf: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, ...]:
        """Return ``R_u``, ``Phi``, the active and stick masks and the stick trial ``y``."""
        nc, r = self.nc, self.r
        w = self.Cf @ uf + self.wD
        lN, lT = lam[:nc], lam[nc:]
        aug = lN + r * (self.g0 - w[:nc])
        active = aug < 0
        b = self.mu * np.maximum(0.0, -aug)
        y = lT - r * (w[nc:] - self.wT_prev)
        stick = np.abs(y) <= b
        Ru = self.Kff @ uf + self.fD - self.CtL @ lam
        PhiN = lN - np.minimum(0.0, aug)
        PhiT = lT - np.clip(y, -b, b)
        return Ru, np.concatenate([PhiN, PhiT]), active, stick, y


def _jacobian(
    Kff: sp.spmatrix,
    CtL: sp.spmatrix,
    Cf: sp.csr_matrix,
    nc: int,
    r: float,
    mu: float,
    active: np.ndarray,
    stick: np.ndarray,
    sgn: np.ndarray,
) -> sp.spmatrix:
    """Generalised Jacobian of ``(R_u, Phi_N, Phi_T)`` with respect to ``(u_f, lam)``."""
    CN, CT = Cf[:nc], Cf[nc:]
    a = active.astype(float)
    # Phi_N: active -> -r g (d/du = r C_N); inactive -> lam_N
    dN_du = sp.diags(r * a) @ CN
    dN_dlN = sp.diags(1.0 - a)
    # Phi_T: stick (and active) -> r dw_T; slip -> lam_T - b sgn(y), b = -mu (lam_N + r g)
    st = (stick & active).astype(float)
    sl = (~stick & active).astype(float)
    dT_du = sp.diags(r * st) @ CT - sp.diags(mu * r * sl * sgn) @ CN
    dT_dlN = sp.diags(mu * sl * sgn)
    dT_dlT = sp.diags(1.0 - st)
    Z = sp.csr_matrix((nc, nc))
    return sp.bmat(
        [
            [Kff, -CtL[:, :nc], -CtL[:, nc:]],
            [dN_du, dN_dlN, Z],
            [dT_du, dT_dlN, dT_dlT],
        ],
        format="csc",
    )
