"""The tall-tree checkpoints benchmark runs on tiny sizes."""

import importlib
import json
from pathlib import Path

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_tall_tree_checkpoints_benchmark_tiny(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("tall_tree_checkpoints_benchmark")
    report = mod.main(["--out", str(tmp_path), "--n", "500", "--m", "40", "--repeats", "1"])
    assert (tmp_path / "tall_tree_checkpoints_benchmark.png").stat().st_size > 0
    saved = json.loads((tmp_path / "tall_tree_checkpoints_benchmark.json").read_text())
    assert [r["contender"] for r in saved["results"]["results"]] == list(mod.CONTENDERS)
    assert all(r["wall_seconds"] > 0 for r in report["results"])
