"""``streamsvd dmd`` and ``ingest --dynamics`` (streamsvd.cli.dmd)."""

import json

import numpy as np
import pytest

from streamsvd.cli import main
from streamsvd.testing.systems import match_eigenvalues, normal_system


@pytest.fixture
def trajectory(tmp_path, rng):
    sysm = normal_system(40, np.array([0.99, 0.9]), np.array([0.3, 1.2]), rng,
                         real=np.array([0.6]))
    X = sysm.trajectory(rng.standard_normal(5), 60)
    np.save(tmp_path / "x.npy", X)
    np.save(tmp_path / "x1.npy", X[:, :35])
    return sysm


def test_dmd_of_a_resumed_dynamics_store(tmp_path, trajectory, capsys):
    store = str(tmp_path / "s.zarr")
    assert main(["ingest", str(tmp_path / "x1.npy"), store, "--dynamics", "--block", "10",
                 "--quiet"]) == 0
    assert main(["ingest", str(tmp_path / "x.npy"), store, "--resume", "--block", "10",
                 "--quiet", "--source-changed-ok"]) == 0
    capsys.readouterr()
    assert main(["dmd", store, "--json", "--dt", "0.5", "--forecast", "2",
                 str(tmp_path / "f.npz"), "--modes", str(tmp_path / "m.npz")]) == 0
    out = json.loads(capsys.readouterr().out)
    lam = np.array([complex(*z) for z in out["eigenvalues"]])
    assert out["dynamics_recorded"] and out["pairs"] == 59
    assert np.max(match_eigenvalues(lam, trajectory.eigenvalues)) < 1e-12
    assert max(out["residual_bounds"]) < 1e-10
    assert np.load(tmp_path / "f.npz")["forecast"].shape == (40, 2)
    assert np.load(tmp_path / "m.npz")["modes"].shape == (40, 5)
    assert main(["dmd", store, "--rank", "2"]) == 0
    text = capsys.readouterr().out
    assert "59 pairs, rank 2" in text and "eta" in text
    assert main(["info", store]) == 0
    assert "dynamics      recorded (1 trajectory)" in capsys.readouterr().out


def test_dmd_refusals(tmp_path, trajectory, capsys):
    store = str(tmp_path / "s.zarr")
    assert main(["ingest", str(tmp_path / "x.npy"), store, "--quiet"]) == 0
    capsys.readouterr()
    assert main(["dmd", store, "--forecast", "0", str(tmp_path / "f.npz")]) == 2
    assert "--forecast N OUT needs a positive integer N; got '0'" in capsys.readouterr().err
    assert main(["dmd", store, "--modes", str(tmp_path / "m.txt")]) == 2
    assert "--modes writes a .npz file" in capsys.readouterr().err
    assert main(["ingest", str(tmp_path / "x.npy"), str(tmp_path / "t.zarr"), "--dynamics",
                 "--scheduler", "threads", "--quiet"]) == 2
    assert "--dynamics applies to the in-memory and tall modes only" in capsys.readouterr().err


@pytest.mark.slow  # dask and panels on disk
def test_dmd_of_a_tall_store(tmp_path, trajectory, capsys):
    store = str(tmp_path / "t.zarr")
    assert main(["ingest", str(tmp_path / "x.npy"), store, "--dynamics", "--tall",
                 "--block", "20", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["dmd", store, "--json", "--forecast", "2", str(tmp_path / "f.npz")]) == 0
    out = json.loads(capsys.readouterr().out)
    lam = np.array([complex(*z) for z in out["eigenvalues"]])
    assert np.max(match_eigenvalues(lam, trajectory.eigenvalues)) < 1e-12
    assert np.load(tmp_path / "f.npz")["forecast"].shape == (40, 2)


@pytest.mark.slow  # a tree on dask
def test_dmd_of_a_tree_store_reads_its_right_vectors_in_order(tmp_path, trajectory, capsys):
    store = str(tmp_path / "t.zarr")
    assert main(["ingest", str(tmp_path / "x.npy"), store, "--scheduler", "threads",
                 "--block", "10", "--leaf-columns", "20", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["dmd", store, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    lam = np.array([complex(*z) for z in out["eigenvalues"]])
    assert out["pairs"] == 59 and not out["dynamics_recorded"]
    assert np.max(match_eigenvalues(lam, trajectory.eigenvalues)) < 1e-12
