"""A local S3-compatible server (moto in server mode) for tests and benchmarks.

:func:`start` launches ``python -m moto.server`` on 127.0.0.1 at a free port, waits for
it to answer and returns it; nothing leaves the machine. :meth:`S3Server.environment` is
what the library and its subprocesses (the CLI, dask workers) need to reach it: the
usual ``AWS_*`` variables, with ``AWS_ENDPOINT_URL`` naming the local server. Needs the
test extra (``moto[server]``, ``s3fs``).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass

__all__ = ["S3Server", "start"]


@dataclass(frozen=True)
class S3Server:
    """A running moto server and how to reach it."""

    process: subprocess.Popen
    endpoint: str

    def environment(self) -> dict[str, str]:
        """``AWS_*`` variables that point boto/s3fs at this server."""
        return {
            "AWS_ACCESS_KEY_ID": "streamsvd-test",
            "AWS_SECRET_ACCESS_KEY": "streamsvd-test",
            "AWS_DEFAULT_REGION": "us-east-1",
            "AWS_ENDPOINT_URL": self.endpoint,
            "AWS_EC2_METADATA_DISABLED": "true",
        }

    def stop(self) -> None:
        """Terminate the server and wait for it."""
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start(timeout: float = 60.0) -> S3Server:
    """Start a moto server on a free local port.

    Parameters
    ----------
    timeout : float
        Seconds to wait for the server to answer.

    Returns
    -------
    S3Server
        The running server; call :meth:`S3Server.stop` when done.

    Raises
    ------
    RuntimeError
        The server exited or did not answer within ``timeout``.
    """
    port = _free_port()
    env = dict(os.environ, MOTO_ALLOW_NONEXISTENT_REGION="true")
    process = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
    )
    server = S3Server(process, f"http://127.0.0.1:{port}")
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(f"{server.endpoint}/moto-api/", timeout=2):
                return server
        except OSError:
            if process.poll() is not None or time.monotonic() > deadline:
                server.stop()
                raise RuntimeError(f"the moto server on port {port} did not start") from None
            time.sleep(0.1)
