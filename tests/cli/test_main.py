"""``python -m streamsvd.cli`` runs the command line (streamsvd.cli.__main__)."""

import subprocess
import sys


def test_python_m_streamsvd_cli_prints_the_help():
    out = subprocess.run([sys.executable, "-m", "streamsvd.cli", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: streamsvd")
