"""The streaming benchmark runs on tiny sizes and writes sane numbers."""

import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

from tests._figures import assert_drawn

BENCH = Path(__file__).resolve().parents[3] / "bench"


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    return importlib.import_module


@pytest.mark.parametrize("cls", ["BrandSVD", "TunedBrandSVD"])
def test_brand_matches_batch_svd(bench, rng, cls):
    brand = bench("brand")
    A = rng.standard_normal((80, 12)) @ rng.standard_normal((12, 45))
    br = getattr(brand, cls)(80, rank=12, max_columns=45, max_block=7)
    for j in range(0, 45, 7):
        br.absorb(A[:, j : j + 7])
    s = np.linalg.svd(A, compute_uv=False)
    np.testing.assert_allclose(br.s, s[:12], rtol=1e-10)
    np.testing.assert_allclose(br.U @ (br.s[:, None] * br.V.T), A, atol=1e-10 * s[0])
    assert np.linalg.norm(br.U.T @ br.U - np.eye(12), 2) < 50 * 80 * np.finfo(float).eps
    assert br.error_bound < 1e-10 * s[0]


def test_stream_benchmark_tiny(bench, tmp_path):
    mod = bench("stream_benchmark")
    report = mod.main([
        "--out", str(tmp_path), "--n", "300", "--m", "80", "--rank", "30", "--target", "6",
        "--blocks", "20,1", "--prefix", "1:30", "--svd-k", "20,80", "--rules", "paper,jacobi",
        "--sweeps", "1,none", "--isolation", "inprocess", "--profile-updates", "20:2,1:5",
        "--ortho-updates", "200", "--long-n", "60", "--long-target", "5", "--long-chunk", "50",
    ])
    assert_drawn(tmp_path / "stream_benchmark.png")
    data = json.loads((tmp_path / "stream_benchmark.json").read_text())["results"]
    assert data["configurations"].keys() == {"block20", "block1"}
    assert data["configurations"]["block20"]["updates"] == 4
    assert data["configurations"]["block1"]["updates"] == 30 - 6 + 1
    eps = np.finfo(float).eps
    for conf in data["configurations"].values():
        methods = conf["methods"]
        assert len(methods) == 2 * 2 + 2
        for r in methods.values():
            assert not r["extrapolated"]
            assert len(r["times"]) == conf["updates"]
            assert all(t > 0 for t in r["times"])
            assert r["total_s"] >= sum(r["times"])
            assert r["peak_extra_mb"] >= 0.0
            assert 0.0 <= r["sv_rel_err"] < 1.0
            # no method beats Eckart-Young, and none is far from it on this easy stream
            assert 1.0 - 1e-9 <= r["recon_over_opt"] < 2.0
            assert r["orthogonality"] < 50 * 300 * eps
            if r["method"] != "ipca":
                # the guaranteed bound holds (to rounding)
                assert r["bound_over_error"] >= 1.0 - 1e-9
        # converged sweeps give the exact SVD of the expansion each update, as Brand
        brand = methods["Brand (CGS2+QR+gesdd)"]
        for rule in ("paper", "jacobi"):
            conv = methods[f"streamsvd {rule} sweeps=conv"]
            assert conv["recon_rel_err"] == pytest.approx(brand["recon_rel_err"], rel=1e-6)
            assert conv["bound_over_error"] == pytest.approx(1.0, rel=1e-6)
    svd = data["numpy_svd"]
    assert [d["k"] for d in svd["measured"]] == [20, 80]
    assert svd["sv_rel_err"] < 1e-10 and svd["recon_over_opt"] == pytest.approx(1.0, rel=1e-9)
    prof = data["profiles"]
    assert len(prof) == 4
    for p in prof:
        assert p["profiled_per_update_s"] > 0
        assert sum(p["parts_share"].values()) == pytest.approx(1.0, rel=1e-6)
    lo = data["long_stream"]
    assert lo["updates"] == 200 and len(lo["chunk_max_orth"]) == 4
    assert lo["max_orthogonality"] < lo["limit_50_n_eps"]
    targets = data["targets"]
    assert set(targets) >= {"speed_10x_ipca", "flat_time_1.2x", "orthogonality_50_n_eps"}
    assert all(math.isfinite(x["speedup_per_update"])
               for t in targets["speed_10x_ipca"].values() for x in t["rows"])
    assert report["wall_s"] > 0



def test_engine_benchmark_tiny(bench, tmp_path):
    mod = bench("engine_benchmark")
    report = mod.main([
        "--out", str(tmp_path), "--n", "2000", "--b", "10", "--cap", "12", "--rank", "40",
        "--updates", "3", "--threads", "1", "--repeats", "1", "--long-updates", "2000",
        "--long-every", "1000",
    ])
    rows = {r["method"]: r for r in report["block"]}
    eps = np.finfo(float).eps
    # the converged stream is the exact SVD of the truncated stream, as Brand's
    assert rows["streamsvd jacobi conv"]["sv_rel_error"] == pytest.approx(
        rows["brand"]["sv_rel_error"], rel=1e-6)
    assert all(r["orthogonality"] < 50 * 2000 * eps for r in rows.values())
    assert all(r["median_update_s"] > 0 and r["peak_bytes"] > 0 for r in rows.values())
    for res in report["long"].values():
        assert res["max_orthogonality"] < res["limit_50_n_eps"]
        assert len(res["mean_per_1000"]) == 2
    saved = json.loads((tmp_path / "engine_benchmark.json").read_text())["results"]
    assert {r["method"] for r in saved["block"]} == set(rows)
    assert_drawn(tmp_path / "engine_benchmark.png")


def test_estimator_benchmark_tiny(bench, tmp_path):
    mod = bench("estimator_benchmark")
    report = mod.main(["--quick", "--out", str(tmp_path)])
    res = report["results"]["StreamingSVD"]
    assert set(res) == {"200", "2000"}
    assert all(v["wall_s"] > 0 and v["cpu_s"] >= 0 for v in res.values())
    assert "IncrementalPCA" in report["results"]  # scikit-learn is a test extra
    assert_drawn(tmp_path / "estimator_benchmark_quick.png")
