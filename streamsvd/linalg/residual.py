"""A block's residual made orthonormal: step 2 of :func:`~streamsvd.linalg.extend.extend_basis`.

:func:`orthonormalize_residual` takes CholeskyQR in place when the residual's Gram is well
conditioned, else the rounds of :func:`~streamsvd.linalg.blocks.orthonormalize_in_rounds`
(on the kept combinations, when the weakest directions were set aside first), and
returns a :class:`ResidualDirections`; :func:`write_directions` writes the rounds'
directions, made orthonormal as a whole, to the front of the basis's workspace.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from streamsvd.algebra.blas import apply_into as m_apply_into
from streamsvd.algebra.blas import gram
from streamsvd.algebra.inner import InnerProduct
from streamsvd.algebra.interface import BasisProducts
from streamsvd.linalg.blocks import (
    COND_SPLIT,
    ONE_PASS_COND,
    cholesky_qr_in_place,
    eigh_desc,
    orthonormalize_in_rounds,
    right_solve,
)

__all__ = ["ResidualDirections", "orthonormalize_residual", "write_directions"]

_EPS = np.finfo(np.float64).eps


@dataclass(frozen=True)
class ResidualDirections:
    """The residual made orthonormal (step 2 of :func:`~streamsvd.linalg.extend.extend_basis`).

    ``Z Fz = [parts] Rz`` for the map ``Fz`` the residual went through (the identity, or
    the kept combinations of a split); ``mparts`` the parts' ``M`` images when the rounds
    measured them; ``rejected`` the ``(map, Gram)`` of every direction set aside, in
    order; ``cross`` the cross block ``(M Q)^T Q_z`` when CholeskyQR made ``Z`` itself
    orthonormal in place (None after the rounds); ``passes`` the products with the basis.
    """

    parts: list[np.ndarray]
    mparts: list[np.ndarray]
    Rz: np.ndarray
    rejected: list[tuple[np.ndarray, np.ndarray]]
    cross: np.ndarray | None
    passes: int


def orthonormalize_residual(
    basis: BasisProducts, G: np.ndarray | None, Z: np.ndarray, MZ: np.ndarray,
    S: np.ndarray, cross: np.ndarray, C: np.ndarray, *, split: tuple[np.ndarray, ...] | None,
    kept: np.ndarray | None, spectrum: tuple[np.ndarray, np.ndarray] | None, budget: float,
    inner: InnerProduct, reject_tol: float, ref: np.ndarray,
) -> ResidualDirections:
    """Orthonormalise the residual ``Z`` (step 2 of :func:`~streamsvd.linalg.extend.extend_basis`).

    With a split, the kept combinations ``Z W_k`` go through the rounds (the tail is never
    formed): on ``Z`` itself, whose first round forms only what it resolves, unless
    ``kept = Z W_k`` was formed already. Otherwise the eigenvalues of ``S`` decide:
    CholeskyQR in place when they lie within ``COND_SPLIT`` of the largest (the common
    case, ``Rz = L^T`` triangular), else the rounds.
    """
    b = Z.shape[1]
    if split is not None:
        Wk, lam_k, Wt, Gt = split
        if kept is None:
            target, F0, spec = Z, None, (lam_k, Wk)
        else:
            target, F0, spec = kept, Wk.T, (lam_k, np.eye(lam_k.size))
        parts, Rz, floor, passes, mparts, apart = orthonormalize_in_rounds(
            basis, G, target, spec, C, inner, reject_tol, ref, F0=F0,
            aside=budget - float(np.trace(Gt)))
        return ResidualDirections(parts, mparts, Rz, [(Wt.T, Gt), *apart, *_measured(floor)],
                                  None, passes)
    if b == 0:
        lam = np.zeros(0)
    else:  # the eigenvalues decide between CholeskyQR and the rounds
        lam = np.linalg.eigvalsh(S)[::-1] if spectrum is None else spectrum[0]
    if b > 0 and lam[-1] > 0 and lam[-1] >= COND_SPLIT * lam[0]:
        Rz, cross_z, passes = cholesky_qr_in_place(basis, Z, MZ, S, lam, cross, inner)
        return ResidualDirections([Z], [], Rz, [], cross_z, passes)
    parts, Rz, floor, passes, mparts, apart = orthonormalize_in_rounds(
        basis, G, Z, eigh_desc(S) if spectrum is None else spectrum, C, inner,
        reject_tol, ref, aside=budget)
    return ResidualDirections(parts, mparts, Rz, [*apart, *_measured(floor)], None, passes)


def _measured(floor: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Return the ``(map, Gram)`` of the directions set aside below the floor: ``(T, M T, F)``."""
    out = []
    for T, MT, F in floor:
        Gt = T.T @ MT
        out.append((F, 0.5 * (Gt + Gt.T)))
    return out


def write_directions(
    found: ResidualDirections, keep: np.ndarray | None, R_new: np.ndarray, Y: np.ndarray,
    MY: np.ndarray, inner: InnerProduct,
) -> tuple[np.ndarray, np.ndarray]:
    """Write the rounds' directions (``Q_z``, or ``Q_z W_acc``) to the front of the workspace.

    The rounds' directions are orthonormal to a few ``eps`` each; when their Gram shows
    more, one CholeskyQR pass over all of them makes the block orthonormal as a whole
    (``R_new`` updated). Returns ``R_new`` and the directions' Gram.
    """
    r = R_new.shape[0]
    Qn = Y[:, :r]
    start = 0
    for i, part in enumerate(found.parts):
        width = part.shape[1]
        if keep is None:
            Qn[:, start : start + width] = part
        elif i == 0:
            np.matmul(part, keep[:width], out=Qn)
        else:
            Qn += part @ keep[start : start + width]
        start += width
    if inner.is_euclidean:
        pass
    elif keep is None and len(found.parts) == 1:
        MY[:, :r] = found.mparts[0]  # the part's image, measured by the rounds
    else:
        m_apply_into(inner, Qn, MY[:, :r])
    gram_new = gram(Qn, inner, None if inner.is_euclidean else MY[:, :r])
    if r and np.max(np.abs(gram_new - np.eye(r))) > ONE_PASS_COND * r * _EPS:
        L = np.linalg.cholesky(gram_new)
        right_solve(Qn, L)
        R_new = L.T @ R_new
        if not inner.is_euclidean:
            m_apply_into(inner, Qn, MY[:, :r])
        gram_new = np.eye(r)
    return R_new, gram_new
