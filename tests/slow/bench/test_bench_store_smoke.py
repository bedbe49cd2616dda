"""The store benchmark runs on tiny sizes and writes sane numbers."""

import importlib
import json
from pathlib import Path

import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    return importlib.import_module


def test_store_benchmark_tiny(bench, tmp_path):
    mod = bench("store_benchmark")
    report = mod.main([
        "--out", str(tmp_path), "--dir", str(tmp_path / "stores"), "--ms", "60,600",
        "--n", "20", "--block", "3", "--updates", "4", "--max-rank", "6",
    ])
    assert_drawn(tmp_path / "store_benchmark.png")
    saved = json.loads((tmp_path / "store_benchmark.json").read_text())["results"]
    assert [r["m"] for r in saved["results"]] == [60, 600]
    for r in report["results"]:
        assert r["same_as_in_memory"] and r["store_reopens_bit_for_bit"]
        assert len(r["commit_seconds_all"]) == 4 and r["commit_seconds"]["median"] > 0
        assert r["written_bytes"]["max"] > 0
        assert r["V0_bytes"] >= 8 * r["m"]
    # a commit writes far less than V0 (the exact test is in test_persistence.py)
    large = report["results"][1]
    assert large["written_bytes"]["max"] < large["V0_bytes"] / 4
    assert saved["machine"]["load_average"] is not None
    # a run of the previous layout can be drawn beside this one
    baseline = tmp_path / "format1.json"
    baseline.write_text((tmp_path / "store_benchmark.json").read_text())
    (tmp_path / "store_benchmark.png").unlink()
    mod.main(["--out", str(tmp_path), "--ms", "60", "--n", "20", "--block", "3", "--updates",
              "2", "--max-rank", "6", "--baseline", str(baseline)])
    assert_drawn(tmp_path / "store_benchmark.png")


def test_store_benchmark_tiny_in_a_mass_matrix_product(bench, tmp_path):
    """With --inner mass the store keeps the matrix: written by the save, never again."""
    report = bench("store_benchmark").main([
        "--out", str(tmp_path), "--dir", str(tmp_path / "stores"), "--ms", "60,600",
        "--n", "20", "--block", "3", "--updates", "4", "--max-rank", "6", "--inner", "mass",
    ])
    assert_drawn(tmp_path / "store_benchmark_mass.png")
    assert not (tmp_path / "store_benchmark.json").exists()
    small, large = report["results"]
    assert small["same_as_in_memory"] and large["store_reopens_bit_for_bit"]
    assert large["written_bytes"]["max"] < large["V0_bytes"] / 4
