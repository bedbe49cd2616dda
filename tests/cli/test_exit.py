"""The executable's exit (:func:`streamsvd.cli.leave`): status, output and handlers kept."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=120)


def test_leave_runs_the_atexit_handlers_and_flushes_the_output(tmp_path: Path) -> None:
    marker = tmp_path / "handler"
    proc = _run(f"""
        import atexit, logging, sys
        from streamsvd.cli import leave
        atexit.register(lambda: open({str(marker)!r}, "w").write("ran"))
        logging.basicConfig(stream=sys.stderr, format="%(message)s")
        sys.stdout.write("summary without a newline")
        logging.getLogger("x").warning("logged")
        leave(3)
        """)
    assert proc.returncode == 3
    assert proc.stdout == "summary without a newline"
    assert proc.stderr.strip() == "logged"
    assert marker.read_text() == "ran"


def test_leave_waits_for_a_thread_still_running(tmp_path: Path) -> None:
    done = tmp_path / "thread"
    proc = _run(f"""
        import threading, time
        from streamsvd.cli import leave
        def work():
            time.sleep(0.5)
            open({str(done)!r}, "w").write("done")
        threading.Thread(target=work).start()
        leave(0)
        """)
    assert proc.returncode == 0, proc.stderr
    assert done.read_text() == "done"


def test_the_executable_reports_its_status_and_output(tmp_path: Path) -> None:
    missing = tmp_path / "missing.svd"
    bad = subprocess.run([sys.executable, "-m", "streamsvd", "info", str(missing)],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.startswith("streamsvd: error:")
    assert bad.stdout == ""
    ok = subprocess.run([sys.executable, "-m", "streamsvd", "--version"],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0
    assert ok.stdout.strip()
