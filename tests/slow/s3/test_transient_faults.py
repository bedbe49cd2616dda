"""Transient object-store faults: throttling and 5xx answers after applied writes.

A proxy in front of the moto server (:func:`streamsvd.testing.s3server.start_faulty_proxy`)
answers some requests ``503 SlowDown`` unapplied and fails some ``PUT`` requests with
``500 InternalError`` after applying them; a whole stream with its store on S3, and the
conditional writes of the lease and the pointer, go through, to the result of a run
without faults, bit for bit.
"""

import numpy as np
import pytest

from streamsvd.storage import open_storage
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.testing import with_spectrum


@pytest.fixture
def faulty(s3_server, s3, monkeypatch):
    from streamsvd.testing.s3server import start_faulty_proxy

    proxy = start_faulty_proxy(s3_server, throttle_every=7, fail_after_every=3)
    yield s3, proxy
    proxy.stop()


def _stream(A, store):
    with StreamCompressor(A.shape[0], max_rank=6, store=store) as sc:
        for j in range(0, A.shape[1], 10):
            sc.absorb(A[:, j:j + 10])
    with StreamCompressor.open(store, mode="r") as back:
        return back.expansion, back.error_bound


def test_a_stream_on_s3_survives_throttling_and_applied_then_failed_writes(faulty):
    bucket, proxy = faulty
    A = with_spectrum(np.logspace(0, -9, 20), 40, 60, np.random.default_rng(5))
    store = open_storage(f"{bucket}/faulty.zarr",
                         storage_options={"endpoint_url": proxy.endpoint})
    got, bound = _stream(A, store)
    assert proxy.faults["slow_down"] > 0 and proxy.faults["internal_after_apply"] > 0
    want = StreamCompressor(A.shape[0], max_rank=6)
    for j in range(0, A.shape[1], 10):
        want.absorb(A[:, j:j + 10])
    want.finalize()
    ref = want.expansion
    assert np.array_equal(got.U, ref.U) and np.array_equal(got.V, ref.V)
    assert bound == want.error_bound


def test_a_conditional_write_applied_before_a_failure_is_recognised(faulty):
    bucket, proxy = faulty
    storage = open_storage(f"{bucket}/cond",
                           storage_options={"endpoint_url": proxy.endpoint})
    # every third PUT is applied and then answered 500: the retry is refused by the
    # precondition, and the object holding this writer's bytes is recognised as its own
    for i in range(6):
        assert storage.put_if_absent(f"k{i}", f"v{i}".encode()) is not None
    assert proxy.faults["internal_after_apply"] >= 1
    assert storage.put_if_absent("k0", b"another writer") is None  # a real conflict
    tag = storage.get_tagged("k1")[1]
    assert storage.put_if_match("k1", b"new", tag) is not None
    assert storage.get("k1") == b"new"
