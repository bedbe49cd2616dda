"""The benchmark suite of streamsvd: ``python -m bench --list`` names its studies.

The scripts of this folder import each other by name (``_common``, ``_suite``, ``brand``):
each runs as ``python bench/NAME.py`` or through ``python -m bench NAME`` (``__main__``).
"""
