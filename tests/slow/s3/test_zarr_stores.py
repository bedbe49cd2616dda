"""obstore beside s3fs: the same stores, sources and tall streams, bit for bit.

The zarr arrays of an ``s3://`` prefix go through obstore with ``storage_options=
{"zarr_store": "obstore"}`` (:mod:`streamsvd.storage.zarr_stores`); what either writes,
the other reads, and the results are those of s3fs bit for bit, also through a proxy
that throttles and fails writes after applying them.
"""

import numpy as np
import pytest
import zarr

from streamsvd.io.open import open_source
from streamsvd.parallel.tall import TallCompressor
from streamsvd.storage import open_storage
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum

OBSTORE = {"zarr_store": "obstore"}


@pytest.fixture(autouse=True)
def _obstore():
    pytest.importorskip("obstore")


def _stream(A, store, options=None, tall=False):
    make = TallCompressor if tall else StreamCompressor
    kw = {"chunk_rows": 64} if tall else {}
    sc = make(A.shape[0], max_rank=6, store=store, storage_options=options, **kw)
    for j in range(0, A.shape[1], 10):
        sc.absorb(A[:, j:j + 10])
    sc.close()


def _read(store, options=None, tall=False):
    with (TallCompressor if tall else StreamCompressor).open(
            store, mode="r", storage_options=options) as back:
        return np.asarray(back.factors()[0]), back.factors()[1], back.error_bound


@pytest.mark.parametrize("tall", [False, True])
def test_obstore_and_s3fs_write_the_same_stores_and_read_each_other(s3, tall):
    A = with_spectrum(np.logspace(0, -9, 20), 300, 40, np.random.default_rng(6))
    _stream(A, f"{s3}/fsspec.zarr", tall=tall)
    _stream(A, f"{s3}/obstore.zarr", OBSTORE, tall=tall)
    want = _read(f"{s3}/fsspec.zarr", tall=tall)
    for got in (_read(f"{s3}/obstore.zarr", tall=tall),
                _read(f"{s3}/fsspec.zarr", OBSTORE, tall=tall)):
        assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))


def test_a_source_on_s3_reads_the_same_through_obstore(s3):
    A = np.random.default_rng(7).standard_normal((500, 30))
    z = zarr.create_array(f"{s3}/src.zarr", shape=A.shape, chunks=(128, 7), dtype="f8")
    z[:] = A
    with open_source(f"{s3}/src.zarr", storage_options=OBSTORE) as src:
        assert np.array_equal(src.read(3, 29), A[:, 3:29])


def test_obstore_survives_throttling_and_applied_then_failed_writes(s3_server, s3):
    from streamsvd.testing.s3server import start_faulty_proxy

    proxy = start_faulty_proxy(s3_server, throttle_every=7, fail_after_every=3)
    try:
        A = with_spectrum(np.logspace(0, -9, 20), 300, 40, np.random.default_rng(5))
        _stream(A, f"{s3}/clean.zarr", tall=True)
        store = open_storage(f"{s3}/faulty.zarr",
                             storage_options={**OBSTORE, "endpoint_url": proxy.endpoint})
        _stream(A, store, tall=True)
        assert proxy.faults["slow_down"] > 0 and proxy.faults["internal_after_apply"] > 0
    finally:
        proxy.stop()
    want, got = _read(f"{s3}/clean.zarr", tall=True), _read(f"{s3}/faulty.zarr", tall=True)
    assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
