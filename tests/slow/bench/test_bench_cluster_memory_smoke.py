"""bench/cluster_memory.py runs end to end on tiny arrays and writes sane numbers."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_bench_cluster_memory_tiny(tmp_path):
    pytest.importorskip("distributed")
    pytest.importorskip("psutil")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    subprocess.run([sys.executable, str(BENCH / "cluster_memory.py"), "--quick", "--out",
                    str(tmp_path)], check=True, env=env, capture_output=True, timeout=900)
    assert_drawn(tmp_path / "cluster_memory_quick.png")
    data = json.loads((tmp_path / "cluster_memory_quick.json").read_text())["results"]
    k = data["config"]["k"]
    assert {(r["contender"], r["n"]) for r in data["summary"]} == {
        (c, n) for c in ("tall", "tall_tree", "svd_compressed") for n in data["config"]["ns"]}
    for row in data["summary"]:
        assert row["modes"] == k
        assert row["s_rel_diff"] <= 1e-6  # the same singular values as svd_compressed
        assert len(row["worker_peaks_mb"]) == data["config"]["workers"]
        assert min(row["worker_peaks_mb"]) > 0 and row["client_peak_mb"] > 0
        assert row["seconds"] > 0
