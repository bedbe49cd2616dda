"""StreamCompressor with a zarr store: resume bit for bit, survive SIGKILL, refuse bad state."""

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import streamsvd as ss
from streamsvd.parallel.cluster import check_store, open_compressor
from streamsvd.storage import open_storage
from streamsvd.store import history
from streamsvd.stream.commits import CommitSchedule
from streamsvd.stream.compressor import StreamCompressor
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
    sc.close(finalize=False)  # a pause: the streamed state, not its SVD
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


class _Clock:
    """A clock that moves only when told."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_schedule_commits_every_given_count_whatever_the_clock():
    clock = _Clock()
    schedule = CommitSchedule(3, clock=clock)
    assert [schedule.due(k) for k in range(4)] == [False, False, True, True]
    clock.now = 1e9
    assert not schedule.due(0)


def test_auto_schedule_keeps_the_commits_within_a_tenth_of_the_time():
    """``spent + last <= overhead * (now - start)``: after a first commit of 2 s, the next
    update due is the first one planned 40 s or more after the start; then 3 s more
    of commits need 60 s."""
    clock = _Clock()
    schedule = CommitSchedule("auto", clock=clock)
    assert schedule.due(0)  # nothing spent yet: the first update is committed
    clock.now = 1.0
    with schedule.timed():
        clock.now = 3.0
    due = []
    for now in (4.0, 20.0, 39.9, 40.1, 50.0):
        clock.now = now
        due.append(schedule.due(7))
    assert due == [False, False, False, True, True]
    with schedule.timed():  # 1 s: 3 s spent, and the next one counted at 1 s
        clock.now = 51.0
    clock.now = 54.0  # (3 + 1) / 0.1 = 40 s after the start: due already
    assert schedule.due(0)
    half = CommitSchedule("auto", overhead=0.5, clock=clock)  # starts at 54
    with half.timed():
        clock.now = 55.0
    clock.now = 57.9  # 2 s of commits (one spent, one to come) over 0.5: 4 s
    assert not half.due(0)
    clock.now = 58.1
    assert half.due(0)


def test_auto_schedule_expects_an_unmeasured_basis_at_the_assumed_rate():
    """A commit is expected to cost as much as the last one, or as the basis it writes at
    the fastest rate measured (at least ``ASSUMED_RATE``): after the quick commit that
    creates a store, the first update writing a 112 MB basis waits until its 1.12 s fit
    in a tenth of the time; then the rate it was written at is used."""
    from streamsvd.stream.commits import ASSUMED_RATE

    clock = _Clock()
    schedule = CommitSchedule("auto", clock=clock)
    with schedule.timed(0):  # the store's creation: no basis
        clock.now = 0.01
    basis = 112_000_000
    expected = basis / ASSUMED_RATE  # 1.12 s
    clock.now = 10 * (0.01 + expected) - 0.01
    assert schedule.due(0, 0)  # appending nothing: as long as the last commit
    assert not schedule.due(0, basis)
    clock.now = 10 * (0.01 + expected) + 0.01
    assert schedule.due(0, basis)
    with schedule.timed(basis):  # written at 224 MB/s
        clock.now += 0.5
    # expected now: max(0.5 s, 2 * basis at 224 MB/s = 1.0 s)
    clock.now = 10 * (0.51 + 1.0) - 0.01
    assert schedule.due(0, basis) and not schedule.due(0, 2 * basis)
    clock.now = 10 * (0.51 + 1.0) + 0.01
    assert schedule.due(0, 2 * basis)


def test_a_failed_commit_leaves_the_schedule_as_it_was():
    clock = _Clock()
    schedule = CommitSchedule("auto", clock=clock)
    with schedule.timed():
        clock.now = 1.0
    clock.now = 25.0
    with pytest.raises(OSError), schedule.timed():
        clock.now = 100.0
        raise OSError("No space left on device")
    assert schedule.due(0)  # still due: only the commit that succeeded is counted


@pytest.mark.parametrize("value", [0, -1, 2.5, "every", True, None])
def test_commit_every_is_a_positive_integer_or_auto(value):
    with pytest.raises(ss.InputError, match=r"`commit_every` must be an integer >= 1 "
                       r"\(updates per commit\) or 'auto' .*; got "):
        StreamCompressor(10, commit_every=value)


def test_auto_commits_by_cost_and_a_kill_resumes_bit_for_bit(tmp_path, rng, monkeypatch):
    """On a clock where a commit takes 1 s and an update 3 s, ``commit_every="auto"``
    commits update 1, then the updates that keep the commits within a tenth of the time
    (one in about 10 s once the share is spent); a copy of the store taken between two
    commits (what a kill leaves) resumes from its last commit, and both end bit for bit
    where a run that commits every update ends."""
    from streamsvd.store import BasisStore

    A = _data(rng, n=60, m=120)
    opts = dict(max_rank=6, oversampling=2)
    ref = _stream(A, 5, **opts)
    clock = _Clock()
    commit = BasisStore.commit
    committed = []

    def timed_commit(self, *args, **kwargs):
        clock.now += 1.0
        committed.append(kwargs["attrs"]["source_offset"])
        return commit(self, *args, **kwargs)

    monkeypatch.setattr(BasisStore, "commit", timed_commit)
    path = tmp_path / "auto.zarr"
    sc = StreamCompressor(A.shape[0], store=path, commit_every="auto", **opts)
    sc._life.persistence.schedule = CommitSchedule("auto", clock=clock)
    committed.clear()
    for j in range(0, A.shape[1], 5):
        clock.now += 3.0
        sc.absorb(A[:, j : j + 5])
        if j == 40:  # update 9: the last commit was update 7
            shutil.copytree(path, tmp_path / "killed.zarr")
    assert committed == [5, 35, 50, 65, 80, 95, 110]
    sc.close(finalize=False)
    assert committed[-1] == A.shape[1]
    with StreamCompressor.open(tmp_path / "killed.zarr") as killed:
        assert killed.commit_every == "auto" and killed.source_offset == 35
        for j in range(killed.source_offset, A.shape[1], 5):
            killed.absorb(A[:, j : j + 5])
        killed.flush()
        _assert_same(killed, ref)
    with StreamCompressor.open(path, mode="r") as done:
        _assert_same(done, ref)


def test_bad_block_leaves_store_bitwise_unchanged(tmp_path, rng):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path)
    sc.absorb(A[:, :10])
    before = sc._life.persistence.handle.read()
    with pytest.raises(ss.NonFiniteError):
        sc.absorb(np.full((A.shape[0], 3), np.inf))
    after = sc._life.persistence.handle.read()
    assert after.generation == before.generation
    assert all(np.array_equal(before.arrays[k], after.arrays[k]) for k in before.arrays)
    sc.close()


def test_failed_commit_leaves_memory_and_store_unchanged(tmp_path, rng, monkeypatch):
    A = _data(rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], store=path)
    sc.absorb(A[:, :10])
    U_before = sc.expansion.U.copy()
    gen = sc._life.persistence.handle.generation

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(sc._life.persistence.handle, "commit", boom)
    with pytest.raises(OSError, match="disk full"):
        sc.absorb(A[:, 10:20])
    monkeypatch.undo()
    assert sc.n_seen == 10 and np.array_equal(sc.expansion.U, U_before)
    assert sc._life.persistence.handle.generation == gen and len(sc.history) == 1
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
        StreamCompressor.open(path, inner=np.ones(A.shape[0]))
    with pytest.raises(ss.StoreMismatchError, match=r"`inner` must be the inner product the store"):
        StreamCompressor.open(path, inner=np.eye(A.shape[0]))
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


def test_read_only_tall_compressor_writes_nothing(tmp_path, rng):
    """Refused before planning, also when no commit would be due: a tall update writes
    panels while it plans."""
    from streamsvd.parallel.tall import TallCompressor

    A = rng.standard_normal((300, 60))
    path = tmp_path / "t.zarr"
    with TallCompressor(300, chunk_rows=100, max_rank=4, store=path, commit_every=5) as tc:
        tc.absorb(A[:, :30])
        tc.flush()
    listing = sorted(p.name for p in (path / "panels").iterdir())
    with TallCompressor.open(path, mode="r") as tc:
        with pytest.raises(ss.StoreError, match=r"open read-only"):
            tc.absorb(A[:, 30:])
        assert tc.n_seen == 30
    assert sorted(p.name for p in (path / "panels").iterdir()) == listing


def _ingest_cmd(src, store, *extra):
    return [sys.executable, "-m", "streamsvd", "ingest", str(src), str(store), "--block", "16",
            "--max-rank", "10", "--quiet", *extra]


def _kill_and_resume(tmp_path, rng, kills, *options):
    # 100 commits: long enough that the kills land while the ingestion runs, now that a
    # commit writes only what changed; ``options`` of the command line (the tall mode)
    A = with_spectrum(np.logspace(0, -9, 40), 300, 1600, rng)
    src = tmp_path / "a.npy"
    np.save(src, A)
    ref_store = tmp_path / "ref.zarr"
    subprocess.run(_ingest_cmd(src, ref_store, *options), check=True, capture_output=True)
    store = tmp_path / "killed.zarr"
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    delays = np.random.default_rng(99).uniform(0.5, 2.5, kills)
    done = False
    for delay in delays:
        extra = ("--resume",) if store.exists() else ()
        proc = subprocess.Popen(_ingest_cmd(src, store, *extra, *options), env=env,
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
            # wherever the kill landed, opening and `check` agree: killed while the store
            # was created, nothing was committed (the next run, with --resume, replaces
            # the leftovers); else the last commit is whole, the first one included
            report = check_store(open_storage(store))
            try:
                reader = open_compressor(store, mode="r")
            except ss.StoreFormatError as exc:
                assert report.problems == [str(exc)]
                assert history(open_storage(store)) in ("empty", "creation"), exc
                continue
            assert report.healthy, report.problems
            with reader:  # the last committed state is readable and consistent
                e = reader.expansion
                assert reader.n_seen == reader.source_offset
                seen = A[:, : reader.n_seen]
                if reader.n_seen:
                    err = np.linalg.norm(seen - e.to_dense())
                    assert err <= reader.error_bound + 1e-10 * np.linalg.norm(seen)
    if not done:
        extra = ("--resume",) if store.exists() else ()
        subprocess.run(_ingest_cmd(src, store, *extra, *options), check=True,
                       capture_output=True, env=env)
    with open_compressor(store, mode="r") as a, open_compressor(ref_store, mode="r") as b:
        _assert_same(a, b)
    return store


def test_sigkill_during_ingest_then_resume_gives_the_uninterrupted_result(tmp_path, rng):
    _kill_and_resume(tmp_path, rng, kills=6)


def test_sigkill_during_tall_ingest_then_resume_gives_the_uninterrupted_result(tmp_path, rng):
    """The tall mode's raw panels, and the zarr copies its commits write, survive kills at
    any instant: every committed state reads back, and the resumed run is bit for bit the
    uninterrupted one; no panel without a zarr copy is ever listed."""
    store = _kill_and_resume(tmp_path, rng, 4, "--tall", "--chunk-rows", "64",
                             "--commit-every", "1")
    import zarr

    with open_compressor(store, mode="r") as done:
        panels = done._life.state.basis.panels
    assert panels and all(zarr.open_array(str(store / "panels" / p)).shape[0] == 300
                          for p in panels)


@pytest.mark.slow
def test_sigkill_many_times(tmp_path, rng):
    _kill_and_resume(tmp_path, rng, kills=40)


# ------------------------------------------------------------ append-only commits


def _written_by_commits(path, m, monkeypatch, *, n=60, b=5, commits=8):
    """Elements written by each commit of ``b`` columns after a stream of ``m`` columns."""
    import streamsvd.store.commit as store_mod

    rng = np.random.default_rng(5)  # the same basis and the same last blocks for every m
    Q1 = np.linalg.qr(rng.standard_normal((n, 8)))[0] * np.logspace(0, -3, 8)
    tail = Q1 @ rng.standard_normal((8, b * commits))
    head = Q1 @ np.random.default_rng(m).standard_normal((8, m))
    sc = StreamCompressor(n, max_rank=12)
    sc.absorb(head)
    sc.save(path)
    packs = []
    real = store_mod._write_pack

    def counting(zstore, name, data, doc, chunk_bytes):
        packs.append(int(data.size))
        real(zstore, name, data, doc, chunk_bytes)

    monkeypatch.setattr(store_mod, "_write_pack", counting)
    per_array = []
    for j in range(commits):
        sc.absorb(tail[:, j * b : (j + 1) * b])
        per_array.append(sc._life.persistence.handle.last_written)
    monkeypatch.undo()
    assert packs == [sum(w.values()) for w in per_array]  # the counter counts what is written
    with StreamCompressor.open(path, mode="r") as back:
        assert back.n_seen == m + b * commits
        assert np.array_equal(back.expansion.V, sc.expansion.V)
    sc.close()
    return packs, per_array


def test_commit_writes_what_changed_whatever_the_number_of_snapshots(tmp_path, monkeypatch):
    small, small_arrays = _written_by_commits(tmp_path / "a.zarr", 200, monkeypatch)
    large, large_arrays = _written_by_commits(tmp_path / "b.zarr", 2000, monkeypatch)
    # every commit writes b new rows of V0 (and the small state, the new history rows);
    # nothing of it depends on m: the written sizes are equal, commit by commit
    assert all(w["V0"] > 0 and w["V0"] % 5 == 0 for w in small_arrays)
    assert small_arrays == large_arrays
    assert small == large
    assert max(large) < 2000  # far below V0 itself (2040 x 8)


def _expansions_equal(a, b):
    ea, eb = a.expansion, b.expansion
    return (
        np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)
        and a.error_bound == b.error_bound and a.history == b.history
        and a.source_offset == b.source_offset
    )


@pytest.mark.parametrize("commit_every", [1, 2])
def test_store_holds_the_state_after_every_kind_of_update(tmp_path, rng, commit_every, monkeypatch):
    import streamsvd.engine.rows as rows_mod

    monkeypatch.setattr(rows_mod, "WIDTH_LIMIT", 1.0)  # rebase V0 whenever it widens
    n = 50
    w = rng.uniform(0.5, 2.0, n)
    A = with_spectrum(np.logspace(0, -6, 30), n, 120, rng) + 1e-7 * rng.standard_normal((n, 120))
    path = tmp_path / "s.zarr"
    sc = StreamCompressor(n, inner=w, max_rank=10, store=path, commit_every=commit_every)
    other = StreamCompressor(n, inner=w, max_rank=6)
    other.absorb(rng.standard_normal((n, 7)))
    steps = [("absorb", j) for j in range(0, 60, 6)] + [("add", 0), ("coeffs", 0), ("merge", 0)]
    steps += [("absorb", j) for j in range(60, 120, 3)]
    for kind, j in steps:
        if kind == "absorb":
            sc.absorb(A[:, j : j + 6 if j < 60 else j + 3])
        elif kind == "add":
            sc.add(rng.standard_normal((n, 2)), rng.standard_normal((sc.n_seen, 2)))
        elif kind == "coeffs":
            sc.add(np.zeros((n, 0)), np.zeros((sc.n_seen, 0)),
                   coefficients=1e-3 * rng.standard_normal((sc.n_seen, sc.rank)))
        else:
            sc.merge(other)
        if sc._life.persistence.uncommitted == 0:  # committed: the store holds exactly this state
            with StreamCompressor.open(path, inner=w, mode="r") as back:
                assert _expansions_equal(back, sc), (kind, j)
    assert sc._life.state.rows.rebases > 0 and sc._life.state.basis.compactions > 0
    sc.close()
    with StreamCompressor.open(path, inner=w) as back:
        assert _expansions_equal(back, sc)
        assert back._life.state.basis.capacity == sc._life.state.basis.capacity
        assert back._life.state.rows.capacity == sc._life.state.rows.capacity


def test_store_of_the_previous_layout_is_refused_naming_both(tmp_path, rng):
    import json

    from streamsvd.store import BasisStore

    path = tmp_path / "old.zarr"
    StreamCompressor(8, store=path).close()
    meta = path / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["format_version"] = 1
    meta.write_text(json.dumps(doc))
    with pytest.raises(ss.StoreFormatError, match=r"format version 1; .*reads format version 2"):
        StreamCompressor.open(path)
    other = tmp_path / "layout3.zarr"
    BasisStore.create(other, n=8, inner_fingerprint=ss.as_inner(None, 8).fingerprint,
                      attrs={"kind": StreamCompressor.KIND, "layout": 3}).close()
    with pytest.raises(ss.StoreFormatError, match=r"of layout 3, .* reads layouts 4 to 7"):
        StreamCompressor.open(other)


def _inner(kind, n, rng):
    import scipy.sparse as sp

    w = rng.uniform(0.5, 2.0, n)
    M = sp.diags_array([w[:-1] / 8, w, w[:-1] / 8], offsets=[-1, 0, 1]).tocsr()
    return {"weights": w, "dense": M.toarray(), "sparse": M}[kind]


@pytest.mark.parametrize("kind", ["weights", "dense", "sparse"])
def test_inner_product_is_kept_written_once_and_reopened_without_it(tmp_path, rng, kind):
    """The first commit writes the inner product's data; later commits keep it (write
    none of it); `open` without `inner` rebuilds it and resumes bit for bit."""
    A = _data(rng)
    M = _inner(kind, A.shape[0], rng)
    path = tmp_path / "b.zarr"
    sc = StreamCompressor(A.shape[0], inner=M, max_rank=12, store=path)
    first = set(sc._life.persistence.handle.last_written)
    assert {k for k in first if k.startswith("inner_")}, first  # written at creation
    for j in range(0, 40, 8):
        sc.absorb(A[:, j : j + 8])
        assert not [k for k in sc._life.persistence.handle.last_written if k.startswith("inner_")]
    fingerprint = sc.inner.fingerprint
    sc.close(finalize=False)  # a pause: resumed below, bit for bit
    with StreamCompressor.open(path, mode="r") as back:
        assert back.inner.fingerprint == fingerprint and type(back.inner) is type(sc.inner)
    sc = StreamCompressor.open(path)  # no inner: the store's own
    for j in range(40, 80, 8):
        sc.absorb(A[:, j : j + 8])
    _assert_same(sc, _stream(A, 8, inner=M, max_rank=12))
    sc.close()


def test_store_without_inner_data_opens_with_inner_and_keeps_it_from_then_on(
        tmp_path, rng, monkeypatch):
    """A store written before stores kept the inner product (none of its data, the same
    layout) still opens with `inner=` given; its next commit writes the data once."""
    A = _data(rng)
    w = rng.uniform(0.5, 2.0, A.shape[0])
    path = tmp_path / "old.zarr"
    with monkeypatch.context() as m:
        m.setattr("streamsvd.stream.lifecycle.inner_arrays", lambda inner: None)
        with StreamCompressor(A.shape[0], inner=w, store=path) as sc:
            sc.absorb(A[:, :20])
    with pytest.raises(ss.StoreMismatchError, match=r"`inner` must be given: the store .* "
                                                    r"was written with an inner product"):
        StreamCompressor.open(path)
    with StreamCompressor.open(path, inner=w) as sc:
        sc.absorb(A[:, 20:30])
        assert "inner_weights" in sc._life.persistence.handle.last_written
        sc.absorb(A[:, 30:40])
        assert "inner_weights" not in sc._life.persistence.handle.last_written
    with StreamCompressor.open(path, mode="r") as back:
        assert back.n_seen == 40 and back.inner == ss.DiagonalInner(w)


def test_source_record_is_kept_by_every_commit_and_compared():
    from streamsvd.io.provenance import SourceRecord

    rec = SourceRecord.of("run.h5", dataset="/u", shape=(60, 30), description="HDF5")
    assert rec.dataset == "u" and rec.resolved.endswith("/run.h5")
    assert SourceRecord.from_attrs(rec.to_attrs()) == rec
    grown = SourceRecord.of("run.h5", dataset="u", shape=(60, 50), description="HDF5")
    assert rec.differences(grown) == []  # columns appended: the same source, continued
    other = SourceRecord.of("other.h5", dataset="v", shape=(60, 20), description="HDF5")
    assert [d[0] for d in rec.differences(other)] == ["path", "dataset", "shape"]
    assert rec.differences(other)[2] == ("shape", "60 x 20", "60 x 30")
    array = SourceRecord.of(np.zeros((60, 30)), dataset=None, shape=(60, 30),
                            description="numpy array of shape (60, 30)")
    assert rec.differences(array)[0] == ("path", "numpy array of shape (60, 30)",
                                         rec.resolved)
    with pytest.raises(ss.InputError, match=r"source record must hold path"):
        SourceRecord.from_attrs({"path": "x"})


def test_source_record_survives_commits_and_reopening(tmp_path, rng):
    from streamsvd.io.provenance import SourceRecord

    A = _data(rng)
    rec = SourceRecord.of("a.npy", dataset=None, shape=A.shape, description=".npy file a.npy")
    path = tmp_path / "b.zarr"
    with StreamCompressor(A.shape[0], store=path, source_record=rec) as sc:
        sc.absorb(A[:, :10])
        assert sc.copy().source_record == rec
    with StreamCompressor.open(path, mode="r") as back:
        assert back.source_record == rec
    with pytest.raises(ss.InputError, match=r"`source_record` must be a SourceRecord or None"):
        StreamCompressor(4, source_record={"path": "a.npy"})
