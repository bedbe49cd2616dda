"""dask scale-out: tree merges on workers, tall (out-of-core) updates, schedulers, failures.

Reference results are the in-memory StreamCompressor fed with the same blocks and numpy's
SVD, compared with LAPACK's test ratios (``streamsvd.testing``). A real LocalCluster
(2 worker processes, 1 thread each) is started once for the module.
"""

import inspect
import math
import os

import dask
import dask.array as da
import h5py
import numpy as np
import pytest
import zarr

import streamsvd as ss
from streamsvd.errors import (
    InputError,
    NonFiniteError,
    ShapeMismatchError,
    SourceError,
    StoreError,
    StoreMismatchError,
)
from streamsvd.parallel.cluster import (
    TallCompressor,
    connect,
    ingest,
    open_compressor,
    tall_compress,
    tree_compress,
)
from streamsvd.store import open_store
from streamsvd.testing import assert_svd_contract, with_spectrum

EPS = np.finfo(float).eps

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    ) as cluster, distributed.Client(cluster) as c:
        yield c


def stream(A, block, **kw):
    sc = ss.StreamCompressor(A.shape[0], **kw)
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
    return sc


def low_rank(rng, n=240, m=120, rank=25, decades=6, noise=0.0):
    A = with_spectrum(np.logspace(0, -decades, rank), n, m, rng)
    return A + noise * rng.standard_normal((n, m)) if noise else A


def rel_diff(a, b):
    return float(np.max(np.abs(a - b))) / max(float(np.max(np.abs(b))), 1e-300)


def store_snapshot(path):
    with open_store(path, "r") as st:
        state = st.read()
        return state.generation, {k: np.array(v) for k, v in state.arrays.items()}


def failing(x, bad_block):
    """``x`` whose chunk ``bad_block`` (block index along columns) fails to read."""

    def read(block, block_info=None):
        if block_info[None]["chunk-location"][1] == bad_block:
            raise OSError("simulated read failure")
        return block

    return x.map_blocks(read, dtype=x.dtype)


# --------------------------------------------------------------------------- tree


def test_one_leaf_is_the_in_memory_stream(rng):
    A = low_rank(rng, noise=1e-8)
    ref = stream(A, 20, max_rank=15)
    sc = tree_compress(A, block=20, leaf_columns=1000, max_rank=15)
    assert sc.n_seen == 120 and sc.source_offset == 120
    np.testing.assert_array_equal(sc.expansion.U, ref.expansion.U)
    np.testing.assert_array_equal(sc.expansion.V, ref.expansion.V)
    assert sc.error_bound == ref.error_bound


def three_chunkings(A):
    return [da.from_array(A, chunks=c) for c in ((A.shape[0], 7), (64, 30), (50, A.shape[1]))]


@pytest.mark.slow
def test_converged_tree_is_the_svd_for_any_chunking_and_scheduler(rng, client):
    A = low_rank(rng, n=200, m=96, rank=20, decades=8)
    s = np.linalg.svd(A, compute_uv=False)
    amps = []
    for x in three_chunkings(A):
        for c in (None, client):
            sc = tree_compress(x, block=12, leaf_columns=24, sweeps=None, rule="jacobi",
                               client=c)
            e = sc.expansion
            assert_svd_contract(A, e, relative_v=False)
            assert e.rank >= 20
            np.testing.assert_allclose(e.amplitudes[:20], s[:20], rtol=0,
                                       atol=50 * 200 * EPS * s[0])
            amps.append(e.amplitudes[:20])
    for a in amps[1:]:
        assert rel_diff(a, amps[0]) < 50 * 200 * EPS


def test_truncated_tree_does_not_depend_on_chunking_or_scheduler(rng, client):
    A = low_rank(rng, n=160, m=120, rank=40, decades=4)
    runs = []
    for x in three_chunkings(A):
        for c in (None, client):
            runs.append(tree_compress(x, block=10, leaf_columns=30, max_rank=12, client=c))
    e0 = runs[0].expansion
    err = float(np.linalg.norm(A - e0.to_dense()))
    assert err <= runs[0].error_bound * (1 + 1e-9)
    for sc in runs[1:]:
        e = sc.expansion
        assert rel_diff(e.U, e0.U) < 1e-10 and rel_diff(e.V, e0.V) < 1e-10
        assert sc.error_bound == pytest.approx(runs[0].error_bound, rel=1e-10, abs=0)


@pytest.mark.parametrize("leaf_columns", [10, 30, 45, 200])
@pytest.mark.parametrize("trunc", [{"eps": 1e-3}, {"rtol": 1e-3}, {"max_rank": 8}])
def test_tree_error_bound_is_guaranteed_and_near_optimal(rng, leaf_columns, trunc):
    s = np.logspace(0, -5, 40)
    A = with_spectrum(s, 120, 150, rng)
    sc = tree_compress(A, block=10, leaf_columns=leaf_columns, rule="jacobi", sweeps=None,
                       **trunc)
    e = sc.expansion
    err = float(np.linalg.norm(A - e.to_dense()))
    assert err <= sc.error_bound * (1 + 1e-9) + 1e-13
    optimal = math.sqrt(float(np.sum(s[e.rank :] ** 2)))
    # HAPOD truncates at every merge: an absolute eps is met with up to ~2x the optimum
    assert err <= 2.0 * optimal + 1e-12
    assert e.orthogonality_error() <= 50 * 120 * EPS


def test_tree_reads_paths_on_workers(rng, tmp_path, client):
    A = low_rank(rng, n=150, m=60, noise=1e-7)
    np.save(tmp_path / "a.npy", A)
    with h5py.File(tmp_path / "a.h5", "w") as h5:
        h5.create_dataset("snap/u", data=A)
    z = zarr.create_array(str(tmp_path / "a.zarr"), shape=A.shape, chunks=(40, 9), dtype="f8")
    z[:] = A
    ref = tree_compress(A, block=9, leaf_columns=27, max_rank=10)
    with h5py.File(tmp_path / "a.h5", "r") as h5:
        from_dataset = tree_compress(h5["snap/u"], block=9, leaf_columns=27, max_rank=10)
    for src, c in [(tmp_path / "a.npy", None), (str(tmp_path / "a.h5"), client),
                   (tmp_path / "a.zarr", client), (z, None)]:
        sc = tree_compress(src, block=9, leaf_columns=27, max_rank=10, client=c)
        assert rel_diff(sc.expansion.U, ref.expansion.U) < 1e-10
    assert rel_diff(from_dataset.expansion.U, ref.expansion.U) < 1e-10


def test_tree_store_is_created_at_the_end_and_resumed(rng, tmp_path, client):
    A = low_rank(rng, n=120, m=100, noise=1e-8)
    path = tmp_path / "s.zarr"
    with tree_compress(A[:, :60], block=10, leaf_columns=20, max_rank=10, store=path) as sc:
        assert sc.store_path == str(path)
    gen, _ = store_snapshot(path)
    with pytest.raises(StoreError, match="already exists; pass resume=True"):
        tree_compress(A, block=10, store=path)
    with pytest.raises(InputError, match="must be empty with resume=True"):
        tree_compress(A, block=10, store=path, resume=True, max_rank=3)
    with tree_compress(A, block=10, leaf_columns=20, store=path, resume=True,
                       client=client) as sc:
        assert sc.n_seen == 100 and sc.source_offset == 100 and sc.max_rank == 10
    # the merge of the new columns, then the final sweeps of close()
    assert store_snapshot(path)[0] == gen + 2
    with ss.StreamCompressor.open(path, mode="r") as back:
        assert back.n_seen == 100 and back.finalized and back.rank == 10
        assert [h.kind for h in back.history][-2:] == ["merge", "finalize"]
        err = float(np.linalg.norm(A - back.expansion.to_dense()))
        assert err <= back.error_bound * (1 + 1e-9)
    # nothing left to read: the store is returned as it was, already finalised
    with tree_compress(A, block=10, store=path, resume=True) as sc:
        assert sc.n_seen == 100
    assert store_snapshot(path)[0] == gen + 2


@pytest.mark.parametrize("on_cluster", [False, True])
def test_failing_read_leaves_the_store_at_its_last_commit(rng, tmp_path, client, on_cluster):
    A = low_rank(rng, n=100, m=80, noise=1e-8)
    path = tmp_path / "s.zarr"
    tree_compress(A[:, :40], block=10, max_rank=8, store=path).close()
    before = store_snapshot(path)
    x = failing(da.from_array(A, chunks=(50, 10)), bad_block=6)
    with pytest.raises(SourceError, match=r"reading columns 60:70 \(offset 60\)"):
        tree_compress(x, block=10, leaf_columns=20, store=path, resume=True,
                      client=client if on_cluster else None)
    after = store_snapshot(path)
    assert after[0] == before[0]
    for k, v in before[1].items():
        np.testing.assert_array_equal(after[1][k], v)
    with tree_compress(A, block=10, leaf_columns=20, store=path, resume=True) as sc:
        assert sc.n_seen == 80  # the lock was released; the rest is absorbed


class KillInMerge:
    """Euclidean inner product that kills its worker process inside a tree merge.

    With a marker path it kills once (the first merge to start); without, every time.
    """

    n = None
    is_euclidean = False  # so that every Gram-Schmidt calls `apply` (the kill hook)
    fingerprint = "kill-in-merge"

    def __init__(self, marker):
        self.marker = marker

    def apply(self, X):
        if any(f.function == "_merge_pair" for f in inspect.stack()):
            try:
                fd = os.open(self.marker, os.O_CREAT | os.O_EXCL) if self.marker else None
            except FileExistsError:
                return X
            if fd is not None:
                os.close(fd)
            os._exit(17)
        return X

    def gram(self, X, Y):
        return X.T @ Y


@pytest.mark.slow
def test_worker_killed_during_a_merge_does_not_corrupt_the_store(rng, tmp_path, client):
    A = low_rank(rng, n=100, m=80, noise=1e-8)
    # the reference takes the same (non-Euclidean) path without a kill: its marker exists
    (tmp_path / "never").touch()
    ref = tree_compress(A, block=10, leaf_columns=20, max_rank=8, store=tmp_path / "ref",
                        inner=KillInMerge(str(tmp_path / "never")))
    ref.close(finalize=False)
    # killed once: the cluster recomputes what the dead worker held; the result is the
    # reference's to rounding, eps ||A|| for every amplitude (the merge recomputed on
    # another worker may sum in another order), as LAPACK's tests scale it
    inner = KillInMerge(str(tmp_path / "killed-once"))
    path = tmp_path / "s.zarr"
    with tree_compress(A, block=10, leaf_columns=20, max_rank=8, inner=inner,
                       client=client, store=path) as sc:
        assert (tmp_path / "killed-once").exists()
        assert sc.amplitudes.shape == ref.amplitudes.shape
        tol = 50 * max(A.shape) * EPS * ref.amplitudes[0]
        np.testing.assert_allclose(sc.amplitudes, ref.amplitudes, rtol=0, atol=tol)
    with ss.StreamCompressor.open(path, inner=inner, mode="r") as back:
        assert back.n_seen == 80
    # killed at every attempt: the computation fails and an existing store is untouched
    path2 = tmp_path / "s2.zarr"
    tree_compress(A[:, :20], block=10, max_rank=8, inner=KillInMerge(None), store=path2).close()
    before = store_snapshot(path2)
    client.run_on_scheduler(lambda dask_scheduler: setattr(dask_scheduler, "allowed_failures", 0))
    try:
        with pytest.raises(distributed.scheduler.KilledWorker):
            tree_compress(A, block=10, leaf_columns=20, store=path2, resume=True,
                          inner=KillInMerge(None), client=client)
    finally:
        client.run_on_scheduler(
            lambda dask_scheduler: setattr(dask_scheduler, "allowed_failures", 3))
    after = store_snapshot(path2)
    assert after[0] == before[0]
    np.testing.assert_array_equal(after[1]["Q"], before[1]["Q"])
    client.wait_for_workers(2, timeout=30)


def test_the_root_merge_loads_the_sweep_kernels_that_finalize_needs(rng, monkeypatch):
    """On the threaded scheduler the root's merge (only it: the leaves keep both cores
    busy) starts loading the compiled sweep kernels, which the root's ``finalize`` uses."""
    import streamsvd.parallel.tree_graph as parallel_tree

    calls = []
    monkeypatch.setattr(parallel_tree, "load_kernels_in_background",
                        lambda: calls.append("load"))
    A = low_rank(rng, noise=1e-8)
    tree_compress(A, block=20, leaf_columns=30, max_rank=5)  # 4 leaves: 3 merges
    assert calls == ["load"]


def test_tree_bad_arguments(rng, tmp_path):
    A = rng.standard_normal((10, 6))
    with pytest.raises(InputError, match="`options` must be among"):
        tree_compress(A, block=2, max_rnak=3)
    with pytest.raises(InputError, match="`block` must be an integer >= 1"):
        tree_compress(A, block=0)
    with pytest.raises(InputError, match="`leaf_columns` must be an integer >= 1"):
        tree_compress(A, leaf_columns=-1)
    with pytest.raises(InputError, match="`client` must be None"):
        tree_compress(A, client="tcp://localhost:1")
    with pytest.raises(InputError, match="`resume` needs `store`"):
        tree_compress(A, resume=True)
    with pytest.raises(InputError, match="got an open Source"):
        tree_compress(ss.sources.open_source(A))
    tree_compress(A[:9], store=tmp_path / "s").close()
    with pytest.raises(ShapeMismatchError, match="must have snapshots of size 9"):
        tree_compress(A, store=tmp_path / "s", resume=True)


# --------------------------------------------------------------------------- tall


@pytest.mark.parametrize(
    "opts",
    [{"sweeps": 1}, {"sweeps": 2, "eps": 1e-4}, {"sweeps": 1, "max_rank": 10, "rule": "jacobi"},
     {"sweeps": None, "rule": "jacobi", "rtol": 1e-5}],
)
def test_tall_is_the_in_memory_stream(rng, opts):
    A = low_rank(rng, n=300, m=90, rank=30, noise=1e-9)
    ref = stream(A, 15, **opts)
    with TallCompressor(300, chunk_rows=64, **opts) as tc:
        for j in range(0, 90, 15):
            tc.absorb(A[:, j : j + 15])
        e, r = tc.expansion, ref.expansion
        assert tc.rank == ref.rank and tc.n_seen == 90
        np.testing.assert_allclose(e.amplitudes, r.amplitudes, rtol=1e-12, atol=1e-13)
        top = r.amplitudes > 1e-6  # well-separated terms: vectors to rounding
        assert rel_diff(e.U[:, top], r.U[:, top]) < 1e-8
        # with a rank cap both absorb through the snapshots' Gram, whose discarded energy
        # is computed to about sqrt(n) eps ||A||^2: the bound to about 1e-11 ||A|| here
        assert tc.error_bound == pytest.approx(
            ref.error_bound, rel=1e-8, abs=1e-10 * np.linalg.norm(A))
        assert tc.orthogonality_error() == pytest.approx(e.orthogonality_error(), abs=20 * EPS)
        assert e.orthogonality_error() <= 50 * 300 * EPS
        assert [h.rank for h in tc.history] == [h.rank for h in ref.history]


@pytest.mark.slow
def test_tall_converged_is_the_svd_for_any_chunking_and_scheduler(rng, client):
    A = low_rank(rng, n=256, m=72, rank=20, decades=8)
    s = np.linalg.svd(A, compute_uv=False)
    runs = []
    for rows, c in [(256, None), (50, None), (64, client), (100, client)]:
        tc = tall_compress(da.from_array(A, chunks=(rows, 12)), block=12, chunk_rows=rows,
                           sweeps=None, rule="jacobi", client=c)
        e = tc.expansion
        assert_svd_contract(A, e, relative_v=False)
        np.testing.assert_allclose(e.amplitudes[:20], s[:20], rtol=0, atol=50 * 256 * EPS * s[0])
        runs.append(e)
        tc.close()
    for e in runs[1:]:  # vectors of close singular values are weighted by them (LAPACK)
        assert rel_diff(e.U[:, :20] * s[:20], runs[0].U[:, :20] * s[:20]) < 1e-12


def test_narrow_blocks_without_cuts_keep_few_panels(rng):
    """Blocks of one column and nothing cut: each update that does not compact adds a
    panel, and every pass reads each panel in tasks of its own; the basis compacts once
    it holds 8, so a pass reads at most 8 (it read 60 at the 60th update: 35.4 s against
    8.4 s for n = 2e5, bench/studies/outofcore-benchmark.md). The result is the
    in-memory stream's to rounding."""
    A = low_rank(rng, n=200, m=30, rank=30, noise=0.0)
    ref = stream(A, 1)
    pieces = []
    with TallCompressor(200, chunk_rows=64) as tc:
        for j in range(30):
            tc.absorb(A[:, j : j + 1])
            pieces.append(tc._life.state.basis.pieces)
        assert max(pieces) <= 8 and pieces.count(1) >= 3  # compacted, more than once
        e = tc.expansion
        assert tc.rank == ref.rank == 30
        np.testing.assert_allclose(e.amplitudes, ref.amplitudes, rtol=0,
                                   atol=50 * 200 * EPS * ref.amplitudes[0])
        assert np.linalg.norm(A - e.to_dense()) <= 50 * 200 * EPS * np.linalg.norm(A)
        assert e.orthogonality_error() <= 50 * 200 * EPS


def test_tall_rejects_dependent_columns_like_the_in_memory_stream(rng):
    B = rng.standard_normal((200, 6))
    A = np.concatenate([B, B[:, :3] @ rng.standard_normal((3, 4)), B[:, 1:2], 3.0 * B], axis=1)
    ref = stream(A, 8)
    with TallCompressor(200, chunk_rows=48) as tc:
        for j in range(0, A.shape[1], 8):
            tc.absorb(A[:, j : j + 8])
        assert tc.rank == ref.rank == 6
        assert [h.rejected for h in tc.history] == [h.rejected for h in ref.history]
        e = tc.expansion
        assert np.linalg.norm(A - e.to_dense()) <= 1e-12 * np.linalg.norm(A)
        assert tc.error_bound < 1e-9 * np.linalg.norm(A)
        assert e.orthogonality_error() <= 50 * 200 * EPS


@pytest.mark.parametrize("scale", [1e-300, 1e150])
def test_tall_extreme_scales(rng, scale):
    # (squared amplitudes, hence the bound's energies, must stay representable)
    A = low_rank(rng, n=120, m=40, rank=10, decades=3, noise=1e-6)
    with TallCompressor(120, chunk_rows=32, max_rank=6) as a, \
            TallCompressor(120, chunk_rows=32, max_rank=6) as b:
        for j in range(0, 40, 10):
            a.absorb(A[:, j : j + 10])
            b.absorb(A[:, j : j + 10] * scale)
        # a rank cap absorbs through the snapshots' Gram (streamsvd.engine.update_gram), which
        # gives an amplitude s_i to about eps (s_1 / s_i)^2: the kept six to rounding, the
        # oversampled noise terms (s_i ~ 1e-5) to 1e-6
        np.testing.assert_allclose(b.amplitudes[:6] / scale, a.amplitudes[:6], rtol=1e-12)
        np.testing.assert_allclose(b.amplitudes / scale, a.amplitudes, rtol=1e-6)
        # the 6 kept directions (the oversampled ones are noise, determined only up to
        # eps / their gaps, in any algorithm)
        a.finalize()
        b.finalize()
        np.testing.assert_allclose(b.amplitudes / scale, a.amplitudes, rtol=1e-12)
        np.testing.assert_allclose(b.expansion.U, a.expansion.U, atol=1e-12)


def test_tall_weights_match_the_in_memory_stream(rng):
    A = low_rank(rng, n=150, m=40, rank=12, noise=1e-8)
    w = rng.uniform(0.5, 2.0, 150)
    ref = stream(A, 10, inner=w, max_rank=9)
    ref.finalize()
    with TallCompressor(150, chunk_rows=40, inner=w, max_rank=9) as tc:
        for j in range(0, 40, 10):
            tc.absorb(A[:, j : j + 10])
        tc.finalize()
        e = tc.expansion
        np.testing.assert_allclose(e.amplitudes, ref.expansion.amplitudes, rtol=1e-11)
        assert np.linalg.norm(e.U.T @ (w[:, None] * e.U) - np.eye(9)) < 50 * 150 * EPS
    with pytest.raises(InputError, match="`inner` must be Euclidean or diagonal"):
        TallCompressor(150, inner=np.diag(w))


def test_tall_store_resume_equals_an_uninterrupted_run(rng, tmp_path):
    A = low_rank(rng, n=180, m=80, noise=1e-8)
    z = zarr.create_array(str(tmp_path / "a.zarr"), shape=A.shape, chunks=(60, 10), dtype="f8")
    z[:] = A
    with tall_compress(tmp_path / "a.zarr", block=10, store=tmp_path / "full",
                       max_rank=9) as full:
        assert full.chunk_rows == 60  # taken from the zarr chunks
        want = full.expansion
    part = tall_compress(da.from_zarr(z)[:, :30], block=10, store=tmp_path / "part",
                         max_rank=9)
    assert part.n_seen == 30
    part.close(finalize=False)  # a pause, as a killed run leaves it
    tc = tall_compress(tmp_path / "a.zarr", block=10, store=tmp_path / "part", resume=True)
    got = tc.expansion
    assert tc.n_seen == 80 and tc.source_offset == 80
    tc.close(finalize=False)
    np.testing.assert_array_equal(got.U, want.U)
    np.testing.assert_array_equal(got.V, want.V)
    with open_compressor(tmp_path / "part") as back:
        assert isinstance(back, TallCompressor) and back.error_bound == tc.error_bound
        U, V = back.factors()
        np.testing.assert_array_equal(U.compute(), want.U)
    # only the panels of the last two commits remain
    with open_store(tmp_path / "part", "r") as st:
        k = st.generation
        current = st.read().attrs["basis"]["panels"]
        previous = st.read(generation=k - 1).attrs["basis"]["panels"]
    on_disk = {p.name for p in (tmp_path / "part" / "panels").iterdir() if p.is_dir()}
    assert set(current) <= on_disk <= set(current) | set(previous)
    with pytest.raises(StoreMismatchError, match="not written by a StreamCompressor \\(its kind is 'streamsvd.TallCompressor'\\)"):
        ss.StreamCompressor.open(tmp_path / "part")


@pytest.mark.parametrize("on_cluster", [False, True])
def test_tall_failing_read_leaves_the_store_at_its_last_commit(rng, tmp_path, client,
                                                               on_cluster):
    A = low_rank(rng, n=120, m=60, noise=1e-8)
    path = tmp_path / "t.zarr"
    x = failing(da.from_array(A, chunks=(40, 10)), bad_block=3)
    c = client if on_cluster else None
    with pytest.raises(SourceError, match=r"reading columns 30:40 \(offset 30\) of dask array "
                       r".* failed.*resume from offset 30"):
        tall_compress(x, block=10, store=path, chunk_rows=40, max_rank=8, client=c)
    gen, arrays = store_snapshot(path)
    with TallCompressor.open(path, mode="r") as tc:
        assert tc.n_seen == 30 and tc.source_offset == 30
    with tall_compress(da.from_array(A, chunks=(40, 10)), block=10, store=path, resume=True,
                       client=c) as tc:
        got = tc.expansion
    with tall_compress(A, block=10, chunk_rows=40, max_rank=8) as tc:
        want = tc.expansion
    # the same terms sigma_j u_j, to the rounding of the reductions over the panels (the
    # workers of a cluster may sum them in another order)
    tol = 100 * np.sqrt(A.shape[0]) * EPS * want.amplitudes[0]
    np.testing.assert_allclose(got.amplitudes, want.amplitudes, rtol=0, atol=tol)
    np.testing.assert_allclose(got.U * got.amplitudes, want.U * want.amplitudes, rtol=0,
                               atol=tol)


def test_tall_non_finite_block_changes_nothing(rng):
    A = rng.standard_normal((50, 8))
    with TallCompressor(50, chunk_rows=16) as tc:
        tc.absorb(A[:, :4])
        before = tc.expansion
        bad = A[:, 4:].copy()
        bad[7, 2] = np.nan
        with pytest.raises(NonFiniteError, match="`columns` must be finite"):
            tc.absorb(da.from_array(bad, chunks=(16, 4)))
        with pytest.raises(NonFiniteError, match="`columns` must be finite"):
            tc.absorb(bad)
        with pytest.raises(ShapeMismatchError, match="`columns` must have 50 rows"):
            tc.absorb(da.zeros((49, 2)))
        assert tc.n_seen == 4
        np.testing.assert_array_equal(tc.expansion.U, before.U)


def test_tall_basis_is_never_in_memory(rng, tmp_path):
    """No task holds the basis: the largest array is the block (n x b), and the basis
    (n x 12 here) only ever exists as row chunks."""
    n, rows, b = 4000, 250, 4
    A = low_rank(rng, n=n, m=40, rank=20, noise=1e-6)
    sizes = []

    class Largest(dask.callbacks.Callback):
        def _posttask(self, key, result, dsk, state, id):
            sizes.append(getattr(result, "nbytes", 0))

    with TallCompressor(n, chunk_rows=rows, max_rank=12, oversampling=0) as tc, Largest():
        for j in range(0, 40, b):
            tc.absorb(da.from_array(A[:, j : j + b], chunks=(rows, b)))
        assert tc.rank == 12 and tc.stored_width >= 12
    assert max(sizes) <= n * b * 8 < n * 12 * 8


def test_tall_merge_reads_the_other_basis_by_row_chunks(rng, monkeypatch):
    """A tall compressor merged into another: no n-sized array in memory (its left
    vectors are read by row chunks in the merge's pass), the in-memory merge's result."""
    from streamsvd.algebra.panels.basis import PanelBasis

    n, rows = 3000, 256
    A = low_rank(rng, n=n, m=48, rank=20, noise=1e-6)
    opts = {"max_rank": 8, "oversampling": 4}
    ref = stream(A[:, :24], 8, **opts)
    ref.merge(stream(A[:, 24:], 8, **opts), spend_target=False)

    def whole(self, G):
        raise AssertionError("the other basis was formed in memory")

    monkeypatch.setattr(PanelBasis, "lincomb", whole)
    sizes = []

    class Largest(dask.callbacks.Callback):
        def _posttask(self, key, result, dsk, state, id):
            sizes.append(getattr(result, "nbytes", 0))

    left, right = (TallCompressor(n, chunk_rows=rows, **opts) for _ in range(2))
    with left, right:
        for tc, cols in ((left, slice(0, 24)), (right, slice(24, 48))):
            for j in range(cols.start, cols.stop, 8):
                tc.absorb(A[:, j:j + 8])
        with Largest():
            left.merge(right, spend_target=False)
        tol = 50 * n * np.finfo(float).eps
        assert left.rank == ref.rank and left.history[-1].kind == "merge"
        assert np.abs(left.amplitudes - ref.amplitudes).max() <= tol * ref.amplitudes[0]
    assert max(sizes) <= rows * 16 * 8  # a row chunk of the stored columns at most


def _zarr_source(tmp_path, A, rows, cols, dtype="float64"):
    z = zarr.create_array(str(tmp_path / "a.zarr"), shape=A.shape, chunks=(rows, cols),
                          dtype=dtype)
    z[:] = A.astype(dtype)
    return tmp_path / "a.zarr"


def test_tall_block_is_read_by_row_chunks_and_never_whole(rng, tmp_path, monkeypatch):
    """With a cut, a block of a zarr source is read row chunk by row chunk within the
    update's pass: no task holds it whole, it is never loaded into memory, and the result
    is the in-memory stream's."""
    from streamsvd.algebra.panels.backend import PanelBackend

    n, rows, b = 4000, 250, 20
    A = low_rank(rng, n=n, m=60, rank=20, noise=1e-6)
    path = _zarr_source(tmp_path, A, rows, b)
    sizes = []

    class Largest(dask.callbacks.Callback):
        def _posttask(self, key, result, dsk, state, id):
            sizes.append(getattr(result, "nbytes", 0))

    def loaded(self, block):
        raise AssertionError("the block was loaded into memory")

    monkeypatch.setattr(PanelBackend, "in_memory", loaded)
    with Largest():
        tc = tall_compress(path, block=b, max_rank=12, oversampling=0)
    with tc:
        assert tc.chunk_rows == rows
        width = tc.stored_width
        got = tc.expansion  # gathers U (n x 12), outside the stream
        kinds = {r.kind for r in tc.history}
    assert kinds == {"absorb"} and width == 12
    # the largest task result is a row chunk of [Q, X] (or its product), never n x b
    assert max(sizes) <= rows * (width + b) * 8 < n * b * 8
    want = stream(A, b, max_rank=12, oversampling=0).expansion
    assert rel_diff(got.U, want.U) < 1e-10 and rel_diff(got.V, want.V) < 1e-10


def test_tall_passes_are_one_task_per_row_chunk(rng, tmp_path, monkeypatch):
    """Each pass of the Gram path runs one task per row chunk, which reads its rows of
    every input and writes its rows of the output; driven by ``ingest``, each update's
    compaction also reads the next block, so the stream makes one pass per update and
    one more."""
    import functools

    from streamsvd.algebra.panels import tasks as panel_tasks

    n, rows, b = 4000, 250, 20
    A = low_rank(rng, n=n, m=60, rank=20, noise=1e-6)
    path = _zarr_source(tmp_path, A, rows, b)
    calls = {"chunk_products": [], "chunk_compaction": [],
             "chunk_compaction_and_products": []}
    for name, seen in calls.items():
        task = getattr(panel_tasks, name)

        def counted(*args, _task=task, _seen=seen, **kw):
            _seen.append(kw["block_info"][0]["array-location"][0])
            return _task(*args, **kw)

        monkeypatch.setattr(panel_tasks, name, functools.wraps(task)(counted))
    with tall_compress(path, block=b, max_rank=12, oversampling=0) as tc:
        updates = sum(r.kind == "absorb" for r in tc.history)
    assert updates == 3
    every_chunk = sorted((i, i + rows) for i in range(0, n, rows))
    passes = {"chunk_products": 1, "chunk_compaction": 1,
              "chunk_compaction_and_products": updates - 1}
    for name, seen in calls.items():
        assert sorted(seen) == sorted(every_chunk * passes[name])


def test_tall_float32_source_stays_float32_in_the_scratch_copy(rng, tmp_path, monkeypatch):
    from streamsvd.algebra.panels.basis import PanelBasis
    from streamsvd.algebra.panels.raw_array import RawArray

    A = low_rank(rng, n=600, m=40, rank=15, noise=1e-6)
    path = _zarr_source(tmp_path, A, 100, 10, dtype="float32")
    sizes = []
    new_scratch = PanelBasis._new_scratch

    def spy(self, cols, dtype):
        name, scratch = new_scratch(self, cols, dtype)
        assert isinstance(scratch, RawArray)  # a local store: one raw file
        sizes.append((scratch.dtype, scratch.path.stat().st_size))
        return name, scratch

    monkeypatch.setattr(PanelBasis, "_new_scratch", spy)
    with tall_compress(path, block=10, max_rank=8) as tc:
        got = tc.expansion
    assert sizes and all(s == (np.dtype(np.float32), 600 * 10 * 4) for s in sizes)
    want = stream(A.astype(np.float32).astype(np.float64), 10, max_rank=8).expansion
    # the leading 8 (separated singular values; the oversampled tail is float32 noise)
    assert got.rank == want.rank and rel_diff(got.U[:, :8], want.U[:, :8]) < 1e-10


def test_tall_writes_its_files_over_the_ones_it_let_go(rng, tmp_path, monkeypatch):
    """The block's scratch copy and the replaced basis's raw panel are kept and written
    over by the next update (renamed: an array handed out before finds its file gone),
    so once the basis is at its cap an update makes no new file; the result is the
    in-memory one, and closing removes the files kept."""
    from streamsvd.algebra.panels.basis import PanelBasis
    from streamsvd.algebra.panels.raw_array import RawArray

    A = low_rank(rng, n=600, m=120, rank=15, noise=1e-9)
    path = _zarr_source(tmp_path, A, 100, 10)
    made, scratches = [], []
    init, new_scratch = RawArray.__init__, PanelBasis._new_scratch

    def counted(self, directory, shape, dtype, *, chunk_rows):
        made.append(shape)
        init(self, directory, shape, dtype, chunk_rows=chunk_rows)

    def spy(self, cols, dtype):
        before = len(made)  # files made by the updates before this one
        name, scratch = new_scratch(self, cols, dtype)
        scratches.append((name, before))
        return name, scratch

    monkeypatch.setattr(RawArray, "__init__", counted)
    monkeypatch.setattr(PanelBasis, "_new_scratch", spy)
    work = tmp_path / "work"
    tc = tall_compress(path, block=20, max_rank=8, workdir=work)
    basis = tc._life.state.basis
    assert len(scratches) == 6
    assert len({name for name, _ in scratches}) == len(scratches)  # renamed every time
    assert len(made) == scratches[3][1]  # no file made from the fourth update on
    assert basis.compactions >= 4
    assert sorted(p.name for p in (work / "panels").iterdir()) == sorted(
        [*basis.panels, *(spare.name for spare in basis.files.spares)])
    U, _ = tc.factors()
    before = U.compute()
    tc.absorb(A[:, :20])  # lets go of the panel that U reads, kept as it was
    np.testing.assert_array_equal(U.compute(), before)
    tc.absorb(A[:, 20:40])  # writes over it, renamed: U finds its file gone
    with pytest.raises(FileNotFoundError):
        U.compute()
    tc.finalize()
    got = tc.expansion
    tc.close()
    assert sorted(p.name for p in (work / "panels").iterdir()) == sorted(basis.panels)
    reference = stream(np.hstack([A, A[:, :40]]), 20, max_rank=8)
    reference.finalize()
    want = reference.expansion
    tol = 100 * np.sqrt(A.shape[0]) * EPS * want.amplitudes[0]
    np.testing.assert_allclose(got.amplitudes, want.amplitudes, rtol=0, atol=tol)
    np.testing.assert_allclose(got.U * got.amplitudes, want.U * want.amplitudes, rtol=0,
                               atol=tol)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_raw_scratch_holds_what_each_task_wrote(rng, tmp_path, dtype):
    """Row ranges written by separate calls (any memory order) read back exactly, by any
    row range and column slice."""
    from streamsvd.algebra.panels.raw_array import RawArray

    A = rng.standard_normal((1003, 7)).astype(dtype)
    scratch = RawArray(tmp_path / "pabc", A.shape, dtype, chunk_rows=250)
    assert scratch.path.stat().st_size == A.nbytes
    for r0 in range(0, 1003, 250):
        scratch[r0:r0 + 250] = np.asfortranarray(A[r0:r0 + 250])
    assert np.array_equal(scratch[0:1003, 0:7], A)
    assert np.array_equal(scratch[(slice(240, 777), slice(2, 5))], A[240:777, 2:5])
    assert scratch[5:9].dtype == np.dtype(dtype)
    with open(scratch.path, "r+b") as f:
        f.truncate(A.nbytes // 2)
    with pytest.raises(StoreError, match="truncated"):
        scratch[400:900]


@pytest.mark.parametrize("workdir", [False, True])
def test_tall_panels_are_raw_files_and_committed_with_a_zarr_copy(rng, tmp_path, workdir):
    """Local panels are raw files; without a store no commit refers to them, and `save`
    copies them into the store, whose commit lists zarr copies of them: the reopened
    compressor is the saved one exactly."""
    from streamsvd.algebra.panels.raw_array import RawArray

    A = low_rank(rng, n=500, m=60, rank=12, noise=1e-9)
    kw = {"workdir": tmp_path / "work"} if workdir else {}
    tc = tall_compress(A, block=10, max_rank=8, chunk_rows=100, **kw)
    basis = tc._life.state.basis
    assert basis.panels and all(isinstance(basis.files.open(p), RawArray) for p in basis.panels)
    tc.finalize()
    want = tc.expansion
    tc.save(tmp_path / "s.zarr")
    saved = tc._life.state.basis
    assert [zarr.open_array(str(tmp_path / "s.zarr" / "panels" / p)).shape
            for p in saved.panels] == [(500, 8)]
    tc.close()
    with TallCompressor.open(tmp_path / "s.zarr") as back:
        got = back.expansion
    assert np.array_equal(got.U, want.U) and np.array_equal(got.amplitudes, want.amplitudes)


def test_tall_store_commits_zarr_copies_of_its_raw_panels(rng, tmp_path):
    """In a store the passes use raw panels; every panel a commit lists has a zarr copy
    (checksummed) equal to the raw file, and a panel no commit lists has none."""
    from streamsvd.algebra.panels.raw_array import RawArray

    A = low_rank(rng, n=500, m=60, rank=12, noise=1e-9)
    store = tmp_path / "s.zarr"
    with TallCompressor(500, store=store, chunk_rows=100, max_rank=8,
                        commit_every=2) as tc:
        for j in range(0, 60, 10):
            tc.absorb(A[:, j:j + 10])
            basis = tc._life.state.basis
            listed = set(tc._life.persistence.recent[0]["panels"])
            for name in basis.panels:
                raw = basis.files.open(name)
                assert isinstance(raw, RawArray)
                copy = store / "panels" / name / "zarr.json"
                assert copy.exists() == (name in listed)
                if name in listed:
                    assert np.array_equal(zarr.open_array(str(store / "panels" / name))[:],
                                          raw[0:500])
        tc.finalize()
        want = tc.expansion
    with TallCompressor.open(store) as back:
        assert np.array_equal(back.expansion.U, want.U)


def test_tall_scratch_left_by_a_crash_is_removed_on_reopen(rng, tmp_path):
    """A scratch copy left by a killed process (named as a panel, referred to by no
    commit) goes when the store is next opened for writing."""
    from streamsvd.algebra.panels.raw_array import RawArray

    A = low_rank(rng, n=500, m=40, rank=10, noise=1e-8)
    store = tmp_path / "s.zarr"
    with tall_compress(A, block=10, max_rank=6, store=store, chunk_rows=100):
        pass
    stray = RawArray(store / "panels" / "p0123456789abcdef", (500, 10), "float64",
                      chunk_rows=100)
    assert stray.path.exists()
    with TallCompressor.open(store):
        pass
    assert not stray.path.parent.exists()


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_tall_reading_the_next_block_ahead_changes_no_digit(rng, tmp_path, monkeypatch,
                                                             weighted, dtype):
    """A compaction that also reads the next block (ingest names it, ``expect``) gives
    the stream of the two passes per update bit for bit, and the expansion of the
    in-memory stream to rounding."""
    from streamsvd.algebra.panels import tasks as panel_tasks
    from streamsvd.algebra.panels.basis import PanelBasis

    A = low_rank(rng, n=2000, m=80, rank=20, noise=1e-6)
    path = _zarr_source(tmp_path, A, 250, 20, dtype=dtype)
    w = rng.uniform(0.5, 2.0, 2000) if weighted else None
    import functools

    fused_tasks = []
    task = panel_tasks.chunk_compaction_and_products

    @functools.wraps(task)  # dask passes block_info to what names it
    def counted(*args, **kw):
        fused_tasks.append(kw["block_info"][0]["array-location"][0])
        return task(*args, **kw)

    monkeypatch.setattr(panel_tasks, "chunk_compaction_and_products", counted)

    def run():
        fused_tasks.clear()
        with tall_compress(path, block=20, max_rank=12, oversampling=0, inner=w) as tc:
            tc.finalize()
            return tc.expansion, [r.error_bound for r in tc.history], len(fused_tasks)

    fused, fused_bounds, tasks = run()
    assert tasks == 3 * 8  # the compactions of the first three updates, 8 row chunks each
    monkeypatch.setattr(PanelBasis, "expect", lambda self, X: None)
    plain, plain_bounds, tasks = run()
    assert tasks == 0
    assert fused_bounds == plain_bounds
    np.testing.assert_array_equal(fused.amplitudes, plain.amplitudes)
    np.testing.assert_array_equal(fused.U, plain.U)
    np.testing.assert_array_equal(fused.V, plain.V)
    want = stream(A.astype(dtype).astype(np.float64), 20, max_rank=12, oversampling=0,
                  inner=w)
    want.finalize()
    s = want.expansion.amplitudes
    np.testing.assert_allclose(fused.amplitudes, s, rtol=0,
                               atol=100 * np.sqrt(2000) * EPS * s[0])


def test_tall_next_block_that_fails_is_reported_by_its_own_update(rng, caplog):
    """A compaction whose read of the next block fails writes the basis alone; the
    update of that block then reports the failure, the state as after the updates
    before it, bit for bit."""
    import logging

    from streamsvd.io.open import open_source
    from streamsvd.stream.ingest import ingest as ingest_blocks

    A = low_rank(rng, n=2000, m=80, rank=20, noise=1e-6)
    x = failing(da.from_array(A, chunks=(250, 20)), bad_block=2)
    with caplog.at_level(logging.DEBUG, logger="streamsvd.algebra.panels.basis"):
        with TallCompressor(2000, max_rank=12, oversampling=0, chunk_rows=250) as tc:
            with pytest.raises(SourceError, match=r"reading columns 40:60 \(offset 40\)"):
                ingest_blocks(open_source(x), tc, block=20, rows=250)
            assert tc.n_seen == 40
            got = tc.expansion
    assert "reading the next block ahead failed (OSError: simulated read failure)" in caplog.text
    with TallCompressor(2000, max_rank=12, oversampling=0, chunk_rows=250) as tc:
        ingest_blocks(open_source(da.from_array(A[:, :40], chunks=(250, 20))), tc, block=20,
                      rows=250)
        want = tc.expansion
    np.testing.assert_array_equal(got.U, want.U)
    np.testing.assert_array_equal(got.amplitudes, want.amplitudes)


def test_tall_lazy_source_names_a_non_finite_entry_in_source_coordinates(rng, tmp_path):
    A = low_rank(rng, n=1000, m=40, noise=1e-8)
    A[730, 23] = np.inf
    path = _zarr_source(tmp_path, A, 250, 10)
    with pytest.raises(NonFiniteError, match=r"holds inf at column 23, row 730 .*rows "
                       r"500:750 of columns 20:30"):
        tall_compress(path, block=10, max_rank=5, store=tmp_path / "s.zarr")
    with TallCompressor.open(tmp_path / "s.zarr", mode="r") as tc:
        assert tc.n_seen == 20 and tc.source_offset == 20


@pytest.mark.parametrize("with_store", [False, True])
def test_tall_replaced_panels_are_deleted(rng, tmp_path, with_store):
    """A compaction's old basis and every scratch panel go once nothing refers to them:
    at once without a store, after the next commits with one (readers may be on the
    last two); at most two raw files that no commit listed stay, to be written over."""
    A = low_rank(rng, n=500, m=200, noise=1e-6)
    store = tmp_path / "s.zarr" if with_store else None
    opts = dict(commit_every=3) if with_store else {}
    with TallCompressor(500, chunk_rows=100, max_rank=6, store=store, **opts) as tc:
        for j in range(0, 200, 20):
            tc.absorb(A[:, j:j + 20])
            on_disk = {p for p in tc._life.state.basis.root.list("panels") if p.startswith("p")}
            live = set(tc._life.state.basis.panels)
            spares = {spare.name for spare in tc._life.state.basis.files.spares}
            assert len(spares) <= 2 and not spares & live
            if with_store:
                recent = set().union(*(a["panels"] for a in tc._life.persistence.recent))
                assert not spares & recent
                assert live <= on_disk <= live | recent | spares
            else:
                assert on_disk == live | spares
        assert tc._life.state.basis.compactions == 10


# ----------------------------------------------------------------------- drivers


@pytest.mark.slow
def test_ingest_tree_and_tall_with_a_local_cluster(rng, tmp_path):
    A = low_rank(rng, n=90, m=50, noise=1e-8)
    np.save(tmp_path / "a.npy", A)
    tree = ingest(tmp_path / "a.npy", tmp_path / "tree", block=10, scheduler="local",
                  workers=2, progress=False, max_rank=7)
    tall = ingest(tmp_path / "a.npy", tmp_path / "tall", block=10, tall=True,
                  chunk_rows=30, progress=False, max_rank=7)
    assert tree["mode"] == "tree" and tall["mode"] == "tall"
    assert tree["n_seen"] == tall["n_seen"] == 50 and tree["rank"] == tall["rank"] == 7
    assert tall["error_bound"] >= np.linalg.norm(A - stream(A, 10, max_rank=7).expansion.to_dense()) * 0.5
    with open_compressor(tmp_path / "tree") as sc:
        assert sc.n_seen == 50
    with pytest.raises(InputError, match="`leaf_columns` does not apply to the tall mode"):
        ingest(tmp_path / "a.npy", tmp_path / "x", tall=True, leaf_columns=10)
    with pytest.raises(InputError, match="`scheduler` must be 'threads', 'local'"):
        with connect(""):
            pass


def test_h5_source_for_the_tall_mode(rng, tmp_path, client):
    A = low_rank(rng, n=100, m=30, noise=1e-8)
    with h5py.File(tmp_path / "a.h5", "w") as h5:
        h5.create_dataset("u", data=A)
    np.save(tmp_path / "a.npy", A)
    want = stream(A, 10, max_rank=5).expansion
    for src in (tmp_path / "a.h5", tmp_path / "a.npy"):
        with tall_compress(src, block=10, chunk_rows=32, max_rank=5, client=client) as tc:
            assert rel_diff(tc.expansion.U, want.U) < 1e-10


@pytest.mark.parametrize("fmt", ["zarr", "h5"])
def test_tall_row_chunk_reads_on_a_cluster(rng, tmp_path, client, fmt):
    """The Gram path's one pass reads the source on the cluster's workers, by row chunks,
    and gives the in-memory stream's basis."""
    A = low_rank(rng, n=400, m=80, rank=20, noise=1e-6)
    if fmt == "zarr":
        path = _zarr_source(tmp_path, A, 100, 20)
    else:
        path = tmp_path / "a.h5"
        with h5py.File(path, "w") as h5:
            h5.create_dataset("u", data=A, chunks=(100, 20))
    with tall_compress(path, block=20, chunk_rows=100, max_rank=4, oversampling=2,
                       client=client) as tc:
        assert all(r.passes == 2 for r in tc.history)  # the Gram path, every update
        got = tc.expansion
    want = stream(A, 20, max_rank=4, oversampling=2).expansion
    assert rel_diff(got.U, want.U) < 1e-10 and rel_diff(got.V, want.V) < 1e-10


def test_results_do_not_depend_on_the_path_taken(rng):
    """In memory, tree of one leaf and tall: one basis (the issue's cross-check)."""
    A = low_rank(rng, n=200, m=60, rank=15, noise=1e-9)
    sa = stream(A, 12, max_rank=10)
    sb = tree_compress(A, block=12, leaf_columns=60, max_rank=10)
    # streamed (max_rank + oversampling terms): the tree of one leaf is the stream
    assert sa.rank == sb.rank == 20
    assert rel_diff(sb.expansion.U, sa.expansion.U) == 0.0
    assert rel_diff(sb.expansion.V, sa.expansion.V) == 0.0
    with tall_compress(A, block=12, chunk_rows=64, max_rank=10) as tc:
        tc.finalize()
        c = tc.expansion
    # finalised (the top 10 singular triplets, well separated): one basis on every path
    sa.finalize()
    sb.finalize()
    a, b = sa.expansion, sb.expansion
    assert a.rank == c.rank == 10
    assert rel_diff(b.U, a.U) == 0.0 and rel_diff(b.V, a.V) == 0.0
    assert rel_diff(c.U, a.U) < 1e-10 and rel_diff(c.V, a.V) < 1e-10
