"""The version of streamsvd (read by the package and by the store's format)."""

__version__ = "0.1.0"
