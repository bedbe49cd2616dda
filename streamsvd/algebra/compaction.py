"""A compaction's columns and their ``M`` image: ``[A_1, A_2, ...] G`` and ``M`` of it.

:func:`write_compaction` writes the combined columns (at once, :func:`combine`, or a slab
of rows at a time over the parts themselves, :func:`combine_by_slabs`) and their image:
``M`` applied to them, or the parts' images combined by ``G`` when that costs less and
keeps the image within a few ``eps`` of the columns' (the in-memory basis,
:class:`~streamsvd.algebra.memory.MemoryBasis`, stores both).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg.blas as blas

from streamsvd._util.slabs import row_slabs
from streamsvd.algebra.blas import apply_into as m_apply_into
from streamsvd.algebra.inner import InnerProduct

__all__ = ["combine", "combine_by_slabs", "write_compaction"]

Combine = Callable[[np.ndarray, list[np.ndarray], np.ndarray], None]

# a compaction's image is combined from the parts' images only while the combination
# amplifies the rounding of its terms at most this much: column j of [M A_1, ...] G errs
# by about eps sum_i |g_ij| ||M a_i||, and an image that is not M applied to the column
# stored makes every product with the basis (projections, its Gram) err by as much,
# unseen by the orthogonality measured from them. A Gram path's G = W Lambda^(-1/2)
# scales weak kept terms up by 1e5 and more: combined, the image of the compacted basis
# was 5e-11 to 1.3e-10 off its columns (tests/algebra/test_memory.py). In a stream under
# weights over four decades the basis then measured its loss of orthogonality at 1e-16
# where its columns had 1.1e-12 (243 n eps, over reorth_tol, never corrected); under the
# mass matrix of linear elements of sizes 1e-5 to 1 (condition 3.9e4) it drifted to
# 1.6e7 n eps by its 311th update (of 345), accepting directions it already held, until
# the factorisation of finalize failed (a stream in a scan by hand; the property test of
# trajectories under an ill-conditioned mass matrix, tests/stream/test_guarantees.py)
_COMBINED_IMAGE_MAX = 8.0


def combine(out: np.ndarray, sources: list[np.ndarray], G: np.ndarray) -> None:
    """Write ``[S_1, S_2, ...] G`` into ``out``: one product per source, none concatenated."""
    row = 0
    for i, source in enumerate(sources):
        Gi = G[row:row + source.shape[1]]
        row += source.shape[1]
        if i == 0:
            np.matmul(source, Gi, out=out)
            continue
        if not source.flags.f_contiguous:
            out += source @ Gi
            continue
        res = blas.dgemm(1.0, source, Gi, beta=1.0, c=out, overwrite_c=1)
        if not np.shares_memory(res, out):
            out[...] = res


def combine_by_slabs(out: np.ndarray, sources: list[np.ndarray], G: np.ndarray) -> None:
    """Write ``[S_1, S_2, ...] G`` into ``out`` a slab of rows at a time.

    ``out`` may share its rows with the sources (a compaction written over the stored
    columns): each slab of the result is formed from the sources' rows, then written.
    """
    p = G.shape[1]
    starts = row_slabs(out)
    slabs = [np.empty((starts.step, p), order="F") for _ in sources]
    for i in starts:
        rows = slice(i, min(i + starts.step, out.shape[0]))
        h = rows.stop - i
        parts = slabs if h == starts.step else [np.empty((h, p), order="F") for _ in sources]
        row = 0
        for source, slab in zip(sources, parts, strict=True):
            np.matmul(source[rows], G[row:row + source.shape[1]], out=slab)
            row += source.shape[1]
        for slab in parts[1:]:
            parts[0] += slab
        out[rows] = parts[0]


def _combines_images(spread: np.ndarray | None, Q: np.ndarray) -> bool:
    """Whether a compaction combines the parts' images (True) or applies ``M`` to ``Q``.

    ``spread`` is :func:`_rounding_spread` (None: ``M`` is applied); the
    images are combined when no column of ``Q`` is smaller than its spread by more than
    :data:`_COMBINED_IMAGE_MAX`.
    """
    if spread is None:
        return False
    written = np.linalg.norm(Q, axis=0)
    return bool(np.all(spread <= _COMBINED_IMAGE_MAX * written))


def write_compaction(inner: InnerProduct, Q: np.ndarray, MQ: np.ndarray, G: np.ndarray,
                     parts: list[tuple[np.ndarray, np.ndarray]], *, combine: Combine) -> None:
    """Write ``[A_1, A_2, ...] G`` into ``Q`` and its ``M`` image into ``MQ``.

    ``parts`` are the ``(A_i, M A_i)`` whose columns the rows of ``G`` combine, in order;
    ``combine(out, sources, G)`` writes ``[S_1, S_2, ...] G`` (:func:`combine`, or
    :func:`combine_by_slabs` when ``Q`` holds the parts' own rows). The image is ``M``
    applied to ``Q``, or the parts' images combined by ``G`` when that costs less and
    keeps the image within a few ``eps`` of ``Q``'s (:func:`_combines_images`).
    """
    spread = _rounding_spread(inner, G, parts)  # before Q is written (over the parts)
    combine(Q, [A for A, _ in parts], G)
    if inner.is_euclidean:
        return
    if _combines_images(spread, Q):
        combine(MQ, [MA for _, MA in parts], G)
    else:
        m_apply_into(inner, Q, MQ)


def _rounding_spread(inner: InnerProduct, G: np.ndarray,
                     parts: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """Return ``sum_i |g_ij| ||a_i||`` for each column ``j`` of ``[A_1, ...] G``, or None.

    None when the image is ``M`` applied whatever the combination: the Euclidean
    product has no image, and an ``M`` whose product costs no more per entry than
    the combination (``entries_per_row`` at most ``G``'s rows: a diagonal, or a
    sparse ``M`` beside a basis wider than its rows' entries) is applied.
    """
    per_row = getattr(inner, "entries_per_row", None)
    if inner.is_euclidean or (per_row is not None and per_row <= G.shape[0]):
        return None
    norms = np.concatenate([np.linalg.norm(A, axis=0) for A, _ in parts])
    return np.abs(G).T @ norms
