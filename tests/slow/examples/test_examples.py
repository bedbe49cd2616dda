"""Every script in examples/ runs on a small size and its numbers are checked."""

import importlib.util
import json
from pathlib import Path

import numpy as np

from tests._figures import assert_drawn

ROOT = Path(__file__).resolve().parents[3]
EXAMPLES = ROOT / "examples"
EPS = np.finfo(float).eps


def _load(name, folder=EXAMPLES):
    spec = importlib.util.spec_from_file_location(name, folder / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_heat_pod(tmp_path, capsys):
    mod = _load("heat_pod")
    assert mod.main(["--n", "120", "--steps", "300", "--block", "25", "--out", str(tmp_path)]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    # the final sweeps keep the terms that carry the data, as the batch SVD counts them
    assert s["rank"] == s["reference_rank"] < s["streamed_rank"]
    assert s["M_orthogonality"] <= 50 * 120 * EPS
    assert s["error_M_norm"] <= s["error_bound"] * (1 + 1e-9) + 1e-12
    assert s["max_rel_singular_value_error"] <= 1e-6
    assert_drawn(tmp_path / "heat_pod.png")
    assert (tmp_path / "pod.zarr").is_dir()


def test_demo_main_job(tmp_path, capsys):
    main = _load("demo", ROOT / "scripts").main

    assert main(["--out", str(tmp_path), "--quiet"]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    # the final sweeps converged: no pair of the core is coupled beyond rounding
    assert s["final_max_cosine"] <= 50 * 480 * EPS
    assert s["final_max_rel_singular_value_error"] <= 50 * 480 * EPS
    assert s["orthogonality"] <= 50 * 480 * EPS
    assert_drawn(tmp_path / "spectrum.png")
