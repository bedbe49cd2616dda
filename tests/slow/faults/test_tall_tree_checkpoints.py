"""A tall-tree run killed midway resumes from the leaves and merges it committed.

The process is killed with SIGKILL at some point of its run (whenever a first node is
committed, or at its end: how far it got is not asserted); the same call run again gives
the uninterrupted result bit for bit (a node is handed on as it is loaded back, in both
runs).
"""

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np

from streamsvd.parallel.tall import TallCompressor
from streamsvd.store import POINTER_NAME
from streamsvd.testing import with_spectrum

SCRIPT = textwrap.dedent("""
    import sys
    import dask
    from streamsvd.parallel import tall_tree_compress
    dask.config.set(scheduler="synchronous")
    with tall_tree_compress(sys.argv[1], block=10, leaf_columns=20, max_rank=8,
                            chunk_rows=500, workdir=sys.argv[2], store=sys.argv[3]):
        pass
""")


def _run(npy, workdir, store):
    from streamsvd.parallel import tall_tree_compress

    with tall_tree_compress(str(npy), block=10, leaf_columns=20, max_rank=8, chunk_rows=500,
                            workdir=workdir, store=store):
        pass


def test_killed_tall_tree_resumes_from_its_committed_nodes(tmp_path):
    A = with_spectrum(np.logspace(0, -9, 30), 3000, 400, np.random.default_rng(4))
    np.save(tmp_path / "a.npy", A)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    store, parts = tmp_path / "killed.zarr", tmp_path / "killed.zarr.tree"
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(tmp_path / "a.npy"),
                             str(tmp_path / "wk"), str(store)], env=env)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        if parts.is_dir() and any((p / POINTER_NAME).exists() for p in parts.iterdir()):
            break
        time.sleep(0.05)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    # the same call again: resumes from what was committed (or finds the store done; a
    # kill within the store's creation leaves leftovers, which the creation replaces)
    if not (store / POINTER_NAME).exists():
        _run(tmp_path / "a.npy", tmp_path / "wk", store)
    _run(tmp_path / "a.npy", tmp_path / "ww", tmp_path / "whole.zarr")
    assert not parts.exists()  # removed once the root was committed
    with TallCompressor.open(store, mode="r") as a, \
            TallCompressor.open(tmp_path / "whole.zarr", mode="r") as b:
        assert np.array_equal(np.asarray(a.factors()[0]), np.asarray(b.factors()[0]))
        assert np.array_equal(a.factors()[1], b.factors()[1])
        assert a.error_bound == b.error_bound and a.n_seen == b.n_seen == A.shape[1]
