"""scikit-learn estimators over the stream: :class:`StreamingSVD`, :class:`StreamingDMD`."""

from streamsvd._util.lazy import lazy_exports

# public name -> the submodule that defines it (imported on first access)
_EXPORTS = {
    "NotFittedError": "estimator",
    "StreamingSVD": "estimator",
    "StreamingDMD": "dmd",
}
__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
