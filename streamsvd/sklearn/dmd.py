"""A scikit-learn style estimator of certified streaming DMD: :class:`StreamingDMD`.

scikit-learn's ``X`` has one sample per row; here a sample is a snapshot and the rows are
consecutive in time, so ``partial_fit(X)`` absorbs ``X.T`` into a
``StreamCompressor(dynamics=True)`` and continues the trajectory (``new_trajectory=True``
starts another). ``fit`` starts over. The learned attributes (ending in ``_``) are read
from the compressor's :meth:`~streamsvd.StreamCompressor.dmd` after each call.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from streamsvd.dynamics import DMDResult
from streamsvd.errors import FloatRangeError, InputError
from streamsvd.sklearn._model import NotFittedError
from streamsvd.stream.compressor import StreamCompressor

__all__ = ["StreamingDMD"]


class StreamingDMD:
    """Dynamic mode decomposition fitted incrementally, each eigenvalue certified.

    Parameters
    ----------
    rank : int, optional
        Eigenvalues kept by the query (``StreamCompressor.dmd(rank=)``).
    rtol : float, optional
        Relative cut of the query (default: the numerical rank).
    model_error : float
        ``delta`` of the certificate (docs: theory, DMD); measurement noise belongs here.
    dt : float, optional
        Time step between samples (for ``continuous_eigenvalues_``).
    max_rank, eps, window, forget, inner
        Options of the underlying :class:`~streamsvd.StreamCompressor`.

    Attributes
    ----------
    eigenvalues_, residual_bounds_, amplitudes_ : ndarray
        As in :class:`~streamsvd.dynamics.result.DMDResult`.
    modes_ : ndarray, shape (r, n_features)
        The DMD modes, one per row (the transpose of ``DMDResult.modes``).
    n_features_in_, n_samples_seen_ : int
        Features per sample; samples in the current expansion.
    result_ : DMDResult
        The full result of the last query.
    """

    def __init__(self, *, rank: int | None = None, rtol: float | None = None,
                 model_error: float = 0.0, dt: float | None = None,
                 max_rank: int | None = None, eps: float = 0.0, window: int | None = None,
                 forget: float = 1.0, inner: Any = None) -> None:
        self.rank = rank
        self.rtol = rtol
        self.model_error = model_error
        self.dt = dt
        self.max_rank = max_rank
        self.eps = eps
        self.window = window
        self.forget = forget
        self.inner = inner

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """Return the parameters (scikit-learn's convention)."""
        names = ("rank", "rtol", "model_error", "dt", "max_rank", "eps", "window", "forget",
                 "inner")
        return {name: getattr(self, name) for name in names}

    def set_params(self, **params: Any) -> StreamingDMD:
        """Set parameters (scikit-learn's convention); unknown names are refused."""
        known = self.get_params()
        for name, value in params.items():
            if name not in known:
                raise InputError(f"unknown parameter `{name}`; the parameters are "
                                 f"{', '.join(known)}.")
            setattr(self, name, value)
        return self

    def fit(self, X: Any, y: Any = None) -> StreamingDMD:
        """Fit on the samples of ``X`` (rows, consecutive in time), starting over."""
        for name in ("compressor_", "result_"):
            self.__dict__.pop(name, None)
        return self.partial_fit(X)

    def partial_fit(self, X: Any, y: Any = None, *, new_trajectory: bool = False
                    ) -> StreamingDMD:
        """Absorb the samples of ``X`` (rows), continuing the trajectory or starting one."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim != 2 or X.shape[0] < 1:
            raise InputError(
                f"`X` must be a 2-D array of samples (rows) x features; got shape "
                f"{X.shape}."
            )
        sc = getattr(self, "compressor_", None)
        if sc is None:
            sc = StreamCompressor(
                X.shape[1], inner=self.inner, dynamics=True, max_rank=self.max_rank,
                eps=self.eps, window=self.window, forget=self.forget,
            )
            self.compressor_ = sc
        elif X.shape[1] != sc.n:
            raise InputError(
                f"`X` must have {sc.n} features (columns), as the samples fitted so far; "
                f"got {X.shape[1]}."
            )
        try:
            sc.absorb(X.T, new_trajectory=new_trajectory)
        except FloatRangeError as exc:
            raise exc.naming("`X`") from exc
        if sc.n_seen >= 2:
            res = sc.dmd(rank=self.rank, rtol=self.rtol, model_error=self.model_error,
                         dt=self.dt)
            self._learn(res)
        self.n_features_in_, self.n_samples_seen_ = sc.n, sc.n_seen
        return self

    def _learn(self, res: DMDResult) -> None:
        self.result_ = res
        self.eigenvalues_ = res.eigenvalues
        self.residual_bounds_ = res.residual_bounds
        self.amplitudes_ = res.amplitudes
        self.modes_ = res.modes.T
        if res.dt is not None:
            self.continuous_eigenvalues_ = res.continuous_eigenvalues

    def _fitted(self) -> DMDResult:
        res = getattr(self, "result_", None)
        if res is None:
            raise NotFittedError(
                "this StreamingDMD is not fitted yet (it needs two samples or more); "
                "call `fit` or `partial_fit` first."
            )
        return res

    def predict(self, n_steps: int) -> np.ndarray:
        """Return the ``n_steps`` samples after the last one fitted (rows)."""
        if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer) \
                or n_steps < 1:
            raise InputError(f"`n_steps` must be an integer >= 1; got {n_steps!r}.")
        return self._fitted().forecast(np.arange(1, int(n_steps) + 1)).T
