"""Helpers over numpy arrays and the process: validation, scaling, slabs, threads, the allocator, dask scheduling.
"""

