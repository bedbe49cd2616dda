"""zarr reads and writes on the package's own event loops (streamsvd.algebra.panels.zarr_io)."""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest
import zarr
from zarr.storage import LocalStore, LoggingStore, MemoryStore

from streamsvd.algebra.panels import zarr_io


def _array(store, shape=(257, 13), chunks=(50, 5)):
    return zarr.create_array(store=store, name="a", shape=shape, chunks=chunks,
                             dtype="float64", fill_value=0.0)


@pytest.fixture(params=["local", "memory"])
def store(request, tmp_path):
    return LocalStore(tmp_path / "s") if request.param == "local" else MemoryStore()


def test_reads_and_writes_are_zarrs_own(store, rng, monkeypatch):
    ran = []
    run = zarr_io._run
    monkeypatch.setattr(zarr_io, "_run", lambda coro: ran.append(1) or run(coro))
    z = _array(store)
    A = rng.standard_normal(z.shape)
    # regions that cut chunks, and the short last chunks
    for rows, cols in [(slice(0, 120), slice(0, 13)), (slice(120, 257), slice(0, 7)),
                       (slice(120, 257), slice(7, 13))]:
        zarr_io.write(z, (rows, cols), A[rows, cols])
    assert np.array_equal(z[:], A)
    got = zarr_io.read(z, (slice(33, 201), slice(2, 11)))
    assert np.array_equal(got, A[33:201, 2:11])
    region = zarr_io.Region(z)
    assert region.shape == z.shape and region.dtype == np.float64 and region.ndim == 2
    assert np.array_equal(region[10:20, 3:4], A[10:20, 3:4])
    region[0:2, 0:2] = np.eye(2)
    assert np.array_equal(z[0:2, 0:2], np.eye(2))
    assert len(ran) == 6  # every call went through the package's loops


def test_threads_read_and_write_at_once(store, rng):
    z = _array(store, shape=(4000, 6), chunks=(250, 6))
    A = rng.standard_normal(z.shape)
    errors = []

    def work(i):
        try:
            rows = (slice(i * 250, (i + 1) * 250), slice(None))
            zarr_io.write(z, rows, A[rows])
            assert np.array_equal(zarr_io.read(z, rows), A[rows])
        except BaseException as exc:  # reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert np.array_equal(z[:], A)


def test_other_stores_use_zarrs_interface(tmp_path, rng, monkeypatch):
    """A store this module does not know (here a wrapper) never reaches its loops."""
    def refused(coro):
        coro.close()
        raise AssertionError("ran on the package's loops")

    monkeypatch.setattr(zarr_io, "_run", refused)
    z = _array(LoggingStore(LocalStore(tmp_path / "s")))
    A = rng.standard_normal(z.shape)
    zarr_io.write(z, (slice(None), slice(None)), A)
    assert np.array_equal(zarr_io.read(z, (slice(None), slice(None))), A)
    assert np.array_equal(zarr_io.read(z, (slice(5, 9), slice(0, 2))), A[5:9, :2])


def test_a_failed_read_raises_in_the_caller(tmp_path):
    z = _array(LocalStore(tmp_path / "s"))
    z[:] = 1.0
    with pytest.raises(IndexError):
        zarr_io.read(z, (slice(0, 3), slice(0, 3), slice(0, 1)))


def _child_read(path):
    z = zarr.open_array(store=LocalStore(path), path="a", mode="r")
    return float(zarr_io.read(z, (slice(0, 3), slice(0, 3))).sum())


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(),
                    reason="no fork on this platform")
def test_a_forked_child_starts_its_own_loops(tmp_path, rng):
    z = _array(LocalStore(tmp_path / "s"))
    A = rng.standard_normal(z.shape)
    zarr_io.write(z, (slice(None), slice(None)), A)  # the parent's loops are running
    with multiprocessing.get_context("fork").Pool(1) as pool:
        got = pool.apply_async(_child_read, (tmp_path / "s",)).get(timeout=60)
    assert got == pytest.approx(float(A[:3, :3].sum()), rel=1e-15, abs=0)
