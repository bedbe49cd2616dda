"""StreamCompressor with a zarr store: resume bit for bit, survive SIGKILL, refuse bad state."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.stream import StreamCompressor
from streamsvd.testing import with_spectrum


def _data(rng, n=60, m=80):
    return with_spectrum(np.logspace(0, -9, 30), n, m, rng)


def _stream(A, block, **kw):
    sc = StreamCompressor(A.shape[0], **kw)
    for j in range(0, A.shape[1], block):
        sc.absorb(A[:, j : j + block])
    return sc


def _assert_same(a, b):
    ea, eb = a.expansion, b.expansion
    assert np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)
    assert a.error_bound == b.error_bound and a.n_seen == b.n_seen
    assert a.source_offset == b.source_offset


@pytest.mark.parametrize("inner", [None, "weights"])
def test_resume_is_bit_for_bit(tmp_path, rng, inner):
    A = _data(rng)
    ip = None if inner is None else rng.uniform(0.5, 2.0, A.shape[0])
    opts = dict(inner=ip, max_rank=12, rule="paper", sweeps=2)
    path = tmp_path / "basis.zarr"
    sc = StreamCompressor(A.shape[0], store=path, **opts)
    for j in range(0, 40, 8):
        sc.absorb(A[:, j : j + 8])
    sc.close()
    sc = StreamCompressor.open(path, inner=ip)
    assert sc.source_offset == 40 and len(sc.history) == 5
    for j in range(40, 80, 8):
        sc.absorb(A[:, j : j + 8])
    ref = _stream(A, 8, **opts)
    _assert_same(sc, ref)
    assert [h.rank for h in sc.history] == [h.rank for h in ref.history]
    sc.close()


def test_commit_every_and_flush(tmp_path, rng):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path, commit_every=3)
    for j in range(0, 20, 5):
        sc.absorb(A[:, j : j + 5])
    with StreamCompressor.open(path, mode="r") as reader:
        assert reader.n_seen == 15  # three updates committed, the fourth pending
    sc.close()
    with StreamCompressor.open(path, mode="r") as reader:
        assert reader.n_seen == 20


def test_bad_block_leaves_store_bitwise_unchanged(tmp_path, rng):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path)
    sc.absorb(A[:, :10])
    before = sc._store.read()
    with pytest.raises(ss.NonFiniteError):
        sc.absorb(np.full((A.shape[0], 3), np.inf))
    after = sc._store.read()
    assert after.generation == before.generation
    assert all(np.array_equal(before.arrays[k], after.arrays[k]) for k in before.arrays)
    sc.close()


def test_failed_commit_leaves_memory_and_store_unchanged(tmp_path, rng, monkeypatch):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path)
    sc.absorb(A[:, :10])
    U_before = sc.expansion.U.copy()
    gen = sc._store.generation

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(sc._store, "commit", boom)
    with pytest.raises(OSError, match="disk full"):
        sc.absorb(A[:, 10:20])
    monkeypatch.undo()
    assert sc.n_seen == 10 and np.array_equal(sc.expansion.U, U_before)
    assert sc._store.generation == gen and len(sc.history) == 1
    sc.absorb(A[:, 10:20])
    ref = _stream(A[:, :20], 10)
    _assert_same(sc, ref)
    sc.close()


def test_second_writer_and_foreign_stores_are_refused(tmp_path, rng):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path, inner=np.ones(A.shape[0]) * 2.0)
    with pytest.raises(ss.StoreLockedError, match=r"locked by another writer: pid \d+"):
        StreamCompressor.open(path, inner=np.ones(A.shape[0]) * 2.0)
    sc.close()
    with pytest.raises(ss.StoreMismatchError, match=r"`inner` must be the inner product the store"):
        StreamCompressor.open(path)
    with pytest.raises(ss.StoreError, match=r"already"):
        StreamCompressor(A.shape[0], store=path)
    from streamsvd.store import BasisStore

    other = BasisStore.create(tmp_path / "other.zarr", n=5, inner_fingerprint="0" * 64)
    other.close()
    with pytest.raises(ss.StoreMismatchError, match=r"not written by a StreamCompressor"):
        StreamCompressor.open(tmp_path / "other.zarr")


def test_read_only_compressor_cannot_absorb(tmp_path, rng):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    StreamCompressor(A.shape[0], store=path).close()
    with StreamCompressor.open(path, mode="r") as sc:
        with pytest.raises(ss.StoreError, match=r"open read-only"):
            sc.absorb(A[:, :3])


def _ingest_cmd(src, store, *extra):
    return [sys.executable, "-m", "streamsvd", "ingest", str(src), str(store), "--block", "16",
            "--max-rank", "10", "--quiet", *extra]


def _kill_and_resume(tmp_path, rng, kills):
    A = with_spectrum(np.logspace(0, -9, 40), 300, 400, rng)
    src = tmp_path / "a.npy"
    np.save(src, A)
    ref_store = tmp_path / "ref.zarr"
    subprocess.run(_ingest_cmd(src, ref_store), check=True, capture_output=True)
    store = tmp_path / "killed.zarr"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    delays = np.random.default_rng(99).uniform(0.5, 2.5, kills)
    done = False
    for delay in delays:
        extra = ("--resume",) if store.exists() else ()
        proc = subprocess.Popen(_ingest_cmd(src, store, *extra), env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(delay)
        if proc.poll() is not None:
            _, err = proc.communicate()
            assert proc.returncode == 0, err.decode()
            done = True
            break
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
        if store.exists():
            try:
                reader = StreamCompressor.open(store, mode="r")
            except ss.StoreFormatError:
                # killed while the store itself was being created: nothing was committed
                import shutil

                shutil.rmtree(store)
                continue
            with reader:  # the last committed state is readable and consistent
                e = reader.expansion
                assert reader.n_seen == reader.source_offset
                seen = A[:, : reader.n_seen]
                if reader.n_seen:
                    err = np.linalg.norm(seen - e.to_dense())
                    assert err <= reader.error_bound + 1e-10 * np.linalg.norm(seen)
    if not done:
        extra = ("--resume",) if store.exists() else ()
        subprocess.run(_ingest_cmd(src, store, *extra), check=True, capture_output=True, env=env)
    with StreamCompressor.open(store, mode="r") as a, StreamCompressor.open(ref_store, mode="r") as b:
        _assert_same(a, b)


def test_sigkill_during_ingest_then_resume_gives_the_uninterrupted_result(tmp_path, rng):
    _kill_and_resume(tmp_path, rng, kills=6)


@pytest.mark.slow
def test_sigkill_many_times(tmp_path, rng):
    _kill_and_resume(tmp_path, rng, kills=40)
