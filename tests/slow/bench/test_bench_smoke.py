"""The benchmark scripts of bench/ run on tiny sizes and write sane numbers."""

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

    def load(name):
        return importlib.import_module(name)

    return load


def _read(path):
    assert path.is_file() and path.stat().st_size > 0, path
    return json.loads(path.read_text())["results"]


def test_fig1_pair_dynamics(bench, tmp_path):
    mod = bench("fig1_pair_dynamics")
    mod.main(["--out", str(tmp_path), "--steps", "12", "--random", "10"])
    assert_drawn(tmp_path / "fig1_pair_dynamics.png")
    data = _read(tmp_path / "fig1_pair_dynamics.json")
    assert data["max_deviation_plotted"] < 1e-12
    assert data["max_deviation_random"]["eta"] < 1e-12
    assert data["max_deviation_random"]["relative_product_change"] < 1e-12
    for t in data["trajectories"]:
        assert 0.0 < t["eta_limit"] < 1.0
        alpha = np.array(t["alpha"])
        eta = np.array(t["eta"])
        assert np.all(np.diff(alpha) <= 0.0) and np.all(np.diff(eta) <= 0.0)
        assert t["invariant_max_dev"] < 1e-10
        assert eta[-1] >= t["eta_limit"] - 1e-12


def test_fig3_rbs480a(bench, tmp_path, rbs480a_path):
    mod = bench("fig3_rbs480a")
    mod.main(["--out", str(tmp_path), "--data", str(rbs480a_path), "--size", "40",
              "--max-sweeps", "8", "--steep-modes", "5"])
    for name in ("fig2_rbs480a_spectra.png", "fig3_rbs480a.png"):
        assert_drawn(tmp_path / name)
    data = _read(tmp_path / "fig3_rbs480a.json")
    assert data["sweep_list"] == [1, 2, 3, 5, 8]
    assert set(data["configurations"]) == {"original", "medium slope", "strong initial slope"}
    for conf in data["configurations"].values():
        s = np.array(conf["s_mod"])
        assert s.size == 40 and np.all(np.diff(s) <= 0.0)
        for rr in conf["rules"].values():
            E = [conf["E0"]] + [r["E"] for r in rr["runs"]]
            assert all(math.isfinite(x) and x >= 0.0 for x in E)
            assert E[-1] < 0.5 * E[0]
            assert len(rr["indicator"]) == rr["runs"][-1]["sweeps"]
    jac = data["configurations"]["original"]["rules"]["jacobi"]["runs"]
    assert np.all(np.diff([r["E"] for r in jac]) <= 1e-12)


def test_fig3_missing_data_says_where_to_get_it(bench, tmp_path):
    mod = bench("fig3_rbs480a")
    with pytest.raises(SystemExit, match="Matrix Market"):
        mod.main(["--out", str(tmp_path), "--data", str(tmp_path / "absent.mtx")])


def test_speed_vs_error_generated(bench, tmp_path):
    mod = bench("speed_vs_error")
    mod.main(["--out", str(tmp_path), "--matrices", "generated", "--n", "48",
              "--decades", "3", "--ranks", "5,20", "--run-cap", "3",
              "--literal-cap", "3", "--literal-max-n", "64"])
    assert_drawn(tmp_path / "speed_vs_error_generated.png")
    st = _read(tmp_path / "speed_vs_error_generated.json")
    assert set(st["series"]) == {"fast/paper", "fast/jacobi", "literal/jacobi"}
    for s in st["series"].values():
        runs = s["runs"]
        assert runs and all(r["seconds"] > 0.0 for r in runs)
        assert runs[-1]["sv"] < runs[0]["sv"]
        assert runs[-1]["excess"]["5"] < runs[0]["excess"]["5"]
    jac = st["series"]["fast/jacobi"]
    assert jac["converged"] and jac["runs"][-1]["sv"] < 1e-12
    lit = st["series"]["literal/jacobi"]["runs"]
    fast = {r["max_sweeps"]: r["sv"] for r in jac["runs"]}
    for r in lit:
        assert abs(r["sv"] - fast[r["max_sweeps"]]) < 1e-10
    for b in st["lapack"].values():
        assert b["seconds"] > 0.0 and b["sv"] < 1e-12
        assert abs(b["excess"]["20"]) < 1e-10 and b["subspace"]["5"] < 1e-8


def test_speed_vs_error_missing_data(bench, tmp_path):
    mod = bench("speed_vs_error")
    with pytest.raises(SystemExit, match="Matrix Market"):
        mod.main(["--out", str(tmp_path), "--matrices", "rbs480a",
                  "--data", str(tmp_path / "absent.mtx")])


def test_final_benchmark_tiny(bench, tmp_path):
    """The final sweeps store the SVD of the expansion kept; oversampling helps."""
    mod = bench("final_benchmark")
    mod.main(["--out", str(tmp_path), "--n", "200", "--m", "60", "--k", "4",
              "--oversampling", "0,10", "--spectra", "gap,log3", "--modes", "memory,tall",
              "--blocks", "20"])
    assert_drawn(tmp_path / "final_benchmark.png")
    rows = _read(tmp_path / "final_benchmark.json")["rows"]
    assert len(rows) == 2 * 2 * 4
    for r in rows:
        if r["case"] == "no max-rank":  # the SVD of the data, at LAPACK accuracy
            assert r["rank"] == 60 and r["sv_err"] <= 50 * 60 * np.finfo(float).eps
        elif "final none" not in r["case"]:
            assert r["rank"] == 4 and r["kept_err_eps"] <= 50 * 60
            assert r["err_over_opt"] >= 1 - 1e-12  # never better than Eckart-Young
    for spectrum in ("gap", "log3"):
        by = {(r["mode"], r["case"]): r for r in rows if r["spectrum"] == spectrum}
        for mode in ("memory", "tall"):
            assert by[mode, "os 10"]["err_over_opt"] < by[mode, "os 0"]["err_over_opt"]
        assert by["tall", "os 10"]["err_over_opt"] == pytest.approx(
            by["memory", "os 10"]["err_over_opt"], rel=1e-9)


def test_target_benchmark_quick(bench, tmp_path):
    """Every mode meets every relative target with the optimal modes (+1), and the bound
    holds after every update."""
    mod = bench("target_benchmark")
    mod.main(["--quick", "--out", str(tmp_path)])
    assert_drawn(tmp_path / "target_benchmark.png")
    rows = _read(tmp_path / "target_benchmark.json")["results"]
    assert len(rows) == 15
    for r in rows:
        assert r["true_error"] <= r["target"]
        assert r["modes"] <= r["optimum"] + 1
        assert 1.0 - 1e-9 <= r["bound_over_true"] <= 1.5
        if r["mode"] == "memory":
            assert r["worst_true_over_bound"] <= 1.0 + 1e-9


def test_merge_benchmark(bench, tmp_path):
    """Both merge paths run, give the same optimal error and orthonormal factors."""
    mod = bench("merge_benchmark")
    mod.main(["--quick", "--out", str(tmp_path)])
    assert_drawn(tmp_path / "merge_benchmark.png")
    rows = {r["path"]: r for r in _read(tmp_path / "merge_benchmark.json")["rows"]}
    assert rows["gram"]["passes"] == 2 and rows["gram"]["sweeps"] == 0
    assert rows["exact"]["passes"] > 2
    for r in rows.values():
        assert 1.0 <= r["err_over_opt"] <= 1.0001
        assert r["orthogonality"] <= 100 * 3000 * np.finfo(float).eps
    assert abs(rows["gram"]["err_over_opt"] - rows["exact"]["err_over_opt"]) <= 1e-6


def test_commit_benchmark(bench, tmp_path):
    """Both layouts commit and read back the basis exactly; compression saves few bytes."""
    mod = bench("commit_benchmark")
    mod.main(["--quick", "--out", str(tmp_path), "--dir", str(tmp_path)])
    assert_drawn(tmp_path / "commit_benchmark.png")
    rows = {r["layout"]: r for r in _read(tmp_path / "commit_benchmark.json")["rows"]}
    assert rows["stored as is"]["bytes_over_data"] == pytest.approx(1.0, abs=0.01)
    assert 0.8 < rows["zstd level 3"]["bytes_over_data"] < 1.0


def test_zarr_io_benchmark(bench, tmp_path):
    """Both routes run the tall mode and the chunk reads and writes, in child processes."""
    import zarr

    mod = bench("zarr_io_benchmark")
    A = np.random.default_rng(0).standard_normal((2000, 30))
    z = zarr.create_array(str(tmp_path / "a.zarr"), shape=A.shape, chunks=(500, 10),
                          dtype="float64")
    z[:] = A
    mod.main(["--source", str(tmp_path / "a.zarr"), "--repeat", "1", "--rows", "200",
              "--ops", "4", "--out", str(tmp_path)])
    assert_drawn(tmp_path / "zarr_io_benchmark.png")
    data = _read(tmp_path / "zarr_io_benchmark.json")
    assert set(data["tall_medians"]) == {"loops", "zarr"}
    assert all(v > 0 for v in data["tall_medians"].values())
    assert set(data["ops_medians"]) == {"loops@1", "zarr@1", "loops@2", "zarr@2"}
