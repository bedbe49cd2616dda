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
:mod:`streamsvd.storage.lockfile` their writer lock or lease. The package's modules have
one job each: :mod:`~streamsvd.store.format` (names, documents, the checks of the root
attributes), :mod:`~streamsvd.store.reading` (the pointer, :func:`history`, verified
reads retried while the pointer moves), :mod:`~streamsvd.store.check`
(:func:`check_store`), :mod:`~streamsvd.store.commit` (the pack and the pointer switch),
:mod:`~streamsvd.store.fence` (every write and delete checked against the lock or
lease), :mod:`~streamsvd.store.collector` (deleting what no pointer can reach),
:mod:`~streamsvd.store.create` (all or nothing), :mod:`~streamsvd.store.session` (what an
open handle holds: opening, reading, committing) and :mod:`~streamsvd.store.handle`
(:class:`BasisStore`, the thin public face of a session). Layout (directory or prefix)::

    <path>/
      zarr.json                  root group; attributes: format, format_version, n,
                                 dtype, inner_fingerprint, created, library_version,
                                 chunk_bytes
      current.json               the pointer: number of the current generation, the
                                 SHA-256 of its attributes, a copy of the root attributes
      writer.lock                present while a writer has the store open (local)
      writer.lease               the same, with an expiry, in an object store
      panels/                    a tall compressor's basis (streamsvd.algebra.panels.files),
                                 written before the commits that list it
      generations/
        g00000005/               an older generation whose segments are still used
        g00000007/               previous generation (kept)
        g00000008/               current generation: one zarr array, the *pack*
          zarr.json              attributes: {"streamsvd": {...}, "attrs": {...}}
          c.0, c.1, ...          chunks of the pack
          committed.json         the commit record: a copy of the pointer that named it

Design
------
*Segments.* Every array of a generation is a list of immutable *segments* along one axis
(:mod:`streamsvd.store.segments`): blocks of rows or columns, each written once into the pack
of the generation that created it, a flat zarr array holding the new segments of that
commit one after the other. The generation's attributes record, for each array, its
shape, dtype, axis and segments (generation, offset in that generation's pack, shape,
SHA-256). An array committed whole is one new segment; an
:class:`~streamsvd.store.segments.Appended` array keeps the segments of the current generation
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

*Creation.* All or nothing: the lock is taken and the root metadata written, then the
first commit writes generation 0 and switches the pointer to it, the last write that
makes the store exist (:meth:`BasisStore.create` commits the attributes it is given; a
compressor begins its store with :meth:`BasisStore.begin` and commits its whole state,
its basis's attributes included, as generation 0). A failure before the switch deletes
everything written under the store; a process killed before it leaves no pointer: the
store does not open ("its creation was interrupted"), :func:`check_store` says so, and
the next creation replaces the leftovers.

*Commit.* A generation's pack is written completely first (with the attributes holding
the caller's attributes and the segment lists), its files and directory are
``fsync``-ed, and only then is the pointer switched. The pointer also records the
SHA-256 of the generation's attributes and a copy of the root attributes, so the chain
pointer -> attributes -> segment bytes is verified on every read, and an edited root
attribute (``n``, ``dtype``) is reported by name. After the switch the writer records
the commit in the generation (``committed.json``) and collects: every generation
*older* than the current one that is neither the previous one nor holds a segment
either of them uses is deleted. A generation left by an interrupted commit is never
pointed to and has no commit record; the next writer deletes it. A generation newer than
the pointer that has a commit record means that the pointer was replaced by an older
copy: the store is reported damaged and nothing is deleted. A store that ever committed
is never replaced by :meth:`BasisStore.create`. Nothing written is ever modified. In an object store
there is nothing to ``fsync``: an object is durable once its ``PUT`` returned, and the
pointer is written after every object of the pack.

*Readers and garbage collection.* A reader (mode ``"r"``) reads the pointer, then the
generation it names. That generation stays until the writer has committed two more
(it is kept as the previous one after the next commit); a read that finds its generation
collected, the pointer having moved, starts again from the new pointer, for as long as
the pointer moves. A generation is reported damaged only when it fails to verify while
the pointer still names it. The same holds in a directory and in an object store:
nothing relies on open files staying readable.

*Fencing.* Every write and delete of a writer goes through its fence
(:mod:`streamsvd.store.fence`): it first checks that the writer still holds its lock or
lease, and objects are only ever created (``O_EXCL``, ``If-None-Match: *``), never
overwritten; the collector runs only in the lease holder and only on generations older
than the pointer it switched. A writer paused (a zombie) and woken after a takeover
therefore writes and deletes nothing that anybody names.

*Checksums.* One per segment: its SHA-256, recorded in the attributes, verified on
every read (this also catches a missing chunk, which zarr would read as zeros). The
chunks are stored as they are: a basis is floating-point noise to a compressor (zstd at
level 3 saved 4 % of the bytes and took 34 % of a commit's processor time and 43 % of a
read's time, ``bench/commit_benchmark.py``); packs written compressed by earlier
versions are read through their own metadata.

*Chunks.* A pack is chunked in equal pieces of at most ``chunk_bytes`` bytes (16 MiB by
default: large enough for efficient reads, small enough to be written and
verified with bounded memory).

*Lock.* A writer (mode ``"a"``) creates ``writer.lock`` with ``O_CREAT | O_EXCL``; it
holds the writer's pid, host name and start time, and the writer keeps an advisory
``flock`` on it while the store is open. A second writer gets
:class:`~streamsvd.errors.StoreLockedError` naming the holder. A lock whose holder is on
this host and no longer runs (its pid is gone, or its ``flock`` is released, which also
covers a reused pid) is stale and is taken over with a logged warning. In an object
store the lock is a lease, ``writer.lease``, created and renewed by conditional writes,
with an expiry after which a dead writer's lease is taken over
(:class:`streamsvd.storage.lease.Lease`). Readers (mode ``"r"``) never take the lock.
"""

from __future__ import annotations

from streamsvd.storage.lockfile import LOCK_NAME
from streamsvd.store.check import CheckReport, check_store
from streamsvd.store.create import check_creatable
from streamsvd.store.fence import CRASH_POINTS, crash_point
from streamsvd.store.format import (
    DEFAULT_CHUNK_BYTES,
    FORMAT,
    FORMAT_VERSION,
    GENERATIONS,
    LEASE_NAME,
    MARKER_NAME,
    POINTER_NAME,
    StoreState,
)
from streamsvd.store.handle import BasisStore, open_store
from streamsvd.store.reading import history
from streamsvd.store.segments import Appended

__all__ = [
    "CRASH_POINTS",
    "DEFAULT_CHUNK_BYTES",
    "FORMAT",
    "FORMAT_VERSION",
    "GENERATIONS",
    "LEASE_NAME",
    "LOCK_NAME",
    "MARKER_NAME",
    "POINTER_NAME",
    "Appended",
    "BasisStore",
    "CheckReport",
    "StoreState",
    "check_creatable",
    "check_store",
    "crash_point",
    "history",
    "open_store",
]
