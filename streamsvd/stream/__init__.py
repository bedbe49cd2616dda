"""The streaming compressor and its parts.

:class:`StreamCompressor`, its options, its lifecycle over a store, its window, its
read-only view, and the one ingestion driver.
"""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "StreamCompressor": "compressor",
    "UpdateRecord": "compressor",
    "summary_of": "summary",
    "CompressorOptions": "options",
    "STREAMING_SHARE": "options",
    "StreamStore": "persistence",
    "open_stream_store": "persistence",
    "IngestResult": "ingest",
    "CommitSchedule": "commits",
    "CommitTracker": "commits",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
