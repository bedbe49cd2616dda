"""bench/tight_targets.py's ingest case runs on a tiny array and writes sane numbers."""

import importlib
import json
from pathlib import Path

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_ingest_case_quick(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("tight_targets")
    mod.main(["--cases", "ingest", "--quick", "--repeat", "1", "--out", str(tmp_path),
              "--ingest-data", str(tmp_path / "data")])
    assert_drawn(tmp_path / "tight_targets_quick_ingest.png")
    assert not (tmp_path / "tight_targets_quick.json").exists()  # nothing else was run
    rows = json.loads((tmp_path / "tight_targets_quick_ingest.json").read_text())
    rows = rows["results"]["ingest"]
    import _ingest

    assert {(r["store"], r["contender"]) for r in rows} == {
        (s, c) for s in ("zstd", "raw") for c in _ingest.CONTENDERS} | {
        ("start-up", c) for c in _ingest.STARTUP}
    for r in rows:
        assert r["wall"] > 0 and r["cpu"] > 0 and len(r["runs"]) == 1
        if r["contender"] == "memory":
            assert r["wall_over_memory"] == r["cpu_over_memory"] == 1.0
        if r["store"] == "start-up":  # processes of their own, beside no in-memory run
            assert r["wall_over_memory"] is None
