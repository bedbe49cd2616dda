"""bench/cluster_benchmark.py runs end to end on a tiny array and writes sane numbers.

In a process of its own: s3fs keeps one file system per set of options and process, and
the session's moto server is another endpoint than the benchmark's own.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_bench_cluster_tiny(tmp_path):
    pytest.importorskip("distributed")
    pytest.importorskip("moto.server")
    pytest.importorskip("s3fs")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    subprocess.run([sys.executable, str(BENCH / "cluster_benchmark.py"), "--quick",
                    "--contenders", "tree,tall,tall_tree,svd_compressed", "--out",
                    str(tmp_path)], check=True, env=env, capture_output=True, timeout=600)
    assert_drawn(tmp_path / "cluster_benchmark_quick.png")
    data = json.loads((tmp_path / "cluster_benchmark_quick.json").read_text())["results"]
    for name in ("tree", "tall", "tall_tree", "svd_compressed"):
        row = data["summary"][name]
        assert row["modes"] == data["config"]["k"]
        assert 1.0 - 1e-9 <= row["err_over_opt"] <= 1.0 + 1e-6
        assert row["seconds"] > 0 and row["client_peak_mb"] > 0
