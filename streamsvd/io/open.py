"""Opening a snapshot matrix: :func:`open_source` wraps what it is given in a Source.

In-memory arrays, ``.npy``/HDF5/zarr paths, zarr URLs, and open h5py datasets, zarr and
dask arrays; files and URLs are opened by :mod:`streamsvd.io.formats`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from streamsvd.errors import InputError
from streamsvd.io.formats import no_dataset, open_file, open_zarr_url
from streamsvd.io.sources import Source
from streamsvd.storage import is_url

__all__ = ["open_source"]


def _is_dask_array(obj: Any) -> bool:
    module = type(obj).__module__ or ""
    if not module.startswith("dask"):
        return False
    import dask.array as da

    return isinstance(obj, da.Array)


def _is_h5py_dataset(obj: Any) -> bool:
    if not (type(obj).__module__ or "").startswith("h5py"):
        return False
    import h5py

    return isinstance(obj, h5py.Dataset)


def _is_zarr_array(obj: Any) -> bool:
    if not (type(obj).__module__ or "").startswith("zarr"):
        return False
    import zarr

    return isinstance(obj, zarr.Array)


def open_source(
    obj: Any, *, dataset: str | None = None, storage_options: Any = None
) -> Source:
    """Wrap a snapshot matrix (columns are snapshots) in a :class:`Source`.

    Parameters
    ----------
    obj : array_like, str, os.PathLike, h5py.Dataset, zarr.Array, dask array or Source
        A real ``n x m`` matrix: an in-memory array, the path of a ``.npy`` file
        (memory-mapped), of an HDF5 file (``.h5``, ``.hdf5``), of a zarr array or group
        (a ``.zarr`` path or a zarr directory), or an open h5py dataset, zarr array or
        dask array, or the URL of a zarr array or group (``s3://bucket/run.zarr``). A
        :class:`Source` is returned as is.
    dataset : str, optional
        Name of the dataset in an HDF5 file or of the array in a zarr group; may be
        omitted when there is exactly one.
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...); not accepted with anything else.

    Returns
    -------
    Source
        Close it (or use it as a context manager) to release a file it opened.

    Raises
    ------
    SourceError
        When the file does not exist, cannot be opened, or has no such dataset.
    InputError
        When the extension is unknown, ``dataset`` is needed or misplaced, or the data
        is not a real 2-D matrix.
    """
    if dataset is not None and not isinstance(dataset, str):
        raise InputError(f"`dataset` must be a str naming a dataset; got {dataset!r}.")
    if is_url(obj):
        arr = open_zarr_url(obj, dataset=dataset, storage_options=storage_options)
        name = f" '{dataset.strip('/')}'" if dataset else ""
        return Source(arr, f"zarr array{name} at {obj}")
    if storage_options is not None:
        raise InputError(
            f"`storage_options` only apply to a URL source (s3://..., file://...); got "
            f"{storage_options!r} with a {type(obj).__name__}. Drop them."
        )
    if isinstance(obj, Source):
        no_dataset(dataset, "a Source")
        return obj
    if isinstance(obj, str | os.PathLike):
        opened = open_file(Path(obj), dataset)
        return Source(opened.data, opened.description, on_close=opened.close)
    if _is_dask_array(obj):
        no_dataset(dataset, "a dask array")
        return Source(obj, f"dask array of shape {obj.shape}", compute=True)
    if _is_h5py_dataset(obj):
        no_dataset(dataset, "an h5py dataset")
        return Source(obj, f"HDF5 dataset '{obj.name}' in {obj.file.filename}")
    if _is_zarr_array(obj):
        no_dataset(dataset, "a zarr array")
        return Source(obj, f"zarr array {obj.store_path}")
    no_dataset(dataset, f"a {type(obj).__name__}")
    if hasattr(obj, "toarray") and not isinstance(obj, np.ndarray):
        raise InputError(
            f"`source` must be a dense array; got a sparse matrix of shape "
            f"{getattr(obj, 'shape', '?')}. Convert it with `.toarray()`."
        )
    try:
        arr = obj if isinstance(obj, np.ndarray) else np.asarray(obj)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"`source` must be a real 2-D array (n x m); {type(obj).__name__} cannot be "
            f"converted to one ({exc}). Pass a numpy array, a file path or a dask array."
        ) from None
    kind = "memmap" if isinstance(arr, np.memmap) else "array"
    return Source(arr, f"numpy {kind} of shape {arr.shape}")
