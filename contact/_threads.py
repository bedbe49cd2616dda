"""Limit the BLAS thread pool during the solvers' iterations.

The LATIN iterations are made of many small dense products (``p x p`` solves,
``2 nc x m`` arrays), for which BLAS threads cost more than they gain, and badly so on
a loaded machine. ``threadpoolctl`` is used when installed; otherwise nothing changes.
"""

from __future__ import annotations

import contextlib
from typing import Any


def blas_threads(limit: int | None) -> contextlib.AbstractContextManager[Any]:
    """Return a context manager limiting BLAS to ``limit`` threads (None: no limit)."""
    if limit is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional dependency
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(limit), user_api="blas")
