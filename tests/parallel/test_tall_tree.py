"""A tree of tall leaves gives the in-memory tree's result, with every basis in panels."""

import shutil

import numpy as np
import pytest

import streamsvd.parallel.tall_tree as tall_tree
from streamsvd.errors import StoreError
from streamsvd.parallel import tall_tree_compress, tree_compress
from streamsvd.parallel.checkpoints import Checkpoints
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


def _same_store(a_path, b_path):
    with TallCompressor.open(a_path, mode="r") as a, TallCompressor.open(b_path, mode="r") as b:
        assert np.array_equal(np.asarray(a.factors()[0]), np.asarray(b.factors()[0]))
        assert np.array_equal(a.factors()[1], b.factors()[1])
        assert a.error_bound == b.error_bound and a.n_seen == b.n_seen


def test_committed_tall_nodes_are_loaded_and_nothing_below_them_runs(tmp_path, monkeypatch):
    A = with_spectrum(np.logspace(0, -9, 20), 300, 60, np.random.default_rng(1))
    kw = dict(block=10, leaf_columns=20, max_rank=5, chunk_rows=64)
    with tall_tree_compress(A, workdir=tmp_path / "w1", store=tmp_path / "whole", **kw):
        pass
    assert not (tmp_path / "whole.tree").exists()  # removed after the root's commit
    assert not any((tmp_path / "w1").rglob("*.*"))  # and the work panels
    monkeypatch.setattr(Checkpoints, "remove", lambda self: None)
    with tall_tree_compress(A, workdir=tmp_path / "w2", store=tmp_path / "first", **kw):
        pass
    (tmp_path / "first.tree").rename(tmp_path / "again.tree")
    shutil.rmtree(tmp_path / "again.tree" / "merge-0-60")  # as if killed before the root
    computed = []
    for name in ("_tall_leaf", "_tall_merge"):
        real = getattr(tall_tree, name)
        monkeypatch.setattr(tall_tree, name,
                            lambda *a, _r=real, _n=name, **k: computed.append(_n) or _r(*a, **k))
    with tall_tree_compress(A, workdir=tmp_path / "w3", store=tmp_path / "again", **kw):
        assert computed == ["_tall_merge"]  # the root's merge only, over loaded nodes
    _same_store(tmp_path / "whole", tmp_path / "again")


def test_checkpoints_of_other_arguments_are_refused(tmp_path, monkeypatch):
    A = with_spectrum(np.logspace(0, -9, 20), 300, 60, np.random.default_rng(1))
    kw = dict(workdir=tmp_path / "w", leaf_columns=20, max_rank=5, chunk_rows=64)
    monkeypatch.setattr(Checkpoints, "remove", lambda self: None)
    tall_tree_compress(A, block=10, **kw).close(finalize=False)
    with pytest.raises(StoreError, match="`block`.*checkpoints=False"):
        tall_tree_compress(A, block=5, **kw)
    B = A.copy()
    B[0, 0] += 1.0  # other bytes, same shape
    with pytest.raises(StoreError, match="`source`"):
        tall_tree_compress(B, block=10, **kw)
    tall_tree_compress(B, block=10, checkpoints=False, **kw).close(finalize=False)
