"""The backend interface: what an update needs from the n-sized factor of an expansion.

An update of a compressor touches the ``n``-sized data only through a handful of
operations (:class:`BasisAlgebra`; how a planned basis is switched to and committed is
:class:`BasisStaging`), all BLAS-3 (written once in :mod:`streamsvd.engine.update`, as
pyMOR writes ``gram_schmidt`` once over its vector arrays):

* ``project(X, G)``: ``G^T (MQ^T X)``, the coefficients of a block on the basis ``Q G``;
* ``subtract(X, G, C)``: ``X -= Q (G C)``;
* ``residual_products(Z, MZ)``: ``MQ^T Z`` and ``Z^T M Z``, what a projection left
  along the basis and the residual's Gram (one product over ``[MQ, MZ]`` in memory);
* ``workspace(b)``: room for ``b`` new columns right after the stored ones, where a block
  is orthonormalised in place; ``accept(r)`` makes the first ``r`` of them basis columns
  (these four and ``width`` are :class:`BasisProducts`, what block Gram-Schmidt needs,
  which a basis with directions found beside it presents as well:
  :mod:`streamsvd.linalg.slices`);
* ``compact_planned(G, r)`` then ``swap(p)``: ``Q <- [Q, Y_r] G`` (and ``M Q`` likewise),
  written aside first so that nothing stored changes before ``swap``; its Gram is
  measured from the written columns;
* ``block_products(X)`` then ``compact_with_block(G)``: the Gram path's two passes
  (:mod:`streamsvd.engine.update_gram`): the block's Gram ``X^T M X`` and its projection
  ``MQ^T X`` with the block staged as it is (in memory: referenced, not copied; a block
  read by row chunks: written once to a scratch panel as it is read), then
  ``Q <- [Q, X] G`` written aside like ``compact_planned`` (or over ``Q`` itself by a
  basis made to: :class:`~streamsvd.algebra.memory.MemoryBasis` with
  ``compact_in_place=True``). A basis that ``defers_gram`` (in memory, compacting aside)
  leaves the Gram of the columns it writes there to the next update, whose
  ``joint_products(X)`` copies the block beside ``Q`` and measures the Gram of ``[Q, X]``
  whole, ``Q^T M Q`` with it, in one product (``measure_gram()`` measures ``Q^T M Q``
  alone for whoever reads the basis before; :class:`~streamsvd.engine.state.State`); its
  ``products_beside(X)`` copies a narrow block beside ``Q`` and returns ``X^T M X`` and
  ``MQ^T X`` in one product, so that the update may keep the block as stored columns
  (``accept``) instead of compacting;
* ``stage_new(r)``, ``commit_arrays(...)``, ``restore(...)``, ``collect(...)``,
  ``release(...)``: what a commit to a store needs, what it may delete afterwards, and
  what an update replaced that no recent commit uses; ``compactions`` counts the swaps,
  so a commit tells the columns appended since the previous one (the others are
  unchanged) from a basis replaced whole.
* ``lincomb(G)``: ``Q G``. (The new block of the basis Gram, ``MQ^T Y``, is measured by
  Gram-Schmidt with ``project``, never formed again.)

A compressor does not choose its basis class: it is given a :class:`Backend`, which
makes its basis and says what that choice implies (the kind of store it writes, how a
copy gets its own basis, how a block reaches memory). The implementations are
:class:`~streamsvd.algebra.memory.MemoryBackend` (the default, its basis
:class:`~streamsvd.algebra.memory.MemoryBasis` in memory) and
:class:`~streamsvd.algebra.panels.backend.PanelBackend` (the basis in panels on disk).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from streamsvd.algebra.inner import InnerProduct

__all__ = [
    "Backend", "BasisAlgebra", "BasisBackend", "BasisProducts", "BasisStaging", "DeferredGram",
]


class BasisProducts(Protocol):
    """What block Gram-Schmidt needs of a basis (:mod:`streamsvd.linalg.extend`)."""

    @property
    def width(self) -> int:
        """Number of stored columns ``w``."""

    def project(self, X: np.ndarray, G: np.ndarray | None) -> np.ndarray:
        """Return ``G^T (MQ^T X)`` (``G = None``: the identity)."""

    def subtract(self, X: np.ndarray, G: np.ndarray | None, C: np.ndarray) -> None:
        """``X -= Q (G C)`` in place."""

    def residual_products(self, Z: np.ndarray, MZ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return ``MQ^T Z`` and ``Z^T M Z`` for a residual ``Z`` with image ``MZ``."""

    def workspace(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Return views ``(Y, MY)`` of ``b`` columns after the stored ones."""


class BasisAlgebra(BasisProducts, Protocol):
    """The products an update computes on the n-sized factor (module docstring)."""

    n: int

    @property
    def capacity(self) -> int:
        """Columns the basis can hold (stored and workspace) without growing its storage."""

    @property
    def pieces(self) -> int:
        """Separately stored pieces every product reads (panels out of core; 1 in memory)."""

    def compact_planned(self, G: np.ndarray, r: int) -> np.ndarray:
        """Write ``[Q, Y[:, :r]] G`` aside; return its Gram ``Q'^T M Q'``."""

    def block_products(self, X: Any, *, project: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Stage the block ``X``; return ``X^T M X`` and ``MQ^T X`` (None unless ``project``).

        A backend that reads ``X`` in one pass computes ``MQ^T X`` whatever ``project``.
        """

    def compact_with_block(self, G: np.ndarray) -> np.ndarray | None:
        """Write ``[Q, X] G`` aside (``X`` the staged block); return its Gram ``Q'^T M Q'``.

        None when the basis ``defers_gram``: the next update measures it.
        """

    @property
    def defers_gram(self) -> bool:
        """Whether ``compact_with_block`` leaves its Gram to be measured later.

        Such a basis is a :class:`DeferredGram` as well.
        """

    def lincomb(self, G: np.ndarray) -> np.ndarray:
        """Return ``Q G`` as a new array."""


class BasisStaging(Protocol):
    """How a planned basis becomes the stored one, and what a commit of it writes."""

    compactions: int  # number of swaps: the stored columns were all replaced

    def accept(self, r: int) -> None:
        """Make the first ``r`` workspace columns stored columns."""

    def stage_new(self, r: int) -> None:
        """Make the first ``r`` workspace columns durable before a commit refers to them."""

    def swap(self, p: int) -> None:
        """Make the basis written by ``compact_planned`` the stored one."""

    def discard_planned(self) -> None:
        """Forget what a plan staged (the update was abandoned)."""

    def commit_arrays(self, r: int, *, compacted: bool) -> tuple[dict[str, np.ndarray], dict]:
        """Return the arrays and attributes a commit of the planned basis writes."""

    def restore(self, arrays: dict[str, np.ndarray], attrs: dict) -> None:
        """Load the basis a commit wrote."""

    def collect(self, committed: Sequence[dict]) -> None:
        """Delete stored data that neither the state nor these commits' attributes use."""

    def release(self, committed: Sequence[dict]) -> None:
        """Delete what this basis replaced and none of these commits' attributes use."""

    def drop_scratch(self) -> None:
        """Free the scratch kept between updates (a compaction buffer, ...)."""


class BasisBackend(BasisAlgebra, BasisStaging, Protocol):
    """What an update needs from the n-sized factor: its algebra and its staging."""


class DeferredGram(BasisBackend, Protocol):
    """A basis whose compactions leave their Gram to be measured later (``defers_gram``)."""

    def joint_products(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X``, ``MQ^T X`` and ``Q^T M Q``."""

    def measure_gram(self) -> np.ndarray:
        """Return the Gram ``Q^T M Q`` of the stored columns, measured."""

    def products_beside(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stage ``X`` beside the basis; return ``X^T M X`` and ``MQ^T X`` (one product)."""

    @property
    def block_beside(self) -> bool:
        """Whether the staged block is in the workspace, after the stored columns."""


class Backend(Protocol):
    """Where a compressor keeps its n-sized factor, and what that choice implies."""

    kind: str  # recorded in the store: a store is reopened with the backend that wrote it
    temporary: bool  # the basis is removed by close() (nothing left to finalise)

    def new_basis(self, n: int, inner: InnerProduct) -> BasisBackend:
        """Return an empty basis for snapshots of size ``n`` in the inner product ``inner``."""

    def fresh(self) -> Backend:
        """Return a backend of the same settings whose basis is independent of this one."""

    def copied(self, basis: BasisBackend, blank: BasisBackend) -> BasisBackend:
        """Return ``basis`` copied for a compressor whose own empty basis is ``blank``."""

    def into_store(self, basis: BasisBackend, storage: Any) -> tuple[Backend, BasisBackend]:
        """Return the backend and basis that a new store in ``storage`` commits.

        This backend and ``basis`` when a commit writes the basis itself; else a copy
        of the basis written into ``storage``, which ``basis`` is left as it was.
        """

    def load(self, columns: Any, *, rows: int, first: int) -> Any:
        """Return ``columns`` checked as a block of ``rows`` rows the basis takes.

        An array, or a block its basis reads when the update needs it (``first``: its
        offset in the source, named when that read fails).
        """

    def in_memory(self, block: Any, *, check: bool = True) -> np.ndarray:
        """Return a block from :meth:`load` as a float64 array, its entries checked finite.

        ``check=False``: a block in memory already is returned as it is, its entries left
        to the caller (the exact path checks them from its columns' peaks, at no extra
        pass: :func:`~streamsvd._util.scaling.scale_into`).
        """

    def describe(self, basis: BasisBackend) -> str:
        """Return what ``repr`` of a compressor shows of its basis (may be empty)."""

    def close(self) -> None:
        """Release what the backend holds (a temporary directory, ...)."""

