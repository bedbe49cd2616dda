"""Out-of-core streaming for tall snapshots: the basis lives in zarr, chunked by rows.

:class:`TallCompressor` is the :class:`~streamsvd.StreamCompressor` of snapshots too
long for ``n x p`` to fit in memory. The stored factor ``U0`` is a list of *panels*, zarr
arrays chunked by rows, in the store directory (``<store>/panels/``); the basis is the
lazy product ``U = U0 @ Gu`` with a small ``Gu``, and only small matrices (``Gu``, the
Gram ``H = U0^T M U0``, the core ``R``, ``Vraw``, ``Gv``) are kept in memory. Every
product with an ``n``-sized factor runs over row chunks with dask (``map_blocks`` and
``da.reduction``), on the threaded scheduler or on a ``distributed`` cluster, so the
peak memory is a few row chunks, not ``n x p``.

Absorbing a block ``B`` (``n x b``) takes four passes over the row chunks:

A. ``B`` is read once from the source and copied to a scratch array; each chunk returns
   ``U0_i^T M B_i`` and the column norms, scaled by exact powers of two chunk by chunk and
   combined exponent-aware (entries from 1e-300 to 1e300 neither overflow nor underflow).
B. First projection ``X' = X - U C1`` (``X`` the scaled block), written to scratch; each
   chunk returns ``U0_i^T M X'_i`` and ``X'_i^T M X'_i``.
C. Second projection ``X'' = X' - U C2`` ("twice is enough"), formed on the fly. The
   Gram of ``X''`` follows from the pass-B sums; its Cholesky factor, computed column by
   column in the block's order, is that of classical Gram-Schmidt, and a column whose
   residual is ``<= reject_tol * ||x_k||_M`` (or below the Gram's resolution, see
   below) is rejected exactly as :func:`~streamsvd.gram_schmidt.extend_basis` rejects
   it. Each chunk returns the Gram sums of ``Q1 = X''[:, acc] L1^{-T}`` and the energy
   of the residual each rejected column leaves out, measured on the vectors.
D. CholeskyQR2's second pass: ``Q = (Q1 - U C3) L2^{-T}`` is written as a new panel, and
   each chunk returns ``U0_i^T M Q_i`` and ``Q_i^T M Q_i``, which extend ``H`` with the
   Gram of what was actually written. When ``X''[:, acc]`` is well conditioned
   (``cond(L1)^2 <= n``) and no accepted column lost more than half its norm in the
   second projection, a single CholeskyQR is accurate to ``O(n eps)``: ``Q = Q1`` is
   written in pass C, and the block costs three passes instead of four.

The coefficients ``C = C1 + C2 + C3 F`` and ``R_new = L2^T F`` then enter the same small
core, the same rotation sweeps (:func:`streamsvd._core.core_step`), the same
truncation and the same error-bound recursion as :class:`~streamsvd.StreamCompressor`,
so both give the same basis up to rounding. When the stored width exceeds
``compact_ratio * rank``, a fifth pass writes ``U0 @ Gu`` as a single panel (applying the
accumulated rotations) and measures its Gram.

Gram resolution. A Gram matrix resolves a residual only down to about
``sqrt(c eps) ||x'_k||`` (``c = 4 (b + sqrt(n))``), ``x'_k`` the column after the first
projection. Columns of a block that are dependent on each other to that level (not on
the basis, which the projections handle to ``eps``) are rejected where the in-memory
Gram-Schmidt would keep a direction of relative size below ``1e-6``; the energy of every
rejected residual is measured on the vectors (pass C), so the error bound stays exact.

Crash safety. Panels are written once and never modified; the small state and the list
of panels are committed through :class:`~streamsvd.store.BasisStore` (atomic pointer
switch); a panel is deleted only when neither the current nor the previous committed
generation refers to it. A process or worker killed at any instant leaves the last
commit readable; leftovers are removed on the next open.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import tempfile
import time
import uuid
import weakref
from functools import partial
from pathlib import Path
from typing import Any, cast

import numpy as np
import scipy.linalg
from scipy.linalg.blas import dsyrk

from ._core import Truncation, UpdateRecord, core_step, history_array, record_from_row
from ._scaling import safe_column_norms
from ._validation import as_float_array, check_choice, check_nonnegative, check_positive_int
from .bound import Bound
from .compress import fix_signs
from .errors import (
    InputError,
    ShapeMismatchError,
    SourceError,
    StoreError,
    StoreMismatchError,
    StreamSVDError,
)
from .expansion import Expansion
from .gram_schmidt import default_reject_tol
from .inner import DiagonalInner, InnerProduct, as_inner
from .parallel_tree import check_client, execute
from .rotations import RULES
from .store import BasisStore, open_store

__all__ = ["DEFAULT_CHUNK_ROWS", "TallCompressor"]

logger = logging.getLogger(__name__)

_EPS = np.finfo(np.float64).eps
_ZERO_EXP = -(2**20)  # exponent of an all-zero column in the exponent-aware sums
DEFAULT_CHUNK_ROWS = 16384
"""Rows per chunk of the stored panels when ``chunk_rows`` is not given."""

KIND = "streamsvd.TallCompressor"


# ------------------------------------------------------------------ chunk kernels
# Each kernel receives the row chunks of [U0] [weights] data... in that order (U0 and the
# weights only when present) and returns either a chunk of an n-sized result or one row
# of partial sums, reduced over the chunks by dask.


def _unpack(blocks: tuple[np.ndarray, ...], has_u: bool, has_w: bool) -> tuple[Any, Any, list]:
    k = 0
    U = blocks[k] if has_u else None
    k += int(has_u)
    w = blocks[k] if has_w else None
    k += int(has_w)
    return U, w, list(blocks[k:])


def _k_first(*blocks: np.ndarray, has_u: bool, has_w: bool) -> np.ndarray:
    """Pass A: ``[non-finite count, exponents, M-norms^2, norms^2, U0^T M X]``.

    Each column is scaled by the power of two of its largest entry in this chunk; the
    partial sums are combined exponent-aware by :func:`_combine_first`.
    """
    U, w, (X,) = _unpack(blocks, has_u, has_w)
    finite = np.isfinite(X)
    bad = X.size - int(np.count_nonzero(finite))
    if bad:
        X = np.where(finite, X, 0.0)
    peak = np.max(np.abs(X), axis=0) if X.shape[0] else np.zeros(X.shape[1])
    exps = np.where(peak > 0, np.frexp(np.where(peak > 0, peak, 1.0))[1], 0)
    Xs = np.ldexp(X, -exps[np.newaxis, :])
    MXs = Xs if w is None else Xs * w
    nu2 = np.einsum("ij,ij->j", Xs, MXs)
    eu2 = np.einsum("ij,ij->j", Xs, Xs)
    S = U.T @ MXs if U is not None else np.zeros((0, X.shape[1]))
    e = np.where(peak > 0, exps, _ZERO_EXP).astype(np.float64)
    return np.concatenate([[float(bad)], e, nu2, eu2, S.ravel()])[np.newaxis, :]


def _keep(x: np.ndarray, axis: Any = None, keepdims: bool = False) -> np.ndarray:
    return x


def _combine_first(x: np.ndarray, axis: Any = None, keepdims: bool = False, *,
                   b: int) -> np.ndarray:
    """Sum pass-A partials, each scaled by its own powers of two, exponent-aware."""
    x = np.atleast_2d(x)
    bad = np.sum(x[:, 0])
    E = x[:, 1 : b + 1]
    e = np.max(E, axis=0)
    shift = np.maximum(E - e, -4096.0).astype(np.int64)
    nu2 = np.sum(np.ldexp(x[:, b + 1 : 2 * b + 1], 2 * shift), axis=0)
    eu2 = np.sum(np.ldexp(x[:, 2 * b + 1 : 3 * b + 1], 2 * shift), axis=0)
    S = x[:, 3 * b + 1 :].reshape(x.shape[0], -1, b)
    S = np.sum(np.ldexp(S, shift[:, np.newaxis, :]), axis=0)
    return np.concatenate([[bad], e, nu2, eu2, S.ravel()])[np.newaxis, :]


def _k_residual(*blocks: np.ndarray, has_u: bool, exps: np.ndarray,
                K1: np.ndarray) -> np.ndarray:
    """Pass B: ``X' = X 2^-e - U0 K1`` (first projection)."""
    U, _, (X,) = _unpack(blocks, has_u, False)
    Xs = np.ldexp(X, -exps[np.newaxis, :])
    if U is not None:
        Xs -= U @ K1
    return Xs


def _sym_gram(Y: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """``Y^T diag(w) Y`` by the BLAS's symmetric rank-k update (half the flops of a product)."""
    if Y.size == 0:
        return np.zeros((Y.shape[1], Y.shape[1]))
    Z = Y if w is None else Y * np.sqrt(w)
    G = dsyrk(1.0, np.asfortranarray(Z.T), trans=0)
    return cast(np.ndarray, np.triu(G) + np.triu(G, 1).T)


def _k_gram(*blocks: np.ndarray, has_u: bool, has_w: bool) -> np.ndarray:
    """``[U0^T M Y, Y^T M Y]`` of one chunk, flattened in one row."""
    U, w, (Y,) = _unpack(blocks, has_u, has_w)
    S = U.T @ (Y if w is None else Y * w) if U is not None else np.zeros((0, Y.shape[1]))
    T = _sym_gram(Y, w)
    return np.concatenate([S.ravel(), T.ravel()])[np.newaxis, :]


def _cols(X: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``X[:, idx]``, without a copy when ``idx`` is every column in order."""
    if idx.size == X.shape[1] and (idx.size == 0 or (idx[0] == 0 and idx[-1] == idx.size - 1)):
        return X
    return X[:, idx]


def _q1(U: Any, Xp: np.ndarray, K2: np.ndarray, acc: np.ndarray, L1i: np.ndarray) -> np.ndarray:
    """``Q1 = (X' - U0 K2)[:, acc] L1^{-T}`` (``L1i = L1^{-T}``, a BLAS-3 product)."""
    Xpp = _cols(Xp, acc) - U @ _cols(K2, acc) if U is not None else _cols(Xp, acc)
    return Xpp @ L1i


def _k_pass_c(*blocks: np.ndarray, has_u: bool, has_w: bool, K2: np.ndarray,
              acc: np.ndarray, L1i: np.ndarray, rej: np.ndarray,
              F_rej: np.ndarray) -> np.ndarray:
    """Pass C: Gram sums of ``Q1 = (X' - U0 K2)[:, acc] L1^{-T}``, rejected residuals.

    Returns ``[U0^T M Q1, Q1^T M Q1, ||r_k||_M^2]`` where ``r_k = x''_k - Q1 F[:, k]`` is
    the residual a rejected column leaves out, measured on the vectors themselves.
    """
    U, w, (Xp,) = _unpack(blocks, has_u, has_w)
    Q1 = _q1(U, Xp, K2, acc, L1i) if acc.size else np.zeros((Xp.shape[0], 0))
    if rej.size:
        Xpp = Xp[:, rej] - U @ K2[:, rej] if U is not None else Xp[:, rej]
        Rr = Xpp - Q1 @ F_rej
        MRr = Rr if w is None else Rr * w
        e = np.einsum("ij,ij->j", Rr, MRr)
    else:
        e = np.zeros(0)
    MQ1 = Q1 if w is None else Q1 * w
    S = U.T @ MQ1 if U is not None else np.zeros((0, Q1.shape[1]))
    T = _sym_gram(Q1, w)
    return np.concatenate([S.ravel(), T.ravel(), e])[np.newaxis, :]


def _k_q(*blocks: np.ndarray, has_u: bool, K2: np.ndarray, acc: np.ndarray, L1i: np.ndarray,
         K3: np.ndarray | None, L2i: np.ndarray | None) -> np.ndarray:
    """Pass D: ``Q = (Q1 - U0 K3) L2^{-T}`` (CholeskyQR2's second pass), or ``Q1`` itself.

    With ``Q1 = X''[:, acc] L1^{-T}`` this is ``X''[:, acc] (L1^{-T} L2^{-T}) - U0 (K3
    L2^{-T})``: one product with the block instead of two.
    """
    U, _, (Xp,) = _unpack(blocks, has_u, False)
    if K3 is None or L2i is None:
        return _q1(U, Xp, K2, acc, L1i)
    Q = _q1(U, Xp, K2, acc, L1i @ L2i)
    if U is not None:
        Q -= U @ (K3 @ L2i)
    return Q


def _k_apply(U: np.ndarray, *, G: np.ndarray) -> np.ndarray:
    """Compaction: one chunk of ``U0 @ G``."""
    return U @ G


# ---------------------------------------------------------------- small matrices


def _ordered_cholesky(
    T: np.ndarray, nu: np.ndarray, reject_tol: float, floors: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cholesky of a residual Gram, column by column in order, with rejection.

    Column ``k`` is projected on the directions accepted before it (``l``); its residual
    energy is ``d = T_kk - l^T l``. It is accepted when ``d > (reject_tol nu_k)^2`` and
    ``d > floors_k`` (the Gram's resolution), as classical Gram-Schmidt accepts a
    direction.

    Returns
    -------
    acc : ndarray of int
        Accepted columns, in order.
    L1 : ndarray, shape (r, r)
        Lower triangular, ``T[acc][:, acc] = L1 L1^T``.
    F : ndarray, shape (r, b)
        Coefficients of every column on the new directions (upper trapezoidal).
    rejected : ndarray, shape (b,)
        Gram estimate ``max(d, 0)`` of each rejected column's residual energy (zero for
        accepted ones); the exact energy is measured on the vectors in pass C.
    """
    b = T.shape[0]
    L = np.zeros((b, b))
    F = np.zeros((b, b))
    rejected = np.zeros(b)
    acc: list[int] = []
    for k in range(b):
        r = len(acc)
        if r:
            col = T[acc, k]
            lvec = scipy.linalg.solve_triangular(L[:r, :r], col, lower=True)
        else:
            lvec = np.zeros(0)
        d = float(T[k, k] - lvec @ lvec)
        floor = float(floors[k])
        F[:r, k] = lvec
        if nu[k] == 0.0 or d <= max((reject_tol * nu[k]) ** 2, floor):
            rejected[k] = max(d, 0.0)
            continue
        L[r, :r] = lvec
        L[r, r] = math.sqrt(d)
        F[r, k] = math.sqrt(d)
        acc.append(k)
    r = len(acc)
    return np.array(acc, dtype=np.int64), L[:r, :r].copy(), F[:r].copy(), rejected


def _cholesky_or_eig(G: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of an SPD Gram; via a clipped eigendecomposition if it fails."""
    G = 0.5 * (G + G.T)
    try:
        return cast(np.ndarray, scipy.linalg.cholesky(G, lower=True))
    except np.linalg.LinAlgError:
        lam, Z = np.linalg.eigh(G)
        lam = np.maximum(lam, _EPS * max(float(lam[-1]), _EPS))
        Rf = np.linalg.qr(np.sqrt(lam)[:, np.newaxis] * Z.T, mode="r")
        sign = np.where(np.diag(Rf) < 0, -1.0, 1.0)
        logger.warning("CholeskyQR2: second Gram not positive definite; used its eigenvalues")
        return cast(np.ndarray, (sign[:, np.newaxis] * Rf).T)


def _inv_t(L: np.ndarray) -> np.ndarray:
    """``L^{-T}`` of a lower triangular ``L`` (applied to row chunks by one product)."""
    eye = np.eye(L.shape[0])
    return cast(np.ndarray, scipy.linalg.solve_triangular(L, eye, lower=True).T)


def _corrected_gram(T: np.ndarray, C: np.ndarray, Hu: np.ndarray) -> np.ndarray:
    """Gram of ``Y - U C`` from ``T = Y^T M Y`` and ``C = U^T M Y``, ``U^T M U = Hu``."""
    if C.size == 0:
        return 0.5 * (T + T.T)
    out = T - 2.0 * (C.T @ C) + C.T @ Hu @ C
    return 0.5 * (out + out.T)


@dataclasses.dataclass(frozen=True)
class _State:
    """The small, in-memory part of a tall compressor (``U = U0 @ Gu``)."""

    panels: tuple[str, ...]
    widths: tuple[int, ...]
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

    @property
    def w(self) -> int:
        return int(self.Gu.shape[0])


def _empty_state() -> _State:
    z = np.zeros((0, 0))
    return _State((), (), z, z, z, z, z)


class TallCompressor:
    """Stream snapshots into a basis kept out of core, in zarr panels chunked by rows.

    The same algorithm, options, error bound and store semantics as
    :class:`~streamsvd.StreamCompressor` (see its notes), with every ``n``-sized
    product run over row chunks by dask (module docstring). Memory holds a few row
    chunks and the small matrices (``O(w^2 + m w)`` with ``w <= compact_ratio * rank``).

    Parameters
    ----------
    n : int
        Size of one snapshot.
    store : str or path-like, optional
        Create a basis store there; the panels of ``U0`` live in its ``panels/`` group and
        the small state is committed every ``commit_every`` updates. Continue an existing
        one with :meth:`TallCompressor.open`.
    workdir : str or path-like, optional
        Without ``store``: directory for the panels and the scratch arrays (a temporary
        directory, removed by :meth:`close`, by default). On a remote cluster it must be
        visible to every worker.
    chunk_rows : int, optional
        Rows per chunk of the panels (default 16384); blocks are rechunked to match.
    client : distributed.Client, optional
        Run the row-chunk products on this cluster; the threaded scheduler by default.
    inner : None, array of weights or DiagonalInner
        Euclidean or diagonal weights (a matrix inner product couples the row chunks and
        is not offered out of core).
    eps, rtol, max_rank, rule, sweeps, reject_tol, compact_ratio, reorth_tol, commit_every
        As for :class:`~streamsvd.StreamCompressor`.

    Notes
    -----
    Cost of absorbing ``b`` columns at stored width ``w``, ``r <= b`` of them new
    directions: about ``2 n (4 w b + 3 b^2)`` flops in three or four passes over the row
    chunks (module docstring), which read the block once from the source, ``U0`` three or
    four times and the scratch copies of the block four or five times, and write
    ``n (2 b + r)`` numbers; plus ``O((p + b)^3)`` on the small core. A compaction (when
    ``w > compact_ratio * p``) reads ``U0`` once and writes ``n x p``. The memory is a few
    row chunks per dask thread (``chunk_rows x max(w, b)`` numbers each) and the small
    matrices (``O(w^2 + m w)``).
    """

    _store: BasisStore | None
    _cleanup: Any

    def __init__(
        self,
        n: int,
        *,
        store: Any = None,
        workdir: Any = None,
        chunk_rows: int | None = None,
        client: Any = None,
        inner: Any = None,
        eps: float = 0.0,
        rtol: float | None = None,
        max_rank: int | None = None,
        rule: str = "paper",
        sweeps: int | None = 1,
        reject_tol: float | None = None,
        compact_ratio: float = 2.0,
        reorth_tol: float | None = None,
        commit_every: int = 1,
    ) -> None:
        self._configure(
            n, chunk_rows=chunk_rows, client=client, inner=inner, eps=eps, rtol=rtol,
            max_rank=max_rank, rule=rule, sweeps=sweeps, reject_tol=reject_tol,
            compact_ratio=compact_ratio, reorth_tol=reorth_tol, commit_every=commit_every,
        )
        if store is not None and workdir is not None:
            raise InputError(
                f"`workdir` must be None when `store` is given (the panels live in the "
                f"store); got workdir={workdir!r}. Drop one of them."
            )
        if store is not None:
            self._store = BasisStore.create(
                store, n=self.n, dtype="float64", inner_fingerprint=self.inner.fingerprint,
                attrs=self._attrs(self._s, self._scalars()),
            )
            self._root = Path(store)
            self._init_panels()
            self._commit(self._s, self._scalars())
        else:
            if workdir is None:
                self._root = Path(tempfile.mkdtemp(prefix="streamsvd-tall-"))
                self._cleanup = weakref.finalize(self, shutil.rmtree, self._root, True)
            else:
                self._root = Path(workdir)
                self._root.mkdir(parents=True, exist_ok=True)
            self._init_panels()

    def _configure(self, n: int, *, chunk_rows: int | None, client: Any, inner: Any,
                   eps: float, rtol: float | None, max_rank: int | None, rule: str,
                   sweeps: int | None, reject_tol: float | None, compact_ratio: float,
                   reorth_tol: float | None, commit_every: int) -> None:
        """Validate and store the options; start from the empty state."""
        self.n = int(check_positive_int(n, "n"))  # type: ignore[arg-type]
        ip = as_inner(inner, self.n)
        if not (ip.is_euclidean or isinstance(ip, DiagonalInner)):
            raise InputError(
                f"`inner` must be Euclidean or diagonal weights out of core; got {ip!r}, "
                "which couples the row chunks. Use the in-memory StreamCompressor, or "
                "lump the mass matrix into weights."
            )
        self.inner: InnerProduct = ip
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
        self.chunk_rows = int(check_positive_int(  # type: ignore[arg-type]
            DEFAULT_CHUNK_ROWS if chunk_rows is None else chunk_rows, "chunk_rows"))
        self.client = check_client(client)
        self._s = _empty_state()
        self._bound = Bound()
        self._history: list[UpdateRecord] = []
        self.source_offset = 0
        self._store = None
        self._uncommitted = 0
        self._committed: tuple[tuple[str, ...], tuple[str, ...]] = ((), ())
        self._zarrs: dict[str, Any] = {}
        self._cleanup = None

    # --------------------------------------------------------------- persistence
    @classmethod
    def open(cls, path: Any, *, inner: Any = None, mode: str = "a", client: Any = None,
             ) -> TallCompressor:
        """Reopen a tall compressor from its store, exactly as at the last commit.

        Parameters
        ----------
        path : str or path-like
            The store written with ``TallCompressor(..., store=path)``.
        inner : optional
            The weights the store was written with (checked by fingerprint).
        mode : {"a", "r"}
            ``"a"`` continues the stream (takes the writer lock and removes panels left
            by an interrupted update); ``"r"`` reads only.
        client : distributed.Client, optional
            Cluster for the row-chunk products.
        """
        mode = check_choice(mode, "mode", ("a", "r"))
        st = open_store(path, mode)  # type: ignore[arg-type]
        try:
            state = st.read()
            attrs = state.attrs
            if attrs.get("kind") != KIND:
                raise StoreMismatchError(
                    f"`path` {path!s} holds a basis store of kind {attrs.get('kind')!r}, "
                    f"not {KIND!r}; open it with `StreamCompressor.open`."
                )
            ip = as_inner(inner, state.n)
            if ip.fingerprint != state.inner_fingerprint:
                raise StoreMismatchError(
                    f"`inner` must be the inner product the store {path!s} was written with "
                    f"(fingerprint {state.inner_fingerprint[:12]}...); got {ip!r}. Pass the "
                    "same weights."
                )
            tc = cls.__new__(cls)
            tc._configure(state.n, inner=ip, client=client,
                          chunk_rows=int(attrs["chunk_rows"]), **attrs["options"])
            tc._root = Path(path)
            tc._store = st
            tc._restore(state.arrays, attrs)
            if mode == "a":
                tc._gc()
        except BaseException:
            st.close()
            raise
        return tc

    def _init_panels(self) -> None:
        import zarr

        zarr.open_group(store=str(self._root), path="panels", mode="a")

    def _options(self) -> dict[str, Any]:
        return {
            "eps": self.eps, "rtol": self.rtol, "max_rank": self.max_rank, "rule": self.rule,
            "sweeps": self.sweeps, "reject_tol": self.reject_tol,
            "compact_ratio": self.compact_ratio, "reorth_tol": self.reorth_tol,
            "commit_every": self.commit_every,
        }

    @property
    def options(self) -> dict[str, Any]:
        """The compression options (as passed to the constructor, normalised)."""
        return self._options()

    def _scalars(self) -> np.ndarray:
        return np.concatenate([self._bound.to_array(), [float(self.source_offset)]])

    def _attrs(self, s: _State, scalars: np.ndarray) -> dict[str, Any]:
        return {
            "kind": KIND, "options": self._options(), "chunk_rows": self.chunk_rows,
            "panels": list(s.panels), "previous_panels": list(self._committed[0]),
            "n_seen": s.m, "rank": s.rank, "source_offset": int(scalars[3]),
            "updates": len(self._history), "error_bound": float(scalars[0]),
            "discarded_norm": float(scalars[2]),
        }

    def _commit(self, s: _State, scalars: np.ndarray) -> None:
        assert self._store is not None
        if self._store.mode != "a":
            raise StoreError(
                f"the store {self._store.path} is open read-only; reopen it with "
                "`TallCompressor.open(path, mode='a')` to continue the stream."
            )
        arrays = {
            "Gu": s.Gu, "H": s.H, "Vraw": s.Vraw, "Gv": s.Gv, "R": s.R, "scalars": scalars,
            "widths": np.array(s.widths, dtype=np.float64),
            "history": history_array(self._history),
        }
        self._store.commit(arrays, attrs=self._attrs(s, scalars))
        self._committed = (s.panels, self._committed[0])

    def _restore(self, arrays: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
        a = {k: np.array(v, dtype=np.float64) for k, v in arrays.items()}
        panels = tuple(str(p) for p in attrs["panels"])
        widths = tuple(int(x) for x in a["widths"])
        self._s = _State(panels, widths, a["Gu"], a["H"], a["Vraw"], a["Gv"], a["R"])
        self._bound = Bound.from_array(a["scalars"])
        self.source_offset = int(a["scalars"][3])
        self._history = [record_from_row(row) for row in a["history"]]
        self._committed = (panels, tuple(str(p) for p in attrs.get("previous_panels", [])))
        for name, width in zip(panels, widths, strict=True):
            z = self._panel(name)
            if z.shape != (self.n, width):
                raise StoreMismatchError(
                    f"`path` {self._root} is damaged: panel {name} has shape {z.shape}, "
                    f"expected {(self.n, width)}. Restore the store from a copy."
                )

    def flush(self) -> None:
        """Commit the current state to the store now (no-op without a store)."""
        if self._store is not None and self._uncommitted:
            self._commit(self._s, self._scalars())
            self._uncommitted = 0
            self._gc()

    def close(self) -> None:
        """Commit what is pending, release the store's lock, remove a temporary workdir."""
        if self._store is not None:
            if self._store.mode == "a":
                self.flush()
            self._store.close()
            self._store = None
        if self._cleanup is not None:
            self._cleanup()
            self._cleanup = None

    def __enter__(self) -> TallCompressor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def store_path(self) -> str | None:
        """Path of the store, or None."""
        return None if self._store is None else str(self._store.path)

    # ------------------------------------------------------------------ panels
    def _panel_dir(self, name: str) -> Path:
        return self._root / "panels" / name

    def _panel(self, name: str) -> Any:
        z = self._zarrs.get(name)
        if z is None:
            import zarr

            try:
                z = zarr.open_array(store=str(self._panel_dir(name)), mode="r")
            except (OSError, ValueError, KeyError) as exc:
                raise StoreError(
                    f"`store` {self._root}: panel {name} of the basis cannot be opened "
                    f"({type(exc).__name__}: {exc}). Restore the store from a copy."
                ) from exc
            self._zarrs[name] = z
        return z

    def _create(self, where: Path, cols: int, *, checksum: bool) -> Any:
        import zarr
        from zarr.codecs import Crc32cCodec

        return zarr.create_array(
            store=str(where), shape=(self.n, cols), chunks=(self.chunk_rows, max(cols, 1)),
            dtype="float64", fill_value=0.0,
            compressors=[Crc32cCodec()] if checksum else None,
        )

    def _row_chunks(self) -> tuple[int, ...]:
        rc = self.chunk_rows
        full, rest = divmod(self.n, rc)
        return (rc,) * full + ((rest,) if rest else ())

    def _u_dask(self, s: _State) -> Any:
        import dask.array as da

        if not s.panels:
            return None
        parts = [da.from_zarr(self._panel(p), name=f"streamsvd-panel-{p}") for p in s.panels]
        if len(parts) == 1:
            return parts[0]
        return da.concatenate(parts, axis=1).rechunk({1: -1})

    def _w_dask(self) -> Any:
        import dask.array as da

        if self.inner.is_euclidean:
            return None
        w = cast(DiagonalInner, self.inner).weights.reshape(-1, 1)
        return da.from_array(w, chunks=(self._row_chunks(), (1,)),
                             name=f"streamsvd-weights-{self.inner.fingerprint[:16]}")

    def _gc(self) -> None:
        """Delete the panels that neither the state nor the last two commits refer to."""
        keep = set(self._s.panels) | set(self._committed[0]) | set(self._committed[1])
        pdir = self._root / "panels"
        if not pdir.is_dir() or (self._store is not None and self._store.mode != "a"):
            return
        for entry in pdir.iterdir():
            if entry.is_dir() and entry.name not in keep:
                logger.debug("removing unreferenced panel %s", entry)
                self._zarrs.pop(entry.name, None)
                shutil.rmtree(entry, ignore_errors=True)

    def _drop(self, names: list[str]) -> None:
        for name in names:
            self._zarrs.pop(name, None)
            shutil.rmtree(self._panel_dir(name), ignore_errors=True)

    # ------------------------------------------------------------------ updates
    def _as_block(self, columns: Any) -> Any:
        import dask.array as da

        chunks = self._row_chunks()
        if type(columns).__module__.startswith("dask") and isinstance(columns, da.Array):
            if columns.ndim != 2 or columns.shape[0] != self.n:
                raise ShapeMismatchError(
                    f"`columns` must have {self.n} rows; got shape {columns.shape}. Pass "
                    "snapshots as columns."
                )
            if columns.dtype.kind not in "biuf":
                raise InputError(
                    f"`columns` must hold real numbers; got dtype {columns.dtype}. "
                    "Convert it with `.astype(float)`."
                )
            if columns.shape[1] == 0:
                raise InputError(f"`columns` must not be empty; got shape {columns.shape}.")
            return columns.astype(np.float64).rechunk((chunks, (columns.shape[1],)))
        B = as_float_array(columns, "columns", ndim=2, rows=self.n, allow_empty=False)
        return da.from_array(B, chunks=(chunks, (B.shape[1],)),
                             name=f"streamsvd-block-{uuid.uuid4().hex}")

    def absorb(self, columns: Any, *, source_offset: int | None = None) -> UpdateRecord:
        """Append a block of snapshots (``n x b``, a numpy or dask array).

        Parameters
        ----------
        columns : array_like or dask array, shape (n, b)
            The new snapshots; a dask array is read chunk by chunk, once.
        source_offset : int, optional
            Position in the source just after this block (recorded in the store).

        On any error (bad input, a failing read, a lost worker) the state in memory and
        in the store is unchanged, and what the update wrote is removed.
        """
        t0 = time.perf_counter()
        X = self._as_block(columns)
        b = int(X.shape[1])
        offset = self.source_offset + b if source_offset is None else int(source_offset)
        scratch = self._root / "scratch" / uuid.uuid4().hex
        created: list[str] = []
        try:
            ext = self._extend(X, scratch, created)
            f = self._s
            p, r = f.rank, ext["R_new"].shape[0]
            K = np.zeros((f.R.shape[0] + b, p + r))
            K[: f.R.shape[0], :p] = f.R
            K[f.R.shape[0] :, :p] = ext["coeffs"].T
            K[f.R.shape[0] :, p:] = ext["R_new"].T
            Vraw = np.zeros((f.m + b, f.Vraw.shape[1] + r))
            Vraw[: f.m, : f.Vraw.shape[1]] = f.Vraw
            Vraw[f.m :, : f.Vraw.shape[1]] = ext["coeffs"].T @ f.Gv.T
            Vraw[f.m :, f.Vraw.shape[1] :] = ext["R_new"].T
            grown = self._grow(f, ext, Vraw)
            self._update(
                b, grown, K, ext, created, t0=t0, source_offset=offset,
                coupling_extra=math.sqrt(math.sqrt(ext["rejected_energy"]) * ext["norm"]),
            )
        except StreamSVDError:
            self._drop(created)
            raise
        except Exception as exc:
            self._drop(created)
            raise SourceError(
                f"absorbing columns {offset - b}:{offset} (offset {offset - b}) failed: "
                f"{type(exc).__name__}: {exc}. The basis is unchanged"
                f"{'' if self._store is None else ' and the store holds its last commit'}; "
                f"fix the cause and resume from offset {self.source_offset}."
            ) from exc
        except BaseException:
            self._drop(created)
            raise
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
        return self._history[-1]

    @staticmethod
    def _grow(f: _State, ext: dict[str, Any], Vraw: np.ndarray) -> _State:
        r = ext["R_new"].shape[0]
        w, p = f.Gu.shape
        if not r:
            return dataclasses.replace(f, Vraw=Vraw)
        H = np.zeros((w + r, w + r))
        H[:w, :w] = f.H
        H[:w, w:] = ext["Hx"]
        H[w:, :w] = ext["Hx"].T
        H[w:, w:] = 0.5 * (ext["Hq"] + ext["Hq"].T)
        Gu = np.zeros((w + r, p + r))
        Gu[:w, :p] = f.Gu
        Gu[w:, p:] = np.eye(r)
        wv = f.Gv.shape[0]
        Gv = np.zeros((wv + r, p + r))
        Gv[:wv, :p] = f.Gv
        Gv[wv:, p:] = np.eye(r)
        return _State(f.panels + (ext["panel"],), f.widths + (r,), Gu, H, Vraw, Gv, f.R)

    def _extend(self, X: Any, scratch: Path, created: list[str]) -> dict[str, Any]:
        """Run passes A-D (module docstring): decompose ``X`` on the basis, write ``Q_new``."""
        import dask.array as da

        f = self._s
        b, w, n = int(X.shape[1]), f.w, self.n
        U, Wt = self._u_dask(f), self._w_dask()
        has_u, has_w = U is not None, Wt is not None
        pre_u = [U] if has_u else []
        pre = pre_u + ([Wt] if has_w else [])
        rows = self._row_chunks()
        ones = (1,) * len(rows)
        client = self.client

        def gram_sums(Y: Any, c: int) -> Any:
            parts = da.map_blocks(_k_gram, *pre, Y, has_u=has_u, has_w=has_w,
                                  dtype=np.float64, chunks=(ones, (w * c + c * c,)))
            return parts.sum(axis=0)

        # pass A: read the block once, copy it to scratch, U0^T M X exponent-aware
        Xz = self._create(scratch / "X", b, checksum=False)
        parts = da.map_blocks(_k_first, *pre, X, has_u=has_u, has_w=has_w, dtype=np.float64,
                              chunks=(ones, (1 + 3 * b + w * b,)))
        comb = partial(_combine_first, b=b)
        red = da.reduction(parts, chunk=_keep, combine=comb, aggregate=comb, axis=0,
                           keepdims=True, dtype=np.float64, concatenate=True,
                           meta=np.empty((0, 0)))
        _, packed = execute([da.store(X, Xz, lock=False, compute=False), red], client=client)
        v = np.asarray(packed).ravel()
        if v[0]:
            from .errors import NonFiniteError

            raise NonFiniteError(
                f"`columns` must be finite; got {int(v[0])} NaN or infinite entries. Remove "
                "or repair them before calling."
            )
        e = v[1 : b + 1]
        exps = np.where(e == _ZERO_EXP, 0, e).astype(np.int64)
        nu = np.sqrt(np.maximum(v[b + 1 : 2 * b + 1], 0.0))
        eu2 = np.maximum(v[2 * b + 1 : 3 * b + 1], 0.0)
        top = int(exps.max()) if b else 0
        norm = float(np.ldexp(math.sqrt(float(np.sum(np.ldexp(eu2, 2 * (exps - top))))), top))
        S1 = v[3 * b + 1 :].reshape(w, b)
        C1 = f.Gu.T @ S1
        # pass B: first projection, written to scratch, and its Gram sums
        Xd = da.from_zarr(Xz, name=f"streamsvd-scratch-X-{scratch.name}")
        Xp = da.map_blocks(_k_residual, *pre_u, Xd, has_u=has_u, exps=exps, K1=f.Gu @ C1,
                           dtype=np.float64, chunks=(rows, (b,)))
        Xpz = self._create(scratch / "Xp", b, checksum=False)
        _, sums = execute([da.store(Xp, Xpz, lock=False, compute=False), gram_sums(Xp, b)],
                          client=client)
        S2, T2 = sums[: w * b].reshape(w, b), sums[w * b :].reshape(b, b)
        C2 = f.Gu.T @ S2
        K2 = f.Gu @ C2
        Hu = f.Gu.T @ f.H @ f.Gu
        Tpp = _corrected_gram(T2, C2, Hu)
        floors = 4.0 * (b + math.sqrt(n)) * _EPS * np.maximum(np.diag(T2), 0.0)
        acc, L1, F, _ = _ordered_cholesky(Tpp, nu, self.reject_tol, floors)
        r = acc.size
        rej = np.setdiff1d(np.arange(b), acc)
        scale = np.ldexp(1.0, exps)
        # pass C: second projection on the fly; CholeskyQR of the accepted columns and the
        # residuals the rejected ones leave out, measured on the vectors. When X''[:, acc]
        # is well conditioned and no column cancelled in the second projection, one
        # CholeskyQR is accurate to O(n eps) and pass C is merged into the writing pass.
        Xpd = da.from_zarr(Xpz, name=f"streamsvd-scratch-Xp-{scratch.name}")
        size = w * r + r * r + rej.size
        L1i = _inv_t(L1)
        parts = da.map_blocks(_k_pass_c, *pre, Xpd, has_u=has_u, has_w=has_w, K2=K2, acc=acc,
                              L1i=L1i, rej=rej, F_rej=F[:, rej], dtype=np.float64,
                              chunks=(ones, (size,)))
        kept = np.diag(Tpp)[acc] >= 0.25 * np.diag(T2)[acc]
        single = bool(r) and bool(np.all(kept)) and np.linalg.cond(L1) ** 2 <= max(n, 100)
        out: dict[str, Any] = {"accepted": np.isin(np.arange(b), acc), "norm": norm}
        name = f"p{uuid.uuid4().hex}"
        if single:
            L2 = np.eye(r)
            Q = da.map_blocks(_k_q, *pre_u, Xpd, has_u=has_u, K2=K2, acc=acc, L1i=L1i, K3=None,
                              L2i=None, dtype=np.float64, chunks=(rows, (r,)))
            created.append(name)
            Qz = self._create(self._panel_dir(name), r, checksum=True)
            _, gsums, sums = execute(
                [da.store(Q, Qz, lock=False, compute=False), gram_sums(Q, r),
                 parts.sum(axis=0)], client=client)
            C3 = np.zeros((f.rank, r))
        else:
            (sums,) = execute([parts.sum(axis=0)], client=client)
        with np.errstate(over="ignore"):
            out["rejected_energy"] = float(np.sum(
                np.ldexp(np.maximum(sums[w * r + r * r :], 0.0), 2 * exps[rej])))
        if not r:
            out.update(coeffs=(C1 + C2) * scale, R_new=np.zeros((0, b)), panel=None)
            return out
        if not single:
            S3, T3 = sums[: w * r].reshape(w, r), sums[w * r : w * r + r * r].reshape(r, r)
            C3 = f.Gu.T @ S3
            L2 = _cholesky_or_eig(_corrected_gram(T3, C3, Hu))
            # pass D: CholeskyQR2's second pass, written as a new panel, and its Gram
            Q = da.map_blocks(_k_q, *pre_u, Xpd, has_u=has_u, K2=K2, acc=acc, L1i=L1i,
                              K3=f.Gu @ C3, L2i=_inv_t(L2), dtype=np.float64,
                              chunks=(rows, (r,)))
            created.append(name)
            Qz = self._create(self._panel_dir(name), r, checksum=True)
            _, gsums = execute([da.store(Q, Qz, lock=False, compute=False), gram_sums(Q, r)],
                               client=client)
        out.update(
            coeffs=(C1 + C2 + C3 @ F) * scale, R_new=(L2.T @ F) * scale, panel=name,
            Hx=gsums[: w * r].reshape(w, r), Hq=gsums[w * r :].reshape(r, r),
        )
        return out

    def _compact(self, s: _State, created: list[str]) -> _State:
        """Write ``U0 @ Gu`` as one panel (pass E) and measure its Gram."""
        import dask.array as da

        U = self._u_dask(s)
        p = s.rank
        rows = self._row_chunks()
        P = da.map_blocks(_k_apply, U, G=s.Gu, dtype=np.float64, chunks=(rows, (p,)))
        Wt = self._w_dask()
        pre = [Wt] if Wt is not None else []
        parts = da.map_blocks(_k_gram, *pre, P, has_u=False, has_w=Wt is not None,
                              dtype=np.float64, chunks=((1,) * len(rows), (p * p,)))
        name = f"p{uuid.uuid4().hex}"
        created.append(name)
        Pz = self._create(self._panel_dir(name), p, checksum=True)
        _, H = execute([da.store(P, Pz, lock=False, compute=False), parts.sum(axis=0)],
                       client=self.client)
        H = np.asarray(H).reshape(p, p)
        logger.info("compacted the basis to one panel of width %d", p)
        return _State((name,), (p,), np.eye(p), 0.5 * (H + H.T), s.Vraw, s.Gv, s.R)

    def _update(
        self,
        columns: int,
        f: _State,
        K: np.ndarray,
        ext: dict[str, Any],
        created: list[str],
        *,
        t0: float,
        source_offset: int,
        coupling_extra: float,
    ) -> None:
        """Sweeps, truncation (:func:`streamsvd._core.core_step`), compaction, the bound."""
        step = core_step(
            K, rule=self.rule, sweeps=self.sweeps, m=f.m,
            truncation=Truncation(self.eps, self.rtol, self.max_rank), kind="absorb",
        )
        new = dataclasses.replace(f, Gu=f.Gu @ step.T, Gv=f.Gv @ step.T, R=step.R)
        limit_w = self.compact_ratio * max(new.rank, 1)
        if new.w > limit_w and new.rank:
            new = self._compact(new, created)
        elif new.w > limit_w:
            new = dataclasses.replace(new, panels=(), widths=(), Gu=np.zeros((0, 0)),
                                      H=np.zeros((0, 0)))
        if new.Gv.shape[0] > limit_w:
            new = dataclasses.replace(new, Vraw=new.Vraw @ new.Gv, Gv=np.eye(new.rank))
        orth = self._orth(new)
        if orth > self.reorth_tol:
            logger.info("re-orthonormalising the basis (||U^T M U - I|| = %.2e)", orth)
            new = _reorthonormalize(new)
            orth = self._orth(new)
        discarded = math.hypot(step.cut_norm, math.sqrt(ext["rejected_energy"]))
        bound = self._bound.step(
            discarded, step.coupling_root, overlapping=False, extra_root=coupling_extra
        )
        record = UpdateRecord(
            kind="absorb", columns=columns, rank=new.rank,
            new_directions=int(np.count_nonzero(ext["accepted"])),
            rejected=int(np.count_nonzero(~ext["accepted"])), cut=step.cut,
            discarded=discarded, sweeps=step.sweeps, max_cosine=step.max_cosine,
            orthogonality=orth, error_bound=bound.bound,
            seconds=time.perf_counter() - t0,
        )
        scalars = np.concatenate([bound.to_array(), [float(source_offset)]])
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
        self._s = new
        self._bound = bound
        self.source_offset = source_offset
        created.clear()
        self._gc()

    @staticmethod
    def _orth(s: _State) -> float:
        if s.rank == 0:
            return 0.0
        G = s.Gu.T @ s.H @ s.Gu
        return float(np.linalg.norm(G - np.eye(s.rank), 2))

    # --------------------------------------------------------------- properties
    @property
    def n_seen(self) -> int:
        """Number of snapshots (columns) in the expansion."""
        return self._s.m

    @property
    def rank(self) -> int:
        """Current number of terms."""
        return self._s.rank

    @property
    def stored_width(self) -> int:
        """Number of columns of the stored factor ``U0`` (all panels)."""
        return self._s.w

    @property
    def amplitudes(self) -> np.ndarray:
        """``||v_i||``, computed on the small core, sorted."""
        return np.sort(safe_column_norms(self._s.R))[::-1]

    @property
    def discarded_energy(self) -> float:
        """Sum of the energies discarded by every update."""
        return self._bound.discarded**2

    @property
    def discarded_norm(self) -> float:
        """``sqrt(sum of the discarded energies)``."""
        return self._bound.discarded

    @property
    def error_bound(self) -> float:
        """Guaranteed bound on ``||A - U V^T||_F`` (theorem in :mod:`streamsvd.bound`)."""
        return self._bound.bound

    @property
    def history(self) -> tuple[UpdateRecord, ...]:
        """One :class:`~streamsvd.UpdateRecord` per update, oldest first."""
        return tuple(self._history)

    def orthogonality_error(self) -> float:
        """Return ``||U^T M U - I||_2`` from the small Gram matrices."""
        return self._orth(self._s)

    def _order_and_signs(self) -> tuple[np.ndarray, np.ndarray, Any]:
        """Amplitude order, sign of each sorted term, and the sorted lazy ``U``."""
        import dask.array as da

        s = self._s
        V = s.Vraw @ s.Gv
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        if not s.rank:
            return perm, np.ones(0), da.zeros((self.n, 0), chunks=(self._row_chunks(), (1,)))
        U = self._u_dask(s)
        rows = self._row_chunks()
        Ud = da.map_blocks(_k_apply, U, G=s.Gu[:, perm], dtype=np.float64,
                           chunks=(rows, (s.rank,)))
        hi, lo = execute([Ud.max(axis=0), Ud.min(axis=0)], client=self.client)
        signs = np.where(np.asarray(hi) >= -np.asarray(lo), 1.0, -1.0)
        return perm, signs, Ud * signs

    def factors(self) -> tuple[Any, np.ndarray]:
        """Return the expansion as ``(U, V)``: ``U`` lazy (dask, over the panels), ``V`` in memory.

        Terms are sorted by decreasing amplitude and signs are fixed as in
        :attr:`~streamsvd.StreamCompressor.expansion` (the largest-modulus entry of each
        ``u_i`` is positive); computing ``U`` chunk by chunk never holds ``n x p``.
        """
        perm, signs, U = self._order_and_signs()
        s = self._s
        V = (s.Vraw @ s.Gv)[:, perm] * signs
        return U, V

    @property
    def expansion(self) -> Expansion:
        """The expansion in memory (forms ``n x p``: for moderate ``n``, tests, export)."""
        s = self._s
        V = s.Vraw @ s.Gv
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U = np.zeros((self.n, 0)) if not s.rank else np.asarray(
            execute([self._u_dask(s)], client=self.client)[0]) @ s.Gu
        U, V = U[:, perm], V[:, perm]
        fix_signs(U, V)
        return Expansion(U, V, inner=self.inner)

    def __repr__(self) -> str:
        return (
            f"TallCompressor(n={self.n}, n_seen={self.n_seen}, rank={self.rank}, "
            f"panels={len(self._s.panels)}, chunk_rows={self.chunk_rows}, rule={self.rule!r}, "
            f"sweeps={self.sweeps}, eps={self.eps}, rtol={self.rtol}, max_rank={self.max_rank})"
        )


def _reorthonormalize(s: _State) -> _State:
    """``U <- U L^{-T}``, ``V <- V L`` with ``U^T M U = L L^T`` (small matrices only)."""
    G = s.Gu.T @ s.H @ s.Gu
    L = np.linalg.cholesky(0.5 * (G + G.T))
    Gu = scipy.linalg.solve_triangular(L, s.Gu.T, lower=True).T
    Vraw = s.Vraw @ (s.Gv @ L)
    return dataclasses.replace(s, Gu=Gu, Vraw=Vraw, Gv=np.eye(s.rank), R=s.R @ L)
