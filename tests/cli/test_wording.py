"""The streamsvd command's messages: option values, storage options, bad data, SOURCE's
layout, --tall's weights, a closed stdout, and data near the ends of the float range."""

import hashlib
import json
import math
import os
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from streamsvd.algebra.inner import DiagonalInner
from streamsvd.cli import main
from streamsvd.cli.reading import open_readonly
from tests.cli.test_ingest import MODES, WORKTREE, assert_one_line_error, run_cli


def _files(path):
    """Every file under ``path`` with the digest of its bytes."""
    return {p.relative_to(path): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------- option values


@pytest.mark.parametrize("given", [["--target-error", "-1e-3"], ["--target-error=-1e-3"],
                                   ["--target-error", "0"], ["--target-error=0"],
                                   ["--target-error", "-inf"], ["--target-error", "nan"]])
def test_a_target_error_not_positive_is_refused_in_one_wording(tmp_path, npy, capsys, given):
    """Spaced or with '=', negative or zero: one message naming the option, what it takes
    and the word given."""
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", npy, store, *given], capsys)
    assert_one_line_error(status, err)
    word = given[-1].split("=")[-1]
    assert f"argument --target-error: must be a positive number; got '{word}'" in err
    assert not store.exists()


def test_a_negative_number_in_any_notation_is_an_option_value(tmp_path, npy, capsys):
    status, _, err = run_cli(["ingest", npy, tmp_path / "s.zarr", "--eps", "-1e-3"], capsys)
    assert_one_line_error(status, err)
    assert "argument --eps: must be a finite number >= 0; got '-1e-3'" in err


@pytest.mark.parametrize("flag,value", [("--window", "30"), ("--forget", "0.9")])
def test_the_tree_mode_refuses_window_and_forget_in_cli_words(tmp_path, npy, capsys, flag,
                                                              value):
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", npy, store, flag, value, "--scheduler", "threads"],
                             capsys)
    assert_one_line_error(status, err)
    assert f"{flag} applies to the in-memory and tall modes only" in err
    assert f"Drop {flag}, or drop --scheduler (or add --tall)." in err
    assert "`options`" not in err and not store.exists()


# ----------------------------------------------------------------- bad data, layout


@pytest.mark.parametrize("mode", ["memory", "tall"])
def test_a_nan_mid_stream_says_the_store_is_kept_and_how_to_resume(tmp_path, matrix, capsys,
                                                                   mode):
    bad = matrix.copy()
    bad[10, 50] = np.nan  # in the block of columns 49:56
    src = tmp_path / "a.npy"
    np.save(src, bad)
    store = tmp_path / "s.zarr"
    argv = ["ingest", str(src), str(store), "--block", "7", "--quiet", *MODES[mode]]
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err)
    assert "holds nan at column 50, row 10" in err
    again = f"streamsvd {' '.join(argv)} --resume"
    assert err.rstrip().endswith(
        f"STORE {store} is kept and holds its last commit, the snapshots up to column 49 of "
        f"SOURCE; once SOURCE is repaired, continue with: {again}"), err
    np.save(src, matrix)  # repaired: the command given continues
    assert main(shlex.split(again)[1:]) == 0
    with open_readonly(store) as sc:
        assert sc.n_seen == 60


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_a_nan_before_any_commit_says_nothing_of_a_store(tmp_path, matrix, capsys, mode):
    """A STORE with nothing committed is removed: the line does not offer to resume it."""
    bad = matrix.copy()
    bad[3, 2] = np.nan
    src = tmp_path / "a.npy"
    np.save(src, bad)
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", src, store, "--block", "7", "--quiet",
                              *MODES[mode]], capsys)
    assert_one_line_error(status, err)
    assert "is kept" not in err and "--resume" not in err and not store.exists()


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_snapshots_saved_as_rows_are_refused_with_a_hint_to_transpose(tmp_path, matrix,
                                                                      capsys, mode):
    rows = tmp_path / "rows.npy"
    np.save(rows, matrix.T)  # 60 x 80: one snapshot per row
    np.save(tmp_path / "w.npy", np.ones(80))
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", rows, store, "--inner", tmp_path / "w.npy",
                              *MODES[mode]], capsys)
    assert_one_line_error(status, err)
    assert (f"SOURCE {rows} (60 x 80) looks saved with one snapshot per row: its rows have "
            "size 80, the size of --inner, while its columns, read as snapshots, have size "
            "60. Save its transpose (80 x 60, one snapshot per column)") in err
    assert not store.exists()
    # continuing a store of snapshots of size 80 with it: the store is left as it was
    np.save(tmp_path / "a.npy", matrix)
    assert main(["ingest", str(tmp_path / "a.npy"), str(store), "--quiet", *MODES[mode]]) == 0
    before = _files(store)
    status, _, err = run_cli(["ingest", rows, store, "--resume", "--quiet", *MODES[mode]],
                             capsys)
    assert_one_line_error(status, err)
    assert f"its rows have size 80, the size of the basis in STORE {store}" in err
    assert "Save its transpose (80 x 60" in err
    assert _files(store) == before


# -------------------------------------------------------------------- --tall weights


@pytest.mark.parametrize("fmt", ["csr", "dia"])
def test_tall_takes_a_diagonal_sparse_mass_matrix_as_weights(tmp_path, matrix, capsys, rng,
                                                             fmt):
    """pyMOR's finite-volume l2_product saved by scipy.sparse.save_npz: a diagonal matrix."""
    w = rng.uniform(0.5, 2.0, 80)
    mass = tmp_path / "mass.npz"
    sp.save_npz(mass, sp.diags_array(w).asformat(fmt))
    np.save(tmp_path / "w.npy", w)
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "tall.zarr"
    assert main(["ingest", str(src), str(store), "--tall", "--inner", str(mass), "--block",
                 "10", "--quiet"]) == 0
    np.save(src, matrix)
    assert main(["ingest", str(src), str(store), "--tall", "--inner", str(mass), "--resume",
                 "--block", "10", "--quiet"]) == 0
    status, out, err = run_cli(["info", store, "--inner", mass, "--json"], capsys)
    assert status == 0, err
    assert json.loads(out)["inner"].startswith("DiagonalInner(n=80")
    with open_readonly(store) as sc:
        assert isinstance(sc.inner, DiagonalInner)
        np.testing.assert_array_equal(sc.inner.weights, w)
        U, amplitudes = sc.expansion.U, sc.amplitudes
    assert np.linalg.norm(U.T @ (w[:, None] * U) - np.eye(U.shape[1]), 2) <= 50 * 80 * 2.3e-16
    # the same as the weights given as a .npy
    weights = tmp_path / "weights.zarr"
    assert main(["ingest", str(src), str(weights), "--tall", "--inner", str(tmp_path / "w.npy"),
                 "--block", "10", "--quiet"]) == 0
    with open_readonly(weights) as sc:
        np.testing.assert_allclose(sc.amplitudes, amplitudes, rtol=1e-12, atol=1e-14)


def test_tall_refuses_a_sparse_matrix_with_entries_off_its_diagonal(tmp_path, npy, capsys):
    mass = tmp_path / "mass.npz"
    sp.save_npz(mass, sp.diags_array([np.full(79, 0.1), np.ones(80), np.full(79, 0.1)],
                                     offsets=[-1, 0, 1]).tocsr())
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", npy, store, "--tall", "--inner", mass], capsys)
    assert_one_line_error(status, err)
    assert ("--inner with --tall must be weights: a 1-D .npy of positive weights, or a matrix "
            f"with nothing off its diagonal; got {mass}, a 80 x 80 matrix with entries off its "
            "diagonal") in err
    assert "Drop --tall, or lump the mass matrix into weights." in err
    assert not store.exists()


# ------------------------------------------------------------------------- stdout


@pytest.mark.parametrize("extra", [[], ["--json"]])
def test_info_into_a_closed_pipe_exits_quietly(tmp_path, npy, extra):
    """`streamsvd info STORE | head`: the reader has gone; no error, no traceback."""
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(npy), str(store), "--quiet"]) == 0
    read, write = os.pipe()
    os.close(read)  # a reader that has gone before the command writes
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "streamsvd", "info", str(store), *extra], stdout=write,
            stderr=subprocess.PIPE, text=True, check=False,
            env={"PYTHONPATH": str(WORKTREE), "PATH": ""})
    finally:
        os.close(write)
    assert (proc.returncode, proc.stderr) == (141, "")


# ------------------------------------------------------------- 1e±300, empty files


@pytest.mark.parametrize("mode", ["memory", "tall"])
def test_data_near_1e200_is_ingested_and_summarised_in_finite_figures(tmp_path, matrix,
                                                                      capsys, mode):
    src = tmp_path / "big.npy"
    np.save(src, matrix * 1e200)
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", src, store, "--max-rank", "5", "--block", "7",
                              "--quiet", *MODES[mode]], capsys)
    assert status == 0, err
    status, out, err = run_cli(["info", store, "--json"], capsys)
    assert status == 0, err
    summary = json.loads(out)
    figures = [v for v in summary.values() if isinstance(v, float)]
    figures += summary["amplitudes_head"]
    assert figures and all(math.isfinite(v) for v in figures), summary
    assert summary["error_bound"] > 1e190
    status, out, err = run_cli(["info", store], capsys)
    assert status == 0, err
    assert not re.search(r"\b(inf|nan)\b", out, re.IGNORECASE), out


@pytest.mark.parametrize("what", ["SOURCE", "--inner .npy", "--inner .npz"])
def test_an_empty_file_is_named_in_one_line(tmp_path, npy, capsys, what):
    empty = tmp_path / ("empty.npz" if what.endswith(".npz") else "empty.npy")
    empty.write_bytes(b"")
    store = tmp_path / "s.zarr"
    argv = (["ingest", empty, store] if what == "SOURCE" else
            ["ingest", npy, store, "--inner", empty])
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err)
    assert str(empty) in err and what.split()[0] in err
    assert not store.exists()


# ------------------------------------------------------------------ --storage-option


@pytest.mark.parametrize("argv,named", [
    (["info", "s3://bucket/basis.zarr"], "STORE"),
    (["ingest", "s3://bucket/run.zarr", "s.zarr"], "SOURCE"),
])
def test_a_zarr_store_not_known_is_named_as_its_storage_option(tmp_path, capsys, monkeypatch,
                                                               argv, named):
    """Refused before any request: the option and the value given, in command-line words."""
    monkeypatch.chdir(tmp_path)
    status, _, err = run_cli([*argv, "--storage-option", "zarr_store=s3fs"], capsys)
    assert_one_line_error(status, err)
    assert (f"--storage-option zarr_store must be one of 'fsspec', 'obstore'; got 's3fs' "
            f"(for {named})." in err)
    assert "storage_options" not in err and not (tmp_path / "s.zarr").exists()


@pytest.fixture
def memory_source(matrix):
    """:func:`matrix` as a zarr array in fsspec's in-memory file system, removed after."""
    import fsspec
    import zarr

    url = "memory://streamsvd-cli-wording/run.zarr"
    zarr.save_array(url, matrix)
    yield url
    fsspec.filesystem("memory").rm(url.removeprefix("memory://"), recursive=True)


def test_obstore_for_a_source_not_on_s3_is_named_as_its_storage_option(tmp_path, capsys,
                                                                       memory_source):
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", memory_source, store, "--storage-option",
                              "zarr_store=obstore"], capsys)
    assert_one_line_error(status, err)
    assert (f"--storage-option zarr_store=obstore is for s3:// URLs; got SOURCE "
            f"{memory_source}. Drop the option for other URLs." in err)
    assert "storage_options" not in err and not store.exists()


# ------------------------------------------------------------------- a missed target


def test_info_names_why_a_target_is_missed(tmp_path, matrix, capsys):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "capped.zarr"
    status, _, err = run_cli(["ingest", src, store, "--target-error", "1e-8", "--max-rank",
                              "3", "--quiet"], capsys)
    assert status == 0, err
    status, out, err = run_cli(["info", store], capsys)
    assert status == 0, err
    assert "NOT met (--max-rank cuts more than the target allows)" in out
    # a relative target over a window whose snapshots shrink a millionfold: what was cut
    # for the large ones exceeds the budget of the small ones; no --max-rank to blame
    shrinking = np.column_stack([matrix[:, :30] * 1e6, matrix[:, 30:]])
    np.save(src, shrinking)
    store = tmp_path / "window.zarr"
    status, _, err = run_cli(["ingest", src, store, "--target-error", "1e-3", "--window",
                              "30", "--block", "10", "--quiet"], capsys)
    assert status == 0, err
    status, out, err = run_cli(["info", store, "--json"], capsys)
    summary = json.loads(out)
    status, out, err = run_cli(["info", store], capsys)
    assert summary["target_met"] is False and summary["target_missed_by"] == "earlier_updates"
    assert "NOT met (what earlier updates discarded exceeds the budget now" in out
    assert "--max-rank" not in out.split("target error")[1].splitlines()[0]
