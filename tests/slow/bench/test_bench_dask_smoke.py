"""bench/bench_dask.py runs end to end on a tiny array and writes sane numbers."""

import importlib
import json
import math
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"

def test_bench_dask_tiny(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("bench_dask")
    mod.main([
        "--size", "3000x120", "--chunk-rows", "1000", "--block", "20", "--tree-block", "20",
        "--tall-block", "40", "--k", "4", "--oversample", "6", "--signal", "12",
        "--workers", "1", "--inprocess", "--out", str(tmp_path), "--tmpdir", str(tmp_path),
    ])
    assert_drawn(tmp_path / "bench_dask.png")
    data = json.loads((tmp_path / "bench_dask.json").read_text())["results"]
    assert not any(p.name.startswith("streamsvd-bench-") for p in tmp_path.iterdir())
    runs = {(r["method"], r["workers"]): r for r in data["runs"]}
    assert set(runs) == {
        ("read", None), ("tsqr", None), ("svd_compressed q=0", None),
        ("svd_compressed q=1", None), ("svd_compressed q=2", None),
        ("streamsvd tree", None), ("streamsvd tall", None),
        ("streamsvd tree", 1), ("streamsvd tall", 1),
    }
    for r in data["runs"]:
        assert r["seconds"] > 0 and r["peak_rss"] > 0
    for (method, _), r in runs.items():
        if method == "read":
            continue
        assert r["orthogonality"] < 1e-10
        assert 1.0 - 1e-9 <= r["error_over_optimal"] < 1.5, method
        assert r["max_angle_sin"] < 1e-2
    for method in ("streamsvd tree", "streamsvd tall"):
        r = runs[(method, None)]
        assert r["error_over_optimal"] < 1.01 and r["sv_error"] < 1e-6
        assert r["update_seconds"] > 0 and r["update_columns"] == 40
        assert r["error_bound"] >= 0 and math.isfinite(r["error_bound"])
        # same result on a LocalCluster as on the threaded scheduler
        assert runs[(method, 1)]["error_rel"] == pytest.approx(r["error_rel"], rel=1e-8)
    assert set(data["targets"]) == {"streamsvd tree", "streamsvd tall"}
