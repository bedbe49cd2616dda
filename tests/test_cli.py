"""The streamsvd command: ingest, info, export, plot, and one-line errors."""

import json

import h5py
import numpy as np
import pytest
import zarr

from streamsvd.cli import main
from streamsvd.stream import StreamCompressor
from streamsvd.testing import with_spectrum


@pytest.fixture
def matrix(rng):
    return with_spectrum(np.logspace(0, -8, 20), 80, 60, rng)


@pytest.mark.parametrize("kind", ["npy", "h5", "zarr"])
def test_ingest_every_source_kind_gives_the_same_basis(tmp_path, matrix, kind, capsys):
    if kind == "npy":
        src = tmp_path / "a.npy"
        np.save(src, matrix)
        extra = []
    elif kind == "h5":
        src = tmp_path / "a.h5"
        with h5py.File(src, "w") as f:
            f.create_dataset("snapshots", data=matrix)
        extra = ["--dataset", "snapshots"]
    else:
        src = tmp_path / "a.zarr"
        z = zarr.open_array(src, mode="w", shape=matrix.shape, chunks=(40, 7), dtype="f8")
        z[:] = matrix
        extra = []
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--block", "7", "--rule", "jacobi",
                 "--sweeps", "0", "--quiet", *extra]) == 0
    with StreamCompressor.open(store, mode="r") as sc:
        s = np.linalg.svd(matrix, compute_uv=False)
        np.testing.assert_allclose(sc.expansion.amplitudes[:20], s[:20], atol=1e-13)
        assert sc.n_seen == 60


def test_info_export_plot(tmp_path, matrix, capsys):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--rtol", "1e-6", "--quiet"]) == 0
    assert main(["info", str(store), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_seen"] == 60 and info["rank"] <= 20
    assert main(["info", str(store)]) == 0
    assert "error bound   ||A - U V^T||_F <=" in capsys.readouterr().out
    for out in ("u.npz", "u.h5"):
        assert main(["export", str(store), str(tmp_path / out)]) == 0
    with np.load(tmp_path / "u.npz") as z:
        assert np.linalg.norm(matrix - z["U"] @ z["V"].T) <= z["error_bound"] + 1e-12
    with h5py.File(tmp_path / "u.h5") as f:
        assert f["U"].shape == (80, info["rank"])
    assert main(["plot", str(store), str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv,match",
    [(["info", "{tmp}/missing.zarr"], r"^streamsvd: error: `path` must be an existing basis store"),
     (["ingest", "{tmp}/missing.npy", "{tmp}/b.zarr"], r"^streamsvd: error: .*missing.npy"),
     (["export", "{tmp}/b.zarr", "{tmp}/x.txt"], r"^streamsvd: error: `out` must end with .npz, .h5 or .hdf5")],
)
def test_user_errors_print_one_line_and_exit_2(tmp_path, matrix, capsys, argv, match):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    assert main(["ingest", str(src), str(tmp_path / "b.zarr"), "--quiet"]) == 0
    capsys.readouterr()
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    import re

    assert re.search(match, err)


def test_existing_store_needs_resume(tmp_path, matrix, capsys):
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--quiet"]) == 0
    assert main(["ingest", str(src), str(store), "--quiet"]) == 2
    assert "pass --resume" in capsys.readouterr().err
    np.save(src, matrix)
    assert main(["ingest", str(src), str(store), "--quiet", "--resume"]) == 0
    with StreamCompressor.open(store, mode="r") as sc:
        assert sc.n_seen == 60


@pytest.mark.parametrize("extra", [["--scheduler", "threads"], ["--tall", "--chunk-rows", "32"]])
def test_ingest_on_dask_then_info_export(tmp_path, matrix, capsys, extra):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--block", "12", "--rule", "jacobi",
                 "--sweeps", "0", "--quiet", *extra]) == 0
    assert main(["info", str(store), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_seen"] == 60
    s = np.linalg.svd(matrix, compute_uv=False)
    np.testing.assert_allclose(info["amplitudes_head"], s[:10], atol=1e-13)
    assert main(["export", str(store), str(tmp_path / "u.npz")]) == 0
    with np.load(tmp_path / "u.npz") as z:
        assert np.linalg.norm(matrix - z["U"] @ z["V"].T) <= 1e-12
