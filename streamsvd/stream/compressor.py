"""Streaming compression: absorb snapshot blocks and low-rank increments.

A :class:`StreamCompressor` keeps the expansion ``A ~ U V^T`` of every snapshot seen so
far (columns of ``A``) with ``U`` orthonormal in the inner product ``M``. Each update

1. decomposes the new left vectors on the basis and orthonormalises their residual at
   BLAS-3 speed, rejecting directions below ``reject_tol``
   (:func:`streamsvd.linalg.extend.extend_basis`);
2. runs ``sweeps`` rotation sweeps of the paper (Algorithm 2, rule ``"paper"`` or
   ``"jacobi"``) on a small core;
3. truncates the terms that fail ``||v_i|| >= eps``, ``||v_i|| >= rtol * ||v_1||`` or
   ``i <= max_rank`` (after the sweeps, on the sorted amplitudes), logging what was cut.

The step is written once (:mod:`streamsvd.engine.update`) over the n-sized basis
(:mod:`streamsvd.algebra.interface`) and the m-sized right vectors
(:mod:`streamsvd.engine.rows`); this class is the facade: its options are
:class:`~streamsvd.stream.options.CompressorOptions`, its store a
:class:`~streamsvd.stream.persistence.StreamStore`, and what it exposes of the expansion
:class:`~streamsvd.stream.view.ExpansionView`.

Store contents: besides the state, the first commit writes the data of the inner
product (weights, a dense matrix or a sparse one's CSR arrays), which later commits
keep unchanged, so :meth:`StreamCompressor.open` needs no ``inner`` (an inner product of another
class than the three of :mod:`streamsvd.algebra.inner` is recorded by fingerprint only).

Error bound: :attr:`StreamCompressor.error_bound` is guaranteed, ``||A - U V^T||_F <= error_bound``
in the norm of ``M`` after every update (theorem in :mod:`streamsvd.engine.bound`); at
convergence (``sweeps=None``) it is the Pythagorean ``sqrt(sum of discarded
energies)``.

Cost: an update costs nothing in the number of snapshots already absorbed: the
right vectors are kept as ``V = Y R`` with ``Y`` orthonormal, appended in Brand's form
``Y = V0 Vp`` (:mod:`streamsvd.engine.rows`), the
basis lives in a buffer grown geometrically (:mod:`streamsvd.algebra.buffer`), and the
rotations act on small matrices (:mod:`streamsvd.engine.update` has the flop count).

Orthogonality: ``H = Q^T M Q`` of the stored basis is kept (exactly, by a Gram of
the stored columns at each compaction), so ``||U^T M U - I||_2`` is measured after
every update and recorded in :attr:`StreamCompressor.history`; above ``reorth_tol`` the basis is
re-orthonormalised through the Cholesky factor of that small Gram
(``U <- U L^{-T}``, ``V <- V L``, which leaves ``U V^T`` unchanged).
"""

from __future__ import annotations

import functools
import time
from typing import Any

import numpy as np

from streamsvd._util.threads import check_threads
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.inner import InnerProduct, as_inner, inner_arrays
from streamsvd.algebra.interface import Backend
from streamsvd.algebra.memory import MEMORY_KIND, MemoryBackend
from streamsvd.engine.record import UpdateRecord
from streamsvd.engine.rows import RowFactor
from streamsvd.engine.state import State
from streamsvd.engine.update import (
    plan_absorb,
    plan_add,
    plan_finalize,
    plan_merge,
)
from streamsvd.engine.update_gram import plan_absorb_by_gram, plan_merge_by_gram
from streamsvd.errors import InputError
from streamsvd.io.provenance import SourceRecord
from streamsvd.linalg.expansion import Expansion
from streamsvd.stream.lifecycle import StoreLifecycle
from streamsvd.stream.operands import _final_options, _increment, _merge_operand, _merge_options
from streamsvd.stream.options import CompressorOptions, option_properties
from streamsvd.stream.persistence import StreamStore
from streamsvd.stream.summary import _sweep_bar
from streamsvd.stream.view import ExpansionView
from streamsvd.stream.window import Removals

__all__ = ["StreamCompressor", "UpdateRecord"]



@option_properties
class StreamCompressor(StoreLifecycle, Removals, ExpansionView):
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
        Rotation rule of the sweeps (see :func:`streamsvd.linalg.compress`).
    sweeps : int or None
        Rotation sweeps per update; ``None`` sweeps to convergence (the exact SVD of the
        current expansion, as Brand's incremental SVD): pair it with ``rule="jacobi"``,
        which converges in a few sweeps, where the paper's rule converges linearly and
        can take the 200 sweeps allowed on clustered amplitudes (``bench/README.md``,
        windows).
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
        state; :mod:`streamsvd.stream.commits`). An existing store is continued with
        :meth:`StreamCompressor.open`, not overwritten.
    commit_every : int or "auto"
        Updates between two commits (the last ones are committed by :meth:`flush` or
        :meth:`close`); ``"auto"`` commits when the commits so far, and one more (as long
        as the last, or as its basis at the fastest rate measured, 100 MB/s before one
        is), stay within a tenth of the time since the start
        (:class:`streamsvd.stream.commits.CommitSchedule`).
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
    backend : Backend, optional
        Where the n-sized factor lives (:class:`~streamsvd.algebra.memory.MemoryBackend`, the
        default; :class:`~streamsvd.algebra.panels.backend.PanelBackend` keeps it in panels on disk,
        as :class:`~streamsvd.parallel.TallCompressor` builds it).
    threads : int or None
        BLAS threads of an update (default 1; ``None`` leaves the BLAS as it is set).
        One thread is never much slower than all cores and is much faster on a machine
        where other work runs (measured in ``bench/README.md``, "BLAS threads"); it is
        a setting of this process, not recorded in the store.

    The result is the SVD: :meth:`close` (or the end of a ``with`` block that raised
    nothing) runs :meth:`finalize`, which converges the small core and truncates it
    optimally, then commits. Call ``close(finalize=False)`` to keep the streamed state
    as it is.
    """

    def __init__(
        self, n: int, *, inner: Any = None, store: Any = None,
        source_record: SourceRecord | None = None,
        storage_options: dict[str, Any] | None = None, threads: int | None = 1,
        backend: Backend | None = None, **options: Any,
    ) -> None:
        self.n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        self._backend: Backend = MemoryBackend() if backend is None else backend
        self.threads = check_threads(threads)
        self.inner: InnerProduct = as_inner(inner, self.n)
        if source_record is not None and not isinstance(source_record, SourceRecord):
            raise InputError(
                f"`source_record` must be a SourceRecord or None; got "
                f"{type(source_record).__name__}. Build one with `SourceRecord.of(...)`."
            )
        self.source_record = source_record
        self.options = CompressorOptions.validated(self.n, **options)
        self._opts = self.options.step_options(self.inner)
        self._state = State(
            basis=self._backend.new_basis(self.n, self.inner),
            rows=RowFactor() if self.options.right_vectors else None,
        )
        self._history: list[UpdateRecord] = []
        self._version = 0  # increases with every state change (for the exposure cache)
        self._exposure: tuple[int, np.ndarray, np.ndarray] | None = None
        self.source_offset = 0
        self._start_removals()
        self._persistence: StreamStore | None = None
        if store is not None:
            self._start_store(store, storage_options)

    KIND = MEMORY_KIND

    @functools.cached_property
    def _inner_data(self) -> dict[str, np.ndarray]:
        """The inner product's arrays that the store keeps (none for an unknown class)."""
        return inner_arrays(self.inner) or {}

    @classmethod
    def _built(cls, n: int, *, backend: Backend, **arguments: Any) -> Any:
        """Return a compressor of this class around ``backend`` (its constructor skipped)."""
        sc = cls.__new__(cls)
        StreamCompressor.__init__(sc, n, backend=backend, **arguments)
        return sc

    def _empty_copy(self, *, backend: Backend | None = None, **changes: Any) -> Any:
        """Return a compressor with these options (but ``changes``), nothing absorbed.

        Its basis is kept by ``backend`` (default: a fresh one of the same settings).
        """
        backend = self._backend.fresh() if backend is None else backend
        return self._built(self.n, backend=backend, inner=self.inner,
                           source_record=self.source_record, threads=self.threads,
                           **{**self.options.as_dict(), **changes})

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(n={self.n}, n_seen={self.n_seen}, rank={self.rank}, "
            f"{self._backend.describe(self._state.basis)}"
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
        B = self._backend.load(columns, rows=self.n, first=self.source_offset)
        offset = self.source_offset + B.shape[1] if source_offset is None else int(source_offset)
        B, state, ledger, removed = self._windowed(B)
        return self._run(
            lambda: plan_absorb_by_gram(state, B, self._opts, t0=t0)
            or plan_absorb(state, self._backend.in_memory(B), self._opts, t0=t0),
            offset, ledger=ledger, removed=removed,
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
        Uk, Vk, dV = _increment(self, U_k, V_k, coefficients)
        dV_int = None if dV is None else self._internal_coefficients(dV)
        return self._run(
            lambda: plan_add(s, Uk, Vk, dV_int, self._opts, t0=t0), self.source_offset
        )

    def merge(
        self, other: StreamCompressor | Expansion, *, spend_target: bool = True
    ) -> UpdateRecord:
        """Append the snapshots represented by ``other`` (they come after the current ones).

        ``other`` is a compressor fed with later columns (for instance on another worker)
        or an expansion of them; it is not modified. Its left vectors are decomposed on
        the basis, and its right vectors enter the small core through their core ``R_o``,
        so the cost is ``O(n w p_o + p_o^2 (p + p_o))`` (plus ``O(m_o p_o p)`` for the new
        rows of ``V`` when they are kept), never ``O(n m_o)``. A term of ``other`` is
        rejected relative to the energy of ``other``, and a term of the merged core below
        ``reject_tol`` times the largest amplitude of the smaller expansion is cut as
        rounding noise, its norm counted in the bound (see
        :func:`streamsvd.engine.update.plan_merge`).
        Error bounds compose: the two parts cover disjoint columns, so before the merge's
        own truncation the bound is ``sqrt(b_self^2 + b_other^2)``, as in the hierarchical
        POD of Himpe, Leibner and Rave (2018).

        With ``spend_target=False`` the merge cuts nothing for the target error (``eps``,
        ``rtol`` and the rank cap still apply): the tree of :func:`streamsvd.parallel.
        tree_compress` merges so, and the budget its leaves left is spent by one optimal
        cut in the root's :meth:`finalize`, as pyMOR's ``dist_vectorarray_hapod`` does.
        """
        t0 = time.perf_counter()
        op = _merge_operand(other, StreamCompressor, n=self.n, inner=self.inner,
                            keep_rows=self._state.rows is not None)
        prior = self._state.bound.combine(op.bound)
        opts = _merge_options(self._opts, spend_target=spend_target)
        s = self._state
        return self._run(
            lambda: plan_merge_by_gram(s, op.Q, op.coordinates(), op.R, op.Y, op.m, prior,
                                       opts, t0=t0)
            or plan_merge(s, op.left_vectors(), op.R, op.Y, op.m, prior, opts, t0=t0),
            self.source_offset + op.m,
            ledger=self._ledger.appended(self.n_seen + op.m, prior.bound),
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
        opts = _final_options(self, rule=rule, max_rank=max_rank)
        with _sweep_bar(self.rank, progress) as on_sweep:
            record = self._run(
                lambda: plan_finalize(self._state, opts, t0=t0, on_sweep=on_sweep),
                self.source_offset,
            )
        self._warn_if_target_missed()
        return record
