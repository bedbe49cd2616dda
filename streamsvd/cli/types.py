"""The types of the ``streamsvd`` command's option values.

Each turns a word of the command line into a value, or raises
:class:`argparse.ArgumentTypeError`, which the parser prints as a one-line usage error
naming the option. Only the standard library is imported here (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

__all__ = [
    "CONVERGE", "DEFAULT_COMMIT_EVERY", "commit_every", "forget", "nonnegative_float",
    "nonnegative_int", "number", "positive_float", "positive_int", "scheduler",
    "storage_option", "sweeps", "threads",
]

#: The ``--sweeps`` value that sweeps every update until no pair rotates.
CONVERGE = "converge"

#: Commits timed to take about a tenth of the time (``streamsvd.stream.commits.AUTO``).
DEFAULT_COMMIT_EVERY = "auto"


def number(text: str, kind: type, low: float, expected: str) -> Any:
    """Parse ``text`` as a finite ``kind`` (int or float) at least ``low``, for argparse."""
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or not math.isfinite(value) or value < low:
        raise argparse.ArgumentTypeError(f"must be {expected}; got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    """Parse an integer >= 0."""
    return int(number(text, int, 0, "an integer >= 0"))


def positive_int(text: str) -> int:
    """Parse an integer >= 1."""
    return int(number(text, int, 1, "a positive integer"))


def nonnegative_float(text: str) -> float:
    """Parse a finite number >= 0."""
    return float(number(text, float, 0.0, "a finite number >= 0"))


def positive_float(text: str) -> float:
    """Parse a finite number > 0 (``--target-error``)."""
    value = float(number(text, float, 0.0, "a positive number"))
    if value == 0.0:
        raise argparse.ArgumentTypeError(f"must be a positive number; got {text!r}")
    return value


def forget(text: str) -> float:
    """Parse a number in (0, 1] (``--forget``)."""
    value = float(number(text, float, 0.0, "a number in (0, 1]"))
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a number in (0, 1]; got {text!r}")
    return value


def commit_every(text: str) -> int | str:
    """Parse a positive number of updates per commit, or ``DEFAULT_COMMIT_EVERY``."""
    if text == DEFAULT_COMMIT_EVERY:
        return text
    return int(number(text, int, 1, "a positive number of updates per commit, or "
                       f"'{DEFAULT_COMMIT_EVERY}'"))


def threads(text: str) -> int | str:
    """Parse a positive number of threads, or ``"all"``."""
    if text == "all":
        return text
    return positive_int(text)


def sweeps(text: str) -> int | str:
    """Parse a positive number of sweeps per update, or ``CONVERGE``."""
    if text == CONVERGE:
        return CONVERGE
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"must be a positive number of sweeps per update, or '{CONVERGE}' to sweep "
            f"until no pair rotates; got {text!r}"
        )
    return value


def storage_option(text: str) -> tuple[str, Any]:
    """``KEY=VALUE``: VALUE as JSON when it parses (true, 3, "x"), else as the text."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip() or any(not part for part in key.strip().split(".")):
        raise argparse.ArgumentTypeError(
            f"must be KEY=VALUE (for example endpoint_url=http://localhost:9000 or "
            f"client_kwargs.region_name=eu-west-1); got {text!r}"
        )
    try:
        parsed: Any = json.loads(value)
    except ValueError:
        parsed = value
    return key.strip(), parsed


def scheduler(text: str) -> str:
    """Parse a scheduler: ``"threads"``, ``"local"`` or an address (``--scheduler``)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(
            "must be 'threads', 'local' or a scheduler address such as tcp://HOST:8786; "
            "got ''"
        )
    return text
