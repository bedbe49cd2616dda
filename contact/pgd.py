"""Space-time separated global stage (LATIN principle P3), with or without compression.

The correction ``y = u - u_lift`` on the free dofs is kept as ``Y = U V^T``: ``U``
(nf x p) orthonormal space modes, ``V`` (m x p) time functions. With the right-hand side
``B = G Z`` of :mod:`contact.globalstage`, the global stage minimises the energy
``J(Y) = sum_t (y_t^T A y_t / 2 - y_t^T b_t)`` in two steps:

1. *preliminary step*: new time functions on the current basis,
   ``V^T = (U^T A U)^{-1} U^T B`` (a p x p solve for all instants);
2. *enrichment*, only when step 1 left the residual ``R = B - A U V^T`` above
   ``enrich_ratio`` times the residual of the previous iterate against the new ``B``
   (comparing with ``||B||`` instead would stall LATIN): a new pair by the alternating
   fixed point ``u = A^{-1} R v / (v^T v)``, ``v = R^T u / (u^T A u)``, started from
   ``v = R^T R 1``; ``u`` is orthonormalised (CGS2) against ``U`` and step 1 is redone on
   the enlarged basis.

With compression (``"latin-pgd"``), the change of the iterate,
``U_old (V[:, :p] - V_old)^T + u v_new^T``, is added to a
:class:`streamsvd.StreamCompressor` in one update: the first term through
``add(..., coefficients=...)`` (an increment inside the compressor's own basis, no
Gram-Schmidt), the new pair through Gram-Schmidt; then one rotation sweep of Algorithm 3
and truncation of the terms with ``||v_i|| < trunc * ||v_1||``. The compressor's
expansion becomes the new ``U, V``.

Residual norms are computed from small matrices (``2 nc x p``, ``p x p``), or block of
instants by block when cancellation requires it, so that no ``nf x m`` array is formed.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import scipy.linalg as sla

from streamsvd import Expansion

from .globalstage import GlobalStage

__all__ = ["SeparatedField"]

log = logging.getLogger(__name__)

_BLOCK = 64


class SeparatedField:
    """Separated global stage used by ``"latin-p3"`` and ``"latin-pgd"``.

    Parameters
    ----------
    stage : GlobalStage
    compress : bool
        Feed every change through a :class:`streamsvd.StreamCompressor`.
    trunc : float
        Relative truncation threshold of the compressor.
    enrich_ratio : float
        Residual reduction below which the preliminary step is enough.
    fixed_point : int
        Alternating iterations for a new pair.
    """

    def __init__(
        self,
        stage: GlobalStage,
        *,
        compress: bool,
        trunc: float,
        enrich_ratio: float,
        fixed_point: int,
    ) -> None:
        self.stage = stage
        self.compress = compress
        self.trunc = trunc
        self.enrich_ratio = enrich_ratio
        self.fixed_point = fixed_point
        nf, m = len(stage.free), stage.problem.m
        self.U = np.zeros((nf, 0))
        self.V = np.zeros((m, 0))
        self.compressor: Any = None
        self.GtG = np.asarray((stage.G.T @ stage.G).todense())
        self.enrichments = 0
        self.rank_history: list[int] = []
        self._refresh()

    # ------------------------------------------------------------------ helpers
    @property
    def basis_size(self) -> int:
        """Number of space modes."""
        return int(self.U.shape[1])

    @property
    def basis(self) -> np.ndarray:
        """Current space modes on the free dofs (read-only view)."""
        b = self.U.view()
        b.setflags(write=False)
        return b

    def _refresh(self) -> None:
        s = self.stage
        self.AU = np.asarray(s.A @ self.U)
        self.UAU = self.U.T @ self.AU
        self.CU = np.asarray(s.Cf @ self.U)
        self.GtU = s.Lw[:, None] * self.CU  # G^T U = L C_f U
        self.GtAU = np.asarray(s.G.T @ self.AU)
        self.AtA = self.AU.T @ self.AU

    def _time_functions(self, Z: np.ndarray) -> np.ndarray:
        if self.U.shape[1] == 0:
            return np.zeros((Z.shape[1], 0))
        rhs = self.GtU.T @ Z  # U^T G Z, p x m
        return sla.cho_solve(sla.cho_factor(self.UAU), rhs).T

    def _residual_norm(self, Z: np.ndarray, V: np.ndarray) -> float:
        """Return ``||G Z - A U V^T||_F``.

        Expanded as ``||G Z||^2 - 2 <G Z, A U V^T> + ||A U V^T||^2`` with small
        matrices only; when cancellation makes this inaccurate (the residual below
        ``1e-4 ||G Z||``) it is recomputed directly, block of instants by block.
        """
        a = float(np.sum(Z * (self.GtG @ Z)))
        b = float(np.sum((Z.T @ self.GtAU) * V)) if V.shape[1] else 0.0
        c = float(np.sum(self.AtA * (V.T @ V))) if V.shape[1] else 0.0
        r2 = a - 2.0 * b + c
        if r2 > 1e-8 * a:
            return float(np.sqrt(r2))
        G, AU = self.stage.G, self.AU
        total = 0.0
        for j in range(0, Z.shape[1], _BLOCK):
            R = G @ Z[:, j : j + _BLOCK] - AU @ V[j : j + _BLOCK].T
            total += float(np.sum(R * R))
        return float(np.sqrt(total))

    def _new_pair(self, Z: np.ndarray, V: np.ndarray) -> np.ndarray | None:
        s = self.stage
        G, AU = s.G, self.AU

        def R(v: np.ndarray) -> np.ndarray:
            return G @ (Z @ v) - AU @ (V.T @ v)

        def Rt(u: np.ndarray) -> np.ndarray:
            return Z.T @ (G.T @ u) - V @ (AU.T @ u)

        v = Rt(R(np.ones(Z.shape[1])))
        if not np.any(v):
            return None
        v /= np.linalg.norm(v)
        u = np.zeros(AU.shape[0])
        for _ in range(self.fixed_point):
            u = s.solve(R(v)) / (v @ v)
            uAu = u @ (s.A @ u)
            if uAu <= 0:
                return None
            v = Rt(u) / uAu
        norm0 = np.linalg.norm(u)
        for _ in range(2):  # CGS2
            u = u - self.U @ (self.U.T @ u)
        norm = np.linalg.norm(u)
        if norm <= 1e-10 * norm0 or norm == 0:
            return None
        return u / norm

    # ------------------------------------------------------------------ one stage
    def update(self, Z: np.ndarray) -> np.ndarray:
        """Run the separated global stage for ``Z``; return the contact displacements."""
        U_old, V_old = self.U, self.V
        p = U_old.shape[1]
        r_before = self._residual_norm(Z, V_old)
        V = self._time_functions(Z)
        r_after = self._residual_norm(Z, V) if p else r_before
        new = None
        if p == 0 or r_after > self.enrich_ratio * r_before:
            new = self._new_pair(Z, V)
        if new is not None:
            self.enrichments += 1
            self.U = np.column_stack([U_old, new])
            self._refresh()
            V = self._time_functions(Z)
        if self.compress:
            # the change of the time functions is an increment inside the compressor's
            # basis (its coordinates are given directly); only the new pair needs
            # Gram-Schmidt
            self._absorb(self.U[:, p:], V[:, p:], V[:, :p] - V_old)
        else:
            self.V = V
        self.rank_history.append(self.U.shape[1])
        return self.CU @ self.V.T + self.stage.w_lift

    def _absorb(self, new_U: np.ndarray, new_V: np.ndarray, dV: np.ndarray) -> None:
        import streamsvd

        if self.compressor is None:
            self.compressor = streamsvd.StreamCompressor(
                new_U.shape[0], rtol=self.trunc, sweeps=1, rule="paper"
            )
            self.compressor.add(new_U, new_V)
        else:
            self.compressor.add(new_U, new_V, coefficients=dV)
        e = self.compressor.expansion
        self.U = np.array(e.U)
        self.V = np.array(e.V)
        self._refresh()

    def finish(self) -> dict[str, Any]:
        """Return the counters and the final expansion (embedded in all dofs)."""
        s = self.stage
        n = s.problem.n
        U = np.zeros((n, self.U.shape[1]))
        U[s.free] = self.U
        info: dict[str, Any] = {
            "expansion": Expansion(U, self.V),
            "enrichments": self.enrichments,
        }
        if self.compressor is not None:
            info["error_bound"] = float(self.compressor.error_bound)
            info["discarded_energy"] = float(self.compressor.discarded_energy)
        return info
