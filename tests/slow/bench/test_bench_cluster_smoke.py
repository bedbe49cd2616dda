"""bench/cluster_benchmark.py runs end to end on a tiny array and writes sane numbers."""

import importlib
import json
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_bench_cluster_tiny(monkeypatch, tmp_path):
    pytest.importorskip("distributed")
    pytest.importorskip("moto.server")
    pytest.importorskip("s3fs")
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("cluster_benchmark")
    mod.main(["--quick", "--contenders", "tree,tall,svd_compressed", "--out", str(tmp_path)])
    assert_drawn(tmp_path / "cluster_benchmark_quick.png")
    data = json.loads((tmp_path / "cluster_benchmark_quick.json").read_text())["results"]
    for name in ("tree", "tall", "svd_compressed"):
        row = data["summary"][name]
        assert row["modes"] == data["config"]["k"]
        assert 1.0 - 1e-9 <= row["err_over_opt"] <= 1.0 + 1e-6
        assert row["seconds"] > 0 and row["client_peak_mb"] > 0
