"""Fault injection against the basis store: crash points, zombie writers, readers during
commits, a full disk at every write of the first commits, and each kind of damage.

Every case is deterministic: a commit is interrupted at a named step by replacing
:func:`streamsvd.store.fence.crash_point`, a zombie writer is a writer whose lease is
taken over while it stands at such a step, and a full disk is ``os.write`` raising
``ENOSPC`` once a byte budget is spent. The random campaign (SIGKILL, SIGINT, SIGSTOP
at random instants, on a directory and on the local S3 server) is
``bench/fault_campaign.py``.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import streamsvd.store.fence as fence_mod
from streamsvd.cli import main
from streamsvd.errors import StoreError, StoreFormatError, StoreLockedError
from streamsvd.storage import open_storage
from streamsvd.store import (
    CRASH_POINTS,
    GENERATIONS,
    LEASE_NAME,
    MARKER_NAME,
    POINTER_NAME,
    BasisStore,
    check_store,
    open_store,
)
from streamsvd.testing.damage import GENERATION_DAMAGE, damage_generation

FP = "f" * 64
BEFORE_SWITCH = CRASH_POINTS[: CRASH_POINTS.index("switched")]
AFTER_SWITCH = CRASH_POINTS[CRASH_POINTS.index("switched") :]
REAL_CRASH_POINT = fence_mod.crash_point


def arrays_of(k, n=50):
    rng = np.random.default_rng(k)
    return {"U": rng.standard_normal((n, 3)), "s": rng.random(3)}


def assert_generation(store_or_path, k):
    with open_store(store_or_path, "r") as reader:
        state = reader.read()
    assert state.generation == k
    if k == 0:
        assert state.arrays == {} and state.attrs == {}
        return
    for name, value in arrays_of(k).items():
        assert np.array_equal(state.arrays[name], value), name
    assert state.attrs == {"k": k}


def tree(root):
    """Every file below ``root`` with its bytes (the lock excluded)."""
    out = {}
    for dirpath, _, files in os.walk(root):
        for name in files:
            if name != "writer.lock":
                path = Path(dirpath) / name
                out[str(path.relative_to(root))] = path.read_bytes()
    return out


def committed(path, upto=2, n=50):
    with BasisStore.create(path, n=n, inner_fingerprint=FP) as s:
        for k in range(1, upto + 1):
            s.commit(arrays_of(k, n), {"k": k})


def interrupt_at(monkeypatch, point, failure, *, on_call=1):
    """Make the ``on_call``-th arrival at ``point`` raise ``failure``."""
    seen = []

    def crash(name):
        if name == point:
            seen.append(name)
            if len(seen) == on_call:
                raise failure
    monkeypatch.setattr(fence_mod, "crash_point", crash)
    return seen


# ------------------------------------------------------------------ crash points


@pytest.mark.parametrize("failure", [KeyboardInterrupt(), OSError(errno.EIO, "I/O error")])
@pytest.mark.parametrize("point", CRASH_POINTS)
def test_an_interrupt_at_each_step_of_a_commit_keeps_a_whole_generation(
        tmp_path, monkeypatch, point, failure):
    path = tmp_path / "s.zarr"
    committed(path, 1)
    store = open_store(path, "a")
    seen = interrupt_at(monkeypatch, point, failure)
    after = point in AFTER_SWITCH
    if isinstance(failure, KeyboardInterrupt):
        with pytest.raises(KeyboardInterrupt):
            store.commit(arrays_of(2), {"k": 2})
    elif after:  # the commit stands; what failed after the switch is logged
        assert store.commit(arrays_of(2), {"k": 2}) == 2
    else:
        with pytest.raises(StoreError, match=r"writing generation 2 failed .*generation 1 is "
                           r"unchanged"):
            store.commit(arrays_of(2), {"k": 2})
    assert seen == [point]
    monkeypatch.undo()
    k = 2 if after else 1
    assert store.generation == k
    assert_generation(path, k)
    if not after:
        assert "g00000002" not in open_storage(path).list(GENERATIONS)
    assert store.commit(arrays_of(k + 1), {"k": k + 1}) == k + 1
    store.close()
    assert_generation(path, k + 1)
    assert check_store(open_storage(path)).healthy


@pytest.mark.parametrize("failure", [KeyboardInterrupt(), OSError(errno.EIO, "I/O error")])
@pytest.mark.parametrize("point", CRASH_POINTS)
def test_an_interrupt_at_each_step_of_a_creation_leaves_nothing_or_the_whole_store(
        tmp_path, monkeypatch, point, failure):
    """The pointer is the creation's last step: interrupted before it, nothing is left
    (opening and `check` agree that there is no store); after it, the store stands."""
    path = tmp_path / "s.zarr"
    seen = interrupt_at(monkeypatch, point, failure)
    after = point in AFTER_SWITCH
    if isinstance(failure, KeyboardInterrupt):
        with pytest.raises(KeyboardInterrupt):
            BasisStore.create(path, n=50, inner_fingerprint=FP).close()
    elif after:  # the creation stands; what failed after the switch is logged
        BasisStore.create(path, n=50, inner_fingerprint=FP).close()
    else:
        with pytest.raises(StoreError, match=r"creating the store failed while writing "
                           r"generation 0 and its pointer \(.*I/O error.*nothing was left"):
            BasisStore.create(path, n=50, inner_fingerprint=FP)
    monkeypatch.undo()
    assert seen == [point] and path.exists() == after
    report = check_store(open_storage(path))
    if after:
        assert report.healthy, report.problems
        assert_generation(path, 0)
    else:
        with pytest.raises(StoreFormatError, match="does not exist") as refused:
            open_store(path)
        assert report.problems == [str(refused.value)]
        committed(path, 1)  # created again
    assert check_store(open_storage(path)).healthy


_KILLED_WRITER = """
import os, signal, sys
import numpy as np
import streamsvd.store.fence as fence
from streamsvd.store import open_store
path, point = sys.argv[1], sys.argv[2]
def crash(name):
    if name == point:
        os.kill(os.getpid(), signal.SIGKILL)
fence.crash_point = crash
rng = np.random.default_rng(2)
with open_store(path, "a") as s:
    s.commit({"U": rng.standard_normal((50, 3)), "s": rng.random(3)}, {"k": 2})
"""


@pytest.mark.parametrize("point", CRASH_POINTS)
def test_a_writer_killed_at_each_step_of_a_commit_leaves_a_whole_generation(tmp_path, point):
    path = tmp_path / "s.zarr"
    committed(path, 1)
    out = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(path), point],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == -signal.SIGKILL, out.stderr
    k = 2 if point in AFTER_SWITCH else 1
    assert_generation(path, k)  # a reader: the lock of the dead writer does not matter
    with open_store(path, "a") as s:  # takes the dead writer's lock, cleans its leftovers
        assert s.generation == k
        assert s.commit(arrays_of(k + 1), {"k": k + 1}) == k + 1
    assert_generation(path, k + 1)
    assert check_store(open_storage(path)).healthy


# ----------------------------------------------------------------- zombie writers


def _expire_lease(url):
    """Make the lease look expired, as after its holder was paused for longer than it."""
    storage = open_storage(url)
    info = json.loads(storage.get(LEASE_NAME))
    info.update(expires=time.time() - 1, host="elsewhere")
    storage.put(LEASE_NAME, json.dumps(info).encode())


@pytest.mark.parametrize("point", CRASH_POINTS)
def test_a_zombie_writer_woken_after_a_takeover_changes_nothing(s3, monkeypatch, point):
    url = f"{s3}/zombie.zarr"
    committed(url, 2)
    zombie = open_store(url, "a")
    storage = open_storage(url)
    root = storage.get("zarr.json")
    rival: list[BasisStore] = []

    def paused(name):  # the zombie stands here while another writer takes over
        if name == point and not rival:
            rival.append(None)
            _expire_lease(url)
            taker = open_store(url, "a")
            rival[0] = taker
            for k in range(taker.generation + 1, taker.generation + 4):
                taker.commit(arrays_of(k), {"k": k})
    monkeypatch.setattr(fence_mod, "crash_point", paused)
    objects_before_wake: dict[str, bytes] = {}

    def snapshot():
        for key in storage.fs.find(storage.path):
            objects_before_wake[key] = storage.fs.cat_file(key)

    try:
        zombie.commit(arrays_of(3), {"k": 3})
    except StoreLockedError:
        pass  # refused before or at the switch: it wrote nothing of its own
    monkeypatch.setattr(fence_mod, "crash_point", REAL_CRASH_POINT)  # the AWS_* stay set
    taker = rival[0]
    last = taker.generation
    snapshot()
    zombie.close()  # its lease is another writer's: it is left in place
    assert storage.get("zarr.json") == root
    assert_generation(url, last)
    report = check_store(storage)
    assert report.healthy, report.problems
    with open_store(url, "r") as reader:  # every generation the pointer needs is there
        reader.read(generation=last - 1)
    taker.commit(arrays_of(last + 1), {"k": last + 1})
    taker.close()
    assert_generation(url, last + 1)
    assert LEASE_NAME not in storage.list()


def test_a_zombie_creation_does_not_rewrite_the_store_created_after_it(s3, monkeypatch):
    url = f"{s3}/zombie-create.zarr"
    rival: list[BasisStore] = []

    def paused(name):
        if name == "pack-started" and not rival:
            rival.append(None)
            _expire_lease(url)
            taker = BasisStore.create(url, n=50, inner_fingerprint="g" * 64)
            taker.commit(arrays_of(1), {"k": 1})
            rival[0] = taker
    monkeypatch.setattr(fence_mod, "crash_point", paused)
    with pytest.raises(StoreLockedError, match="lost its writer lock"):
        BasisStore.create(url, n=50, inner_fingerprint=FP)
    monkeypatch.setattr(fence_mod, "crash_point", REAL_CRASH_POINT)
    rival[0].close()
    with open_store(url, "r") as reader:
        assert reader.inner_fingerprint == "g" * 64
    assert_generation(url, 1)
    assert check_store(open_storage(url)).healthy


def test_a_pointer_refused_after_a_retried_put_that_took_effect_is_this_commit(s3, monkeypatch):
    """An HTTP 500 on a PUT the server applied: the retry's If-Match fails on our own write."""
    from streamsvd.storage import ObjectStorage

    url = f"{s3}/retried.zarr"
    committed(url, 1)
    real = ObjectStorage.put_if_match

    def applied_then_refused(self, key, data, tag):
        if key == POINTER_NAME:
            real(self, key, data, tag)  # applied, but the reply was lost
            return None  # the retry is refused: the ETag moved
        return real(self, key, data, tag)
    with open_store(url, "a") as s:
        monkeypatch.setattr(ObjectStorage, "put_if_match", applied_then_refused)
        assert s.commit(arrays_of(2), {"k": 2}) == 2
    assert_generation(url, 2)


def test_a_pointer_changed_under_a_lease_holder_does_not_blame_itself(s3):
    url = f"{s3}/by-hand.zarr"
    committed(url, 1)
    with open_store(url, "a") as s:
        storage = open_storage(url)
        same = json.dumps(json.loads(storage.get(POINTER_NAME))).encode()
        storage.put(POINTER_NAME, same)  # the same pointer, other bytes: a new ETag
        with pytest.raises(StoreLockedError, match="although this writer still holds the "
                           "lease") as err:
            s.commit(arrays_of(2), {"k": 2})
        assert f"pid {os.getpid()}" not in str(err.value)


# ------------------------------------------------------------ readers and commits


def test_a_reader_whose_generation_is_collected_at_every_read_retries_until_it_reads(
        tmp_path, monkeypatch):
    path = tmp_path / "s.zarr"
    committed(path, 1)
    writer = open_store(path, "a")
    reader = open_store(path, "r")
    real = BasisStore._load
    moves = []

    def slow_reader(self, k, digest):
        if self is reader and len(moves) < 6:  # the writer commits twice during each read
            for _ in range(2):
                g = writer.generation + 1
                writer.commit(arrays_of(g), {"k": g})
            moves.append(k)
        return real(self, k, digest)
    monkeypatch.setattr(BasisStore, "_load", slow_reader)
    state = reader.read()
    assert len(moves) == 6 and state.generation == writer.generation == 13
    assert state.attrs == {"k": 13}
    reader.close()
    writer.close()


def test_readers_in_a_loop_during_commits_never_fail(tmp_path):
    path = tmp_path / "s.zarr"
    committed(path, 1)
    failures, reads = [], []
    done = threading.Event()

    def read_loop():
        while not done.is_set():
            try:
                with open_store(path, "r") as reader:
                    state = reader.read()
                k = state.generation
                assert state.attrs == {"k": k}
                assert np.array_equal(state.arrays["U"], arrays_of(k)["U"])
                reads.append(k)
            except Exception as exc:  # noqa: BLE001 - every failure is collected
                failures.append(repr(exc))
    threads = [threading.Thread(target=read_loop) for _ in range(2)]
    for t in threads:
        t.start()
    with open_store(path, "a") as writer:
        for k in range(2, 40):
            writer.commit(arrays_of(k), {"k": k})
    done.set()
    for t in threads:
        t.join()
    assert failures == []
    assert reads  # each thread read at least once before the writer ended (or after)


# ---------------------------------------------------------------------- full disk


class _Disk:
    """``os.write`` that fails with ENOSPC once ``budget`` bytes were written."""

    def __init__(self, budget):
        self.budget = budget
        self.real = os.write

    def __call__(self, fd, data):
        if self.budget <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        n = self.real(fd, bytes(data)[: self.budget])
        self.budget -= n
        return n


def _bytes_of_first_commits(path, monkeypatch):
    disk = _Disk(1 << 40)
    monkeypatch.setattr(os, "write", disk)
    committed(path, 2)
    monkeypatch.undo()
    return (1 << 40) - disk.budget


def test_a_full_disk_at_every_byte_budget_of_the_first_commits(tmp_path, monkeypatch):
    total = _bytes_of_first_commits(tmp_path / "probe.zarr", monkeypatch)
    budgets = sorted(set(range(0, total, max(1, total // 60))) | {total - 1})
    for i, budget in enumerate(budgets):
        path = tmp_path / f"s{i}.zarr"
        stage = {"k": -1}
        monkeypatch.setattr(os, "write", _Disk(budget))
        try:
            with BasisStore.create(path, n=50, inner_fingerprint=FP) as s:
                stage["k"] = 0
                before = tree(path)
                for k in (1, 2):
                    s.commit(arrays_of(k), {"k": k})
                    stage["k"] = k
                    before = tree(path)
        except StoreError as exc:
            assert "No space left on device" in str(exc), (budget, exc)
            monkeypatch.undo()
            if stage["k"] < 0:  # the creation failed: nothing is left, the store is named
                assert str(path) in str(exc) and "nothing was left behind" in str(exc)
                assert not path.exists(), (budget, sorted(tree(path)))
                committed(path, 2)  # once space is freed, creating works
            else:  # a commit failed: the last one is intact and the store continues
                assert tree(path) == before, budget
                assert_generation(path, stage["k"])
                with open_store(path, "a") as s:
                    s.commit(arrays_of(stage["k"] + 1), {"k": stage["k"] + 1})
        else:
            monkeypatch.undo()
        assert check_store(open_storage(path)).healthy, budget


def test_cli_full_disk_at_creation_leaves_nothing_and_resume_works(tmp_path, monkeypatch,
                                                                   capsys):
    A = np.random.default_rng(0).standard_normal((30, 40))
    np.save(tmp_path / "a.npy", A)
    store = tmp_path / "basis.zarr"
    args = ["ingest", str(tmp_path / "a.npy"), str(store), "--block", "10", "--quiet"]
    for budget in (0, 100, 900):
        monkeypatch.setattr(os, "write", _Disk(budget))
        assert main([*args, "--resume"]) == 2
        monkeypatch.undo()
        err = capsys.readouterr().err
        assert f"STORE {store}" in err and "No space left on device" in err, err
        assert not store.exists()
    assert main([*args, "--resume"]) == 0
    assert main(["check", str(store)]) == 0


# ------------------------------------------------------------------------ damage


def test_edited_root_attributes_are_named_by_file_and_field(tmp_path, capsys):
    path = tmp_path / "s.zarr"
    committed(path, 2)
    meta = path / "zarr.json"
    original = meta.read_text()
    for field, value in (("n", 51), ("dtype", "float32"), ("chunk_bytes", 4096)):
        doc = json.loads(original)
        doc["attributes"][field] = value
        meta.write_text(json.dumps(doc))
        with pytest.raises(StoreFormatError, match=rf"root attribute '{field}' in "
                           rf".*zarr.json is {value!r}"):
            open_store(path)
        assert main(["info", str(path)]) == 2
        err = capsys.readouterr().err
        assert "zarr.json" in err and repr(field) in err and "broadcast" not in err
        assert main(["check", str(path)]) == 2
        out = capsys.readouterr().out
        assert out.count("\n") == 1 and out.startswith("damaged: ") and repr(field) in out
    meta.write_text(original)
    assert main(["check", str(path)]) == 0


def test_resume_never_deletes_a_store_whose_pointer_is_missing(tmp_path, capsys):
    A = np.random.default_rng(1).standard_normal((30, 60))
    np.save(tmp_path / "a.npy", A)
    np.save(tmp_path / "b.npy", A[:, :20])
    store = tmp_path / "basis.zarr"
    args = ["ingest", str(tmp_path / "a.npy"), str(store), "--block", "10", "--quiet"]
    assert main(args) == 0
    (store / POINTER_NAME).unlink()
    before = tree(store)
    for source in ("a.npy", "b.npy"):
        assert main(["ingest", str(tmp_path / source), str(store), "--resume", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "pointer current.json is missing" in err and "nothing was deleted" in err
        assert "The last readable generation is" in err, err
        assert tree(store) == before
    assert main(["check", str(store)]) == 2
    assert "The last readable generation is" in capsys.readouterr().out


def test_a_pointer_rolled_back_is_reported_and_nothing_is_deleted(tmp_path, capsys):
    path = tmp_path / "s.zarr"
    committed(path, 2)
    old = (path / GENERATIONS / "g00000001" / MARKER_NAME).read_bytes()
    (path / POINTER_NAME).write_bytes(old)  # current.json replaced by an older copy
    before = tree(path)
    with pytest.raises(StoreFormatError, match=r"names generation 1, but generation 2 was "
                       r"committed after it .*Nothing was deleted"):
        open_store(path, "a")
    assert tree(path) == before
    assert main(["check", str(path)]) == 2
    assert "generation 2 was committed after it" in capsys.readouterr().out
    (path / POINTER_NAME).write_bytes(
        (path / GENERATIONS / "g00000002" / MARKER_NAME).read_bytes())  # the advice given
    assert_generation(path, 2)
    assert main(["check", str(path)]) == 0


@pytest.mark.parametrize("damage", ["flip", "missing-chunk", "attrs", "pointer"])
def test_each_damage_is_reported_naming_what_and_the_last_readable_generation(
        tmp_path, capsys, damage):
    path = tmp_path / "s.zarr"
    committed(path, 3)
    if damage in GENERATION_DAMAGE:
        damage_generation(path / GENERATIONS / "g00000003", damage, attr="k", value=99)
    else:
        (path / POINTER_NAME).write_text("{not json")
    before = tree(path)
    assert main(["check", str(path)]) == 2
    lines = capsys.readouterr().out.splitlines()
    assert lines and all(line.startswith("damaged: ") for line in lines)
    assert any("generation 3" in line or "current.json" in line for line in lines), lines
    if damage == "pointer":
        assert "The last readable generation is 3" in lines[0]
    else:
        assert "The last readable generation is 2" in " ".join(lines), lines  # the previous
    np.save(tmp_path / "a.npy", np.ones((50, 30)))
    assert main(["ingest", str(tmp_path / "a.npy"), str(path), "--resume"]) == 2
    assert tree(path) == before  # nothing repaired by deletion


def test_a_lock_that_is_a_directory_names_the_lock_and_the_store(tmp_path, capsys):
    path = tmp_path / "s.zarr"
    committed(path, 1)
    (path / "writer.lock").mkdir()
    with pytest.raises(StoreError, match=r"its lock .*writer.lock is a directory"):
        open_store(path, "a")
    np.save(tmp_path / "a.npy", np.ones((50, 4)))
    assert main(["ingest", str(tmp_path / "a.npy"), str(path), "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"STORE {path}" in err and "writer.lock is a directory" in err


@pytest.mark.parametrize("weights", [[1.0, 0.0, 2.0], [1.0, -1.0, 1.0], [1.0, np.nan, 1.0]])
def test_bad_inner_weights_name_inner(tmp_path, capsys, weights):
    np.save(tmp_path / "a.npy", np.ones((3, 4)))
    np.save(tmp_path / "w.npy", np.array(weights))
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "s.zarr"),
                 "--inner", str(tmp_path / "w.npy")]) == 2
    err = capsys.readouterr().err
    assert "--inner" in err and "`weights`" not in err, err
    assert not (tmp_path / "s.zarr").exists()


@pytest.mark.parametrize("matrix", ["singular", "not-spd", "asymmetric"])
def test_bad_inner_matrices_name_inner(tmp_path, capsys, matrix):
    M = {"singular": np.array([[1.0, 1.0], [1.0, 1.0]]),
         "not-spd": np.array([[1.0, 0.0], [0.0, -1.0]]),
         "asymmetric": np.array([[2.0, 1.0], [0.0, 2.0]])}[matrix]
    np.save(tmp_path / "a.npy", np.ones((2, 4)))
    np.save(tmp_path / "m.npy", M)
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "s.zarr"),
                 "--inner", str(tmp_path / "m.npy")]) == 2
    err = capsys.readouterr().err
    assert "--inner" in err and "`M`" not in err, err


def test_a_source_of_snapshots_of_size_zero_names_source(tmp_path, capsys):
    np.save(tmp_path / "a.npy", np.ones((0, 4)))
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "s.zarr")]) == 2
    err = capsys.readouterr().err
    assert "SOURCE" in err and "size 0" in err and "`n`" not in err, err
    assert not (tmp_path / "s.zarr").exists()


# ------------------------------------------------------------------- the campaign


def test_the_fault_campaign_runs_its_damage_scenarios(monkeypatch, capsys):
    """The bench campaign (bench/fault_campaign.py) on its fastest group: every line passes."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[3] / "bench"))
    import fault_campaign

    assert fault_campaign.main(["--no-s3", "--only", "damage", "--seconds", "600"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines()
             if line.startswith(("PASS", "FAIL"))]
    assert len(lines) == 8 and all(line.startswith("PASS  damage") for line in lines)


def test_if_match_on_an_object_deleted_meanwhile_is_not_matched(s3):
    """A zombie renewing a lease its taker has released and deleted: refused, not an error."""
    storage = open_storage(f"{s3}/gone")
    tag = storage.put_if_absent("lease", b"mine")
    storage.delete("lease")
    assert storage.put_if_match("lease", b"again", tag) is None
    assert storage.list() == []
