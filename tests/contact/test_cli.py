"""The contact command's parser (contact.cli) and ``python -m contact``."""

import subprocess
import sys

import pytest

from contact.cli import main


def test_help_of_billet_names_its_options(capsys):
    with pytest.raises(SystemExit) as exited:
        main(["billet", "--help"])
    assert exited.value.code == 0
    out = capsys.readouterr().out
    assert "--out" in out and "--dt" in out


def test_python_m_contact_without_a_command_prints_its_usage():
    out = subprocess.run([sys.executable, "-m", "contact"], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2
    assert "usage: contact" in out.stderr and "billet" in out.stderr
