"""What a tree task is given: where its columns come from, and its compressor's options.

:class:`SourceSpec` is how a task opens the snapshot source where it runs (the part of an
in-memory or dask source it reads, a :class:`_Window`, is all that is shipped to it);
:func:`leaf_ranges` and :func:`default_leaf_columns` cut the columns into leaves;
:func:`check_options`, :func:`options_of` and :func:`_node_options` are the options of the
tree's compressors, at the root and at the nodes.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, cast

import numpy as np

from streamsvd._util.scheduling import local_get
from streamsvd.algebra.inner import as_inner
from streamsvd.errors import InputError
from streamsvd.io.formats import open_zarr_url
from streamsvd.io.open import open_source
from streamsvd.io.sources import Source
from streamsvd.storage import is_url, without_secrets
from streamsvd.stream.compressor import StreamCompressor
from streamsvd.stream.options import TREE_OPTIONS as COMPRESSOR_OPTIONS
from streamsvd.stream.options import CompressorOptions

__all__ = [
    "TREE_OVERSAMPLING",
    "SourceSpec",
    "check_options",
    "default_leaf_columns",
    "leaf_ranges",
    "options_of",
]

TREE_OVERSAMPLING = 2  # the oversampling of the tree's nodes, in the compressor's


# -------------------------------------------------------------------------- sources


class _Window:
    """Columns ``[start, start + w)`` of an ``n x m`` source, addressed by global columns.

    Lets a leaf read its own part of an in-memory or dask source with the offsets of the
    whole source (so that error messages name the right columns) while only that part is
    shipped to the worker. Dask slices are evaluated with the synchronous scheduler inside
    the task that reads them (a nested ``compute`` on a worker must not go back to the
    cluster).
    """

    def __init__(self, data: Any, start: int, m: int, *, is_dask: bool) -> None:
        self.data = data
        self.start = start
        self.shape = (int(data.shape[0]), m)
        self.dtype = data.dtype
        self.is_dask = is_dask
        self.chunks = data.chunks if is_dask else None  # read by whole dask chunks

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, cols = key
        lo, hi = int(cols.start) - self.start, int(cols.stop) - self.start
        if lo < 0 or hi > self.data.shape[1]:
            raise IndexError(
                f"columns {cols.start}:{cols.stop} are outside this leaf's columns "
                f"{self.start}:{self.start + self.data.shape[1]}"
            )
        part = self.data[rows, lo:hi]
        if self.is_dask:
            return np.asarray(part.compute(scheduler=local_get("sync")), dtype=np.float64)
        return np.array(part, dtype=np.float64, copy=True)


class SourceSpec:
    """How a task opens a snapshot source where it runs (picklable, never a collection).

    Built on the client by :meth:`SourceSpec.of`, which opens the source once to check it.
    A path (``.npy``, HDF5, zarr) is reopened by each task; an h5py dataset becomes its
    file name and dataset name; a zarr array is shipped as is (it pickles as its store
    location); numpy and dask arrays are cut into the column windows the tasks need.
    """

    def __init__(self, kind: str, obj: Any, dataset: str | None, n: int, m: int,
                 description: str) -> None:
        self.kind = kind
        self.obj = obj
        self.dataset = dataset
        self.n = n
        self.m = m
        self.description = description

    @classmethod
    def of(cls, source: Any, *, dataset: str | None = None) -> SourceSpec:
        """Check ``source`` (as :func:`~streamsvd.io.open.open_source` does) and describe it."""
        if isinstance(source, Source):
            raise InputError(
                "`source` must be an array, a path, an h5py dataset or a zarr/dask array; "
                "got an open Source, which cannot be reopened on a worker. Pass what you "
                "opened it from."
            )
        with open_source(source, dataset=dataset) as src:
            n, m, desc = src.n, src.m, src.description
        if is_url(source):  # a zarr array at a URL: reopened by its URL where it runs
            return cls("url", (source, {}), dataset, n, m, desc)
        if isinstance(source, str | os.PathLike):
            return cls("path", os.fspath(Path(source).resolve()), dataset, n, m, desc)
        module = type(source).__module__ or ""
        if module.startswith("h5py"):
            return cls("path", os.fspath(Path(source.file.filename).resolve()),
                       source.name, n, m, desc)
        if module.startswith("dask"):
            return cls("dask", source, None, n, m, desc)
        if module.startswith("zarr"):
            at = _url_of(source)
            if at is not None:  # reopened by its URL (pickled without secrets)
                return cls("url", at[:2], at[2], n, m, desc)
            return cls("zarr", source, None, n, m, desc)
        return cls("array", np.asarray(source), None, n, m, desc)

    def window(self, start: int, stop: int) -> SourceSpec:
        """Return the part of this spec that a task reading columns ``start:stop`` needs."""
        if self.kind in ("array", "dask"):
            part = _Window(self.obj[:, start:stop], start, self.m, is_dask=self.kind == "dask")
            return SourceSpec("window", part, None, self.n, self.m, self.description)
        return self

    def open(self) -> Source:
        """Open the source (on the worker); close the returned Source when done."""
        if self.kind == "path":
            return open_source(self.obj, dataset=self.dataset)
        if self.kind == "window":
            return Source(self.obj, self.description)
        if self.kind == "url":
            url, options = self.obj
            array = open_zarr_url(url, dataset=self.dataset, storage_options=options or None)
            return open_source(array)
        return open_source(self.obj)

    def __reduce__(self) -> Any:
        # sent to workers through the scheduler: a URL's options travel without secrets
        obj = self.obj
        if self.kind == "url":
            obj = (obj[0], without_secrets(obj[1]))
        return (SourceSpec, (self.kind, obj, self.dataset, self.n, self.m, self.description))

    def local_path(self) -> str | None:
        """Return the local file every task opens (None for other sources)."""
        return cast(str, self.obj) if self.kind == "path" else None

    def url(self) -> tuple[str, dict[str, Any]] | None:
        """Return the object-store URL every task opens, with its options, or None."""
        return cast(tuple[str, dict[str, Any]], self.obj) if self.kind == "url" else None

    def __repr__(self) -> str:
        return f"SourceSpec({self.kind}, {self.description}, n={self.n}, m={self.m})"


def _url_of(array: Any) -> tuple[str, dict[str, Any], str | None] | None:
    """Return the URL, options and path of a zarr array in an object store (else None)."""
    store: Any = getattr(array, "store", None)
    fs = getattr(store, "fs", None)
    if fs is None or not hasattr(store, "path"):
        return None
    protocols = fs.protocol if isinstance(fs.protocol, tuple | list) else (fs.protocol,)
    if protocols[0] in ("file", "local", "memory"):
        return None
    url = f"{protocols[0]}://{str(store.path).rstrip('/')}"
    options = {k: v for k, v in getattr(fs, "storage_options", {}).items()
               if k not in ("asynchronous", "loop")}  # zarr's own: reopened as a user would
    return url, options, (array.path or None)


# ---------------------------------------------------------------------- validation


def check_options(options: dict[str, Any], n: int) -> dict[str, Any]:
    """Validate a tree's compressor options (:class:`~streamsvd.stream.CompressorOptions`)."""
    unknown = sorted(set(options) - set(COMPRESSOR_OPTIONS))
    if unknown:
        raise InputError(
            f"`options` must be among {COMPRESSOR_OPTIONS}; got unknown {unknown}. "
            "Pass the store with `store=` and the other options by their names."
        )
    opts = dict(options)
    inner = as_inner(opts.pop("inner", None), n)
    return {"inner": inner, **_tree_options(CompressorOptions.validated(n, **opts))}


def options_of(sc: StreamCompressor) -> dict[str, Any]:
    """Return the options of an existing compressor, as :func:`check_options` does."""
    return {"inner": sc.inner, **_tree_options(sc.options)}


def _tree_options(options: CompressorOptions) -> dict[str, Any]:
    """Return the options a tree forwards (:data:`COMPRESSOR_OPTIONS`) of ``options``."""
    return {name: value for name, value in options.as_dict().items()
            if name in COMPRESSOR_OPTIONS}


_NODE_CHANGES = ("oversampling", "target_error", "error_measure")  # see _node_options


def _node_options(opts: dict[str, Any], *, columns: int) -> dict[str, Any]:
    """Return the options of a tree's leaves and merges (the root gets ``opts`` back).

    Every level of a tree cuts to the rank cap: its nodes keep twice the oversampling.
    An ``"absolute"`` target is spent by the leaves as the ``"mean_l2"`` target
    ``target / sqrt(columns)``: a leaf of ``m_i`` columns spends
    ``share target sqrt(m_i / columns)``, and the merges compose the leaves' bounds as
    ``sqrt(sum b_i^2) <= share target`` (:meth:`streamsvd.engine.bound.Bound.combine`),
    whatever the number of leaves; each leaf spending the whole ``share target`` would
    overspend ``sqrt(L)`` times with ``L`` leaves. ``"mean_l2"`` and ``"relative"``
    budgets compose so already (``sum_i m_i = m``, ``sum_i ||A_i||^2 = ||A||^2``).
    ``columns`` counts every column the target covers (with a resumed store, those
    before the tree's too).
    """
    node = dict(opts, oversampling=TREE_OVERSAMPLING * opts["oversampling"])
    if opts["target_error"] is not None and opts["error_measure"] == "absolute":
        node.update(error_measure="mean_l2",
                    target_error=opts["target_error"] / math.sqrt(columns))
    return node


def default_leaf_columns(columns: int, block: int, *, tasks: int = 1) -> int:
    """Return the default columns per leaf: ten blocks, fewer to give ``tasks`` tasks work.

    Ten blocks per leaf (never fewer than one block, never more than ``columns``), cut down
    to whole blocks so that there are at least ``tasks`` leaves (the tasks the cluster runs
    at once) when the columns allow it.
    """
    columns = max(columns, 1)
    width = min(10 * block, columns)
    if tasks > 1:
        share = block * math.ceil(math.ceil(columns / tasks) / block)
        width = min(width, share)
    return max(block, width)


def leaf_ranges(start: int, stop: int, leaf_columns: int) -> list[tuple[int, int]]:
    """Return the column ranges of the leaves covering ``start:stop``."""
    return [(a, min(a + leaf_columns, stop)) for a in range(start, stop, leaf_columns)]
