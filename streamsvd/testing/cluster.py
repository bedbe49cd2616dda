"""A dask cluster whose workers share nothing with the client but the network.

:func:`start` launches ``dask scheduler`` and ``dask worker`` as separate processes, each
in its own temporary working directory (and its own ``TMPDIR``), with an environment of
its own: what a cluster of other machines looks like to a client. Where the system allows
unprivileged user and mount namespaces (``unshare -rm``, Linux), every worker also runs
with the directories named in ``hidden`` covered by an empty ``tmpfs``, so that it cannot
see the client's files even by their absolute paths. Credentials reach the workers through
``env`` (their own environment), never through the task graph.

Used by the slow tests and the cluster benchmark; nothing leaves the machine.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["IsolatedCluster", "can_hide", "start"]


def can_hide() -> bool:
    """Whether workers can run in a mount namespace of their own (``unshare -rm``)."""
    unshare = shutil.which("unshare")
    if unshare is None:
        return False
    probe = subprocess.run([unshare, "-rm", "true"], capture_output=True, check=False)
    return probe.returncode == 0


@dataclass(frozen=True)
class IsolatedCluster:
    """A running scheduler and its workers (see the module docstring)."""

    address: str
    """The scheduler's address (``tcp://127.0.0.1:port``)."""
    processes: tuple[subprocess.Popen, ...]
    """The scheduler first, then the workers."""
    root: Path
    """The directory holding every process's working directory and log."""
    hidden: tuple[str, ...] = field(default=())
    """The directories the workers cannot see (empty when namespaces are unavailable)."""

    def logs(self) -> str:
        """Return the processes' standard error, concatenated (for a failing test's report)."""
        parts = []
        for path in sorted(self.root.glob("*/stderr.log")):
            parts.append(f"--- {path.parent.name}\n{path.read_text(errors='replace')[-4000:]}")
        return "\n".join(parts)

    def stop(self) -> None:
        """Terminate the workers, then the scheduler, and remove their directories."""
        for proc in reversed(self.processes):
            if proc.poll() is None:
                proc.terminate()
        for proc in reversed(self.processes):
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        shutil.rmtree(self.root, ignore_errors=True)


def _spawn(name: str, argv: list[str], root: Path, env: Mapping[str, str],
           hidden: tuple[str, ...]) -> subprocess.Popen:
    home = root / name
    (home / "tmp").mkdir(parents=True)
    full_env = dict(env, TMPDIR=str(home / "tmp"), HOME=str(home), PYTHONUNBUFFERED="1")
    if hidden:  # cover the client's directories, then run the worker in its own directory
        mounts = " && ".join(f"mount -t tmpfs none {shlex.quote(h)}" for h in hidden)
        argv = ["unshare", "-rm", "sh", "-c",
                f"{mounts} && cd {shlex.quote(str(home))} && exec {shlex.join(argv)}"]
    with (home / "stderr.log").open("wb") as log:  # the child keeps its own descriptor
        return subprocess.Popen(argv, cwd=home, env=full_env, stdout=log, stderr=log)


def start(
    *,
    workers: int = 2,
    threads: int = 1,
    env: Mapping[str, str] | None = None,
    hidden: Iterable[str | os.PathLike[str]] = (),
    timeout: float = 90.0,
) -> IsolatedCluster:
    """Start a scheduler and ``workers`` worker processes on localhost.

    Parameters
    ----------
    workers : int
        Worker processes (``dask worker --nworkers 1``, each started on its own).
    threads : int
        Threads per worker.
    env : mapping, optional
        The whole environment of the processes (default: this process's, without the
        ``AWS_*`` variables: workers then have no credentials). ``PATH`` and
        ``PYTHONPATH`` are taken from this process when missing.
    hidden : iterable of paths
        Directories the workers must not see (covered by an empty tmpfs where
        :func:`can_hide`; ignored elsewhere, the separate working directories remain).
    timeout : float
        Seconds to wait for the scheduler and the workers.

    Returns
    -------
    IsolatedCluster
        Call :meth:`IsolatedCluster.stop` when done.

    Raises
    ------
    RuntimeError
        A process exited or the workers did not connect within ``timeout``.
    """
    base = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    environment = dict(base if env is None else env)
    for name in ("PATH", "PYTHONPATH"):
        if name in os.environ:
            environment.setdefault(name, os.environ[name])
    covered = tuple(os.fspath(Path(h).resolve()) for h in hidden) if can_hide() else ()
    root = Path(tempfile.mkdtemp(prefix="streamsvd-cluster-"))
    if any(root.is_relative_to(h) for h in covered):
        shutil.rmtree(root)
        raise RuntimeError(f"the cluster's directory {root} is under a hidden directory")
    dask = _dask_command()
    sched_file = root / "scheduler.json"
    procs = [_spawn("scheduler", [*dask, "scheduler", "--host",
                                  "127.0.0.1", "--port", "0", "--dashboard-address", ":0",
                                  "--scheduler-file", str(sched_file)],
                    root, environment, ())]
    cluster = IsolatedCluster("", tuple(procs), root, covered)
    try:
        deadline = time.monotonic() + timeout
        while not sched_file.exists():
            _check_alive(cluster, deadline)
            time.sleep(0.1)
        time.sleep(0.2)  # the file is written whole, but give the writer a moment
        import json

        address = json.loads(sched_file.read_text())["address"]
        for i in range(workers):
            procs.append(_spawn(
                f"worker-{i}",
                [*dask, "worker", address, "--nthreads",
                 str(threads), "--nworkers", "1", "--no-dashboard", "--memory-limit", "0",
                 "--name", f"worker-{i}", "--local-directory", "."],
                root, environment, covered,
            ))
        cluster = IsolatedCluster(address, tuple(procs), root, covered)
        from distributed import Client

        with Client(address, timeout=f"{timeout}s") as client:
            while len(client.scheduler_info()["workers"]) < workers:
                _check_alive(cluster, deadline)
                time.sleep(0.2)
    except BaseException:
        cluster.stop()
        raise
    return cluster


def _dask_command() -> list[str]:
    """``dask`` of this interpreter's environment (the ``dask scheduler``/``worker`` CLI)."""
    exe = Path(sys.executable).parent / "dask"
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-m", "dask"]


def _check_alive(cluster: IsolatedCluster, deadline: float) -> None:
    if any(p.poll() is not None for p in cluster.processes) or time.monotonic() > deadline:
        logs = cluster.logs()
        raise RuntimeError(f"the isolated dask cluster did not start:\n{logs}")
