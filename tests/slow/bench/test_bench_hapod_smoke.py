"""bench/hapod_benchmark.py runs on its tiny size beside pyMOR (skipped without pyMOR)."""

import importlib
import json
import math
from pathlib import Path

import pytest

from tests._figures import assert_drawn

pytest.importorskip("pymor")

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_hapod_benchmark_quick(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("hapod_benchmark")
    mod.main(["--quick", "--out", str(tmp_path), "--cache", str(tmp_path / "cache")])
    assert_drawn(tmp_path / "hapod_benchmark.png")
    data = json.loads((tmp_path / "hapod_benchmark.json").read_text())["results"]
    for case in ("burgers", "heat"):
        res = data["cases"][case]["results"]
        for t in data["targets"]:
            opt = res[f"pod@{t:g}"]
            for name in ("inc_hapod", "dist_hapod", "streamsvd"):
                r = res[f"{name}@{t:g}"]
                assert r["seconds"] > 0.0 and r["modes"] >= opt["modes"]
                assert r["error"] <= t * (1 + 1e-9), (case, name, t, r["error"])
            sv = res[f"streamsvd@{t:g}"]
            assert sv["error"] <= sv["bound_mean_l2"] * (1 + 1e-9)
    res = data["cases"]["synthetic"]["results"]
    for key, r in res.items():
        assert r["modes"] == data["cases"]["synthetic"]["cap"], key
        assert 1.0 - 1e-9 <= r["err_opt"] < 1.01, key
        assert math.isfinite(r["sv_err"]), key
    assert set(data["threads"]["results"]) == {"1", "default"}
