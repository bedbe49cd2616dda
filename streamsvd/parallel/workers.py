"""What the workers of a cluster have and see: cores, threads, paths and credentials.

A dask worker may run on another machine, with its own file system, its own cores and
its own credentials. Three things are therefore asked of the workers themselves, never
assumed from the client:

* :func:`check_workers_see` -- before a run, every worker opens what it will need (a
  source path or URL, the store, the tall mode's panels) and reports what it could not
  see: the error then names the workers, the location and what to do, instead of a read
  failure blamed on the source halfway through;
* :func:`blas_plan` and :func:`blas_here` -- BLAS threads per task from the cores of the
  worker's host over the threads of the workers on that host;
* :func:`worker_threads` -- how many tasks the cluster runs at once (the tree's default
  number of leaves).

Credentials never travel in a task graph: a storage pickles without its secrets
(:meth:`streamsvd.storage.ObjectStorage.__reduce__`), so the workers use their own
environment (``AWS_*`` variables, ``AWS_PROFILE`` and ``~/.aws``, an instance role).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from streamsvd.errors import SourceError, StoreError
from streamsvd.storage import LocalStorage, ObjectStorage, open_storage

__all__ = ["blas_here", "blas_plan", "check_workers_see", "source_places", "worker_threads"]

_CREDENTIAL_WORDS = ("NoCredentialsError", "InvalidAccessKeyId", "SignatureDoesNotMatch",
                     "AccessDenied", "ExpiredToken", "Forbidden", "credentials")

CREDENTIALS_HINT = (
    "Give every worker its own credentials: AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY (and "
    "AWS_ENDPOINT_URL for a non-AWS endpoint) in the environment the worker is started "
    "with, AWS_PROFILE with ~/.aws on its machine, or an instance role; secrets passed in "
    "`storage_options` are not sent to workers."
)


def worker_threads(client: Any) -> int:
    """Return the number of tasks ``client``'s cluster runs at once (1 without a client)."""
    if client is None:
        return 1
    try:
        workers = client.scheduler_info(n_workers=-1)["workers"]
    except Exception:  # a client that cannot report its workers
        return 1
    return max(1, sum(int(w.get("nthreads", 1)) for w in workers.values()))


def _cores() -> int:
    """Return the cores this process may run on (on the worker)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def blas_plan(client: Any) -> int | dict[str, int]:
    """Return the BLAS threads of the tasks: 1 without a client, else per worker address.

    Each worker reports its own cores (:meth:`distributed.Client.run`); the workers on one
    host share its cores, so each of their threads gets ``cores // threads on the host``.
    """
    if client is None:
        return 1
    try:
        cores = client.run(_cores)
        workers = client.scheduler_info(n_workers=-1)["workers"]
    except Exception:  # a client that cannot reach its workers: stay conservative
        return 1
    threads: dict[str, int] = {}
    host_cores: dict[str, int] = {}
    for address, info in workers.items():
        host = str(info.get("host", address))
        threads[host] = threads.get(host, 0) + int(info.get("nthreads", 1))
        host_cores[host] = max(host_cores.get(host, 1), int(cores.get(address, 1)))
    return {address: max(1, host_cores[str(info.get("host", address))]
                          // max(1, threads[str(info.get("host", address))]))
            for address, info in workers.items()}


def blas_here(plan: int | dict[str, int]) -> int:
    """Return the BLAS threads of a task running here under ``plan`` (see :func:`blas_plan`)."""
    if isinstance(plan, int):
        return plan
    try:
        from distributed import get_worker

        return int(plan.get(get_worker().address, 1))
    except (ImportError, ValueError):  # not on a worker
        return 1


# ------------------------------------------------------------------------- probes


def _describe(exc: BaseException) -> str:
    text = f"{type(exc).__name__}: {exc}"
    cause = exc.__cause__
    if cause is not None:
        text += f" ({type(cause).__name__}: {cause})"
    return text


def _probe(paths: Sequence[tuple[str, str]], storages: Sequence[tuple[str, Any]]
           ) -> list[tuple[str, str, str]]:
    """Run on a worker: return ``(argument, location, problem)`` for what it cannot see."""
    problems = []
    for argument, path in paths:
        if not os.path.exists(path):
            problems.append((argument, path, "not-found"))
    for argument, storage in storages:
        try:
            if isinstance(storage, LocalStorage):
                if not storage.root.is_dir():
                    problems.append((argument, str(storage.root), "not-found"))
            else:
                storage.exists()
        except Exception as exc:  # reported with the worker's name, never raised here
            text = _describe(exc)
            kind = ("credentials" if any(w in text for w in _CREDENTIAL_WORDS)
                    else f"unreachable: {text}")
            problems.append((argument, str(storage), kind))
    return problems


def source_places(spec: Any) -> dict[str, list[tuple[str, Any]]]:
    """Return the ``paths`` and ``storages`` of :func:`check_workers_see` for a source.

    ``spec`` is a :class:`~streamsvd.parallel.spec.SourceSpec`: a local path or an
    object-store URL that the tasks reopen (nothing for in-memory and dask sources).
    """
    path, url = spec.local_path(), spec.url()
    paths = [("`source`", path)] if path is not None else []
    storages = ([("`source`", open_storage(url[0], storage_options=url[1] or None,
                                           argument="source"))] if url is not None else [])
    return {"paths": paths, "storages": storages}


def check_workers_see(
    client: Any,
    *,
    paths: Sequence[tuple[str, str]] = (),
    storages: Sequence[tuple[str, LocalStorage | ObjectStorage]] = (),
) -> None:
    """Raise if a worker of ``client`` cannot see a path or reach a storage it will need.

    Parameters
    ----------
    client : distributed.Client or None
        Nothing is checked without a client (the tasks run in this process).
    paths : sequence of (name, path)
        Local files or directories every worker opens (``("`source`", "/data/a.npy")``:
        the name as messages give it).
    storages : sequence of (name, storage)
        Stores, panels or checkpoints the workers read or write; a local one must exist
        (the client creates it first), an object store must answer with the worker's own
        credentials.

    Raises
    ------
    SourceError
        A worker cannot see ``source``.
    StoreError
        A worker cannot see or reach another location (``store``, ``workdir``, ...).
    """
    if client is None or (not paths and not storages):
        return
    found = client.run(_probe, list(paths), list(storages))
    by_place: dict[tuple[str, str, str], list[str]] = {}
    for address, problems in sorted(found.items()):
        for problem in problems:
            by_place.setdefault(tuple(problem), []).append(address)
    if not by_place:
        return
    (argument, location, kind), addresses = next(iter(sorted(by_place.items())))
    who = (f"dask worker {addresses[0]}" if len(addresses) == 1 else
           f"{len(addresses)} of {len(found)} dask workers ({', '.join(addresses[:3])}"
           f"{', ...' if len(addresses) > 3 else ''})")
    if kind == "not-found":
        message = (
            f"{argument} {location}: {who} could not see it (this process can). On a "
            "cluster the workers open it themselves: put it on a file system mounted at "
            "the same path on every worker, or on an object store (s3://...) that the "
            "workers can reach (for the tall mode's panels: pass `store=` or `workdir=` "
            "there)."
        )
    elif kind == "credentials":
        message = (
            f"{argument} {location}: {who} could not reach it with the workers' own credentials "
            f"(this process can). {CREDENTIALS_HINT}"
        )
    else:
        message = (f"{argument} {location}: {who} could not reach it ({kind[13:]}). "
                   "Check the workers' network, endpoint (AWS_ENDPOINT_URL) and "
                   f"credentials. {CREDENTIALS_HINT}")
    error = SourceError if argument == "`source`" else StoreError
    raise error(message)
