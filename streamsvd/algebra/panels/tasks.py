"""The tasks of the tall mode's passes: one row chunk of the basis and of a block each.

:class:`~streamsvd.algebra.panels.basis.PanelBasis` maps them over the row chunks of its panels
(``dask.array.map_blocks``); each reads its chunk of every input, writes what its pass
writes, and returns its share of the small products, which a reduction sums. Plain
functions over arrays, so that a worker of a cluster runs them as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "chunk_compaction", "chunk_compaction_and_products", "chunk_products", "combined",
]


def chunk_products(x: np.ndarray, *rest: np.ndarray, weighted: bool, target: Any,
                   block_info: dict | None = None) -> np.ndarray:
    """Return ``[X^T M X; MQ_1^T X; ...]`` of one row chunk; write the chunk to ``target``.

    ``x`` is the block's chunk, ``rest`` the panels' chunks (then the weights' when
    ``weighted``); ``target`` is the scratch copy of a block read from its source, or
    None.
    """
    if target is not None:
        assert block_info is not None
        target[slice(*block_info[0]["array-location"][0])] = x
    panels = rest[:-1] if weighted else rest
    x64 = np.asarray(x, dtype=np.float64)
    mx = x64 * rest[-1] if weighted else x64
    b = x.shape[1]
    out = np.empty((b + sum(q.shape[1] for q in panels), b))
    out[:b] = mx.T @ x64  # a rank-k update (syrk) when Euclidean
    row = b
    for q in panels:
        out[row:row + q.shape[1]] = q.T @ mx
        row += q.shape[1]
    return out


def chunk_compaction(*parts: np.ndarray, weighted: bool, target: Any, G: np.ndarray,
                     block_info: dict | None = None) -> np.ndarray:
    """Write one row chunk of ``[Q_1, ..., X] G`` to ``target``; return its ``P^T M P``."""
    assert block_info is not None
    P = combined(parts[:-1] if weighted else parts, G)
    target[slice(*block_info[0]["array-location"][0])] = P
    return (P * parts[-1]).T @ P if weighted else P.T @ P


def chunk_compaction_and_products(*parts: np.ndarray, weighted: bool, target: Any,
                                  next_target: Any, G: np.ndarray,
                                  block_info: dict | None = None) -> np.ndarray:
    """One row chunk of :func:`chunk_compaction` and of the next block's :func:`chunk_products`.

    ``parts`` are the chunks of ``Q_1, ..., X``, then the next block's ``x`` (then the
    weights' when ``weighted``). Writes ``P = [Q_1, ..., X] G`` to ``target`` and ``x``
    to ``next_target``; returns ``[[P^T M P, P^T M x], [0, x^T M x]]``, each block
    formed as those two tasks form it.
    """
    assert block_info is not None
    *old, x = parts[:-1] if weighted else parts
    P = combined(old, G)
    rows = slice(*block_info[0]["array-location"][0])
    target[rows] = P
    next_target[rows] = x
    x64 = np.asarray(x, dtype=np.float64)
    mx = x64 * parts[-1] if weighted else x64
    p = P.shape[1]
    out = np.zeros((p + x.shape[1], p + x.shape[1]))
    out[:p, :p] = (P * parts[-1]).T @ P if weighted else P.T @ P
    out[:p, p:] = P.T @ mx
    out[p:, p:] = mx.T @ x64
    return out


def combined(parts: Sequence[np.ndarray], G: np.ndarray) -> np.ndarray:
    """Return ``[A_1, A_2, ...] G`` of row chunks, a product per part (none concatenated)."""
    first, *others = parts
    row = first.shape[1]
    P = np.asarray(first, dtype=np.float64) @ G[:row]
    for part in others:
        P += np.asarray(part, dtype=np.float64) @ G[row:row + part.shape[1]]
        row += part.shape[1]
    return P
