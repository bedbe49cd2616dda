"""Planning writes nothing the state or a commit refers to; the backend is composed."""

import copy
import pickle
import time

import numpy as np
import pytest

from streamsvd import DiagonalInner, Euclidean, StreamCompressor
from streamsvd.algebra.buffer import BasisBuffer
from streamsvd.algebra.interface import Backend, BasisBackend, DeferredGram
from streamsvd.algebra.memory import MemoryBackend, MemoryBasis
from streamsvd.algebra.panels.backend import PanelBackend
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.engine import rows as rows_module
from streamsvd.engine.state import apply_plan, stage_plan
from streamsvd.engine.update import plan_absorb
from streamsvd.parallel.cluster import TallCompressor, open_compressor


def _panels(basis):
    return sorted(e for e in basis.root.list("panels") if e.startswith("p"))


def test_planning_a_panel_update_writes_no_panel_until_staged(rng):
    """The new columns of an update that does not compact are written when the plan is
    staged for a commit (or applied), never while it is planned."""
    A = rng.standard_normal((300, 24))
    with TallCompressor(300, chunk_rows=64) as tc:  # no cut: the exact path, no compaction
        tc.absorb(A[:, :8])
        s, opts = tc._life.state, tc._life.opts
        before = _panels(s.basis)
        plan = plan_absorb(s, A[:, 8:16], opts, t0=time.perf_counter())
        assert not plan.writes.compacted and plan.writes.columns == 8
        assert _panels(s.basis) == before  # planned: nothing written
        stage_plan(s, plan)
        staged = _panels(s.basis)
        assert len(staged) == len(before) + 1  # staged: the new panel, not yet stored
        assert s.basis.width == 8
        apply_plan(s, plan)
        assert s.basis.width == 16 and _panels(s.basis) == staged
        np.testing.assert_allclose(tc.expansion.to_dense(), A[:, :16], atol=1e-12)


def test_planning_leaves_the_rows_and_their_rebase_to_staging(rng, monkeypatch):
    """A plan made when the row factor is due for a rebase writes no row and does not
    rebase; staging does both, and V is unchanged by the rebase."""
    monkeypatch.setattr(rows_module, "WIDTH_LIMIT", 0.5)  # a rebase before every update
    sc = StreamCompressor(80, max_rank=4, oversampling=0, rule="jacobi", sweeps=None)
    A = rng.standard_normal((80, 40))
    sc.absorb(A[:, :36])
    s, rows = sc._life.state, sc._life.state.rows
    assert rows.wide
    V_before, buffer = sc.right_factor(), rows._V0.copy()
    rebases = rows.rebases
    plan = plan_absorb(s, A[:, 36:40], sc._life.opts, t0=time.perf_counter())
    assert plan.writes.rows is not None and plan.writes.rows.rebase
    assert rows.rebases == rebases and np.array_equal(rows._V0, buffer)  # nothing written
    stage_plan(s, plan)
    assert rows.rebases == rebases + 1
    np.testing.assert_allclose(sc.right_factor(), V_before, atol=1e-13)  # V unchanged
    apply_plan(s, plan)
    assert sc._life.state.m == 40


def test_a_backend_is_given_not_subclassed(rng, tmp_path):
    """StreamCompressor with a PanelBackend is the tall mode: the same factors bit for bit
    as TallCompressor, a tall store, reopened as a TallCompressor."""
    A = rng.standard_normal((200, 30))
    opts = dict(max_rank=6, rule="jacobi", sweeps=None)
    backend = PanelBackend.create(store=tmp_path / "s.zarr", workdir=None, chunk_rows=48,
                                  client=None, storage_options=None)
    with StreamCompressor(200, store=backend.root, backend=backend, **opts) as sc, \
            TallCompressor(200, chunk_rows=48, **opts) as tc:
        for j in range(0, 30, 10):
            sc.absorb(A[:, j:j + 10])
            tc.absorb(A[:, j:j + 10])
        assert "panels=" in repr(sc) and "chunk_rows=48" in repr(tc)
        np.testing.assert_array_equal(sc.left_vectors, tc.left_vectors)
        np.testing.assert_array_equal(sc.amplitudes, tc.amplitudes)
    assert sc.finalized and sc.rank == 6  # closing finalised the stored compressor
    back = open_compressor(tmp_path / "s.zarr")
    try:
        assert isinstance(back, TallCompressor) and back.chunk_rows == 48
        np.testing.assert_array_equal(back.amplitudes, sc.amplitudes)
    finally:
        back.close()
    with pytest.raises(Exception, match="TallCompressor"):
        StreamCompressor.open(tmp_path / "s.zarr", mode="r")
    assert isinstance(StreamCompressor(5)._life.backend, MemoryBackend)


def _members(protocol):
    """The attributes and methods a Protocol asks for (its own and its bases')."""
    names = set()
    for cls in protocol.__mro__:
        if cls.__module__ == protocol.__module__:
            names |= {n for n in vars(cls) if not n.startswith("_")}
            names |= set(getattr(cls, "__annotations__", {}))
    return names


@pytest.mark.parametrize(("implementation", "protocol"), [
    (MemoryBasis, DeferredGram), (PanelBasis, BasisBackend),
    (MemoryBackend, Backend), (PanelBackend, Backend),
])
def test_each_backend_offers_what_the_interface_asks(implementation, protocol):
    """The backend interface is the Protocols of ``algebra.interface``: both backends and
    their bases offer every member (the memory basis the deferred Gram's as well)."""
    members = _members(protocol)
    assert {"project", "swap", "commit_arrays"} <= _members(BasisBackend)
    instance_only = {"n", "compactions", "kind", "temporary"}  # set by the constructor
    missing = {m for m in members - instance_only if not hasattr(implementation, m)}
    assert not missing, missing


@pytest.mark.parametrize("inner", [Euclidean(), DiagonalInner(np.linspace(1.0, 2.0, 30))])
def test_the_memory_buffer_grows_and_copies_its_stored_columns_only(rng, inner):
    """The growable buffer of a memory basis: its capacity grows geometrically, a copy
    (pickle) holds the stored columns alone, and a commit's arrays restore the basis."""
    buffer = BasisBuffer(30, inner)
    assert buffer.width == 0 and buffer.capacity == 0
    for b, capacity in ((3, 8), (4, 8), (2, 16)):
        Y, MY = buffer.workspace(b)
        Y[...] = rng.standard_normal((30, b))
        MY[...] = inner.apply(Y)
        buffer.accept(b)
        assert buffer.capacity == capacity
    assert buffer.width == 9 and buffer.reallocations == 2
    np.testing.assert_array_equal(buffer.MQ, inner.apply(buffer.Q))
    for other in (pickle.loads(pickle.dumps(buffer)), copy.deepcopy(buffer)):
        assert other.width == 9 and other.capacity == 9
        np.testing.assert_array_equal(other.Q, buffer.Q)
        np.testing.assert_array_equal(other.MQ, buffer.MQ)
    arrays, attrs = buffer.commit_arrays(0, compacted=False)
    assert sorted(arrays) == (["Q"] if inner.is_euclidean else ["MQ", "Q"])
    restored = BasisBuffer(30, inner)
    restored.restore({k: v.copy() for k, v in arrays.items()}, attrs)
    assert restored.width == 9 and restored.capacity == 16
    np.testing.assert_array_equal(restored.MQ, buffer.MQ)
