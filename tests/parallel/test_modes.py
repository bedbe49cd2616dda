"""Every mode gives the in-memory result; the tall mode's copies and factors never
gather the basis; the final sweeps survive an interrupt."""

import dask
import dask.array as da
import numpy as np
import pytest

import streamsvd as ss
import streamsvd.linalg.rotations as rotations
from streamsvd.parallel.cluster import TallCompressor, tall_compress, tree_compress

EPS = np.finfo(float).eps


def _spectrum_matrix(rng, n, m, s):
    Uq = np.linalg.qr(rng.standard_normal((n, s.size)))[0]
    Vq = np.linalg.qr(rng.standard_normal((m, s.size)))[0]
    return (Uq * s) @ Vq.T


def _pulses(n=600, m=360):
    """A travelling, spreading pulse: nearly collinear neighbouring snapshots."""
    x = np.linspace(0.0, 1.0, n)[:, np.newaxis]
    t = np.linspace(0.0, 1.0, m)[np.newaxis, :]
    width = 0.05 + 0.05 * t
    return np.exp(-((x - 0.2 - 0.6 * t) / width) ** 2)


def _error(A, U, V):
    return float(np.linalg.norm(A - np.asarray(U) @ np.asarray(V).T))


def test_tall_and_tree_cut_to_the_memory_modes_error(rng):
    """Truncated to k = 30 on a slowly decaying spectrum: the tall mode makes the memory
    mode's cut of the same expansion (errors equal to rounding); the tree, whose leaves
    and merges keep twice the oversampling (every level cuts), is within 1e-5 of the
    optimum and hands its root back with the compressor's options."""
    s = np.logspace(0, -10, 200)
    A = _spectrum_matrix(rng, 2000, 400, s)
    sc = ss.StreamCompressor(2000, max_rank=30)
    for j in range(0, 400, 50):
        sc.absorb(A[:, j : j + 50])
    sc.finalize()
    E = sc.expansion
    memory = _error(A, E.U, E.V)
    tc = tall_compress(A, block=50, chunk_rows=700, max_rank=30)
    tc.finalize()
    tall = _error(A, *tc.factors())
    tree = tree_compress(A, block=50, leaf_columns=100, max_rank=30)
    tree.finalize()
    Et = tree.expansion
    optimum = float(np.linalg.norm(s[30:]))
    assert memory <= 1.0001 * optimum
    assert abs(tall - memory) <= 1e-10 * memory
    assert _error(A, Et.U, Et.V) <= 1.00001 * optimum
    assert tree.oversampling == 10
    assert tc.rank == tree.rank == sc.rank == 30


def test_tree_keeps_the_memory_modes_numerical_rank_at_eps_zero():
    """At eps = 0 the ranks differ only by terms below rounding; above LAPACK's rank
    tolerance (max(n, m) eps sigma_1) the tree and the stream count the same terms."""
    A = _pulses()
    sc = ss.StreamCompressor(A.shape[0], rule="jacobi", sweeps=None)
    for j in range(0, A.shape[1], 40):
        sc.absorb(A[:, j : j + 40])
    tree = tree_compress(A, block=40, leaf_columns=80, rule="jacobi", sweeps=None)
    tol = max(A.shape) * EPS
    want = np.linalg.matrix_rank(A)
    for c in (sc, tree):
        a = c.amplitudes
        assert int(np.sum(a > tol * a[0])) == want
    np.testing.assert_allclose(tree.amplitudes[:20], sc.amplitudes[:20], rtol=1e-10)


def test_tall_copy_is_independent_of_the_original(rng):
    A = _spectrum_matrix(rng, 900, 120, np.logspace(0, -6, 60))
    tc = TallCompressor(900, chunk_rows=256, max_rank=15)
    for j in range(0, 120, 30):
        tc.absorb(A[:, j : j + 30])
    twin = tc.copy()
    assert isinstance(twin, TallCompressor) and twin.chunk_rows == 256
    U0, V0 = tc.factors()
    U0 = np.asarray(U0)
    tc.close()  # removes the original's panels
    U1, V1 = twin.factors()
    np.testing.assert_array_equal(np.asarray(U1), U0)
    np.testing.assert_array_equal(V1, V0)
    twin.absorb(A[:, :30])
    assert twin.n_seen == 150 and twin.rank == 25
    twin.close()


def test_tall_factors_and_copy_never_hold_the_basis(rng):
    """Signing the terms is a reduction over row chunks; copying writes chunk by chunk:
    no task result is as large as the basis (n x 12)."""
    n, rows = 4000, 250
    A = _spectrum_matrix(rng, n, 40, np.logspace(0, -4, 20))
    tc = TallCompressor(n, chunk_rows=rows, max_rank=12, oversampling=0)
    for j in range(0, 40, 4):
        tc.absorb(A[:, j : j + 4])
    sizes = []

    class Sizes(dask.callbacks.Callback):
        def _posttask(self, key, result, dsk, state, id):
            sizes.append(getattr(result, "nbytes", 0))

    with Sizes():
        U, V = tc.factors()
        norms = da.linalg.norm(U, axis=0).compute()
        twin = tc.copy()
    assert max(sizes) < n * 12 * 8
    np.testing.assert_allclose(norms, 1.0, atol=1e-12)
    E = tc.expansion
    np.testing.assert_allclose(np.asarray(U), E.U, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(V, E.V)
    twin.close()
    tc.close()


def test_an_interrupt_in_the_final_sweeps_keeps_the_last_commit(rng, tmp_path, monkeypatch):
    """Ctrl-C during finalize: the compressor and its store stay at the last commit, and
    finalize run again (or after reopening) gives the uninterrupted result."""
    A = _spectrum_matrix(rng, 300, 200, np.logspace(0, -8, 80))
    path = tmp_path / "s.zarr"
    with ss.StreamCompressor(300, store=path, max_rank=20) as sc:
        for j in range(0, 200, 25):
            sc.absorb(A[:, j : j + 25])
        sc.flush()
        reference = sc.copy()
        reference.finalize()
        before = sc.expansion
        calls = []

        def interrupt(*args, **kwargs):
            calls.append(1)
            raise KeyboardInterrupt

        with monkeypatch.context() as mp:
            mp.setattr(rotations, "sweep_core", interrupt)
            with pytest.raises(KeyboardInterrupt):
                sc.finalize(progress=True)
        assert calls and not sc.finalized
        np.testing.assert_array_equal(sc.expansion.U, before.U)
        sc.close(finalize=False)
    with ss.StreamCompressor.open(path) as back:
        np.testing.assert_array_equal(back.expansion.U, before.U)
        assert len(back.history) == 8
        back.finalize()
        np.testing.assert_array_equal(back.expansion.U, reference.expansion.U)
        assert back.rank == 20


def test_final_sweeps_show_progress_on_stderr(rng, capsys):
    A = _spectrum_matrix(rng, 200, 100, np.logspace(0, -8, 60))
    sc = ss.StreamCompressor(200, rule="paper", sweeps=1)
    sc.absorb(A)
    rec = sc.finalize(progress=True)
    err = capsys.readouterr().err
    assert "final sweeps (60 terms)" in err and f"{rec.sweeps}sweep" in err.replace(" ", "")
