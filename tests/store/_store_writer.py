"""Commit generations of known content to a basis store in a loop, until killed.

Used by the kill test of ``test_handle.py``: generation ``k`` holds the arrays and the
attributes returned by :func:`expected_generation` (``k``), so a reader can check that
whatever generation is current after a ``SIGKILL`` holds exactly what was committed.
Besides arrays committed whole, each generation appends rows to the array ``T``
(:func:`appended_rows`), which gains zero columns and starts anew every ``EPOCH``
generations, so that kills land in commits that keep, merge and drop segments.

Usage: ``python _store_writer.py STORE_PATH MAX_SECONDS``; prints ``ready`` once the store
is open, then ``committed K`` after each commit.
"""

from __future__ import annotations

import importlib
import os
import sys
import time
import types
from pathlib import Path

import numpy as np

N = 3000
P = 6
CHUNK_BYTES = 16 * 1024  # several chunks per factor, so that kills land between chunks
CREATE_ATTRS = {"k": 0, "note": "created by the kill test"}


EPOCH = 25  # generations between two rewrites of T
T_ROWS = 3  # rows appended to T per generation


def _t_shape(k: int) -> tuple[int, int]:
    return T_ROWS * (k % EPOCH + 1), 1 + (k % EPOCH) // 8


def appended_rows(k: int) -> tuple[np.ndarray, int]:
    """``T`` of generation ``k`` (k >= 1) and how many of its rows generation ``k - 1`` has."""
    rows, width = _t_shape(k)
    T = np.zeros((rows, width))
    start = k - k % EPOCH
    for g in range(start, k + 1):  # the rows generation g appended, at its width
        r0, w = T_ROWS * (g - start), _t_shape(g)[1]
        rng = np.random.default_rng([k // EPOCH, g])
        T[r0 : r0 + T_ROWS, :w] = rng.standard_normal((T_ROWS, w))
    unchanged = 0 if k % EPOCH == 0 or k == 1 else _t_shape(k - 1)[0]
    return T, unchanged


def expected_generation(k: int) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays and attributes the writer commits as generation ``k`` (k >= 1)."""
    rng = np.random.default_rng(k)
    U = rng.standard_normal((N, P))
    V = rng.standard_normal((k % 37 + 1, P))
    s = rng.random(P)
    attrs = {"k": k, "n_seen": 10 * k, "history": [float(x) for x in s[:3]]}
    return {"U": U, "V": V, "amplitudes": s, "T": appended_rows(k)[0]}, attrs


def _import_store() -> types.ModuleType:
    """Import ``streamsvd.store`` from this working tree, skipping the package's other
    modules (numba compilation and all), so that each restarted writer starts fast."""
    package = types.ModuleType("streamsvd")
    package.__path__ = [str(Path(__file__).resolve().parents[2] / "streamsvd")]
    sys.modules["streamsvd"] = package
    return importlib.import_module("streamsvd.store")


def main(path: str, max_seconds: float) -> None:
    store_mod = _import_store()
    open_store, Appended = store_mod.open_store, store_mod.Appended

    parent = os.getppid()
    deadline = time.monotonic() + max_seconds
    with open_store(path, mode="a") as store:
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        while time.monotonic() < deadline and os.getppid() == parent:
            arrays, attrs = expected_generation(store.generation + 1)
            T, unchanged = appended_rows(store.generation + 1)
            del arrays["T"]
            k = store.commit(arrays, attrs, appended={"T": Appended(T, axis=0, unchanged=unchanged)})
            sys.stdout.write(f"committed {k}\n")
            sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
