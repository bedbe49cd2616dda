"""The one block reader (Source.blocks, read ahead in a thread) and the one ingest driver."""

from __future__ import annotations

import threading

import dask
import dask.array as da
import numpy as np
import pytest
import zarr
from dask.system import CPU_COUNT

from streamsvd import StreamCompressor
from streamsvd._util.scheduling import execute
from streamsvd.errors import InputError, NonFiniteError, SourceError
from streamsvd.io.open import open_source
from streamsvd.io.sources import Source
from streamsvd.linalg.rotations import load_kernels_in_background
from streamsvd.parallel.cluster import tall_compress, tree_compress
from streamsvd.stream.ingest import IngestResult, ingest

EPS = np.finfo(np.float64).eps
N, M = 37, 23


class CountingColumns:
    """A 2-D array-like that records every column range read, and where the caller was."""

    def __init__(self, A, *, fail_from=None):
        self.A, self.shape, self.dtype = A, A.shape, A.dtype
        self.reads: list[tuple[int, int]] = []
        self.fail_from = fail_from
        self.consumer = -1  # index of the block the caller holds, set by the test
        self.ahead: list[int] = []
        self.lock = threading.Lock()

    def __getitem__(self, key):
        cols = key[1]
        with self.lock:
            self.reads.append((cols.start, cols.stop))
            self.ahead.append(len(self.reads) - 1 - self.consumer)
        if self.fail_from is not None and cols.stop > self.fail_from:
            raise OSError(5, "Input/output error")
        return self.A[key]


@pytest.fixture
def A(rng):
    return rng.standard_normal((N, M))


@pytest.mark.parametrize("depth", [1, 2, 5])
@pytest.mark.parametrize("block", [1, 4, 7, M])
def test_reader_yields_every_block_once_in_order(A, depth, block):
    data = CountingColumns(A)
    src = Source(data, "counting array")
    got = []
    for k, (offset, X) in enumerate(src.blocks(block, depth=depth)):
        data.consumer = k
        got.append((offset, X))
    want = [(a, min(a + block, M)) for a in range(0, M, block)]
    assert data.reads == want  # each block read exactly once, in order
    assert [o for o, _ in got] == [a for a, _ in want]
    for offset, X in got:
        np.testing.assert_array_equal(X, A[:, offset:offset + block])
    # the queue is bounded: a read starts only when the caller has asked for the block
    # `depth` before it (so the caller's block and `depth` others at most are in memory)
    assert max(data.ahead) <= depth + 1


def test_reader_range_stop_and_errors(A):
    src = Source(CountingColumns(A), "counting array")
    assert [o for o, _ in src.blocks(5, start=3, stop=14)] == [3, 8, 13]
    assert [X.shape[1] for _, X in src.blocks(5, start=3, stop=14)] == [5, 5, 1]
    assert list(src.blocks(5, start=9, stop=9)) == []
    with pytest.raises(InputError, match=r"`stop` must be >= `start` \(9\); got 4"):
        src.blocks(5, start=9, stop=4)
    with pytest.raises(InputError, match=rf"`stop` must be in \[0, {M}\].*got {M + 1}"):
        src.blocks(5, stop=M + 1)
    with pytest.raises(InputError, match="`depth` must be"):
        src.blocks(5, depth=0)


def test_reader_exception_surfaces_at_its_block_after_the_earlier_ones(A):
    data = CountingColumns(A, fail_from=10)
    src = Source(data, "flaky array")
    seen = []
    with pytest.raises(SourceError, match=r"reading columns 8:12 \(offset 8\) of flaky array"):
        for offset, _ in src.blocks(4, depth=3):
            seen.append(offset)
    assert seen == [0, 4]
    assert data.reads == [(0, 4), (4, 8), (8, 12)]  # the reader stops at the failure


def test_driver_equals_the_loop_bit_for_bit(A):
    want = StreamCompressor(N, max_rank=6)
    for a in range(0, M, 5):
        want.absorb(A[:, a:a + 5], source_offset=min(a + 5, M))
    got = StreamCompressor(N, max_rank=6)
    result = ingest(open_source(A), got, block=5)
    assert isinstance(result, IngestResult)
    assert (result.start, result.stop, result.blocks) == (0, M, 5)
    assert 0.0 <= result.waiting <= result.seconds
    assert got.source_offset == M
    np.testing.assert_array_equal(got.expansion.U, want.expansion.U)
    np.testing.assert_array_equal(got.expansion.V, want.expansion.V)
    assert got.error_bound == want.error_bound


def test_driver_resumes_at_the_compressor_offset_and_stops_at_stop(A):
    sc = StreamCompressor(N)
    ingest(open_source(A), sc, block=4, stop=10)
    assert sc.source_offset == 10 and sc.n_seen == 10
    ingest(open_source(A), sc, block=4)
    assert sc.source_offset == M and sc.n_seen == M
    assert [h.columns for h in sc.history] == [4, 4, 2, 4, 4, 4, 1]


@pytest.mark.parametrize("mode", ["prefetch", "serial", "lazy", "off"])
def test_driver_loads_the_sweep_kernels_when_the_last_block_is_absorbed(A, monkeypatch, mode):
    """Once every read is done (the last block handed over), not beside the reads; lazy
    blocks, read inside their updates, load them from the start; never when told not to."""
    import streamsvd.stream.ingest as driver

    sc = StreamCompressor(N)
    at = []
    monkeypatch.setattr(driver, "load_kernels_in_background",
                        lambda: at.append(sc.source_offset))
    if mode == "lazy":
        class Lazy:  # a compressor that reads its lazy blocks itself
            source_offset = 0

            def absorb(self, X, *, source_offset):
                Lazy.source_offset = source_offset
                sc.absorb(X.data.compute(), source_offset=source_offset)
                return sc.history[-1]

        ingest(Source(A, "array"), Lazy(), block=5, rows=8)
        assert at[0] == 0 and set(at) == {0, 20}
    else:
        ingest(Source(A, "array"), sc, block=5, prefetch=mode == "prefetch",
               preload_sweeps=mode != "off")
        assert at == ([] if mode == "off" else [20])  # blocks 0, 5, 10, 15 absorbed before
    assert sc.source_offset == M


def test_driver_stops_the_reader_on_a_failed_update(A):
    bad = A.copy()
    bad[3, 12] = np.inf
    loading = load_kernels_in_background()  # once per process, by the first ingest
    if loading is not None:
        loading.join()
    before = threading.active_count()
    sc = StreamCompressor(N)
    with pytest.raises(NonFiniteError, match="column 12, row 3"):
        ingest(open_source(bad), sc, block=4)
    assert sc.source_offset == 12  # every block before the bad one was absorbed
    assert threading.active_count() == before

    class Failing(StreamCompressor):
        def absorb(self, columns, *, source_offset=None):
            if source_offset > 8:
                raise RuntimeError("update failed")
            return super().absorb(columns, source_offset=source_offset)

    with pytest.raises(RuntimeError, match="update failed"):
        ingest(open_source(A), Failing(N), block=4)
    assert threading.active_count() == before


# ------------------------------------------------------------------------- float32


def test_float32_stays_float32_in_transit_and_is_computed_in_float64(rng, tmp_path):
    n, m = 300, 40
    A32 = (rng.standard_normal((n, 12)) @ rng.standard_normal((12, m))).astype(np.float32)
    z = zarr.create_array(tmp_path / "a.zarr", shape=A32.shape, chunks=(100, 8),
                          dtype="f4")
    z[:] = A32
    with open_source(tmp_path / "a.zarr") as src:
        assert src.block_dtype == np.float32
        assert all(X.dtype == np.float32 for _, X in src.blocks(8))
    A = A32.astype(np.float64)  # the rounded data, exactly
    sc = StreamCompressor(n)
    with open_source(tmp_path / "a.zarr") as src:
        ingest(src, sc, block=8)
    ref = StreamCompressor(n)
    ingest(open_source(A), ref, block=8)
    sc.finalize()  # converged: the amplitudes are singular values
    ref.finalize()
    # float64 arithmetic on the float32 values: the same as absorbing the rounded data
    np.testing.assert_array_equal(sc.expansion.U, ref.expansion.U)
    s = np.linalg.svd(A, compute_uv=False)
    e = sc.expansion
    tol = 50 * max(n, m) * EPS * s[0]  # LAPACK's test ratio, in float64
    np.testing.assert_allclose(e.amplitudes, s[:e.amplitudes.size], rtol=0, atol=tol)
    assert np.linalg.norm(A - e.U @ e.V.T) <= tol * np.sqrt(m)


def test_float32_tall_and_tree_agree_with_the_memory_mode(rng, tmp_path):
    n, m, k = 240, 50, 7
    A32 = (rng.standard_normal((n, 20)) * np.logspace(0, -4, 20)
           @ rng.standard_normal((20, m))).astype(np.float32)
    z = zarr.create_array(tmp_path / "a.zarr", shape=A32.shape, chunks=(80, 10),
                          dtype="f4")
    z[:] = A32
    A = A32.astype(np.float64)
    s = np.linalg.svd(A, compute_uv=False)
    optimum = np.sqrt(np.sum(s[k:] ** 2))
    mem = StreamCompressor(n, max_rank=k)
    ingest(open_source(tmp_path / "a.zarr"), mem, block=10)
    mem.finalize()
    with tall_compress(tmp_path / "a.zarr", block=10, max_rank=k) as tc:
        tc.finalize()
        tall = tc.expansion
    tree = tree_compress(tmp_path / "a.zarr", block=10, max_rank=k, leaf_columns=20)
    tree.finalize()
    for e in (mem.expansion, tall, tree.expansion):
        err = np.linalg.norm(A - e.U @ e.V.T)
        assert err <= optimum * (1 + 1e-3)
    scale = 50 * n * EPS * s[0]
    np.testing.assert_allclose(tall.amplitudes, mem.expansion.amplitudes, rtol=0, atol=scale)
    np.testing.assert_allclose(np.abs(tall.U.T @ mem.expansion.U), np.eye(k), atol=1e-6)


# ------------------------------------------------------------------------ scheduler


def test_execute_honours_the_configured_synchronous_scheduler(rng):
    threads: set[int] = set()

    def record(x):
        threads.add(threading.get_ident())
        return x

    x = da.from_array(rng.standard_normal((40, 4)), chunks=(5, 4)).map_blocks(record)
    with dask.config.set(scheduler="synchronous"):
        (got,) = execute([x.sum()])
    assert threads == {threading.get_ident()}
    threads.clear()
    execute([x.sum()])  # the threaded scheduler otherwise: never this thread
    assert threading.get_ident() not in threads
    np.testing.assert_allclose(got, x.sum().compute(scheduler="sync"))


def test_tall_mode_runs_on_the_synchronous_scheduler(rng, monkeypatch):
    import streamsvd.algebra.panels.row_chunks as row_chunks

    seen: set[str] = set()
    real = row_chunks.execute

    def spy(collections, *, client=None, progress=False, overlap_io=False):
        seen.add(dask.config.get("scheduler", None))
        return real(collections, client=client, progress=progress, overlap_io=overlap_io)

    monkeypatch.setattr(row_chunks, "execute", spy)
    A = rng.standard_normal((90, 30))
    with dask.config.set(scheduler="synchronous"):
        with tall_compress(A, block=10, max_rank=5, chunk_rows=30) as tc:
            got = tc.expansion
    assert seen == {"synchronous"}
    want = StreamCompressor(90, max_rank=5)
    ingest(open_source(A), want, block=10)
    np.testing.assert_allclose(got.amplitudes, want.expansion.amplitudes, rtol=1e-12)


def _workers_asked(monkeypatch) -> list:
    """Record the ``num_workers`` each run of dask's threaded scheduler is given."""
    from dask import threaded

    asked: list = []
    real = threaded.get

    def get(dsk, keys, **kwargs):
        asked.append(kwargs.get("num_workers"))
        return real(dsk, keys, **kwargs)

    monkeypatch.setattr(threaded, "get", get)
    return asked


def test_tasks_that_wait_on_io_run_one_more_than_the_cores(rng, monkeypatch):
    asked = _workers_asked(monkeypatch)
    x = da.from_array(rng.standard_normal((40, 4)), chunks=(5, 4))
    (got,) = execute([x.sum()], overlap_io=True)
    execute([x.sum()])
    with dask.config.set(num_workers=3):  # the user's choice stands
        execute([x.sum()], overlap_io=True)
    with dask.config.set(scheduler="synchronous"):
        execute([x.sum()], overlap_io=True)
    assert asked == [CPU_COUNT + 1, None, None]
    np.testing.assert_allclose(got, x.sum().compute(scheduler="sync"))


def test_tall_passes_overlap_their_waits(rng, monkeypatch):
    asked = _workers_asked(monkeypatch)
    with tall_compress(rng.standard_normal((90, 30)), block=10, max_rank=5,
                       chunk_rows=30) as tc:
        tc.finalize()
        tc.left_vectors  # noqa: B018 - the signs of the exposed vectors are one more pass
    assert asked and set(asked) == {CPU_COUNT + 1}


@pytest.mark.slow
def test_local_modes_never_import_distributed(tmp_path):
    # without a client no default client can be in use: the threaded scheduler is
    # handed to dask as a function, which spares the import of distributed
    import subprocess
    import sys

    script = (
        "import sys, numpy as np, zarr\n"
        "from streamsvd.parallel import tall_compress, tree_compress\n"
        f"p = {str(tmp_path / 'A.zarr')!r}\n"
        "z = zarr.create_array(p, shape=(400, 60), chunks=(100, 20), dtype='f8')\n"
        "z[:] = np.random.default_rng(0).standard_normal((400, 60))\n"
        "for run in (lambda: tall_compress(p, block=20, max_rank=5, chunk_rows=100),\n"
        "            lambda: tree_compress(p, block=20, max_rank=5, leaf_columns=30)):\n"
        "    with run() as c:\n"
        "        c.finalize()\n"
        "print('distributed' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          check=True)
    assert done.stdout.strip() == "False", done.stderr


def test_a_dask_chunk_is_computed_once_per_block_read(rng, monkeypatch):
    # a tree leaf reads its window of a dask source by slabs of whole dask chunks, even
    # when a slab of the reader's size holds fewer rows than a chunk
    import streamsvd.io.sources
    from streamsvd.parallel.spec import SourceSpec

    monkeypatch.setattr(streamsvd.io.sources, "_READ_BYTES", 4 * 5 * 8)  # 4 rows of 5 columns

    computed: list[int] = []
    A = rng.standard_normal((N, M))

    def record(x, block_info=None):
        computed.append(block_info[0]["chunk-location"][1])
        return x

    D = da.from_array(A, chunks=(N, 5)).map_blocks(record, dtype=A.dtype)
    spec = SourceSpec.of(D).window(5, 15)
    with spec.open() as src:
        got = [X for _, X in src.blocks(5, start=5, stop=15)]
    np.testing.assert_array_equal(np.hstack(got), A[:, 5:15])
    assert sorted(computed) == [1, 2]
    computed.clear()
    with open_source(zarr_of(A, rng)) as src:  # zarr: slabs of whole row chunks
        got = [X for _, X in src.blocks(5)]
    np.testing.assert_array_equal(np.hstack(got), A)


def zarr_of(A, rng):
    z = zarr.create_array(zarr.storage.MemoryStore(), shape=A.shape, chunks=(10, 5),
                          dtype="f8")
    z[:] = A
    return z
