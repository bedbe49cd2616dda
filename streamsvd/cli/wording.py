"""How the ``streamsvd`` command words what went wrong: errors and interruptions.

The library's messages speak to Python callers (argument names in backticks, calls such
as ``BasisStore.create(...)``); :func:`in_cli_words` says them in the words of the
command line; :func:`failed` is the line printed after a user mistake, and
:func:`interrupted` the line printed after Ctrl-C.

Only the standard library is imported here (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import re
import shlex
from typing import Any

from streamsvd.errors import NonFiniteError, StreamSVDError
from streamsvd.stream.options import CompressorOptions

__all__ = ["failed", "in_cli_words", "interrupted"]

# Advice the library gives Python callers, and what a command-line user does instead.
_REWRITES = (
    (r"Create one with `BasisStore\.create\([^`]*\)`\.",
     "Create it with `streamsvd ingest SOURCE STORE`."),
    (r"Pass the directory given to `BasisStore\.create`\.",
     "Pass a directory written by `streamsvd ingest`."),
    (r"Create it again with `BasisStore\.create`, which replaces the leftovers\.",
     "Delete it and run `streamsvd ingest` again."),
    (r"Close that writer first, open the store with mode='r' to read it without the "
     r"lock, or delete the lock file if that process is gone\.",
     "Wait for that writer (another `streamsvd ingest`) to finish, or delete the lock "
     "file if that process is gone; `streamsvd info`, `export` and `plot` can read the "
     "store meanwhile."),
    (r"Open it with `open_store\(path, mode='a'\)`, or delete it first to start afresh\.",
     "Pass --resume to continue it, or delete it first to start afresh."),
    (r"The previous generation is kept: read it with `store\.read\(generation=(\d+)\)` and "
     r"commit it again, or restore the store from a copy\.",
     r"The previous generation \1 is kept (`streamsvd check STORE` verifies it); restore "
     "the store from a copy."),
    (r"Pass dataset=<one of them>\.", "Pass --dataset with one of them."),
    (r"Use the in-memory StreamCompressor, or lump the mass matrix into weights\.",
     "Drop --tall, or lump the mass matrix into weights."),
    (r"Drop the `dataset` argument\.", "Drop --dataset."),
    (r"got dataset=('[^']*')", r"got --dataset \1"),
    # a storage option by its key (`storage_options['zarr_store']`), with its value or not
    (r"`storage_options\['([\w.]+)'\]='([^'`]*)'`", r"--storage-option \1=\2"),
    (r"`storage_options\['([\w.]+)'\]`", r"--storage-option \1"),
)

# Python argument names (as the library quotes them) -> command-line words
_NAMES = {
    **{name: CompressorOptions.flag(name) for name in CompressorOptions.names()
       if name not in ("reject_tol", "reorth_tol", "right_vectors")},
    "path": "STORE", "store": "STORE", "source": "SOURCE", "out": "OUT",
    "dataset": "--dataset", "block": "--block", "scheduler": "--scheduler",
    "workers": "--workers", "leaf_columns": "--leaf-columns", "chunk_rows": "--chunk-rows",
    "resume": "--resume", "inner": "--inner", "storage_options": "--storage-option",
    "M": "--inner (its matrix)", "weights": "--inner (its weights)",
}

# a sentence holding Python code: a quoted call, a keyword argument, a module path
_PYTHON = re.compile(r"`[\w.]+\(|\b\w+=(?:True|False|None|'|\.\.\.)|`streamsvd\.\w|\bmode='")


def in_cli_words(message: str) -> str:
    """Say a library message in the words of the command line, on one line.

    Known Python advice is replaced by what a command-line user does; argument names
    become the command's arguments and options; any remaining sentence that still shows
    Python code is dropped (the first sentence, the fact, is always kept).
    """
    text = " ".join(message.split())
    for pattern, replacement in _REWRITES:
        text = re.sub(pattern, replacement, text)
    text = re.sub(r"`(\w+)`", lambda m: _NAMES.get(m[1], m[0]), text)
    sentences = re.split(r"(?<=[.;])\s+(?=[A-Z`])", text)
    kept = sentences[:1] + [s for s in sentences[1:] if not _PYTHON.search(s)]
    return " ".join(kept)


def failed(err: Exception, args: Any, argv: list[str]) -> str:
    """Return the line printed after ``streamsvd: error:`` for a user mistake.

    When ``ingest`` stopped at a NaN or infinite entry after committing snapshots, the
    line also says that STORE was kept, what it holds and the command that continues.
    """
    text = in_cli_words(str(err))
    if args.command != "ingest" or not isinstance(err, NonFiniteError):
        return text
    offset = _committed_offset(args.store)
    if not offset:  # nothing committed: a STORE this command created was removed
        return text
    return (
        f"{text} STORE {args.store} is kept and holds its last commit, the snapshots up to "
        f"column {offset} of SOURCE; once SOURCE is repaired, continue with: "
        f"streamsvd {_again(argv)} --resume"
    )


def interrupted(args: Any, argv: list[str]) -> str:
    """Return the line printed after Ctrl-C: what the store holds, how to continue."""
    if args.command != "ingest":
        return "streamsvd: interrupted."
    offset = _committed_offset(args.store)
    if offset is None:
        return (
            f"streamsvd: interrupted; nothing was committed to STORE {args.store}; start "
            f"again with: streamsvd {_again(argv)} --resume"
        )
    return (
        f"streamsvd: interrupted; STORE {args.store} holds the snapshots up to column "
        f"{offset} of SOURCE (its last commit); continue with: streamsvd {_again(argv)} "
        "--resume"
    )


def _again(argv: list[str]) -> str:
    """Return the command line ``argv`` without ``--resume``, quoted for a shell."""
    return " ".join(shlex.quote(a) for a in argv if a != "--resume")


def _committed_offset(store: Any) -> int | None:
    """Return the source offset of STORE's last commit, or None when it has none."""
    try:
        from streamsvd.store import open_store

        with open_store(store, "r") as st:
            return int(st.read().attrs.get("source_offset", 0))
    except (StreamSVDError, OSError, ValueError):
        return None
