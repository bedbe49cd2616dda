"""bench/dmd_benchmark.py runs on tiny sizes and writes sane numbers (needs the bench extra)."""

import importlib
import json
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_dmd_benchmark_tiny(tmp_path, monkeypatch):
    pytest.importorskip("pydmd")
    pytest.importorskip("odmd")
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("dmd_benchmark")
    mod.main(["--n", "200", "--m", "400", "--noises", "0,1e-8,1e-4", "--cost-n", "200",
              "--cost-m", "300", "--repeat", "1", "--odmd-max-n", "200", "--out",
              str(tmp_path)])
    report = json.loads((tmp_path / "dmd_benchmark.json").read_text())["results"]
    acc = {r["noise"]: r for r in report["accuracy"]}
    assert all(r["stream_certified"] for r in acc.values())
    assert acc[0.0]["stream"] <= 1e-12 and acc[0.0]["odmd_full"] is None
    for r in acc.values():  # within ten times the batch error
        assert r["stream"] <= 10 * r["pydmd"] + 1e-12
    cost = report["cost"][0]
    assert {"stream_dynamics", "stream_plain", "stream_query", "pydmd", "odmd_full"} <= set(cost)
    assert_drawn(tmp_path / "dmd_benchmark.png")
