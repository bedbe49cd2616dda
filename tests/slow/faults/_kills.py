"""Kill a child process once a tree has committed a node (for the resume tests)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from streamsvd.store import POINTER_NAME


def kill_after_a_committed_node(args: list[str], checkpoints: Path, *, within: float = 120.0
                                ) -> None:
    """Run ``python -c *args`` and SIGKILL it once ``checkpoints`` holds a committed node.

    The child may also end first (a fast machine) or be killed at ``within`` seconds
    without any node: the resume tests hold for every instant of the kill, and assert
    nothing about how far the child got.
    """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", *args], env=env)
    deadline = time.monotonic() + within
    while proc.poll() is None and time.monotonic() < deadline:
        if checkpoints.is_dir() and any((p / POINTER_NAME).exists()
                                        for p in checkpoints.iterdir()):
            break
        time.sleep(0.05)
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
