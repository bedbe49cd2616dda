"""An object storage pickles without secrets; what is a transient failure."""

import pickle

import pytest

from streamsvd.storage.objects import transient, without_secrets


def test_secrets_are_dropped_at_any_depth():
    options = {"key": "K", "secret": "S", "endpoint_url": "http://x",
               "client_kwargs": {"region_name": "r", "aws_secret_access_key": "S"}}
    assert without_secrets(options) == {"endpoint_url": "http://x",
                                        "client_kwargs": {"region_name": "r"}}


def test_a_pickled_storage_carries_no_secret():
    pytest.importorskip("s3fs")
    from streamsvd.storage import open_storage

    storage = open_storage("s3://bucket/basis.zarr",
                           storage_options={"key": "K-ID", "secret": "S-SECRET",
                                            "endpoint_url": "http://127.0.0.1:9"})
    data = pickle.dumps(storage)
    assert b"S-SECRET" not in data and b"K-ID" not in data
    back = pickle.loads(data)
    assert back.url == storage.url and back.storage_options["endpoint_url"] == "http://127.0.0.1:9"
    assert "secret" in storage.storage_options  # this process keeps them


def test_what_is_transient():
    assert transient(OSError("An error occurred (SlowDown): Please reduce your request rate."))
    assert transient(OSError("An error occurred (InternalError) when calling PutObject"))
    assert transient(ConnectionResetError())
    assert not transient(FileNotFoundError("k"))
    assert not transient(OSError("An error occurred (PreconditionFailed)"))
    assert not transient(PermissionError("AccessDenied"))
