"""A local zarr array decoded chunk by chunk: the same values as zarr's own read."""

import numpy as np
import pytest
import zarr
import zarr.codecs

import streamsvd.io.sources as sources
from streamsvd.errors import NonFiniteError, SourceError
from streamsvd.io.chunks import ChunkFiles
from streamsvd.io.open import open_source
from streamsvd.io.sources import Source, _ChunkReader

COMPRESSORS = {
    "zstd": "auto",
    "blosc": zarr.codecs.BloscCodec(cname="lz4", shuffle="shuffle"),
    "none": None,
}


def _array(tmp_path, A, *, compressor="zstd", chunks=(10, 4), fill_value=0.0, dtype="f8",
           empty=False):
    z = zarr.create_array(tmp_path / f"{compressor}.zarr", shape=A.shape, chunks=chunks,
                          dtype=dtype, compressors=COMPRESSORS[compressor],
                          fill_value=fill_value, config={"write_empty_chunks": empty})
    z[...] = A.astype(dtype)
    return z


@pytest.mark.parametrize("compressor", list(COMPRESSORS))
@pytest.mark.parametrize("threads", [1, 2])
def test_any_region_is_the_array_in_either_layout(rng, tmp_path, compressor, threads):
    """Edge chunks (203 x 17 in chunks of 10 x 4), regions across chunk boundaries,
    column- and row-major blocks, one or two threads: the values zarr reads."""
    A = rng.standard_normal((203, 17))
    z = _array(tmp_path, A, compressor=compressor)
    files = ChunkFiles.of(z)
    assert files is not None
    for r0, r1, c0, c1 in [(0, 203, 0, 17), (0, 203, 4, 12), (7, 188, 3, 16), (200, 203, 16, 17),
                           (30, 40, 8, 12)]:
        for order in "FC":
            out = np.empty((r1 - r0, c1 - c0), order=order)
            assert files.fill(out, r0, c0, threads=threads)
            assert np.array_equal(out, z[r0:r1, c0:c1]), (r0, r1, c0, c1, order)


def test_chunks_never_written_read_as_the_fill_value(tmp_path):
    A = np.zeros((40, 12))
    A[:10, :4] = 3.0  # one chunk written; the others equal the fill value and are left out
    z = _array(tmp_path, A - 2.5, fill_value=-2.5)
    assert sorted(p.name for p in (tmp_path / "zstd.zarr" / "c").rglob("*") if p.is_file()) == ["0"]
    out = np.empty((40, 12), order="F")
    assert ChunkFiles.of(z).fill(out, 0, 0)
    assert np.array_equal(out, z[:, :])


@pytest.mark.parametrize("make", [
    lambda tmp: np.zeros((4, 4)),
    lambda tmp: zarr.create_array(zarr.storage.MemoryStore(), shape=(8, 8), chunks=(4, 4),
                                  dtype="f8"),
    lambda tmp: zarr.create_array(tmp / "i.zarr", shape=(8, 8), chunks=(4, 4), dtype="i4"),
    lambda tmp: zarr.create_array(tmp / "g.zarr", shape=(8, 8), chunks=(4, 4), dtype="f8",
                                  compressors=zarr.codecs.GzipCodec()),
    lambda tmp: zarr.create_array(tmp / "s.zarr", shape=(8, 8), chunks=(4, 4), shards=(8, 8),
                                  dtype="f8"),
    lambda tmp: zarr.create_array(tmp / "v2.zarr", shape=(8, 8), chunks=(4, 4), dtype="f8",
                                  zarr_format=2),
    lambda tmp: zarr.create_array(tmp / "b.zarr", shape=(8, 8), chunks=(4, 4), dtype="f8",
                                  serializer=zarr.codecs.BytesCodec(endian="big")),
])
def test_other_arrays_are_left_to_zarr(tmp_path, make):
    assert ChunkFiles.of(make(tmp_path)) is None


@pytest.mark.parametrize("compressor", list(COMPRESSORS))
def test_blocks_are_those_of_zarrs_read_bit_for_bit(rng, tmp_path, monkeypatch, compressor):
    """The blocks of ``Source.blocks`` (read ahead, the first on two threads), of
    ``read`` and of the tall mode's row chunks equal those read through zarr, in order."""
    A = rng.standard_normal((203, 17)) * 1e3
    _array(tmp_path, A, compressor=compressor)
    path = tmp_path / f"{compressor}.zarr"

    def read_all():
        with open_source(path) as src:
            blocks = [(o, X.copy(order="K")) for o, X in src.blocks(5, start=2)]
            one = src.read(3, 11)
            lazy = _ChunkReader(src, 4, 13)[slice(17, 190), slice(1, 8)]
            return blocks, one, lazy, src._files is not None

    blocks, one, lazy, direct = read_all()
    monkeypatch.setattr(sources.ChunkFiles, "of", classmethod(lambda cls, data: None))
    want_blocks, want_one, want_lazy, zarr_read = read_all()
    assert direct and not zarr_read
    assert [o for o, _ in blocks] == [o for o, _ in want_blocks] == [2, 7, 12]
    for (_, X), (_, Y) in zip(blocks, want_blocks, strict=True):
        assert X.flags.f_contiguous and X.tobytes(order="F") == Y.tobytes(order="F")
    assert one.tobytes(order="F") == want_one.tobytes(order="F")
    assert lazy.flags.c_contiguous and np.array_equal(lazy, want_lazy)


def test_a_non_finite_entry_is_reported_as_zarrs_read_reports_it(rng, tmp_path, monkeypatch):
    A = rng.standard_normal((95, 24))
    A[3, 22] = np.inf  # first row chunk, last column
    A[81, 21] = np.nan  # a later row chunk, an earlier column
    _array(tmp_path, A)
    path = tmp_path / "zstd.zarr"

    def messages():
        found = []
        with open_source(path) as src:
            for call in (lambda: list(src.blocks(4, start=20)), lambda: src.read(20, 24),
                         lambda: _ChunkReader(src, 20, 24)[slice(0, 95), slice(0, 4)]):
                with pytest.raises(NonFiniteError) as info:
                    call()
                found.append(str(info.value))
        return found

    direct = messages()
    monkeypatch.setattr(sources.ChunkFiles, "of", classmethod(lambda cls, data: None))
    assert direct == messages()
    assert "column 21, row 81" in direct[0] and "2 NaN or infinite entries" in direct[0]


@pytest.mark.parametrize("compressor", ["zstd", "none"])
def test_a_damaged_chunk_fails_its_block_with_its_offset(rng, tmp_path, compressor):
    A = rng.standard_normal((40, 12))
    _array(tmp_path, A, compressor=compressor)
    (tmp_path / f"{compressor}.zarr" / "c" / "2" / "1").write_bytes(b"not a chunk")
    with open_source(tmp_path / f"{compressor}.zarr") as src:
        seen = []
        with pytest.raises(SourceError, match=r"reading columns 4:8 \(offset 4\) of zarr array"):
            for offset, _ in src.blocks(4):
                seen.append(offset)
    assert seen == [0]


def test_a_float32_array_keeps_its_dtype_and_other_dtypes_go_through_zarr(rng, tmp_path):
    A = np.rint(rng.standard_normal((50, 9)) * 100)
    for dtype, direct in (("f4", True), ("i2", False)):
        z = zarr.create_array(tmp_path / f"{dtype}.zarr", shape=A.shape, chunks=(10, 4),
                              dtype=dtype)
        z[...] = A.astype(dtype)
        src = Source(z, "z")
        assert (src._files is not None) == direct
        X = src.read(0, 9)
        assert X.dtype == (np.float32 if dtype == "f4" else np.float64)
        assert np.array_equal(X, A)


def test_a_frame_decoded_without_a_target_buffer_gives_the_same_block(rng, tmp_path):
    """A codec that cannot decode into a given buffer (a zstd frame that does not state
    its size) is asked for the bytes instead."""
    A = rng.standard_normal((40, 12))
    z = _array(tmp_path, A)
    files = ChunkFiles.of(z)
    decode = files.decode

    def no_target(buf, out=None):
        if out is not None:
            raise RuntimeError("could not determine zstd frame content size")
        return decode(buf)

    files.decode = no_target
    out = np.empty((40, 12), order="F")
    assert files.fill(out, 0, 0)
    assert np.array_equal(out, A)


def test_an_early_read_is_the_first_block_and_keeps_its_error_for_it(rng, tmp_path):
    A = rng.standard_normal((40, 12))
    _array(tmp_path, A)
    with open_source(tmp_path / "zstd.zarr") as src:
        src.read_early(0, 5)
        got = [(o, X.copy()) for o, X in src.blocks(5)]
        assert [o for o, _ in got] == [0, 5, 10]
        assert all(np.array_equal(X, A[:, o:o + 5]) for o, X in got)
        src.read_early(0, 4)  # not the first block of the next read: dropped
        assert [o for o, _ in src.blocks(5, start=5)] == [5, 10]
    A[7, 2] = np.nan
    (tmp_path / "nan").mkdir()
    _array(tmp_path / "nan", A)
    with open_source(tmp_path / "nan" / "zstd.zarr") as src:
        src.read_early(0, 5)
        with pytest.raises(NonFiniteError, match="column 2, row 7"):
            next(src.blocks(5))
