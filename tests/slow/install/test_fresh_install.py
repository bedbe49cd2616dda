"""The library and the main job work without the test extras (hypothesis, pytest, sklearn)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

# A meta-path finder that refuses the test extras, as on a machine where only the
# project's own dependencies are installed.
BLOCK = """
import importlib.abc, sys
class _Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split('.')[0] in {'hypothesis', 'pytest', 'sklearn', '_pytest'}:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None
sys.meta_path.insert(0, _Refuse())
"""


def _run(code, *args):
    return subprocess.run(
        [sys.executable, "-c", BLOCK + code, *args], capture_output=True, text=True,
        cwd=ROOT, timeout=600,
    )


def test_library_imports_without_test_extras():
    out = _run(
        "import streamsvd, streamsvd.testing, streamsvd.parallel, streamsvd.cli, contact\n"
        "from streamsvd.testing import assert_svd_contract, hard_matrices, with_spectrum\n"
        "import numpy as np\n"
        "A = with_spectrum(np.logspace(0, -3, 5), 20, 10, np.random.default_rng(0))\n"
        "from streamsvd.sklearn.estimator import StreamingSVD\n"
        "print(type(StreamingSVD()).__name__)\n"
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "StreamingSVD"
    refused = _run("import streamsvd.testing as t; t.low_rank_matrices")
    assert refused.returncode != 0 and "hypothesis" in refused.stderr


def test_main_job_runs_without_test_extras(tmp_path):
    out = _run(
        "import runpy, sys; sys.argv = ['demo'] + sys.argv[1:]; "
        "runpy.run_path('scripts/demo.py', run_name='__main__')",
        "--out", str(tmp_path), "--quiet",
    )
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "summary.json").is_file() and (tmp_path / "basis.zarr").is_dir()
