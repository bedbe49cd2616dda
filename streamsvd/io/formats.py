"""Snapshot files: the one dispatch on a file's format, for every reader.

A snapshot matrix on disk is a ``.npy`` file (memory-mapped), an HDF5 dataset (``.h5``,
``.hdf5``, ``.he5``, with a dataset name, optional when the file holds one dataset) or a
zarr array (a ``.zarr`` path or a zarr directory, with an array name, optional when the
group holds one array); a zarr array may also sit at a URL (:func:`open_zarr_url`).
:func:`open_file` decides the format of a path once and opens it as an
:class:`OpenedFile`, from whose :attr:`OpenedFile.data` the one block reader
(:meth:`streamsvd.io.sources.Source.blocks`) reads, in every mode: the command line, the
tall mode, and each leaf of the tree mode, which opens the path again where it runs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from streamsvd.errors import InputError, SourceError
from streamsvd.storage import ObjectStorage, open_storage

__all__ = [
    "HDF5_SUFFIXES",
    "NPY_SUFFIXES",
    "ZARR_SUFFIXES",
    "OpenedFile",
    "no_dataset",
    "open_file",
    "open_zarr_url",
]

HDF5_SUFFIXES = (".h5", ".hdf5", ".he5")
NPY_SUFFIXES = (".npy",)
ZARR_SUFFIXES = (".zarr",)


@dataclass(frozen=True)
class OpenedFile:
    """A snapshot matrix opened from a local file (see :func:`open_file`).

    Attributes
    ----------
    format : {"npy", "hdf5", "zarr"}
        The file's format.
    path : pathlib.Path
        The file (or zarr directory).
    data : numpy.memmap, h5py.Dataset or zarr.Array
        The matrix, sliced as ``data[:, a:b]``.
    description : str
        How the matrix is named in messages (``"HDF5 dataset '/u' in run.h5"``).
    close : callable
        Releases what was opened (the HDF5 file); idempotent.
    """

    format: str
    path: Path
    data: Any
    description: str
    close: Callable[[], None]


def _nothing_to_close() -> None:
    """Close nothing: a memory map or a zarr array holds no open file."""


def open_file(path: Path, dataset: str | None) -> OpenedFile:
    """Open the snapshot matrix in the file ``path``, whichever its format.

    Parameters
    ----------
    path : pathlib.Path
        A ``.npy`` file, an HDF5 file, or a zarr array or group.
    dataset : str or None
        The dataset of an HDF5 file or the array of a zarr group; None when the file
        holds exactly one (refused for a ``.npy`` file or a zarr array).

    Returns
    -------
    OpenedFile
        Close it when done.

    Raises
    ------
    SourceError
        The file does not exist, cannot be opened, or has no such dataset.
    InputError
        The format is unknown, or ``dataset`` is needed or misplaced.
    """
    if not path.exists():
        raise SourceError(
            f"`source` {path} does not exist. Check the path (relative paths start in "
            f"{Path.cwd()})."
        )
    suffix = path.suffix.lower()
    if suffix in NPY_SUFFIXES:
        no_dataset(dataset, f"the .npy file {path}")
        try:
            arr = np.load(path, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty file
            raise SourceError(
                f"`source` {path} cannot be read as a .npy file ({exc}). Check the file."
            ) from exc
        return OpenedFile("npy", path, arr, f".npy file {path}", _nothing_to_close)
    if suffix in HDF5_SUFFIXES:
        return _open_hdf5(path, dataset)
    if suffix in ZARR_SUFFIXES or (
        path.is_dir() and any((path / m).exists() for m in ("zarr.json", ".zarray", ".zgroup"))
    ):
        node, description = _zarr_node(str(path), dataset, path)
        return OpenedFile("zarr", path, node, description, _nothing_to_close)
    if path.is_dir():
        raise InputError(
            f"`source` {path} is a directory but not a zarr array or group (no zarr.json, "
            ".zarray or .zgroup in it). Pass the path of the zarr array or of a file."
        )
    raise InputError(
        f"`source` {path} has an unknown extension {path.suffix!r}; expected .npy, "
        f"{', '.join(HDF5_SUFFIXES)}, .zarr or a zarr directory. Convert the data to one "
        "of these formats (if it already is one, give the file its extension)."
    )


def _open_hdf5(path: Path, dataset: str | None) -> OpenedFile:
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise SourceError(
            f"`source` {path} cannot be opened as an HDF5 file ({exc}). Check the file."
        ) from exc
    try:
        names: list[str] = []

        def visit(name: str, obj: Any) -> None:
            if isinstance(obj, h5py.Dataset):
                names.append(name)

        f.visititems(visit)
        name = _choose(names, dataset, "dataset", f"HDF5 file {path}")
        return OpenedFile("hdf5", path, f[name], f"HDF5 dataset '/{name}' in {path}", f.close)
    except BaseException:
        f.close()
        raise


def open_zarr_url(
    url: str, *, dataset: str | None = None, storage_options: Any = None
) -> Any:
    """Open the zarr array (or the array ``dataset`` of the group) at an fsspec URL.

    The array pickles with its URL and ``storage_options``, so dask workers reopen it
    where they run.

    Parameters
    ----------
    url : str
        ``s3://bucket/run.zarr`` or any fsspec URL of a zarr v2/v3 array or group.
    dataset : str, optional
        Name of the array in a group; may be omitted when there is exactly one.
    storage_options : dict, optional
        Options of the fsspec file system (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...).

    Returns
    -------
    zarr.Array

    Raises
    ------
    SourceError
        Nothing is stored at the URL, or it is not a zarr array or group.
    InputError
        The URL names a ``.npy`` or HDF5 file, or ``dataset`` is needed or misplaced.
    OptionalDependencyError
        The URL needs a package of the ``s3`` extra that is not installed.
    """
    storage = open_storage(url, storage_options=storage_options, argument="source")
    if not isinstance(storage, ObjectStorage):  # file://
        return _zarr_node(str(storage.root), dataset, storage.url)[0]
    suffix = Path(url.rstrip("/")).suffix.lower()
    if suffix in NPY_SUFFIXES + HDF5_SUFFIXES:
        raise InputError(
            f"`source` {url} is a {suffix} file at a URL; .npy and HDF5 sources are read "
            "from local paths only. Copy it to a local path, or convert it to a zarr array."
        )
    if not storage.exists():
        raise SourceError(
            f"`source` {url} does not exist (no object under that prefix). Check the URL, "
            "the credentials (AWS_* variables, `storage_options`) and the endpoint."
        )
    return _zarr_node(storage.zarr_store(read_only=True), dataset, url)[0]


def _zarr_node(store: Any, dataset: str | None, path: Any) -> tuple[Any, str]:
    """Open the zarr array to read in ``store``; return it and its description."""
    import zarr

    try:
        node = zarr.open(store=store, mode="r")
    except (OSError, ValueError, KeyError) as exc:
        raise SourceError(
            f"`source` {path} cannot be opened as a zarr array or group ({exc}). Check the path."
        ) from exc
    if isinstance(node, zarr.Array):
        no_dataset(dataset, f"the zarr array {path}")
        return node, f"zarr array {path}"
    names = sorted(
        name for name, member in node.members(max_depth=None) if isinstance(member, zarr.Array)
    )
    name = _choose(names, dataset, "array", f"zarr group {path}")
    return node[name], f"zarr array '{name}' in {path}"


def _choose(names: list[str], dataset: str | None, kind: str, where: str) -> str:
    """Pick the dataset name to open among ``names``."""
    if dataset is not None:
        wanted = dataset.strip("/")
        if wanted not in names:
            raise SourceError(
                f"`dataset` {dataset!r} is not in {where}; it holds the {kind}s "
                f"{names}. Pass one of these names."
            )
        return wanted
    if len(names) == 1:
        return names[0]
    if not names:
        raise SourceError(f"`source` {where} holds no {kind}. Pass a file holding the snapshots.")
    raise InputError(
        f"`dataset` must be given because {where} holds {len(names)} {kind}s: {names}. "
        f"Pass dataset=<one of them>."
    )


def no_dataset(dataset: Any, what: str) -> None:
    """Refuse ``dataset`` for a source that has none (``what`` names the source)."""
    if dataset is not None:
        raise InputError(
            f"`dataset` only applies to HDF5 files and zarr groups; got dataset="
            f"{dataset!r} for {what}. Drop the `dataset` argument."
        )
