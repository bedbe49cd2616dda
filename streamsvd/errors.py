"""The exception hierarchy of streamsvd.

Every exception raised on purpose by the library derives from :class:`StreamSVDError`
and also from the builtin exception a caller would naturally catch (``ValueError`` for
bad arguments, ``OSError`` for storage problems), as zarr's ``errors.py`` does.
"""

from __future__ import annotations

from typing import Any


class StreamSVDError(Exception):
    """Base class of every error raised on purpose by streamsvd."""


class InputError(StreamSVDError, ValueError):
    """An argument has the wrong type, shape, dtype or value."""


class InputTypeError(InputError, TypeError):
    """An array argument holds entries that are not numbers."""


class SparseInputError(InputError, TypeError):
    """A sparse matrix is passed where only a dense array is accepted."""


class NonFiniteError(InputError):
    """An array argument holds NaN or infinite entries."""


class FloatRangeError(InputError, OverflowError):
    """Data whose expansion (its norm, amplitudes, error bound) lies beyond float64's range.

    Parameters
    ----------
    argument : str
        The argument the update came from, in the words of the call (a quoted name:
        ``"`columns`"``).
    norm : float, optional
        The norm of the expansion before the update, when known.
    """

    def __init__(self, argument: str, norm: float | None = None) -> None:
        before = "" if norm is None else f" (the expansion's norm before it is {norm:.3g})"
        super().__init__(
            f"{argument} would take the expansion beyond the float64 range: its norm, a "
            f"singular value, the error bound or a right vector's entry would exceed "
            f"1.8e308{before}. Scale the snapshots down by a power of two (2**-64, say: "
            f"the left vectors are unchanged and the amplitudes scale with the data, "
            f"exactly). Nothing was changed."
        )
        self.argument = argument
        self.norm = norm

    def naming(self, argument: str, norm: float | None = None) -> FloatRangeError:
        """Return the same error for the argument of an outer call (``source``)."""
        return FloatRangeError(argument, self.norm if norm is None else norm)


class ShapeMismatchError(InputError):
    """An array argument does not have the shape the operation needs."""


class InnerProductMismatchError(InputError):
    """Two objects were built with different inner products."""


class ConvergenceError(StreamSVDError, RuntimeError):
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


class BrokenStateError(StreamSVDError, RuntimeError):
    """A compressor was left unusable by an update that wrote in place and did not complete.

    Only a compressor whose basis compacts in place (the leaves and merges of a tree) can
    be left so; a store it writes keeps its last commit. Raised as well when a basis whose
    Gram was left to measure (:class:`streamsvd.engine.state.State`) is found not positive
    definite, its rounding beyond what its update checked (never observed).
    """


class StoreError(StreamSVDError, OSError):
    """A basis store cannot be read or written."""


class StoreLockedError(StoreError):
    """Another writer holds the lock of a basis store."""


class StoreFormatError(StoreError):
    """A basis store was written in another format version or is corrupt."""


class StoreMismatchError(StoreError, ValueError):
    """A basis store holds a basis of another size, dtype or inner product."""


class OptionalDependencyError(StreamSVDError, ImportError):
    """An optional package (of an extra such as ``s3``) is needed but not installed."""


class SourceError(StreamSVDError, OSError):
    """A snapshot source cannot be opened or read."""
