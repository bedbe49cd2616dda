"""The compiled kernels of the rotation sweeps (:mod:`streamsvd.linalg.rotations`), by numba.

Kept apart so that importing the package does not import numba (a third of a second):
the first sweep imports this module, or
:func:`streamsvd.linalg.rotations.load_kernels_in_background`
does it in a thread while a driver reads its first blocks.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["insertion_sort", "rotation_tangent", "sweep_rows"]


@numba.njit(cache=True, inline="always")
def rotation_tangent(wjj: float, wii: float, wij: float, jacobi: bool) -> float:
    """Return ``tan(theta)`` of the rotation of a pair with Gram entries ``wjj >= wii, wij``.

    ``"paper"``: ``t = alpha = wij / wjj`` (eq. 5). ``"jacobi"``: the root of smaller modulus
    of ``t^2 - 2 zeta t - 1 = 0`` with ``zeta = (wii - wjj) / (2 wij)``, which makes the
    rotated coupling ``wij (1 - t^2) + t (wii - wjj)`` vanish.
    """
    if not jacobi:
        return wij / wjj
    zeta = (wii - wjj) / (2.0 * wij)
    az = abs(zeta)
    if az > 1.0:
        root = az * math.sqrt(1.0 + (1.0 / az) * (1.0 / az))
    else:
        root = math.sqrt(1.0 + az * az)
    t = 1.0 / (az + root)
    return t if zeta <= 0.0 else -t



@numba.njit(cache=True)
def insertion_sort(order: np.ndarray, q: int, nrm2: np.ndarray) -> None:
    """Sort ``order[:q]`` by decreasing ``nrm2``, stably, in place.

    Nearly sorted after each pass of a sweep, so ``O(q)``.
    """
    for a in range(1, q):
        key = order[a]
        val = nrm2[key]
        b = a - 1
        while b >= 0 and nrm2[order[b]] < val:
            order[b + 1] = order[b]
            b -= 1
        order[b + 1] = key


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
def sweep_rows(
    Rt: np.ndarray,
    Qt: np.ndarray,
    order: np.ndarray,
    q: int,
    nrm2: np.ndarray,
    jacobi: bool,
    eps2: float,
    tol: float,
    out: np.ndarray,
) -> int:
    """Run one sweep of Algorithm 3 on the rows of ``Rt`` and ``Qt``; return the terms left.

    ``Rt`` holds one row per term (the core vector ``r_i``), ``Qt`` the accumulated
    rotation of each term; ``order[:q]`` maps positions to rows.
    """
    k = Rt.shape[1]
    pq = Qt.shape[1]
    sum_a2 = 0.0
    n_alpha = 0
    max_cos = 0.0
    n_rot = 0
    cut = 0.0
    i = q - 1
    while i >= 1:
        insertion_sort(order, q, nrm2)
        while q > 0 and nrm2[order[q - 1]] < eps2:
            cut += nrm2[order[q - 1]]
            q -= 1
        if i > q - 1:
            i = q - 1
        if i < 1:
            break
        b = order[i]
        for j in range(i):
            a = order[j]
            wjj = nrm2[a]
            wii = nrm2[b]
            if wjj == 0.0:
                continue
            wij = 0.0
            for c in range(k):
                wij += Rt[a, c] * Rt[b, c]
            alpha = wij / wjj
            sum_a2 += alpha * alpha
            n_alpha += 1
            if wii == 0.0:
                continue
            cosine = abs(wij) / (math.sqrt(wjj) * math.sqrt(wii))
            if cosine > max_cos:
                max_cos = cosine
            if cosine <= tol:
                continue
            t = rotation_tangent(wjj, wii, wij, jacobi)
            cs = 1.0 / math.sqrt(1.0 + t * t)
            sn = cs * t
            na = 0.0
            nb = 0.0
            for c in range(k):
                ra = Rt[a, c]
                rb = Rt[b, c]
                xa = cs * ra + sn * rb
                xb = cs * rb - sn * ra
                Rt[a, c] = xa
                Rt[b, c] = xb
                na += xa * xa
                nb += xb * xb
            for c in range(pq):
                qa = Qt[a, c]
                qb = Qt[b, c]
                Qt[a, c] = cs * qa + sn * qb
                Qt[b, c] = cs * qb - sn * qa
            nrm2[a] = na
            nrm2[b] = nb
            n_rot += 1
        i -= 1
    insertion_sort(order, q, nrm2)
    while q > 0 and nrm2[order[q - 1]] < eps2:
        cut += nrm2[order[q - 1]]
        q -= 1
    out[0] = math.sqrt(sum_a2 / n_alpha) if n_alpha else 0.0
    out[1] = max_cos
    out[2] = n_rot
    out[3] = cut
    return q
