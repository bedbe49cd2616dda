"""The BLAS threads of an update.

OpenBLAS threads spin while they wait: on a machine where other work runs, a BLAS that
uses every core can be several times slower than one thread (measured in
``bench/README.md``). An update therefore limits the BLAS to ``threads`` threads while it
runs (``None``: leave the BLAS as it is set).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

from streamsvd._util.validation import check_positive_int

__all__ = ["blas_threads", "check_threads"]

_controller: Any = None


def check_threads(threads: Any) -> int | None:
    """Validate a ``threads`` option: a positive int, or None (the BLAS's own setting)."""
    return check_positive_int(threads, "threads", allow_none=True)


def blas_threads(threads: int | None) -> contextlib.AbstractContextManager[Any]:
    """Return a context that limits the loaded BLAS libraries to ``threads`` threads.

    The libraries are found once (threadpoolctl's scan); on entry only those running
    another count are set, and they are set back on exit: an update whose BLAS already
    runs ``threads`` threads pays one query per library (5 microseconds with two
    OpenBLAS libraries loaded, against 11.5 for threadpoolctl's limiter).
    """
    global _controller
    if threads is None:
        return contextlib.nullcontext()
    if _controller is None:
        from threadpoolctl import ThreadpoolController

        # scans the loaded libraries once
        _controller = ThreadpoolController().select(user_api="blas")
    return _limited(_controller.lib_controllers, threads)


@contextlib.contextmanager
def _limited(libraries: list[Any], threads: int) -> Iterator[None]:
    changed = [(lib, n) for lib in libraries if (n := lib.get_num_threads()) != threads]
    for lib, _ in changed:
        lib.set_num_threads(threads)
    try:
        yield
    finally:
        for lib, n in changed:
            lib.set_num_threads(n)
