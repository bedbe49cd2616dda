"""The zarr store of an object-store prefix: chosen by a storage option, checked."""

import importlib.util
import pickle

import pytest

from streamsvd.errors import InputError
from streamsvd.storage.zarr_stores import OPTION, fsspec_options, zarr_store_of


def test_the_option_is_checked_and_never_reaches_fsspec():
    with pytest.raises(InputError, match=r"storage_options\['zarr_store'\].*'s3fs'"):
        zarr_store_of("s3://b/p", {OPTION: "s3fs"}, read_only=True, argument="store")
    with pytest.raises(InputError, match="s3:// URLs.*`source` gs://b/p"):
        zarr_store_of("gs://b/p", {OPTION: "obstore"}, read_only=True, argument="source")
    assert fsspec_options({OPTION: "obstore", "anon": True}) == {"anon": True}


def test_an_obstore_storage_pickles_its_choice_and_no_secret():
    pytest.importorskip("s3fs")
    pytest.importorskip("obstore")
    from zarr.storage import ObjectStore

    from streamsvd.storage import open_storage

    storage = open_storage("s3://bucket/basis.zarr", storage_options={
        OPTION: "obstore", "key": "K-ID", "secret": "S-SECRET",
        "endpoint_url": "http://127.0.0.1:9"})
    assert isinstance(storage.zarr_store(read_only=True), ObjectStore)
    data = pickle.dumps(storage)
    assert b"S-SECRET" not in data and b"K-ID" not in data
    back = pickle.loads(data)
    assert back.storage_options[OPTION] == "obstore"
    assert isinstance(back.zarr_store(read_only=True), ObjectStore)


def test_obstore_finds_credentials_as_s3fs_does(tmp_path, monkeypatch):
    pytest.importorskip("botocore")
    from streamsvd.storage.zarr_stores import BotocoreCredentials

    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN",
                 "AWS_PROFILE"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / "credentials").write_text(
        "[default]\naws_access_key_id = D-ID\naws_secret_access_key = D-S\n"
        "[other]\naws_access_key_id = O-ID\naws_secret_access_key = O-S\n")
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "credentials"))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "config"))
    assert BotocoreCredentials(None)()["access_key_id"] == "D-ID"
    assert BotocoreCredentials("other")()["secret_access_key"] == "O-S"
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "E-ID")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "E-S")
    assert BotocoreCredentials(None)()["access_key_id"] == "E-ID"  # the environment first


def test_the_environment_sets_the_default_for_s3_only(monkeypatch):
    from streamsvd.storage.zarr_stores import ENVIRONMENT, choice_of

    monkeypatch.setenv(ENVIRONMENT, "obstore")
    assert choice_of("s3://b/p", {}, "store") == "obstore"
    assert choice_of("memory://p", {}, "store") == "fsspec"
    assert choice_of("s3://b/p", {OPTION: "fsspec"}, "store") == "fsspec"  # the option wins
    monkeypatch.setenv(ENVIRONMENT, "rust")
    with pytest.raises(InputError, match="the variable STREAMSVD_ZARR_STORE"):
        choice_of("s3://b/p", {}, "store")


def test_the_default_is_obstore_for_s3_with_options_it_honours(monkeypatch):
    from streamsvd.storage.zarr_stores import ENVIRONMENT, choice_of

    monkeypatch.delenv(ENVIRONMENT, raising=False)
    installed = importlib.util.find_spec("obstore") is not None
    assert choice_of("s3://b/p", {"endpoint_url": "http://h", "profile": "p",
                                  "client_kwargs": {"region_name": "r"}}, "store") == (
        "obstore" if installed else "fsspec")
    # s3fs options obstore does not take keep fsspec, which takes them
    assert choice_of("s3://b/p", {"anon": True}, "store") == "fsspec"
    assert choice_of("s3://b/p", {"client_kwargs": {"verify": False}}, "store") == "fsspec"
    assert choice_of("gs://b/p", {}, "store") == "fsspec"
    monkeypatch.setenv(ENVIRONMENT, "fsspec")  # the environment replaces the default
    assert choice_of("s3://b/p", {}, "store") == "fsspec"
