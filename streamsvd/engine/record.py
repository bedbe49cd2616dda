"""The record of one update and the history schema a store keeps it in.

:class:`UpdateRecord` is what every update returns (an entry of a compressor's
``history``); :func:`history_array` and :func:`record_from_row` encode a history as a
float array, one row per record in the order of :data:`HISTORY_FIELDS`, and back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["HISTORY_FIELDS", "UpdateRecord", "history_array", "record_from_row"]


@dataclass(frozen=True)
class UpdateRecord:
    """What one update did (an entry of a compressor's ``history``).

    Attributes
    ----------
    kind : {"absorb", "add", "merge", "finalize", "remove"}
    columns : int
        Snapshots added (``absorb``, ``merge``), removed (``remove``) or terms of the
        increment (``add``).
    rank : int
        Rank after the update.
    new_directions : int
        Directions accepted by Gram-Schmidt.
    rejected : int
        Directions rejected by Gram-Schmidt.
    cut : int
        Terms removed by truncation.
    discarded : float
        ``||D_t||``: the norm of what the update removed (truncated terms and rejected
        residuals), kept as a norm so that amplitudes up to 1e300 stay finite.
    sweeps : int
        Rotation sweeps run.
    max_cosine : float
        Largest pair cosine met in the last sweep (0 at the SVD).
    orthogonality : float
        ``||U^T M U - I||_2`` after the update: from the Gram of the stored basis, or,
        after the Gram path on an in-memory basis (whose Gram the next update measures),
        the one the Gram of the basis and the block predicts, bounded by its Frobenius
        norm (:mod:`streamsvd.engine.update_gram`).
    error_bound : float
        The guaranteed bound on ``||A - U V^T||_F`` after the update.
    seconds : float
        Wall time of the update.
    passes : int
        Passes over the stored basis (products with ``Q`` or ``M Q``, and the compaction
        that writes a new one): 2 for an absorb by the snapshots' Gram
        (:mod:`streamsvd.engine.update_gram`), 2 to 4 for the exact path on a well-conditioned
        block, more for nearly collinear blocks (rounds of
        :func:`streamsvd.linalg.extend.extend_basis`).
    """

    kind: str
    columns: int
    rank: int
    new_directions: int
    rejected: int
    cut: int
    discarded: float
    sweeps: int
    max_cosine: float
    orthogonality: float
    error_bound: float
    seconds: float
    passes: int = 0


HISTORY_FIELDS = (
    "kind", "columns", "rank", "new_directions", "rejected", "cut", "discarded", "sweeps",
    "max_cosine", "orthogonality", "error_bound", "seconds", "passes",
)
_KINDS = ("absorb", "add", "merge", "finalize", "remove")


def history_array(history: list[UpdateRecord]) -> np.ndarray:
    """Encode a history as a float array (one row per record) for a store."""
    out = np.zeros((len(history), len(HISTORY_FIELDS)))
    for i, rec in enumerate(history):
        row = [getattr(rec, k) for k in HISTORY_FIELDS]
        row[0] = _KINDS.index(rec.kind)
        out[i] = row
    return out


def record_from_row(row: np.ndarray) -> UpdateRecord:
    """Decode one row of :func:`history_array`."""
    vals: dict[str, Any] = dict(zip(HISTORY_FIELDS, row.tolist(), strict=True))
    vals["kind"] = _KINDS[int(vals["kind"])]
    for k in ("columns", "rank", "new_directions", "rejected", "cut", "sweeps", "passes"):
        vals[k] = int(vals[k])
    return UpdateRecord(**vals)
