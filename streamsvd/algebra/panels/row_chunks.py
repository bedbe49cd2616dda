"""The tall mode's dask arrays by row chunks, and the passes over them.

:class:`RowChunks` shows the panels of a :class:`~streamsvd.algebra.panels.basis.PanelBasis` (kept
by :class:`~streamsvd.algebra.panels.files.PanelFiles`) and its in-memory blocks to dask as arrays
chunked by the basis's rows, and maps a task of :mod:`streamsvd.algebra.panels.tasks` over those
chunks: a *pass*, one task per row chunk, whose shares of the small products a reduction
sums. Every graph runs through :func:`streamsvd._util.scheduling.execute`, on the threaded
scheduler with a task more than the cores (the tasks wait on reads and writes) or on the
given cluster.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from typing import Any, cast

import numpy as np

from streamsvd._util.scheduling import execute
from streamsvd.algebra.inner import DiagonalInner, InnerProduct
from streamsvd.algebra.panels.files import PanelFiles
from streamsvd.algebra.panels.raw_array import RawArray, RowView
from streamsvd.algebra.panels.zarr_io import Region

__all__ = ["RowChunks", "io_target"]


class RowChunks:
    """Dask views by row chunks of ``chunk_rows`` rows (``n`` in all), computed on ``client``.

    Parameters
    ----------
    n : int
        Rows of every array.
    chunk_rows : int
        Rows per chunk.
    inner : InnerProduct
        Euclidean or :class:`~streamsvd.algebra.inner.DiagonalInner` (its weights are chunked as
        the rows).
    client : distributed.Client or None
        Where the graphs run (the threaded scheduler when None).
    files : PanelFiles
        The panels read by :meth:`panel`.
    """

    def __init__(self, n: int, *, chunk_rows: int, inner: InnerProduct, client: Any,
                 files: PanelFiles) -> None:
        full, rest = divmod(int(n), int(chunk_rows))
        self.sizes: tuple[int, ...] = (int(chunk_rows),) * full + ((rest,) if rest else ())
        self.inner = inner
        self.client = client
        self.files = files

    def compute(self, collections: list[Any]) -> list[Any]:
        """Compute a pass: its tasks read and write panels, so they overlap their waits."""
        return execute(collections, client=self.client, overlap_io=True)

    def rows_of(self, X: Any) -> Any:
        """Return the dask array ``X`` rechunked to these row chunks (one column chunk)."""
        return X.rechunk({0: self.sizes, 1: -1})

    def panel(self, name: str) -> Any:
        """Return panel ``name`` as a dask array of its row chunks."""
        import dask.array as da

        z = self.files.open(name)
        return da.from_array(io_target(z), chunks=z.chunks, name=f"streamsvd-panel-{name}",
                             meta=np.empty((0, 0), z.dtype), asarray=False)

    def stacked(self, names: Sequence[str]) -> Any:
        """Return the panels ``names`` side by side as one dask array, or None if none."""
        import dask.array as da

        if not names:
            return None
        parts = [self.panel(name) for name in names]
        return self.rows_of(parts[0] if len(parts) == 1 else da.concatenate(parts, axis=1))

    def block(self, X: np.ndarray) -> Any:
        """Return an in-memory block as a dask array of its row chunks (views, no copy).

        The graph is computed before the block changes: every caller runs it at once.
        """
        import dask.array as da

        return da.from_array(RowView(X), chunks=(self.sizes, (X.shape[1],)),
                             name=f"streamsvd-block-{uuid.uuid4().hex}", meta=X[:0, :0])

    def _weights(self) -> Any:
        import dask.array as da

        w = cast(DiagonalInner, self.inner).weights.reshape(-1, 1)
        return da.from_array(w, chunks=(self.sizes, (1,)))

    def weighted(self, Y: Any) -> Any:
        """``M Y`` of a dask array of these row chunks (diagonal ``M``)."""
        return Y if self.inner.is_euclidean else Y * self._weights()

    def run_pass(self, task: Any, arrays: list[Any], rows: int, cols: int,
                 **kwargs: Any) -> Any:
        """Return the sum of the ``rows x cols`` shares ``task`` computes per row chunk.

        ``arrays`` are chunked by these rows (one column chunk each); with a diagonal
        inner product the weights' chunk is passed after them, and ``task`` gets
        ``weighted=True``.
        """
        import dask.array as da

        if not self.inner.is_euclidean:
            arrays = [*arrays, self._weights()]
        chunks = arrays[0].rechunk({0: self.sizes}).chunks[0]
        aligned = [a.rechunk({0: chunks, 1: -1}) for a in arrays]
        shares = da.map_blocks(
            task, *aligned, weighted=not self.inner.is_euclidean,
            chunks=((rows,) * len(chunks), (cols,)), dtype=np.float64,
            meta=np.empty((0, 0)), name=f"streamsvd-pass-{uuid.uuid4().hex}", **kwargs,
        )
        return shares.reshape((len(chunks), rows, cols)).sum(axis=0)


def io_target(z: Any) -> Any:
    """Return what dask reads and writes a panel through (zarr via :mod:`.zarr_io`)."""
    return z if isinstance(z, RawArray) else Region(z)
