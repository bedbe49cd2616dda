"""A generation's pack: its data as the pieces written, and the zarr objects that hold it.

A commit (:mod:`streamsvd.store.commit`) writes the new segments of a generation
(:mod:`streamsvd.store.segments`) into one flat zarr array, its *pack*: :func:`pack`
lays the pieces end to end (their offsets and SHA-256 filled in, nothing copied) and
:func:`encode_pack` turns them into the array's objects, ``zarr.json`` first, then the
chunks, taken from the pieces' memory where the chunks are stored as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import zarr
import zarr.codecs
from zarr.storage import MemoryStore

from streamsvd.store.segments import Piece, digest

__all__ = ["PACK_COMPRESSORS", "Packed", "encode_pack", "pack"]

#: The codecs a pack's chunks are compressed with: none. A pack is mostly the basis, whose
#: floating-point digits zstd (level 3) shrank by 4 % for a third of a commit's processor
#: time and 43 % of a read's (``bench/commit_benchmark.py``). Readers follow each pack's own
#: metadata, so packs written compressed before stay readable.
PACK_COMPRESSORS: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Packed:
    """The flat data of a pack: its pieces' elements in order, never concatenated.

    Attributes
    ----------
    parts : tuple of ndarray
        One flat, C-contiguous, little-endian array per piece, in pack order (views of
        the pieces' data where their layout allows).
    dtype : numpy.dtype
        The pack's element type.
    """

    parts: tuple[np.ndarray, ...]
    dtype: np.dtype

    @property
    def size(self) -> int:
        """Number of elements."""
        return sum(int(p.size) for p in self.parts)

    def chunks(self, chunk: int) -> list[Any]:
        """Return the bytes of each chunk of ``chunk`` elements, the last one padded with zeros.

        A chunk inside one part is a read-only ``memoryview`` of it (no copy); a chunk
        across parts, or the padded last one, is ``bytes``.
        """
        out: list[Any] = []
        pending: list[np.ndarray] = []  # the start of a chunk that crosses parts
        filled = 0
        for part in self.parts:
            a = 0
            while a < part.size:
                take = min(chunk - filled, part.size - a)
                piece = part[a : a + take]
                a += take
                if not pending and take == chunk:
                    out.append(piece.view(np.uint8).data.toreadonly())
                    continue
                pending.append(piece)
                filled += take
                if filled == chunk:
                    out.append(np.concatenate(pending).tobytes())
                    pending, filled = [], 0
        if pending:
            pending.append(np.zeros(chunk - filled, self.dtype.newbyteorder("<")))
            out.append(np.concatenate(pending).tobytes())
        return out

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        flat = (np.concatenate(self.parts) if self.parts
                else np.zeros(0, self.dtype.newbyteorder("<")))
        return flat if dtype is None else flat.astype(dtype, copy=False)


def pack(pieces: list[Piece], dtype: np.dtype) -> Packed:
    """Return the pack of ``pieces``; fill their offsets and SHA-256.

    Nothing is copied when a piece is already C-contiguous, little-endian and of
    ``dtype``.
    """
    offset = 0
    parts = []
    le = np.dtype(dtype).newbyteorder("<")
    for piece in pieces:
        piece.segment["offset"] = offset
        flat = np.ascontiguousarray(piece.data, dtype=le).reshape(-1)
        piece.segment["sha256"] = digest(flat)
        parts.append(flat)
        offset += flat.size
    return Packed(tuple(parts), np.dtype(dtype))


def encode_pack(data: np.ndarray | Packed, doc: dict[str, Any], chunk_bytes: int
                ) -> dict[str, Any]:
    """Encode the pack ``data`` (a flat array with attributes ``doc``) as zarr objects.

    Without compressors a chunk is the little-endian bytes of its elements (the last one
    padded with the fill value 0 to a whole chunk), taken from ``data`` directly: a
    ``memoryview`` of the data where a chunk lies in one piece (:meth:`Packed.chunks`),
    where zarr would copy each chunk twice on the way (into its buffers, then into
    bytes), 0.2 s of a 100 MB commit. The objects are the same bytes as zarr writes
    (tested).
    """
    packed = data if isinstance(data, Packed) else Packed(
        (np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<")).reshape(-1),),
        data.dtype)
    size = packed.size
    # equal chunks of at most chunk_bytes: the last one is not padded by a chunk's worth
    most = max(1, chunk_bytes // packed.dtype.itemsize)
    chunk = max(1, -(-size // -(-size // most))) if size else 1
    memory: dict[str, Any] = {}
    arr = zarr.create_array(
        store=MemoryStore(memory),
        name="pack",
        shape=(size,),
        chunks=(chunk,),
        dtype=packed.dtype,
        compressors=PACK_COMPRESSORS,
        fill_value=0.0,
        attributes=doc,
        chunk_key_encoding={"name": "default", "separator": "."},
        config={"write_empty_chunks": True},
    )
    if size and _raw_chunks(arr, packed.dtype):
        objects: dict[str, Any] = {f"c.{i}": blob for i, blob in enumerate(packed.chunks(chunk))}
        objects["zarr.json"] = memory["pack/zarr.json"].to_bytes()
    else:
        if size:
            arr[...] = np.asarray(packed)
        objects = {k[len("pack/"):]: v.to_bytes() for k, v in memory.items()
                   if k.startswith("pack/")}
    # the metadata first: it claims the generation; then the chunks in order
    return {"zarr.json": objects.pop("zarr.json"), **dict(sorted(objects.items()))}


def _raw_chunks(arr: Any, dtype: np.dtype) -> bool:
    """Whether ``arr``'s chunks are the raw little-endian bytes of its ``dtype`` elements."""
    codecs = arr.metadata.codecs
    return (dtype.kind == "f" and len(codecs) == 1
            and isinstance(codecs[0], zarr.codecs.BytesCodec)
            and str(getattr(codecs[0].endian, "value", codecs[0].endian)) in ("little", "None"))


