import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", derandomize=True, max_examples=60, deadline=None,
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
def rbs480a_path():
    path = DATA_DIR / "rbs480a.mtx"
    if not path.exists():
        pytest.skip(
            f"rbs480a.mtx not found at {path}; get RBS480A from the Matrix Market "
            "collection (Harwell-Boeing) and place it in ../shared/data/"
        )
    return path
