"""The facade's DMD: windows, forgetting, a mass matrix, trajectories, the store."""

import numpy as np
import pytest
import scipy.sparse as sp

import streamsvd as ss
from streamsvd.testing.systems import batch_dmd, match_eigenvalues, normal_system

EPS = np.finfo(float).eps


def _sorted(z):
    return np.sort_complex(np.round(np.asarray(z), 12))


def _drifting(rng, n=30, m=160):
    """Snapshots of x_(j+1) = A_j x_j whose rotation angles drift with j (rank 4)."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, 4)))
    z, Z = rng.standard_normal(4), np.empty((4, m))
    for j in range(m):
        Z[:, j] = z
        D = np.zeros((4, 4))
        for i, (r, t) in enumerate([(0.99, 0.3 + 0.004 * j), (0.97, 1.1 - 0.003 * j)]):
            c, s = np.cos(t), np.sin(t)
            D[2 * i:2 * i + 2, 2 * i:2 * i + 2] = r * np.array([[c, -s], [s, c]])
        z = D @ z
    return Q @ Z


def test_window_equals_batch_dmd_of_the_window(rng):
    X = _drifting(rng)
    W = 40
    sc = ss.StreamCompressor(X.shape[0], dynamics=True, window=W)
    for j in range(0, X.shape[1], 8):
        sc.absorb(X[:, j:j + 8])
        if j + 8 >= W:
            res = sc.dmd()
            ref = batch_dmd(X[:, j + 8 - W:j + 8])
            assert res.pairs == W - 1
            assert np.max(match_eigenvalues(res.eigenvalues, ref)) < 1e-9
            assert np.max(match_eigenvalues(ref, res.eigenvalues)) < 1e-9


def test_forgetting_equals_its_weighted_batch(rng):
    X = _drifting(rng, m=90)
    g = 0.97
    sc = ss.StreamCompressor(X.shape[0], dynamics=True, forget=g)
    for j in range(0, 90, 9):
        sc.absorb(X[:, j:j + 9])
    w = g ** np.arange(89, -1, -1)
    ref = g * batch_dmd(X * w)
    res = sc.dmd()
    assert np.max(match_eigenvalues(res.eigenvalues, ref)) < 1e-9
    assert res.forget == g


def test_mass_matrix_gives_m_normal_eigenvalues_and_m_norm_modes(rng):
    n = 50
    sysm = normal_system(n, np.array([0.95, 0.9]), np.array([0.4, 1.3]), rng,
                         real=np.array([0.6]))
    d = rng.uniform(0.5, 2.0, n)
    M = sp.diags(d)
    # A = M^(-1/2) Q D Q^T M^(1/2) is M-normal; its snapshots are M^(-1/2) Q D^j z
    X = sysm.trajectory(rng.standard_normal(5), 70) / np.sqrt(d)[:, None]
    sc = ss.StreamCompressor(n, inner=M, dynamics=True)
    for j in range(0, 70, 10):
        sc.absorb(X[:, j:j + 10])
    res = sc.dmd()
    err = match_eigenvalues(res.eigenvalues, sysm.eigenvalues)
    assert np.all(err <= res.residual_bounds) and np.max(err) < 1e3 * EPS
    Phi = res.modes
    assert np.allclose(np.einsum("ij,i,ij->j", Phi.conj(), d, Phi).real, 1.0)


def test_trajectories_make_no_pair_across_their_start(rng):
    sysm = normal_system(30, np.array([0.95, 0.8]), np.array([0.5, 1.5]), rng)
    A = sysm.trajectory(rng.standard_normal(4), 25)
    B = sysm.trajectory(rng.standard_normal(4), 25)
    sc = ss.StreamCompressor(30, dynamics=True)
    sc.absorb(A[:, :10])
    sc.absorb(A[:, 10:])
    sc.absorb(B[:, :7], new_trajectory=True)
    sc.absorb(B[:, 7:])
    assert sc.trajectory_starts.tolist() == [0, 25]
    res = sc.dmd()
    assert res.pairs == 48
    ref = batch_dmd(np.hstack([A[:, :-1], B[:, :-1]]), Y=np.hstack([A[:, 1:], B[:, 1:]]))
    assert np.max(match_eigenvalues(res.eigenvalues, ref)) < 1e-10
    assert np.max(match_eigenvalues(res.eigenvalues, sysm.eigenvalues)) < 1e-10


def test_removing_a_middle_column_splits_its_trajectory(rng):
    sysm = normal_system(20, np.array([0.9]), np.array([0.7]), rng)
    X = sysm.trajectory(rng.standard_normal(2), 12)
    sc = ss.StreamCompressor(20, dynamics=True)
    sc.absorb(X)
    assert sc.dmd().pairs == 11
    sc.remove(5)
    assert sc.dmd().pairs == 9


def test_store_keeps_trajectories_and_answers_dmd(rng, tmp_path):
    sysm = normal_system(30, np.array([0.95, 0.8]), np.array([0.5, 1.5]), rng)
    A = sysm.trajectory(rng.standard_normal(4), 20)
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(30, dynamics=True, store=path) as sc:
        sc.absorb(A[:, :10])
    with ss.StreamCompressor.open(path) as sc:  # resumed
        sc.absorb(A[:, 10:], new_trajectory=True)
        live = sc.dmd()
    assert live.pairs == 18
    with ss.StreamCompressor.open(path, mode="r") as sc:
        assert sc.dynamics and sc.trajectory_starts.tolist() == [0, 10]
    stored = ss.dmd(path)
    assert np.allclose(_sorted(stored.eigenvalues), _sorted(live.eigenvalues), atol=1e-12)


def test_store_without_right_vectors_refuses(rng, tmp_path):
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(10, right_vectors=False, store=path) as sc:
        sc.absorb(rng.standard_normal((10, 5)))
    with pytest.raises(ss.InputError, match="`right_vectors=False`"):
        ss.dmd(path)


@pytest.mark.parametrize("options", [{}, {"forget": 0.98}, {"max_rank": 3, "oversampling": 1},
                                     {"sweeps": None, "rule": "jacobi"}])
def test_carried_pair_factor_equals_the_pairs_read_from_v(rng, options):
    """Queries between updates extend the stored rows' factor: equal to reading V whole."""
    from streamsvd.dynamics import dmd_from_pairs, pair_factor, pair_positions

    sysm = normal_system(40, np.array([0.99, 0.9, 0.8]), np.array([0.3, 1.1, 2.0]), rng,
                         real=np.array([0.5]))
    X = sysm.trajectory(rng.standard_normal(7), 150, noise=1e-6, rng=rng)
    sc = ss.StreamCompressor(40, dynamics=True, **options)
    for j in range(0, 150, 10):
        sc.absorb(X[:, j:j + 10], new_trajectory=j == 70)
        if j == 100:  # an increment over every row: Y is written anew (a rewrite)
            sc.add(1e-3 * rng.standard_normal((40, 1)), rng.standard_normal((sc.n_seen, 1)))
        if j % 30 == 0 or j == 140:
            got = sc.dmd(modes=False)
            V = sc._view.right_factor()
            first, second = pair_positions(np.arange(sc.n_seen), sc._life.trajectory_starts)
            ref = dmd_from_pairs(pair_factor(V, first, second), error_bound=sc.error_bound,
                                 orthogonality=sc.orthogonality_error(), forget=sc.forget)
            assert got.pairs == ref.pairs
            scale = np.max(np.abs(ref.eigenvalues))
            assert np.max(match_eigenvalues(got.eigenvalues, ref.eigenvalues)) < 1e-9 * scale
    assert sc._life.state.rows.rewrites > 0  # the factor was rebuilt on the way


def test_resumed_stream_answers_the_same_dmd_bit_for_bit(rng, tmp_path):
    sysm = normal_system(30, np.array([0.95, 0.8]), np.array([0.5, 1.5]), rng)
    X = sysm.trajectory(rng.standard_normal(4), 40, noise=1e-6, rng=rng)
    ref = ss.StreamCompressor(30, dynamics=True)
    for j in range(0, 40, 8):
        ref.absorb(X[:, j:j + 8], new_trajectory=j == 24)
    path = tmp_path / "s.zarr"
    sc = ss.StreamCompressor(30, dynamics=True, store=path)
    for j in range(0, 24, 8):
        sc.absorb(X[:, j:j + 8])
    sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as sc:
        for j in range(24, 40, 8):
            sc.absorb(X[:, j:j + 8], new_trajectory=j == 24)
        got = sc.dmd(modes=False)
    want = ref.dmd(modes=False)
    assert np.array_equal(got.eigenvalues, want.eigenvalues)
    assert np.array_equal(got.residual_bounds, want.residual_bounds)
