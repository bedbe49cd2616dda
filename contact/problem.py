"""The discrete frictional contact problem and the two scenes built on it.

A :class:`Problem` holds plain arrays only, so that any solution can be checked
independently of the solvers of this package:

* ``K`` (n x n, sparse): the stiffness matrix;
* ``C`` (2 nc x n, sparse): ``w = C u`` stacks the normal displacements ``w_N = n_i . u``
  of the ``nc`` contact nodes, then their tangential displacements ``w_T = t_i . u``;
* ``weights`` (nc): tributary measures ``w_i = int N_i ds`` (times ``r`` when
  axisymmetric), so that contact tractions ``lam`` act on the body as the nodal forces
  ``C^T diag(weights, weights) lam``;
* ``gaps`` (nc): initial normal gaps ``g_i`` (``w_N <= g_i`` is non-penetration);
* ``dirichlet_dofs`` (nD) and ``dirichlet_values`` (nD x m): prescribed displacements at
  every instant; there are no other loads;
* ``times`` (m): the time grid, ``mu``: the Coulomb coefficient.

The discrete laws at contact node ``i`` and instant ``t_k`` (tractions are those of the
rigid obstacle on the body, ``n_i`` points from the body into the obstacle):

* Signorini: ``g_i - w_N >= 0``, ``lam_N <= 0``, ``lam_N (g_i - w_N) = 0``;
* Coulomb (implicit Euler): with the slip increment ``dw_T = w_T(t_k) - w_T(t_{k-1})``
  (``w_T(t_{-1}) = 0``, the undeformed state), ``|lam_T| <= -mu lam_N``; ``dw_T = 0``
  when ``|lam_T| < -mu lam_N``; otherwise ``dw_T = -beta lam_T`` with ``beta >= 0``;
* equilibrium: ``(K u - C^T L lam)_f = 0`` on the free dofs ``f`` and
  ``u_D = dirichlet_values``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp

from .errors import ProblemError
from .fem import boundary_weights, contact_operator, stiffness
from .mesh import Mesh, mapped_grid, rectangle

__all__ = ["Problem", "billet", "block"]


@dataclass(frozen=True, eq=False)
class Problem:
    """A discrete quasi-static frictional contact problem against a rigid obstacle.

    See the module docstring for the meaning of every array and for the laws.

    Parameters
    ----------
    mesh : Mesh
        The quadrangle mesh (for post-processing).
    K : sparse matrix, shape (n, n)
        Stiffness matrix.
    C : sparse matrix, shape (2 nc, n)
        Contact operator: normal rows first, then tangential rows.
    weights, gaps : ndarray, shape (nc,)
        Tributary measures (positive) and initial normal gaps (non-negative).
    mu : float
        Coulomb friction coefficient.
    dirichlet_dofs : ndarray of int, shape (nD,)
    dirichlet_values : ndarray, shape (nD, m)
    times : ndarray, shape (m,)
        Increasing instants.
    contact_nodes : ndarray of int, shape (nc,)
    normals, tangents : ndarray, shape (nc, 2)
    E, nu : float
        Young's modulus and Poisson's ratio.
    axisymmetric : bool
        Whether ``K`` and ``weights`` are per radian of an axisymmetric body.
    info : dict
        Free-form description of the scene (dimensions, loading), JSON-serialisable.
    """

    mesh: Mesh
    K: sp.csr_matrix
    C: sp.csr_matrix
    weights: np.ndarray
    gaps: np.ndarray
    mu: float
    dirichlet_dofs: np.ndarray
    dirichlet_values: np.ndarray
    times: np.ndarray
    contact_nodes: np.ndarray
    normals: np.ndarray
    tangents: np.ndarray
    E: float
    nu: float
    axisymmetric: bool
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = 2 * self.mesh.n_nodes
        nc = len(self.contact_nodes)
        m = len(self.times)
        if self.K.shape != (n, n):
            raise ProblemError(f"`K` must be {n} x {n} (2 dofs per node); got {self.K.shape}.")
        if self.C.shape != (2 * nc, n):
            raise ProblemError(
                f"`C` must be {2 * nc} x {n} (normal then tangential rows); got {self.C.shape}."
            )
        for name in ("weights", "gaps"):
            if np.shape(getattr(self, name)) != (nc,):
                raise ProblemError(
                    f"`{name}` must have one entry per contact node ({nc}); got shape "
                    f"{np.shape(getattr(self, name))}."
                )
        if np.any(self.weights <= 0):
            raise ProblemError("`weights` must be positive; got a non-positive entry.")
        if np.any(self.gaps < 0):
            raise ProblemError(
                f"`gaps` must be non-negative (no initial penetration); got min "
                f"{self.gaps.min():.3g}."
            )
        if not self.mu >= 0:
            raise ProblemError(f"`mu` must be non-negative; got {self.mu}.")
        if m < 1 or np.any(np.diff(self.times) <= 0):
            raise ProblemError("`times` must be a non-empty increasing grid.")
        nD = len(self.dirichlet_dofs)
        if self.dirichlet_values.shape != (nD, m):
            raise ProblemError(
                f"`dirichlet_values` must be {nD} x {m} (dofs x instants); got "
                f"{self.dirichlet_values.shape}."
            )
        if len(np.unique(self.dirichlet_dofs)) != nD:
            raise ProblemError("`dirichlet_dofs` must not repeat a dof.")

    @property
    def n(self) -> int:
        """Number of displacement dofs."""
        return int(self.K.shape[0])

    @property
    def m(self) -> int:
        """Number of instants."""
        return int(len(self.times))

    @property
    def nc(self) -> int:
        """Number of contact nodes."""
        return int(len(self.contact_nodes))

    @property
    def free_dofs(self) -> np.ndarray:
        """Dofs that are not prescribed, increasing."""
        mask = np.ones(self.n, dtype=bool)
        mask[self.dirichlet_dofs] = False
        return np.flatnonzero(mask)

    @property
    def CN(self) -> sp.csr_matrix:
        """Normal rows of ``C`` (nc x n)."""
        return self.C[: self.nc]

    @property
    def CT(self) -> sp.csr_matrix:
        """Tangential rows of ``C`` (nc x n)."""
        return self.C[self.nc :]

    @property
    def L(self) -> np.ndarray:
        """``diag(weights, weights)`` as a vector of length 2 nc."""
        return np.concatenate([self.weights, self.weights])

    def summary(self) -> dict[str, Any]:
        """Return the sizes and the scene description as a JSON-serialisable dict."""
        return {
            "dofs": self.n,
            "free_dofs": int(len(self.free_dofs)),
            "contact_nodes": self.nc,
            "instants": self.m,
            "dt": float(self.times[1] - self.times[0]) if self.m > 1 else None,
            "E": self.E,
            "nu": self.nu,
            "mu": self.mu,
            "axisymmetric": self.axisymmetric,
            **self.info,
        }


def _check_positive_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ProblemError(f"`{name}` must be a positive integer; got {value!r}.")
    return int(value)


def _time_grid(T: float, dt: float) -> np.ndarray:
    if not (dt > 0 and dt <= T):
        raise ProblemError(f"`dt` must be in (0, {T}]; got {dt!r}.")
    steps = round(T / dt)
    if abs(steps * dt - T) > 1e-9 * T:
        raise ProblemError(f"`dt` must divide the time interval {T}; got dt={dt!r}.")
    return np.linspace(0.0, T, steps + 1)


def billet(
    *,
    refine: int = 1,
    dt: float = 5e-3,
    radius: float = 6.0,
    height: float = 45.0,
    die_angle: float = 5.0,
    gap: float = 0.012,
    push: float = 0.12,
    pull: float = 0.08,
    E: float = 68.86e3,
    nu: float = 0.32,
    mu: float = 0.1,
) -> Problem:
    """Return the aluminium billet pushed into, then pulled out of, a rigid conical die.

    Units are mm, MPa, N (per radian) and s.

    **Kinematics: axisymmetric.** A round billet in a conical die is a body of revolution
    loaded symmetrically, so the axisymmetric model is the faithful 2D reduction: the
    hoop strain ``u_r / r`` is what makes a cone squeeze a billet. Plane strain would
    model a prismatic bar in a wedge-shaped channel, a different scene.

    **Geometry** (the paper does not give dimensions). The billet is ``height`` tall with
    radius ``radius`` at its bottom face. The die wall is the cone
    ``r = radius + z tan(die_angle)`` opening upwards, with a 5 degree wall. The billet
    side follows the wall with a slight initial normal gap growing linearly from 0 at the
    bottom node to ``gap`` at the top candidate node, so contact starts at the bottom and
    the contact zone climbs the wall as the billet is pushed in, then recedes during the
    extraction. The candidate nodes are the side nodes below ``41 / 45`` of the height
    (the die is shorter than the billet).

    **Mesh.** ``3 refine`` x ``45 refine`` Q1 elements (radial x axial): 4 x 46 nodes,
    368 dofs and 42 contact nodes by default, as in the paper.

    **Loading.** The axis is held radially (``u_r = 0``); the top face has a prescribed
    axial displacement ``-d(t)`` (its radial displacement is free), with ``d`` piecewise
    linear from 0 to ``push`` at ``t = 0.5`` then to ``-pull`` at ``t = 1``: pushed into
    the die, then extracted until it leaves it. The time grid is ``[0, 1]`` with step
    ``dt`` (201 instants by default).

    Parameters
    ----------
    refine : int
        Mesh refinement factor in both directions.
    dt : float
        Time step (must divide 1).
    radius, height : float
        Billet radius at the bottom face and height (mm).
    die_angle : float
        Angle between the die wall and the axis (degrees).
    gap : float
        Initial normal gap at the topmost candidate node (mm).
    push, pull : float
        Largest insertion and final extraction of the top face (mm).
    E, nu, mu : float
        Young's modulus (MPa), Poisson's ratio and Coulomb coefficient.

    Returns
    -------
    Problem
    """
    refine = _check_positive_int(refine, "refine")
    times = _time_grid(1.0, dt)
    nr, nz = 3 * refine, 45 * refine
    alpha = np.deg2rad(die_angle)
    z_c = height * 41 / 45
    cos, sin, tan = np.cos(alpha), np.sin(alpha), np.tan(alpha)

    def side(z: np.ndarray) -> np.ndarray:
        return radius + z * tan - gap * (z / z_c) / cos

    mesh = mapped_grid(nr, nz, height, side)
    K = stiffness(mesh, E, nu, axisymmetric=True)
    n = 2 * mesh.n_nodes
    nodes = mesh.column(nr)[: 41 * refine + 1]
    z = mesh.coords[nodes, 1]
    normals = np.tile([cos, -sin], (len(nodes), 1))
    tangents = np.tile([sin, cos], (len(nodes), 1))
    C = contact_operator(n, nodes, normals, tangents)
    weights = boundary_weights(mesh.coords, nodes, axisymmetric=True)
    # distance to the die wall measured along its normal
    gaps = np.maximum((radius + z * tan - mesh.coords[nodes, 0]) * cos, 0.0)

    d = np.interp(times, [0.0, 0.5, 1.0], [0.0, push, -pull])
    axis = 2 * mesh.column(0)
    top = 2 * mesh.row(nz) + 1
    dofs = np.concatenate([axis, top])
    values = np.vstack([np.zeros((len(axis), len(times))), np.tile(-d, (len(top), 1))])
    info = {
        "scene": "billet",
        "radius_mm": radius,
        "height_mm": height,
        "die_angle_deg": die_angle,
        "die_height_mm": z_c,
        "gap_mm": gap,
        "push_mm": push,
        "pull_mm": pull,
        "refine": refine,
        "elements": [nr, nz],
    }
    return Problem(
        mesh, K, C, weights, gaps, float(mu), dofs, values, times, nodes, normals, tangents,
        float(E), float(nu), True, info,
    )


def block(
    uy: np.ndarray,
    ux: np.ndarray | None = None,
    *,
    nx: int = 4,
    ny: int = 2,
    width: float = 2.0,
    height: float = 1.0,
    E: float = 1.0e3,
    nu: float = 0.0,
    mu: float = 0.0,
) -> Problem:
    """Return a plane-strain block on a rigid flat floor (small cases with known answers).

    The block ``[0, width] x [0, height]`` rests on the floor ``y = 0`` (zero gap); its
    bottom nodes are the contact nodes, with outward normal ``(0, -1)`` and tangent
    ``(1, 0)``. The top face is given the vertical displacement ``uy(t)`` and, when
    ``ux`` is given, the horizontal displacement ``ux(t)``; otherwise the left side is a
    symmetry line (``u_x = 0`` above the floor). The instants are ``0, 1, ..., m - 1``.

    Parameters
    ----------
    uy : array_like, shape (m,)
        Vertical displacement of the top face at each instant (negative presses).
    ux : array_like, shape (m,), optional
        Horizontal displacement of the top face.
    nx, ny : int
        Elements along the width and the height.
    width, height, E, nu, mu : float
        Dimensions, Young's modulus, Poisson's ratio and Coulomb coefficient.

    Returns
    -------
    Problem
    """
    uy = np.asarray(uy, dtype=float)
    if uy.ndim != 1 or uy.size < 1:
        raise ProblemError(f"`uy` must be a non-empty 1-D history; got shape {uy.shape}.")
    if ux is not None:
        ux = np.asarray(ux, dtype=float)
        if ux.shape != uy.shape:
            raise ProblemError(
                f"`ux` must have the shape of `uy` {uy.shape}; got {ux.shape}."
            )
    nx = _check_positive_int(nx, "nx")
    ny = _check_positive_int(ny, "ny")
    mesh = rectangle(nx, ny, width, height)
    n = 2 * mesh.n_nodes
    K = stiffness(mesh, E, nu, axisymmetric=False)
    nodes = mesh.row(0)
    normals = np.tile([0.0, -1.0], (len(nodes), 1))
    tangents = np.tile([1.0, 0.0], (len(nodes), 1))
    C = contact_operator(n, nodes, normals, tangents)
    weights = boundary_weights(mesh.coords, nodes, axisymmetric=False)
    top = mesh.row(ny)
    m = uy.size
    if ux is None:
        side = 2 * mesh.column(0)[1:]  # the contact node keeps its tangential freedom
        dofs = np.concatenate([2 * top + 1, side])
        values = np.vstack([np.tile(uy, (len(top), 1)), np.zeros((len(side), m))])
    else:
        dofs = np.concatenate([2 * top + 1, 2 * top])
        values = np.vstack([np.tile(uy, (len(top), 1)), np.tile(ux, (len(top), 1))])
    info = {"scene": "block", "width": width, "height": height, "elements": [nx, ny]}
    return Problem(
        mesh, K, C, weights, np.zeros(len(nodes)), float(mu), dofs, values,
        np.arange(m, dtype=float), nodes, normals, tangents, float(E), float(nu), False, info,
    )
