"""bench/tight_targets.py runs on its tiny size beside pyMOR (skipped without pyMOR)."""

import importlib
import json
from pathlib import Path

import pytest

from tests._figures import assert_drawn

pytest.importorskip("pymor")

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_tight_targets_quick(monkeypatch, tmp_path, rbs480a_path):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("tight_targets")
    mod.main(["--quick", "--repeat", "1", "--out", str(tmp_path),
              "--cache", str(tmp_path / "cache"), "--blocks", "traj,10",
              "--dtypes", "float64,float32", "--products"])
    assert_drawn(tmp_path / "tight_targets_quick.png")
    data = json.loads((tmp_path / "tight_targets_quick.json").read_text())["results"]
    # 2 cases x 2 measures x 5 targets, for each block width and dtype
    assert len(data["targets"]) == 80
    assert {(r["dtype"], r["block"]) for r in data["targets"]} == {
        (d, b) for d in ("float64", "float32") for b in ("traj", "10")}
    for r in data["targets"]:
        # the certified bound holds and covers the true error; never more modes than HAPOD
        assert r["streamsvd_error"] <= r["bound"] * (1 + 1e-9) <= 1.0 + 1e-9, r
        assert r["streamsvd_modes"] <= r["hapod_modes"], r
        assert r["streamsvd_cpu"] > 0 and r["hapod_cpu"] > 0
        # --products: the products are counted (a wrapper that no longer takes would
        # count nothing) and every snapshot meets M at least once in each contender (per
        # update, at least the updates' width; the last update may be narrower)
        for side in ("streamsvd_products", "hapod_products"):
            counts = r[side]
            assert counts["total"] > 0 and counts["gram"] > 0, (side, r)
            assert counts["m_columns"] >= 0.9 * r["width"], (side, r)
    assert {r["contender"] for r in data["cap"]} >= {"streamsvd (default)", "HAPOD pod(modes=k)"}
    for r in data["rbs480a"]:
        if "residual" in r:
            assert max(r["residual"], r["orthogonality_u"], r["singular_values"]) < 50, r
