"""Streaming compression: absorb snapshot blocks and low-rank increments.

A :class:`StreamCompressor` keeps the expansion ``A ~ U V^T`` of every snapshot seen so
far (columns of ``A``) with ``U`` orthonormal in the inner product ``M``. Each update

1. decomposes the new left vectors on the basis and orthonormalises their residual at
   BLAS-3 speed, rejecting directions below ``reject_tol``
   (:func:`streamsvd.gram_schmidt.extend_basis`);
2. runs ``sweeps`` rotation sweeps of the paper (Algorithm 2, rule ``"paper"`` or
   ``"jacobi"``) on a small core;
3. truncates the terms that fail ``||v_i|| >= eps``, ``||v_i|| >= rtol * ||v_1||`` or
   ``i <= max_rank`` (after the sweeps, on the sorted amplitudes), logging what was cut.

The step is written once (:mod:`streamsvd.update`) over the n-sized basis
(:mod:`streamsvd.basis`) and the m-sized right vectors (:mod:`streamsvd.rows`); this
class is the facade: options, properties, persistence.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from ._core import Truncation, UpdateRecord, r_factor, record_from_row
from ._scaling import safe_column_norms
from ._threads import blas_threads, check_threads
from ._validation import (
    as_float_array,
    check_choice,
    check_forget,
    check_nonnegative,
    check_nonnegative_int,
    check_positive_int,
    check_target,
)
from .basis import BasisBackend, MemoryBasis
from .bound import Bound
from .commits import CommitTracker
from .compress import fix_signs
from .downdate import (
    Ledger,
    bound_after_removal,
    intervals_add,
    intervals_contain,
    intervals_count_below,
    intervals_skip,
    plan_remove,
)
from .errors import InputError, StoreError, StoreFormatError, StoreMismatchError
from .expansion import Expansion
from .gram_schmidt import default_reject_tol
from .inner import InnerProduct, as_inner, check_same_inner, inner_arrays, inner_from_arrays
from .provenance import SourceRecord
from .rotations import RULES
from .rows import RowFactor
from .storage import open_storage
from .store import BasisStore, open_store
from .update import (
    Plan,
    State,
    StepOptions,
    apply_plan,
    plan_absorb,
    plan_add,
    plan_finalize,
    plan_merge,
)
from .update_gram import plan_absorb_by_gram

__all__ = ["StreamCompressor", "UpdateRecord", "summary_of"]

logger = logging.getLogger(__name__)

_EPS = np.finfo(np.float64).eps
KIND = "streamsvd.StreamCompressor"
# the target error's budget spent while streaming: HAPOD's split at omega = 0.9, whose
# root (here: finalize) spends omega of the budget and the updates before it the rest
STREAMING_SHARE = math.sqrt(1.0 - 0.9**2)
# version of the arrays a StreamCompressor commits (3: Q, V0, history appended; 4: V0 Vp
# is the orthonormal factor Y of V = Y R)
LAYOUT = 4


def _norm(x: np.ndarray) -> float:
    """``||x||_2`` without overflow."""
    top = float(np.max(np.abs(x))) if x.size else 0.0
    if top == 0.0:
        return 0.0
    return top * float(np.linalg.norm(x / top))


def stored_options(attrs: dict[str, Any]) -> dict[str, Any]:
    """Return the compressor options recorded in a store's attributes.

    Stores written before ``oversampling`` existed truncated to ``max_rank`` at every
    update: they continue so; stores written before ``target_error`` existed have none,
    and those written before ``window`` and ``forget`` take the constructor's defaults
    (no window, nothing forgotten).
    """
    defaults = {
        "oversampling": 0, "target_error": None, "error_measure": "relative",
        "streaming_share": 0.9,
    }
    return {**defaults, **attrs["options"]}
def _stored_inner(path: Any, state: Any) -> InnerProduct:
    """Return the inner product a store keeps; Euclidean when it keeps none."""
    stored = inner_from_arrays(state.arrays)
    if stored is None:
        return as_inner(None)
    if stored.fingerprint != state.inner_fingerprint:
        raise StoreFormatError(
            f"`path` {path!s} is damaged: the inner product it keeps does not match its "
            f"fingerprint {state.inner_fingerprint[:12]}... Restore the store from a copy."
        )
    return stored


class StreamCompressor:
    """Absorb snapshots (columns) and low-rank increments into an orthonormal expansion.

    Parameters
    ----------
    n : int
        Size of one snapshot.
    inner : None, array_like, sparse matrix or InnerProduct
        Inner product ``M`` in which ``U`` is orthonormal (Euclidean by default).
    eps : float
        Absolute threshold: terms with ``||v_i|| < eps`` are cut (Algorithm 3).
    rtol : float, optional
        Relative threshold: terms with ``||v_i|| < rtol * ||v_1||`` are cut.
    max_rank : int, optional
        Keep this many terms in the end (the ones of largest amplitude). While streaming,
        ``max_rank + oversampling`` terms are kept, and :meth:`finalize` (called by
        :meth:`close`) cuts to ``max_rank`` once the core is converged: a cap applied at
        every update compounds its errors, the oversampled stream much less (measured in
        ``bench/README.md``, "The SVD by default"). An update whose cut by the cap would
        drop terms that the thresholds keep first sweeps its core to convergence (Jacobi
        rule), so that the cut is the optimal one of the current expansion.
    oversampling : int
        Extra terms kept while streaming with ``max_rank`` (default 10; 0 truncates to
        ``max_rank`` at every update, as IncrementalPCA does). Ignored without
        ``max_rank``.
    rule : {"paper", "jacobi"}
        Rotation rule of the sweeps (see :func:`streamsvd.compress`).
    sweeps : int or None
        Rotation sweeps per update; ``None`` sweeps to convergence (the exact SVD of the
        current expansion, as Brand's incremental SVD).
    reject_tol : float, optional
        Gram-Schmidt rejection threshold relative to a column's norm; default ``n * eps``.
    reorth_tol : float, optional
        Re-orthonormalise when ``||U^T M U - I||_2`` exceeds it; default ``10 n eps``.
    right_vectors : bool
        Keep the right vectors ``V`` (default). With ``False`` only ``U``, the amplitudes
        and the small core ``R`` (``V^T V = R^T R``) are kept, as IncrementalPCA keeps no
        per-sample coefficients: :attr:`expansion` and :meth:`add` are then unavailable,
        and nothing held grows with the number of snapshots.
    store : str, path-like or storage, optional
        Create a zarr basis store there (a local path, or a URL such as
        ``s3://bucket/basis.zarr``: see :mod:`streamsvd.store`) and commit the state
        to it every ``commit_every`` updates; a commit writes only what changed since the
        previous one (new basis columns, new rows of ``V0`` and of the history, the small
        state; :mod:`streamsvd.commits`). An existing store is continued with
        :meth:`StreamCompressor.open`, not overwritten.
    commit_every : int
        Updates between two commits (the last ones are committed by :meth:`flush` or
        :meth:`close`).
    source_record : SourceRecord, optional
        Where the snapshots come from (path, dataset, shape), kept in the attributes of
        every commit as :attr:`source_record` (the command line refuses to resume a
        store from another source). It may be replaced before a commit, when a resumed
        stream reads a source that gained columns.
    storage_options : dict, optional
        Options of the object store of a URL ``store``, as for
        :func:`streamsvd.open_storage`.
    target_error : float, optional
        The error the result must meet, in ``error_measure``: the fewest terms are kept
        whose guaranteed bound meets it. While streaming, each update cuts the smallest
        terms of its converged core while the bound stays within ``streaming_share`` of
        the budget (which grows with the snapshots seen: the stream's length need not be
        known); :meth:`finalize` makes the optimal cut within the whole budget. Not
        combined with ``eps`` or ``rtol``; ``max_rank`` still caps the rank (then the
        target may be missed: :attr:`target_met` says so, and a warning is logged).
    error_measure : {"relative", "mean_l2", "absolute"}
        ``"relative"``: ``||A - U V^T||_F <= target_error ||A||_F`` (the energy
        criterion); ``"mean_l2"``: ``sqrt(sum_j ||a_j - U V^T e_j||_M^2 / m) <=
        target_error``, the measure of pyMOR's HAPOD; ``"absolute"``:
        ``||A - U V^T||_F <= target_error``. Norms are those of ``M``.
    streaming_share : float
        The share of the budget the stream may spend (0 < share <= 1); the rest,
        ``sqrt(1 - share^2)``, is left to the final optimal cut. The default,
        ``sqrt(1 - 0.9^2) = 0.436``, is the split of pyMOR's HAPOD at its ``omega = 0.9``
        (``omega`` is the root's share there): on pyMOR's Burgers demo it keeps the
        optimal number of modes, where a share of 0.9 kept up to one more in memory
        and up to four more in the tree (``bench/README.md``).
    window : int, optional
        Keep the ``window`` most recent snapshots only: each :meth:`absorb` first
        removes (:meth:`remove`) the oldest ones that would fall out, so the expansion is
        that of the last ``window`` snapshots. Needs ``right_vectors=True``.
    forget : float
        Forgetting factor ``gamma`` in (0, 1] (1: none): each snapshot is weighted by
        ``gamma`` to the number of snapshots absorbed after it, so the expansion is that
        of ``[gamma^(m-1) a_1, ..., gamma a_(m-1), a_m]`` whatever the block sizes (the
        core, the error bound and the discarded norm are scaled by ``gamma^b`` before a
        block of ``b`` columns, weighted ``gamma^(b-1), ..., 1``, is absorbed).
    threads : int or None
        BLAS threads of an update (default 1; ``None`` leaves the BLAS as it is set).
        One thread is never much slower than all cores and is much faster on a machine
        where other work runs (measured in ``bench/README.md``, "BLAS threads"); it is
        a setting of this process, not recorded in the store.

    The result is the SVD: :meth:`close` (or the end of a ``with`` block that raised
    nothing) runs :meth:`finalize`, which converges the small core and truncates it
    optimally, then commits. Call ``close(finalize=False)`` to keep the streamed state
    as it is.

    Notes
    -----
    Store contents: besides the state, the first commit writes the data of the inner
    product (weights, a dense matrix or a sparse one's CSR arrays), which later commits
    keep unchanged, so :meth:`open` needs no ``inner`` (an inner product of another
    class than the three of :mod:`streamsvd.inner` is recorded by fingerprint only).

    Error bound: :attr:`error_bound` is guaranteed, ``||A - U V^T||_F <= error_bound``
    in the norm of ``M`` after every update (theorem in :mod:`streamsvd.bound`); at
    convergence (``sweeps=None``) it is the Pythagorean ``sqrt(sum of discarded
    energies)``.

    Cost: an update costs nothing in the number of snapshots already absorbed: the
    right vectors are kept as ``V = Y R`` with ``Y`` orthonormal, appended in Brand's form
    ``Y = V0 Vp`` (:mod:`streamsvd.rows`), the
    basis lives in a buffer grown geometrically (:mod:`streamsvd.basis`), and the
    rotations act on small matrices (:mod:`streamsvd.update` has the flop count).

    Orthogonality: ``H = Q^T M Q`` of the stored basis is kept (exactly, by a Gram of
    the stored columns at each compaction), so ``||U^T M U - I||_2`` is measured after
    every update and recorded in :attr:`history`; above ``reorth_tol`` the basis is
    re-orthonormalised through the Cholesky factor of that small Gram
    (``U <- U L^{-T}``, ``V <- V L``, which leaves ``U V^T`` unchanged).
    """

    def __init__(
        self,
        n: int,
        *,
        inner: Any = None,
        eps: float = 0.0,
        rtol: float | None = None,
        max_rank: int | None = None,
        oversampling: int = 10,
        rule: str = "paper",
        sweeps: int | None = 1,
        reject_tol: float | None = None,
        reorth_tol: float | None = None,
        right_vectors: bool = True,
        store: Any = None,
        commit_every: int = 1,
        source_record: SourceRecord | None = None,
        storage_options: dict[str, Any] | None = None,
        threads: int | None = 1,
        target_error: float | None = None,
        error_measure: str = "relative",
        streaming_share: float = STREAMING_SHARE,
        window: int | None = None,
        forget: float = 1.0,
    ) -> None:
        self.n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        self.threads = check_threads(threads)
        self.inner: InnerProduct = as_inner(inner, self.n)
        if source_record is not None and not isinstance(source_record, SourceRecord):
            raise InputError(
                f"`source_record` must be a SourceRecord or None; got "
                f"{type(source_record).__name__}. Build one with `SourceRecord.of(...)`."
            )
        self.source_record = source_record
        self.eps = check_nonnegative(eps, "eps")
        self.rtol = None if rtol is None else check_nonnegative(rtol, "rtol")
        self.max_rank = check_positive_int(max_rank, "max_rank", allow_none=True)
        self.oversampling = check_nonnegative_int(oversampling, "oversampling")
        self.rule = check_choice(rule, "rule", RULES)
        self.sweeps = check_positive_int(sweeps, "sweeps", allow_none=True)
        self.target_error, self.error_measure, self.streaming_share = check_target(
            target_error, error_measure, streaming_share, eps=self.eps, rtol=self.rtol
        )
        self.reject_tol = (
            default_reject_tol(self.n)
            if reject_tol is None
            else check_nonnegative(reject_tol, "reject_tol")
        )
        self.reorth_tol = (
            10 * self.n * _EPS
            if reorth_tol is None
            else check_nonnegative(reorth_tol, "reorth_tol")
        )
        if not isinstance(right_vectors, bool | np.bool_):
            raise InputError(f"`right_vectors` must be True or False; got {right_vectors!r}.")
        self.right_vectors = bool(right_vectors)
        self.window = check_positive_int(window, "window", allow_none=True)
        self.forget = check_forget(forget)
        if self.window is not None and not self.right_vectors:
            raise InputError(
                f"`window` needs the right vectors to remove the snapshots that leave it; "
                f"got window={self.window} with right_vectors=False. Pass "
                "`right_vectors=True`, or use `forget` (which needs none)."
            )
        self.commit_every = int(check_positive_int(commit_every, "commit_every"))  # type: ignore[arg-type]
        self._opts = StepOptions(
            inner=self.inner, rule=self.rule, sweeps=self.sweeps,
            truncation=Truncation(
                self.eps, self.rtol, self.streaming_rank, self.target_error,
                self.error_measure, self.streaming_share,
            ),
            reject_tol=self.reject_tol, reorth_tol=self.reorth_tol,
        )
        self._state = State(
            basis=self._new_basis(),
            rows=RowFactor() if self.right_vectors else None,
        )
        self._history: list[UpdateRecord] = []
        self._version = 0  # increases with every state change (for the exposure cache)
        self._exposure: tuple[int, np.ndarray, np.ndarray] | None = None
        self.source_offset = 0
        # global indices of the snapshots removed (sorted disjoint [start, stop) rows),
        # and the error ledger (streamsvd.downdate); the values a planned update leads to
        self._removed = np.zeros((0, 2), dtype=np.int64)
        self._ledger = Ledger.start(0, 0.0)
        self._pending: tuple[Ledger, np.ndarray] = (self._ledger, self._removed)
        self._store: BasisStore | None = None
        self._uncommitted = 0
        self._tracker = CommitTracker()
        if store is not None:
            self._store = BasisStore.create(
                store, n=self.n, dtype="float64", inner_fingerprint=self.inner.fingerprint,
                attrs=self._attrs(None), storage_options=storage_options,
            )
            try:
                self._commit(None, self.source_offset)
            except BaseException:
                self._store.close()  # release the lock of the store left at generation 0
                self._store = None
                raise

    KIND = KIND

    @property
    def streaming_rank(self) -> int | None:
        """Most terms kept between updates: ``max_rank + oversampling`` (None: no cap)."""
        return None if self.max_rank is None else self.max_rank + self.oversampling
    @functools.cached_property
    def _inner_data(self) -> dict[str, np.ndarray]:
        """The inner product's arrays that the store keeps (none for an unknown class)."""
        return inner_arrays(self.inner) or {}

    def _new_basis(self) -> BasisBackend:
        """Return the n-sized backend of this facade (in memory)."""
        return MemoryBasis(self.n, self.inner)

    # ------------------------------------------------------------------ persistence
    @classmethod
    def open(
        cls, path: Any, *, inner: Any = None, mode: str = "a",
        storage_options: dict[str, Any] | None = None,
    ) -> StreamCompressor:
        """Reopen a compressor from its store, exactly as it was at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``StreamCompressor(..., store=path)``.
        inner : optional
            The inner product the store was written with (checked by fingerprint). When
            omitted, the one the store keeps (Euclidean if none); a store written before
            stores kept it, with another inner product than the Euclidean one, needs it.
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock); ``"r"`` reads only.
        storage_options : dict, optional
            Options of the object store of a URL ``path`` (``s3://``: ``key``,
            ``secret``, ``endpoint_url``, ...), as for :func:`streamsvd.open_storage`.
        """
        return cls._open(path, inner=inner, mode=mode, backend={},
                         storage_options=storage_options)

    @classmethod
    def _open(cls, path: Any, *, inner: Any, mode: str, backend: dict[str, Any],
              storage_options: dict[str, Any] | None = None) -> Any:
        """Open a store and restore the compressor it holds (``backend``: for ``_reopen``)."""
        mode = check_choice(mode, "mode", ("a", "r"))
        path = open_storage(path, storage_options=storage_options)
        st = open_store(path, mode)  # type: ignore[arg-type]
        try:
            state = st.read()
            attrs = state.attrs
            if attrs.get("kind") != cls.KIND:
                raise StoreMismatchError(
                    f"`path` {path!s} holds a basis store that was not written by a "
                    f"{cls.__name__} (its kind is {attrs.get('kind')!r}); open any "
                    "compressor's store with "
                    "`streamsvd.parallel.open_compressor`, any other with "
                    "`streamsvd.store.open_store`."
                )
            if attrs.get("layout") != LAYOUT:
                raise StoreFormatError(
                    f"`path` {path!s} holds a StreamCompressor of layout "
                    f"{attrs.get('layout', 1)!r}, written by another version of streamsvd; "
                    f"this version reads layout {LAYOUT}. Ingest the snapshots again into a "
                    "new store."
                )
            ip = _stored_inner(path, state) if inner is None else as_inner(inner, state.n)
            if inner is None and ip.fingerprint != state.inner_fingerprint:
                raise StoreMismatchError(
                    f"`inner` must be given: the store {path!s} was written with an inner "
                    f"product (fingerprint {state.inner_fingerprint[:12]}...) that it does not "
                    "keep (an earlier version of streamsvd, or an inner product of another "
                    "class). Pass the same matrix or weights."
                )
            if ip.fingerprint != state.inner_fingerprint:
                raise StoreMismatchError(
                    f"`inner` must be the inner product the store {path!s} was written with "
                    f"(fingerprint {state.inner_fingerprint[:12]}...); got {ip!r}. Pass the "
                    "same matrix or weights."
                )
            sc = cls._reopen(state.n, ip, attrs, path, **backend)
            sc._restore(state.arrays, attrs)
            sc.source_record = SourceRecord.from_attrs(attrs.get("source"))
            sc._store = st
            if state.arrays:
                sc._tracker.restored(
                    state.generation, sc._state, state.arrays["history"],
                    inner=all(name in state.arrays for name in sc._inner_data),
                )
            sc._reopened(mode)
        except BaseException:
            st.close()
            raise
        return sc

    @classmethod
    def _reopen(
        cls, n: int, inner: InnerProduct, attrs: dict[str, Any], path: Any, **backend: Any
    ) -> Any:
        """Return a compressor with a store's options, before its state is restored."""
        return cls(n, inner=inner, **stored_options(attrs))

    def _reopened(self, mode: str) -> None:
        """Run once a store was reopened (a backend may clean what it left)."""

    def copy(self) -> StreamCompressor:
        """Return an independent copy of the compressor (without its store)."""
        return self._copy_with()

    def _copy_with(self, **changes: Any) -> StreamCompressor:
        """Return an independent copy whose options differ by ``changes``."""
        out = self._empty_copy(**changes)
        basis = self._copied_basis(out._state.basis)
        out._state = copy.deepcopy(self._state, {id(self._state.basis): basis})
        out._history = list(self._history)
        out.source_offset = self.source_offset
        out._removed, out._ledger = self._removed, self._ledger
        return out

    def _empty_copy(self, **changes: Any) -> StreamCompressor:
        """Return a compressor with these options (but ``changes``), nothing absorbed."""
        return StreamCompressor(self.n, inner=self.inner, source_record=self.source_record,
                                threads=self.threads, **{**self._options(), **changes})

    def _copied_basis(self, blank: BasisBackend) -> BasisBackend:
        """Return the stored basis copied for :meth:`copy` (``blank``: the copy's own)."""
        return copy.deepcopy(self._state.basis)

    def save(self, path: Any) -> None:
        """Write the compressor into a new store at ``path`` and keep committing there.

        One commit of the current state, bit for bit (no update is run). The compressor
        must not have a store already.
        """
        if self._store is not None:
            raise StoreError(
                f"this compressor already commits to {self._store.path}; `save` writes a "
                "compressor that has no store."
            )
        self._store = BasisStore.create(
            path, n=self.n, dtype="float64", inner_fingerprint=self.inner.fingerprint,
            attrs=self._attrs(None),
        )
        try:
            self._commit(None, self.source_offset)
        except BaseException:
            self._store.close()
            self._store = None
            raise
        self._uncommitted = 0

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        if self._store is not None and self._uncommitted:
            self._commit(None, self.source_offset)
            self._uncommitted = 0

    def close(self, *, finalize: bool = True) -> None:
        """Finalise the expansion, commit what is pending and release the store's lock.

        Parameters
        ----------
        finalize : bool
            Run :meth:`finalize` first (default) unless :attr:`finalized`, so that the
            closed expansion is the SVD, truncated to ``max_rank``. A store opened
            read-only is never finalised.
        """
        writable = self._store is None or self._store.mode == "a"
        if finalize and writable and not self.finalized:
            self.finalize()
        if self._store is not None:
            if writable:
                self.flush()
            self._store.close()
            self._store = None

    @property
    def finalized(self) -> bool:
        """Whether the expansion is its own SVD, truncated by the rules without oversampling.

        True when the last update was :meth:`finalize`, or nothing was absorbed yet.
        """
        return not self._history or self._history[-1].kind == "finalize"

    def __enter__(self) -> StreamCompressor:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        # a block that raised keeps its streamed state: what was committed stays as it was
        self.close(finalize=exc_type is None)

    @property
    def store_path(self) -> str | None:
        """Path of the store, or None."""
        return None if self._store is None else str(self._store.path)

    def _options(self) -> dict[str, Any]:
        return {
            "eps": self.eps, "rtol": self.rtol, "max_rank": self.max_rank,
            "oversampling": self.oversampling, "rule": self.rule, "sweeps": self.sweeps,
            "reject_tol": self.reject_tol,
            "reorth_tol": self.reorth_tol, "right_vectors": self.right_vectors,
            "commit_every": self.commit_every, "target_error": self.target_error,
            "error_measure": self.error_measure, "streaming_share": self.streaming_share,
            "window": self.window, "forget": self.forget,
        }

    def _attrs(self, plan: Plan | None) -> dict[str, Any]:
        s = self._state
        bound = s.bound if plan is None else plan.bound
        rank = s.rank if plan is None else plan.Gu.shape[1]
        ledger, removed = (self._ledger, self._removed) if plan is None else self._pending
        return {
            "kind": self.KIND, "layout": LAYOUT, "options": self._options(),
            "n_seen": s.m if plan is None else plan.m, "rank": rank,
            "source_offset": self.source_offset, "updates": len(self._history),
            "error_bound": bound.bound, "discarded_norm": bound.discarded,
            "source": None if self.source_record is None else self.source_record.to_attrs(),
            "removed": removed.tolist(), "ledger": ledger.entries.tolist(),
        }

    def _commit(self, plan: Plan | None, source_offset: int) -> None:
        """Write the current state, or the state ``plan`` leads to, as a new generation."""
        assert self._store is not None
        if self._store.mode != "a":
            raise StoreError(
                f"the store {self._store.path} is open read-only; reopen it with "
                "`StreamCompressor.open(path, mode='a')` to continue the stream."
            )
        s = self._state
        if plan is None:
            basis, basis_attrs = s.basis.persisted(0, compacted=False)
            rows = None if s.rows is None else (s.rows.V0, s.rows.Vp)
            compact = replaced = False
            Gu, H, R, m, waste, bound = s.Gu, s.H, s.R, s.m, s.waste, s.bound
        else:
            basis, basis_attrs = plan.stored_basis(s)
            rows = plan.stored_rows(s)
            compact, replaced = plan.compact, plan.Y_replace is not None
            Gu, H, R, m, waste, bound = plan.Gu, plan.H, plan.R, plan.m, plan.waste, plan.bound
        # the bound's norms are >= 0; an infinite one (the coupling after `add`) is stored
        # as -1, since a store holds finite numbers only
        norms = np.where(np.isinf(bound.to_array()), -1.0, bound.to_array())
        scalars = np.concatenate([norms, [float(source_offset), float(m), waste]])
        small = [Gu, H, R, scalars]
        if rows is not None:
            small.insert(3, rows[1])
        # only what changed since the previous commit is written (streamsvd.commits)
        appended = self._tracker.appended(
            self._store.generation, s, basis=dict(basis), compact=compact,
            V0=None if rows is None else rows[0], replaced=replaced, history=self._history,
            inner=self._inner_data,
        )
        attrs = self._attrs(plan)
        attrs.update(
            source_offset=int(source_offset), updates=len(self._history),
            small_layout=[list(a.shape) for a in small], basis=basis_attrs,
            rows_capacity=None if s.rows is None else list(s.rows.capacity),
            rows_dead=None if s.rows is None else intervals_add(
                np.zeros((0, 2)), _planned_dead(s.rows.dead, plan)).tolist(),
        )
        k = self._store.commit(
            {"small": np.concatenate([a.ravel() for a in small])}, attrs=attrs,
            appended=appended,
        )
        self._tracker.committed(k)
        if plan is None:
            self._tracker.settle(s, len(self._history))
        self._committed(basis_attrs)

    def _committed(self, basis_attrs: dict[str, Any]) -> None:
        """Run after every commit (a backend may release what no commit refers to)."""

    def _restore(self, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
        if not arrays:
            # killed between the creation of the store and its first commit: the store
            # holds the options only, and nothing was absorbed
            return
        a = {k: np.array(v, dtype=np.float64) for k, v in arrays.items()
             if not k.startswith("inner_")}
        pieces, start = [], 0
        for shape in attrs["small_layout"]:
            size = int(np.prod(shape))
            pieces.append(a["small"][start : start + size].reshape(shape))
            start += size
        Gu, H, R = pieces[:3]
        scalars, history = pieces[-1], a["history"]
        s = self._state
        s.basis.restore(a, attrs["basis"])
        if s.rows is not None:
            dead = [np.arange(a0, b0) for a0, b0 in attrs.get("rows_dead") or []]
            s.rows.restore(a["V0"], pieces[3], capacity=tuple(attrs["rows_capacity"]),
                           dead=np.concatenate(dead + [np.zeros(0, dtype=np.int64)]))
        s.Gu, s.H, s.R = Gu, H, R
        s.bound = Bound.from_array(np.where(scalars[:3] < 0, np.inf, scalars[:3]))
        self.source_offset = int(scalars[3])
        s.m = int(scalars[4])
        s.waste = float(scalars[5])
        self._history = [record_from_row(row) for row in history]
        self._removed = np.array(attrs.get("removed", []), dtype=np.int64).reshape(-1, 2)
        self._ledger = (Ledger(np.array(attrs["ledger"], dtype=np.float64).reshape(-1, 2))
                        if "ledger" in attrs else Ledger.start(s.m, s.bound.bound))
        self._version += 1

    # ------------------------------------------------------------------ properties
    @property
    def n_seen(self) -> int:
        """Number of snapshots (columns) in the expansion."""
        return self._state.m

    @property
    def n_absorbed(self) -> int:
        """Number of snapshots absorbed, removed ones included (the next one's index)."""
        return self._state.m + int(np.sum(self._removed[:, 1] - self._removed[:, 0]))

    @property
    def removed(self) -> np.ndarray:
        """Indices (in absorption order) of the snapshots removed, as ``[start, stop)`` rows."""
        return self._removed.copy()

    @property
    def rank(self) -> int:
        """Current number of terms."""
        return self._state.rank

    def _order(self, V: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``U`` of the exposed terms with its sort order and signs.

        Terms are sorted by the norms of ``V`` when it is given, else of the core ``R``
        (equal up to rounding).
        """
        s = self._state
        U = s.basis.take(s.Gu)
        perm = np.argsort(-safe_column_norms(s.R if V is None else V), kind="stable")
        U = U[:, perm]
        signs = fix_signs(U, np.zeros((0, U.shape[1])))
        return U, perm, signs

    @property
    def left_vectors(self) -> np.ndarray:
        """``U`` (``n x p``, ``M``-orthonormal), terms sorted by decreasing amplitude.

        Signed so that the largest entry of each ``u_i`` is positive. Costs
        ``O(n w p)``, nothing in the number of snapshots; available in every mode.
        """
        return self._order()[0]

    @property
    def expansion(self) -> Expansion:
        """The current expansion ``U V^T`` (formed from the stored factors, signs fixed).

        Terms are sorted by decreasing amplitude and signed so that the largest entry of
        each ``u_i`` is positive; ``add(..., coefficients=dV)`` takes ``dV`` in the
        coordinates of this ``U``. Needs ``right_vectors=True``.
        """
        V = self.right_factor()
        U, perm, signs = self._order(V)
        self._exposure = (self._version, perm, signs)  # the coordinates of `add`
        return Expansion(U, V[:, perm] * signs, inner=self.inner)

    def right_factor(self) -> np.ndarray:
        """``V = Y R`` (``m x p``) in the stored term order, unsorted and unsigned.

        ``Y`` is kept orthonormal (:mod:`streamsvd.update`), so the right vectors
        ``v_i / ||v_i||`` are orthonormal to rounding at convergence, whatever the spread
        of the amplitudes. Needs ``right_vectors=True``.
        """
        rows = self._state.rows
        if rows is None:
            raise InputError(
                "this StreamCompressor keeps no right vectors (`right_vectors=False`); use "
                "`left_vectors` and `amplitudes`, or create it with `right_vectors=True`."
            )
        return rows.value() @ self._state.R if self.rank else np.zeros((self.n_seen, 0))

    @property
    def amplitudes(self) -> np.ndarray:
        """``||v_i||``, computed on the small core (``||v_i|| = ||r_i||``), sorted."""
        return np.sort(safe_column_norms(self._state.R))[::-1]

    @property
    def discarded_energy(self) -> float:
        """Sum of the energies ``||D_t||_F^2`` discarded by every update.

        ``inf`` above about 1e154; :attr:`discarded_norm` is its square root, always finite.
        """
        return self._state.bound.discarded**2

    @property
    def discarded_norm(self) -> float:
        """``sqrt(sum_t ||D_t||_F^2)``, kept as a norm (finite for amplitudes to 1e300)."""
        return self._state.bound.discarded

    @property
    def error_bound(self) -> float:
        """Guaranteed bound on ``||A - U V^T||_F`` (theorem in :mod:`streamsvd.bound`)."""
        return self._state.bound.bound

    @property
    def error_in_measure(self) -> float:
        """:attr:`error_bound` in the ``error_measure`` of the target (a guaranteed bound).

        ``"absolute"``: the bound itself; ``"mean_l2"``: ``bound / sqrt(m)``;
        ``"relative"``: ``bound / (||U V^T||_F - bound)``, which bounds
        ``||A - U V^T|| / ||A||`` since ``||A|| >= ||U V^T|| - bound`` (``inf`` when the
        bound is not below the expansion's norm).
        """
        b = self.error_bound
        if self.error_measure == "absolute":
            return b
        if self.error_measure == "mean_l2":
            return b / math.sqrt(self.n_seen) if self.n_seen else 0.0
        norm = _norm(self.amplitudes)
        return b / (norm - b) if norm > b else (0.0 if b == 0.0 else math.inf)

    @property
    def target_met(self) -> bool | None:
        """Whether :attr:`error_in_measure` is within ``target_error`` (None without one)."""
        if self.target_error is None:
            return None
        return self.error_in_measure <= self.target_error

    @property
    def history(self) -> tuple[UpdateRecord, ...]:
        """One :class:`UpdateRecord` per update, oldest first."""
        return tuple(self._history)

    def orthogonality_error(self) -> float:
        """Return ``||U^T M U - I||_2`` from the small Gram matrices."""
        return self._state.orthogonality()

    def __repr__(self) -> str:
        return (
            f"StreamCompressor(n={self.n}, n_seen={self.n_seen}, rank={self.rank}, "
            f"rule={self.rule!r}, sweeps={self.sweeps}, eps={self.eps}, rtol={self.rtol}, "
            f"max_rank={self.max_rank})"
        )

    # ------------------------------------------------------------------ updates
    def absorb(self, columns: Any, *, source_offset: int | None = None) -> UpdateRecord:
        """Append a block of snapshots (the columns of ``columns``, ``n x b``, ``b >= 1``).

        Parameters
        ----------
        columns : array_like, shape (n, b)
            The new snapshots.
        source_offset : int, optional
            Position in the source just after this block, recorded in the store so that
            an interrupted ingestion resumes there; default: the previous offset + ``b``.

        With ``window``, the oldest snapshots that would fall out are removed first
        (:meth:`remove`, an update of its own in :attr:`history`); with ``forget``, the
        expansion is scaled by ``forget^b`` and the block's columns weighted
        ``forget^(b-1), ..., 1`` (``b`` the block's width).

        On bad input an :class:`~streamsvd.errors.InputError` is raised and the state,
        in memory and in the store, is unchanged.
        """
        t0 = time.perf_counter()
        B = as_float_array(columns, "columns", ndim=2, rows=self.n, allow_empty=False)
        offset = self.source_offset + B.shape[1] if source_offset is None else int(source_offset)
        if self.window is not None:
            # the oldest snapshots that fall out leave first (an update of their own), and
            # a block wider than the window enters by its last `window` columns only
            skipped = max(B.shape[1] - self.window, 0)
            out = self.n_seen + B.shape[1] - skipped - self.window
            if out > 0:
                self._remove_positions(np.arange(out))
            if skipped:
                B = B[:, skipped:]
        removed = self._removed
        if self.window is not None and skipped:
            removed = intervals_add(removed, self.n_absorbed + np.arange(skipped))
        state, ledger = self._state, self._ledger
        if self.forget < 1.0:
            b = B.shape[1]
            B = B * self.forget ** np.arange(b - 1, -1, -1, dtype=np.float64)
            scale = self.forget**b
            state = dataclasses.replace(
                state, R=state.R * scale, bound=Bound.from_array(state.bound.to_array() * scale)
            )
            ledger = ledger.scaled(scale)
        return self._run(
            lambda: plan_absorb_by_gram(state, B, self._opts, t0=t0)
            or plan_absorb(state, B, self._opts, t0=t0),
            offset, ledger=ledger, removed=removed,
        )

    def remove(self, columns: Any) -> UpdateRecord:
        """Remove absorbed snapshots exactly: the result is as if they were never absorbed.

        Parameters
        ----------
        columns : int or sequence of int
            Indices of the snapshots in the order they were absorbed (0 is the first one
            ever absorbed; :attr:`n_absorbed` the next), unchanged by earlier removals.

        Brand's downdate (:mod:`streamsvd.downdate`): the removed rows of the orthonormal
        right factor ``Y`` are read, and the small core is downdated, swept and truncated
        like any update. ``U`` is unchanged. Cost ``O(r w k + (r + k)^3 + k^2 p)`` for
        ``r`` columns, nothing in the number of snapshots absorbed, while every right
        direction keeps at least half its support on the remaining columns; otherwise
        (and once the removed rows outnumber the others) the remaining rows of ``Y``
        are orthonormalised again, ``O(m w k)`` with ``m`` the snapshots kept (the
        window's size with ``window``).

        Guarantee: the new expansion is, to rounding, ``U V^T`` with the removed columns
        deleted (then swept and truncated by the compressor's rules). Without truncation
        so far it is the expansion of the remaining snapshots; with truncation, that of
        the remaining columns of the truncated expansion, and
        ``||A_rest - U V^T||_F <= error_bound`` still holds (module
        :mod:`streamsvd.downdate`: the bound is kept, or lowered to the ledger's sum of
        the discards that still lie on remaining columns). Needs ``right_vectors=True``.

        Raises
        ------
        InputError
            Without right vectors, or when an index is not an integer, out of range,
            repeated or already removed; the state, in memory and in the store, is then
            unchanged.
        """
        if self._state.rows is None:
            raise InputError(
                "`remove` needs the right vectors, and this StreamCompressor keeps none "
                "(`right_vectors=False`); create it with `right_vectors=True`."
            )
        g = np.asarray(columns)
        if g.ndim == 0:
            g = g.reshape(1)
        if g.ndim != 1 or g.size == 0 or g.dtype.kind not in "iu":
            raise InputError(
                "`columns` must be a non-empty sequence of integer snapshot indices; got "
                + f"{columns!r}"[:120] + "."
            )
        g = g.astype(np.int64)
        total = self.n_absorbed
        bad = g[(g < 0) | (g >= total)]
        if bad.size:
            raise InputError(
                f"`columns` must be indices of absorbed snapshots, 0 <= index < {total} "
                f"(the snapshots absorbed so far); got {bad[:5].tolist()}."
            )
        values, counts = np.unique(g, return_counts=True)
        if np.any(counts > 1):
            raise InputError(
                f"`columns` must name each snapshot once; got "
                f"{values[counts > 1][:5].tolist()} more than once."
            )
        gone = g[intervals_contain(self._removed, g)]
        if gone.size:
            raise InputError(
                f"`columns` must name snapshots still in the expansion; got "
                f"{gone[:5].tolist()}, already removed (see `removed`)."
            )
        return self._remove_positions(values - intervals_count_below(self._removed, values))

    def _remove_positions(self, positions: np.ndarray) -> UpdateRecord:
        """Remove the current columns at ``positions`` (sorted, distinct, valid)."""
        t0 = time.perf_counter()
        ledger = self._ledger.removed(positions)
        prior = bound_after_removal(self._state.bound, ledger)
        removed = intervals_add(self._removed, intervals_skip(self._removed, positions))
        return self._run(
            lambda: plan_remove(self._state, positions, self._opts, prior=prior, t0=t0),
            self.source_offset, ledger=ledger, removed=removed,
        )

    def add(self, U_k: Any, V_k: Any, *, coefficients: Any = None) -> UpdateRecord:
        """Add the low-rank increment ``U dV^T + U_k V_k^T`` to the current matrix.

        Parameters
        ----------
        U_k : array_like, shape (n, k)
            Left vectors of the increment (any, not necessarily orthonormal); ``k`` may
            be 0 when ``coefficients`` is given.
        V_k : array_like, shape (m, k)
            Right vectors; ``m`` must equal :attr:`n_seen` (or fixes it when the
            compressor is empty).
        coefficients : array_like, shape (m, p), optional
            ``dV``: an increment *inside* the current basis, in the coordinates of the
            ``U`` last returned by :attr:`expansion` (its column ``i`` is the change of
            ``v_i``). It costs ``O(m p^2)`` instead of a Gram-Schmidt of ``U`` against
            itself. This is how a PGD solver updates its time functions.

        A term whose residual carries ``||r_j||_M ||v_j|| <= reject_tol * max_i
        ||u_i||_M ||v_i||`` is rejected; the rejected residuals share the same columns, so
        their norm ``||Res V_rej^T||`` is computed exactly from two small Gram matrices.
        Needs ``right_vectors=True``.
        """
        t0 = time.perf_counter()
        s = self._state
        if s.rows is None:
            raise InputError(
                "`add` needs the right vectors, and this StreamCompressor keeps none "
                "(`right_vectors=False`); create it with `right_vectors=True`."
            )
        Uk = as_float_array(U_k, "U_k", ndim=2, rows=self.n)
        m = s.m if (s.m or s.rank) else None
        Vk = as_float_array(V_k, "V_k", ndim=2, rows=m, cols=Uk.shape[1])
        dV_int = None
        if coefficients is not None:
            dV = as_float_array(coefficients, "coefficients", ndim=2, rows=s.m, cols=s.rank)
            dV_int = self._internal_coefficients(dV)
        elif Uk.shape[1] == 0:
            raise InputError(
                f"`U_k` must have at least one column (or pass `coefficients`); got shape "
                f"{Uk.shape}."
            )
        return self._run(
            lambda: plan_add(s, Uk, Vk, dV_int, self._opts, t0=t0), self.source_offset
        )

    def _internal_coefficients(self, dV: np.ndarray) -> np.ndarray:
        """Map coefficients on the exposed basis (sorted, signed) to the stored terms."""
        if self._exposure is None or self._exposure[0] != self._version:
            _ = self.expansion  # computes and caches the exposure of this state
        assert self._exposure is not None
        _, perm, signs = self._exposure
        out = np.empty_like(dV)
        out[:, perm] = dV * signs
        return out

    def merge(
        self, other: StreamCompressor | Expansion, *, spend_target: bool = True
    ) -> UpdateRecord:
        """Append the snapshots represented by ``other`` (they come after the current ones).

        ``other`` is a compressor fed with later columns (for instance on another worker)
        or an expansion of them; it is not modified. Its left vectors are decomposed on
        the basis, and its right vectors enter the small core through their core ``R_o``,
        so the cost is ``O(n w p_o + p_o^2 (p + p_o))`` (plus ``O(m_o p_o p)`` for the new
        rows of ``V`` when they are kept), never ``O(n m_o)``. A term of ``other`` is
        rejected relative to the energy of ``other`` (see :func:`streamsvd.update.plan_merge`).
        Error bounds compose: the two parts cover disjoint columns, so before the merge's
        own truncation the bound is ``sqrt(b_self^2 + b_other^2)``, as in the hierarchical
        POD of Himpe, Leibner and Rave (2018).

        With ``spend_target=False`` the merge cuts nothing for the target error (``eps``,
        ``rtol`` and the rank cap still apply): the tree of :func:`streamsvd.parallel.
        tree_compress` merges so, and the budget its leaves left is spent by one optimal
        cut in the root's :meth:`finalize`, as pyMOR's ``dist_vectorarray_hapod`` does.
        """
        t0 = time.perf_counter()
        if not isinstance(other, StreamCompressor | Expansion):
            raise InputError(
                "`other` must be a StreamCompressor or an Expansion; got "
                f"{type(other).__name__}."
            )
        if other.n != self.n:
            raise InputError(f"`other` must have snapshots of size {self.n}; got {other.n}.")
        check_same_inner(self.inner, other.inner, "other")
        Y_o: np.ndarray | None
        if isinstance(other, StreamCompressor):
            o = other._state
            U_o, R_o, m_o, prior = o.basis.take(o.Gu), o.R, o.m, o.bound
            if self._state.rows is not None and o.rows is None:
                raise InputError(
                    "`other` keeps no right vectors (`right_vectors=False`) but this "
                    "compressor does; merge compressors created alike."
                )
            Y_o = None if self._state.rows is None or o.rows is None else o.rows.value()
        else:
            U_o, V_o, prior = np.array(other.U), np.array(other.V), Bound()
            m_o = V_o.shape[0]
            if self._state.rows is None:
                Y_o, R_o = None, r_factor(V_o)
            else:
                Y_o, R_o = np.linalg.qr(V_o)
        prior = self._state.bound.combine(prior)
        opts = self._opts
        if not spend_target:
            opts = dataclasses.replace(
                opts, truncation=dataclasses.replace(opts.truncation, target=None)
            )
        return self._run(
            lambda: plan_merge(self._state, U_o, R_o, Y_o, m_o, prior, opts, t0=t0),
            self.source_offset + m_o,
            ledger=self._ledger.appended(self.n_seen + m_o, prior.bound),
        )

    def finalize(
        self, *, rule: str = "jacobi", max_rank: int | None = None, progress: bool = False
    ) -> UpdateRecord:
        """Converge the small core to the SVD of the current expansion, then truncate.

        Rotation sweeps of ``rule`` (``"jacobi"`` by default: quadratic convergence) run
        on the core until a sweep rotates nothing (at most 200), and the truncation rules
        (``eps``, ``rtol``, and ``max_rank``, or the compressor's own when omitted, without
        the oversampling) are applied to the converged amplitudes: the optimal
        (Eckart-Young) truncation of the expansion. Costs one compaction of the basis at
        most, nothing in the number of snapshots; recorded in :attr:`history` (kind
        ``"finalize"``) and committed like any update. :meth:`close` calls it. The stream
        may continue afterwards (with the compressor's options). ``progress=True`` shows
        the sweeps on stderr (tqdm). An interrupt (Ctrl-C) or an error during the sweeps
        leaves the compressor and its store at the last commit: calling ``finalize``
        again starts the sweeps over from it.
        """
        t0 = time.perf_counter()
        cap = check_positive_int(max_rank, "max_rank", allow_none=True)
        opts = dataclasses.replace(
            self._opts, rule=check_choice(rule, "rule", RULES), sweeps=None,
            truncation=Truncation(
                self.eps, self.rtol, self.max_rank if cap is None else cap, self.target_error,
                self.error_measure, 1.0,
            ),
        )
        with _sweep_bar(self.rank, progress) as on_sweep:
            record = self._run(
                lambda: plan_finalize(self._state, opts, t0=t0, on_sweep=on_sweep),
                self.source_offset,
            )
        if self.target_met is False:
            logger.warning(
                "the target error %.3g (%s) is not met: the bound is %.3g in that measure "
                "(max_rank=%s cuts more than the target allows)", self.target_error,
                self.error_measure, self.error_in_measure, self.max_rank,
            )
        return record

    # ------------------------------------------------------------------ internals
    def _run(
        self, make_plan: Callable[[], Plan], source_offset: int, *,
        ledger: Ledger | None = None, removed: np.ndarray | None = None,
    ) -> UpdateRecord:
        """Plan an update, persist it when a commit is due, then switch to it.

        The plan runs with the BLAS limited to :attr:`threads` threads. ``ledger`` and
        ``removed`` are the error ledger and the removed indices before the update's own
        discard (default: the current ones).
        """
        with blas_threads(self.threads):
            plan = make_plan()
        base = self._ledger if ledger is None else ledger
        self._pending = (
            base.appended(plan.m, plan.record.discarded),
            self._removed if removed is None else removed,
        )
        # persist first, then switch the in-memory state: an exception anywhere before
        # or in the commit leaves both the memory and the store as they were
        self._history.append(plan.record)
        try:
            if self._store is not None and self._uncommitted + 1 >= self.commit_every:
                self._commit(plan, source_offset)
                self._uncommitted = 0
            elif self._store is not None:
                self._uncommitted += 1
        except BaseException:
            self._history.pop()
            self._state.basis.discard_planned()
            raise
        apply_plan(self._state, plan)
        self._ledger, self._removed = self._pending
        self._tracker.settle(self._state, len(self._history))
        self._version += 1
        self.source_offset = source_offset
        return plan.record


def summary_of(sc: StreamCompressor) -> dict[str, Any]:
    """Return what ``streamsvd info --json`` prints of a compressor (JSON-able)."""
    return {
        "store": sc.store_path, "n": sc.n, "n_seen": sc.n_seen, "rank": sc.rank,
        "source_offset": sc.source_offset, "updates": len(sc.history),
        "finalized": sc.finalized, "error_bound": sc.error_bound,
        "discarded_energy": sc.discarded_energy, "orthogonality": sc.orthogonality_error(),
        "error_in_measure": sc.error_in_measure, "target_met": sc.target_met,
        "n_absorbed": sc.n_absorbed, "removed": sc.removed.tolist(),
        "options": sc._options(), "inner": repr(sc.inner),
        "source": None if sc.source_record is None else sc.source_record.to_attrs(),
        "amplitudes_head": sc.amplitudes[:10].tolist(),
    }


def _planned_dead(dead: np.ndarray, plan: Plan | None) -> np.ndarray:
    """Return the dead stored rows of the right factor once ``plan`` is applied."""
    if plan is None:
        return dead
    if plan.Y_replace is not None:
        return np.zeros(0, dtype=np.int64)
    return dead if plan.dead is None else plan.dead


@contextlib.contextmanager
def _sweep_bar(rank: int, show: bool) -> Iterator[Callable[[int, float], None] | None]:
    """Yield the ``on_sweep`` callback of a progress bar of the final sweeps (or None)."""
    if not show:
        yield None
        return
    from tqdm import tqdm

    with tqdm(desc=f"final sweeps ({rank} terms)", unit="sweep", file=sys.stderr,
              dynamic_ncols=True) as bar:
        def on_sweep(done: int, max_cosine: float) -> None:
            bar.set_postfix(max_cosine=f"{max_cosine:.1e}", refresh=False)
            bar.update(done - bar.n)

        yield on_sweep
