r"""The LATIN local stage: the explicit solution of the Signorini-Coulomb laws.

Given a state ``s = (w, lam)`` of the global stage (contact displacements and tractions,
``2 nc x m`` arrays, normal rows first), the local stage finds ``s_hat = (w_hat,
lam_hat)`` satisfying the contact laws of :mod:`contact.problem` at every node and instant,
on the ascent search direction

.. math:: \hat\lambda - \lambda = k\,(\hat w - w) \qquad (E^+).

With ``c = lam - k w`` the solution is explicit:

* normal (contact or separation):
  ``lam_hat_N = min(0, c_N + k g)``, ``w_hat_N = (lam_hat_N - c_N) / k``;
* tangential, instant after instant from ``w_hat_T(t_{-1}) = 0`` (stick or slip, a radial
  return on the slip history): the stick trial ``tau = c_T + k w_hat_T(t_{k-1})``; if
  ``|tau| <= -mu lam_hat_N``, stick (``lam_hat_T = tau``, ``w_hat_T`` unchanged); otherwise
  slip with ``lam_hat_T = -mu lam_hat_N sign(tau)`` and ``w_hat_T = (lam_hat_T - c_T) / k``,
  so that the slip increment is opposite to ``lam_hat_T``.

The normal part is vectorised with numpy over nodes and instants; the tangential part,
sequential in time, runs in a numba kernel.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["local_stage"]


@numba.njit(cache=True)
def _friction(cT: np.ndarray, lamN: np.ndarray, k: float, mu: float,
              wT: np.ndarray, lamT: np.ndarray) -> None:  # pragma: no cover - compiled
    nc, m = cT.shape
    for i in range(nc):
        prev = 0.0
        for j in range(m):
            tau = cT[i, j] + k * prev
            bound = -mu * lamN[i, j]
            if abs(tau) <= bound:
                lamT[i, j] = tau
                wT[i, j] = prev
            else:
                lt = bound if tau > 0.0 else -bound
                lamT[i, j] = lt
                wT[i, j] = (lt - cT[i, j]) / k
            prev = wT[i, j]


def local_stage(
    w: np.ndarray,
    lam: np.ndarray,
    *,
    k: float,
    gaps: np.ndarray,
    mu: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(w_hat, lam_hat)``, the local-stage solution from ``(w, lam)``.

    Parameters
    ----------
    w, lam : ndarray, shape (2 nc, m)
        Contact displacements and tractions of the global stage (normal rows first).
    k : float
        Search direction (positive), in traction per length.
    gaps : ndarray, shape (nc,)
        Initial normal gaps.
    mu : float
        Coulomb coefficient.

    Returns
    -------
    w_hat, lam_hat : ndarray, shape (2 nc, m)
        They satisfy Signorini and the implicit Coulomb law exactly (up to rounding) and
        ``lam_hat - lam = k (w_hat - w)``.
    """
    nc = gaps.shape[0]
    c = lam - k * w
    w_hat = np.empty_like(w)
    lam_hat = np.empty_like(lam)
    lamN = np.minimum(0.0, c[:nc] + k * gaps[:, None])
    lam_hat[:nc] = lamN
    w_hat[:nc] = (lamN - c[:nc]) / k
    # in contact, return the gap itself rather than a rounded copy of it
    w_hat[:nc] = np.where(lamN < 0.0, np.broadcast_to(gaps[:, None], lamN.shape), w_hat[:nc])
    _friction(np.ascontiguousarray(c[nc:]), np.ascontiguousarray(lamN), float(k), float(mu),
              w_hat[nc:], lam_hat[nc:])
    return w_hat, lam_hat
