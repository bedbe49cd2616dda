"""The estimator's checks: its options validated, its batches, its first compressor.

:func:`_validate_options` turns the options of a
:class:`~streamsvd.sklearn.estimator.StreamingSVD` into an :class:`_Options`, and
:func:`_check_unchanged` refuses a change of one that the fitted state was built with
(:data:`_STATEFUL`); :func:`_new_compressor` builds the compressor of a first batch;
:class:`_SparseSamples` and :class:`_Batches` are what the ingest driver reads and feeds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from streamsvd._util.validation import (
    check_choice,
    check_forget,
    check_nonnegative,
    check_positive_int,
)
from streamsvd.algebra.inner import InnerProduct, as_inner
from streamsvd.errors import InputError
from streamsvd.linalg.rotations import RULES
from streamsvd.sklearn._model import check_bool
from streamsvd.stream.compressor import StreamCompressor

if TYPE_CHECKING:
    from streamsvd.sklearn.estimator import StreamingSVD

__all__: list[str] = []

# learned state, removed by ``fit`` before it starts again
_LEARNED = (
    "compressor_", "n_samples_seen_", "n_features_in_", "mean_", "var_", "components_",
    "singular_values_", "explained_variance_", "explained_variance_ratio_",
    "noise_variance_", "n_components_", "error_bound_", "batch_size_",
    "_options", "_inner_arg", "_inner", "_energy", "_mu", "_m2", "_projection",
)
# options the compressor's state is built with: changing one between two ``partial_fit``
# calls is refused (as ``IncrementalPCA`` refuses a change of ``n_components``)
_STATEFUL = ("n_components", "tol", "center", "rule", "sweeps", "window", "forget")


@dataclass(frozen=True)
class _Options:
    """The estimator's options, validated and normalised (see ``_validate_options``)."""

    n_components: int | float | None
    tol: float | None
    center: bool
    whiten: bool
    batch_size: int | None
    rule: str
    sweeps: int | None
    window: int | None
    forget: float

    @property
    def max_rank(self) -> int | None:
        """The compressor's rank cap: ``n_components`` when it is an int."""
        return self.n_components if isinstance(self.n_components, int) else None


def _validate_options(est: StreamingSVD, n_features: int) -> _Options:
    """Validate every option of ``est`` for data with ``n_features`` features."""
    k = est.n_components
    if isinstance(k, bool) or not (
        k is None
        or (isinstance(k, int | np.integer) and k >= 1)
        or (isinstance(k, float) and 0.0 < k < 1.0)
    ):
        raise InputError(
            f"`n_components` must be None, an int >= 1 or a float in (0, 1); got {k!r}."
        )
    if isinstance(k, int | np.integer):
        k = int(k)
        if k > n_features:
            raise InputError(
                f"`n_components` must be <= n_features = {n_features}: n_components={k} "
                f"invalid for n_features={n_features}, need more rows than columns for "
                f"StreamingSVD processing. Pass `n_components` <= {n_features} or None."
            )
    return _Options(
        n_components=k,
        tol=None if est.tol is None else check_nonnegative(est.tol, "tol"),
        center=check_bool(est.center, "center"),
        whiten=check_bool(est.whiten, "whiten"),
        batch_size=check_positive_int(est.batch_size, "batch_size", allow_none=True),
        rule=check_choice(est.rule, "rule", RULES),
        sweeps=check_positive_int(est.sweeps, "sweeps", allow_none=True),
        window=check_positive_int(est.window, "window", allow_none=True),
        forget=check_forget(est.forget),
    )


class _SparseSamples:
    """A sparse ``X`` seen as the matrix of its samples as columns, densified by block."""

    def __init__(self, X: Any) -> None:
        self._X = X.tocsr()
        self.shape = (X.shape[1], X.shape[0])
        self.dtype = np.dtype(np.float64)
        self.chunks = (X.shape[1], 1)  # one read takes every row (feature)

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        features, samples = key
        return np.asarray(self._X[samples].toarray(), dtype=np.float64)[:, features].T


class _Batches:
    """A fitting estimator as the ingest driver sees it: a block of columns is a batch."""

    def __init__(self, est: StreamingSVD, opts: _Options) -> None:
        self._est, self._opts = est, opts
        self.source_offset = 0

    def absorb(self, X: np.ndarray, *, source_offset: int) -> Any:
        """Absorb the samples ``X.T`` (a view: the block is column-major)."""
        self._est._absorb(X.T, self._opts)
        self.source_offset = source_offset
        return self._est.compressor_.history[-1]


def _new_compressor(opts: _Options, *, n_features: int, inner: InnerProduct,
                    n_samples: int) -> StreamCompressor:
    """Return the compressor of a first batch of ``n_samples`` samples (no right vectors)."""
    if opts.max_rank is not None and opts.max_rank > n_samples:
        raise InputError(
            "`n_components` must be at most the number of samples of the first "
            f"batch (n_components={opts.max_rank} must be less or equal to the "
            f"batch number of samples {n_samples} for the first partial_fit call); got "
            f"n_samples={n_samples}. Pass at least {opts.max_rank} samples first, or a "
            "smaller `n_components`."
        )
    return StreamCompressor(
        n_features, inner=inner, rtol=opts.tol, max_rank=opts.max_rank,
        oversampling=0, rule=opts.rule, sweeps=opts.sweeps, right_vectors=False,
    )


def _check_unchanged(est: StreamingSVD, opts: _Options) -> None:
    """Refuse a change of an option the state was built with (see the class notes)."""
    for name in _STATEFUL:
        old, new = getattr(est._options, name), getattr(opts, name)
        if old != new:
            raise InputError(
                f"`{name}` must stay {old!r} between calls to partial_fit (the fitted "
                f"state was built with it); got {new!r}. Set it back, or call `fit` to "
                "start again with the new value."
            )
    if est.inner is not est._inner_arg:
        new_inner = as_inner(est.inner, est.n_features_in_)
        if new_inner.fingerprint != est._inner.fingerprint:
            raise InputError(
                f"`inner` must stay {est._inner!r} between calls to partial_fit (the "
                f"fitted state was built with it); got {new_inner!r}. Set it back, or "
                "call `fit` to start again with the new value."
            )
