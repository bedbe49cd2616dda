"""The object-store lease (streamsvd.storage.lease) over an in-memory conditional storage."""

import json
import logging
import time

import pytest

from streamsvd.errors import StoreLockedError
from streamsvd.storage.lease import Lease


class MemoryObjects:
    """Keys and bytes with ETags and conditional writes, as an object store offers them."""

    url = "memory://bucket/basis.zarr"

    def __init__(self):
        self.objects = {}
        self.writes = 0

    def _put(self, key, data):
        self.writes += 1
        tag = f"etag-{self.writes}"
        self.objects[key] = (data, tag)
        return tag

    def get_tagged(self, key):
        return self.objects.get(key)

    def put_if_absent(self, key, data):
        return None if key in self.objects else self._put(key, data)

    def put_if_match(self, key, data, tag):
        seen = self.objects.get(key)
        return self._put(key, data) if seen is not None and seen[1] == tag else None

    def delete(self, key):
        self.objects.pop(key, None)


def test_a_live_lease_keeps_a_second_writer_out_until_released():
    storage = MemoryObjects()
    first, second = Lease(storage, "writer.lease"), Lease(storage, "writer.lease")
    first.acquire()
    try:
        assert first.held() and first.owned()
        with pytest.raises(StoreLockedError, match="locked by another writer: pid"):
            second.acquire()
    finally:
        first.release()
    assert storage.get_tagged("writer.lease") is None
    second.acquire()
    assert second.held() and second.token == 1
    second.release()


def test_an_expired_lease_is_taken_over_and_its_holder_fenced(caplog):
    storage = MemoryObjects()
    zombie, taker = Lease(storage, "writer.lease"), Lease(storage, "writer.lease")
    zombie.acquire()
    data, tag = storage.get_tagged("writer.lease")
    doc = json.loads(data)
    doc["expires"] = time.time() - 100
    storage.objects["writer.lease"] = (json.dumps(doc).encode(), tag)
    with caplog.at_level(logging.WARNING):
        taker.acquire()
    assert "taking over the lease" in caplog.text and "expired" in caplog.text
    assert taker.token == 2 and taker.held()
    assert not zombie.held() and not zombie.owned()
    zombie.release()  # taken over: the lease is left to its new holder
    assert storage.get_tagged("writer.lease") is not None
    taker.release()
    assert storage.get_tagged("writer.lease") is None
