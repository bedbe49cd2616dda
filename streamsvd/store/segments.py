"""The arrays of a basis store as lists of immutable segments: what a commit writes.

Every array a generation of a :class:`~streamsvd.store.BasisStore` holds is recorded as a
list of *segments* along one axis (rows, ``axis=0``, or columns, ``axis=1``); a segment
is a contiguous block of the array, written once into the *pack* of the generation that
created it (one flat zarr array per generation) and never modified. A later generation
refers to the segments of earlier ones that it keeps, so a commit writes only what
changed since the current generation:

* an array committed whole (``arrays=`` of :meth:`~streamsvd.store.BasisStore.commit`)
  is one new segment;
* an :class:`Appended` array keeps the segments of the current generation that lie in
  its first ``unchanged`` rows (columns) and writes the rest as one new segment.

Padding. A segment may be narrower, across its axis, than the array: the rest is zero.
This is how the right factor ``V0`` of a compressor gains columns that are zero in every
old row without rewriting the old rows.

Merging. So that the number of segments stays small, a new segment absorbs the last
kept segment while that one is smaller than twice the new one, unless the merged
segment would exceed ``seal_bytes`` (the store's ``chunk_bytes``): the sizes of the
segments then at least double from the newest to the oldest up to ``seal_bytes``, a list
holds ``O(log2(seal_bytes / segment))`` segments besides the sealed ones, and each entry
is rewritten ``O(log2)`` times over a stream. A commit therefore writes at most about
``seal_bytes`` plus what changed, whatever the size of the array; the merged rows are
taken from the data passed (in memory), never read back from the store.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from streamsvd._util.validation import check_finite
from streamsvd.errors import InputError

__all__ = ["Appended", "Piece", "assemble", "digest", "plan_appended", "plan_whole"]


@dataclass(frozen=True)
class Appended:
    """An array committed by appending to the same array of the current generation.

    Parameters
    ----------
    data : array_like, 1-D or 2-D
        The whole array of the new generation (a view is fine: only the part written is
        read, converted and checked).
    axis : {0, 1}
        Axis along which the array grows (rows or columns).
    unchanged : int
        Number of leading rows (``axis=0``) or columns (``axis=1``) of ``data`` equal
        to those of the array of the same name in the current generation, whose
        segments are kept; across ``axis`` ``data`` may be wider than those segments
        were, and is then zero there. ``0`` writes the array anew.
    """

    data: Any
    axis: int = 0
    unchanged: int = 0


@dataclass
class Piece:
    """A new segment to be written into the pack: its record (offset filled by :func:`pack`)."""

    segment: dict[str, Any]
    data: np.ndarray


def digest(arr: np.ndarray) -> str:
    """SHA-256 of the little-endian bytes of ``arr`` in C order."""
    data = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
    return hashlib.sha256(data.reshape(-1).view(np.uint8).data).hexdigest()


def _segment(generation: int, data: np.ndarray) -> Piece:
    return Piece(
        {"generation": generation, "offset": 0, "shape": list(data.shape)}, data
    )


def _convert(data: Any, dtype: np.dtype, label: str) -> np.ndarray:
    out = np.ascontiguousarray(data, dtype=dtype)
    check_finite(out, label)
    return out


def plan_whole(
    arr: np.ndarray, *, generation: int
) -> tuple[dict[str, Any], list[Piece]]:
    """Record and new segment of an array committed whole (already converted)."""
    record: dict[str, Any] = {
        "shape": list(arr.shape), "dtype": arr.dtype.name, "axis": 0, "segments": [],
    }
    if arr.size or (arr.ndim and arr.shape[0]):
        piece = _segment(generation, arr)
        record["segments"].append(piece.segment)
        return record, [piece]
    return record, []


def _extent(segment: dict[str, Any], axis: int) -> int:
    return int(segment["shape"][axis])


def _nbytes(shape: list[int] | tuple[int, ...], itemsize: int) -> int:
    return int(np.prod(shape, dtype=np.int64)) * itemsize


def plan_appended(
    name: str,
    value: Appended,
    current: dict[str, Any] | None,
    *,
    generation: int,
    dtype: np.dtype,
    seal_bytes: int,
) -> tuple[dict[str, Any], list[Piece]]:
    """Return the record of an appended array and its new segment (see the module doc).

    ``current`` is the record of the array of the same name in the current generation
    (None if it has none).
    """
    label = f"appended['{name}']"
    if not isinstance(value, Appended):
        raise InputError(
            f"`{label}` must be an Appended(data, axis=..., unchanged=...); got "
            f"{type(value).__name__}."
        )
    data = value.data if isinstance(value.data, np.ndarray) else np.asarray(value.data)
    if data.dtype.kind not in "biuf" or data.ndim not in (1, 2):
        raise InputError(
            f"`{label}.data` must be a real 1-D or 2-D array; got dtype {data.dtype} and "
            f"shape {data.shape}."
        )
    axis = value.axis
    if axis not in (0, 1) or axis >= data.ndim:
        raise InputError(
            f"`{label}.axis` must be 0 or (for a 2-D array) 1; got {axis!r} for shape "
            f"{data.shape}."
        )
    total = int(data.shape[axis])
    unchanged = value.unchanged
    if not isinstance(unchanged, int | np.integer) or not 0 <= unchanged <= total:
        raise InputError(
            f"`{label}.unchanged` must be an integer in [0, {total}]; got {unchanged!r}."
        )
    other = 1 - axis if data.ndim == 2 else None
    kept: list[dict[str, Any]] = []
    start = 0
    if unchanged:
        if current is None or current.get("axis") != axis or len(current["shape"]) != data.ndim:
            raise InputError(
                f"`{label}.unchanged` is {unchanged}, but the current generation holds no "
                f"array {name!r} grown along axis {axis}; pass unchanged=0."
            )
        if unchanged > current["shape"][axis]:
            raise InputError(
                f"`{label}.unchanged` is {unchanged}, but the current array {name!r} has "
                f"only {current['shape'][axis]} along axis {axis}; pass at most that."
            )
        for seg in current["segments"]:
            e = _extent(seg, axis)
            if start + e > unchanged:
                break
            if other is not None and seg["shape"][other] > data.shape[other]:
                raise InputError(
                    f"`{label}.data` has {data.shape[other]} along axis {other}, fewer "
                    f"than the kept segments of {name!r} ({seg['shape'][other]}); pass "
                    "unchanged=0 to write it anew."
                )
            kept.append(seg)
            start += e
    itemsize = np.dtype(dtype).itemsize
    across = 1 if other is None else int(data.shape[other])

    def range_bytes(a: int) -> int:
        return (total - a) * across * itemsize

    if start < total:
        while kept:
            last = kept[-1]
            e = _extent(last, axis)
            small = _nbytes(last["shape"], itemsize) < 2 * range_bytes(start)
            if not (small and range_bytes(start - e) <= seal_bytes):
                break
            kept.pop()
            start -= e
    record: dict[str, Any] = {
        "shape": list(data.shape), "dtype": np.dtype(dtype).name, "axis": axis,
        "segments": list(kept),
    }
    if start == total:
        return record, []
    part = data[start:] if axis == 0 else data[:, start:]
    piece = _segment(generation, _convert(part, dtype, label))
    record["segments"].append(piece.segment)
    return record, [piece]


def assemble(
    record: dict[str, Any], read: Callable[[dict[str, Any]], np.ndarray]
) -> np.ndarray:
    """Rebuild an array from its record; ``read(segment)`` returns a segment's data.

    ``read`` returns the segment reshaped to its recorded shape, its SHA-256 verified.
    Raises ``ValueError`` when the segments do not tile the recorded shape.
    """
    shape = tuple(int(s) for s in record["shape"])
    axis = int(record["axis"])
    out = np.zeros(shape, dtype=np.dtype(record["dtype"]))
    pos = 0
    for seg in record["segments"]:
        part = read(seg)
        e = part.shape[axis]
        if len(shape) == 1:
            out[pos : pos + e] = part
        elif axis == 0:
            out[pos : pos + e, : part.shape[1]] = part
        else:
            out[: part.shape[0], pos : pos + e] = part
        pos += e
    if pos != (shape[axis] if shape else 0):
        raise ValueError(f"its segments cover {pos} of {shape[axis]} along axis {axis}")
    return out
