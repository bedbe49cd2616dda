"""Helpers shared by the benchmark scripts: paths, JSON output, timing, plotting setup.

The scripts in ``bench/`` import this module by name; running ``python bench/NAME.py``
puts ``bench/`` first on ``sys.path`` (``python -m bench NAME`` puts it there too).
Every study writes its results with :class:`Run`, in the envelope that ``_suite``
describes and reads.
"""

from __future__ import annotations

import contextlib
import datetime
import importlib.metadata
import json
import logging
import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _suite import FORMAT

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO_ROOT / "bench" / "results"
DEFAULT_RBS480A = REPO_ROOT.parent / "shared" / "data" / "rbs480a.mtx"
RBS480A_SOURCE = (
    "The Matrix Market publishes RBS480A in its Harwell-Boeing collection "
    "(https://math.nist.gov/MatrixMarket/, search for 'rbs480a'; also at "
    "https://sparse.tamu.edu/HB/rbs480a): download rbs480a.mtx.gz, gunzip it and pass "
    "its path with --data."
)


def pyplot() -> Any:
    """Return ``matplotlib.pyplot`` with the non-interactive Agg backend selected."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def out_dir(path: str | os.PathLike[str] | None) -> Path:
    """Return the output directory (``bench/results`` by default), created if needed."""
    p = Path(path) if path is not None else DEFAULT_OUT
    p.mkdir(parents=True, exist_ok=True)
    return p


def _to_json(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _to_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _to_json(obj.tolist())
    if isinstance(obj, np.integer | np.bool_):
        return obj.item()
    if isinstance(obj, float | np.floating):
        x = float(obj)
        return x if math.isfinite(x) else None
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    return str(obj)


def write_json(path: Path, data: Any) -> Path:
    """Write ``data`` as indented JSON (numpy values converted, non-finite floats as null)."""
    path.write_text(json.dumps(_to_json(data), indent=1) + "\n")
    return path


def load_average() -> list[float] | None:
    """The 1, 5 and 15 minute load averages of the machine (None where unknown)."""
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def host_info() -> dict[str, Any]:
    """The machine: platform, cores, CPU model and the BLAS the timings were taken with."""
    info: dict[str, Any] = {
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "blas_env": {k: v for k, v in os.environ.items() if "BLAS" in k or "OMP" in k},
    }
    try:
        from threadpoolctl import threadpool_info

        info["blas"] = [
            {k: d.get(k) for k in ("internal_api", "version", "architecture", "num_threads")}
            for d in threadpool_info()
            if d.get("user_api") == "blas"
        ]
    except ImportError:
        info["blas"] = None
    try:
        with open("/proc/cpuinfo") as f:
            names = [ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")]
        info["cpu_model"] = names[0] if names else None
    except OSError:
        info["cpu_model"] = None
    return info


def machine_info() -> dict[str, Any]:
    """Describe the machine, its load and the BLAS the timings were taken with."""
    import scipy

    return {"python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "load_average": load_average(), **host_info()}


VERSIONED = ("streamsvd", "numpy", "scipy", "zarr", "numcodecs", "dask", "distributed",
             "numba", "matplotlib", "threadpoolctl", "scikit-learn", "pymor", "s3fs")


def versions() -> dict[str, str]:
    """Python's version and those of the installed packages of :data:`VERSIONED`."""
    found = {"python": platform.python_version()}
    for name in VERSIONED:
        try:
            found[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
    return found


def git_commit() -> dict[str, Any] | None:
    """The checkout's commit and whether tracked files differ from it (None without git)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(REPO_ROOT), *args], capture_output=True,
                              text=True, check=True, timeout=30).stdout.strip()

    try:
        return {"commit": git("rev-parse", "HEAD"),
                "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}
    except (OSError, subprocess.SubprocessError):
        return None


class Run:
    """One run of a study, which writes its results in the suite's common envelope.

    Made at the start of the study's ``main(argv)``, it notes the study's name, ``argv``
    (``sys.argv[1:]`` when None), the date and the load average; :meth:`write` puts the
    study's own payload under ``results`` beside them, the machine (with the load average
    before and after), the versions of the libraries and the git commit.
    """

    def __init__(self, study: str, argv: Sequence[str] | None = None) -> None:
        self.study = study
        self.argv = [str(a) for a in (sys.argv[1:] if argv is None else argv)]
        self.date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        self.load_before = load_average()
        self._start = time.perf_counter()

    def envelope(self, results: Any) -> dict[str, Any]:
        """The envelope of ``results``, as of now."""
        return {
            "format": FORMAT, "study": self.study, "argv": self.argv, "date": self.date,
            "seconds": time.perf_counter() - self._start,
            "machine": {**host_info(), "load_before": self.load_before,
                        "load_after": load_average()},
            "versions": versions(), "git": git_commit(), "results": results,
        }

    def write(self, path: Path, results: Any) -> Path:
        """Write ``results`` in the envelope to ``path`` (see :func:`write_json`)."""
        return write_json(path, self.envelope(results))


@dataclass(frozen=True)
class Timing:
    """Wall-clock and process CPU times of repeated calls (seconds)."""

    wall: list[float]
    cpu: list[float]

    @property
    def best(self) -> float:
        """Smallest wall time."""
        return min(self.wall)

    @property
    def best_cpu(self) -> float:
        """CPU time (all threads of the process) of the call with the smallest wall time."""
        return self.cpu[self.wall.index(self.best)]


def best_time(
    fn: Callable[[], Any], *, repeat: int = 3, short: float = 2.0
) -> tuple[Timing, Any]:
    """Time ``fn()``; repeat up to ``repeat`` times while one call takes under ``short`` s.

    Returns the wall and CPU times of every call and the result of the last call. The CPU
    time counts every thread of the process, so it exceeds the wall time of a call that
    runs on two threads and is close to it for a single-threaded call; unlike the wall
    time it is not inflated by other processes competing for the cores.
    """
    wall: list[float] = []
    cpu: list[float] = []
    result = None
    for _ in range(max(repeat, 1)):
        c0 = time.process_time()
        t0 = time.perf_counter()
        result = fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if wall[-1] >= short:
            break
    return Timing(wall, cpu), result


def load_rbs480a(path: str | os.PathLike[str] | None) -> np.ndarray:
    """Read rbs480a with ``scipy.io.mmread`` as a dense array; exit with a message if absent."""
    import scipy.io

    p = Path(path) if path is not None else DEFAULT_RBS480A
    if not p.is_file():
        raise SystemExit(f"rbs480a.mtx not found at {p}. {RBS480A_SOURCE}")
    A = scipy.io.mmread(str(p))
    return np.asarray(A.toarray() if hasattr(A, "toarray") else A, dtype=np.float64)


def format_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Format rows as a plain aligned text table (floats in ``%.3g``)."""

    def cell(x: Any) -> str:
        if isinstance(x, float | np.floating):
            return "-" if not math.isfinite(float(x)) else f"{float(x):.3g}"
        return str(x)

    body = [[cell(x) for x in r] for r in rows]
    widths = [max(len(h), *(len(r[c]) for r in body)) if body else len(h)
              for c, h in enumerate(headers)]
    lines = ["  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True))]
    lines += ["  ".join(x.rjust(w) for x, w in zip(r, widths, strict=True)) for r in body]
    return "\n".join(lines)


def print_table(headers: Sequence[str], rows: Sequence[Sequence[Any]], *, title: str = "") -> None:
    """Print a summary table to stdout."""
    if title:
        print(title)
    print(format_table(headers, rows))
    sys.stdout.flush()


@contextlib.contextmanager
def library_warnings_silenced() -> Iterator[None]:
    """Silence the library's warnings (a benchmark counts missed targets instead) in the block.

    Logging is restored on exit, so a benchmark run inside a test session leaves the
    tests after it their warnings.
    """
    logging.disable(logging.WARNING)
    try:
        yield
    finally:
        logging.disable(logging.NOTSET)


def rows_of_revision(rev: str, script: str | os.PathLike[str], args: Sequence[str]) -> Any:
    """Return what ``script --rows-only OUT *args`` writes to ``OUT`` on revision ``rev``.

    The revision is checked out in a temporary git worktree and the script runs in a
    child process with that worktree first on ``PYTHONPATH``, so ``import streamsvd``
    there is the older code while the benchmark itself is this revision's.
    """
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(REPO_ROOT), "worktree", "add", "--detach", "-q",
                        str(tree), rev], check=True)
        try:
            out = Path(tmp) / "rows.json"
            env = dict(os.environ, PYTHONPATH=str(tree))
            subprocess.run([sys.executable, str(script), "--rows-only", str(out), *args],
                           check=True, env=env)
            return json.loads(out.read_text())
        finally:
            subprocess.run(["git", "-C", str(REPO_ROOT), "worktree", "remove", "--force",
                            str(tree)], check=True)


def _tree_of(proc: Any) -> list[Any]:
    """``proc`` and its descendants (none when it is gone)."""
    import psutil

    try:
        return [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return []


def tree_rss(proc: Any) -> int:
    """Resident bytes of the psutil process ``proc`` and its descendants."""
    import psutil

    total = 0
    for p in _tree_of(proc):
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def tree_cpu(proc: Any) -> float:
    """CPU seconds (user and system) of ``proc`` and its living descendants."""
    import psutil

    total = 0.0
    for p in _tree_of(proc):
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.Error:
            pass
    return total


class ProcessPeaks:
    """Sample, in a thread, the peak resident memory of this process and of others.

    ``client`` is the peak of this process (with its descendants when ``client_tree``:
    a ``LocalCluster``'s workers), ``base`` its memory on entry; ``sched`` the peak of
    the ``scheduler`` process's tree, ``worker`` that of each of ``workers``' trees
    (``worker_base`` on entry, ``worker_cpu`` their CPU seconds in the block). The
    processes are ``subprocess.Popen`` objects or anything with a ``pid``.
    """

    def __init__(self, *, workers: Sequence[Any] = (), scheduler: Any = None,
                 client_tree: bool = False, period: float = 0.05) -> None:
        import psutil

        self.me = psutil.Process()
        self.client_tree = client_tree
        self.scheduler = None if scheduler is None else psutil.Process(scheduler.pid)
        self.workers = [psutil.Process(p.pid) for p in workers]
        self.period = period
        self.client = self.sched = 0
        self.worker = [0] * len(self.workers)
        self.cpu0 = [tree_cpu(w) for w in self.workers]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _mine(self) -> int:
        return tree_rss(self.me) if self.client_tree else int(self.me.memory_info().rss)

    def _sample(self) -> None:
        self.client = max(self.client, self._mine())
        if self.scheduler is not None:
            self.sched = max(self.sched, tree_rss(self.scheduler))
        self.worker = [max(a, tree_rss(w)) for a, w in zip(self.worker, self.workers, strict=True)]

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.period)

    def __enter__(self) -> ProcessPeaks:
        self.base = self._mine()
        self.client = self.base
        self.worker_base = [tree_rss(w) for w in self.workers]
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()
        self.worker_cpu = [tree_cpu(w) - c for w, c in zip(self.workers, self.cpu0, strict=True)]
