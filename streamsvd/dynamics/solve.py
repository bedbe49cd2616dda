"""DMD from the small pair factor: eigenpairs, amplitudes and a residual certificate.

Given the :class:`~streamsvd.dynamics.pairs.PairFactor` ``T = [T_x, T_y]`` of the pairs
(``Zx = T_x^T Q^T``, ``Zy = T_y^T Q^T``), the query costs ``O(k^3)`` and never touches an
n-sized array:

1. the SVD ``T_x^T = P S W^T`` (so ``Zx = P S (Q W)^T``), cut to ``r`` terms by ``rank``
   and ``rtol``;
2. ``B = T_y^T W S^(-1)`` (``k x r``: ``B w = Zy c`` with ``c = Q W S^(-1) w``) and the
   projected operator ``A~ = P^T B`` (``r x r``), as in Schmid's DMD of the coordinates;
3. its eigenpairs ``A~ w = mu w`` (``||w|| = 1``); the mode's coordinates on ``U`` are
   ``P w`` (``||U P w||_M = 1``);
4. the certificate (docs: theory, DMD; theorem there): with ``rho = ||B w - mu P w||``,
   ``||c|| = ||S^(-1) w||``, ``e`` the compressor's certified bound
   ``||X - U V^T||_(F,M) <= e``, ``delta`` the model error ``||A X_0 - X_1||_(F,M)`` and
   ``omega = ||U^T M U - I||_2``::

       eta = (sqrt(1 + omega) rho + ((1 + |mu|) e + delta) ||c||)
             / (sqrt(1 - omega) - e ||c||)

   (``inf`` when the denominator is not positive), so that ``||(A - mu) psi||_M <= eta
   ||psi||_M`` for the data vector ``psi = X_0 c`` and every ``A`` with ``||A X_0 -
   X_1||_(F,M) <= delta``: ``mu`` lies in the ``eta``-pseudospectrum of ``A``.

With forgetting (factor ``gamma``) the weighted pairs follow ``A / gamma``: the
eigenvalues and their bounds are multiplied by ``gamma``.
"""

from __future__ import annotations

import math

import numpy as np

from streamsvd._util.scaling import pow2_exponent
from streamsvd._util.validation import check_nonnegative, check_positive_int
from streamsvd.dynamics.pairs import PairFactor
from streamsvd.dynamics.result import DMDResult
from streamsvd.errors import InputError

__all__ = ["dmd_from_pairs"]

_EPS = float(np.finfo(np.float64).eps)


def dmd_from_pairs(
    pairs: PairFactor, *, rank: int | None = None, rtol: float | None = None,
    error_bound: float = 0.0, model_error: float = 0.0, orthogonality: float = 0.0,
    forget: float = 1.0, dt: float | None = None, basis: np.ndarray | None = None,
) -> DMDResult:
    """Return the DMD of the pairs with a residual bound per eigenvalue.

    Parameters
    ----------
    pairs : PairFactor
        The triangular factor of the snapshot pairs (:func:`~streamsvd.dynamics.pairs.
        pair_factor`).
    rank : int, optional
        Keep at most ``rank`` singular directions of the first snapshots of the pairs.
    rtol : float, optional
        Keep the directions with ``s_i > rtol * s_1``; default ``max(k, q) * eps``
        (the numerical rank).
    error_bound : float
        Certified ``||X - U V^T||_(F,M)`` of the expansion the pairs come from.
    model_error : float
        ``delta >= ||A X_0 - X_1||_(F,M)`` for the operators ``A`` the certificate is
        about (0 for exact linear data; noise must be counted here).
    orthogonality : float
        ``||U^T M U - I||_2`` of the basis.
    forget : float
        Forgetting factor ``gamma`` the snapshots were weighted by.
    dt : float, optional
        Time step, for :attr:`DMDResult.continuous_eigenvalues`.
    basis : ndarray, shape (n, k), optional
        ``U``, for :attr:`DMDResult.modes` and :meth:`DMDResult.forecast`.

    Returns
    -------
    DMDResult
        Eigenvalues, their residual bounds ``eta`` (module docstring), the modes'
        coordinates and the amplitudes at the last snapshot.
    """
    rank = check_positive_int(rank, "rank", allow_none=True)
    rtol = None if rtol is None else check_nonnegative(rtol, "rtol")
    e = check_nonnegative(error_bound, "error_bound")
    delta = check_nonnegative(model_error, "model_error")
    omega = check_nonnegative(orthogonality, "orthogonality")
    if dt is not None and not (math.isfinite(float(dt)) and float(dt) > 0):
        raise InputError(f"`dt` must be a finite number > 0 (the time step); got {dt!r}.")
    k, q = pairs.k, pairs.pairs
    if q == 0:
        raise InputError(
            f"DMD needs at least one pair of consecutive snapshots of one trajectory; got "
            f"0 pairs at rank {k}. Absorb more snapshots."
        )
    if k == 0:
        raise InputError(
            f"DMD needs a basis of rank >= 1; got {q} pairs in a basis of rank 0: the "
            f"compressor's truncation (`target_error`, `eps`, `rtol` or `max_rank`) cut "
            f"every term, or the snapshots are zero. A smaller `target_error` keeps terms."
        )
    P, S, Wt = np.linalg.svd(pairs.Tx.T, full_matrices=False)
    tol = (max(k, q) * _EPS if rtol is None else rtol) * (S[0] if S.size else 0.0)
    r = int(np.count_nonzero(S > tol))
    if rank is not None:
        r = min(r, rank)
    if r == 0:
        raise InputError(
            f"the first snapshots of the pairs are zero to `rtol`={rtol} (largest "
            f"singular value {S[0] if S.size else 0.0:.3g}); nothing to fit."
        )
    P, S, W = P[:, :r], S[:r], Wt[:r].T
    # S scaled by a power of two to [1/2, 1) at its top (exact): for data near 1e-200,
    # ||S^-1 w|| ~ 1e200 is a float64 but its square, which a norm forms, is not
    top = pow2_exponent(S)
    S_unit = np.ldexp(S, -top)
    B = np.ldexp(pairs.Ty.T @ (W / S_unit), -top)  # B w = Zy c, c = Q W S^-1 w
    A_tilde = P.T @ B
    mu, Wv = np.linalg.eig(A_tilde)
    Wv = Wv / np.linalg.norm(Wv, axis=0)
    order = np.lexsort((-mu.imag, -np.abs(mu)))
    mu, Wv = mu[order], Wv[:, order]
    with np.errstate(over="ignore"):  # beyond the range: nothing certified (eta = inf)
        c_norm = np.ldexp(np.linalg.norm(Wv / S_unit[:, None], axis=0), -top)
    rho = np.linalg.norm(B @ Wv - (P @ Wv) * mu, axis=0)
    # rounding of the O(k^3) solve (not rigorous: docs, theory, DMD)
    rho = rho + 8 * (k + r) * _EPS * (np.linalg.norm(B @ Wv, axis=0) + np.abs(mu))
    # an infinite ||c|| (0 * inf when e = 0: NaN) leaves the denominator not positive
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        denom = math.sqrt(max(1.0 - omega, 0.0)) - e * c_norm
        num = math.sqrt(1.0 + omega) * rho + ((1.0 + np.abs(mu)) * e + delta) * c_norm
        eta = np.where(denom > 0, num / np.where(denom > 0, denom, 1.0), np.inf)
    modes = P @ Wv  # coordinates on U, unit norm
    amplitudes = np.linalg.lstsq(modes, pairs.last.astype(complex), rcond=None)[0]
    return DMDResult(
        eigenvalues=forget * mu, residual_bounds=forget * eta, amplitudes=amplitudes,
        mode_coordinates=modes, singular_values=S, pairs=q, error_bound=e,
        model_error=delta, orthogonality=omega, forget=forget, dt=dt, basis=basis,
        start=pairs.last.copy(),
    )
