"""The one place where user input is checked and normalised.

Every public function passes its array arguments through these helpers, which return
float64 arrays of the expected shape or raise an :mod:`streamsvd.errors` exception whose
message names the argument, states the requirement, shows what was received and says how
to fix it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from streamsvd.errors import InputError, InputTypeError, NonFiniteError, ShapeMismatchError

__all__ = [
    "as_float_array",
    "check_choice",
    "check_finite",
    "check_nonnegative",
    "check_positive_int",
    "check_target",
]


def _describe(x: Any) -> str:
    if isinstance(x, np.ndarray):
        return f"an array of shape {x.shape} and dtype {x.dtype}"
    return f"{type(x).__name__} {x!r}"[:120]


def as_float_array(
    x: Any,
    name: str,
    *,
    ndim: int,
    rows: int | None = None,
    cols: int | None = None,
    allow_empty: bool = True,
    copy: bool = False,
    finite: bool = True,
) -> np.ndarray:
    """Return ``x`` as a finite float64 array of the given number of dimensions.

    Parameters
    ----------
    x : array_like
        The user's argument.
    name : str
        Its name, used in error messages.
    ndim : int
        Required number of dimensions (1 or 2).
    rows, cols : int, optional
        Required sizes of the first and second axes.
    allow_empty : bool
        Whether a zero-sized array is acceptable.
    copy : bool
        Return a copy even when ``x`` is already a float64 array.
    finite : bool
        Check that every entry is finite (False: the caller checks it later, with
        :func:`check_finite` or from a product that propagates NaN and infinities).

    Raises
    ------
    InputError
        When the dtype is complex, non-numeric, or the array is empty and must not be.
    ShapeMismatchError
        When the number of dimensions or a size differs from the requirement.
    NonFiniteError
        When an entry is NaN or infinite.
    """
    if hasattr(x, "toarray") and not isinstance(x, np.ndarray):
        raise InputError(
            f"`{name}` must be a dense array; got a sparse matrix of shape "
            f"{getattr(x, 'shape', '?')}. Convert it with `.toarray()`."
        )
    arr = np.asarray(x)
    if arr.dtype.kind == "O":
        try:
            arr = arr.astype(np.float64)
        except (TypeError, ValueError) as err:
            raise InputTypeError(
                f"`{name}` must hold real numbers; got an object array with an entry that is "
                f"not a number ({err}). Convert it with `np.asarray(..., dtype=float)`."
            ) from None
    if arr.dtype.kind == "c":
        raise InputError(
            f"`{name}` must be real; got complex dtype {arr.dtype} (Complex data not "
            "supported). Pass the real and imaginary parts as separate snapshots."
        )
    if arr.dtype.kind not in "biuf":
        raise InputError(
            f"`{name}` must hold real numbers; got dtype {arr.dtype}. "
            "Convert it with `np.asarray(..., dtype=float)`."
        )
    if arr.ndim != ndim:
        hint = " Reshape your data: pass a 2-D array." if ndim == 2 else ""
        raise ShapeMismatchError(
            f"`{name}` must be {ndim}-D; got {arr.ndim}-D of shape {arr.shape}.{hint}"
        )
    if rows is not None and arr.shape[0] != rows:
        raise ShapeMismatchError(
            f"`{name}` must have {rows} rows; got {arr.shape[0]} (shape {arr.shape}). "
            "Pass snapshots as columns."
        )
    if cols is not None and ndim == 2 and arr.shape[1] != cols:
        raise ShapeMismatchError(
            f"`{name}` must have {cols} columns; got {arr.shape[1]} (shape {arr.shape})."
        )
    if not allow_empty and arr.size == 0:
        raise InputError(f"`{name}` must not be empty; got shape {arr.shape}.")
    out = np.array(arr, dtype=np.float64, copy=True) if copy else arr.astype(np.float64, copy=False)
    if finite:
        check_finite(out, name)
    return out


def first_non_finite(block: np.ndarray) -> tuple[int, int, int] | None:
    """Return ``(row, column, count)`` of a 2-D block's first NaN or infinite entry.

    The first in column order (the earliest snapshot), and how many there are; None
    when every entry is finite.
    """
    finite = np.isfinite(block)
    if finite.all():
        return None
    col = int(np.flatnonzero(~finite.all(axis=0))[0])
    row = int(np.flatnonzero(~finite[:, col])[0])
    return row, col, int(block.size - np.count_nonzero(finite))


def check_finite(arr: np.ndarray, name: str) -> None:
    """Raise :class:`NonFiniteError` if ``arr`` holds NaN or infinite entries.

    The sum decides first (one pass, nothing allocated): NaN and infinities propagate
    through it, so a finite sum proves every entry finite; a sum that is not (a bad
    entry, or an overflow of finite ones) sends to the entry-by-entry check.
    """
    if not arr.size:
        return
    with np.errstate(over="ignore", invalid="ignore"):
        total = np.sum(arr)
    if not np.isfinite(total) and not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))
        first = tuple(int(i) for i in bad[0])
        raise NonFiniteError(
            f"`{name}` must be finite; got {len(bad)} NaN or infinite entries, the first at "
            f"index {first} ({arr[first]!r}). Remove or repair them before calling."
        )


def check_choice(value: Any, name: str, choices: tuple[str, ...]) -> str:
    """Return ``value`` if it is one of ``choices``; raise :class:`InputError` otherwise."""
    if value not in choices:
        raise InputError(f"`{name}` must be one of {choices}; got {_describe(value)}.")
    return str(value)


def check_nonnegative(value: Any, name: str) -> float:
    """Return ``value`` as a finite float >= 0; raise :class:`InputError` otherwise."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise InputError(f"`{name}` must be a number >= 0; got {_describe(value)}.") from None
    if not np.isfinite(out) or out < 0:
        raise InputError(f"`{name}` must be a finite number >= 0; got {value!r}.")
    return out


def check_nonnegative_int(value: Any, name: str) -> int:
    """Return ``value`` as an int >= 0; raise otherwise."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise InputError(f"`{name}` must be an integer >= 0; got {_describe(value)}.")
    return int(value)


def check_positive_int(value: Any, name: str, *, allow_none: bool = False) -> int | None:
    """Return ``value`` as an int >= 1 (or None when allowed); raise otherwise."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        allowed = "an integer >= 1" + (" or None" if allow_none else "")
        raise InputError(f"`{name}` must be {allowed}; got {_describe(value)}.")
    return int(value)


def check_forget(value: Any) -> float:
    """Return the forgetting factor as a float in (0, 1]; raise :class:`InputError` otherwise."""
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = float("nan")
    if isinstance(value, bool) or not 0.0 < out <= 1.0:
        raise InputError(
            f"`forget` must be a number in (0, 1] (1 forgets nothing); got {_describe(value)}."
        )
    return out


def check_target(
    target_error: Any, error_measure: Any, streaming_share: Any, *, eps: float,
    rtol: float | None,
) -> tuple[float | None, str, float]:
    """Validate the target-error options; return them normalised.

    A target is a finite number > 0; it is not combined with ``eps`` or ``rtol``, whose
    cuts could break it.
    """
    measure = check_choice(error_measure, "error_measure", ("relative", "mean_l2", "absolute"))
    try:
        share = float(streaming_share)
    except (TypeError, ValueError):
        share = float("nan")
    if not 0.0 < share <= 1.0:
        raise InputError(
            f"`streaming_share` must be a number in (0, 1]; got {_describe(streaming_share)}."
        )
    if target_error is None:
        return None, measure, share
    target = check_nonnegative(target_error, "target_error")
    if target == 0.0:
        raise InputError(
            "`target_error` must be > 0 (omit it to keep every term); got 0.0."
        )
    if eps > 0 or rtol is not None:
        given = f"eps={eps!r}" if eps > 0 else f"rtol={rtol!r}"
        raise InputError(
            f"`target_error` and `{given.split('=')[0]}` cannot be combined: the cuts of "
            f"`{given.split('=')[0]}` ({given}) could break the target {target!r}. Pass one "
            "of them."
        )
    return target, measure, share
