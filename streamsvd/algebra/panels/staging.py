"""What a store needs of the panels: the staged panels made the basis, listed, let go.

Module functions taking the :class:`~streamsvd.algebra.panels.basis.PanelBasis`, its
staging part of :class:`~streamsvd.algebra.interface.BasisStaging` (the basis binds each as
its method of the same name): :func:`stage_new` writes the new columns as a panel and
:func:`swap` makes the compacted panel the basis, :func:`discard_planned` removes what an
abandoned plan wrote; :func:`commit_arrays` lists the panels a commit refers to (each
with its checksummed zarr copy, :func:`_seal`) and :func:`restore` reads that list back;
:func:`adopt` copies another basis's columns; :func:`release` and :func:`collect` delete
the panels no recent commit refers to, :func:`drop_scratch` the raw files kept to be
written over.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from streamsvd.algebra.panels.zarr_io import Region
from streamsvd.errors import StoreFormatError

if TYPE_CHECKING:
    from streamsvd.algebra.panels.basis import PanelBasis

__all__ = [
    "adopt",
    "collect",
    "commit_arrays",
    "discard_planned",
    "drop_scratch",
    "release",
    "restore",
    "stage_new",
    "swap",
]

# the basis's own logger: what the staging logs is named as before the move
logger = logging.getLogger("streamsvd.algebra.panels.basis")


def swap(basis: PanelBasis, p: int) -> None:
    """Make the panel written by :meth:`compact_planned` the stored basis."""
    assert basis._staged_compact is not None and basis._staged_compact[1] == p
    name, _ = basis._staged_compact
    basis._retired += [old for old in basis.panels if old != name]
    basis.panels, basis.widths = ([name], [p]) if p else ([], [])
    basis._staged_compact, basis._ws, basis._mws = None, None, None
    basis._drop_block()
    basis.compactions += 1
    logger.info("compacted the basis to one panel of width %d", p)


def discard_planned(basis: PanelBasis) -> None:
    """Remove the panels an abandoned plan wrote (and the next block it read ahead)."""
    basis._expected = None
    basis._drop_read_ahead()
    for staged in (basis._staged_new, basis._staged_compact):
        if staged is not None and staged[0]:
            basis.files.delete(staged[0])
    basis._staged_new = basis._staged_compact = None
    basis._drop_block()


def stage_new(basis: PanelBasis, r: int) -> None:
    """Write the first ``r`` workspace columns as a new panel (before any commit)."""
    if r:
        basis._staged_new = basis._write(basis.planned_new(r)[0])


def _seal(basis: PanelBasis, names: list[str]) -> None:
    """Write a zarr copy of each raw panel of ``names`` that has none (for a commit).

    The copy lies in the panel's own directory, beside the raw file, which the
    passes go on using; both go when the panel is deleted.
    """
    import dask.array as da

    todo = basis.files.unsealed(names)
    if not todo:
        return
    basis.rows.compute([
        # a Region takes the rows written into it (dask stores into any __setitem__)
        da.store(basis.rows.panel(name), cast(Any, Region(basis.files.zarr_copy(name))),
                 lock=False, compute=False)
        for name in todo
    ])
    basis.files.sealed.update(todo)


def commit_arrays(
    basis: PanelBasis, r: int, *, compacted: bool
) -> tuple[dict[str, np.ndarray], dict]:
    """Return what a commit writes: no array, the planned list of panels.

    Each raw panel of the list gets its zarr copy first (:meth:`_seal`), so a commit
    only ever lists panels that a reopened store can read and check.
    """
    if compacted:
        assert basis._staged_compact is not None
        name, p = basis._staged_compact
        panels, widths = ([name], [p]) if p else ([], [])
    elif r:
        assert basis._staged_new is not None
        panels = basis.panels + [basis._staged_new[0]]
        widths = basis.widths + [basis._staged_new[1]]
    else:
        panels, widths = list(basis.panels), list(basis.widths)
    basis._seal(panels)
    return {}, {"panels": panels, "widths": widths, "chunk_rows": basis.chunk_rows}


def restore(basis: PanelBasis, arrays: dict[str, np.ndarray], attrs: dict) -> None:
    """Load the list of panels a commit wrote, checking each panel's shape."""
    basis.panels = [str(p) for p in attrs["panels"]]
    basis.widths = [int(w) for w in attrs["widths"]]
    for name, width in zip(basis.panels, basis.widths, strict=True):
        z = basis.files.open(name)
        if z.shape != (basis.n, width):
            raise StoreFormatError(
                f"`path` {basis.root} is damaged: panel {name} has shape {z.shape}, "
                f"expected {(basis.n, width)}. Restore the store from a copy."
            )


def adopt(basis: PanelBasis, other: PanelBasis) -> None:
    """Hold a copy of ``other``'s stored columns, written as one panel of this root."""
    Q = other.rows.stacked(other.panels)
    if Q is None:
        basis.panels, basis.widths = [], []
        return
    name, width = basis._write(basis.rows.rows_of(Q))
    basis.panels, basis.widths = [name], [width]


def release(basis: PanelBasis, committed: Sequence[dict]) -> None:
    """Let go of the panels a compaction replaced that none of these commits refers to.

    Only panels this basis wrote and replaced go, so a work directory shared with
    other data is safe; without a store the replaced basis goes at once. A raw file
    that no commit ever listed is kept for the next compaction to write over
    (:meth:`~streamsvd.algebra.panels.files.PanelFiles.let_go`), the others are deleted.
    """
    live = set(basis.panels).union(*(attrs.get("panels", ()) for attrs in committed))
    keep = [name for name in basis._retired if name in live]
    for name in basis._retired:
        if name not in live:
            basis.files.let_go(name)
    basis._retired = keep


def collect(basis: PanelBasis, committed: Sequence[dict]) -> None:
    """Delete the panels that neither the state nor these commits' attributes refer to."""
    live = set(basis.panels).union(*(attrs.get("panels", ()) for attrs in committed))
    live.update(spare.name for spare in basis.files.spares)
    if basis._read_ahead is not None:
        live.add(basis._read_ahead.scratch)
    for entry in basis.files.listed():
        if entry not in live:
            logger.debug("removing unreferenced panel %s of %s", entry, basis.root)
            basis.files.delete(entry)


def drop_scratch(basis: PanelBasis) -> None:
    """Remove the raw files kept to be written over (made again when needed)."""
    basis._drop_read_ahead()
    basis.files.drop_spares()
