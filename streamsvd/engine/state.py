"""The state of a compressor and the plan of one update, with its deferred writes.

State. ``U = Q coords`` with ``Q`` the stored basis (a
:class:`~streamsvd.algebra.interface.BasisBackend`,
``n x w``) and ``coords`` small (``w x p``, the coordinates of ``U`` on ``Q``);
``gram = Q^T M Q`` (small) measures orthogonality;
``R`` (``k x p``, ``k <= p``) is the core of the right factor: ``V = Y R`` with ``Y``
(``m x k``) orthonormal, so ``V^T V = R^T R``. When the right vectors are kept, ``Y`` is
stored, as ``Y = V0 Vp`` (:class:`~streamsvd.engine.rows.RowFactor`), never ``V`` itself: ``V``
carries the amplitudes, and rounding relative to the largest one would leave the right
vectors of amplitudes below ``eps sigma_1`` far from orthogonal, where every product
with ``Y`` is rounded relative to 1. Each update replaces ``Y`` by
``blockdiag(Y, Y_new) P`` with ``P`` orthonormal (a Householder QR of the core), so
``||Y^T Y - I||`` stays at rounding level, and at convergence the right singular vectors
``Y R diag(1 / ||r_i||)`` are orthonormal to the Jacobi tolerance ``sqrt(m) eps``.

An update (:mod:`streamsvd.engine.update`) computes a :class:`Plan` without writing;
:func:`stage_plan` makes its :class:`Writes` durable for a commit and :func:`apply_plan`
switches the state to it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import cast

import numpy as np
from scipy.linalg.lapack import dtrtri

from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisBackend, DeferredGram
from streamsvd.engine.bound import Bound
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.rows import RightFactor, RowAppend
from streamsvd.engine.truncation import Truncation
from streamsvd.errors import BrokenStateError

__all__ = [
    "Extents", "Plan", "State", "StepOptions", "Writes", "apply_plan", "gram_orthogonality",
    "stage_plan",
]


@dataclass(frozen=True)
class StepOptions:
    """Options of the update step (validated by the facade)."""

    inner: InnerProduct
    rule: str
    sweeps: int | None
    truncation: Truncation
    reject_tol: float
    reorth_tol: float


@dataclass
class State:
    """The state of a compressor (see the module docstring); mutated by :func:`apply_plan`.

    Attributes
    ----------
    basis, rows
        The n-sized factor ``Q`` and the m-sized factor ``Y`` (None without right vectors).
    coords : ndarray, shape (w, p)
        The coordinates of ``U`` on the stored basis: ``U = Q coords``.
    gram : ndarray, shape (w, w), or None
        ``Q^T M Q``, measured from the stored columns (orthogonality is
        ``||coords^T gram coords - I||``); None while it is pending.
    R : ndarray, shape (k, p)
        The core of the right factor: ``V = Y R``.
    m : int
        Snapshots represented.
    wasted_flops : float
        Flops spent on the stored columns beyond ``p`` since the last compaction (a
        compaction pays once they reach its own cost).
    bound : Bound
        The error bound's account (:mod:`streamsvd.engine.bound`).

    Notes
    -----
    After an update by the Gram path on an in-memory basis
    (:mod:`streamsvd.engine.update_gram`) the Gram of the basis just written is *pending*:
    ``gram`` is None, ``coords`` the identity and ``R`` the diagonal of the amplitudes
    (``U V^T = Q R^T Y^T`` holds; ``Q`` is orthonormal only to about ``eps lambda_1 /
    lambda_k``). The next update by that path measures it in one product with its block;
    anything else reads :meth:`settled` (measured once, cached, the state unchanged), and
    the other updates plan from :meth:`as_settled`. So a state reads the same whether or not
    it was read between two updates.
    """

    basis: BasisBackend
    rows: RightFactor | None
    coords: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    gram: np.ndarray | None = field(default_factory=lambda: np.zeros((0, 0)))
    R: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    m: int = 0
    wasted_flops: float = 0.0
    bound: Bound = field(default_factory=Bound)
    _settled: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = field(
        default=None, repr=False, compare=False)

    @property
    def rank(self) -> int:
        """Number of terms ``p``."""
        return int(self.coords.shape[1])

    @property
    def pending(self) -> bool:
        """Whether the Gram of the stored basis is not measured yet (class notes)."""
        return self.gram is None

    def settled(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``(coords, gram, R)`` with the Gram measured; the state is unchanged.

        For a pending state the Gram ``H = Q^T M Q`` is measured (one product over the
        basis, made once and kept until the state changes) and the loss of
        orthogonality moves into the small factors, as an update by the Gram path does:
        ``coords = L^(-T)``, ``R <- R L`` with ``H = L L^T``.
        """
        if self.gram is not None:
            return self.coords, self.gram, self.R
        if self._settled is None or self._settled[0] is not self.R:
            H = cast(DeferredGram, self.basis).measure_gram()
            try:
                L = np.linalg.cholesky(H)
            except np.linalg.LinAlgError as exc:
                raise BrokenStateError(
                    "the basis written by the last update lost its orthogonality "
                    "(its Gram matrix is not positive definite): its rounding exceeded "
                    "the bound that update checked. Start again, or reopen its store."
                ) from exc
            coords = dtrtri(L, lower=1)[0].T  # L^{-T}
            self._settled = (self.R, coords, H, self.R @ L)
        return self._settled[1], self._settled[2], self._settled[3]

    def as_settled(self) -> State:
        """Return this state with its Gram measured (:meth:`settled`).

        Itself, or a copy sharing its basis and rows: every update that does not take the
        Gram path plans from it, so that a plan that fails leaves the state as it was.
        """
        if not self.pending:
            return self
        coords, gram, R = self.settled()
        return replace(self, coords=coords, gram=gram, R=R, _settled=None)

    def orthogonality(self) -> float:
        """``||U^T M U - I||_2`` from the small Gram matrices."""
        coords, gram, _ = self.settled()
        return gram_orthogonality(coords, gram)

    def extents(self) -> Extents:
        """Return what the stored arrays hold, and the epochs in which they only grow."""
        rows = self.rows
        return Extents(
            compactions=self.basis.compactions, columns=self.basis.width,
            rewrites=0 if rows is None else rows.rewrites, rows=0 if rows is None else rows.m,
        )


@dataclass(frozen=True)
class Extents:
    """The stored columns of the basis and rows of ``Y``, with their epochs.

    Between two compactions the basis's columns only grow; between two rewrites (a rebase
    or a replacement) the stored rows of ``Y`` only grow (:mod:`streamsvd.stream.commits`).
    """

    compactions: int
    columns: int
    rewrites: int
    rows: int


@dataclass(frozen=True)
class Writes:
    """What applying a plan writes to the stored factors (nothing is written while planning).

    ``columns``: workspace columns that become stored columns of the basis; ``compacted``:
    the compacted basis (written in the backend's workspace by
    :meth:`~streamsvd.algebra.interface.BasisAlgebra.compact_planned`) replaces the stored one;
    ``rows``: new rows of ``Y`` and its new small factor; ``rows_replaced``: ``Y`` written
    anew whole (``add``, or a removal that orthonormalises the live rows again);
    ``dead_rows``: the stored rows no longer live (:mod:`streamsvd.engine.downdate`).
    """

    columns: int = 0
    compacted: bool = False
    rows: RowAppend | None = None
    rows_replaced: np.ndarray | None = None
    dead_rows: np.ndarray | None = None


@dataclass(frozen=True)
class Plan:
    """Everything an update computed: the small matrices, and the writes deferred to apply."""

    coords: np.ndarray
    gram: np.ndarray | None  # None: pending (the State's notes)
    R: np.ndarray
    m: int
    wasted_flops: float
    bound: Bound
    record: UpdateRecord
    writes: Writes


def stage_plan(state: State, plan: Plan) -> None:
    """Make the plan's new columns and rows durable before a commit refers to them.

    Nothing stored changes until :func:`apply_plan` (a rebase of the rows changes their
    representation, never ``V``).
    """
    w = plan.writes
    if not w.compacted:
        state.basis.stage_new(w.columns)
    if state.rows is not None and w.rows is not None:
        state.rows.stage(w.rows)


def apply_plan(state: State, plan: Plan) -> None:
    """Switch the state to the planned one, writing what the plan deferred."""
    w = plan.writes
    if w.compacted:
        state.basis.swap(plan.coords.shape[1])
    else:
        state.basis.accept(w.columns)
    if state.rows is not None:
        if w.rows_replaced is not None:
            state.rows.replace(w.rows_replaced)
        else:
            assert w.rows is not None
            state.rows.commit(w.rows)
            if w.dead_rows is not None:
                state.rows.dead = w.dead_rows
    state.coords, state.gram, state.R = plan.coords, plan.gram, plan.R
    state.m, state.wasted_flops, state.bound = plan.m, plan.wasted_flops, plan.bound
    state._settled = None


def gram_orthogonality(coords: np.ndarray, gram: np.ndarray) -> float:
    """``||coords^T gram coords - I||_2``: the largest eigenvalue modulus of a symmetric matrix."""
    p = coords.shape[1]
    if p == 0:
        return 0.0
    E = coords.T @ gram @ coords - np.eye(p)
    return float(np.max(np.abs(np.linalg.eigvalsh(0.5 * (E + E.T)))))
