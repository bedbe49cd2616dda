"""A pack's objects: the same bytes as zarr writes, whichever way they are made."""

import numpy as np
import pytest

import streamsvd.store.pack as pack_mod
from streamsvd.store.pack import Packed


@pytest.mark.parametrize("size", [0, 1, 7, 1000, 4097, 12345])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("chunk_bytes", [64, 1000, 1 << 20])
def test_raw_chunks_are_zarrs_bytes(rng, monkeypatch, size, dtype, chunk_bytes):
    """Chunks taken from the array (the last padded with zeros) are the objects zarr
    writes, in the same order, metadata first."""
    data = rng.standard_normal(size).astype(dtype)
    data[: min(3, size)] = 0.0
    doc = {"streamsvd": {"generation": 3}, "attrs": {"a": [1, 2]}}
    fast = pack_mod.encode_pack(data, doc, chunk_bytes)
    monkeypatch.setattr(pack_mod, "_raw_chunks", lambda arr, data: False)
    assert list(fast) == list(want := pack_mod.encode_pack(data, doc, chunk_bytes))
    assert list(fast)[0] == "zarr.json"
    assert all(fast[k] == want[k] for k in want)


@pytest.mark.parametrize("sizes", [(5,), (3, 0, 9, 1), (600, 600), (7, 1200, 4)])
@pytest.mark.parametrize("chunk_bytes", [64, 4800])
def test_a_pack_of_pieces_is_the_concatenation(rng, sizes, chunk_bytes):
    """A pack is never concatenated: its chunks are the bytes of the concatenation, views
    of a piece's memory where they lie inside it."""
    parts = tuple(rng.standard_normal(s) for s in sizes)
    doc = {"streamsvd": {"generation": 1}, "attrs": {}}
    fast = pack_mod.encode_pack(Packed(parts, np.dtype(np.float64)), doc, chunk_bytes)
    want = pack_mod.encode_pack(np.concatenate(parts), doc, chunk_bytes)
    assert list(fast) == list(want)
    assert all(bytes(fast[k]) == want[k] for k in want)
    views = [blob for blob in fast.values() if isinstance(blob, memoryview)]
    assert all(blob.readonly for blob in views)
    # a chunk inside a piece is that piece's memory
    assert all(any(np.shares_memory(np.frombuffer(blob, np.float64), p) for p in parts)
               for blob in views)
    # every chunk that lies inside one piece is a view, the others are copies
    size, most = sum(sizes), chunk_bytes // 8
    chunk = -(-size // -(-size // most))
    ends = np.cumsum(sizes)
    inside = sum(int(np.searchsorted(ends, a, "right") == np.searchsorted(ends, a + chunk - 1,
                                                                         "right"))
                 for a in range(0, size, chunk) if a + chunk <= size)
    assert len(views) == inside


def test_a_failed_chunk_write_leaves_nothing(tmp_path, rng, monkeypatch):
    """The chunks are written on several threads: when one write fails, every other has
    ended before the generation is deleted, and the store is as it was."""
    import threading
    import time

    import streamsvd.storage.local as local
    from streamsvd.errors import StoreError
    from streamsvd.store import BasisStore
    from tests.store.test_handle import FP, tree_bytes

    U = rng.standard_normal((1000, 3))
    real = local._write_new_file
    started = []

    def failing(path, data):
        started.append(path.name)
        if path.name == "c.1":
            raise OSError(28, "No space left on device")
        time.sleep(0.01)  # the other thread's writes outlive the failure
        real(path, data)

    with BasisStore.create(tmp_path / "s", n=1000, inner_fingerprint=FP, chunk_bytes=800) as s:
        s.commit({"U": U})
        before = tree_bytes(s.path)
        monkeypatch.setattr(local, "_write_new_file", failing)
        with pytest.raises(StoreError, match="No space"):
            s.commit({"U": 2 * U})
        monkeypatch.undo()
        assert threading.active_count() == 1 or not any(
            t.name.startswith("streamsvd-commit") for t in threading.enumerate())
        assert "c.1" in started and len(started) > 2
        assert tree_bytes(s.path) == before
        assert np.array_equal(s.read().arrays["U"], U)
