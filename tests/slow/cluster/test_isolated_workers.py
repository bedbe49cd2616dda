"""A real ``dask scheduler`` and ``dask worker`` processes that share nothing with the client.

Each worker runs in its own working directory and ``TMPDIR`` and, where ``unshare -rm``
is allowed, with the client's directory covered by an empty tmpfs
(:mod:`streamsvd.testing.cluster`). Source and store live on a moto S3 server; the
workers get their credentials from their own environment, never from the task graph.
Covered: the tree and the tall mode through the API and the CLI (equal to the same modes
run in this process), errors that name the worker and the remedy (a path the workers
cannot see, workers without credentials, the tall mode's temporary panels), BLAS threads
from the workers' own cores, the tree's default leaves following the workers, and a
client killed midway whose workers' committed nodes the next run resumes from (the tree
and the tall tree).
"""

import os
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from streamsvd.cli import main
from streamsvd.errors import SourceError, StoreError
from streamsvd.testing import with_spectrum

pytest.importorskip("distributed")
pytest.importorskip("moto.server")
pytest.importorskip("s3fs")

BUCKET = "cluster-tests"


@pytest.fixture(scope="module")
def hidden_dir():
    """A directory of this process that the workers cannot see (where namespaces allow)."""
    path = tempfile.mkdtemp(prefix="streamsvd-client-")
    yield path
    import shutil

    shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def server_env(s3_environment):
    """The S3 server's variables, with the bucket of these tests made."""
    import s3fs

    s3fs.S3FileSystem().mkdir(BUCKET)
    return s3_environment


@pytest.fixture(scope="module")
def cluster(server_env, workers_environment, hidden_dir):
    from streamsvd.testing.cluster import start

    env = workers_environment(**server_env)  # the workers' own credentials
    running = start(workers=2, env=env, hidden=[hidden_dir])
    yield running
    running.stop()


@pytest.fixture
def client(cluster):
    from distributed import Client

    with Client(cluster.address, timeout="30s") as c:
        yield c


@pytest.fixture(scope="module")
def data(server_env):
    rng = np.random.default_rng(7)
    A = with_spectrum(np.logspace(0, -9, 30), 96, 120, rng)
    import zarr
    from zarr.storage import FsspecStore

    store = FsspecStore.from_url(f"s3://{BUCKET}/a.zarr", read_only=False)
    arr = zarr.create_array(store=store, shape=A.shape, dtype=A.dtype, chunks=(96, 16))
    arr[...] = A
    return A, f"s3://{BUCKET}/a.zarr"


def _same(sc, ref, A, *, exact):
    es, er = sc.expansion, ref.expansion
    assert sc.n_seen == ref.n_seen == A.shape[1]
    if exact:
        assert np.array_equal(es.U, er.U) and np.array_equal(es.V, er.V)
        assert sc.error_bound == ref.error_bound
        return
    tol = 50 * max(A.shape) * np.finfo(float).eps
    assert np.abs(es.U - er.U).max() <= tol
    assert np.abs(es.V - er.V).max() <= tol * np.linalg.norm(A, 2)
    assert abs(sc.error_bound - ref.error_bound) <= tol * np.linalg.norm(A)


@pytest.mark.parametrize("mode", ["tree", "tall"])
def test_api_on_isolated_workers_with_source_and_store_on_s3(client, data, mode):
    from streamsvd.parallel import open_compressor, tall_compress, tree_compress

    A, url = data
    store = f"s3://{BUCKET}/api-{mode}"
    if mode == "tree":
        run, kw = tree_compress, {"leaf_columns": 40}
    else:
        run, kw = tall_compress, {"chunk_rows": 32}
    with run(url, block=10, max_rank=8, client=client, store=store, finalize=True,
             **kw) as sc:
        assert sc.rank <= 8
    with run(A, block=10, max_rank=8, finalize=True, **kw) as ref:  # the same, here
        with open_compressor(store) as back:
            _same(back, ref, A, exact=mode == "tree")


@pytest.mark.parametrize("mode", ["tree", "tall"])
def test_cli_on_isolated_workers_with_source_and_store_on_s3(cluster, data, mode, tmp_path):
    from streamsvd.parallel import open_compressor

    A, url = data
    np.save(tmp_path / "a.npy", A)
    extra = ["--tall", "--chunk-rows", "32"] if mode == "tall" else ["--leaf-columns", "40"]
    opts = ["--block", "10", "--max-rank", "8", "--quiet", *extra]
    assert main(["ingest", str(tmp_path / "a.npy"), str(tmp_path / "ref"), *opts,
                 "--scheduler", "threads"]) == 0
    store = f"s3://{BUCKET}/cli-{mode}"
    assert main(["ingest", url, store, *opts, "--scheduler", cluster.address]) == 0
    with open_compressor(tmp_path / "ref") as ref, open_compressor(store) as sc:
        assert sc.rank <= 8
        _same(sc, ref, A, exact=mode == "tree")


def test_a_path_the_workers_cannot_see_is_named_with_the_remedy(client, cluster, data,
                                                               hidden_dir):
    from streamsvd.parallel import tree_compress

    if not cluster.hidden:
        pytest.skip("no user and mount namespaces here: the workers see the client's files")
    A, _ = data
    path = os.path.join(hidden_dir, "a.npy")
    np.save(path, A)
    with pytest.raises(SourceError, match="dask workers .* could not see it") as info:
        tree_compress(path, block=10, client=client)
    assert "(this process can)" in str(info.value)
    assert "object store" in str(info.value)


def test_tall_panels_in_a_client_temporary_directory_are_named(client, cluster, data,
                                                             hidden_dir, monkeypatch):
    from streamsvd.parallel import tall_compress

    if not cluster.hidden:
        pytest.skip("no user and mount namespaces here: the workers see the client's files")
    A, _ = data
    monkeypatch.setattr(tempfile, "tempdir", hidden_dir)
    with pytest.raises(StoreError, match="panels' temporary directory .* could not see it"):
        tall_compress(A, block=10, max_rank=8, client=client, chunk_rows=32)


def test_workers_without_credentials_are_told_how_to_get_them(server_env, data,
                                                             workers_environment):
    from distributed import Client

    from streamsvd.parallel import tall_compress, tree_compress
    from streamsvd.testing.cluster import start

    _, url = data
    env = workers_environment(AWS_ENDPOINT_URL=server_env["AWS_ENDPOINT_URL"],  # no keys
                              AWS_EC2_METADATA_DISABLED="true")
    # the client's secrets given as options: they must not reach the workers
    options = {"key": server_env["AWS_ACCESS_KEY_ID"],
               "secret": server_env["AWS_SECRET_ACCESS_KEY"]}
    bare = start(workers=1, env=env)
    try:
        with Client(bare.address, timeout="30s") as c:
            with pytest.raises(SourceError, match="could not reach it with the workers' own"
                               " credentials") as info:
                tree_compress(url, block=10, client=c)
            assert "AWS_ACCESS_KEY_ID" in str(info.value)
            with pytest.raises(StoreError, match="`store` .* own credentials"):
                tall_compress(np.ones((8, 4)), block=2, client=c, chunk_rows=4,
                              store=f"s3://{BUCKET}/nocred", storage_options=options)
    finally:
        bare.stop()


def test_blas_threads_and_default_leaves_follow_the_workers(client):
    from streamsvd.parallel.spec import default_leaf_columns
    from streamsvd.parallel.workers import blas_plan, worker_threads

    cores = len(os.sched_getaffinity(0))
    plan = blas_plan(client)
    assert isinstance(plan, dict) and len(plan) == 2
    assert set(plan.values()) == {max(1, cores // 2)}  # two 1-thread workers on one host
    assert worker_threads(client) == 2
    # 120 columns in blocks of 10 on 2 workers: two leaves of 60, not one of 100 and 20
    assert default_leaf_columns(120, 10, tasks=worker_threads(client)) == 60


def _kill_once_a_node_is_committed(proc, fs, parts):
    """SIGKILL the client ``proc`` once a node under ``parts`` has a pointer (or it ends)."""
    from streamsvd.store import POINTER_NAME

    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        fs.invalidate_cache()
        if fs.exists(parts) and any(fs.exists(f"{p}/{POINTER_NAME}") for p in fs.ls(parts)):
            break
        time.sleep(0.05)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()


CLIENT = """
import sys
from distributed import Client
from streamsvd.parallel import tree_compress
with Client(sys.argv[1]) as client:
    with tree_compress(sys.argv[2], block=10, leaf_columns=10, max_rank=8, client=client,
                       store=sys.argv[3]):
        pass
"""


def test_a_killed_client_leaves_the_workers_nodes_to_the_next_run(cluster, data):
    """The workers commit the nodes to S3: a new client resumes from them (bit for bit)."""
    import s3fs

    from streamsvd.parallel import tree_compress
    from streamsvd.store import POINTER_NAME
    from streamsvd.stream.compressor import StreamCompressor

    A, url = data
    store = f"s3://{BUCKET}/killed"
    fs = s3fs.S3FileSystem()
    proc = subprocess.Popen([sys.executable, "-c", CLIENT, cluster.address, url, store],
                            env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    _kill_once_a_node_is_committed(proc, fs, f"{BUCKET}/killed.tree")
    fs.invalidate_cache()
    if fs.exists(f"{BUCKET}/killed") and not fs.exists(f"{BUCKET}/killed/{POINTER_NAME}"):
        fs.rm(f"{BUCKET}/killed", recursive=True)  # killed within the store's creation
    from distributed import Client

    with Client(cluster.address, timeout="30s") as client:
        if not fs.exists(f"{BUCKET}/killed/{POINTER_NAME}"):
            with tree_compress(url, block=10, leaf_columns=10, max_rank=8, client=client,
                               store=store):
                pass
    with tree_compress(A, block=10, leaf_columns=10, max_rank=8, finalize=True) as whole:
        with StreamCompressor.open(store, mode="r") as resumed:
            _same(resumed, whole, A, exact=True)
    fs.invalidate_cache()
    assert not fs.exists(f"{BUCKET}/killed.tree")


def test_tall_tree_on_isolated_workers_with_panels_on_s3(client, data):
    """Tall leaves in parallel on the workers, every panel on S3: the tree's result."""
    from streamsvd.parallel import tall_tree_compress, tree_compress

    A, url = data
    tall = tall_tree_compress(url, workdir=f"s3://{BUCKET}/scratch", block=10,
                              leaf_columns=30, chunk_rows=32, max_rank=8, client=client,
                              store=f"s3://{BUCKET}/tall-tree", finalize=True)
    tree = tree_compress(A, block=10, leaf_columns=30, max_rank=8, finalize=True)
    tol = 50 * max(A.shape) * np.finfo(float).eps
    assert tall.rank == tree.rank == 8
    assert np.abs(tall.amplitudes - tree.amplitudes).max() <= tol * tree.amplitudes[0]
    U = np.asarray(tall.factors()[0])
    assert np.abs(np.abs(U.T @ tree.expansion.U) - np.eye(8)).max() <= tol
    tall.close()


TALL_CLIENT = """
import sys
from distributed import Client
from streamsvd.parallel import tall_tree_compress
with Client(sys.argv[1]) as client:
    with tall_tree_compress(sys.argv[2], workdir=sys.argv[3], block=10, leaf_columns=10,
                            chunk_rows=32, max_rank=8, client=client, store=sys.argv[4]):
        pass
"""


def test_a_killed_tall_tree_client_leaves_the_workers_nodes_to_the_next_run(cluster, data):
    """The tall tree's nodes, committed to S3 by the workers, resume it (bit for bit)."""
    import s3fs

    from streamsvd.parallel import tall_tree_compress
    from streamsvd.parallel.tall import TallCompressor
    from streamsvd.store import POINTER_NAME

    A, url = data
    store, workdir = f"s3://{BUCKET}/tall-killed", f"s3://{BUCKET}/tall-killed-work"
    fs = s3fs.S3FileSystem()
    proc = subprocess.Popen([sys.executable, "-c", TALL_CLIENT, cluster.address, url,
                             workdir, store],
                            env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    parts = f"{BUCKET}/tall-killed.tree"
    _kill_once_a_node_is_committed(proc, fs, parts)
    from distributed import Client

    kw = dict(block=10, leaf_columns=10, chunk_rows=32, max_rank=8)
    with Client(cluster.address, timeout="30s") as client:
        fs.invalidate_cache()
        if not fs.exists(f"{BUCKET}/tall-killed/{POINTER_NAME}"):  # leftovers are replaced
            tall_tree_compress(url, workdir=workdir, client=client, store=store,
                               **kw).close(finalize=False)
        tall_tree_compress(url, workdir=f"{workdir}-whole", client=client,
                           store=f"{store}-whole", **kw).close(finalize=False)
    with TallCompressor.open(store, mode="r") as a, \
            TallCompressor.open(f"{store}-whole", mode="r") as b:
        assert np.array_equal(np.asarray(a.factors()[0]), np.asarray(b.factors()[0]))
        assert np.array_equal(a.factors()[1], b.factors()[1])
        assert a.error_bound == b.error_bound and a.n_seen == b.n_seen == A.shape[1]
    fs.invalidate_cache()
    assert not fs.exists(parts)
