"""The unread column block of a source: a dask array read by row chunks when needed.

:class:`LazyBlock` is what :meth:`streamsvd.io.sources.Source.lazy` returns and what
:class:`~streamsvd.algebra.panels.basis.PanelBasis` absorbs in one pass over its row
chunks. It lives with the panels (layer 1) so that the out-of-core basis recognises it
without importing the readers of :mod:`streamsvd.io`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, cast

from streamsvd.errors import SourceError

__all__ = ["LazyBlock"]


@dataclass(frozen=True)
class LazyBlock:
    """Columns ``first:first + b`` of a source, read by row chunks when a product needs them.

    ``data`` is a dask array (``n x b``, float32 or float64, chunked by rows) whose tasks
    read and check the source; :class:`~streamsvd.algebra.panels.basis.PanelBasis` absorbs it in one
    pass over its row chunks, and :meth:`failed` names the columns when a read fails.
    """

    data: Any
    first: int
    description: str

    @property
    def shape(self) -> tuple[int, int]:
        """``(n, b)``."""
        return cast(tuple[int, int], tuple(self.data.shape))

    def failed(self, exc: BaseException) -> SourceError:
        """Return the error that reports a failed read of these columns."""
        a, b = self.first, self.first + self.shape[1]
        return SourceError(
            f"reading columns {a}:{b} (offset {a}) of {self.description} failed: "
            f"{type(exc).__name__}: {exc}. The basis is unchanged and a store holds its "
            f"last commit; fix the cause and resume from offset {a}."
        )
