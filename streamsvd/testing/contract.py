"""The SVD contract every backend must meet, measured with LAPACK's test ratios."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from streamsvd.linalg.expansion import Expansion

__all__ = ["SVDRatios", "assert_svd_contract", "svd_ratios"]

_EPS = np.finfo(np.float64).eps


@dataclass(frozen=True)
class SVDRatios:
    """LAPACK-style test ratios of an expansion against a reference matrix.

    Attributes
    ----------
    residual : float
        ``||A - U V^T||_F / (max(||A||_F, tiny) * max(n, m) * eps)``.
    orthogonality_u : float
        ``||U^T M U - I||_2 / (n * eps)``.
    orthogonality_v : float
        ``||Vn^T Vn - I||_2 / (m * eps)`` with ``Vn`` the columns of ``V`` of amplitude above
        ``max(n, m) * eps * sigma_1``, normalised (LAPACK's ratio, relative accuracy of
        every right vector).
    coupling : float
        ``||V^T V - diag(||v_i||^2)||_2 / (max(n, m) * eps * sigma_1^2)``: ``W`` of eq. (15)
        diagonal to working accuracy. Since ``V`` carries the amplitudes, this absolute
        measure is what a backward-stable update can guarantee for terms of amplitude near
        ``eps * sigma_1``, whose normalised right vectors are not determined by the data.
    singular_values : float
        ``max_i |s_i - sigma_i| / (max(n, m) * eps * sigma_1)`` against ``scipy.linalg.svdvals``.
    sorted : bool
        Whether the amplitudes are non-increasing.
    """

    residual: float
    orthogonality_u: float
    orthogonality_v: float
    coupling: float
    singular_values: float
    sorted: bool


def svd_ratios(A: np.ndarray, expansion: Expansion) -> SVDRatios:
    """Return the test ratios of ``expansion`` as an SVD of ``A`` (see :class:`SVDRatios`)."""
    A = np.asarray(A, dtype=np.float64)
    n, m = A.shape
    big = max(n, m, 1)
    scale = 2.0 ** -np.frexp(max(float(np.max(np.abs(A))) if A.size else 0.0, 1e-300))[1]
    As = A * scale
    Us, Vs = expansion.U, expansion.V * scale
    normA = float(np.linalg.norm(As)) if A.size else 0.0
    resid = float(np.linalg.norm(As - Us @ Vs.T)) if A.size else 0.0
    residual = resid / (max(normA, np.finfo(float).tiny) * big * _EPS)
    orth_u = expansion.orthogonality_error() / (max(n, 1) * _EPS)
    amps = expansion.amplitudes * scale
    sref = scipy.linalg.svdvals(As) if A.size else np.zeros(0)
    s1 = float(sref[0]) if sref.size else 0.0
    live = amps > big * _EPS * s1
    if np.count_nonzero(live) > 1:
        Vn = Vs[:, live] / amps[live]
        orth_v = float(np.linalg.norm(Vn.T @ Vn - np.eye(Vn.shape[1]), 2)) / (max(m, 1) * _EPS)
    else:
        orth_v = 0.0
    W = Vs.T @ Vs
    W_off = W - np.diag(np.diag(W))
    coupling = (
        float(np.linalg.norm(W_off, 2)) / (big * _EPS * s1 * s1) if (W.size and s1 > 0) else 0.0
    )
    s_cmp = np.zeros(max(len(amps), len(sref)))
    r_cmp = np.zeros_like(s_cmp)
    s_cmp[: len(amps)] = amps
    r_cmp[: len(sref)] = sref
    denom = big * _EPS * s1
    sv = float(np.max(np.abs(s_cmp - r_cmp))) / denom if (s_cmp.size and denom > 0) else 0.0
    return SVDRatios(residual, orth_u, orth_v, coupling, sv, bool(np.all(np.diff(amps) <= 0)))


def assert_svd_contract(
    A: np.ndarray,
    expansion: Expansion,
    *,
    threshold: float = 50.0,
    error_bound: float | None = None,
    relative_v: bool = True,
) -> SVDRatios:
    """Assert that ``expansion`` is an SVD of ``A`` to LAPACK's test accuracy.

    Checks shapes, sorted amplitudes, and that each ratio of :func:`svd_ratios` is below
    ``threshold``. When ``error_bound`` is given, also checks the truncation contract
    ``||A - U V^T||_F <= error_bound + threshold * max(n, m) * eps * ||A||_F`` in place of
    the residual ratio. With ``relative_v=False`` the right vectors are checked by the
    absolute ``coupling`` ratio instead of LAPACK's relative ``orthogonality_v``.
    """
    A = np.asarray(A, dtype=np.float64)
    assert expansion.U.shape[0] == A.shape[0], (expansion.U.shape, A.shape)
    assert expansion.V.shape[0] == A.shape[1], (expansion.V.shape, A.shape)
    r = svd_ratios(A, expansion)
    assert r.sorted, f"amplitudes not sorted: {expansion.amplitudes}"
    assert r.orthogonality_u < threshold, f"||U^T M U - I|| / (n eps) = {r.orthogonality_u:.1f}"
    if error_bound is None:
        assert r.residual < threshold, f"||A - U V^T|| / (||A|| n eps) = {r.residual:.1f}"
        if relative_v:
            assert r.orthogonality_v < threshold, (
                f"||Vn^T Vn - I|| / (m eps) = {r.orthogonality_v:.1f}"
            )
        assert r.coupling < threshold, f"||offdiag(V^T V)|| / (n eps s1^2) = {r.coupling:.1f}"
        assert r.singular_values < threshold, f"|s - sigma| / (n eps s1) = {r.singular_values:.1f}"
    else:
        err = float(np.linalg.norm(A - expansion.to_dense()))
        slack = threshold * max(A.shape) * _EPS * float(np.linalg.norm(A))
        assert err <= error_bound + slack, f"error {err:.3e} > bound {error_bound:.3e}"
    return r
