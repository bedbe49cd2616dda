"""The slow tier's end-to-end files: every test below this folder is marked ``slow``.

Benchmarks' smoke runs (``bench/``), the examples (``examples/``), kills, resumes, fault
injection and creation crash points (``faults/``), a pip install into a fresh virtualenv
(``install/``) and the S3 server (``s3/``). A ``pytestmark`` set in a conftest does not
reach the test modules, so the mark is added at collection, by the tests' path.
"""

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config, items):
    """Mark every collected test under this folder ``slow``."""
    for item in items:
        if item.path.resolve().is_relative_to(HERE):
            item.add_marker(pytest.mark.slow)
