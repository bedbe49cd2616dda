"""Forwarding a facade's attributes to the parts it holds.

:class:`~streamsvd.StreamCompressor` is composed of parts (a
:class:`~streamsvd.stream.lifecycle.Lifecycle`, an :class:`~streamsvd.stream.updates.Updates`,
a :class:`~streamsvd.stream.window.Window`, an
:class:`~streamsvd.stream.view.ExpansionView`), each held as an attribute. A public name
that is a part's is declared in the facade's body as ``rank = Forward[int]("_view",
ExpansionView)``: one line, typed for type checkers, and at run time the part's own
attribute (a method comes bound to the part, so ``help(sc.absorb)`` reads the part's
docstring and signature).
"""

from __future__ import annotations

from typing import Any, Generic, TypeVar, overload

__all__ = ["Forward"]

T = TypeVar("T")


class Forward(Generic[T]):
    """A facade attribute that reads the attribute of the same name of one of its parts.

    Parameters
    ----------
    part : str
        Name of the facade's instance attribute that holds the part.
    owner : type
        The part's class (its attribute of the same name gives the docstring).
    """

    def __init__(self, part: str, owner: type) -> None:
        self.part, self.owner, self.name = part, owner, ""

    def __set_name__(self, cls: type, name: str) -> None:
        self.name = name
        self.__doc__ = getattr(self.owner, name).__doc__

    @overload
    def __get__(self, instance: None, cls: type) -> Forward[T]: ...

    @overload
    def __get__(self, instance: object, cls: type) -> T: ...

    def __get__(self, instance: object, cls: type) -> Any:
        if instance is None:
            return self
        return getattr(getattr(instance, self.part), self.name)
