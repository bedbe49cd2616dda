"""The frozen result of a DMD query: eigenvalues, residual bounds, modes, forecasts."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streamsvd.errors import InputError

__all__ = ["DMDResult"]


@dataclass(frozen=True, eq=False)
class DMDResult:
    """A DMD of a stream with a residual certificate per eigenvalue.

    Attributes
    ----------
    eigenvalues : ndarray of complex, shape (r,)
        Discrete-time eigenvalues ``lambda_i`` (sorted by decreasing modulus).
    residual_bounds : ndarray, shape (r,)
        ``eta_i``: ``lambda_i`` lies in the ``eta_i``-pseudospectrum (in the norm of
        ``M``) of every operator ``A`` with ``||A X_0 - X_1||_(F,M) <= model_error``;
        for such an ``A`` that is normal, an eigenvalue of ``A`` lies within ``eta_i``
        of ``lambda_i`` (docs: theory, DMD). ``inf``: nothing certified.
    amplitudes : ndarray of complex, shape (r,)
        ``b``: the last snapshot's coordinates ``z_m ~ Psi b`` on the modes.
    mode_coordinates : ndarray of complex, shape (k, r)
        ``Psi``: the modes' coordinates on ``U`` (unit norm, so ``||U Psi_i||_M = 1``).
    singular_values : ndarray, shape (r,)
        Singular values of the first snapshots of the pairs, kept by the query's cut.
    pairs : int
        Number of snapshot pairs fitted.
    error_bound, model_error, orthogonality : float
        The certified bound of the expansion, the model error ``delta`` and
        ``||U^T M U - I||_2`` the certificate used.
    forget : float
        Forgetting factor of the stream (the eigenvalues are rescaled by it).
    dt : float or None
        Time step between snapshots.
    basis : ndarray, shape (n, k), or None
        ``U``, when the query formed it (for :attr:`modes` and :meth:`forecast`).
    start : ndarray, shape (k,)
        The last snapshot's coordinates on ``U`` (the forecast's start).
    """

    eigenvalues: np.ndarray
    residual_bounds: np.ndarray
    amplitudes: np.ndarray
    mode_coordinates: np.ndarray
    singular_values: np.ndarray
    pairs: int
    error_bound: float
    model_error: float
    orthogonality: float
    forget: float
    dt: float | None
    basis: np.ndarray | None = field(default=None, repr=False)
    start: np.ndarray | None = field(default=None, repr=False)

    @property
    def rank(self) -> int:
        """Number ``r`` of eigenvalues."""
        return int(self.eigenvalues.shape[0])

    @property
    def continuous_eigenvalues(self) -> np.ndarray:
        """``log(lambda_i) / dt`` (growth rate + i angular frequency); needs ``dt``."""
        if self.dt is None:
            raise InputError(
                "`continuous_eigenvalues` needs the time step; pass `dt` to the DMD query."
            )
        with np.errstate(divide="ignore"):
            return np.log(self.eigenvalues.astype(complex)) / self.dt

    @property
    def modes(self) -> np.ndarray:
        """The DMD modes ``U Psi`` (``n x r``, unit norm in ``M``); needs the basis."""
        return self._basis() @ self.mode_coordinates

    def _basis(self) -> np.ndarray:
        if self.basis is None:
            raise InputError(
                "this DMDResult holds no basis `U`; query it with `modes=True` to form "
                "the modes and forecasts in the snapshots' space."
            )
        return self.basis

    def forecast_coordinates(self, steps: Any) -> np.ndarray:
        """Return the coordinates on ``U`` of ``Psi diag(lambda^s) b`` for each ``s`` in ``steps``.

        ``s = 0`` is the last snapshot (projected on the modes); ``steps`` are integers
        (or reals, with ``lambda^s`` on the principal branch). Shape ``(k, len(steps))``.
        """
        s = np.atleast_1d(np.asarray(steps, dtype=np.float64))
        with np.errstate(divide="ignore", invalid="ignore"):
            powers = self.eigenvalues.astype(complex)[:, None] ** s[None, :]
        Z = self.mode_coordinates @ (self.amplitudes[:, None] * powers)
        return np.asarray(Z.real)

    def forecast(self, steps: Any) -> np.ndarray:
        """Return the forecast snapshots ``U Psi diag(lambda^s) b`` (``n x len(steps)``).

        ``steps`` counts time steps after the last snapshot absorbed (0: that snapshot,
        as the modes represent it). Costs ``O(n k len(steps))``; needs the basis.
        """
        return self._basis() @ self.forecast_coordinates(steps)

    def to_dict(self) -> dict[str, Any]:
        """Return the result as JSON-able values (complex numbers as ``[re, im]``)."""

        def cplx(a: np.ndarray) -> list[list[float]]:
            return [[float(z.real), float(z.imag)] for z in np.asarray(a, dtype=complex)]

        out: dict[str, Any] = {
            "rank": self.rank, "pairs": self.pairs, "eigenvalues": cplx(self.eigenvalues),
            "residual_bounds": [float(x) for x in self.residual_bounds],
            "amplitudes": cplx(self.amplitudes),
            "singular_values": [float(x) for x in self.singular_values],
            "error_bound": self.error_bound, "model_error": self.model_error,
            "orthogonality": self.orthogonality, "forget": self.forget, "dt": self.dt,
        }
        if self.dt is not None:
            out["continuous_eigenvalues"] = cplx(self.continuous_eigenvalues)
        return out
