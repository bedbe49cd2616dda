"""Where a store's snapshots came from: the source record kept in its attributes.

A compressor that commits to a store records the snapshot source it reads
(:class:`SourceRecord`: the path as given and resolved, the dataset, the shape, a
description) in the attributes of every commit, so that continuing the store from
another source can be refused. A source *differs* from the recorded one when its
resolved path, its dataset or its snapshot size ``n`` differ, or when it has fewer
columns than recorded; a source that gained columns (a solver appending snapshots to
its file) is the same source, continued.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from streamsvd.errors import InputError

__all__ = ["SourceRecord"]


def _resolved(path: str) -> str:
    """Return an absolute form of ``path`` (a URL is kept as it is)."""
    if "://" in path:
        return path
    return os.fspath(Path(path).expanduser().resolve())


@dataclass(frozen=True)
class SourceRecord:
    """The snapshot source of a store, as recorded at creation and on every resume.

    Attributes
    ----------
    path : str or None
        The path (or URL) as it was given; None for an in-memory array.
    resolved : str or None
        The absolute path (a URL as given); None for an in-memory array.
    dataset : str or None
        The dataset of an HDF5 file or array of a zarr group as given (without a
        leading ``/``); None when it was not given.
    shape : tuple of int
        ``(n, m)``: snapshot size and number of snapshots when the record was made.
    description : str
        How the source is named in messages (:attr:`streamsvd.io.sources.Source.description`).
    """

    path: str | None
    resolved: str | None
    dataset: str | None
    shape: tuple[int, int]
    description: str

    @classmethod
    def of(cls, source: Any, *, dataset: str | None, shape: tuple[int, int],
           description: str) -> SourceRecord:
        """Record ``source`` (a path, an h5py dataset or an array) of the given shape.

        Parameters
        ----------
        source : str, os.PathLike, h5py.Dataset or array_like
            What was passed to :func:`~streamsvd.io.open.open_source`.
        dataset : str or None
            The ``dataset`` passed with it.
        shape : tuple of int
            ``(n, m)`` of the opened source.
        description : str
            The opened source's description.
        """
        path: str | None = None
        if isinstance(source, str | os.PathLike):
            path = os.fspath(source)
        elif (type(source).__module__ or "").startswith("h5py"):
            path, dataset = source.file.filename, source.name
        name = None if dataset is None else str(dataset).strip("/")
        n, m = (int(s) for s in shape)
        return cls(path, None if path is None else _resolved(path), name, (n, m),
                   str(description))

    def to_attrs(self) -> dict[str, Any]:
        """Return the record as the JSON-able dictionary a store keeps."""
        return {
            "path": self.path, "resolved": self.resolved, "dataset": self.dataset,
            "shape": list(self.shape), "description": self.description,
        }

    @classmethod
    def from_attrs(cls, attrs: Any) -> SourceRecord | None:
        """Return the record a store keeps (None when the store has none)."""
        if attrs is None:
            return None
        try:
            n, m = (int(s) for s in attrs["shape"])
            return cls(attrs["path"], attrs["resolved"], attrs["dataset"], (n, m),
                       str(attrs["description"]))
        except (KeyError, TypeError, ValueError):
            raise InputError(
                f"a store's source record must hold path, resolved, dataset, shape and "
                f"description; got {attrs!r}."
            ) from None

    def differences(self, given: SourceRecord) -> list[tuple[str, str, str]]:
        """Return how ``given`` differs from this recorded source (see the module doc).

        Returns
        -------
        list of (str, str, str)
            ``(what, given value, recorded value)`` for the path, the dataset and the
            shape, in that order; empty when ``given`` is this source, possibly with
            more columns.
        """
        out = []
        if given.resolved != self.resolved:
            out.append(("path", _show(given.resolved, given.description),
                        _show(self.resolved, self.description)))
        if given.dataset != self.dataset:
            out.append(("dataset", _show(given.dataset, "none"), _show(self.dataset, "none")))
        (n, m), (n0, m0) = given.shape, self.shape
        if n != n0 or m < m0:
            out.append(("shape", f"{n} x {m}", f"{n0} x {m0}"))
        return out


def _show(value: str | None, otherwise: str) -> str:
    return otherwise if value is None else value
