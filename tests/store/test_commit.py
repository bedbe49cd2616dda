"""A pack's objects: the same bytes as zarr writes, whichever way they are made."""

import numpy as np
import pytest

import streamsvd.store.commit as commit


@pytest.mark.parametrize("size", [0, 1, 7, 1000, 4097, 12345])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("chunk_bytes", [64, 1000, 1 << 20])
def test_raw_chunks_are_zarrs_bytes(rng, monkeypatch, size, dtype, chunk_bytes):
    """Chunks taken from the array (the last padded with zeros) are the objects zarr
    writes, in the same order, metadata first."""
    data = rng.standard_normal(size).astype(dtype)
    data[: min(3, size)] = 0.0
    doc = {"streamsvd": {"generation": 3}, "attrs": {"a": [1, 2]}}
    fast = commit.encode_pack(data, doc, chunk_bytes)
    monkeypatch.setattr(commit, "_raw_chunks", lambda arr, data: False)
    assert list(fast) == list(want := commit.encode_pack(data, doc, chunk_bytes))
    assert list(fast)[0] == "zarr.json"
    assert all(fast[k] == want[k] for k in want)
