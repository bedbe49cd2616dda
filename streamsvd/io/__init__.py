"""Snapshot sources, read by blocks, and the record of where they came from.

Numpy arrays, ``.npy``, HDF5, zarr and dask arrays.
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
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
