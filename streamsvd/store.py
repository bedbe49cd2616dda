"""Versioned, crash-safe persistence of a basis in a zarr v3 group.

A basis store holds a set of named float arrays (the factors ``U``, ``V``, the
amplitudes, ...) and a JSON-able dictionary of attributes (columns absorbed, source
offset, tolerances, discarded energy, error bound, history, ...). Every
:meth:`BasisStore.commit` writes a new *generation* and then switches a pointer to it,
so that a process killed at any instant leaves the last committed generation intact and
readable.

A store lives in a local directory or under a prefix of an object store
(``s3://bucket/basis.zarr``); :mod:`streamsvd.storage` gives both the same small
interface (keys and bytes, conditional writes, a zarr store over the root) and
:mod:`streamsvd.locks` their writer lock or lease. Layout (directory or prefix)::

    <path>/
      zarr.json                  root group; attributes: format, format_version, n,
                                 dtype, inner_fingerprint, created, library_version,
                                 chunk_bytes
      current.json               the pointer: number of the current generation
      writer.lock                present while a writer has the store open (local)
      writer.lease               the same, with an expiry, in an object store
      generations/
        g00000005/               an older generation whose segments are still used
        g00000007/               previous generation (kept)
        g00000008/               current generation: one zarr array, the *pack*
          zarr.json              attributes: {"streamsvd": {...}, "attrs": {...}}
          c.0, c.1, ...          chunks of the pack

Design
------
*Segments.* Every array of a generation is a list of immutable *segments* along one axis
(:mod:`streamsvd.segments`): blocks of rows or columns, each written once into the pack
of the generation that created it, a flat zarr array holding the new segments of that
commit one after the other. The generation's attributes record, for each array, its
shape, dtype, axis and segments (generation, offset in that generation's pack, shape,
SHA-256). An array committed whole is one new segment; an
:class:`~streamsvd.segments.Appended` array keeps the segments of the current generation
that it leaves unchanged and writes only the rest, so a commit costs what changed since
the previous one. Small segments are merged into the new one (never beyond
``chunk_bytes``), so an array has few segments. One pack per commit keeps the number of
files (each ``fsync``-ed) to two plus the chunks.

*Pointer.* The current generation is named by ``current.json``, a small JSON file
written to a temporary file, ``fsync``-ed, moved into place with :func:`os.replace`
(atomic on POSIX) and made durable by an ``fsync`` of the directory. The root
``zarr.json`` attributes are deliberately *not* used as the pointer: zarr's
``LocalStore`` (3.1) does replace files through a temporary file and a rename, so a
reader never sees a torn document, but it never calls ``fsync`` on the file nor on the
directory, so after a power failure the rename may be lost or the file found empty;
atomic replacement is moreover not part of zarr's store contract (other stores do not
offer it). Keeping the pointer apart from zarr metadata also leaves the root metadata
immutable after creation. In an object store, which has no rename, the pointer is one
object overwritten by a single ``PUT`` (atomic: a reader gets the old or the new one
whole), and conditionally: ``If-Match`` the ETag of the pointer this writer last wrote or
read (``If-None-Match: *`` at creation). A writer that lost its lease therefore can never
replace another writer's commit; it gets :class:`~streamsvd.errors.StoreLockedError`,
and so does a commit that finds, before writing anything, that the pointer changed.

*Commit.* A generation's pack is written completely first (with the attributes holding
the caller's attributes and the segment lists), its files and directory are
``fsync``-ed, and only then is the pointer switched. The pointer also records the
SHA-256 of the generation's attributes, so the chain pointer -> attributes -> segment
bytes is verified on every read. After the switch, every generation directory that is
neither the current nor the previous generation nor holds a segment either of them
uses is deleted. A generation left half-written by a killed process is never pointed to
and is deleted by the next writer. Nothing written is ever modified. In an object store
there is nothing to ``fsync``: an object is durable once its ``PUT`` returned, and the
pointer is written after every object of the pack.

*Readers and garbage collection.* A reader (mode ``"r"``) reads the pointer, then the
generation it names. That generation stays until the writer has committed two more
(it is kept as the previous one after the next commit), so a read that takes less than
one commit interval always succeeds; a read that finds its generation deleted, and the
pointer moved, starts again from the new pointer (three attempts). The same holds in a
directory and in an object store: nothing relies on open files staying readable.

*Checksums.* One per segment: its SHA-256, recorded in the attributes, verified on
every read (this also catches a missing chunk, which zarr would read as zeros). The
chunks are compressed with zstd (level 3) without zstd's own frame checksum.

*Chunks.* A pack is chunked in pieces of about ``chunk_bytes`` bytes (16 MiB by
default: large enough for efficient compressed reads, small enough to be written and
verified with bounded memory).

*Lock.* A writer (mode ``"a"``) creates ``writer.lock`` with ``O_CREAT | O_EXCL``; it
holds the writer's pid, host name and start time, and the writer keeps an advisory
``flock`` on it while the store is open. A second writer gets
:class:`~streamsvd.errors.StoreLockedError` naming the holder. A lock whose holder is on
this host and no longer runs (its pid is gone, or its ``flock`` is released, which also
covers a reused pid) is stale and is taken over with a logged warning. In an object
store the lock is a lease, ``writer.lease``, created and renewed by conditional writes,
with an expiry after which a dead writer's lease is taken over
(:class:`streamsvd.locks.Lease`). Readers (mode ``"r"``) never take the lock.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import logging
import os
import re
import weakref
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, cast

import numpy as np
import zarr
import zarr.codecs

from ._validation import check_finite, check_positive_int
from .errors import (
    InputError,
    StoreError,
    StoreFormatError,
    StoreLockedError,
    StoreMismatchError,
)
from .locks import LOCK_NAME
from .segments import Appended, Piece, assemble, digest, pack, plan_appended, plan_whole
from .storage import LocalStorage, Storage, open_storage, remote_errors

__all__ = [
    "DEFAULT_CHUNK_BYTES",
    "FORMAT",
    "FORMAT_VERSION",
    "Appended",
    "BasisStore",
    "StoreState",
    "open_store",
]

logger = logging.getLogger(__name__)

FORMAT = "streamsvd-basis"
"""Value of the root attribute ``format`` of every basis store."""

FORMAT_VERSION = 2
"""Version of the store layout written by this module (1: one zarr array per
array and generation, each rewritten whole by every commit; 2: segments in packs)."""

DEFAULT_CHUNK_BYTES = 16 * 2**20
"""Target size in bytes of one (uncompressed) chunk of a stored array."""

POINTER_NAME = "current.json"
LEASE_NAME = "writer.lease"
GENERATIONS = "generations"

_GEN_RE = re.compile(r"^g(\d{8})$")
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_DTYPES = ("float32", "float64")
# Errors that zarr, numcodecs and the JSON decoder raise on damaged or missing data.
_READ_ERRORS = (RuntimeError, ValueError, KeyError, TypeError, IndexError, OSError)


@dataclass(frozen=True, eq=False)
class StoreState:
    """One committed generation of a basis store, as read back.

    Attributes
    ----------
    generation : int
        Number of the generation (0 for the state written by :meth:`BasisStore.create`).
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


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _library_version() -> str:
    try:
        return importlib.metadata.version("streamsvd")
    except importlib.metadata.PackageNotFoundError:
        import streamsvd

        return str(getattr(streamsvd, "__version__", "unknown"))


def _gen_name(k: int) -> str:
    return f"g{k:08d}"


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _normalise_attrs(attrs: Any) -> dict[str, Any]:
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


def _attrs_digest(doc: Any) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def _prepare_arrays(arrays: Any, dtype: np.dtype) -> dict[str, np.ndarray]:
    if not isinstance(arrays, Mapping):
        raise InputError(
            f"`arrays` must be a dict mapping names to arrays; got {type(arrays).__name__}. "
            "Pass e.g. {'U': U, 'V': V}."
        )
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
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
        cast = np.ascontiguousarray(arr, dtype=dtype)
        check_finite(cast, label)
        out[name] = cast
    return out


def _write_pack(
    zstore: Any, path: str, pack: np.ndarray, doc: dict[str, Any], chunk_bytes: int
) -> None:
    """Create the pack ``path`` (a flat zarr array with attributes ``doc``) and fill it."""
    chunk = max(1, min(chunk_bytes // pack.dtype.itemsize, pack.size))
    arr = zarr.create_array(
        store=zstore,
        name=path,
        shape=pack.shape,
        chunks=(chunk,),
        dtype=pack.dtype,
        compressors=zarr.codecs.ZstdCodec(level=3, checksum=False),
        fill_value=0.0,
        attributes=doc,
        chunk_key_encoding={"name": "default", "separator": "."},
        config={"write_empty_chunks": True},
    )
    if pack.size:
        arr[...] = pack


def _read_generation_doc(storage: Storage, k: int) -> dict[str, Any] | None:
    """Return the attributes of generation ``k`` from its ``zarr.json`` (None if unreadable)."""
    try:
        doc = json.loads(storage.get(f"{GENERATIONS}/{_gen_name(k)}/zarr.json"))
    except (OSError, ValueError):
        return None
    attrs = doc.get("attributes") if isinstance(doc, dict) else None
    meta = attrs.get("streamsvd") if isinstance(attrs, dict) else None
    if not isinstance(meta, dict) or not isinstance(meta.get("arrays"), dict):
        return None
    return cast(dict[str, Any], attrs)


def _sources(doc: dict[str, Any]) -> set[int]:
    """Return the generations whose packs hold a segment the generation ``doc`` uses."""
    out = set()
    for info in doc["streamsvd"]["arrays"].values():
        for seg in info.get("segments", ()):
            out.add(int(seg["generation"]))
    return out


# ----------------------------------------------------------------------- the store


def _check_dtype(dtype: Any) -> str:
    try:
        name = np.dtype(dtype).name
    except TypeError:
        name = None
    if name not in _DTYPES:
        raise InputError(f"`dtype` must be one of {_DTYPES}; got {dtype!r}.")
    return name


def _positive_int(value: Any, name: str) -> int:
    return cast(int, check_positive_int(value, name))


def _check_fingerprint(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise InputError(
            f"`inner_fingerprint` must be a non-empty string; got {value!r}. "
            "Pass `inner.fingerprint` of the inner product in use."
        )
    return value


def _named(storage: Storage) -> Path | str:
    """How a store is named: its directory (a Path) or its URL."""
    return storage.root if isinstance(storage, LocalStorage) else storage.url


def _lock_key(storage: Storage) -> str:
    return LOCK_NAME if isinstance(storage, LocalStorage) else LEASE_NAME


def _read_root_attrs(storage: Storage) -> dict[str, Any]:
    """Read and check the root attributes of the store in ``storage``."""
    path = _named(storage)
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
    for key, kind in (("n", int), ("dtype", str), ("inner_fingerprint", str)):
        if not isinstance(attrs.get(key), kind):
            raise StoreFormatError(
                f"`path` {path} is a damaged basis store: root attribute {key!r} is "
                f"{attrs.get(key)!r}. Restore the store from a copy."
            )
    return attrs


def _read_pointer(storage: Storage) -> dict[str, Any]:
    return _read_pointer_tagged(storage)[0]


def _read_pointer_tagged(storage: Storage) -> tuple[dict[str, Any], str]:
    """Return the pointer and its version tag (the ETag on an object store)."""
    path = _named(storage)
    pointer = f"{path}/{POINTER_NAME}"
    try:
        seen = storage.get_tagged(POINTER_NAME)
        if seen is None:
            raise FileNotFoundError(pointer)
        raw, tag = seen
        doc = json.loads(raw)
    except FileNotFoundError:
        raise StoreFormatError(
            f"`path` {path} is an incomplete basis store: it has no {POINTER_NAME} (its "
            "creation was interrupted). Create it again with `BasisStore.create`, which "
            "replaces the leftovers."
        ) from None
    except (OSError, ValueError) as exc:
        raise StoreFormatError(
            f"`path` {path} is a damaged basis store: {pointer} cannot be read ({exc}). "
            "Restore the store from a copy."
        ) from exc
    if (
        not isinstance(doc, dict)
        or doc.get("format") != FORMAT
        or not isinstance(doc.get("generation"), int)
        or not isinstance(doc.get("attrs_sha256"), str)
    ):
        raise StoreFormatError(
            f"`path` {path} is a damaged basis store: {pointer} does not name a "
            "generation. Restore the store from a copy."
        )
    if doc.get("format_version") != FORMAT_VERSION:
        raise StoreFormatError(
            f"`path` {path} has a pointer of format version {doc.get('format_version')!r}; "
            f"this version of streamsvd reads format version {FORMAT_VERSION}. Open it with "
            "the streamsvd release that wrote it."
        )
    return doc, tag


def _is_interrupted_creation(storage: Storage) -> bool:
    """Whether ``storage`` holds only what an interrupted :meth:`BasisStore.create` leaves."""
    ours = {"zarr.json", GENERATIONS, LOCK_NAME, LEASE_NAME}
    entries = storage.list()
    for name in entries:
        if name in ours or name.startswith((f"{POINTER_NAME}.", f"{LOCK_NAME}.stale-")):
            continue
        return False
    if "zarr.json" in entries:
        try:
            doc = json.loads(storage.get("zarr.json"))
        except (OSError, ValueError):
            return True
        attrs = doc.get("attributes") if isinstance(doc, dict) else None
        return isinstance(attrs, dict) and attrs.get("format") == FORMAT
    return True


class BasisStore:
    """A versioned, crash-safe basis store in a zarr v3 group (a directory or an object store).

    Open one with :func:`open_store` or create one with :meth:`BasisStore.create`; see
    the module docstring for the layout and the guarantees. A store opened for writing
    holds the writer lock (the lease, on an object store) until :meth:`close` (also
    called on leaving a ``with`` block).

    Parameters
    ----------
    path : str, os.PathLike or Storage
        Directory of the store, a ``file://`` or ``s3://`` URL, or a storage from
        :func:`streamsvd.storage.open_storage`.
    mode : {"r", "a"}
        ``"r"`` to read only (no lock taken), ``"a"`` to read and commit (takes the
        writer lock).
    n : int, optional
        Expected snapshot size; checked against the store.
    dtype : str or numpy.dtype, optional
        Expected dtype of the stored arrays; checked against the store.
    inner_fingerprint : str, optional
        Expected inner-product fingerprint; checked against the store.
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...).

    Raises
    ------
    StoreFormatError
        ``path`` is not a basis store, is damaged, or has another format version.
    StoreMismatchError
        The store's ``n``, ``dtype`` or ``inner_fingerprint`` differs from the one passed.
    StoreLockedError
        ``mode="a"`` and another live writer holds the lock.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | Storage,
        mode: Literal["r", "a"] = "r",
        *,
        n: int | None = None,
        dtype: Any = None,
        inner_fingerprint: str | None = None,
        storage_options: Mapping[str, Any] | None = None,
    ) -> None:
        storage = open_storage(path, storage_options=storage_options)
        root = _named(storage)
        if mode not in ("r", "a"):
            raise InputError(
                f"`mode` must be 'r' (read only) or 'a' (read and commit); got {mode!r}."
            )
        expected_n = check_positive_int(n, "n", allow_none=True)
        expected_dtype = None if dtype is None else _check_dtype(dtype)
        expected_fp = None if inner_fingerprint is None else _check_fingerprint(inner_fingerprint)
        attrs = _read_root_attrs(storage)
        _read_pointer(storage)
        for key, want in (
            ("n", expected_n),
            ("dtype", expected_dtype),
            ("inner_fingerprint", expected_fp),
        ):
            if want is not None and attrs[key] != want:
                raise StoreMismatchError(
                    f"`{key}` must match the store {root}: expected {want!r}, found "
                    f"{attrs[key]!r}. Open the store that belongs to this problem, or "
                    "create a new one."
                )
        lock = None
        if mode == "a":
            lock = storage.lock(_lock_key(storage))
            lock.acquire()
        try:
            pointer, tag = _read_pointer_tagged(storage)
            self._setup(storage, mode, attrs, lock, pointer["generation"], pointer.get("previous"),
                        pointer_tag=tag)
            if lock is not None:
                self._clean_leftovers()
        except BaseException:
            if lock is not None:
                lock.release()
            raise

    def _setup(
        self,
        storage: Storage,
        mode: str,
        attrs: dict[str, Any],
        lock: Any,
        generation: int,
        previous: int | None,
        *,
        pointer_tag: str | None = None,
    ) -> None:
        self._storage = storage
        self._path = _named(storage)
        self._pointer_tag = pointer_tag  # the pointer's version as this writer last saw it
        self._mode = mode
        self._root_attrs = dict(attrs)
        self._lock = lock
        self._closed = False
        self._generation = generation
        self._previous = previous
        self._docs: dict[int, dict[str, Any]] = {}  # attributes of retained generations
        self._written: dict[str, int] = {}
        self._finalizer = weakref.finalize(self, lock.release) if lock is not None else None

    # ------------------------------------------------------------------ creation

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str] | Storage,
        *,
        n: int,
        dtype: Any = "float64",
        inner_fingerprint: str,
        attrs: Mapping[str, Any] | None = None,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        storage_options: Mapping[str, Any] | None = None,
    ) -> BasisStore:
        """Create a new store at ``path`` and return it opened for writing.

        The new store is at generation 0, which holds no arrays and the attributes
        ``attrs``.

        Parameters
        ----------
        path : str, os.PathLike or Storage
            A directory (or a ``file://`` URL) that does not exist yet or is empty, an
            ``s3://`` URL under which nothing is stored yet, or a storage from
            :func:`streamsvd.storage.open_storage`. Leftovers of an interrupted
            creation are replaced.
        n : int
            Snapshot size (the number of rows of ``U``).
        dtype : {"float64", "float32"}
            Dtype in which every array is stored; committed arrays are cast to it.
        inner_fingerprint : str
            Fingerprint of the inner product (``inner.fingerprint``).
        attrs : dict, optional
            JSON-able attributes of generation 0.
        chunk_bytes : int
            Target size of one uncompressed chunk; each chunk holds whole rows.
        storage_options : dict, optional
            Options of the fsspec file system of a URL (``s3://``: ``key``,
            ``secret``, ``endpoint_url``, ...).

        Returns
        -------
        BasisStore
            The store, opened with mode ``"a"`` (it holds the writer lock).

        Raises
        ------
        StoreError
            A store already exists at ``path``, or ``path`` is a file or a non-empty
            directory that is not a store.
        StoreLockedError
            Another process is creating or writing a store at ``path``.
        """
        storage = open_storage(path, storage_options=storage_options)
        root = _named(storage)
        n = _positive_int(n, "n")
        dtype_name = _check_dtype(dtype)
        fingerprint = _check_fingerprint(inner_fingerprint)
        chunk_bytes = _positive_int(chunk_bytes, "chunk_bytes")
        user_attrs = _normalise_attrs(attrs)
        cls._check_creatable(storage)
        storage.prepare()
        key = _lock_key(storage)
        lock = storage.lock(key)
        lock.acquire()
        try:
            cls._check_creatable(storage)
            for entry in storage.list():
                if entry == key:
                    continue
                logger.warning(
                    "removing %s/%s, left by an interrupted store creation", root, entry
                )
                storage.delete(entry)
            root_attrs = {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "n": n,
                "dtype": dtype_name,
                "inner_fingerprint": fingerprint,
                "created": _now(),
                "library_version": _library_version(),
                "chunk_bytes": chunk_bytes,
            }
            zstore = storage.zarr_store(read_only=False)
            try:
                group = zarr.create_group(
                    store=zstore, zarr_format=3, attributes=cast(Any, root_attrs)
                )
                group.create_group(GENERATIONS)
            finally:
                zstore.close()
            self = cls.__new__(cls)
            self._setup(storage, "a", root_attrs, lock, -1, None)
            self._write_generation(0, {}, [], user_attrs)
        except BaseException:
            lock.release()
            raise
        logger.info("created basis store %s (n=%d, dtype=%s)", root, n, dtype_name)
        return self

    @staticmethod
    def _check_creatable(storage: Storage) -> None:
        root = _named(storage)
        if storage.is_file():
            raise StoreError(
                f"`path` must be a directory to create a store in; {root} is a file. "
                "Choose another path."
            )
        entries = storage.list()
        if POINTER_NAME in entries:
            raise StoreError(
                f"`path` {root} already holds a basis store. Open it with "
                "`open_store(path, mode='a')`, or delete it first to start afresh."
            )
        if entries and not _is_interrupted_creation(storage):
            raise StoreError(
                f"`path` must be a new or empty directory to create a store in; {root} "
                "holds other files. Choose another path."
            )

    # --------------------------------------------------------------- properties

    @property
    def path(self) -> Path | str:
        """Directory of the store (a Path), or its URL on an object store."""
        return self._path

    @property
    def mode(self) -> str:
        """``"r"`` (read only) or ``"a"`` (read and commit)."""
        return self._mode

    @property
    def format_version(self) -> int:
        """Format version of the store layout."""
        return int(self._root_attrs["format_version"])

    @property
    def generation(self) -> int:
        """Number of the current generation, as last seen by this handle."""
        return self._generation

    @property
    def n(self) -> int:
        """Snapshot size recorded at creation."""
        return int(self._root_attrs["n"])

    @property
    def dtype(self) -> str:
        """Dtype of the stored arrays."""
        return str(self._root_attrs["dtype"])

    @property
    def inner_fingerprint(self) -> str:
        """Fingerprint of the inner product recorded at creation."""
        return str(self._root_attrs["inner_fingerprint"])

    @property
    def root_attrs(self) -> dict[str, Any]:
        """Root attributes (format, version, n, dtype, fingerprint, created, ...)."""
        return dict(self._root_attrs)

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called."""
        return self._closed

    # -------------------------------------------------------------------- reading

    def read(self, *, generation: int | None = None) -> StoreState:
        """Read the current generation (or a retained one) and verify its checksums.

        Parameters
        ----------
        generation : int, optional
            Number of the generation to read: the current one (default) or the previous
            one, which is kept too.

        Returns
        -------
        StoreState
            The generation's arrays (read-only) and attributes.

        Raises
        ------
        StoreFormatError
            The generation is missing or damaged (a checksum does not match); the
            previous generation is not substituted silently.
        """
        self._check_open()
        for attempt in range(3):
            pointer = _read_pointer(self._storage)
            current = pointer["generation"]
            retained = [current] + (
                [pointer["previous"]] if isinstance(pointer.get("previous"), int) else []
            )
            wanted = current if generation is None else generation
            if wanted not in retained:
                raise InputError(
                    f"`generation` must be one of the retained generations {retained}; got "
                    f"{generation!r}. Older generations are deleted after each commit."
                )
            digest = pointer["attrs_sha256"] if wanted == current else None
            try:
                state = self._load(wanted, digest)
            except StoreFormatError:
                # A reader racing a writer may find its generation pruned: retry then.
                moved = _read_pointer(self._storage)["generation"] != current
                if moved and self._mode == "r" and attempt < 2:
                    continue
                raise
            self._generation = current
            self._previous = retained[1] if len(retained) > 1 else None
            return state
        raise AssertionError("unreachable")  # pragma: no cover

    def _load(self, k: int, attrs_digest: str | None) -> StoreState:
        where = f"{self._path}/{GENERATIONS}/{_gen_name(k)}"
        hint = (
            f" The previous generation is kept: read it with `store.read(generation="
            f"{self._previous})` and commit it again, or restore the store from a copy."
            if self._previous is not None and self._previous != k
            else " Restore the store from a copy."
        )
        zstore = self._storage.zarr_store(read_only=True)
        packs: dict[int, zarr.Array] = {}

        def open_pack(g: int) -> zarr.Array:
            if g not in packs:
                node = zarr.open_array(
                    store=zstore, mode="r", path=f"{GENERATIONS}/{_gen_name(g)}", zarr_format=3
                )
                packs[g] = node
            return packs[g]

        try:
            try:
                doc = open_pack(k).attrs.asdict()
            except _READ_ERRORS as exc:
                raise StoreFormatError(
                    f"`path` {self._path} is damaged: generation {k} ({where}) cannot be "
                    f"opened ({type(exc).__name__}: {exc}).{hint}"
                ) from exc
            meta = doc.get("streamsvd")
            if (
                not isinstance(meta, dict)
                or meta.get("generation") != k
                or not isinstance(meta.get("arrays"), dict)
                or not isinstance(doc.get("attrs"), dict)
                or (attrs_digest is not None and _attrs_digest(doc) != attrs_digest)
            ):
                raise StoreFormatError(
                    f"`path` {self._path} is damaged: the attributes of generation {k} "
                    f"({where}) do not match the checksum recorded in {POINTER_NAME}.{hint}"
                )
            arrays: dict[str, np.ndarray] = {}
            for name, info in meta["arrays"].items():

                def read(seg: dict[str, Any], name: str = name) -> np.ndarray:
                    g = int(seg["generation"])
                    shape = tuple(int(x) for x in seg["shape"])
                    size = int(np.prod(shape, dtype=np.int64))
                    start = int(seg["offset"])
                    try:
                        flat = np.asarray(open_pack(g)[start : start + size]) if size else (
                            np.zeros(0, dtype=np.dtype(self.dtype))
                        )
                    except _READ_ERRORS as exc:
                        raise StoreFormatError(
                            f"`path` {self._path} is damaged: array {name!r} of generation "
                            f"{k} cannot be read from the pack of generation {g} "
                            f"({type(exc).__name__}: {exc}).{hint}"
                        ) from exc
                    if flat.size != size or digest(flat) != seg.get("sha256"):
                        raise StoreFormatError(
                            f"`path` {self._path} is damaged: array {name!r} of generation "
                            f"{k} does not match its recorded shape, dtype or SHA-256 "
                            f"checksum (its segment in the pack of generation {g}).{hint}"
                        )
                    return flat.reshape(shape)

                try:
                    data = assemble(info, read)
                except StoreFormatError:
                    raise
                except _READ_ERRORS as exc:
                    raise StoreFormatError(
                        f"`path` {self._path} is damaged: array {name!r} of generation {k} "
                        f"does not match its recorded shape, dtype or SHA-256 checksum "
                        f"({type(exc).__name__}: {exc}).{hint}"
                    ) from exc
                data.setflags(write=False)
                arrays[name] = data
        finally:
            zstore.close()
        self._docs[k] = doc
        return StoreState(
            generation=k,
            arrays=arrays,
            attrs=cast(dict[str, Any], doc["attrs"]),
            n=self.n,
            dtype=self.dtype,
            inner_fingerprint=self.inner_fingerprint,
        )

    # --------------------------------------------------------------------- writing

    @property
    def last_written(self) -> dict[str, int]:
        """Elements written per array name by the last :meth:`commit` of this handle.

        An array whose segments were all kept is absent; merged segments count.
        """
        return dict(self._written)

    def commit(
        self,
        arrays: Mapping[str, Any],
        attrs: Mapping[str, Any] | None = None,
        *,
        appended: Mapping[str, Appended] | None = None,
    ) -> int:
        """Write ``arrays`` and ``attrs`` as a new generation and make it current.

        The switch is atomic: a reader, or a process reopening the store after this one
        was killed at any instant, sees either the previous generation or the new one,
        complete. If the commit fails, the previous generation stays current and intact.

        Parameters
        ----------
        arrays : dict of str to array_like
            Named real 1-D or 2-D arrays (for example ``{"U": U, "V": V,
            "amplitudes": s}``), each written whole; names are identifiers. Each is cast
            to the store's ``dtype`` and must be finite.
        attrs : dict, optional
            JSON-able attributes of the generation (columns absorbed, source offset,
            tolerances, discarded energy, error bound, history, ...).
        appended : dict of str to Appended, optional
            Arrays that keep the unchanged part of the same array of the current
            generation and write only the rest (see :class:`~streamsvd.segments.Appended`);
            only the part written is cast and checked.

        Returns
        -------
        int
            Number of the new generation.

        Raises
        ------
        StoreError
            The store is read-only or closed, or writing failed (the previous
            generation is then still current).
        StoreLockedError
            The lock was taken over by another writer meanwhile.
        """
        self._check_open()
        if self._mode != "a":
            raise StoreError(
                f"`store` {self._path} was opened read-only (mode='r'); commit needs "
                "mode='a'. Reopen it with `open_store(path, mode='a')`."
            )
        dtype = np.dtype(self.dtype)
        prepared = _prepare_arrays(arrays, dtype)
        user_attrs = _normalise_attrs(attrs)
        k = self._generation + 1
        records: dict[str, Any] = {}
        pieces: list[Piece] = []
        for name, arr in prepared.items():
            records[name], new = plan_whole(arr, generation=k)
            pieces += new
        if appended:
            if not isinstance(appended, Mapping):
                raise InputError(
                    f"`appended` must be a dict mapping names to Appended; got "
                    f"{type(appended).__name__}."
                )
            current = self._current_doc()["streamsvd"]["arrays"] if any(
                getattr(v, "unchanged", 0) for v in appended.values()
            ) else {}
            seal = int(self._root_attrs.get("chunk_bytes", DEFAULT_CHUNK_BYTES))
            for name, value in appended.items():
                if not isinstance(name, str) or not _NAME_RE.match(name) or name in records:
                    raise InputError(
                        f"`appended` keys must be identifiers not used in `arrays`; got "
                        f"{name!r}. Rename the array."
                    )
                records[name], new = plan_appended(
                    name, value, current.get(name), generation=k, dtype=dtype,
                    seal_bytes=seal,
                )
                pieces += new
        self._write_generation(k, records, pieces, user_attrs)
        return k

    def _current_doc(self) -> dict[str, Any]:
        """Attributes of the current generation (its digest checked against the pointer)."""
        k = self._generation
        doc = self._docs.get(k)
        if doc is None:
            doc = _read_generation_doc(self._storage, k)
            digest_ok = doc is not None and (
                _attrs_digest(doc) == _read_pointer(self._storage)["attrs_sha256"]
            )
            if doc is None or not digest_ok:
                raise StoreFormatError(
                    f"`path` {self._path} is damaged: the attributes of the current "
                    f"generation {k} cannot be read or do not match {POINTER_NAME}, so "
                    "nothing can be appended to it. Restore the store from a copy."
                )
            self._docs[k] = doc
        return doc

    def _write_generation(
        self,
        k: int,
        records: dict[str, Any],
        pieces: list[Piece],
        user_attrs: dict[str, Any],
    ) -> None:
        gkey = f"{GENERATIONS}/{_gen_name(k)}"
        self._check_pointer_unchanged(k)
        if _gen_name(k) in self._storage.list(GENERATIONS):
            logger.warning("removing %s/%s, left by an interrupted commit", self._path, gkey)
            self._storage.delete(gkey)
        data = pack(pieces, np.dtype(self.dtype))
        written: dict[str, int] = {}
        for name, info in records.items():
            for seg in info["segments"]:
                if seg["generation"] == k:
                    written[name] = written.get(name, 0) + int(np.prod(seg["shape"]))
        doc = {
            "streamsvd": {"generation": k, "committed": _now(), "arrays": records},
            "attrs": user_attrs,
        }
        doc = json.loads(json.dumps(doc))
        previous = self._generation if self._generation >= 0 else None
        pointer = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "generation": k,
            "previous": previous,
            "attrs_sha256": _attrs_digest(doc),
            "committed": doc["streamsvd"]["committed"],
        }
        failures: tuple[type[BaseException], ...] = (OSError, *remote_errors())
        try:
            zstore = self._storage.zarr_store(read_only=False)
            try:
                _write_pack(
                    zstore,
                    gkey,
                    data,
                    doc,
                    int(self._root_attrs.get("chunk_bytes", DEFAULT_CHUNK_BYTES)),
                )
            finally:
                zstore.close()
            self._storage.flush(gkey)
            if self._lock is None or not self._lock.owned():
                holder = self._lock.holder() if self._lock is not None else "nobody"
                raise StoreLockedError(
                    f"`store` {self._path} lost its writer lock to {holder}; generation {k} "
                    "was not committed. Make sure a single writer opens the store."
                )
            self._switch(pointer, k)
        except BaseException as exc:
            if not self._pointer_is(pointer):
                if self._not_named(k):
                    self._storage.delete(gkey)
                if isinstance(exc, failures) and not isinstance(exc, StoreError):
                    raise StoreError(
                        f"`store` {self._path}: writing generation {k} failed ({exc}); the "
                        f"current generation {self._generation} is unchanged. Fix the cause "
                        "and commit again."
                    ) from exc
                raise
            # The pointer names this commit: the switch took effect and only what follows
            # it (the directory's fsync, the reply) failed or was interrupted. The commit
            # stands and is never undone; an interrupt still propagates once it is recorded.
            logger.warning(
                "generation %d of %s was committed; the step after its pointer switch "
                "failed (%s)", k, self._path, type(exc).__name__,
            )
            self._adopt(k, doc, previous, written)
            if not isinstance(exc, failures):
                raise
            return
        self._adopt(k, doc, previous, written)

    def _adopt(
        self, k: int, doc: dict[str, Any], previous: int | None, written: dict[str, int]
    ) -> None:
        """Record generation ``k``, which the pointer now names, as this writer's current one."""
        self._docs = {g: d for g, d in self._docs.items() if g == self._generation}
        self._docs[k] = doc
        self._previous = previous
        self._generation = k
        self._written = written
        self._prune()
        logger.debug("committed generation %d of %s (%s)", k, self._path, written)

    def _pointer_is(self, pointer: dict[str, Any]) -> bool:
        """Whether the stored pointer is ``pointer`` (then its version tag is recorded).

        Asked after a commit failed or was interrupted, to tell whether its switch took
        effect; a pointer that cannot be read counts as not switched.
        """
        try:
            seen = self._storage.get_tagged(POINTER_NAME)
            if seen is None or json.loads(seen[0]) != pointer:
                return False
        except (OSError, ValueError, *remote_errors()):
            return False
        if self._storage.conditional:
            self._pointer_tag = seen[1]
        return True

    def _not_named(self, k: int) -> bool:
        """Whether no pointer can name generation ``k`` (so deleting it loses nothing).

        True when the store has no pointer yet (its creation) or a readable pointer names
        an older generation; a pointer that cannot be read keeps ``k``.
        """
        try:
            seen = self._storage.get_tagged(POINTER_NAME)
            if seen is None:
                return True
            named = json.loads(seen[0]).get("generation")
        except (OSError, ValueError, AttributeError, *remote_errors()):
            return False
        return isinstance(named, int) and named < k

    def _pointer_changed(self, k: int) -> StoreLockedError:
        return StoreLockedError(
            f"`store` {self._path}: the pointer {POINTER_NAME} was changed by another "
            f"writer ({self._lock.holder() if self._lock is not None else 'unknown'}) "
            f"since this one last committed; generation {k} was not committed. Make "
            "sure a single writer opens the store."
        )

    def _check_pointer_unchanged(self, k: int) -> None:
        """On an object store, refuse to start a commit if another writer committed since.

        Nothing is written or deleted then (generation ``k`` may be the other writer's).
        """
        if not self._storage.conditional or self._pointer_tag is None:
            return
        seen = self._storage.get_tagged(POINTER_NAME)
        if seen is None or seen[1] != self._pointer_tag:
            raise self._pointer_changed(k)

    def _switch(self, pointer: dict[str, Any], k: int) -> None:
        """Make ``pointer`` current: an atomic replace locally, a conditional PUT remotely.

        On an object store the pointer is replaced only if it is still the version this
        writer last wrote or read (``If-Match`` its ETag; ``If-None-Match`` at creation),
        so a writer that lost its lease can never overwrite another writer's commit.
        """
        data = json.dumps(pointer, indent=2).encode()
        storage = self._storage
        if not storage.conditional:
            storage.put(POINTER_NAME, data)
            return
        tag = (
            storage.put_if_absent(POINTER_NAME, data)
            if self._pointer_tag is None
            else storage.put_if_match(POINTER_NAME, data, self._pointer_tag)
        )
        if tag is None:
            raise self._pointer_changed(k)
        self._pointer_tag = tag

    def _prune(self) -> None:
        """Delete every generation that neither the current nor the previous one uses."""
        keep: set[int | None] = {self._generation, self._previous}
        for g in (self._generation, self._previous):
            if g is None:
                continue
            doc = self._docs.get(g) or _read_generation_doc(self._storage, g)
            if doc is None:
                # cannot tell which older packs it uses: delete only the newer leftovers
                logger.warning(
                    "generation %d of %s cannot be read; keeping every older generation",
                    g, self._path,
                )
                keep.update(range(0, max(self._generation, self._previous or 0) + 1))
                break
            keep.update(_sources(doc))
        for entry in self._storage.list(GENERATIONS):
            m = _GEN_RE.match(entry)
            if m and int(m.group(1)) not in keep:
                logger.debug("removing generation %s of %s", entry, self._path)
                self._storage.delete(f"{GENERATIONS}/{entry}")

    def _clean_leftovers(self) -> None:
        """Delete what killed writers left: half-written generations, temporary files."""
        self._prune()
        for entry in self._storage.list():
            if entry.startswith((f"{POINTER_NAME}.", f"{LOCK_NAME}.stale-")):
                logger.info("removing %s/%s, left by an interrupted writer", self._path, entry)
                self._storage.delete(entry)

    # --------------------------------------------------------------------- closing

    def _check_open(self) -> None:
        if self._closed:
            raise StoreError(
                f"`store` {self._path} is closed. Open it again with `open_store(path)`."
            )

    def close(self) -> None:
        """Release the writer lock (if held); the handle cannot be used afterwards."""
        if self._closed:
            return
        self._closed = True
        if self._finalizer is not None:
            self._finalizer()

    def __enter__(self) -> BasisStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"mode={self._mode!r}"
        return (
            f"BasisStore({str(self._path)!r}, {state}, generation={self._generation}, "
            f"n={self.n}, dtype={self.dtype!r})"
        )


def open_store(
    path: str | os.PathLike[str] | Storage,
    mode: Literal["r", "a"] = "r",
    *,
    n: int | None = None,
    dtype: Any = None,
    inner_fingerprint: str | None = None,
    storage_options: Mapping[str, Any] | None = None,
) -> BasisStore:
    """Open an existing basis store.

    Parameters
    ----------
    path : str, os.PathLike or Storage
        Directory of the store, a ``file://`` or ``s3://`` URL, or a storage from
        :func:`streamsvd.storage.open_storage`.
    mode : {"r", "a"}
        ``"r"`` to read only (no lock is taken), ``"a"`` to read and commit (takes the
        writer lock; leftovers of interrupted commits are deleted).
    n, dtype, inner_fingerprint : optional
        Expected snapshot size, stored dtype and inner-product fingerprint; each one
        given is checked against the store.
    storage_options : dict, optional
        Options of the fsspec file system of a URL (``s3://``: ``key``, ``secret``,
        ``endpoint_url``, ...); the ``AWS_*`` environment variables apply too.

    Returns
    -------
    BasisStore
        The open store; use it as a context manager or call :meth:`BasisStore.close`.

    Raises
    ------
    StoreFormatError
        ``path`` is not a basis store, is damaged, or has another format version.
    StoreMismatchError
        An expectation differs from what the store holds.
    StoreLockedError
        ``mode="a"`` and another live writer holds the lock.
    """
    return BasisStore(
        path, mode, n=n, dtype=dtype, inner_fingerprint=inner_fingerprint,
        storage_options=storage_options,
    )
