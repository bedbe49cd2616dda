"""Basis stores and sources in an object store: a real S3-compatible server on localhost.

The ``s3`` fixture (conftest) gives a fresh bucket on a moto server started for the
session on 127.0.0.1; the ``AWS_*`` variables point this process and its subprocesses
(the CLI, dask workers) at it. Covered: the store's round trip and garbage collection,
the writer lease (refusal, expiry, takeover, lost races, loss while open), the
conditional pointer switch, and the CLI from an ``s3://`` source into an ``s3://`` store
(bit for bit the local result, SIGKILL and ``--resume``, a second writer refused) in
memory, tree and tall modes on a LocalCluster.
"""

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from streamsvd.cli import main
from streamsvd.engine.record import HISTORY_FIELDS
from streamsvd.errors import (
    InputError,
    OptionalDependencyError,
    StoreError,
    StoreLockedError,
)
from streamsvd.storage import LocalStorage, ObjectStorage, open_storage
from streamsvd.storage.lease import Lease
from streamsvd.store import GENERATIONS, LEASE_NAME, POINTER_NAME, BasisStore, open_store
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum


def _write_zarr(url, A, chunks=(None, 16)):
    import zarr
    from zarr.storage import FsspecStore

    store = FsspecStore.from_url(url, read_only=False)
    arr = zarr.create_array(store=store, shape=A.shape, dtype=A.dtype,
                            chunks=(A.shape[0], chunks[1]))
    arr[...] = A


def _arrays(store):
    with open_store(store, "r") as st:
        state = st.read()
        return {k: np.array(v) for k, v in state.arrays.items()}, state.attrs


def _assert_same_store(a, b):
    arrays_a, attrs_a = _arrays(a)
    arrays_b, attrs_b = _arrays(b)
    assert sorted(arrays_a) == sorted(arrays_b)
    seconds = HISTORY_FIELDS.index("seconds")  # wall time of each update: not data
    for name in arrays_a:
        if name == "history":
            arrays_a[name][:, seconds] = arrays_b[name][:, seconds] = 0.0
        assert np.array_equal(arrays_a[name], arrays_b[name]), name
    assert attrs_a["source_offset"] == attrs_b["source_offset"]
    with StreamCompressor.open(a, mode="r") as sa, StreamCompressor.open(b, mode="r") as sb:
        ea, eb = sa.expansion, sb.expansion
        assert np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)
        assert sa.error_bound == sb.error_bound


# --------------------------------------------------------------------- storage


def test_server_enforces_conditional_writes(s3):
    storage = open_storage(f"{s3}/cond")
    assert isinstance(storage, ObjectStorage) and storage.conditional
    tag = storage.put_if_absent("x", b"one")
    assert tag is not None
    assert storage.put_if_absent("x", b"two") is None
    assert storage.put_if_match("x", b"three", '"0123456789abcdef0123456789abcdef"') is None
    new = storage.put_if_match("x", b"four", tag)
    assert new is not None and new != tag
    assert storage.get_tagged("x") == (b"four", new)
    assert storage.get_tagged("missing") is None
    storage.delete("x")
    assert storage.list() == []


def test_storage_options_are_checked(tmp_path, s3):
    with pytest.raises(InputError, match="`storage_options` only apply to object-store URLs"):
        open_storage(tmp_path / "a", storage_options={"anon": True})
    with pytest.raises(InputError, match="`storage_options` must be a dict with string keys"):
        open_storage(f"{s3}/a", storage_options=["anon"])
    with pytest.raises(InputError, match="`path` must be a local path"):
        open_store(3.5)
    assert isinstance(open_storage(f"file://{tmp_path}/b"), LocalStorage)
    # the options reach the file system: a wrong endpoint cannot be reached
    with pytest.raises(StoreError, match=r"cannot be reached .* Check the endpoint"):
        open_store(f"{s3}/a", storage_options={"endpoint_url": "http://127.0.0.1:9",
                                               "config_kwargs": {"retries": {"max_attempts": 1}}})


def test_missing_object_store_package_names_the_extra(monkeypatch):
    import fsspec

    def missing(url, **kw):
        raise ImportError("Install s3fs to access S3")

    monkeypatch.setattr(fsspec, "url_to_fs", missing)
    with pytest.raises(OptionalDependencyError, match=r"pip install 'streamsvd\[s3\]'"):
        open_store("s3://bucket/basis.zarr")


def test_protocol_without_conditional_writes_is_read_only(tmp_path):
    with pytest.raises(StoreError, match="conditional writes .* s3:// only"):
        BasisStore.create("memory://streamsvd-test/basis.zarr", n=4, inner_fingerprint="e")


# ----------------------------------------------------------------------- store


def test_store_round_trip_and_gc_on_s3(s3, rng):
    url = f"{s3}/basis.zarr"
    st = BasisStore.create(url, n=50, inner_fingerprint="euclid", attrs={"k": 0})
    arrays = {}
    for k in range(1, 6):
        arrays[k] = {"U": rng.standard_normal((50, 3)), "s": rng.random(3)}
        assert st.commit(arrays[k], {"k": k}) == k
    assert st.path == url
    # the current and the previous generation are kept, every other one is deleted
    assert open_storage(url).list(GENERATIONS) == ["g00000004", "g00000005", "zarr.json"]
    with open_store(url, "r") as reader:
        state = reader.read()
        assert state.generation == 5 and state.attrs == {"k": 5}
        assert np.array_equal(state.arrays["U"], arrays[5]["U"])
        assert np.array_equal(reader.read(generation=4).arrays["s"], arrays[4]["s"])
    st.close()
    assert LEASE_NAME not in open_storage(url).list()
    with open_store(url, "a") as again:  # reopened for writing: the lease is free
        assert again.commit({"U": arrays[1]["U"]}) == 6


def test_store_appends_on_s3(s3, rng):
    from streamsvd.store.segments import Appended

    url = f"{s3}/appended.zarr"
    rows = rng.standard_normal((12, 2))
    with BasisStore.create(url, n=12, inner_fingerprint="e") as st:
        st.commit({}, appended={"T": Appended(rows[:4], unchanged=0)})
        st.commit({}, appended={"T": Appended(rows[:9], unchanged=4)})
    with open_store(url) as reader:
        assert np.array_equal(reader.read().arrays["T"], rows[:9])


def test_interrupted_creation_and_existing_store(s3):
    url = f"{s3}/c.zarr"
    storage = open_storage(url)
    # what a creation killed before its first pointer leaves
    storage.put("zarr.json", json.dumps({"zarr_format": 3, "node_type": "group",
                                         "attributes": {"format": "streamsvd-basis"}}).encode())
    storage.put("generations/g00000000/zarr.json", b"{}")
    with BasisStore.create(url, n=3, inner_fingerprint="e"):
        pass
    with pytest.raises(StoreError, match="already holds a basis store"):
        BasisStore.create(url, n=3, inner_fingerprint="e")
    other = f"{s3}/other"
    open_storage(other).put("data.bin", b"x")
    with pytest.raises(StoreError, match="holds other files"):
        BasisStore.create(other, n=3, inner_fingerprint="e")


# ----------------------------------------------------------------------- lease


def _foreign_lease(url, *, expires, host="elsewhere", pid=1):
    doc = {"holder": "f" * 32, "pid": pid, "host": host, "started": None,
           "since": "2026-01-01T00:00:00+00:00", "expires": expires}
    open_storage(url).put(LEASE_NAME, json.dumps(doc).encode())


def _store_under_foreign_lease(url, **lease):
    """Create a store at ``url`` and close it; then another writer holds its lease."""
    BasisStore.create(url, n=3, inner_fingerprint="e").close()
    _foreign_lease(url, **lease)


def test_second_writer_is_refused_while_the_first_holds_the_lease(s3):
    url = f"{s3}/l.zarr"
    with BasisStore.create(url, n=3, inner_fingerprint="e") as first:
        with pytest.raises(StoreLockedError, match=r"is locked by another writer: pid \d+"):
            open_store(url, "a")
        first.commit({"x": np.ones(3)})
        with open_store(url, "r") as reader:  # readers take no lease
            assert reader.read().generation == 1


def test_live_lease_of_another_host_is_respected(s3):
    url = f"{s3}/live.zarr"
    _store_under_foreign_lease(url, expires=time.time() + 3600)
    with pytest.raises(StoreLockedError, match="host 'elsewhere'"):
        open_store(url, "a")


def test_expired_lease_of_a_dead_writer_is_taken_over(s3, caplog):
    url = f"{s3}/exp.zarr"
    _store_under_foreign_lease(url, expires=time.time() - 5)
    with caplog.at_level(logging.WARNING, logger="streamsvd.storage.lockfile"):
        with open_store(url, "a") as st:
            st.commit({"x": np.zeros(3)})
    assert "taking over the lease" in caplog.text and "expired" in caplog.text


def test_lease_of_a_dead_process_on_this_host_is_taken_over(s3, caplog):
    url = f"{s3}/dead.zarr"
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    _store_under_foreign_lease(url, expires=time.time() + 3600, host=socket.gethostname(),
                               pid=proc.pid)
    with caplog.at_level(logging.WARNING, logger="streamsvd.storage.lockfile"):
        with open_store(url, "a"):
            pass
    assert "no longer running" in caplog.text


def test_conditional_write_losing_the_race_raises_store_locked(s3, monkeypatch):
    url = f"{s3}/race.zarr"
    _store_under_foreign_lease(url, expires=time.time() - 5)
    real = ObjectStorage.put_if_match

    def rival_first(self, key, data, tag):
        if key == LEASE_NAME:  # another writer takes the dead lease just before us
            _foreign_lease(url, expires=time.time() + 3600, host="rival")
        return real(self, key, data, tag)

    monkeypatch.setattr(ObjectStorage, "put_if_match", rival_first)
    with pytest.raises(StoreLockedError, match="lost the race"):
        open_store(url, "a")
    monkeypatch.undo()
    assert json.loads(open_storage(url).get(LEASE_NAME))["host"] == "rival"


def test_lease_is_renewed_while_held_and_loss_is_noticed(s3):
    storage = open_storage(f"{s3}/renew")
    lease = Lease(storage, "writer.lease", seconds=0.6)
    lease.acquire()
    try:
        first = json.loads(storage.get("writer.lease"))["expires"]
        time.sleep(1.0)  # several heartbeats of 0.2 s
        assert json.loads(storage.get("writer.lease"))["expires"] > first
        assert lease.owned()
        storage.put("writer.lease", b'{"expires": 0, "host": "rival"}')  # taken over
        assert not lease.owned()
    finally:
        lease.release()
    assert storage.get("writer.lease") == b'{"expires": 0, "host": "rival"}'


def test_commit_after_losing_the_lease_is_refused_and_changes_nothing(s3, rng):
    url = f"{s3}/lost.zarr"
    with BasisStore.create(url, n=4, inner_fingerprint="e") as st:
        st.commit({"x": np.ones(4)})
        pointer = open_storage(url).get(POINTER_NAME)
        _foreign_lease(url, expires=time.time() + 3600, host="rival")
        with pytest.raises(StoreLockedError, match="lost its writer lock"):
            st.commit({"x": np.zeros(4)})
        assert open_storage(url).get(POINTER_NAME) == pointer
        assert "g00000002" not in open_storage(url).list(GENERATIONS)


def test_pointer_switch_refuses_to_overwrite_another_writers_commit(s3, monkeypatch):
    url = f"{s3}/ptr.zarr"
    first = BasisStore.create(url, n=4, inner_fingerprint="e")
    open_storage(url).delete(LEASE_NAME)  # as if the lease had been broken by hand
    with open_store(url, "a") as second:
        second.commit({"x": np.full(4, 2.0)})
    with monkeypatch.context() as patch:  # the s3 fixture's variables stay set after it
        patch.setattr(first._lock, "owned", lambda: True)  # a zombie that thinks it leads
        with pytest.raises(StoreLockedError, match="changed by another writer"):
            first.commit({"x": np.full(4, 1.0)})
    first.close()
    with open_store(url) as reader:
        assert np.array_equal(reader.read().arrays["x"], np.full(4, 2.0))


# ------------------------------------------------------------------------- CLI


def _problem(rng, n=120, m=240):
    return with_spectrum(np.logspace(0, -9, 30), n, m, rng)


def _endpoint_in_options_only(monkeypatch):
    """Unset ``AWS_ENDPOINT_URL`` for the test and return it, for the options to name."""
    endpoint = os.environ["AWS_ENDPOINT_URL"]
    monkeypatch.delenv("AWS_ENDPOINT_URL")
    return endpoint


def test_cli_s3_source_into_s3_store_matches_local_bit_for_bit(s3, rng, tmp_path, capsys):
    A = _problem(rng)
    np.save(tmp_path / "a.npy", A)
    _write_zarr(f"{s3}/a.zarr", A)
    opts = ["--block", "16", "--max-rank", "10", "--quiet"]
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "basis.zarr"), *opts]) == 0
    assert main(["ingest", f"{s3}/a.zarr", f"{s3}/basis.zarr", *opts]) == 0
    _assert_same_store(tmp_path / "basis.zarr", f"{s3}/basis.zarr")
    assert main(["info", f"{s3}/basis.zarr", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["store"] == f"{s3}/basis.zarr" and summary["n_seen"] == A.shape[1]
    assert main(["export", f"{s3}/basis.zarr", str(tmp_path / "f.npz")]) == 0


def test_cli_storage_option_reaches_the_file_system(s3, rng, tmp_path, capsys, monkeypatch):
    A = _problem(rng, m=32)
    _write_zarr(f"{s3}/a.zarr", A)
    endpoint = _endpoint_in_options_only(monkeypatch)
    code = main(["ingest", f"{s3}/a.zarr", f"{s3}/b.zarr", "--quiet",
                 "--storage-option", f"endpoint_url={endpoint}",
                 "--storage-option", "client_kwargs.region_name=us-east-1"])
    assert code == 0, capsys.readouterr().err
    assert main(["info", f"{s3}/b.zarr", "--storage-option", f"endpoint_url={endpoint}"]) == 0
    assert main(["ingest", str(tmp_path / "x.npy"), str(tmp_path / "s"),
                 "--storage-option", "anon=true"]) == 2
    assert "--storage-option only applies to URLs" in capsys.readouterr().err
    assert main(["info", str(tmp_path), "--storage-option", "novalue"]) == 2
    assert "must be KEY=VALUE" in capsys.readouterr().err


def test_python_api_takes_storage_options(s3, rng, monkeypatch):
    """`storage_options=` reaches the file system from every facade of the library."""
    from streamsvd.parallel.cluster import TallCompressor, open_compressor, tree_compress

    A = _problem(rng, m=40)
    options = {"endpoint_url": _endpoint_in_options_only(monkeypatch)}
    with StreamCompressor(A.shape[0], max_rank=6, store=f"{s3}/m.zarr",
                          storage_options=options) as sc:
        sc.absorb(A)
    with StreamCompressor.open(f"{s3}/m.zarr", mode="r", storage_options=options) as back:
        np.testing.assert_array_equal(back.expansion.U, sc.expansion.U)
    with TallCompressor(A.shape[0], chunk_rows=32, max_rank=6, store=f"{s3}/t.zarr",
                        storage_options=options) as tc:
        tc.absorb(A)
    with TallCompressor.open(f"{s3}/t.zarr", mode="r", storage_options=options) as back:
        assert back.rank == 6 and back.finalized
    with open_compressor(f"{s3}/t.zarr", storage_options=options) as back:
        assert isinstance(back, TallCompressor) and back.n_seen == 40
    tree = tree_compress(A, block=10, leaf_columns=20, max_rank=6, store=f"{s3}/r.zarr",
                         storage_options=options)
    tree.close()
    with open_store(f"{s3}/r.zarr", "r", storage_options=options) as st:
        assert st.read().attrs["n_seen"] == 40
    with pytest.raises(InputError, match="`storage_options` only apply to object-store URLs"):
        StreamCompressor(4, store="local.zarr", storage_options=options)


def test_cli_missing_s3_source_is_a_clear_error(s3, capsys):
    assert main(["ingest", f"{s3}/nothing.zarr", f"{s3}/b.zarr"]) == 2
    err = capsys.readouterr().err
    assert f"SOURCE {s3}/nothing.zarr does not exist" in err


def _cli(*args):
    return [sys.executable, "-m", "streamsvd", *args]


def _wait_for(predicate, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.05)


def test_cli_sigkill_then_resume_on_s3_is_bit_identical(s3, rng, tmp_path):
    A = _problem(rng, n=150, m=400)
    np.save(tmp_path / "a.npy", A)
    _write_zarr(f"{s3}/a.zarr", A)
    opts = ["--block", "4", "--max-rank", "10", "--quiet"]  # 100 commits
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "ref.zarr"), *opts]) == 0
    store = f"{s3}/killed.zarr"
    storage = open_storage(store)
    env = dict(os.environ, PYTHONWARNINGS="ignore")

    def generation():
        seen = storage.get_tagged(POINTER_NAME)
        return -1 if seen is None else json.loads(seen[0])["generation"]

    def killed_runs(delays) -> int:
        """Run the ingest once per delay, killed that long after its first own commit."""
        kills = 0
        for delay in delays:
            before = generation()
            resume = ["--resume"] if before >= 0 else []
            if not resume and storage.list():
                storage.delete("")  # killed while the store itself was being created
            proc = subprocess.Popen(_cli("ingest", f"{s3}/a.zarr", store, *opts, *resume),
                                    env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            floor = max(before, 0)  # generation 0: the creation's commit (the empty state)
            try:  # kill once this run has committed an update of its own
                _wait_for(lambda p=proc, g=floor: generation() > g or p.poll() is not None)
            except AssertionError:
                proc.kill()
                raise
            time.sleep(delay)
            if proc.poll() is not None:
                _, err = proc.communicate()
                assert proc.returncode == 0, err.decode()
                return kills
            proc.send_signal(signal.SIGKILL)
            proc.communicate()
            kills += 1
            with StreamCompressor.open(store, mode="r") as reader:  # the last commit is whole
                assert reader.n_seen == reader.source_offset > 0
            # the killed writer's lease is left behind: the next run takes it over (dead pid)
        subprocess.run(_cli("ingest", f"{s3}/a.zarr", store, *opts, "--resume"),
                       check=True, capture_output=True, env=env)
        return kills

    if not killed_runs(np.random.default_rng(7).uniform(0.0, 0.4, 4)):
        # a fast writer finished before any kill: again from scratch, killed right after
        # its first commit (the comparison below holds whether or not a kill landed)
        storage.delete("")
        killed_runs([0.0])
    _assert_same_store(tmp_path / "ref.zarr", store)


def test_cli_second_writer_is_refused_while_the_first_runs(s3, rng, capsys):
    A = _problem(rng, n=150, m=600)
    _write_zarr(f"{s3}/a.zarr", A)
    store = f"{s3}/busy.zarr"
    storage = open_storage(store)
    proc = subprocess.Popen(_cli("ingest", f"{s3}/a.zarr", store, "--block", "4", "--quiet"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for(lambda: POINTER_NAME in storage.list() or proc.poll() is not None)
        assert proc.poll() is None, proc.communicate()[1].decode()
        assert main(["ingest", f"{s3}/a.zarr", store, "--resume", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert "is locked by another writer" in err and f"pid {proc.pid}" in err
    finally:
        proc.kill()
        proc.communicate()


@pytest.mark.parametrize("mode", ["tree", "tall"])
def test_cli_tree_and_tall_modes_on_a_local_cluster_with_s3(s3, rng, tmp_path, mode):
    pytest.importorskip("distributed")
    A = _problem(rng, n=96, m=80)
    np.save(tmp_path / "a.npy", A)
    _write_zarr(f"{s3}/a.zarr", A)
    extra = (["--tall", "--chunk-rows", "32"] if mode == "tall" else ["--leaf-columns", "40"])
    opts = ["--block", "10", "--max-rank", "8", "--quiet", "--scheduler", "local",
            "--workers", "2", *extra]
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "ref"), *opts]) == 0
    assert main(["ingest", f"{s3}/a.zarr", f"{s3}/{mode}", *opts]) == 0
    from streamsvd.parallel.cluster import open_compressor

    with open_compressor(tmp_path / "ref") as ref, open_compressor(f"{s3}/{mode}") as sc:
        assert sc.n_seen == ref.n_seen == A.shape[1]
        es, er = sc.expansion, ref.expansion
        if mode == "tree":  # the same tasks on the same data: bit for bit
            assert np.array_equal(es.U, er.U) and np.array_equal(es.V, er.V)
            assert sc.error_bound == ref.error_bound
        else:
            # the tall mode's final sweeps reduce row chunks on the cluster in the order
            # the workers finish, so two runs on local paths differ by rounding too:
            # LAPACK's test ratio (threshold 50) between the two stored bases
            tol = 50 * max(A.shape) * np.finfo(float).eps
            assert np.abs(es.U - er.U).max() <= tol
            assert np.abs(es.V - er.V).max() <= tol * np.linalg.norm(A, 2)
            assert abs(sc.error_bound - ref.error_bound) <= tol * np.linalg.norm(A)
    if mode == "tall":
        assert any(name.startswith("p") for name in open_storage(f"{s3}/tall").list("panels"))


def test_local_stores_work_without_the_s3_extra_and_urls_name_it(tmp_path):
    refuse = (
        "import importlib.abc, sys\n"
        "class _Refuse(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.split('.')[0] in {'s3fs', 'botocore', 'aiobotocore', 'moto', 'obstore'}:\n"
        "            raise ModuleNotFoundError(f'No module named {name!r}', name=name)\n"
        "sys.meta_path.insert(0, _Refuse())\n"
    )
    code = refuse + (
        "import numpy as np, streamsvd as ss\n"
        f"st = ss.BasisStore.create({str(tmp_path / 'b')!r}, n=3, inner_fingerprint='e')\n"
        "st.commit({'x': np.ones(3)}); st.close()\n"
        "try:\n"
        "    ss.open_store('s3://bucket/basis.zarr')\n"
        "except ss.errors.OptionalDependencyError as exc:\n"
        "    print(exc)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, cwd=Path(__file__).resolve().parents[3])
    assert out.returncode == 0, out.stderr
    assert "pip install 'streamsvd[s3]'" in out.stdout


def test_reader_whose_generation_is_collected_retries_from_the_new_pointer(s3, monkeypatch):
    url = f"{s3}/race-read.zarr"
    writer = BasisStore.create(url, n=4, inner_fingerprint="e")
    writer.commit({"x": np.full(4, 1.0)})
    reader = open_store(url, "r")
    real = BasisStore._load
    calls = []

    def writer_moves_on(self, k, digest):
        if self is reader and not calls:  # between the reader's pointer read and its load
            writer.commit({"x": np.full(4, 2.0)})
            writer.commit({"x": np.full(4, 3.0)})  # generation 1 is collected now
            assert "g00000001" not in open_storage(url).list(GENERATIONS)
        calls.append(k)
        return real(self, k, digest)

    monkeypatch.setattr(BasisStore, "_load", writer_moves_on)
    state = reader.read()
    assert calls == [1, 3] and np.array_equal(state.arrays["x"], np.full(4, 3.0))
    reader.close()
    writer.close()


def test_sources_at_urls(s3, rng, tmp_path, monkeypatch):
    from streamsvd.errors import SourceError
    from streamsvd.io.open import open_source

    A = rng.standard_normal((20, 30))
    _write_zarr(f"{s3}/a.zarr", A)
    with open_source(f"{s3}/a.zarr") as src:
        assert src.shape == (20, 30) and np.array_equal(src.read(3, 9), A[:, 3:9])
    endpoint = _endpoint_in_options_only(monkeypatch)  # the options alone reach the server
    with open_source(f"{s3}/a.zarr", storage_options={"endpoint_url": endpoint}) as src:
        assert np.array_equal(src.read(0, 30), A)
    import zarr

    zarr.create_array(store=str(tmp_path / "b.zarr"), shape=A.shape, dtype=A.dtype)[...] = A
    with open_source(f"file://{tmp_path / 'b.zarr'}") as src:
        assert np.array_equal(src.read(0, 30), A)
    with pytest.raises(InputError, match="`storage_options` only apply to a URL source"):
        open_source(A, storage_options={"anon": True})
    with pytest.raises(InputError, match="read from local paths only"):
        open_source(f"{s3}/a.npy")
    with pytest.raises(SourceError, match="does not exist"):
        open_source(f"{s3}/missing.zarr", storage_options={"endpoint_url": endpoint})
