"""The basis out of core: panels chunked by rows, written once each, used by dask."""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "DEFAULT_CHUNK_ROWS": "backend",
    "KIND": "backend",
    "PanelBackend": "backend",
    "PanelBasis": "basis",
    "PanelFiles": "files",
    "LazyBlock": "lazy",
    "RawArray": "raw_array",
    "RowView": "raw_array",
    "RowChunks": "row_chunks",
    "Region": "zarr_io",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
