"""A tree run killed midway resumes from the leaves and merges it committed.

The process is killed with SIGKILL at some point of its run (whenever a first node is
committed, or at its end: how far it got is not asserted); the same call run again gives
the uninterrupted result bit for bit (a loaded node is the computed one, the code path is
the same).
"""

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np

from streamsvd.store import POINTER_NAME
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum

SCRIPT = textwrap.dedent("""
    import sys
    import dask
    import numpy as np
    from streamsvd.parallel import tree_compress
    dask.config.set(scheduler="synchronous")
    with tree_compress(sys.argv[1], block=10, leaf_columns=20, max_rank=8,
                       store=sys.argv[2]):
        pass
""")


def test_killed_tree_resumes_from_its_committed_nodes(tmp_path):
    rng = np.random.default_rng(3)
    A = with_spectrum(np.logspace(0, -9, 30), 3000, 600, rng)
    np.save(tmp_path / "a.npy", A)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    store, parts = tmp_path / "killed.zarr", tmp_path / "killed.zarr.tree"
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(tmp_path / "a.npy"),
                             str(store)], env=env)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        if parts.is_dir() and any((p / POINTER_NAME).exists() for p in parts.iterdir()):
            break
        time.sleep(0.05)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    from streamsvd.parallel import tree_compress

    # the same call again: resumes from what was committed (or finds the store done); a
    # kill within the store's creation leaves a store without pointer, removed first
    if store.exists() and not (store / POINTER_NAME).exists():
        shutil.rmtree(store)
    if not store.exists():
        with tree_compress(str(tmp_path / "a.npy"), block=10, leaf_columns=20, max_rank=8,
                           store=store):
            pass
    with tree_compress(str(tmp_path / "a.npy"), block=10, leaf_columns=20, max_rank=8,
                       store=tmp_path / "whole.zarr"):
        pass
    assert not parts.exists()  # removed once the root was committed
    with StreamCompressor.open(store, mode="r") as a, \
            StreamCompressor.open(tmp_path / "whole.zarr", mode="r") as b:
        ea, eb = a.expansion, b.expansion
        assert np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)
        assert a.error_bound == b.error_bound and a.n_seen == b.n_seen == A.shape[1]
        assert a.rank <= 8
