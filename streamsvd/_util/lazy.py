"""Lazy re-exports for a package's face: public names imported on first access."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports", "lazy_module"]


def lazy_exports(
    package: str, table: Mapping[str, str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Return the ``__getattr__`` and ``__dir__`` of a package that re-exports names lazily.

    ``table`` maps each public name to the submodule (relative to ``package``) that
    defines it; the submodule is imported when the name is first looked up (PEP 562), so
    that a face never imports its layer's modules ahead of the ones that need them, and
    no import circle runs through it.
    """

    def __getattr__(name: str) -> Any:
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # later look-ups do not come here
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(table))

    return __getattr__, __dir__


class _LazyModule:
    """A module imported when one of its attributes is first looked up (see :func:`lazy_module`)."""

    def __init__(self, name: str, absent: Mapping[str, Any]) -> None:
        self._name = name
        self._absent = absent

    def __getattr__(self, attr: str) -> Any:
        if self._name not in sys.modules and attr in self._absent:
            return self._absent[attr]
        value = getattr(importlib.import_module(self._name), attr)
        if attr not in self._absent:
            setattr(self, attr, value)  # later look-ups do not come here
        return value

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


def lazy_module(name: str, *, absent: Mapping[str, Any] | None = None) -> Any:
    """Return a stand-in for module ``name`` that imports it at its first attribute look-up.

    ``absent`` maps attribute names to what they are while the module is not imported
    yet (by anyone): ``{"issparse": lambda x: False}`` for ``scipy.sparse``, since no
    sparse matrix exists before its module is imported. It lets a module name a heavy
    dependency at its top (``sp = lazy_module("scipy.sparse")``) and pay for it only in
    the calls that use it.
    """
    return _LazyModule(name, dict(absent or {}))
