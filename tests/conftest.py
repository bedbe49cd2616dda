import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", derandomize=True, max_examples=60, deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
# the fast tier's property tests: fewer examples, still derandomised
settings.register_profile(
    "fast", derandomize=True, max_examples=15, deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("dev", max_examples=60, deadline=None)
settings.register_profile("thorough", max_examples=1000, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))

DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


@pytest.fixture
def matrix(rng):
    """An 80 x 60 snapshot matrix of rank 20, singular values 1 .. 1e-8."""
    from streamsvd.testing import with_spectrum

    return with_spectrum(np.logspace(0, -8, 20), 80, 60, rng)


@pytest.fixture
def npy(tmp_path, matrix):
    """:func:`matrix` saved as ``a.npy``."""
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    return src


@pytest.fixture
def rbs480a_path():
    path = DATA_DIR / "rbs480a.mtx"
    if not path.exists():
        pytest.skip(
            f"rbs480a.mtx not found at {path}; get RBS480A from the Matrix Market "
            "collection (Harwell-Boeing) and place it in ../shared/data/"
        )
    return path


@pytest.fixture(scope="session")
def s3_server():
    """A moto S3 server on localhost for the session (skipped without moto and s3fs)."""
    pytest.importorskip("moto.server")
    pytest.importorskip("s3fs")
    from streamsvd.testing.s3server import start

    server = start()
    yield server
    server.stop()


@pytest.fixture
def s3(s3_server, monkeypatch, request):
    """A fresh bucket on the local S3 server; ``AWS_*`` set for this process and children.

    Yields the bucket's URL prefix, ``s3://<bucket>``.
    """
    import s3fs

    # the file-system instances fsspec caches are kept for the session: the endpoint is
    # the same throughout, and dropping them would leave their aiohttp sessions unclosed
    for key, value in s3_server.environment().items():
        monkeypatch.setenv(key, value)
    bucket = "t" + hashlib.sha256(request.node.nodeid.encode()).hexdigest()[:24]
    s3fs.S3FileSystem().mkdir(bucket)
    return f"s3://{bucket}"


@pytest.fixture
def spy_on(monkeypatch):
    """``spy_on(module, name)``: replace ``module.name`` by a spy; return its record.

    The record is a list that receives, call by call, whether the call returned
    something other than None (a path taken, or declined).
    """
    def install(module, name):
        original, calls = getattr(module, name), []

        def spy(*args, **kwargs):
            result = original(*args, **kwargs)
            calls.append(result is not None)
            return result

        monkeypatch.setattr(module, name, spy)
        return calls

    return install
