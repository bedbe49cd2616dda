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

The step is written once (:mod:`streamsvd.engine.update`) over the n-sized basis (a
:class:`~streamsvd.algebra.interface.Backend`'s) and the m-sized right vectors
(:mod:`streamsvd.engine.rows`). This class is the facade, composed of parts it holds as
attributes and forwards to: a :class:`~streamsvd.stream.lifecycle.Lifecycle` (the
state, each update's run and commit, the store), an
:class:`~streamsvd.stream.updates.Updates` (``absorb``, ``add``, ``merge``,
``finalize``), a :class:`~streamsvd.stream.window.Window` (``remove``, the window,
forgetting), an :class:`~streamsvd.stream.view.ExpansionView` (every read-only
attribute) and a :class:`~streamsvd.stream.dynamics.Dynamics` (``dmd``); its options
are :class:`~streamsvd.stream.options.CompressorOptions`.

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

from collections.abc import Callable
from typing import Any

import numpy as np

from streamsvd._util.threads import check_threads
from streamsvd._util.validation import check_positive_int
from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.algebra.interface import Backend
from streamsvd.algebra.memory import MEMORY_KIND, MemoryBackend
from streamsvd.engine.record import UpdateRecord
from streamsvd.errors import InputError
from streamsvd.io.provenance import SourceRecord
from streamsvd.linalg.expansion import Expansion
from streamsvd.stream.delegation import Forward
from streamsvd.stream.dynamics import Dynamics
from streamsvd.stream.lifecycle import Lifecycle
from streamsvd.stream.options import CompressorOptions, option_properties
from streamsvd.stream.updates import Updates
from streamsvd.stream.view import ExpansionView
from streamsvd.stream.window import Window

__all__ = ["StreamCompressor", "UpdateRecord"]


@option_properties
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
    dynamics : bool
        Record the stream for :meth:`dmd` (dynamic mode decomposition with a residual
        bound per eigenvalue): needs ``right_vectors=True``, from which the snapshot
        pairs are read at query time; ``absorb(..., new_trajectory=True)`` starts a
        trajectory. Recorded in the store (``streamsvd info``); :meth:`dmd` answers on
        any compressor that keeps its right vectors.
    backend : Backend, optional
        Where the n-sized factor lives (:class:`~streamsvd.algebra.memory.MemoryBackend`, the
        default; :class:`~streamsvd.algebra.panels.backend.PanelBackend` keeps it in panels on disk,
        as :class:`~streamsvd.parallel.TallCompressor` builds it).
    threads : int or None
        BLAS threads of an update (default 1; ``None`` leaves the BLAS as it is set).
        One thread is never much slower than all cores and is much faster on a machine
        where other work runs (measured in ``bench/README.md``, "BLAS threads"); it is
        a setting of this process, not recorded in the store.

    Notes
    -----
    The result is the SVD: :meth:`close` (or the end of a ``with`` block that raised
    nothing) runs :meth:`finalize`, which converges the small core and truncates it
    optimally, then commits. Call ``close(finalize=False)`` to keep the streamed state
    as it is.

    Its updates are :class:`~streamsvd.stream.updates.Updates`', its removals
    :class:`~streamsvd.stream.window.Window`'s, its read-only attributes
    :class:`~streamsvd.stream.view.ExpansionView`'s (one per option too).
    """

    def __init__(
        self, n: int, *, inner: Any = None, store: Any = None,
        source_record: SourceRecord | None = None,
        storage_options: dict[str, Any] | None = None, threads: int | None = 1,
        backend: Backend | None = None, **options: Any,
    ) -> None:
        n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        backend = MemoryBackend() if backend is None else backend
        threads = check_threads(threads)
        ip = as_inner(inner, n)
        if source_record is not None and not isinstance(source_record, SourceRecord):
            raise InputError(
                f"`source_record` must be a SourceRecord or None; got "
                f"{type(source_record).__name__}. Build one with `SourceRecord.of(...)`."
            )
        self._attach(Lifecycle(n, inner=ip, options=CompressorOptions.validated(n, **options),
                               backend=backend, threads=threads, source_record=source_record))
        if store is not None:
            self._life.start_store(store, storage_options)

    KIND = MEMORY_KIND

    # the parts' public names (documented there; `help(sc.absorb)` shows the part's)
    absorb = Forward[Callable[..., UpdateRecord]]("_updates", Updates)
    add = Forward[Callable[..., UpdateRecord]]("_updates", Updates)
    merge = Forward[Callable[..., UpdateRecord]]("_updates", Updates)
    finalize = Forward[Callable[..., UpdateRecord]]("_updates", Updates)
    expect = Forward[Callable[[Any], None]]("_updates", Updates)
    remove = Forward[Callable[[Any], UpdateRecord]]("_window", Window)
    n_absorbed = Forward[int]("_window", Window)
    removed = Forward[np.ndarray]("_window", Window)
    n = Forward[int]("_view", ExpansionView)
    inner = Forward[InnerProduct]("_view", ExpansionView)
    options = Forward[CompressorOptions]("_view", ExpansionView)
    source_offset = Forward[int]("_view", ExpansionView)
    store_path = Forward["str | None"]("_view", ExpansionView)
    chunk_rows = Forward["int | None"]("_view", ExpansionView)
    client = Forward[Any]("_view", ExpansionView)
    n_seen = Forward[int]("_view", ExpansionView)
    rank = Forward[int]("_view", ExpansionView)
    left_vectors = Forward[np.ndarray]("_view", ExpansionView)
    expansion = Forward[Expansion]("_view", ExpansionView)
    factors = Forward[Callable[[], tuple[Any, np.ndarray]]]("_view", ExpansionView)
    right_factor = Forward[Callable[[], np.ndarray]]("_view", ExpansionView)
    amplitudes = Forward[np.ndarray]("_view", ExpansionView)
    discarded_energy = Forward[float]("_view", ExpansionView)
    discarded_norm = Forward[float]("_view", ExpansionView)
    error_bound = Forward[float]("_view", ExpansionView)
    error_in_measure = Forward[float]("_view", ExpansionView)
    target_met = Forward["bool | None"]("_view", ExpansionView)
    target_missed_by = Forward["str | None"]("_view", ExpansionView)
    history = Forward[tuple[UpdateRecord, ...]]("_view", ExpansionView)
    orthogonality_error = Forward[Callable[[], float]]("_view", ExpansionView)
    finalized = Forward[bool]("_view", ExpansionView)
    streaming_rank = Forward["int | None"]("_view", ExpansionView)
    stored_width = Forward[int]("_view", ExpansionView)
    dmd = Forward[Callable[..., Any]]("_dynamics", Dynamics)
    trajectory_starts = Forward[np.ndarray]("_dynamics", Dynamics)

    def _attach(self, life: Lifecycle) -> StreamCompressor:
        """Hold the parts around ``life``: the lifecycle, the window and the view."""
        self._life = life
        self._window = Window(life)
        self._view = ExpansionView(life)
        self._updates = Updates(life, self._window, self._view)
        self._dynamics = Dynamics(life, self._view)
        return self

    @classmethod
    def _around(cls, life: Lifecycle) -> StreamCompressor:
        """Return the compressor whose lifecycle is ``life`` (its constructor skipped)."""
        return StreamCompressor.__new__(StreamCompressor)._attach(life)

    def __repr__(self) -> str:
        life, o = self._life, self._life.options
        return (
            f"{life.kind.rpartition('.')[2]}(n={self.n}, n_seen={self.n_seen}, "
            f"rank={self.rank}, {life.backend.describe(life.state.basis)}"
            f"rule={o.rule!r}, sweeps={o.sweeps}, eps={o.eps}, rtol={o.rtol}, "
            f"max_rank={o.max_rank})"
        )

    # ------------------------------------------------------------------ settings
    @property
    def threads(self) -> int | None:
        """BLAS threads of an update (None: the BLAS as it is set); may be changed."""
        return self._life.threads

    @threads.setter
    def threads(self, value: int | None) -> None:
        self._life.threads = check_threads(value)

    @property
    def source_record(self) -> SourceRecord | None:
        """Where the snapshots come from, kept by every commit; may be replaced."""
        return self._life.source_record

    @source_record.setter
    def source_record(self, value: SourceRecord | None) -> None:
        self._life.source_record = value

    # ------------------------------------------------------------------ the store
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
        return cls._open(path, inner=inner, mode=mode, kind=MEMORY_KIND,
                         backend=lambda attrs, root: MemoryBackend(),
                         storage_options=storage_options)

    @classmethod
    def _open(cls, path: Any, *, inner: Any, mode: str, kind: str,
              backend: Callable[[dict[str, Any], Any], Backend],
              storage_options: dict[str, Any] | None = None) -> StreamCompressor:
        """Open a store of ``kind`` and return the compressor it holds.

        ``backend(basis_attrs, root)`` returns the backend of the store at ``root``.
        """
        return cls._around(Lifecycle.open(
            path, inner=inner, mode=mode, kind=kind, name=kind.rpartition(".")[2],
            backend=backend, storage_options=storage_options,
        ))

    def copy(self) -> StreamCompressor:
        """Return an independent copy of the compressor (without its store)."""
        return self._copy_with()

    def _copy_with(self, *, backend: Backend | None = None, **changes: Any) -> StreamCompressor:
        """Return a copy whose options differ by ``changes``, its basis kept by ``backend``."""
        return self._around(self._life.copied(backend=backend, **changes))

    def _drop_scratch(self) -> None:
        """Free the basis's buffers for its next update (a finished leaf of a tree)."""
        self._life.state.basis.drop_scratch()

    def save(self, path: Any) -> None:
        """Write the compressor into a new store at ``path`` and keep committing there.

        One commit of the current state, bit for bit (no update is run). The compressor
        must not have a store already.
        """
        self._life.start_store(path, None)

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        self._life.flush()

    def close(self, *, finalize: bool = True) -> None:
        """Finalise the expansion, commit what is pending and release the store's lock.

        Parameters
        ----------
        finalize : bool
            Run :meth:`finalize` first (default) unless :attr:`finalized`, so that the
            closed expansion is the SVD, truncated to ``max_rank``. A store opened
            read-only is never finalised, nor a basis that closing removes (a
            temporary backend's).
        """
        life = self._life
        if finalize and life.writable and not self.finalized and not life.backend.temporary:
            self.finalize()
        life.close()

    def __enter__(self) -> StreamCompressor:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        # a block that raised keeps its streamed state: what was committed stays as it was
        self.close(finalize=exc_type is None)
