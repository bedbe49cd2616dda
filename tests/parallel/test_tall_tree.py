"""A tree of tall leaves gives the in-memory tree's result, with every basis in panels."""

import numpy as np

from streamsvd.parallel import tall_tree_compress, tree_compress
from streamsvd.parallel.tall import TallCompressor
from streamsvd.testing import with_spectrum

EPS = np.finfo(float).eps


def test_tall_tree_equals_the_tree_to_rounding(tmp_path):
    A = with_spectrum(np.logspace(0, -9, 30), 400, 120, np.random.default_rng(0))
    kw = dict(block=10, leaf_columns=30, max_rank=8, finalize=True)
    tall = tall_tree_compress(A, workdir=tmp_path / "wd", chunk_rows=100, **kw)
    tree = tree_compress(A, **kw)
    assert isinstance(tall, TallCompressor) and tall.rank == tree.rank == 8
    tol = 50 * max(A.shape) * EPS
    assert np.abs(tall.amplitudes - tree.amplitudes).max() <= tol * tree.amplitudes[0]
    U = np.asarray(tall.factors()[0])
    assert np.abs(np.abs(U.T @ tree.expansion.U) - np.eye(8)).max() <= tol
    assert abs(tall.error_bound - tree.error_bound) <= tol * np.linalg.norm(A)
    assert any((tmp_path / "wd").rglob("*"))  # the panels lived in the workdir
