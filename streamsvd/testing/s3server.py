"""A local S3-compatible server (moto in server mode) for tests and benchmarks.

:func:`start` launches ``python -m moto.server`` on 127.0.0.1 at a free port, waits for
it to answer and returns it; nothing leaves the machine. :meth:`S3Server.environment` is
what the library and its subprocesses (the CLI, dask workers) need to reach it: the
usual ``AWS_*`` variables, with ``AWS_ENDPOINT_URL`` naming the local server. Needs the
test extra (``moto[server]``, ``s3fs``).

:func:`start_faulty_proxy` puts an HTTP proxy in front of it that injects the transient
faults of a real object store: ``503 SlowDown`` without applying the request, and
``500 InternalError`` *after* applying it (the client cannot tell the write happened).
"""

from __future__ import annotations

import http.client
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

__all__ = ["FaultyProxy", "S3Server", "start", "start_faulty_proxy"]


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


_SLOW_DOWN = (b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>SlowDown</Code>'
              b"<Message>Please reduce your request rate.</Message></Error>")
_INTERNAL = (b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>InternalError</Code>'
             b"<Message>We encountered an internal error. Please try again.</Message>"
             b"</Error>")


@dataclass
class FaultyProxy:
    """A proxy to an :class:`S3Server` that fails some requests (see the module docstring).

    Every ``throttle_every``-th request is answered ``503 SlowDown`` unapplied; every
    ``fail_after_every``-th ``PUT`` is applied, then answered ``500 InternalError``.
    ``faults`` counts the injected faults by kind.
    """

    server: ThreadingHTTPServer
    endpoint: str
    faults: dict[str, int]

    def environment(self, base: S3Server) -> dict[str, str]:
        """``base``'s variables with ``AWS_ENDPOINT_URL`` naming this proxy."""
        return dict(base.environment(), AWS_ENDPOINT_URL=self.endpoint)

    def stop(self) -> None:
        """Stop serving."""
        self.server.shutdown()
        self.server.server_close()


def start_faulty_proxy(target: S3Server, *, throttle_every: int = 7,
                       fail_after_every: int = 5) -> FaultyProxy:
    """Start a :class:`FaultyProxy` to ``target`` on a free local port (a thread)."""
    host, port = target.endpoint.rsplit("//", 1)[1].split(":")
    counts = {"requests": 0, "puts": 0}
    faults = {"slow_down": 0, "internal_after_apply": 0}
    lock = threading.Lock()

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args: object) -> None:  # quiet
            pass

        def _answer(self, status: int, headers: list[tuple[str, str]], body: bytes) -> None:
            self.send_response(status)
            for name, value in headers:
                if name.lower() not in ("content-length", "transfer-encoding", "connection"):
                    self.send_header(name, value)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _forward(self) -> None:
            length = int(self.headers.get("Content-Length") or 0)
            body = self.rfile.read(length) if length else None
            with lock:
                counts["requests"] += 1
                throttle = counts["requests"] % throttle_every == 0
                counts["puts"] += self.command == "PUT"
                fail_after = self.command == "PUT" and counts["puts"] % fail_after_every == 0
                if throttle:
                    faults["slow_down"] += 1
                elif fail_after:
                    faults["internal_after_apply"] += 1
            if throttle:
                self._answer(503, [("Content-Type", "application/xml")], _SLOW_DOWN)
                return
            conn = http.client.HTTPConnection(host, int(port), timeout=60)
            try:
                headers = {k: v for k, v in self.headers.items() if k.lower() != "host"}
                headers["Host"] = f"{host}:{port}"
                conn.request(self.command, self.path, body=body, headers=headers)
                response = conn.getresponse()
                data = response.read()
            finally:
                conn.close()
            if fail_after and response.status < 300:
                self._answer(500, [("Content-Type", "application/xml")], _INTERNAL)
                return
            self._answer(response.status, response.getheaders(), data)

        do_GET = do_PUT = do_POST = do_DELETE = do_HEAD = _forward

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    endpoint = f"http://127.0.0.1:{server.server_address[1]}"
    return FaultyProxy(server, endpoint, faults)
