"""bench/outofcore_benchmark.py runs on a tiny array and writes sane numbers."""

import importlib
import json
from pathlib import Path

import numpy as np
import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.mark.parametrize(("dtype", "methods"), [
    ("float32", ("read", "cli-c100", "tall", "tree", "svdc-q1-QR")),
    ("float64", ("read", "tall")),
])
def test_outofcore_benchmark_smoke(monkeypatch, tmp_path, dtype, methods):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("outofcore_benchmark")
    report = mod.main(["--sizes", "3000x250", "--dtype", dtype, "--methods",
                       ",".join(methods), "--data", str(tmp_path / "data"),
                       "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "outofcore_benchmark.json").read_text())["results"]
    assert_drawn(tmp_path / "outofcore_benchmark.png")
    (case,) = saved["cases"]
    assert case["dtype"] == dtype and (case["n"], case["m"]) == (3000, 250)
    runs = {r["method"]: r for r in case["runs"]}
    assert set(runs) == set(methods)
    for name in set(methods) & {"cli-c100", "tall", "tree"}:
        r = runs[name]
        assert r["seconds"] > 0 and r["peak_rss_mb"] > 0 and r["vs_read"] > 0
        # the CPU time of the process over the timed part, and the floor it sets
        assert r["cpu_seconds"] > 0 and r["process_cpu_seconds"] >= r["cpu_seconds"]
        assert r["cores"] == pytest.approx(r["cpu_seconds"] / r["seconds"])
        assert r["floor_vs_read"] == pytest.approx(
            r["cpu_seconds"] / saved["cores"] / r["read_seconds"])
        # rank 60 of a rank-200 spectrum: streamsvd is within 1e-3 of the optimum
        assert 1.0 - 1e-9 <= r["error_over_optimum"] <= 1.001
    assert report["cases"][0]["optimum"] == pytest.approx(case["optimum"])
    s = np.logspace(0, -10, 200)
    want = np.sqrt(np.sum(s[60:] ** 2))
    # the float32 optimum is that of the rounded data: within 2^-24 ||A||_F of the exact
    assert abs(case["optimum"] - want) <= (0 if dtype == "float64" else 2.0**-23) * np.sqrt(
        np.sum(s**2)) + 1e-15
