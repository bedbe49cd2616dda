"""The tree's checkpoints: committed nodes are loaded and nothing below them runs; another
plan's are replaced; they are removed once the root is committed."""

import numpy as np
import pytest

import streamsvd.parallel.tree_graph as tree_graph
from streamsvd.parallel.checkpoints import Checkpoints
from streamsvd.parallel.spec import default_leaf_columns
from streamsvd.parallel.tree import tree_compress
from streamsvd.parallel.workers import blas_here, blas_plan, worker_threads
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum


@pytest.fixture
def A():
    return with_spectrum(np.logspace(0, -9, 20), 50, 80, np.random.default_rng(2))


def _same(a, b):
    ea, eb = a.expansion, b.expansion
    assert np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)
    assert a.error_bound == b.error_bound


def test_committed_nodes_are_loaded_and_nothing_below_them_runs(A, tmp_path, monkeypatch):
    kw = dict(block=10, leaf_columns=20, max_rank=6)
    with tree_compress(A, store=tmp_path / "whole", **kw) as whole:
        pass
    assert not (tmp_path / "whole.tree").exists()  # removed after the root's commit
    # a run whose checkpoints stay (as if killed after its nodes, before the store)
    monkeypatch.setattr(Checkpoints, "remove", lambda self: None)
    with tree_compress(A, store=tmp_path / "first", **kw):
        pass
    (tmp_path / "first.tree").rename(tmp_path / "again.tree")
    computed = []
    real_leaf, real_merge = tree_graph._compress_leaf, tree_graph._merge_pair
    monkeypatch.setattr(tree_graph, "_compress_leaf",
                        lambda *a, **k: computed.append("leaf") or real_leaf(*a, **k))
    monkeypatch.setattr(tree_graph, "_merge_pair",
                        lambda *a, **k: computed.append("merge") or real_merge(*a, **k))
    with tree_compress(A, store=tmp_path / "again", **kw) as again:
        assert computed == []  # the root was committed: loaded, nothing else
    with StreamCompressor.open(tmp_path / "whole", mode="r") as w, \
            StreamCompressor.open(tmp_path / "again", mode="r") as g:
        _same(w, g)
    del whole, again


def test_checkpoints_of_another_plan_are_replaced(A, tmp_path, monkeypatch):
    monkeypatch.setattr(Checkpoints, "remove", lambda self: None)
    with tree_compress(A, block=10, leaf_columns=20, max_rank=6, store=tmp_path / "s"):
        pass
    B = A.copy()
    B[0, 0] += 1.0  # other bytes, same shape: the nodes of A must not be reused
    (tmp_path / "s.tree").rename(tmp_path / "t.tree")
    with tree_compress(B, block=10, leaf_columns=20, max_rank=6, store=tmp_path / "t"):
        pass
    with tree_compress(B, block=10, leaf_columns=20, max_rank=6, checkpoints=False,
                       store=tmp_path / "u"):
        pass
    with StreamCompressor.open(tmp_path / "t", mode="r") as t, \
            StreamCompressor.open(tmp_path / "u", mode="r") as u:
        _same(t, u)


def test_max_rank_is_met_with_finalize(A):
    tree = tree_compress(A, block=10, leaf_columns=20, max_rank=6, finalize=True)
    assert tree.rank <= 6 and tree.finalized
    uncut = tree_compress(A, block=10, leaf_columns=20, max_rank=6)
    assert not uncut.finalized and uncut.rank > 6  # the explicit uncut state


def test_default_leaves_give_every_task_work_and_blas_without_a_cluster():
    assert default_leaf_columns(1000, 10) == 100  # ten blocks
    assert default_leaf_columns(120, 10, tasks=2) == 60  # two leaves, not 100 + 20
    assert default_leaf_columns(120, 10, tasks=64) == 10  # never below one block
    assert default_leaf_columns(5, 10) == 10
    assert worker_threads(None) == 1 and blas_plan(None) == 1 and blas_here(3) == 3
    assert blas_here({"tcp://elsewhere:1": 4}) == 1  # not on a worker
