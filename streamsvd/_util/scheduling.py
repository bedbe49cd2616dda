"""Where dask graphs run: the threaded scheduler, the one set in dask's configuration, or a cluster.

:func:`execute` is the one place where the package computes a dask collection (the
tall mode's products over the row panels, the tree's leaves and merges, the writes of
panels); :func:`check_client` validates a ``client=`` argument and
:func:`blas_threads_per_task` sizes the BLAS of the tasks that set their own limit.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from typing import Any, cast

from streamsvd._util.threads import blas_threads
from streamsvd.errors import InputError

__all__ = [
    "LOCAL_SCHEDULERS", "blas_threads_per_task", "check_client", "execute", "local_get",
]

LOCAL_SCHEDULERS = (
    "sync", "synchronous", "single-threaded", "threads", "threading", "processes",
    "multiprocessing",
)
"""Schedulers of ``dask.config`` that :func:`execute` honours without a client."""


def check_client(client: Any) -> Any:
    """Return ``client`` if it is None or a :class:`distributed.Client`; raise otherwise."""
    if client is None:
        return None
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - distributed is a dependency
        Client = ()  # type: ignore[assignment,misc]
    if not isinstance(client, Client):
        raise InputError(
            f"`client` must be None (the threaded scheduler) or a dask.distributed.Client; "
            f"got {type(client).__name__}. Create one with `Client(LocalCluster())` or "
            "`Client('tcp://host:8786')`."
        )
    if client.status not in ("running", "newly-created"):
        raise InputError(
            f"`client` must be connected; got a client with status {client.status!r}. "
            "Reconnect it or create a new one."
        )
    return client


def execute(collections: list[Any], *, client: Any = None, progress: bool = False,
            overlap_io: bool = False) -> list[Any]:
    """Compute dask collections on the threaded scheduler or on ``client``'s cluster.

    Parameters
    ----------
    collections : list
        Dask collections (delayed objects, arrays) computed together, so that tasks they
        share run once.
    client : distributed.Client, optional
        Run on this cluster. When omitted, in this process: on the local scheduler set
        with ``dask.config.set(scheduler=...)`` (``"synchronous"``, ``"threads"``,
        ``"processes"``), else on the threaded scheduler (even if a default client is
        registered); the threaded scheduler runs one BLAS thread per task.
    progress : bool
        Show dask's progress bar (:class:`dask.diagnostics.ProgressBar`, or
        :func:`distributed.progress` on a cluster).
    overlap_io : bool
        The tasks wait on reads and writes (the tall mode's passes over its panels and
        its source): the threaded scheduler then runs one task more than there are cores,
        so that every core computes while a task waits, unless ``dask.config`` sets
        ``num_workers`` or ``pool``. On a 200000 x 1000 zarr array (2 cores) the tall mode
        took 5.28 s against 5.73 s (medians of 8 interleaved processes, with
        :func:`~streamsvd._util.malloc.keep_freed_memory`'s arena limit; ``bench/README.md``).

    Returns
    -------
    list
        The computed values, in the order of ``collections``.
    """
    import dask

    if client is None:
        chosen = dask.config.get("scheduler", None)
        scheduler = chosen if chosen in LOCAL_SCHEDULERS else "threads"
        # the threaded scheduler runs a task per core (one more with `overlap_io`): one
        # BLAS thread each, or the cores are oversubscribed (tasks that limit themselves
        # keep their own limit)
        threaded = scheduler in ("threads", "threading")
        options: dict[str, Any] = {}
        if overlap_io and threaded and dask.config.get("num_workers", None) is None and (
                dask.config.get("pool", None) is None):
            from dask.system import CPU_COUNT  # the cores this process may use

            options["num_workers"] = CPU_COUNT + 1
        with blas_threads(1 if threaded else None), _progress_bar(progress):
            return list(dask.compute(*collections, scheduler=local_get(scheduler), **options))
    futures = client.compute(list(collections))
    try:
        if progress:
            from distributed import progress as show_progress

            show_progress(futures)
        return list(client.gather(futures))
    finally:
        client.cancel(futures)


def local_get(scheduler: str) -> Callable[..., Any]:
    """Return the function that runs a graph on the local scheduler named ``scheduler``.

    ``scheduler`` is one of :data:`LOCAL_SCHEDULERS`. dask given the name looks for a
    default client first, which imports :mod:`distributed` (0.5 s of CPU per process,
    ``bench/README.md``); given the function, it runs the graph at once, as it would.
    """
    if scheduler in ("threads", "threading"):
        from dask import threaded

        return cast(Callable[..., Any], threaded.get)
    if scheduler in ("processes", "multiprocessing"):
        from dask import multiprocessing

        return cast(Callable[..., Any], multiprocessing.get)
    from dask import local

    return cast(Callable[..., Any], local.get_sync)


def blas_threads_per_task(client: Any) -> int:
    """BLAS threads each task may use: this machine's cores over the tasks run at once.

    With dask's threaded scheduler (``client=None``) as many tasks run as there are
    cores, so each gets one BLAS thread; on a cluster, a worker's threads share the cores
    of its host (workers on this host are counted together).
    """
    cores = os.cpu_count() or 1
    if client is None:
        return 1
    try:
        threads = sum(client.nthreads().values())
    except Exception:  # a client that cannot report its workers: stay conservative
        return 1
    return max(1, cores // max(threads, 1))


@contextlib.contextmanager
def _progress_bar(show: bool) -> Iterator[None]:
    """Show dask's progress bar (on stderr) around local computations when ``show``."""
    if not show:
        yield
        return
    from dask.diagnostics import ProgressBar

    with ProgressBar(out=sys.stderr):
        yield
