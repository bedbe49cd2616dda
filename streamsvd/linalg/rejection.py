"""What the rejection rule measures a residual against.

A residual ``r_j`` is rejected when ``||r_j|| <= reject_tol * ref_j``: for the columns of
a block ``ref_j`` is the column's own norm, for the terms ``u_j v_j^T`` of an increment or
of a merged expansion it is the largest term's energy over ``||v_j||``
(:func:`term_reference`); the default ``reject_tol`` is ``n eps``
(:func:`default_reject_tol`). :func:`streamsvd.linalg.extend.extend_basis` applies the
rule (:func:`streamsvd.linalg.blocks.column_rule`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["default_reject_tol", "term_reference", "top_energy"]

_EPS = np.finfo(np.float64).eps


def default_reject_tol(n: int) -> float:
    """Return the default rejection threshold ``n * eps`` (relative to a column's norm)."""
    return max(n, 1) * _EPS


def top_energy(u_norms: np.ndarray, v_norms: np.ndarray) -> float:
    """Return ``max_i ||u_i|| ||v_i||``, the largest term's energy (0 without a term)."""
    return float(np.max(u_norms * v_norms)) if u_norms.size else 0.0


def term_reference(u_norms: np.ndarray, v_norms: np.ndarray) -> np.ndarray:
    """Return reference norms: a term's rejection relative to the largest term's energy.

    For the terms ``u_j v_j^T`` of an increment or of an expansion merged (the
    ``reference`` of :func:`extend_basis`).

    The residual ``r_j`` of ``u_j`` is rejected when ``||r_j|| <= tol * ref_j`` with
    ``ref_j = max_i(||u_i|| ||v_i||) / ||v_j||``; a term with ``v_j = 0`` carries nothing
    (reference 0: rejected).
    """
    top = top_energy(u_norms, v_norms)
    with np.errstate(divide="ignore"):
        ref = np.where(v_norms > 0, top / np.where(v_norms > 0, v_norms, 1.0), 0.0)
    return ref
