"""Small-strain linear elasticity on bilinear quadrangles (Q1) and the contact operators.

Degrees of freedom are interleaved: node ``a`` carries dofs ``2a`` (``x`` or ``r``) and
``2a + 1`` (``y`` or ``z``). Two kinematic settings are offered:

* plane strain (thickness 1), strains ``(e_xx, e_yy, g_xy)``;
* axisymmetric (per radian of revolution), strains ``(e_rr, e_zz, e_tt, g_rz)`` with the
  hoop strain ``e_tt = u_r / r``; every integral carries the weight ``r``.

Element integrals use 2 x 2 Gauss points, so the hoop term never evaluates ``1 / r`` on
the axis.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .mesh import Mesh

__all__ = [
    "boundary_weights",
    "contact_operator",
    "element_strains",
    "elasticity_matrix",
    "stiffness",
]

_G = 1.0 / np.sqrt(3.0)
_GAUSS = np.array([[-_G, -_G], [_G, -_G], [_G, _G], [-_G, _G]])
_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def elasticity_matrix(E: float, nu: float, *, axisymmetric: bool) -> np.ndarray:
    """Return Hooke's matrix in Voigt notation (engineering shear strain).

    Plane strain: 3 x 3 on ``(e_xx, e_yy, g_xy)``; axisymmetric: 4 x 4 on
    ``(e_rr, e_zz, e_tt, g_rz)``. Lame constants ``lam = E nu / ((1 + nu)(1 - 2 nu))``
    and ``G = E / (2 (1 + nu))``.
    """
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    G = E / (2.0 * (1.0 + nu))
    k = 3 if axisymmetric else 2
    D = np.zeros((k + 1, k + 1))
    D[:k, :k] = lam
    D[np.arange(k), np.arange(k)] = lam + 2.0 * G
    D[k, k] = G
    return D


def _shape(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Q1 shape functions and their reference gradients at one point ``xi``."""
    N = 0.25 * (1 + _CORNERS[:, 0] * xi[0]) * (1 + _CORNERS[:, 1] * xi[1])
    dN = np.column_stack(
        [
            0.25 * _CORNERS[:, 0] * (1 + _CORNERS[:, 1] * xi[1]),
            0.25 * _CORNERS[:, 1] * (1 + _CORNERS[:, 0] * xi[0]),
        ]
    )
    return N, dN


def _strain_operator(
    mesh: Mesh, xi: np.ndarray, *, axisymmetric: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``B`` (ne x ncomp x 8) and the integration weight ``detJ * r`` at ``xi``."""
    X = mesh.coords[mesh.quads]  # ne x 4 x 2
    N, dN = _shape(xi)
    J = np.einsum("eai,aj->eij", X, dN)  # dX_i / dxi_j
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    inv = np.empty_like(J)
    inv[:, 0, 0] = J[:, 1, 1] / det
    inv[:, 1, 1] = J[:, 0, 0] / det
    inv[:, 0, 1] = -J[:, 0, 1] / det
    inv[:, 1, 0] = -J[:, 1, 0] / det
    dNdx = np.einsum("aj,eji->eai", dN, inv)  # ne x 4 x 2
    ne = X.shape[0]
    ncomp = 4 if axisymmetric else 3
    B = np.zeros((ne, ncomp, 8))
    B[:, 0, 0::2] = dNdx[:, :, 0]
    B[:, 1, 1::2] = dNdx[:, :, 1]
    B[:, -1, 0::2] = dNdx[:, :, 1]
    B[:, -1, 1::2] = dNdx[:, :, 0]
    weight = det.copy()
    if axisymmetric:
        r = X[:, :, 0] @ N
        B[:, 2, 0::2] = N[None, :] / r[:, None]
        weight = weight * r
    return B, weight


def _element_dofs(mesh: Mesh) -> np.ndarray:
    q = mesh.quads
    return np.stack([2 * q, 2 * q + 1], axis=2).reshape(q.shape[0], 8)


def stiffness(mesh: Mesh, E: float, nu: float, *, axisymmetric: bool) -> sp.csr_matrix:
    """Assemble the stiffness matrix ``K`` (n x n, n = 2 * n_nodes).

    ``K = sum_e sum_g B^T D B detJ w_g (r_g)``, with 2 x 2 Gauss points and the factor
    ``r_g`` in the axisymmetric case (stiffness per radian).
    """
    D = elasticity_matrix(E, nu, axisymmetric=axisymmetric)
    ne = mesh.quads.shape[0]
    Ke = np.zeros((ne, 8, 8))
    for xi in _GAUSS:
        B, w = _strain_operator(mesh, xi, axisymmetric=axisymmetric)
        Ke += np.einsum("eki,kl,elj,e->eij", B, D, B, w)
    dofs = _element_dofs(mesh)
    rows = np.repeat(dofs, 8, axis=1).ravel()
    cols = np.tile(dofs, (1, 8)).ravel()
    n = 2 * mesh.n_nodes
    K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    K.sum_duplicates()
    return K


def element_strains(
    mesh: Mesh, u: np.ndarray, *, axisymmetric: bool
) -> np.ndarray:
    """Return the strain norm ``sqrt(eps : eps)`` at the centre of each element.

    Parameters
    ----------
    u : ndarray, shape (n,) or (n, m)
        Displacements (one column per field).

    Returns
    -------
    ndarray, shape (n_elements,) or (n_elements, m)
    """
    B, _ = _strain_operator(mesh, np.zeros(2), axisymmetric=axisymmetric)
    ue = np.asarray(u)[_element_dofs(mesh)]  # ne x 8 (x m)
    eps = np.einsum("eki,ei...->ek...", B, ue)
    eps[:, -1] *= 0.5  # tensor shear component
    sq = np.sum(eps**2, axis=1) + eps[:, -1] ** 2  # shear counted twice in eps : eps
    return np.sqrt(sq)


def boundary_weights(
    coords: np.ndarray, chain: np.ndarray, *, axisymmetric: bool
) -> np.ndarray:
    """Return ``w_i = integral of N_i (r) ds`` for the nodes of a boundary polyline.

    Parameters
    ----------
    coords : ndarray, shape (n_nodes, 2)
    chain : ndarray of int
        Consecutive nodes of the boundary.
    axisymmetric : bool
        Weight the line integral by ``r`` (measure per radian).

    Returns
    -------
    ndarray, shape (len(chain),)
        For an edge of length ``h`` between ``a`` and ``b``: ``h / 2`` each in the plane,
        ``h (2 r_a + r_b) / 6`` and ``h (r_a + 2 r_b) / 6`` when axisymmetric (exact for
        linear ``N`` and ``r``). A uniform traction ``p`` is thus carried by the nodal
        forces ``p w_i``.
    """
    P = coords[chain]
    h = np.linalg.norm(np.diff(P, axis=0), axis=1)
    w = np.zeros(len(chain))
    if axisymmetric:
        ra, rb = P[:-1, 0], P[1:, 0]
        w[:-1] += h * (2 * ra + rb) / 6.0
        w[1:] += h * (ra + 2 * rb) / 6.0
    else:
        w[:-1] += h / 2.0
        w[1:] += h / 2.0
    return w


def contact_operator(
    n: int, nodes: np.ndarray, normals: np.ndarray, tangents: np.ndarray
) -> sp.csr_matrix:
    """Return ``C`` (2 nc x n): rows ``0..nc-1`` give ``n_i . u``, rows ``nc..`` ``t_i . u``."""
    nc = len(nodes)
    rows = np.repeat(np.arange(2 * nc), 2)
    cols = np.tile(np.column_stack([2 * nodes, 2 * nodes + 1]), (2, 1)).ravel()
    vals = np.vstack([normals, tangents]).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(2 * nc, n))
