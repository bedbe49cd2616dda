import numpy as np
import pytest

import contact
from contact.fem import boundary_weights, element_strains, stiffness
from contact.mesh import mapped_grid, rectangle


def test_billet_default_sizes_match_the_paper():
    P = contact.billet()
    assert P.n == 368
    assert P.nc == 42
    assert P.m == 201
    assert np.isclose(P.times[1] - P.times[0], 5e-3, rtol=1e-12, atol=0)
    assert P.axisymmetric
    assert P.E == 68.86e3 and P.nu == 0.32 and P.mu == 0.1


def test_billet_refinement_and_time_step():
    P = contact.billet(refine=2, dt=5e-3 / 4)
    assert P.n == 2 * 7 * 91
    assert P.nc == 83
    assert P.m == 801


def test_billet_gap_grows_from_the_bottom_and_normals_are_unit():
    P = contact.billet()
    assert P.gaps[0] == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.diff(P.gaps) > 0)
    assert np.allclose(np.linalg.norm(P.normals, axis=1), 1.0)
    assert np.allclose(np.sum(P.normals * P.tangents, axis=1), 0.0, rtol=0,
                       atol=4 * np.finfo(float).eps)


def test_stiffness_is_symmetric_and_has_the_rigid_axial_translation_in_its_kernel():
    P = contact.billet()
    K = P.K.toarray()
    assert np.allclose(K, K.T, atol=1e-9 * np.abs(K).max())
    t = np.zeros(P.n)
    t[1::2] = 1.0
    assert np.abs(K @ t).max() < 1e-9 * np.abs(K).max()
    # radial translation is not a rigid motion of an axisymmetric body (hoop strain)
    r = np.zeros(P.n)
    r[0::2] = 1.0
    assert r @ K @ r > 1e-3 * np.abs(K).max()


@pytest.mark.parametrize("axisymmetric", [False, True])
def test_patch_test_uniaxial_stress_is_exact(axisymmetric):
    """A linear displacement field of uniaxial stress is reproduced by Q1 exactly."""
    E, nu, p = 200.0, 0.3, 1.5
    mesh = mapped_grid(3, 4, 2.0, lambda y: 1.0 + 0.2 * y)  # distorted quadrangles
    K = stiffness(mesh, E, nu, axisymmetric=axisymmetric)
    x, y = mesh.coords[:, 0], mesh.coords[:, 1]
    if axisymmetric:
        ex = nu * p / E  # sigma_zz = -p only
        ey = -p / E
    else:
        ex = nu * (1 + nu) * p / E  # plane strain
        ey = -(1 - nu**2) * p / E
    u = np.zeros(2 * mesh.n_nodes)
    u[0::2], u[1::2] = ex * x, ey * y
    f = K @ u
    top = mesh.row(4)
    bottom = mesh.row(0)
    interior = np.setdiff1d(np.arange(mesh.n_nodes), np.concatenate([top, bottom,
                            mesh.column(0), mesh.column(3)]))
    assert np.abs(f[2 * interior]).max() < 1e-10 * p
    assert np.abs(f[2 * interior + 1]).max() < 1e-10 * p
    w = boundary_weights(mesh.coords, top, axisymmetric=axisymmetric)
    # the right corner also carries the traction of the slanted side
    assert np.allclose(f[2 * top[:-1] + 1], -p * w[:-1], rtol=1e-10, atol=0)


def test_boundary_weights_integrate_r():
    mesh = rectangle(1, 4, 2.0, 1.0)
    chain = mesh.column(1)
    assert boundary_weights(mesh.coords, chain, axisymmetric=False).sum() == pytest.approx(1.0)
    assert boundary_weights(mesh.coords, chain, axisymmetric=True).sum() == pytest.approx(2.0)
    chain = mesh.row(0)
    assert boundary_weights(mesh.coords, chain, axisymmetric=True).sum() == pytest.approx(2.0)


def test_strain_norm_of_a_uniform_shear():
    mesh = rectangle(2, 2, 1.0, 1.0)
    u = np.zeros(2 * mesh.n_nodes)
    u[0::2] = 0.01 * mesh.coords[:, 1]  # gamma_xy = 0.01, eps_xy = 0.005
    s = element_strains(mesh, u, axisymmetric=False)
    assert np.allclose(s, np.sqrt(2) * 0.005, rtol=1e-12, atol=0)


def test_block_frictionless_problem_data():
    P = contact.block(np.array([0.0, -0.01]), nx=3, ny=2)
    assert P.nc == 4
    assert not P.axisymmetric
    # the contact nodes keep their tangential freedom
    assert not np.intersect1d(2 * P.contact_nodes, P.dirichlet_dofs).size


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"refine": 0}, "`refine` must be a positive integer"),
        ({"refine": 1.5}, "`refine` must be a positive integer"),
        ({"dt": 0.003}, "`dt` must divide"),
        ({"dt": -1.0}, r"`dt` must be in \(0, 1"),
    ],
)
def test_billet_rejects_bad_options(kwargs, match):
    with pytest.raises(contact.ProblemError, match=match):
        contact.billet(**kwargs)


def test_problem_validation_messages():
    P = contact.block(np.array([0.0, -0.01]))
    with pytest.raises(ValueError, match="`gaps` must be non-negative"):
        contact.Problem(**{**_fields(P), "gaps": -np.ones(P.nc)})
    with pytest.raises(contact.ProblemError, match="`dirichlet_values` must be"):
        contact.Problem(**{**_fields(P), "dirichlet_values": np.zeros((2, 2))})
    with pytest.raises(contact.ProblemError, match="`weights` must have one entry"):
        contact.Problem(**{**_fields(P), "weights": np.ones(2)})
    with pytest.raises(contact.ProblemError, match="`ux` must have the shape"):
        contact.block(np.zeros(3), np.zeros(2))


def _fields(P):
    import dataclasses

    return {f.name: getattr(P, f.name) for f in dataclasses.fields(P)}
