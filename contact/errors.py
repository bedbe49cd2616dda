"""The exception hierarchy of :mod:`contact`.

Every exception raised on purpose by the package derives from :class:`ContactError` and
also from the builtin exception a caller would naturally catch (``ValueError`` for a bad
argument, ``RuntimeError`` for an iteration that did not converge).
"""

from __future__ import annotations

from typing import Any

__all__ = ["ContactError", "ConvergenceError", "ProblemError", "SolverOptionError"]


class ContactError(Exception):
    """Base class of every error raised on purpose by :mod:`contact`."""


class ProblemError(ContactError, ValueError):
    """A problem definition (mesh, operators, loading) is inconsistent."""


class SolverOptionError(ContactError, ValueError):
    """A solver option has the wrong type or value."""


class ConvergenceError(ContactError, RuntimeError):
    """An iteration stopped before its convergence test was met.

    Parameters
    ----------
    message : str
        What did not converge and why.
    result : object
        The partial result reached when the iteration stopped.
    """

    def __init__(self, message: str, result: Any) -> None:
        super().__init__(message)
        self.result = result
