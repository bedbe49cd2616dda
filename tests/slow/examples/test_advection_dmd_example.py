"""examples/advection_dmd.py runs on a small grid and its numbers are checked."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from tests._figures import assert_drawn

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def _example():
    spec = importlib.util.spec_from_file_location("advection_dmd", EXAMPLES / "advection_dmd.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_propagator_eigenvalues_are_scipys():
    mod = _example()
    N, dt = 12, 0.01
    L = mod.operator(N).toarray()
    eye = np.eye(N * N)
    P = np.linalg.solve(eye - dt / 2 * L, eye + dt / 2 * L)
    dense = scipy.linalg.eigvals(P)
    ours = mod.propagator_eigenvalues(N, dt)
    assert np.max([np.min(np.abs(ours - z)) for z in dense]) < 1e-12
    assert np.max([np.min(np.abs(dense - z)) for z in ours]) < 1e-12
    assert sp.issparse(mod.operator(N))


def test_advection_dmd(tmp_path, capsys):
    mod = _example()
    assert mod.main(["--n-grid", "24", "--steps", "160", "--block", "16", "--horizon", "40",
                     "--out", str(tmp_path)]) == 0
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["violations"] == 0  # every eigenvalue within its eta of the propagator's
    assert s["pinned"] == 9  # the 9 Fourier modes of the initial field
    assert s["max_error_of_pinned"] <= 1e-9 and s["max_eta_of_pinned"] <= 1e-6
    assert s["max_forecast_rel_error"] <= 1e-7
    assert_drawn(tmp_path / "advection_dmd.png")
