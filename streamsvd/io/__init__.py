"""Snapshot sources, read by blocks, and the record of where they came from.

Numpy arrays, ``.npy``, HDF5, zarr and dask arrays; and an inner product read from a file
(:mod:`~streamsvd.io.inner_file`).
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "Source": "sources",
    "open_source": "open",
    "OpenedFile": "formats",
    "open_file": "formats",
    "open_zarr_url": "formats",
    "SourceRecord": "provenance",
    "load_inner": "inner_file",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
