"""Streaming compression: absorb snapshot blocks and low-rank increments.

A :class:`StreamCompressor` keeps the expansion ``A ~ U V^T`` of every snapshot seen so
far (columns of ``A``) with ``U`` orthonormal in the inner product ``M``. Each update

1. decomposes the new left vectors on the basis by block CGS2, rejecting directions whose
   residual is below ``reject_tol`` (:func:`streamsvd.gram_schmidt.cgs2_extend`);
2. runs ``sweeps`` rotation sweeps of the paper (Algorithm 2, rule ``"paper"`` or
   ``"jacobi"``) on a small core;
3. truncates the terms that fail ``||v_i|| >= eps``, ``||v_i|| >= rtol * ||v_1||`` or
   ``i <= max_rank`` (after the sweeps, on the sorted amplitudes), logging the energy cut.

Cost. The large factors are kept lazily as products ``U = U0 @ Gu`` and
``V = Vraw @ Gv`` of a stored factor and a small matrix with orthonormal columns, and the
rotations act on a small core ``R`` with ``V^T V = R^T R``. Absorbing ``b`` columns at
rank ``p`` costs ``O(n w b + (p + b)^3)`` with ``w <= compact_ratio * p`` the stored width,
independent of the number of snapshots already absorbed; when the stored width exceeds
``compact_ratio * p`` the products are formed once (compaction).

Orthogonality. The small Gram ``H = U0^T M U0`` is kept up to date, so
``||U^T M U - I|| = ||Gu^T H Gu - I||`` is measured after every update at a cost of
``O(w^2 p)``; when it exceeds ``reorth_tol`` (default ``10 n eps``) the basis is
re-orthonormalised through the Cholesky factor of that small Gram (``U <- U L^{-T}``,
``V <- V L``, which leaves ``U V^T`` unchanged).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from ._core import (
    HISTORY_FIELDS,
    Bound,
    Truncation,
    UpdateRecord,
    core_step,
    history_array,
    r_factor,
    record_from_row,
)
from ._scaling import safe_column_norms
from ._validation import as_float_array, check_choice, check_nonnegative, check_positive_int
from .compress import fix_signs
from .errors import InputError, StoreError, StoreMismatchError
from .expansion import Expansion
from .gram_schmidt import cgs2_extend, default_reject_tol
from .inner import InnerProduct, as_inner, check_same_inner
from .rotations import RULES
from .store import BasisStore, open_store

__all__ = ["StreamCompressor", "UpdateRecord"]

logger = logging.getLogger(__name__)

_EPS = np.finfo(np.float64).eps


@dataclass(frozen=True)
class _Factors:
    """The lazy state: U = U0 Gu, V = Vraw Gv, V^T V = R^T R, H = U0^T M U0."""

    U0: np.ndarray
    MU0: np.ndarray
    Gu: np.ndarray
    H: np.ndarray
    Vraw: np.ndarray
    Gv: np.ndarray
    R: np.ndarray

    @property
    def rank(self) -> int:
        return int(self.Gu.shape[1])

    @property
    def m(self) -> int:
        return int(self.Vraw.shape[0])


def _empty_factors(n: int, euclidean: bool) -> _Factors:
    U0 = np.zeros((n, 0))
    return _Factors(
        U0=U0,
        MU0=U0 if euclidean else np.zeros((n, 0)),
        Gu=np.zeros((0, 0)),
        H=np.zeros((0, 0)),
        Vraw=np.zeros((0, 0)),
        Gv=np.zeros((0, 0)),
        R=np.zeros((0, 0)),
    )


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
        Keep at most this many terms (the ones of largest amplitude after the sweeps).
    rule : {"paper", "jacobi"}
        Rotation rule of the sweeps (see :func:`streamsvd.compress`).
    sweeps : int or None
        Rotation sweeps per update; ``None`` sweeps to convergence (the exact SVD of the
        current expansion, as Brand's incremental SVD).
    reject_tol : float, optional
        Gram-Schmidt rejection threshold relative to a column's norm; default ``n * eps``.
    compact_ratio : float
        Compact the lazy factors when their stored width exceeds ``compact_ratio * rank``.
    reorth_tol : float, optional
        Re-orthonormalise when ``||U^T M U - I||_2`` exceeds it; default ``10 n eps``.
    store : str or path-like, optional
        Create a zarr basis store there (see :mod:`streamsvd.store`) and commit the state
        to it every ``commit_every`` updates. An existing store is continued with
        :meth:`StreamCompressor.open`, not overwritten.
    commit_every : int
        Updates between two commits (the last ones are committed by :meth:`flush` or
        :meth:`close`).

    Notes
    -----
    Error bound. Let ``A_t`` be every snapshot (and increment) received after ``t``
    updates, ``K_t = U V^T`` the expansion and ``E_t = A_t - K_t``. Update ``t`` discards
    ``D_t`` (truncated terms and rejected residuals) of energy ``e_t = ||D_t||_F^2``, so
    ``E_t = E_{t-1} + D_t`` (padded with zero columns). Then

        ||E_t||^2 = ||E_{t-1}||^2 + e_t + 2 <E_{t-1}, D_t>.

    For ``absorb`` only, ``|<E_{t-1}, D_t>| <= c_{t-1}`` where ``c_t = c_{t-1} +
    ||W_kd||_*`` accumulates the nuclear norm of the coupling ``W_kd = V_kept^T V_cut``
    between kept and cut terms at each truncation (``K_t D_t^T = U_k W_kd U_d^T``, and
    ``K_t E_t^T = (I - P_t) K_{t-1} E_{t-1}^T + K_t D_t^T`` with ``P_t`` an orthogonal
    projection). By Cauchy-Schwarz the cross term is also at most
    ``sqrt(e_t) ||E_{t-1}||``. Hence the guaranteed bound

        b_t^2 = b_{t-1}^2 + e_t + 2 min(c_{t-1}, sqrt(e_t) b_{t-1}),

    with ``c = inf`` once an ``add`` has overlapped earlier columns. When every truncation
    happens at convergence (``sweeps=None``), ``W_kd = 0`` and the bound is the
    Pythagorean ``sqrt(sum_t e_t)``; it is never worse than the triangle inequality
    ``sum_t sqrt(e_t)``. Rounding errors (of order ``eps ||A||_F``) are not included.
    """

    def __init__(
        self,
        n: int,
        *,
        inner: Any = None,
        eps: float = 0.0,
        rtol: float | None = None,
        max_rank: int | None = None,
        rule: str = "paper",
        sweeps: int | None = 1,
        reject_tol: float | None = None,
        compact_ratio: float = 2.0,
        reorth_tol: float | None = None,
        store: Any = None,
        commit_every: int = 1,
    ) -> None:
        self.n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        self.inner: InnerProduct = as_inner(inner, self.n)
        self.eps = check_nonnegative(eps, "eps")
        self.rtol = None if rtol is None else check_nonnegative(rtol, "rtol")
        self.max_rank = check_positive_int(max_rank, "max_rank", allow_none=True)
        self.rule = check_choice(rule, "rule", RULES)
        self.sweeps = check_positive_int(sweeps, "sweeps", allow_none=True)
        self.reject_tol = (
            default_reject_tol(self.n)
            if reject_tol is None
            else check_nonnegative(reject_tol, "reject_tol")
        )
        self.compact_ratio = check_nonnegative(compact_ratio, "compact_ratio")
        if self.compact_ratio < 1.0:
            raise InputError(f"`compact_ratio` must be >= 1; got {compact_ratio!r}.")
        self.reorth_tol = (
            10 * self.n * _EPS
            if reorth_tol is None
            else check_nonnegative(reorth_tol, "reorth_tol")
        )
        self.commit_every = int(check_positive_int(commit_every, "commit_every"))  # type: ignore[arg-type]
        self._truncation = Truncation(self.eps, self.rtol, self.max_rank)
        self._f = _empty_factors(self.n, self.inner.is_euclidean)
        self._bound = Bound()
        self._history: list[UpdateRecord] = []
        self._version = 0  # increases with every state change (for the exposure cache)
        self._exposure: tuple[int, np.ndarray, np.ndarray] | None = None
        self.source_offset = 0
        self._store: BasisStore | None = None
        self._uncommitted = 0
        if store is not None:
            self._store = BasisStore.create(
                store, n=self.n, dtype="float64", inner_fingerprint=self.inner.fingerprint,
                attrs=self._attrs(),
            )
            self._commit(self._f, self._scalars())

    # ------------------------------------------------------------------ persistence
    @classmethod
    def open(cls, path: Any, *, inner: Any = None, mode: str = "a") -> StreamCompressor:
        """Reopen a compressor from its store, exactly as it was at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``StreamCompressor(..., store=path)``.
        inner : optional
            The inner product the store was written with (checked by fingerprint);
            Euclidean when omitted.
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock); ``"r"`` reads only.
        """
        mode = check_choice(mode, "mode", ("a", "r"))
        st = open_store(path, mode)  # type: ignore[arg-type]
        try:
            state = st.read()
            attrs = state.attrs
            if attrs.get("kind") != "streamsvd.StreamCompressor":
                raise StoreMismatchError(
                    f"`path` {path!s} holds a basis store that was not written by a "
                    "StreamCompressor; open a TallCompressor's store with "
                    "`streamsvd.parallel.open_compressor`, any other with "
                    "`streamsvd.store.open_store`."
                )
            ip = as_inner(inner, state.n)
            if ip.fingerprint != state.inner_fingerprint:
                raise StoreMismatchError(
                    f"`inner` must be the inner product the store {path!s} was written with "
                    f"(fingerprint {state.inner_fingerprint[:12]}...); got {ip!r}. Pass the "
                    "same matrix or weights."
                )
            opts = attrs["options"]
            sc = cls(state.n, inner=ip, **opts)
            sc._restore(state.arrays, attrs.get("small_layout"))
            sc._store = st
        except BaseException:
            st.close()
            raise
        return sc

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        if self._store is not None and self._uncommitted:
            self._commit(self._f, self._scalars())
            self._uncommitted = 0

    def close(self) -> None:
        """Commit what is pending and release the store's writer lock."""
        if self._store is not None:
            if self._store.mode == "a":
                self.flush()
            self._store.close()
            self._store = None

    def __enter__(self) -> StreamCompressor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def store_path(self) -> str | None:
        """Path of the store, or None."""
        return None if self._store is None else str(self._store.path)

    def _options(self) -> dict[str, Any]:
        return {
            "eps": self.eps, "rtol": self.rtol, "max_rank": self.max_rank, "rule": self.rule,
            "sweeps": self.sweeps, "reject_tol": self.reject_tol,
            "compact_ratio": self.compact_ratio, "reorth_tol": self.reorth_tol,
            "commit_every": self.commit_every,
        }

    def _attrs(self) -> dict[str, Any]:
        return {
            "kind": "streamsvd.StreamCompressor",
            "options": self._options(),
            "n_seen": self.n_seen,
            "rank": self.rank,
            "source_offset": self.source_offset,
            "updates": len(self._history),
            "error_bound": self.error_bound,
            "discarded_energy": self._bound.discarded,
        }

    def _scalars(self) -> np.ndarray:
        b = self._bound
        return np.array([b.bound2, b.coupling, b.discarded, float(self.source_offset)])

    def _arrays(self, f: _Factors, scalars: np.ndarray) -> dict[str, np.ndarray]:
        # the small matrices travel packed in one array (fewer files to write and fsync
        # per commit); their shapes are in the attributes (see `_small_layout`)
        small = [f.Gu, f.H, f.Gv, f.R, scalars, history_array(self._history)]
        arrays = {
            "U0": f.U0, "Vraw": f.Vraw,
            "small": np.concatenate([a.ravel() for a in small]) if small else np.zeros(0),
        }
        if not self.inner.is_euclidean:
            arrays["MU0"] = f.MU0
        return arrays

    def _small_layout(self, f: _Factors) -> list[list[int]]:
        return [list(a.shape) for a in (f.Gu, f.H, f.Gv, f.R)] + [
            [4], [len(self._history), len(HISTORY_FIELDS)]
        ]

    def _commit(self, f: _Factors, scalars: np.ndarray) -> None:
        assert self._store is not None
        if self._store.mode != "a":
            raise StoreError(
                f"the store {self._store.path} is open read-only; reopen it with "
                "`StreamCompressor.open(path, mode='a')` to continue the stream."
            )
        attrs = self._attrs()
        attrs.update(n_seen=f.m, rank=f.rank, source_offset=int(scalars[3]),
                     error_bound=math.sqrt(scalars[0]), discarded_energy=float(scalars[2]),
                     updates=len(self._history), small_layout=self._small_layout(f))
        self._store.commit(self._arrays(f, scalars), attrs=attrs)

    def _restore(self, arrays: dict[str, np.ndarray], layout: Any) -> None:
        if not arrays:
            # killed between the creation of the store and its first commit: the store
            # holds the options only, and nothing was absorbed
            return
        a = {k: np.array(v, dtype=np.float64) for k, v in arrays.items()}
        pieces = []
        start = 0
        for shape in layout:
            size = int(np.prod(shape))
            pieces.append(a["small"][start : start + size].reshape(shape))
            start += size
        Gu, H, Gv, R, scalars, history = pieces
        U0 = a["U0"]
        self._version += 1
        self._f = _Factors(
            U0=U0, MU0=a["MU0"] if "MU0" in a else U0, Gu=Gu, H=H, Vraw=a["Vraw"], Gv=Gv, R=R,
        )
        bound2, coupling, discarded, offset = (float(x) for x in scalars)
        self._bound = Bound(bound2, coupling, discarded)
        self.source_offset = int(offset)
        self._history = [record_from_row(row) for row in history]

    # ------------------------------------------------------------------ properties
    @property
    def n_seen(self) -> int:
        """Number of snapshots (columns) in the expansion."""
        return self._f.m

    @property
    def rank(self) -> int:
        """Current number of terms."""
        return self._f.rank

    @property
    def expansion(self) -> Expansion:
        """The current expansion ``U V^T`` (formed from the lazy factors, signs fixed).

        Terms are sorted by decreasing amplitude and signed so that the largest entry of
        each ``u_i`` is positive; ``add(..., coefficients=dV)`` takes ``dV`` in the
        coordinates of this ``U``.
        """
        f = self._f
        U = f.U0 @ f.Gu
        V = f.Vraw @ f.Gv
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U, V = U[:, perm], V[:, perm]
        signs = fix_signs(U, V)
        self._exposure = (self._version, perm, signs)
        return Expansion(U, V, inner=self.inner)

    @property
    def amplitudes(self) -> np.ndarray:
        """``||v_i||``, computed on the small core (``||v_i|| = ||r_i||``), sorted."""
        return np.sort(safe_column_norms(self._f.R))[::-1]

    @property
    def discarded_energy(self) -> float:
        """Sum of the energies ``||D_t||_F^2`` discarded by every update."""
        return self._bound.discarded

    @property
    def error_bound(self) -> float:
        """Guaranteed bound on ``||A - U V^T||_F`` (see the class notes for the theorem)."""
        return math.sqrt(self._bound.bound2)

    @property
    def history(self) -> tuple[UpdateRecord, ...]:
        """One :class:`UpdateRecord` per update, oldest first."""
        return tuple(self._history)

    def orthogonality_error(self) -> float:
        """Return ``||U^T M U - I||_2`` from the small Gram matrices."""
        return _orthogonality(self._f)

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

        On bad input an :class:`~streamsvd.errors.InputError` is raised and the state,
        in memory and in the store, is unchanged.
        """
        t0 = time.perf_counter()
        B = as_float_array(columns, "columns", ndim=2, rows=self.n, allow_empty=False)
        f = self._f
        ext = cgs2_extend(
            f.U0, f.MU0, B, inner=self.inner, reject_tol=self.reject_tol, G=f.Gu
        )
        b = B.shape[1]
        r = ext.Q_new.shape[1]
        # V_new = [[V, 0], [C^T, R_new^T]] = blockdiag(Q_V, I_b) K
        K = np.zeros((f.R.shape[0] + b, f.rank + r))
        K[: f.R.shape[0], : f.rank] = f.R
        K[f.R.shape[0] :, : f.rank] = ext.coeffs.T
        K[f.R.shape[0] :, f.rank :] = ext.R_new.T
        Vraw = np.zeros((f.m + b, f.Vraw.shape[1] + r))
        Vraw[: f.m, : f.Vraw.shape[1]] = f.Vraw
        Vraw[f.m :, : f.Vraw.shape[1]] = ext.coeffs.T @ f.Gv.T
        Vraw[f.m :, f.Vraw.shape[1] :] = ext.R_new.T
        rejected_energy = float(np.sum(ext.rejected_norms**2))
        grown = _grow(f, ext.Q_new, ext.MQ_new, Vraw, self.inner)
        offset = self.source_offset + b if source_offset is None else int(source_offset)
        self._update(
            "absorb", b, grown, K, ext, rejected_energy, overlapping=False, t0=t0,
            coupling_extra=math.sqrt(rejected_energy) * float(np.linalg.norm(B)),
            source_offset=offset,
        )
        return self._history[-1]

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
        """
        t0 = time.perf_counter()
        Uk = as_float_array(U_k, "U_k", ndim=2, rows=self.n)
        f = self._f
        m = f.m if (f.m or f.rank) else None
        Vk = as_float_array(V_k, "V_k", ndim=2, rows=m, cols=Uk.shape[1])
        dV_int = None
        if coefficients is not None:
            dV = as_float_array(coefficients, "coefficients", ndim=2, rows=f.m, cols=f.rank)
            dV_int = self._internal_coefficients(dV)
        elif Uk.shape[1] == 0:
            raise InputError(
                f"`U_k` must have at least one column (or pass `coefficients`); got shape "
                f"{Uk.shape}."
            )
        if f.m == 0 and f.rank == 0:
            f = _Factors(f.U0, f.MU0, f.Gu, f.H, np.zeros((Vk.shape[0], 0)), f.Gv, np.zeros((0, 0)))
        ext = cgs2_extend(
            f.U0, f.MU0, Uk, inner=self.inner, reject_tol=self.reject_tol, G=f.Gu
        )
        # V_new = [V + V_k C^T, V_k R_new^T], formed explicitly (V_k spans every row)
        V_old = f.Vraw @ f.Gv
        if dV_int is not None:
            V_old = V_old + dV_int
        V_new = np.concatenate([V_old + Vk @ ext.coeffs.T, Vk @ ext.R_new.T], axis=1)
        K = r_factor(V_new)
        vnorms = safe_column_norms(Vk)
        rejected_energy = float(np.sum((ext.rejected_norms * vnorms) ** 2))
        grown = _grow(f, ext.Q_new, ext.MQ_new, V_new, self.inner, reset_v=True)
        self._update(
            "add", Uk.shape[1], grown, K, ext, rejected_energy, overlapping=True, t0=t0,
            source_offset=self.source_offset,
        )
        return self._history[-1]

    def _internal_coefficients(self, dV: np.ndarray) -> np.ndarray:
        """Map coefficients on the exposed basis (sorted, signed) to the lazy factors."""
        if self._exposure is None or self._exposure[0] != self._version:
            _ = self.expansion  # computes and caches the exposure of this state
        assert self._exposure is not None
        _, perm, signs = self._exposure
        out = np.empty_like(dV)
        out[:, perm] = dV * signs
        return out

    def merge(self, other: StreamCompressor | Expansion) -> UpdateRecord:
        """Append the snapshots represented by ``other`` (they come after the current ones).

        ``other`` is a compressor fed with later columns (for instance on another worker)
        or an expansion of them; its left vectors are decomposed on the basis by CGS2 and
        its right vectors enter the small core through their QR factor, so the cost is
        ``O(n w p_o + m_o p_o (p + p_o))``, never ``O(n m_o)``. Error bounds compose: the
        two parts cover disjoint columns, so before the merge's own truncation the bound is
        ``sqrt(b_self^2 + b_other^2)`` (see the class notes), as in the hierarchical POD
        of Himpe, Leibner and Rave (2018).
        """
        t0 = time.perf_counter()
        if isinstance(other, StreamCompressor):
            if other.n != self.n:
                raise InputError(
                    f"`other` must have snapshots of size {self.n}; got {other.n}."
                )
            check_same_inner(self.inner, other.inner, "other")
            e_o = other.expansion
            other_bound = other._bound
        elif isinstance(other, Expansion):
            if other.n != self.n:
                raise InputError(
                    f"`other` must have snapshots of size {self.n}; got {other.n}."
                )
            check_same_inner(self.inner, other.inner, "other")
            e_o, other_bound = other, Bound()
        else:
            raise InputError(
                "`other` must be a StreamCompressor or an Expansion; got "
                f"{type(other).__name__}."
            )
        f = self._f
        if f.m == 0 and f.rank == 0:
            f = _Factors(f.U0, f.MU0, f.Gu, f.H, np.zeros((0, 0)), np.zeros((0, 0)), f.R)
        Ub, Vb = np.array(e_o.U), np.array(e_o.V)
        ext = cgs2_extend(
            f.U0, f.MU0, Ub, inner=self.inner, reject_tol=self.reject_tol, G=f.Gu
        )
        r = ext.Q_new.shape[1]
        mb = Vb.shape[0]
        Rb = r_factor(Vb)
        K = np.zeros((f.R.shape[0] + Rb.shape[0], f.rank + r))
        K[: f.R.shape[0], : f.rank] = f.R
        K[f.R.shape[0] :, : f.rank] = Rb @ ext.coeffs.T
        K[f.R.shape[0] :, f.rank :] = Rb @ ext.R_new.T
        Vraw = np.zeros((f.m + mb, f.Vraw.shape[1] + r))
        Vraw[: f.m, : f.Vraw.shape[1]] = f.Vraw
        Vraw[f.m :, : f.Vraw.shape[1]] = Vb @ (ext.coeffs.T @ f.Gv.T)
        Vraw[f.m :, f.Vraw.shape[1] :] = Vb @ ext.R_new.T
        # rejected residuals r_k v_k^T share columns: bound their sum by the triangle rule
        rejected_energy = float(np.sum(ext.rejected_norms * safe_column_norms(Vb))) ** 2
        grown = _grow(f, ext.Q_new, ext.MQ_new, Vraw, self.inner)
        self._update(
            "merge", mb, grown, K, ext, rejected_energy, overlapping=False, t0=t0,
            source_offset=self.source_offset + mb,
            prior=self._bound.combine(other_bound),
        )
        return self._history[-1]

    # ------------------------------------------------------------------ internals
    def _update(
        self,
        kind: str,
        columns: int,
        f: _Factors,
        K: np.ndarray,
        ext: Any,
        rejected_energy: float,
        *,
        overlapping: bool,
        t0: float,
        source_offset: int,
        coupling_extra: float = 0.0,
        prior: Bound | None = None,
    ) -> None:
        step = core_step(
            K, rule=self.rule, sweeps=self.sweeps, m=f.m, truncation=self._truncation,
            kind=kind,
        )
        new = _Factors(
            U0=f.U0, MU0=f.MU0, Gu=f.Gu @ step.T, H=f.H, Vraw=f.Vraw, Gv=f.Gv @ step.T,
            R=step.R,
        )
        new = _maybe_compact(new, self.compact_ratio, self.inner)
        orth = _orthogonality(new)
        if orth > self.reorth_tol:
            logger.info("re-orthonormalising the basis (||U^T M U - I|| = %.2e)", orth)
            new = _reorthonormalize(new)
            orth = _orthogonality(new)
        energy = step.cut_energy + rejected_energy
        bound = (self._bound if prior is None else prior).step(
            energy, step.coupling, overlapping=overlapping, extra=coupling_extra
        )
        record = UpdateRecord(
            kind=kind, columns=columns, rank=new.rank,
            new_directions=int(ext.Q_new.shape[1]),
            rejected=int(np.count_nonzero(~ext.accepted)), cut=step.cut,
            cut_energy=energy, sweeps=step.sweeps, max_cosine=step.max_cosine,
            orthogonality=orth, error_bound=math.sqrt(bound.bound2),
            seconds=time.perf_counter() - t0,
        )
        scalars = np.array([bound.bound2, bound.coupling, bound.discarded, float(source_offset)])
        # persist first, then switch the in-memory state: an exception anywhere above or
        # in the commit leaves both the memory and the store as they were
        self._history.append(record)
        try:
            if self._store is not None and self._uncommitted + 1 >= self.commit_every:
                self._commit(new, scalars)
                self._uncommitted = 0
            elif self._store is not None:
                self._uncommitted += 1
        except BaseException:
            self._history.pop()
            raise
        self._f = new
        self._version += 1
        self._bound = bound
        self.source_offset = source_offset


def _grow(
    f: _Factors,
    Q_new: np.ndarray,
    MQ_new: np.ndarray,
    Vraw: np.ndarray,
    inner: InnerProduct,
    *,
    reset_v: bool = False,
) -> _Factors:
    """Append new directions to the lazy factors (Gu, Gv grow by an identity block)."""
    r = Q_new.shape[1]
    w, p = f.Gu.shape
    U0 = np.concatenate([f.U0, Q_new], axis=1)
    MU0 = U0 if inner.is_euclidean else np.concatenate([f.MU0, MQ_new], axis=1)
    H = np.zeros((w + r, w + r))
    H[:w, :w] = f.H
    if r:
        cross = f.MU0.T @ Q_new
        H[:w, w:] = cross
        H[w:, :w] = cross.T
        H[w:, w:] = MQ_new.T @ Q_new
    Gu = np.zeros((w + r, p + r))
    Gu[:w, :p] = f.Gu
    Gu[w:, p:] = np.eye(r)
    if reset_v:
        Gv = np.eye(p + r)
    else:
        wv = f.Gv.shape[0]
        Gv = np.zeros((wv + r, p + r))
        Gv[:wv, :p] = f.Gv
        Gv[wv:, p:] = np.eye(r)
    return _Factors(U0=U0, MU0=MU0, Gu=Gu, H=H, Vraw=Vraw, Gv=Gv, R=f.R)


def _maybe_compact(f: _Factors, ratio: float, inner: InnerProduct) -> _Factors:
    """Form ``U0 @ Gu`` and ``Vraw @ Gv`` when the stored width exceeds ``ratio * rank``."""
    p = f.rank
    limit = ratio * max(p, 1)
    U0, MU0, Gu, H = f.U0, f.MU0, f.Gu, f.H
    if Gu.shape[0] > limit:
        U0 = U0 @ Gu
        MU0 = U0 if inner.is_euclidean else MU0 @ Gu
        H = Gu.T @ H @ Gu
        Gu = np.eye(p)
    Vraw, Gv = f.Vraw, f.Gv
    if Gv.shape[0] > limit:
        Vraw = Vraw @ Gv
        Gv = np.eye(p)
    return _Factors(U0=U0, MU0=MU0, Gu=Gu, H=H, Vraw=Vraw, Gv=Gv, R=f.R)


def _orthogonality(f: _Factors) -> float:
    p = f.rank
    if p == 0:
        return 0.0
    G = f.Gu.T @ f.H @ f.Gu
    return float(np.linalg.norm(G - np.eye(p), 2))


def _reorthonormalize(f: _Factors) -> _Factors:
    """``U <- U L^{-T}``, ``V <- V L`` with ``U^T M U = L L^T``: ``U V^T`` is unchanged.

    ``V L`` is formed explicitly (``Gv`` must keep orthonormal columns, since new rows are
    appended as ``C^T Gv^T``); this costs ``O(m w p)`` and happens rarely.
    """
    G = f.Gu.T @ f.H @ f.Gu
    G = 0.5 * (G + G.T)
    L = np.linalg.cholesky(G)
    Gu = scipy.linalg.solve_triangular(L, f.Gu.T, lower=True).T
    Vraw = f.Vraw @ (f.Gv @ L)
    return _Factors(
        U0=f.U0, MU0=f.MU0, Gu=Gu, H=f.H, Vraw=Vraw, Gv=np.eye(f.rank), R=f.R @ L,
    )



