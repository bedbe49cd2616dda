"""examples/moving_source.py runs on a small size and its numbers are checked."""

import importlib.util
import json
from pathlib import Path

import numpy as np

from tests._figures import assert_drawn

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"
EPS = np.finfo(float).eps


def test_moving_source(tmp_path):
    spec = importlib.util.spec_from_file_location("moving_source", EXAMPLES / "moving_source.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    argv = ["--n", "120", "--steps", "400", "--window", "60", "--block", "10", "--out",
            str(tmp_path)]
    assert mod.main(argv) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["n_seen"] == 60 and s["n_absorbed"] == 400
    # the windowed modes are the batch SVD's where a gap separates them
    assert s["gaps"] and s["max_angle"] <= 1e-8
    assert s["max_sv_rel_top5"] <= 1e-10
    assert s["max_orthogonality"] <= 50 * 120 * EPS
    assert_drawn(tmp_path / "moving_source.png")
