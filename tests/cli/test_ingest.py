"""The streamsvd command: ingest, info, export, plot, output streams and one-line errors."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr

from streamsvd.cli import main
from streamsvd.cli.parsing import build_parser
from streamsvd.cli.reading import open_readonly
from streamsvd.cli.wording import in_cli_words
from streamsvd.plotting import compressor_figure
from streamsvd.stream.compressor import StreamCompressor

WORKTREE = Path(__file__).resolve().parents[2]
EPS = np.finfo(np.float64).eps

# the ingest options of each mode, as a user picks them
MODES = {"memory": [], "tree": ["--scheduler", "threads"], "tall": ["--tall"]}

# how Python advice looks: a quoted call, a keyword argument, a module path, a library
# argument name in backticks
PYTHON_ADVICE = re.compile(
    r"`[\w.]+\(|\b\w+=(True|False|None|'|\.\.\.)|mode=|BasisStore|open_store|open_compressor"
    r"|streamsvd\.\w|Rename the file|pass the array|`(path|source|store|dataset|block|out"
    r"|leaf_columns|chunk_rows|workers|scheduler|tall)`"
)


def run_cli(argv, capsys):
    """Run the command in this process; return (status, stdout, stderr)."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


def assert_one_line_error(status, err):
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("streamsvd: error: "), err
    assert "Traceback" not in err
    assert not PYTHON_ADVICE.search(err), err


# ---------------------------------------------------------------------------- ingest


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
                 "--sweeps", "converge", "--quiet", *extra]) == 0
    with StreamCompressor.open(store, mode="r") as sc:
        s = np.linalg.svd(matrix, compute_uv=False)
        np.testing.assert_allclose(sc.expansion.amplitudes[:20], s[:20], atol=1e-13)
        assert sc.n_seen == 60
        assert sc.sweeps is None  # --sweeps converge is the API's sweeps=None


def test_sweeps_takes_a_positive_count_or_converge(tmp_path, npy, capsys):
    for bad in ("0", "-1", "all"):
        status, out, err = run_cli(["ingest", npy, tmp_path / f"s{bad}.zarr", "--sweeps", bad],
                                   capsys)
        assert_one_line_error(status, err)
        assert f"argument --sweeps: must be a positive number of sweeps per update, or " \
               f"'converge' to sweep until no pair rotates; got '{bad}'" in err
        assert not (tmp_path / f"s{bad}.zarr").exists()
    assert main(["ingest", str(npy), str(tmp_path / "two.zarr"), "--sweeps", "2", "--quiet"]) == 0
    with StreamCompressor.open(tmp_path / "two.zarr", mode="r") as sc:
        assert sc.sweeps == 2
    assert main(["ingest", str(npy), str(tmp_path / "conv.zarr"), "--sweeps", "converge",
                 "--quiet"]) == 0
    status, out, _ = run_cli(["info", tmp_path / "conv.zarr"], capsys)
    assert status == 0 and "sweeps converge" in out


def test_commit_every_takes_a_positive_count_or_auto(tmp_path, npy, capsys):
    for bad in ("0", "-2", "often"):
        status, _, err = run_cli(["ingest", npy, tmp_path / f"s{bad}.zarr", "--commit-every",
                                  bad], capsys)
        assert_one_line_error(status, err)
        assert "argument --commit-every: must be a positive number of updates per commit, " \
               f"or 'auto'; got '{bad}'" in err
        assert not (tmp_path / f"s{bad}.zarr").exists()
    for given, recorded in ([], "auto"), (["--commit-every", "auto"], "auto"), \
            (["--commit-every", "4"], 4), (["--tall"], "auto"):
        store = tmp_path / f"s{len(given)}{recorded}.zarr"
        assert main(["ingest", str(npy), str(store), "--block", "7", "--quiet", *given]) == 0
        with open_readonly(store) as sc:
            assert sc.commit_every == recorded and sc.n_seen == 60  # the end commits all
    status, out, _ = run_cli(["ingest", "--help"], capsys)
    text = " ".join(out.split())
    assert "--commit-every C|auto when the updates are committed to STORE" in text
    assert "take at most a tenth of the time since the start" in text
    assert "(default: auto)" in text


def test_existing_store_needs_resume(tmp_path, matrix, capsys):
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--quiet"]) == 0
    status, _, err = run_cli(["ingest", src, store, "--quiet"], capsys)
    assert_one_line_error(status, err)
    assert "pass --resume to continue it" in err
    np.save(src, matrix)
    assert main(["ingest", str(src), str(store), "--quiet", "--resume"]) == 0
    with StreamCompressor.open(store, mode="r") as sc:
        assert sc.n_seen == 60


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_resume_continues_in_every_mode(tmp_path, matrix, capsys, mode):
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--block", "10", "--rule", "jacobi",
                 "--sweeps", "converge", "--quiet", *MODES[mode]]) == 0
    np.save(src, matrix[:, :40])
    # no option but the mode: the store's options are used
    assert main(["ingest", str(src), str(store), "--block", "10", "--resume", "--quiet",
                 *MODES[mode]]) == 0
    np.save(src, matrix)
    # the first command line with --resume added: options equal to the store's are accepted
    assert main(["ingest", str(src), str(store), "--block", "10", "--rule", "jacobi",
                 "--sweeps", "converge", "--resume", "--quiet", *MODES[mode]]) == 0
    status, out, _ = run_cli(["info", store, "--json"], capsys)
    info = json.loads(out)
    assert info["n_seen"] == 60 and info["options"]["rule"] == "jacobi"
    s = np.linalg.svd(matrix, compute_uv=False)
    np.testing.assert_allclose(info["amplitudes_head"], s[:10], atol=1e-12)


@pytest.mark.parametrize("extra", [["--scheduler", "threads"], ["--tall", "--chunk-rows", "32"]])
def test_ingest_on_dask_then_info_export(tmp_path, matrix, capsys, extra):
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(src), str(store), "--block", "12", "--rule", "jacobi",
                 "--sweeps", "converge", "--quiet", *extra]) == 0
    assert main(["info", str(store), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_seen"] == 60
    s = np.linalg.svd(matrix, compute_uv=False)
    np.testing.assert_allclose(info["amplitudes_head"], s[:10], atol=1e-13)
    assert main(["export", str(store), str(tmp_path / "u.npz")]) == 0
    with np.load(tmp_path / "u.npz") as z:
        assert np.linalg.norm(matrix - z["U"] @ z["V"].T) <= 1e-12


# ------------------------------------------------------------- output and progress


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_progress_goes_to_stderr_and_stdout_is_pure_json(tmp_path, npy, capsys, mode):
    store = tmp_path / "b.zarr"
    status, out, err = run_cli(["ingest", npy, store, "--block", "7", *MODES[mode]], capsys)
    assert status == 0
    summary = json.loads(out)  # nothing but the summary on stdout
    assert summary["n_seen"] == 60 and summary["store"] == str(store)
    bar = "Completed" if mode == "tree" else "60/60"  # dask's bar for the tree, else tqdm's
    assert bar in err
    status, out, err = run_cli(["info", store, "--json"], capsys)
    assert status == 0 and err == ""
    info = json.loads(out)
    assert info["n_seen"] == 60 and info["rank"] == summary["rank"]


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_quiet_prints_nothing(tmp_path, npy, capsys, mode):
    status, out, err = run_cli(["ingest", npy, tmp_path / "b.zarr", "--block", "7", "--quiet",
                                *MODES[mode]], capsys)
    assert (status, out, err) == (0, "", "")


@pytest.mark.slow
def test_tree_progress_stays_off_stdout_in_a_real_process(tmp_path, npy):
    """dask's bar writes to the process's stdout; the command sends it to stderr."""
    store = tmp_path / "b.zarr"
    proc = subprocess.run(
        [sys.executable, "-m", "streamsvd", "ingest", str(npy), str(store), "--block", "7",
         "--scheduler", "threads"],
        capture_output=True, text=True, env={"PYTHONPATH": str(WORKTREE), "PATH": ""},
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["n_seen"] == 60
    assert "100% Completed" in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "streamsvd", "info", str(store), "--json"],
                          capture_output=True, text=True,
                          env={"PYTHONPATH": str(WORKTREE), "PATH": ""}, check=False)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["n_seen"] == 60


def test_progress_postfix_shows_the_update_just_done(tmp_path, rng, capsys, monkeypatch):
    """Each redraw of the bar shows the rank after the columns it counts."""
    import tqdm

    class EveryUpdate(tqdm.tqdm):  # draw at every update, whatever the clock says
        def __init__(self, *args, **kwargs):
            kwargs.update(mininterval=0, miniters=1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(tqdm, "tqdm", EveryUpdate)
    src = tmp_path / "full.npy"
    np.save(src, rng.standard_normal((80, 42)))  # full rank: rank = columns absorbed
    status, out, err = run_cli(["ingest", src, tmp_path / "b.zarr", "--block", "7"], capsys)
    assert status == 0
    frames = re.findall(r"(\d+)/42 \[[^\]]*rank=(\d+)\]", err)
    counted = {int(cols) for cols, _ in frames}
    assert counted >= {7, 14, 21, 28, 35, 42}, err  # every update was drawn
    for cols, rank in frames:
        assert int(rank) == int(cols), (cols, rank)


# ---------------------------------------------------------------- errors, CLI words


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_one_resume_command_starts_and_restarts_in_every_mode(tmp_path, matrix, capsys, mode):
    """--resume on a missing STORE creates it: a restart script needs one command line."""
    src = tmp_path / "a.npy"
    store = tmp_path / "b.zarr"
    command = ["ingest", str(src), str(store), "--block", "10", "--rule", "jacobi",
               "--sweeps", "converge", "--resume", "--quiet", *MODES[mode]]
    np.save(src, matrix[:, :30])
    assert main(command) == 0  # the first run: STORE does not exist yet
    with open_readonly(store) as sc:
        assert sc.n_seen == 30 and sc.rule == "jacobi" and sc.sweeps is None
    np.save(src, matrix)  # the solver appended snapshots: the same SOURCE, continued
    assert main(command) == 0
    assert main(command) == 0  # nothing new: a no-op
    info = json.loads(run_cli(["info", store, "--json"], capsys)[1])
    assert info["n_seen"] == 60 and info["source"]["shape"] == [80, 60]
    assert info["source"]["resolved"] == str(src.resolve())
    s = np.linalg.svd(matrix, compute_uv=False)
    np.testing.assert_allclose(info["amplitudes_head"], s[:10], atol=100 * 80 * EPS * s[0])


def _as_an_interrupted_creation(store):
    """Leave of ``store`` what a creation killed before its pointer switch leaves.

    A store that has committed generations is never replaced, pointer or not
    (tests/slow/faults/test_store_faults.py): its generations above 0 go too.
    """
    (store / "current.json").unlink()
    for gen in (store / "generations").glob("g*"):
        if gen.name != "g00000000":
            shutil.rmtree(gen)
    (store / "generations" / "g00000000" / "committed.json").unlink(missing_ok=True)


def test_resume_replaces_the_leftovers_of_an_interrupted_creation(tmp_path, npy, capsys):
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(npy), str(store), "--quiet"]) == 0
    _as_an_interrupted_creation(store)
    assert main(["ingest", str(npy), str(store), "--resume", "--quiet"]) == 0
    with StreamCompressor.open(store, mode="r") as sc:
        assert sc.n_seen == 60
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    status, _, err = run_cli(["ingest", npy, foreign, "--resume", "--quiet"], capsys)
    assert_one_line_error(status, err)
    assert "holds other files" in err and (foreign / "notes.txt").exists()


def test_help_says_that_resume_creates_a_missing_store(capsys):
    status, out, _ = run_cli(["ingest", "--help"], capsys)
    text = " ".join(out.split())
    assert status == 0
    assert "create STORE when it does not exist yet" in text
    assert "STORE is continued from its recorded source offset if it exists and created " \
           "otherwise, so one command line starts an ingestion and restarts it" in text


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_resume_from_another_source_is_refused_naming_both(tmp_path, matrix, capsys, mode,
                                                           monkeypatch, caplog):
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(a, matrix[:, :30])
    np.save(b, matrix)
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(a), str(store), "--block", "10", "--quiet", *MODES[mode]]) == 0
    generation = ss_generation(store)
    status, _, err = run_cli(["ingest", b, store, "--resume", "--quiet", *MODES[mode]], capsys)
    assert_one_line_error(status, err)
    assert f"SOURCE {b.resolve()} (STORE has {a.resolve()}): STORE {store} was built from " \
           "another source. Pass the SOURCE (and --dataset) it was built from, or add " \
           "--source-changed-ok to continue it from this one." in err
    np.save(a, matrix[:, :20])  # fewer columns than recorded: another file at that path
    status, _, err = run_cli(["ingest", a, store, "--resume", "--quiet", *MODES[mode]], capsys)
    assert_one_line_error(status, err)
    assert "SOURCE of shape 80 x 20 (STORE has 80 x 30)" in err
    assert ss_generation(store) == generation  # refused: STORE unchanged
    # the same file by another relative path is the same source
    monkeypatch.chdir(tmp_path)
    np.save(a, matrix[:, :40])
    assert main(["ingest", "a.npy", "s.zarr", "--resume", "--block", "10", "--quiet",
                 *MODES[mode]]) == 0
    # the override: continued from b, which the store then records
    status, _, err = run_cli(["ingest", b, store, "--resume", "--source-changed-ok",
                              "--block", "10", "--quiet", *MODES[mode]], capsys)
    assert status == 0, err
    assert "continuing STORE" in caplog.text and f"-> {b.resolve()}" in caplog.text
    info = json.loads(run_cli(["info", store, "--json"], capsys)[1])
    assert info["n_seen"] == 60 and info["source"]["resolved"] == str(b.resolve())
    assert main(["ingest", str(b), str(store), "--resume", "--quiet", *MODES[mode]]) == 0


def test_resume_with_another_dataset_is_refused(tmp_path, matrix, capsys):
    src = tmp_path / "a.h5"
    with h5py.File(src, "w") as f:
        f["u"], f["v"] = matrix[:, :30], matrix
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(src), str(store), "--dataset", "/u", "--quiet"]) == 0
    status, _, err = run_cli(["ingest", src, store, "--dataset", "v", "--resume", "--quiet"],
                             capsys)
    assert_one_line_error(status, err)
    assert "--dataset v (STORE has u)" in err and "SOURCE " + str(src) not in err
    assert main(["ingest", str(src), str(store), "--dataset", "u", "--resume", "--quiet"]) == 0


def ss_generation(store):
    from streamsvd.store import open_store

    with open_store(store, "r") as st:
        return st.generation


def _nan_first_block(tmp_path, matrix):
    bad = matrix.copy()
    bad[3, 2] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    return ["ingest", tmp_path / "nan.npy"]


def _unreadable_first_block(tmp_path, matrix):
    src = tmp_path / "a.h5"
    with h5py.File(src, "w") as f:  # a dataset compressed by a filter, then damaged
        f.create_dataset("u", data=matrix, chunks=(80, 60), compression="gzip")
        offset = f["u"].id.get_chunk_info(0).byte_offset
    with open(src, "r+b") as fh:
        fh.seek(offset + 10)
        fh.write(b"\xff" * 64)
    return ["ingest", src]


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
@pytest.mark.parametrize("cause", ["nan", "unreadable", "weights", "commit", "interrupt"])
def test_a_failed_start_leaves_no_store(tmp_path, matrix, capsys, mode, cause, monkeypatch):
    """A command that fails before its first commit of snapshots removes the STORE it made,
    with --resume too; one that existed before is never removed."""
    np.save(tmp_path / "a.npy", matrix)
    argv = ["ingest", tmp_path / "a.npy"]
    if cause == "nan":
        argv = _nan_first_block(tmp_path, matrix)
    elif cause == "unreadable":
        argv = _unreadable_first_block(tmp_path, matrix)
    elif cause == "weights":  # a bad --inner, refused after SOURCE was opened
        np.save(tmp_path / "w.npy", -np.ones(80))
        argv += ["--inner", tmp_path / "w.npy"]
    elif cause == "commit":  # the first commit fails (a full disk)
        def full(*args, **kwargs):
            raise OSError("No space left on device")

        monkeypatch.setattr("streamsvd.store.BasisStore.commit", full)
    else:  # Ctrl-C during the first update
        def interrupt(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr("streamsvd.stream.updates.plan_absorb", interrupt)
    for resume in ([], ["--resume"]):
        store = tmp_path / "s.zarr"
        status, _, err = run_cli([*argv, store, "--block", "7", "--quiet", *resume,
                                  *MODES[mode]], capsys)
        if cause == "interrupt":
            assert status == 130, err
            assert err.strip().endswith(f"nothing was committed to STORE {store}; start again "
                                        f"with: streamsvd {' '.join(map(str, argv))} {store} "
                                        f"--block 7 --quiet {' '.join(MODES[mode])}"
                                        .strip() + " --resume"), err
        else:
            assert_one_line_error(status, err)
        assert not store.exists(), (resume, err)
    if cause in ("interrupt", "commit"):
        return
    # a store that existed before the command is kept, even when it holds no snapshot
    store = tmp_path / "kept.zarr"
    if mode == "tall":
        from streamsvd.parallel.cluster import TallCompressor

        TallCompressor(80, store=store).close()
    else:
        StreamCompressor(80, store=store).close()
    status, _, err = run_cli([*argv, store, "--resume", "--quiet", *MODES[mode]], capsys)
    assert status == 2 and store.exists(), err


def test_a_failure_after_a_commit_keeps_the_store(tmp_path, matrix, capsys):
    bad = matrix.copy()
    bad[10, 50] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    store = tmp_path / "s.zarr"
    status, _, err = run_cli(["ingest", tmp_path / "bad.npy", store, "--block", "7",
                              "--quiet"], capsys)
    assert status == 2
    with StreamCompressor.open(store, mode="r") as sc:
        assert sc.source_offset == 49


@pytest.mark.parametrize("mode", ["memory", "tree", "tall"])
def test_non_finite_entry_is_reported_in_source_coordinates(tmp_path, matrix, capsys, mode):
    bad = matrix.copy()
    bad[10, 50] = np.nan  # in the block of columns 49:56, at (10, 1) inside it
    src = tmp_path / "bad.npy"
    np.save(src, bad)
    status, _, err = run_cli(["ingest", src, tmp_path / "b.zarr", "--block", "7", "--quiet",
                              *MODES[mode]], capsys)
    assert_one_line_error(status, err)
    assert "holds nan at column 50, row 10 (counted from 0" in err
    assert "(10, 1)" not in err and "index" not in err


def test_user_mistakes_print_one_line_in_cli_words(tmp_path, matrix, capsys):
    t = tmp_path
    np.save(t / "a.npy", matrix)
    np.save(t / "small.npy", matrix[:50])
    np.save(t / "complex.npy", matrix + 1j * matrix)
    (t / "x.mtx").write_text("%%MatrixMarket matrix coordinate real general\n")
    (t / "afile").write_text("hi")
    (t / "plain").mkdir()
    with h5py.File(t / "two.h5", "w") as f:
        f["a"], f["b"] = matrix, matrix
    assert main(["ingest", str(t / "a.npy"), str(t / "mem.zarr"), "--quiet"]) == 0
    assert main(["ingest", str(t / "a.npy"), str(t / "tall.zarr"), "--tall", "--quiet"]) == 0
    incomplete = t / "incomplete.zarr"
    assert main(["ingest", str(t / "a.npy"), str(incomplete), "--quiet"]) == 0
    _as_an_interrupted_creation(incomplete)
    capsys.readouterr()
    cases = [
        (["info", t / "missing.zarr"], r"STORE must be an existing basis store; .* Create it "
                                       r"with `streamsvd ingest SOURCE STORE`\."),
        (["plot", t / "plain", t / "p.png"], r"STORE must be a basis store .* Pass a directory "
                                             r"written by `streamsvd ingest`\."),
        (["info", t / "afile"], r"STORE .*afile is a file"),
        (["info", incomplete], r"Delete it and run `streamsvd ingest` again\."),
        (["export", t / "mem.zarr", t / "x.txt"], r"OUT must end with .npz, .h5 or .hdf5"),
        (["ingest", t / "missing.npy", t / "s.zarr"], r"SOURCE .*missing.npy does not exist"),
        (["ingest", t / "x.mtx", t / "s.zarr"], r"SOURCE .*x.mtx has an unknown extension "
                                                r"'.mtx'.*Convert the data to one of these"),
        (["ingest", t / "two.h5", t / "s.zarr"], r"--dataset must be given .* Pass --dataset "
                                                 r"with one of them\."),
        (["ingest", t / "a.npy", t / "s.zarr", "--dataset", "u"], r"got --dataset 'u' .* Drop "
                                                                   r"--dataset\."),
        (["ingest", t / "complex.npy", t / "s.zarr"], r"SOURCE must be real"),
        (["ingest", t / "a.npy", t / "s.zarr", "--source-changed-ok"],
         r"--source-changed-ok applies to --resume only"),
        (["ingest", t / "a.npy", t / "s.zarr", "--inner", t / "x.mtx"],
         r"--inner file .*x.mtx cannot be read as a .mtx file"),
        (["ingest", t / "a.npy", t / "s.zarr", "--inner", t / "afile"],
         r"--inner must be a .npy \(weights or a dense matrix\), .npz \(scipy.sparse.save_npz\) "
         r"or .mtx \(Matrix Market\) file; got 'afile'"),
        (["ingest", t / "a.npy", t / "tall.zarr", "--resume"],
         r"was written with --tall; resume it with --tall\."),
        (["ingest", t / "a.npy", t / "mem.zarr", "--resume", "--tall"],
         r"was written without --tall .*; resume it without --tall\."),
        (["ingest", t / "small.npy", t / "mem.zarr", "--resume"],
         r"SOURCE has snapshots of size 50; STORE .* holds a basis of size 80"),
        (["ingest", t / "small.npy", t / "tall.zarr", "--resume", "--tall"],
         r"SOURCE has snapshots of size 50; STORE .* holds a basis of size 80"),
        (["ingest", t / "a.npy", t / "mem.zarr", "--resume", "--eps", "1", "--rule", "jacobi"],
         r"--eps 1.0 \(STORE has 0.0\), --rule jacobi \(STORE has paper\): --resume continues "
         r"STORE with the options it was created with"),
        (["ingest", t / "a.npy", t / "tall.zarr", "--resume", "--tall", "--sweeps", "converge"],
         r"--sweeps converge \(STORE has 1\)"),
        (["ingest", t / "a.npy", t / "mem.zarr", "--resume", "--scheduler", "threads",
          "--rtol", "0.1"], r"--rtol 0.1 \(STORE has none\): --resume continues STORE"),
        (["ingest", t / "a.npy", t / "mem.zarr", "--resume", "--commit-every", "3"],
         r"--commit-every 3 \(STORE has auto\)"),
        (["ingest", t / "a.npy", t / "tall.zarr", "--resume", "--tall", "--chunk-rows", "7",
          "--max-rank", "3"],
         r"--max-rank 3 \(STORE has none\), --chunk-rows 7 \(STORE has 16384\): --resume "),
        (["ingest", t / "a.npy", t / "s.zarr", "--block", "0"],
         r"argument --block: must be a positive integer; got '0'"),
        (["ingest", t / "a.npy", t / "s.zarr", "--eps", "nan"],
         r"argument --eps: must be a finite number >= 0"),
        (["ingest", t / "a.npy", t / "s.zarr", "--eps", "1", "--rtol", "1"],
         r"argument --rtol: not allowed with argument --eps"),
        (["ingest", t / "a.npy", t / "s.zarr", "--rule", "fast"], r"argument --rule: invalid "
                                                                   r"choice: 'fast'"),
        (["ingest", t / "a.npy", t / "s.zarr", "--scheduler", ""], r"argument --scheduler"),
        (["ingest"], r"the following arguments are required: SOURCE, STORE"),
        (["frobnicate"], r"invalid choice: 'frobnicate'"),
    ]
    for argv, match in cases:
        status, _, err = run_cli(argv, capsys)
        assert_one_line_error(status, err)
        assert re.search(match, err), (argv, err)
    assert not (t / "s.zarr").exists()  # a refused command leaves nothing behind


def test_a_locked_store_is_reported_without_python_advice(tmp_path, npy, capsys):
    store = tmp_path / "b.zarr"
    assert main(["ingest", str(npy), str(store), "--quiet"]) == 0
    with StreamCompressor.open(store):  # another writer holds the lock
        status, _, err = run_cli(["ingest", npy, store, "--resume", "--quiet"], capsys)
        assert_one_line_error(status, err)
        assert "is locked by another writer" in err
        assert "Wait for that writer (another `streamsvd ingest`) to finish" in err
        status, out, err = run_cli(["info", store, "--json"], capsys)  # readers are let in
        assert status == 0 and json.loads(out)["n_seen"] == 60


def test_advice_the_command_line_does_not_know_is_dropped_not_shown():
    """A library message with Python advice that no rewrite knows keeps only its facts."""
    text = in_cli_words(
        "`path` /x/b.zarr holds a store of kind 'other'.\nOpen it with `other.open(path)`. "
        "Or pass resume=True and `block` 5."
    )
    assert text == "STORE /x/b.zarr holds a store of kind 'other'."


@pytest.mark.parametrize(
    "extra,match",
    [(["--leaf-columns", "10"], r"--leaf-columns applies to the tree mode only .*add "
                                r"--scheduler"),
     (["--tall", "--leaf-columns", "10"], r"--leaf-columns applies to the tree mode only .*drop "
                                          r"it with --tall"),
     (["--chunk-rows", "16"], r"--chunk-rows applies to the tall mode only; add --tall"),
     (["--scheduler", "threads", "--chunk-rows", "16"], r"--chunk-rows applies to the tall mode"),
     (["--workers", "2"], r"--workers .* applies to --scheduler local only; got it without "
                          r"--scheduler"),
     (["--tall", "--workers", "2"], r"--workers .* got it without --scheduler"),
     (["--scheduler", "threads", "--workers", "2"], r"--workers .* got it with --scheduler "
                                                    r"threads"),
     (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], r"--workers .* got it with "
                                                              r"--scheduler tcp://127.0.0.1:1"),
     (["--scheduler", "threads", "--commit-every", "2"], r"--commit-every does not apply to the "
                                                         r"tree mode")],
)
def test_options_of_another_mode_are_refused(tmp_path, npy, capsys, extra, match):
    store = tmp_path / "b.zarr"
    status, _, err = run_cli(["ingest", npy, store, *extra], capsys)
    assert_one_line_error(status, err)
    assert re.search(match, err), err
    assert not store.exists()


# ----------------------------------------------------------------------------- help


def _subparsers():
    import argparse

    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return parser, sub.choices


def test_help_gives_every_option_a_help_line_and_its_default(capsys):
    import argparse

    parser, commands = _subparsers()
    assert set(commands) == {"ingest", "info", "export", "plot", "check", "dmd"}
    for name, sub in [("streamsvd", parser), *commands.items()]:
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction | argparse._VersionAction
                          | argparse._SubParsersAction):
                continue
            assert action.help, (name, action.dest)
            if action.option_strings:
                assert "(default: " in action.help, (name, action.option_strings)
    for name in commands:
        status, out, _ = run_cli([name, "--help"], capsys)
        assert status == 0 and out.startswith(f"usage: streamsvd {name}")
    status, out, _ = run_cli(["ingest", "--help"], capsys)
    text = " ".join(out.split())
    assert "--block B snapshots (columns) absorbed per update (default: 100)" in text
    assert "'paper' turns by tan(theta)" in text and "'jacobi' by the angle" in text
    assert "(default: paper)" in text and "'converge' to sweep until no pair rotates" in text


def test_ingest_defaults_are_none_so_given_options_can_be_told_apart():
    _, commands = _subparsers()
    args = commands["ingest"].parse_args(["a.npy", "b.zarr"])
    for name in ("block", "eps", "rtol", "max_rank", "rule", "sweeps", "commit_every",
                 "scheduler", "workers", "leaf_columns", "chunk_rows", "dataset", "inner",
                 "dynamics"):
        assert getattr(args, name) is None, name


def _fresh_python(code):
    """Run ``code`` in a new interpreter that sees only this checkout."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={"PYTHONPATH": str(WORKTREE), "PATH": ""}, check=False)


def test_the_command_line_module_imports_no_numerical_library():
    code = (
        "import json, sys, streamsvd.cli\n"
        "heavy = ('numpy', 'numba', 'dask', 'distributed', 'zarr', 'scipy', 'h5py',"
        " 'matplotlib', 'tqdm')\n"
        "print(json.dumps(sorted(m for m in heavy if m in sys.modules)))\n"
    )
    proc = _fresh_python(code)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout) == []


def test_lazy_exports_resolve_to_the_same_objects():
    """In a fresh process: the public names load on first use, ``compress`` stays a function."""
    code = (
        "import sys, streamsvd as ss\n"
        "assert 'numpy' not in sys.modules\n"
        "import streamsvd.stream\n"  # imports the submodule streamsvd.linalg.compress on the way
        "assert ss.StreamCompressor is streamsvd.stream.StreamCompressor\n"
        "assert ss.compress is sys.modules['streamsvd.linalg.compress'].compress\n"
        "assert set(ss.__all__) <= set(dir(ss))\n"
        "assert all(getattr(ss, name) is not None for name in ss.__all__)\n"
        "from streamsvd import *\n"
        "assert callable(compress) and Expansion is ss.Expansion\n"
        "try:\n"
        "    ss.nope\n"
        "except AttributeError as exc:\n"
        "    assert \"has no attribute 'nope'\" in str(exc)\n"
        "else:\n"
        "    raise AssertionError('ss.nope resolved')\n"
        "print('ok')\n"
    )
    proc = _fresh_python(code)
    assert proc.returncode == 0 and proc.stdout == "ok\n", proc.stderr


# ------------------------------------------------------------ info, export, plot


def test_info_export(tmp_path, matrix, capsys):
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


def test_store_of_the_heat_example_is_read_without_its_mass_matrix(tmp_path, capsys):
    """examples/heat_pod.py writes a store in the mass-matrix inner product: info, export
    and plot read it without being given the matrix."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("heat_pod", WORKTREE / "examples" / "heat_pod.py")
    heat = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(heat)
    assert heat.main(["--n", "60", "--steps", "100", "--block", "25", "--out", str(tmp_path)]) == 0
    store = tmp_path / "pod.zarr"
    capsys.readouterr()
    status, out, err = run_cli(["info", store, "--json"], capsys)
    assert status == 0, err
    info = json.loads(out)
    assert info["inner"].startswith("MatrixInner(n=60, sparse") and info["n_seen"] == 100
    assert info["orthogonality"] <= 50 * 60 * EPS
    assert run_cli(["plot", store, tmp_path / "p.png"], capsys)[0] == 0
    assert run_cli(["export", store, tmp_path / "u.npz"], capsys)[0] == 0
    M = heat.fe_matrices(60)[0]
    with np.load(tmp_path / "u.npz") as z:
        U = z["U"]
    gram = U.T @ (M @ U)
    assert np.linalg.norm(gram - np.eye(U.shape[1]), 2) <= 50 * 60 * EPS


def _inner_file(tmp_path, kind, n, rng):
    """An inner product on R^n and a file holding it, in each format --inner reads."""
    import scipy.io
    import scipy.sparse as sp

    w = rng.uniform(0.5, 2.0, n)
    M = sp.diags_array([w[:-1] / 8, w, w[:-1] / 8], offsets=[-1, 0, 1]).tocsr()
    path = tmp_path / {"weights": "w.npy", "dense": "m.npy", "sparse": "m.npz",
                       "mtx": "m.mtx"}[kind]
    if kind == "weights":
        np.save(path, w)
        return path, np.diag(w)
    if kind == "dense":
        np.save(path, M.toarray())
    elif kind == "sparse":
        sp.save_npz(path, M)
    else:
        scipy.io.mmwrite(path, M)
    return path, M.toarray()


@pytest.mark.parametrize("kind", ["weights", "dense", "sparse", "mtx"])
def test_inner_file_for_ingest_kept_by_the_store(tmp_path, matrix, capsys, kind, rng):
    path, M = _inner_file(tmp_path, kind, 80, rng)
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "s.zarr"
    assert main(["ingest", str(src), str(store), "--inner", str(path), "--block", "10",
                 "--quiet"]) == 0
    np.save(src, matrix)
    assert main(["ingest", str(src), str(store), "--resume", "--block", "10", "--quiet"]) == 0
    with StreamCompressor.open(store, mode="r") as sc:  # the store's own inner product
        U, bound, n_seen = sc.expansion.U, sc.error_bound, sc.n_seen
        V = sc.expansion.V
    assert n_seen == 60
    assert np.linalg.norm(U.T @ M @ U - np.eye(U.shape[1]), 2) <= 50 * 80 * EPS
    L = np.linalg.cholesky(M)
    assert np.linalg.norm(L.T @ (matrix - U @ V.T)) <= bound * (1 + 1e-9) + 1e-12
    # given again, it is checked against the store; another one is refused
    assert run_cli(["info", store, "--inner", path], capsys)[0] == 0
    np.save(tmp_path / "other.npy", np.ones(80))
    for argv in (["info", store], ["ingest", src, store, "--resume", "--quiet"]):
        status, _, err = run_cli([*argv, "--inner", tmp_path / "other.npy"], capsys)
        assert_one_line_error(status, err)
        assert "--inner must be the inner product the store" in err


def test_dask_modes_keep_the_inner_product_and_tall_refuses_a_matrix(tmp_path, matrix,
                                                                     capsys, rng):
    w_path, _ = _inner_file(tmp_path, "weights", 80, rng)
    m_path, M = _inner_file(tmp_path, "sparse", 80, rng)
    src = tmp_path / "a.npy"
    np.save(src, matrix)
    store = tmp_path / "t.zarr"
    status, _, err = run_cli(["ingest", src, store, "--tall", "--inner", m_path, "--quiet"],
                             capsys)
    assert_one_line_error(status, err)
    assert "Drop --tall, or lump the mass matrix into weights." in err
    assert not store.exists()
    assert main(["ingest", str(src), str(store), "--tall", "--inner", str(w_path), "--quiet"]) == 0
    status, out, _ = run_cli(["info", store, "--json"], capsys)
    assert status == 0 and json.loads(out)["inner"].startswith("DiagonalInner(n=80")
    tree = tmp_path / "tree.zarr"
    assert main(["ingest", str(src), str(tree), "--scheduler", "threads", "--inner",
                 str(m_path), "--quiet"]) == 0
    assert run_cli(["export", tree, tmp_path / "u.npz"], capsys)[0] == 0
    with np.load(tmp_path / "u.npz") as z:
        U = z["U"]
    assert np.linalg.norm(U.T @ M @ U - np.eye(U.shape[1]), 2) <= 50 * 80 * EPS


def test_store_that_does_not_keep_its_inner_product_needs_inner(tmp_path, matrix, capsys,
                                                                rng, monkeypatch):
    """A store written before stores kept the inner product opens with --inner, and keeps
    it from the next commit on."""
    path, _ = _inner_file(tmp_path, "weights", 80, rng)
    src = tmp_path / "a.npy"
    np.save(src, matrix[:, :30])
    store = tmp_path / "old.zarr"
    with monkeypatch.context() as m:  # as an earlier version wrote it: no inner data
        m.setattr("streamsvd.stream.lifecycle.inner_arrays", lambda inner: None)
        assert main(["ingest", str(src), str(store), "--inner", str(path), "--quiet"]) == 0
    status, _, err = run_cli(["info", store], capsys)
    assert_one_line_error(status, err)
    assert f"--inner must be given: the store {store} was written with an inner product" in err
    assert "Pass the same matrix or weights." in err
    assert run_cli(["info", store, "--inner", path], capsys)[0] == 0
    np.save(src, matrix)
    assert main(["ingest", str(src), str(store), "--resume", "--inner", str(path),
                 "--quiet"]) == 0
    status, out, _ = run_cli(["info", store, "--json"], capsys)
    assert status == 0 and json.loads(out)["n_seen"] == 60


def test_plot_of_a_tree_store_draws_every_panel(tmp_path, npy, capsys):
    """A tree store without final sweeps has one update: its point is drawn, ticks are
    integers, titles say what."""
    import matplotlib.image

    store = tmp_path / "tree.zarr"
    assert main(["ingest", str(npy), str(store), "--scheduler", "threads", "--quiet",
                 "--final-sweeps", "none"]) == 0
    png = tmp_path / "p.png"
    status, out, _ = run_cli(["plot", store, png], capsys)
    assert status == 0 and out == f"wrote {png}\n"
    image = matplotlib.image.imread(png)
    assert image.shape[:2] == (528, 1680)  # 14 x 4.4 inches at 120 dpi
    ink = (image[..., :3] < 0.9).any(axis=-1)
    assert 0.01 < ink.mean() < 0.5  # drawn on, not blank, not a black square

    with StreamCompressor.open(store, mode="r") as sc:
        fig = compressor_figure(sc, name="tree.zarr")
        rank, amps, orth = sc.rank, sc.amplitudes, sc.history[0].orthogonality
        now_orth = sc.orthogonality_error()
        relative = sc.error_in_measure  # no target: the relative measure
    assert fig._suptitle.get_text().startswith(f"tree.zarr: n = 80, rank {rank}, 60 snapshots")
    amp_ax, bound_ax, orth_ax = fig.axes
    assert amp_ax.get_xlabel() == "term i"
    assert amp_ax.get_ylabel() == "amplitude ||v_i|| (units of the data)"
    np.testing.assert_array_equal(amp_ax.lines[0].get_ydata(), amps)
    # the error bound against k: keeping every term gives the store's own bound, and the
    # bound of fewer terms is larger, on a log scale
    shown = bound_ax.lines[0].get_ydata()
    assert shown[-1] == pytest.approx(max(relative, 1e-300), rel=1e-12, abs=0)
    assert np.all(np.diff(shown) <= 0) and bound_ax.get_yscale() == "log"
    assert bound_ax.get_xlabel() == "terms kept k"
    assert "||A - U_k V_k^T||_F / ||A||_F" in bound_ax.get_ylabel()
    assert orth_ax.get_xlabel() == "update" and "||U^T M U - I||_2" in orth_ax.get_ylabel()
    (line,) = [ln for ln in orth_ax.lines if ln.get_label() == "recorded after each update"]
    assert line.get_marker() not in ("", "None", None)  # one point is visible as a marker
    np.testing.assert_array_equal(line.get_xdata(), [1])
    np.testing.assert_allclose(line.get_ydata(), [max(orth, 1e-18)])
    # beside the history, the orthogonality of U as the store gives it now
    (now,) = [ln for ln in orth_ax.lines if ln.get_label().startswith("U as read now")]
    np.testing.assert_allclose(now.get_ydata(), max(now_orth, 1e-18))
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    for ax in fig.axes:
        lo, hi = ax.get_xlim()
        ticks = [t for t in ax.get_xticks() if lo <= t <= hi]
        assert ticks and all(float(t).is_integer() for t in ticks), ticks
    # the point itself is painted: red pixels around its position in the rendered figure
    x, y = orth_ax.transData.transform((1, max(orth, 1e-18)))
    rgba = np.asarray(canvas.buffer_rgba())
    row = rgba.shape[0] - int(round(y))
    patch = rgba[row - 3:row + 4, int(round(x)) - 3:int(round(x)) + 4, :3].astype(int)
    assert ((patch[..., 0] > 200) & (patch[..., 1] < 80) & (patch[..., 2] < 80)).any()


@pytest.mark.parametrize("mode", ["memory", "tall"])
def test_ctrl_c_commits_every_update_absorbed(tmp_path, npy, capsys, monkeypatch, mode):
    """With the default --commit-every auto, Ctrl-C during an update commits the updates
    absorbed before it (whichever of them the schedule had committed), and --resume ends
    bit for bit where an uninterrupted run ends."""
    import streamsvd.stream.updates

    plan = streamsvd.stream.updates.plan_absorb
    calls = []

    def interrupted_at_the_fifth(*args, **kwargs):
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return plan(*args, **kwargs)

    argv = ["ingest", npy, tmp_path / "s.zarr", "--block", "7", "--max-rank", "4", "--quiet",
            *MODES[mode]]
    monkeypatch.setattr("streamsvd.stream.updates.plan_absorb", interrupted_at_the_fifth)
    status, _, err = run_cli(argv, capsys)
    assert status == 130, err
    assert "holds the snapshots up to column 28 of SOURCE (its last commit)" in err
    monkeypatch.setattr("streamsvd.stream.updates.plan_absorb", plan)
    assert main([str(a) for a in [*argv, "--resume"]]) == 0
    assert main([str(a) for a in [*argv[:2], tmp_path / "ref.zarr", *argv[3:]]]) == 0
    with open_readonly(tmp_path / "s.zarr") as a, open_readonly(tmp_path / "ref.zarr") as b:
        ea, eb = a.expansion, b.expansion
        assert np.array_equal(ea.U, eb.U) and np.array_equal(ea.V, eb.V)


def test_ctrl_c_inside_a_commit_prints_one_line_and_no_warning(tmp_path, npy, capsys,
                                                                 monkeypatch):
    """Ctrl-C can land in zarr's sync() between creating a commit's coroutine and running
    it; the coroutine is then released without its "never awaited" warning, so stderr
    holds the one line that says what the store holds."""
    import warnings

    import streamsvd.stream.updates

    plan = streamsvd.stream.updates.plan_absorb
    calls = []

    async def create_array():
        pass

    def interrupted_in_a_commit(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            _pending = create_array()  # created, never awaited: as in an interrupted sync()
            raise KeyboardInterrupt
        return plan(*args, **kwargs)

    monkeypatch.setattr("streamsvd.stream.updates.plan_absorb", interrupted_in_a_commit)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status, _, err = run_cli(["ingest", npy, tmp_path / "s.zarr", "--block", "7",
                                  "--max-rank", "4", "--quiet"], capsys)
    assert status == 130, err
    assert not [w for w in caught if "never awaited" in str(w.message)]
    assert len(err.strip().splitlines()) == 1 and "holds the snapshots" in err


def test_ctrl_c_reports_the_last_commit_and_how_to_resume(tmp_path, rng):
    """SIGINT during a long ingestion: exit 130, one line naming the last committed column
    and the command to resume; the store holds exactly that commit, readable."""
    import signal
    import time

    import streamsvd as ss

    A = rng.standard_normal((300, 20000))
    src = tmp_path / "a.npy"
    np.save(src, A)
    store = tmp_path / "s.zarr"
    # a process started with SIGINT ignored (a background job of a script, nohup) passes
    # that on and Python keeps it: the child gets the default disposition, as from a shell
    inherited = signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "streamsvd", "ingest", str(src), str(store), "--block",
             "1", "--max-rank", "5", "--commit-every", "1", "--quiet"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    finally:
        signal.signal(signal.SIGINT, inherited)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # wait for a few commits (not timing the process)
        try:
            with ss.open_store(store, "r") as st:
                if st.generation >= 3:
                    break
        except (ss.StoreError, OSError):
            pass
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:  # say where it was: faulthandler dumps on SIGABRT
        proc.send_signal(signal.SIGABRT)
        out, err = proc.communicate()
        pytest.fail(f"the interrupted ingest did not stop; its threads:\n{err[-8000:]}")
    assert proc.returncode == 130, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err
    with ss.StreamCompressor.open(store, mode="r") as sc:
        offset = sc.source_offset
        assert sc.n_seen == offset and 1 <= offset < 20000
    assert f"holds the snapshots up to column {offset} of SOURCE" in lines[0]
    assert lines[0].endswith("--resume") and str(store) in lines[0]
