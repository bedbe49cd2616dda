"""The layout of a basis store: names, documents, and the checks of the root attributes.

Everything here reads; nothing writes. :func:`read_root_attrs` returns the root
attributes of a store after checking them, :func:`check_root_against_pointer` checks
them against the copy the pointer records (so that an edited ``n`` or ``dtype`` is
reported by field). Reading the pointer itself, which names the last readable generation
when it is damaged, is :mod:`streamsvd.store.reading`'s.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, cast

import numpy as np

from streamsvd._util.validation import check_finite, check_positive_int
from streamsvd.errors import InputError, StoreFormatError, StoreMismatchError
from streamsvd.storage import LocalStorage, Storage, remote_errors
from streamsvd.storage.lockfile import LOCK_NAME

FORMAT = "streamsvd-basis"
"""Value of the root attribute ``format`` of every basis store."""

FORMAT_VERSION = 2
"""Version of the store layout written by this package (1: one zarr array per
array and generation, each rewritten whole by every commit; 2: segments in packs)."""

DEFAULT_CHUNK_BYTES = 16 * 2**20
"""Target size in bytes of one (uncompressed) chunk of a stored array."""

POINTER_NAME = "current.json"
LEASE_NAME = "writer.lease"
GENERATIONS = "generations"
MARKER_NAME = "committed.json"
"""Written into a generation after the pointer named it: the generation was committed."""

GEN_RE = re.compile(r"^g(\d{8})$")
NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
DTYPES = ("float32", "float64")
# Errors that zarr, numcodecs and the JSON decoder raise on damaged or missing data.
READ_ERRORS = (RuntimeError, ValueError, KeyError, TypeError, IndexError, OSError)


@dataclass(frozen=True, eq=False)
class StoreState:
    """One committed generation of a basis store, as read back.

    Attributes
    ----------
    generation : int
        Number of the generation (0 for the first commit, which created the store).
    arrays : dict of str to numpy.ndarray
        The committed arrays, read-only, in the store's ``dtype``; their SHA-256 was
        verified.
    attrs : dict
        The attributes committed with them, as JSON decodes them (tuples become lists).
    n : int
        Snapshot size recorded at creation.
    dtype : str
        Floating dtype of the stored arrays (``"float32"`` or ``"float64"``).
    inner_fingerprint : str
        Fingerprint of the inner product the basis is orthonormal in.
    """

    generation: int
    arrays: dict[str, np.ndarray]
    attrs: dict[str, Any]
    n: int
    dtype: str
    inner_fingerprint: str


# --------------------------------------------------------------------------- helpers


def unreadable() -> tuple[type[BaseException], ...]:
    """Return the errors of reading a small document that is missing, damaged or unreachable."""
    return (OSError, ValueError, AttributeError, *remote_errors())


def now() -> str:
    """Return the current UTC time, ISO 8601 to the second."""
    return datetime.now(UTC).isoformat(timespec="seconds")


def library_version() -> str:
    """Return the installed version of streamsvd."""
    try:
        return importlib.metadata.version("streamsvd")
    except importlib.metadata.PackageNotFoundError:
        from streamsvd._version import __version__

        return __version__


def gen_name(k: int) -> str:
    """Directory name of generation ``k``."""
    return f"g{k:08d}"


def gen_key(k: int) -> str:
    """Key of generation ``k`` below the store's root."""
    return f"{GENERATIONS}/{gen_name(k)}"


def named(storage: Storage) -> Path | str:
    """How a store is named: its directory (a Path) or its URL."""
    return storage.root if isinstance(storage, LocalStorage) else storage.url


def lock_key(storage: Storage) -> str:
    """Key of the writer lock (a file locally) or lease (an object store)."""
    return LOCK_NAME if isinstance(storage, LocalStorage) else LEASE_NAME


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def normalise_attrs(attrs: Any) -> dict[str, Any]:
    """Return ``attrs`` as JSON decodes it, or raise :class:`InputError`."""
    if attrs is None:
        return {}
    if not isinstance(attrs, Mapping):
        raise InputError(
            f"`attrs` must be a dict of JSON-able values; got {type(attrs).__name__}. "
            "Pass a dict such as {'n_seen': 100}."
        )
    try:
        text = json.dumps(dict(attrs), default=_json_default)
    except (TypeError, ValueError) as exc:
        raise InputError(
            f"`attrs` must hold only JSON-able values (numbers, strings, lists, dicts, "
            f"None, numpy scalars and arrays); {exc}. Convert the offending value."
        ) from None
    out = json.loads(text)
    if not all(isinstance(key, str) for key in attrs):
        raise InputError("`attrs` must have string keys; got a non-string key. Use str keys.")
    return dict(out)


def attrs_digest(doc: Any) -> str:
    """SHA-256 of a JSON document (keys sorted)."""
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def prepare_arrays(arrays: Any, dtype: np.dtype) -> dict[str, np.ndarray]:
    """Check the arrays of a commit and cast them to the store's dtype."""
    if not isinstance(arrays, Mapping):
        raise InputError(
            f"`arrays` must be a dict mapping names to arrays; got {type(arrays).__name__}. "
            "Pass e.g. {'U': U, 'V': V}."
        )
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise InputError(
                f"`arrays` keys must be identifiers (letters, digits, underscores, not "
                f"starting with a digit); got {name!r}. Rename the array."
            )
        arr = np.asarray(value)
        label = f"arrays['{name}']"
        if arr.dtype.kind not in "biuf":
            raise InputError(
                f"`{label}` must hold real numbers; got dtype {arr.dtype}. "
                "Store real and imaginary parts as separate arrays."
            )
        if arr.ndim not in (1, 2):
            raise InputError(
                f"`{label}` must be 1-D or 2-D; got {arr.ndim}-D of shape {arr.shape}. "
                "Store scalars in `attrs` and reshape higher-dimensional data."
            )
        cast_ = np.ascontiguousarray(arr, dtype=dtype)
        check_finite(cast_, label)
        out[name] = cast_
    return out


def check_dtype(dtype: Any) -> str:
    """Return the name of a storable dtype, or raise :class:`InputError`."""
    try:
        name = np.dtype(dtype).name
    except TypeError:
        name = None
    if name not in DTYPES:
        raise InputError(f"`dtype` must be one of {DTYPES}; got {dtype!r}.")
    return name


def positive_int(value: Any, name: str) -> int:
    """Return ``value`` checked to be an integer >= 1."""
    return cast(int, check_positive_int(value, name))


def check_fingerprint(value: Any) -> str:
    """Return ``value`` checked to be a non-empty string."""
    if not isinstance(value, str) or not value:
        raise InputError(
            f"`inner_fingerprint` must be a non-empty string; got {value!r}. "
            "Pass `inner.fingerprint` of the inner product in use."
        )
    return value


# ------------------------------------------------------------------- documents


def read_generation_doc(storage: Storage, k: int) -> dict[str, Any] | None:
    """Return the attributes of generation ``k`` from its ``zarr.json`` (None if unreadable)."""
    try:
        doc = json.loads(storage.get(f"{gen_key(k)}/zarr.json"))
    except unreadable():
        return None
    attrs = doc.get("attributes") if isinstance(doc, dict) else None
    meta = attrs.get("streamsvd") if isinstance(attrs, dict) else None
    if not isinstance(meta, dict) or not isinstance(meta.get("arrays"), dict):
        return None
    return cast(dict[str, Any], attrs)


def read_marker(storage: Storage, k: int) -> dict[str, Any] | None:
    """Return the pointer recorded in generation ``k`` once it was committed (None if none)."""
    try:
        doc = json.loads(storage.get(f"{gen_key(k)}/{MARKER_NAME}"))
    except unreadable():
        return None
    return doc if isinstance(doc, dict) and doc.get("generation") == k else None


def sources(doc: dict[str, Any]) -> set[int]:
    """Return the generations whose packs hold a segment the generation ``doc`` uses."""
    out = set()
    for info in doc["streamsvd"]["arrays"].values():
        for seg in info.get("segments", ()):
            out.add(int(seg["generation"]))
    return out


def generations(storage: Storage) -> list[int]:
    """Numbers of the generation directories present, ascending."""
    out = []
    for entry in storage.list(GENERATIONS):
        m = GEN_RE.match(entry)
        if m:
            out.append(int(m.group(1)))
    return sorted(out)


def committed_generations(storage: Storage) -> list[int]:
    """Return the generations that were committed: every one above 0, and 0 once marked.

    Generation 0 is written by the creation, whose pointer switch may not have happened;
    its commit record (written after that switch) tells.
    """
    return [k for k in generations(storage) if k > 0 or read_marker(storage, k) is not None]


# ------------------------------------------------------------------------- root

ROOT_FIELDS = ("format", "format_version", "n", "dtype", "inner_fingerprint", "chunk_bytes")


def read_root_attrs(storage: Storage) -> dict[str, Any]:
    """Read and check the root attributes of the store in ``storage``."""
    path = named(storage)
    meta = f"{path}/zarr.json"
    if not storage.exists():
        raise StoreFormatError(
            f"`path` must be an existing basis store; {path} does not exist. "
            "Create one with `BasisStore.create(path, n=..., inner_fingerprint=...)`."
        )
    try:
        doc = json.loads(storage.get("zarr.json"))
    except FileNotFoundError:
        raise StoreFormatError(
            f"`path` must be a basis store (a zarr v3 group); {path} has no zarr.json. "
            "Pass the directory given to `BasisStore.create`."
        ) from None
    except (OSError, ValueError) as exc:
        raise StoreFormatError(
            f"`path` must be a basis store; {meta} cannot be read ({exc}). "
            "The store is damaged: restore it from a copy."
        ) from exc
    attrs = doc.get("attributes") if isinstance(doc, dict) else None
    if not isinstance(attrs, dict) or doc.get("zarr_format") != 3 or attrs.get("format") != FORMAT:
        found = attrs.get("format") if isinstance(attrs, dict) else None
        raise StoreFormatError(
            f"`path` must be a basis store (zarr v3 group with format {FORMAT!r}); "
            f"{path} has format {found!r}. Pass the directory given to `BasisStore.create`."
        )
    version = attrs.get("format_version")
    if version != FORMAT_VERSION:
        raise StoreFormatError(
            f"`path` {path} holds a basis store of format version {version!r}; this "
            f"version of streamsvd reads format version {FORMAT_VERSION}. Open it with the "
            "streamsvd release that wrote it, or export it and create a new store."
        )
    checks = (
        ("n", lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 1),
        ("dtype", lambda v: v in DTYPES),
        ("inner_fingerprint", lambda v: isinstance(v, str) and bool(v)),
    )
    for key, ok in checks:
        if not ok(attrs.get(key)):
            raise StoreFormatError(
                f"`path` {path} is a damaged basis store: root attribute {key!r} in {meta} "
                f"is {attrs.get(key)!r}. Restore the store from a copy."
            )
    return attrs


def check_root_against_pointer(
    storage: Storage, attrs: dict[str, Any], pointer: dict[str, Any]
) -> None:
    """Raise :class:`StoreFormatError` naming a root attribute that differs from the pointer's copy.

    A pointer written before pointers kept that copy is not checked.
    """
    recorded = pointer.get("root")
    if not isinstance(recorded, dict):
        return
    path = named(storage)
    for key, value in recorded.items():
        if attrs.get(key) != value:
            raise StoreFormatError(
                f"`path` {path} is damaged: root attribute {key!r} in {path}/zarr.json is "
                f"{attrs.get(key)!r}, but the store was created with {value!r} (recorded "
                f"in {POINTER_NAME}). Restore {path}/zarr.json from a copy, or set "
                f"{key!r} back to {value!r}."
            )


def root_record(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """Return the root attributes a pointer records (checked on every open)."""
    return {key: attrs[key] for key in ROOT_FIELDS if key in attrs}


def expectations(n: Any, dtype: Any, inner_fingerprint: Any) -> dict[str, Any]:
    """Check what a caller expects of a store (None: not checked) and normalise it."""
    return {
        "n": check_positive_int(n, "n", allow_none=True),
        "dtype": None if dtype is None else check_dtype(dtype),
        "inner_fingerprint": None if inner_fingerprint is None
        else check_fingerprint(inner_fingerprint),
    }


def check_expected(storage: Storage, attrs: dict[str, Any], want: dict[str, Any]) -> None:
    """Raise :class:`StoreMismatchError` if ``n``, ``dtype`` or ``inner_fingerprint`` differ."""
    for key, value in want.items():
        if value is not None and attrs[key] != value:
            raise StoreMismatchError(
                f"`{key}` must match the store {named(storage)}: expected {value!r}, "
                f"found {attrs[key]!r}. Open the store that belongs to this problem, "
                "or create a new one."
            )
