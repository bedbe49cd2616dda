"""Damage a local store's generation the way a disk or a careless hand would (for tests).

Used by the fault-injection tests and by ``bench/fault_campaign.py``: each kind is one
defect that ``streamsvd check`` must report, naming what it found and the last readable
generation.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["GENERATION_DAMAGE", "damage_generation"]

GENERATION_DAMAGE = ("flip", "missing-chunk", "attrs")


def damage_generation(
    generation: Path, kind: str, *, attr: str = "n_seen", value: int | None = None
) -> None:
    """Damage one generation directory of a local store in place.

    ``"flip"`` inverts a byte in the middle of its first chunk, ``"missing-chunk"``
    removes that chunk, ``"attrs"`` sets the integer attribute ``attr`` of its
    ``zarr.json`` to ``value`` (default: one more), so its checksum no longer matches.
    """
    if kind == "flip":
        chunk = generation / "c.0"
        data = bytearray(chunk.read_bytes())
        data[len(data) // 2] ^= 0xFF
        chunk.write_bytes(bytes(data))
    elif kind == "missing-chunk":
        (generation / "c.0").unlink()
    elif kind == "attrs":
        meta = generation / "zarr.json"
        doc = json.loads(meta.read_text())
        attrs = doc["attributes"]["attrs"]
        attrs[attr] = attrs[attr] + 1 if value is None else value
        meta.write_text(json.dumps(doc))
    else:
        raise ValueError(f"`kind` must be one of {GENERATION_DAMAGE}; got {kind!r}.")
