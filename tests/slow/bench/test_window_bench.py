"""bench/window_benchmark.py runs on tiny sizes and writes sane numbers."""

import importlib
import json
from pathlib import Path

import numpy as np

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"
EPS = np.finfo(float).eps


def test_window_benchmark_tiny(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("window_benchmark")
    mod.main(["--n", "600", "--m", "600", "--window", "60", "--block", "10",
              "--cost-windows", "20,100", "--check", "4", "--forget-m", "60",
              "--out", str(tmp_path)])
    report = json.loads((tmp_path / "window_benchmark.json").read_text())["results"]
    s = report["summary"]
    assert report["runs"][0]["W"] == 60 and len(report["runs"][0]["checks"]) == 4
    assert s["gaps"]  # the four amplitude groups leave gaps of at least 10
    assert s["max_orthogonality"] <= 50 * 600 * EPS
    assert s["forget_sv_error"] <= 50 * 600 * EPS
    assert s["bound_over_true"][0] >= 1.0
    exact = s["exact_window"]  # nothing truncated: the window's SVD to rounding
    assert exact["max_sv_rel"] <= 1e3 * 600 * EPS
    assert exact["max_orthogonality"] <= 50 * 600 * EPS
    assert_drawn(tmp_path / "window_benchmark.png")
