"""The object-store benchmark runs on tiny sizes against the local S3 server."""

import importlib
import json
from pathlib import Path

BENCH = Path(__file__).resolve().parents[3] / "bench"


def test_object_store_benchmark_tiny(s3, s3_server, tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    mod = importlib.import_module("object_store_benchmark")
    report = mod.main([
        "--out", str(tmp_path), "--dir", str(tmp_path / "local"), "--n", "20",
        "--block", "3", "--updates", "3", "--max-rank", "6",
        "--endpoint", s3_server.endpoint, "--bucket", s3.split("://")[1],
        "--source-rows", "300", "--source-cols", "30", "--repeats", "1",
    ])
    assert (tmp_path / "object_store_benchmark.png").stat().st_size > 0
    saved = json.loads((tmp_path / "object_store_benchmark.json").read_text())["results"]
    assert [r["store"] for r in saved["results"]] == ["local directory", "S3, fsspec",
                                                    "S3, obstore"]
    for r in report["results"]:
        assert r["reopens_bit_for_bit"] and len(r["commit_seconds_all"]) == 3
        assert r["commit_seconds"]["median"] > 0
