"""A tree run killed midway resumes from the leaves and merges it committed.

The process is killed with SIGKILL at some point of its run (whenever a first node is
committed, or at its end: how far it got is not asserted); the same call run again gives
the uninterrupted result bit for bit (a loaded node is the computed one, the code path is
the same).
"""

import shutil
import textwrap

import numpy as np

from streamsvd.store import POINTER_NAME
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum

from ._kills import kill_after_a_committed_node

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
    store, parts = tmp_path / "killed.zarr", tmp_path / "killed.zarr.tree"
    kill_after_a_committed_node([SCRIPT, str(tmp_path / "a.npy"),
                                 str(store)], parts)
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
