"""Scale-out on dask.

The tree of leaves (:func:`tree_compress`), the tree of tall leaves
(:func:`tall_tree_compress`), the tall mode (:class:`TallCompressor`,
:func:`tall_compress`), and opening (or checking) the compressor a store holds.
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "COMPRESSOR_OPTIONS": "cluster",
    "check_opens": "cluster",
    "check_store": "cluster",
    "compressor_class": "cluster",
    "ingest": "cluster",
    "connect": "cluster",
    "execute": "cluster",
    "open_compressor": "cluster",
    "stored_kind": "cluster",
    "tall_compress": "tall",
    "TallCompressor": "tall",
    "SourceSpec": "spec",
    "tree_compress": "tree",
    "tall_tree_compress": "tall_tree",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
