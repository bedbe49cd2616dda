"""The BLAS threads of an update.

OpenBLAS threads spin while they wait: on a machine where other work runs, a BLAS that
uses every core can be several times slower than one thread (measured in
``bench/README.md``). An update therefore limits the BLAS to ``threads`` threads while it
runs (``None``: leave the BLAS as it is set).
"""

from __future__ import annotations

import contextlib
from typing import Any

from streamsvd._util.validation import check_positive_int

__all__ = ["blas_threads", "check_threads"]

_controller: Any = None


def check_threads(threads: Any) -> int | None:
    """Validate a ``threads`` option: a positive int, or None (the BLAS's own setting)."""
    return check_positive_int(threads, "threads", allow_none=True)


def blas_threads(threads: int | None) -> contextlib.AbstractContextManager[Any]:
    """Return a context that limits the loaded BLAS libraries to ``threads`` threads."""
    global _controller
    if threads is None:
        return contextlib.nullcontext()
    if _controller is None:
        from threadpoolctl import ThreadpoolController

        _controller = ThreadpoolController()  # scans the loaded libraries once
    return _controller.limit(limits=threads, user_api="blas")
