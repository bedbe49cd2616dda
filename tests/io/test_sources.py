import threading

import dask.array as da
import h5py
import numpy as np
import pytest
import scipy.io
import scipy.sparse as sp
import zarr

from streamsvd.algebra.inner import DiagonalInner, MatrixInner
from streamsvd.errors import InputError, NonFiniteError, ShapeMismatchError, SourceError
from streamsvd.io.inner_file import load_inner
from streamsvd.io.open import open_source
from streamsvd.io.sources import Source

N, M = 9, 23


@pytest.fixture
def A(rng):
    return rng.standard_normal((N, M))


def make_source(kind, A, tmp_path):
    """Return (obj, dataset, closer) for every supported kind of source."""
    if kind == "numpy":
        return A, None
    if kind == "numpy_int":
        return np.rint(A * 100).astype(np.int32), None
    if kind == "list":
        return A.tolist(), None
    if kind == "npy":
        np.save(tmp_path / "a.npy", A)
        return tmp_path / "a.npy", None
    if kind == "npy_fortran":
        np.save(tmp_path / "f.npy", np.asfortranarray(A))
        return str(tmp_path / "f.npy"), None
    if kind == "hdf5_single":
        with h5py.File(tmp_path / "a.h5", "w") as f:
            f.create_dataset("run/u", data=A, chunks=(N, 4))
        return tmp_path / "a.h5", None
    if kind == "hdf5_named":
        with h5py.File(tmp_path / "b.hdf5", "w") as f:
            f["u"] = A
            f["other"] = np.zeros((2, 2))
        return tmp_path / "b.hdf5", "u"
    if kind == "h5py_dataset":
        with h5py.File(tmp_path / "c.h5", "w") as f:
            f["u"] = A
        f = h5py.File(tmp_path / "c.h5", "r")
        return f["u"], None
    if kind == "zarr_path":
        z = zarr.create_array(tmp_path / "a.zarr", shape=A.shape, chunks=(N, 5), dtype="f8")
        z[...] = A
        return tmp_path / "a.zarr", None
    if kind == "zarr_group":
        g = zarr.open_group(tmp_path / "g", mode="w")
        g.create_array("snapshots", data=A, chunks=(4, 6))
        g.create_array("mesh", data=np.zeros((3, 2)))
        return tmp_path / "g", "snapshots"
    if kind == "zarr_array":
        z = zarr.create_array(tmp_path / "b.zarr", shape=A.shape, chunks=(N, 7), dtype="f4")
        z[...] = A
        return z, None
    if kind == "dask":
        return da.from_array(A, chunks=(N, 6)), None
    raise AssertionError(kind)


KINDS = [
    "numpy",
    "numpy_int",
    "list",
    "npy",
    "npy_fortran",
    "hdf5_single",
    "hdf5_named",
    "h5py_dataset",
    "zarr_path",
    "zarr_group",
    "zarr_array",
    "dask",
]


def expected_matrix(kind, A):
    if kind == "numpy_int":
        return np.rint(A * 100).astype(np.int32).astype(np.float64)
    if kind == "zarr_array":
        return A.astype(np.float32).astype(np.float64)
    return A


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_gives_the_same_blocks(kind, A, tmp_path):
    obj, dataset = make_source(kind, A, tmp_path)
    want = expected_matrix(kind, A)
    with open_source(obj, dataset=dataset) as src:
        assert (src.n, src.m) == (N, M) and src.shape == (N, M) and len(src) == M
        for b in (1, 4, 7, M, M + 5):
            for start in (0, 5, M):
                for prefetch in (True, False):
                    blocks = list(src.blocks(b, start=start, prefetch=prefetch))
                    assert [o for o, _ in blocks] == list(range(start, M, b))
                    for offset, X in blocks:
                        # float32 stays float32 (half the bytes); the rest is float64
                        assert X.dtype == (np.float32 if src.dtype == np.float32
                                           else np.float64) == src.block_dtype
                        assert X.flags.f_contiguous
                        assert X.shape == (N, min(b, M - offset))
                        assert np.array_equal(X, want[:, offset : offset + b])
        assert np.array_equal(src.read(3, 11), want[:, 3:11])
        assert src.read(4, 4).shape == (N, 0)
    if kind == "h5py_dataset":
        obj.file.close()


@pytest.mark.parametrize("dtype", ["f8", "f4", "i2"])
def test_zarr_blocks_decoded_slab_by_slab_are_the_array(rng, tmp_path, monkeypatch, dtype):
    """A zarr array of the block's dtype is decoded straight into the column-major block,
    a slab of whole row chunks at a time (the last one shorter); other dtypes are
    converted as they are copied. Either way the block is the array, and a non-finite
    entry is named where it is."""
    import streamsvd.io.sources as sources

    monkeypatch.setattr(sources, "_READ_BYTES", 3 * 10 * 5 * 8)  # three row chunks
    A = np.rint(rng.standard_normal((203, 17)) * 100)
    z = zarr.create_array(tmp_path / "t.zarr", shape=A.shape, chunks=(10, 4), dtype=dtype)
    z[...] = A.astype(dtype)
    want = A.astype(np.float32 if dtype == "f4" else np.float64)
    with open_source(tmp_path / "t.zarr") as src:
        for offset, X in src.blocks(5, prefetch=False):
            assert X.flags.f_contiguous and X.dtype == want.dtype
            assert np.array_equal(X, want[:, offset:offset + 5])
    if dtype != "i2":
        z[157, 11] = np.nan
        with open_source(tmp_path / "t.zarr") as src, pytest.raises(
                NonFiniteError, match="column 11, row 157"):
            src.read(10, 15)


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_gives_the_same_lazy_blocks(kind, A, tmp_path):
    """Blocks handed over unread (``rows=``) hold the same values, by row chunks."""
    obj, dataset = make_source(kind, A, tmp_path)
    want = expected_matrix(kind, A)
    with open_source(obj, dataset=dataset) as src:
        blocks = list(src.blocks(7, start=2, rows=9))
        assert [o for o, _ in blocks] == list(range(2, M, 7))
        for offset, X in blocks:
            assert X.first == offset and X.data.chunks[0][0] == 9
            got = X.data.compute(scheduler="synchronous")
            assert got.dtype == src.block_dtype
            assert np.array_equal(got, want[:, offset : offset + 7])
    if kind == "h5py_dataset":
        obj.file.close()


def test_a_lazy_block_of_an_array_carries_its_columns_only():
    """What a cluster's workers receive for a block of an in-memory array is the block's
    columns, not the whole array."""
    import pickle

    A = np.random.default_rng(0).standard_normal((2000, 200))
    block = open_source(A).lazy(50, 60, rows=500)
    assert len(pickle.dumps(block.data)) < 2 * 2000 * 10 * 8 < A.nbytes
    assert np.array_equal(block.data.compute(), A[:, 50:60])


def test_a_lazy_block_names_a_bad_entry_in_source_coordinates(A):
    bad = A.copy()
    bad[N - 1, 9] = np.nan
    block = open_source(bad, dataset=None).lazy(8, 12, rows=5)
    with pytest.raises(NonFiniteError, match=rf"holds nan at column 9, row {N - 1} "):
        block.data.compute(scheduler="synchronous")


def test_prefetch_on_and_off_agree(A):
    src = open_source(A)
    on = list(src.blocks(5, prefetch=True))
    off = list(src.blocks(5, prefetch=False))
    assert len(on) == len(off) == 5
    for (o1, x1), (o2, x2) in zip(on, off, strict=True):
        assert o1 == o2 and np.array_equal(x1, x2)


def test_blocks_do_not_share_memory_with_the_data(A):
    src = open_source(A)
    for _, X in src.blocks(4):
        X[:] = 0.0
    assert np.array_equal(src.read(0, M), A) and np.any(A != 0)


def test_dask_blocks_are_computed_one_at_a_time(A):
    computed = []
    lock = threading.Lock()

    def record(x, block_info=None):
        with lock:
            computed.append(block_info[0]["chunk-location"][1])
        return x

    D = da.from_array(A, chunks=(N, 5)).map_blocks(record, dtype=A.dtype)
    src = open_source(D)
    X = src.read(0, 5)
    assert np.array_equal(X, A[:, :5]) and computed == [0]
    computed.clear()
    got = [X for _, X in src.blocks(5)]
    assert np.array_equal(np.hstack(got), A)
    assert sorted(computed) == [0, 1, 2, 3, 4]  # each chunk once: never the whole array


def test_read_ahead_fills_a_dropped_block_again_and_never_one_still_held():
    """A block the caller dropped is handed to a later read to be filled again; a block
    the caller still holds (in a list, as a view, or as its loop variable) never is."""
    from streamsvd.io.readahead import read_ahead

    spares = []

    def read(a, b, spare):
        spares.append(spare is not None)
        out = np.empty((4, 2), order="F") if spare is None else spare
        out[:] = a
        return out

    ranges = [(a, a + 2) for a in range(0, 16, 2)]
    kept = [X for _, X in read_ahead(read, ranges, 1)]
    assert not any(spares) and [X[0, 0] for X in kept] == [a for a, _ in ranges]
    spares.clear()
    views = []
    for _, X in read_ahead(read, ranges, 1):
        views.append(X[:, :1])
    assert not any(spares) and [v[0, 0] for v in views] == [a for a, _ in ranges]
    spares.clear()
    blocks = read_ahead(read, ranges, 1)
    while (item := next(blocks, None)) is not None:
        a, X = item
        assert np.all(X == a)
        del X, item
    assert spares == [False] * 2 + [True] * (len(ranges) - 2)  # all but depth + 1 blocks


def test_blocks_filled_again_are_the_array_and_name_the_first_bad_entry(rng, tmp_path,
                                                                        monkeypatch):
    """Blocks read into dropped ones, slab by slab, are the array; a non-finite entry is
    named by the first in column order, even when an earlier slab holds a later one."""
    import streamsvd.io.sources as sources

    monkeypatch.setattr(sources, "_READ_BYTES", 2 * 10 * 4 * 8)  # two row chunks
    A = rng.standard_normal((95, 24))
    z = zarr.create_array(tmp_path / "t.zarr", shape=A.shape, chunks=(10, 4), dtype="f8")
    z[...] = A
    with open_source(tmp_path / "t.zarr") as src:
        blocks = src.blocks(4)
        while (item := next(blocks, None)) is not None:
            offset, X = item
            assert np.array_equal(X, A[:, offset:offset + 4])
            del X, item
    z[3, 22] = np.inf  # first slab, last column
    z[81, 21] = np.nan  # a later slab, an earlier column
    with open_source(tmp_path / "t.zarr") as src, pytest.raises(
            NonFiniteError, match="column 21, row 81 .*2 NaN or infinite entries"):
        for _ in src.blocks(4, start=20):
            pass


class FlakyColumns:
    """A 2-D array-like whose columns from `bad` on cannot be read."""

    def __init__(self, A, bad):
        self.A, self.bad = A, bad
        self.shape, self.dtype = A.shape, A.dtype
        self.reads = []

    def __getitem__(self, key):
        cols = key[1]
        self.reads.append(cols.start)
        if cols.stop > self.bad:
            raise OSError(5, "Input/output error")
        return self.A[key]


@pytest.mark.parametrize("prefetch", [True, False])
def test_read_error_surfaces_at_its_block(A, prefetch):
    data = FlakyColumns(A, bad=10)
    src = Source(data, "flaky test array")
    seen = []
    with pytest.raises(
        SourceError, match=r"reading columns 8:12 \(offset 8\) of flaky test array failed"
    ) as info:
        for offset, X in src.blocks(4, prefetch=prefetch):
            seen.append(offset)
            assert np.array_equal(X, A[:, offset : offset + 4])
    assert seen == [0, 4]
    assert isinstance(info.value.__cause__, OSError)
    assert "Input/output error" in str(info.value)


def test_dask_read_error_is_chained(A):
    def fail_on_third(x, block_info=None):
        if block_info[0]["chunk-location"][1] == 2:
            raise ValueError("corrupt chunk")
        return x

    D = da.from_array(A, chunks=(N, 5)).map_blocks(fail_on_third, dtype=A.dtype)
    with pytest.raises(SourceError, match=r"offset 9.*ValueError: corrupt chunk") as info:
        list(open_source(D).blocks(3))
    assert isinstance(info.value.__cause__, ValueError)


def test_abandoned_iteration_stops_the_prefetch_thread(A):
    before = threading.active_count()
    it = open_source(A).blocks(2)
    next(it)
    it.close()
    assert threading.active_count() == before


def test_resume_from_offset(A):
    src = open_source(A)
    offsets = [o for o, _ in src.blocks(6, start=17)]
    assert offsets == [17]
    assert list(src.blocks(6, start=M)) == []


# ------------------------------------------------------------------------ errors


def test_missing_file_names_the_path(tmp_path):
    path = tmp_path / "nothing.h5"
    with pytest.raises(SourceError, match=rf"`source` {path} does not exist"):
        open_source(path)


def test_unknown_extension(tmp_path):
    path = tmp_path / "data.csv"
    path.write_text("1,2\n")
    with pytest.raises(InputError, match=r"unknown extension '.csv'; expected .npy, .h5"):
        open_source(path)


def test_directory_that_is_not_zarr(tmp_path):
    with pytest.raises(InputError, match=r"is a directory but not a zarr array or group"):
        open_source(tmp_path)


def test_dataset_needed_lists_the_datasets(A, tmp_path):
    with h5py.File(tmp_path / "two.h5", "w") as f:
        f["grp/u"] = A
        f["v"] = A
    with pytest.raises(InputError, match=r"`dataset` must be given .* \['grp/u', 'v'\]"):
        open_source(tmp_path / "two.h5")
    with pytest.raises(SourceError, match=r"`dataset` 'w' is not in .* \['grp/u', 'v'\]"):
        open_source(tmp_path / "two.h5", dataset="w")
    with open_source(tmp_path / "two.h5", dataset="/grp/u") as src:
        assert np.array_equal(src.read(0, M), A)


def test_zarr_group_needs_an_array_name(A, tmp_path):
    g = zarr.open_group(tmp_path / "g.zarr", mode="w")
    g.create_array("a", data=A)
    g.create_array("b", data=A)
    with pytest.raises(InputError, match=r"`dataset` must be given .* \['a', 'b'\]"):
        open_source(tmp_path / "g.zarr")


def test_empty_hdf5_file(tmp_path):
    with h5py.File(tmp_path / "empty.h5", "w"):
        pass
    with pytest.raises(SourceError, match=r"holds no dataset"):
        open_source(tmp_path / "empty.h5")


def test_dataset_for_an_array_is_refused(A):
    with pytest.raises(InputError, match=r"`dataset` only applies to HDF5 files and zarr"):
        open_source(A, dataset="u")


@pytest.mark.parametrize("shape", [(5,), (2, 3, 4)])
def test_array_not_2d(shape, tmp_path):
    with pytest.raises(ShapeMismatchError, match=rf"`source` must be 2-D .*{len(shape)}-D"):
        open_source(np.zeros(shape))
    np.save(tmp_path / "x.npy", np.zeros(shape))
    with pytest.raises(ShapeMismatchError, match=r"must be 2-D"):
        open_source(tmp_path / "x.npy")


def test_complex_and_non_numeric_dtypes(tmp_path):
    with pytest.raises(InputError, match=r"`source` must be real; .*complex128"):
        open_source(np.zeros((3, 3), dtype=complex))
    with pytest.raises(InputError, match=r"`source` must hold real numbers; .*<U1"):
        open_source(np.array([["a", "b"], ["c", "d"]]))
    with h5py.File(tmp_path / "c.h5", "w") as f:
        f["z"] = np.zeros((3, 3), dtype=np.complex64)
    with pytest.raises(InputError, match=r"must be real; HDF5 dataset '/z'.*complex64"):
        open_source(tmp_path / "c.h5")


def test_ragged_lists_are_refused():
    with pytest.raises(InputError, match=r"`source` must be a real 2-D array .*list"):
        open_source([[1.0, 2.0], [3.0]])


@pytest.mark.parametrize("block", [0, -3, 2.5, None, True])
def test_block_must_be_a_positive_integer(A, block):
    with pytest.raises(InputError, match=r"`block` must be an integer >= 1"):
        open_source(A).blocks(block)


@pytest.mark.parametrize("start", [-1, M + 1, 1.0])
def test_start_outside_the_source(A, start):
    with pytest.raises(InputError, match=rf"`start` must be .*\[0, {M}\]"):
        open_source(A).blocks(4, start=start)


def test_read_range_errors(A):
    src = open_source(A)
    with pytest.raises(InputError, match=rf"`stop` must be in \[0, {M}\].*got {M + 1}"):
        src.read(0, M + 1)
    with pytest.raises(InputError, match=r"`stop` must be >= `start` \(5\); got 2"):
        src.read(5, 2)


def test_an_inner_product_is_read_from_each_kind_of_file(tmp_path):
    """``--inner FILE``: weights or a dense matrix (.npy), a sparse matrix (.npz, .mtx)."""
    w = np.linspace(1.0, 2.0, N)
    M = sp.diags_array([w, np.full(N - 1, 0.1), np.full(N - 1, 0.1)], offsets=[0, -1, 1])
    np.save(tmp_path / "w.npy", w)
    np.save(tmp_path / "m.npy", M.toarray())
    sp.save_npz(tmp_path / "m.npz", sp.csr_array(M))
    scipy.io.mmwrite(tmp_path / "m.mtx", sp.coo_matrix(M))
    assert load_inner(tmp_path / "w.npy") == DiagonalInner(w)
    dense, sparse, market = (load_inner(str(tmp_path / f"m.{suffix}"))
                             for suffix in ("npy", "npz", "mtx"))
    assert isinstance(dense, MatrixInner) and sparse == market == MatrixInner(M)
    np.testing.assert_allclose(dense.matrix, M.toarray())


def test_an_inner_product_file_must_exist_and_be_of_a_known_kind(tmp_path):
    with pytest.raises(InputError, match=r"must be a \.npy .*got 'w\.txt'"):
        load_inner(tmp_path / "w.txt")
    with pytest.raises(InputError, match=r"`inner` file .*w\.npy does not exist"):
        load_inner(tmp_path / "w.npy")
    (tmp_path / "e.npz").write_bytes(b"")
    with pytest.raises(InputError, match=r"cannot be read as a \.npz file"):
        load_inner(tmp_path / "e.npz")
