import numpy as np
import pytest
import scipy.sparse.linalg as spla

import contact


@pytest.fixture(scope="module")
def billet_reference():
    P = contact.billet()
    return P, contact.reference_solve(P)


def frictionless_press(d=0.01, E=1.0e3, nu=0.3, h=1.0):
    return contact.block(np.array([0.0, -d / 2, -d]), nx=4, ny=2, E=E, nu=nu, mu=0.0,
                         height=h)


def shear_block(s, mu=0.3, d=0.01):
    uy = np.array([0.0, -d / 2, -d, -d, -d])
    ux = np.array([0.0, 0.0, 0.0, s / 2, s])
    return contact.block(uy, ux, nx=4, ny=2, E=1.0e3, nu=0.0, mu=mu)


def bonded_tractions(P, k):
    """Tractions on a block whose bottom is glued to the floor (a plain linear solve)."""
    fixed = np.concatenate([P.dirichlet_dofs, 2 * P.contact_nodes, 2 * P.contact_nodes + 1])
    values = np.concatenate([P.dirichlet_values[:, k], np.zeros(2 * P.nc)])
    free = np.setdiff1d(np.arange(P.n), fixed)
    K = P.K.tocsr()
    u = np.zeros(P.n)
    u[fixed] = values
    u[free] = spla.spsolve(K[free][:, free].tocsc(), -K[free][:, fixed] @ values)
    f = K @ u  # nodal forces of the floor on the body
    fc = np.concatenate([f[2 * P.contact_nodes], f[2 * P.contact_nodes + 1]])
    CL = P.C[:, np.concatenate([2 * P.contact_nodes, 2 * P.contact_nodes + 1])]
    # f = C^T L lam at the contact dofs
    return np.linalg.solve((CL.T.toarray() * P.L), fc)


def test_frictionless_block_has_the_uniform_plane_strain_pressure():
    E, nu, d, h = 1.0e3, 0.3, 0.01, 1.0
    P = frictionless_press(d, E, nu, h)
    R = contact.reference_solve(P)
    p = E * d / (h * (1 - nu**2))
    assert np.allclose(R.lam[: P.nc, -1], -p, rtol=1e-10, atol=0)
    assert np.allclose(R.lam[P.nc :, -1], 0.0, atol=1e-10 * p)
    assert np.allclose(R.w[: P.nc, -1], 0.0, atol=1e-12)
    x = P.mesh.coords[P.contact_nodes, 0]
    assert np.allclose(R.w[P.nc :, -1], nu * (1 + nu) * p / E * x, rtol=1e-9, atol=1e-14)


def test_tangential_load_below_the_friction_limit_sticks():
    P = shear_block(s=0.003)  # G s / h = 1.5 < mu p = 3
    R = contact.reference_solve(P)
    assert np.allclose(R.w[P.nc :, -1], 0.0, atol=1e-13)
    assert np.all(np.abs(R.lam[P.nc :, -1]) < P.mu * np.abs(R.lam[: P.nc, -1]))
    assert np.allclose(R.lam[:, -1], bonded_tractions(P, -1), rtol=1e-9, atol=1e-12)


def test_tangential_load_above_the_friction_limit_slips_on_the_cone():
    P = shear_block(s=0.012)  # G s / h = 6 > mu p = 3
    R = contact.reference_solve(P)
    lN, lT, wT = R.lam[: P.nc, -1], R.lam[P.nc :, -1], R.w[P.nc :, -1]
    assert np.all(wT > 1e-4)  # every node slides forward
    assert np.allclose(lT, P.mu * lN, rtol=1e-10, atol=0)  # and is held back at the limit
    # resultants: the tangential force is mu times the normal one
    L = P.weights
    assert np.isclose(L @ lT, P.mu * (L @ lN), rtol=1e-10, atol=0)


@pytest.mark.parametrize("s", [None, 0.003, 0.012])
def test_latin_reproduces_the_block_answers(s):
    P = frictionless_press() if s is None else shear_block(s)
    R = contact.reference_solve(P)
    L = contact.solve(P, "latin", tol=1e-12, max_iter=5000)
    assert L.converged
    assert np.allclose(L.lam_hat, R.lam, atol=1e-8 * np.abs(R.lam).max())
    assert np.allclose(L.displacement(), R.u, atol=1e-8 * np.abs(R.u).max())


def test_reference_billet_satisfies_the_laws(billet_reference):
    P, R = billet_reference
    check = contact.check_laws(P, R.w, R.lam)
    assert check.worst() < 1e-10
    assert check.dissipation > 0
    # the contact zone moves: it climbs the wall, then recedes until the billet is out
    lN = R.lam[: P.nc]
    in_contact = lN < -1e-8 * np.abs(lN).max()
    n_contact = np.count_nonzero(in_contact, axis=0)
    assert n_contact[0] == 0 and n_contact.max() == P.nc and n_contact[-1] == 0
    assert len(np.unique(n_contact)) > 15
    first = in_contact.argmax(axis=1)  # first instant in contact, node by node
    assert first[0] <= first[P.nc // 2] <= first[-1]


def test_reference_equilibrium_holds(billet_reference):
    P, R = billet_reference
    free = P.free_dofs
    res = (P.K @ R.u - P.C.T @ (P.L[:, None] * R.lam))[free]
    assert np.abs(res).max() < 1e-9 * np.abs(P.K @ R.u).max()
    assert np.allclose(R.u[P.dirichlet_dofs], P.dirichlet_values)


def test_reference_rejects_a_bad_tolerance():
    with pytest.raises(contact.SolverOptionError, match="`tol` must be a positive number"):
        contact.reference_solve(frictionless_press(), tol=0.0)


def test_reference_reports_non_convergence_with_the_partial_result():
    with pytest.raises(contact.ConvergenceError, match="did not converge") as info:
        contact.reference_solve(shear_block(0.012), max_newton=0)
    assert isinstance(info.value, RuntimeError)
    assert info.value.result.u.shape[1] < 5
