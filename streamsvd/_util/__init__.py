"""Helpers over numpy arrays and the process.

Validation, scaling, slabs, threads, the allocator, dask scheduling.
"""

