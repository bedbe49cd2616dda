r"""LATIN-PGD global stage with block enrichment and compression (``"latin-pgd"``).

The correction ``y = u - u_lift`` on the free dofs is kept as ``Y = U V^T``, ``U``
(nf x p) orthonormal in the indicator metric ``M`` (:func:`contact.indicator_metric`).
With ``B = G Z`` the right-hand side of :mod:`contact.globalstage`, every iteration runs:

1. **Preliminary stage** (every iteration): all time functions are updated on the
   current basis, ``V^T = (U^T A U)^{-1} U^T G Z`` (the Galerkin projection of the global
   stage, eq. (16) of the paper restricted to the time functions). With the small
   matrix ``P = (U^T A U)^{-1} (G^T U)^T`` (p x 2nc, formed when the basis changes) it
   costs ``O(p nc m)``: nothing proportional to the number of free dofs ``nf``.
2. **Enrichment** (only when the rule below asks for it): a *block* of space modes is
   added at once. The part of the full LATIN global stage that the basis misses is
   ``E = A^{-1} B - U V^T = A^{-1} R`` (``R = B - A U V^T``, the residual of eq. (15)).
   Its dominant left vectors are found by a randomized range finder (Halko, Martinsson
   and Tropp, Algorithm 4.3; 4.4 with ``power`` subspace iterations):
   ``X = E Omega``, then ``power`` times ``X <- E (E^T A X)``, with ``Omega`` (m x b)
   Gaussian. ``E Omega`` costs ``b`` back-substitutions (``A^{-1} G (Z Omega)``) and a
   product with ``U``; ``E^T A X = R^T X = Z^T G^T X - V U^T A X`` costs no solve. With
   ``power >= 1`` the block tends to the dominant modes of the global-stage correction
   in the energy norm (the block form of the PGD's alternating fixed point
   ``u = A^{-1} R v``, ``v = R^T u``). The block is split (CGS2 in ``M``) into its
   coordinates in ``W`` and a rest, whose ``M``-orthonormal basis (SVQB) extends ``W``;
   the projection against ``U`` and the orthonormalisation of the block are then small
   coordinate products, directions already in ``span U`` are dropped, and step 1 is
   redone on the enlarged basis.
3. **Compression**: at each enrichment the :class:`streamsvd.StreamCompressor` receives
   one ``add``: the change of the time functions since its last update as an in-basis
   increment (``coefficients=``) and the new block as new columns. It runs one rotation
   sweep (Algorithm 3 of the paper, ``rule="paper"``) and truncates in ``M`` the terms
   with ``||v_i|| < trunc ||v_1||``. Its expansion gives the new basis, and step 1 is
   redone on it (the truncated ``V`` is not the Galerkin one). At the end, the last
   time functions are added as an in-basis increment and ``finalize`` converges the
   core and cuts it at ``trunc``: the result is the SVD of the last iterate, truncated.

The enrichment rule
-------------------
LATIN restricted to a fixed basis converges to a state set by the basis, so its
indicator stops decreasing (``contact/README.md``, "What a basis of p modes can reach").
With ``enrich="departure"`` (the default) every iteration sketches ``E`` with 4 Gaussian
columns (``E[||E omega||_M^2] = ||E||_M^2``): the reduced global state departs from the
full one by ``d = C_f E``, which moves the indicator by at most ``||E||_{M_c} / D``
(``D`` the indicator's denominator, see :mod:`contact.pgd`). A block is added when that
estimate exceeds ``enrich_tol`` (0.03) times the last indicator; the sketch is then the
first columns of the block. The other rules, measured in ``contact/README.md``:
``"stall"`` (a block when ``eta_{i-1} > enrich_tol eta_{i-2}``, default 0.9) and
``"always"`` (a block every iteration).

Storage: the solver keeps its own ``M``-orthonormal columns ``W`` (nf x w) with the
projections ``W^T A W``, ``G^T A W`` and ``C_f W``; the modes are ``U = W U_c`` and
the compressor works in the coordinates of ``W`` (on ``span W`` their Euclidean product
is ``M``). When a block does not fit in the compressor's room, ``W`` is compacted to
``U`` and a new compressor continues from the current expansion (room
``3 p / 2 + 2 b + 16``); their error bounds and discarded energies add up.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg as sla

from streamsvd import Expansion, StreamCompressor

from .globalstage import GlobalStage
from .pgd import free_metric, full_metric, mode_former

__all__ = ["BlockPGD", "ENRICH_RULES"]

log = logging.getLogger(__name__)

ENRICH_RULES = ("departure", "stall", "always")
# sketch columns of the "departure" rule (reused in the block)
_RULE_COLUMNS = 4
# default `enrich_tol` of each rule
ENRICH_TOL = {"departure": 0.03, "stall": 0.9, "always": 1.0}
# a block direction whose M-norm after CGS2 against the basis is below this fraction of
# its norm before lies in the basis (to rounding) and is dropped
_IN_BASIS = 1e-8


class BlockPGD:
    """Block-enriched, compressed separated global stage (see the module docstring).

    Parameters
    ----------
    stage : GlobalStage
    trunc : float
        Relative truncation of the compressor, in ``M``.
    block : int
        Columns of the random sketch per enrichment (space modes added at most).
    power : int
        Subspace iterations of the range finder.
    enrich : {"departure", "stall", "always"}
        Enrichment rule.
    enrich_tol : float
        Threshold of the rule (a ratio of indicators; see the module docstring).
    seed : int
        Seed of the Gaussian sketches.
    """

    def __init__(self, stage: GlobalStage, *, trunc: float, block: int, power: int,
                 enrich: str, enrich_tol: float, seed: int = 0) -> None:
        self.stage = stage
        self.trunc = trunc
        self.block = block
        self.power = power
        self.enrich = enrich
        self.enrich_tol = enrich_tol
        self.rng = np.random.default_rng(seed)
        nf, m = len(stage.free), stage.problem.m
        nc2 = stage.G.shape[1]
        self.M = free_metric(stage)
        self.W = np.zeros((nf, 0))
        self.WAW = np.zeros((0, 0))
        self.GtAW = np.zeros((nc2, 0))
        self.CW = np.zeros((nc2, 0))
        self.Uc = np.zeros((0, 0))
        self.V = np.zeros((m, 0))
        self.compressor: Any = None
        self.V_c = np.zeros((m, 0))  # the compressor's time functions
        self.cap = 0
        self.compactions = 0
        self.enrichments = 0
        self.pairs_added = 0
        self.solves = 0
        self.nf_columns: list[int] = []
        self._work = 0
        self._etas: list[float] = []
        self._dens: list[float] = []
        self._error_bound = 0.0
        self._discarded = 0.0
        self._updates: list[Any] = []
        self._project()

    # ------------------------------------------------------------------ helpers
    @property
    def basis_size(self) -> int:
        """Number of space modes."""
        return int(self.Uc.shape[1])

    def modes(self) -> Callable[[], np.ndarray]:
        """Return a function forming this iteration's modes (``W``, ``Uc`` are replaced)."""
        return mode_former(self.W, self.Uc)

    def record(self, eta: float, den: float) -> None:
        """Receive the indicator of the iteration just run and its denominator ``D``."""
        self._etas.append(eta)
        self._dens.append(den)

    def _project(self) -> None:
        """Projections of the modes and the preliminary-stage operator ``P`` (small)."""
        Uc, s = self.Uc, self.stage
        self.CU = self.CW @ Uc
        self.GtAU = self.GtAW @ Uc
        if Uc.shape[1] == 0:
            self.P = np.zeros((0, self.CW.shape[0]))
            return
        UAU = Uc.T @ self.WAW @ Uc
        GtU = s.Lw[:, None] * self.CU  # G^T U = L C_f U
        self.P = sla.cho_solve(sla.cho_factor(UAU), GtU.T)

    def _time_functions(self, Z: np.ndarray) -> np.ndarray:
        """Preliminary stage: ``V = Z^T P^T`` (m x p)."""
        return (self.P @ Z).T

    def _append(self, Q: np.ndarray) -> None:
        """Append the M-orthonormal columns ``Q`` (M-orthogonal to ``W``) to ``W``."""
        s = self.stage
        AQ = s.A @ Q
        self._work += self.W.shape[1] + 2 * Q.shape[1]
        w = self.W.shape[1]
        WAQ = self.W.T @ AQ
        b = Q.shape[1]
        S = np.empty((w + b, w + b))
        S[:w, :w] = self.WAW
        S[:w, w:] = WAQ
        S[w:, :w] = WAQ.T
        S[w:, w:] = 0.5 * (Q.T @ AQ + (Q.T @ AQ).T)
        self.WAW = S
        self.W = np.column_stack([self.W, Q])
        self.GtAW = np.column_stack([self.GtAW, s.G.T @ AQ])
        self.CW = np.column_stack([self.CW, s.Cf @ Q])

    def _compact(self) -> None:
        """Replace ``W`` by ``U = W Uc`` (the directions cut by truncation are dropped)."""
        Uc = self.Uc
        self._work += self.W.shape[1]
        self.W = self.W @ Uc
        self.WAW = Uc.T @ self.WAW @ Uc
        self.GtAW = self.GtAW @ Uc
        self.CW = self.CW @ Uc
        self.Uc = np.eye(Uc.shape[1])
        self.compactions += 1

    # ------------------------------------------------------------------ the block
    def _sketch(self, Z: np.ndarray, V: np.ndarray, Omega: np.ndarray) -> np.ndarray:
        """Return ``E Omega = A^{-1} G Z Omega - U V^T Omega`` (nf x b)."""
        s = self.stage
        b = Omega.shape[1]
        X = s.solve(s.G @ (Z @ Omega))
        self.solves += b
        self._work += 2 * b
        if V.shape[1]:
            X -= self.W @ (self.Uc @ (V.T @ Omega))
            self._work += self.W.shape[1]
        return X

    def _adjoint(self, Z: np.ndarray, V: np.ndarray, Q: np.ndarray) -> np.ndarray:
        """Return ``E^T A Q = R^T Q = Z^T G^T Q - V U^T A Q`` (m x b), no solve."""
        s = self.stage
        out = Z.T @ (s.G.T @ Q)
        if V.shape[1]:
            out -= V @ (self.Uc.T @ (self.W.T @ (s.A @ Q)))
            self._work += self.W.shape[1] + Q.shape[1]
        return out

    def _block_coordinates(self, X: np.ndarray) -> np.ndarray:
        """Return the ``W``-coordinates of an M-orthonormal basis of ``span X`` minus ``U``.

        The basis spans the part of ``span X`` M-orthogonal to ``U = W Uc``, and ``W`` is
        extended first as needed. ``X`` is split (CGS2 in ``M``) into its coordinates
        ``C`` in ``W`` and a rest ``R`` outside ``span W``; an M-orthonormal basis of
        ``span R`` (SVQB, twice) is appended to ``W``. The projection against ``U`` and
        the orthonormalisation of the block are then products of small coordinate
        matrices (on ``span W`` the Euclidean product of the coordinates is ``M``).
        Directions of ``X`` within ``_IN_BASIS`` of ``span U`` are dropped.
        """
        M, W = self.M, self.W
        MX = M @ X
        X = X / np.sqrt(np.maximum(np.einsum("ij,ij->j", X, MX), np.finfo(float).tiny))
        C = np.zeros((W.shape[1], X.shape[1]))
        R = X
        if W.shape[1]:
            for _ in range(2):
                D = W.T @ (M @ R)
                C += D
                R = R - W @ D
            self._work += 4 * W.shape[1] + 2 * X.shape[1]
        Q = _svqb(R, M, cut=1e-10)
        self._work += 4 * X.shape[1]
        if Q.shape[1]:
            Cn = Q.T @ (M @ R)
            self._append(Q)
            C = np.vstack([C, Cn])
        w1 = self.W.shape[1]
        Uc = np.zeros((w1, self.Uc.shape[1]))
        Uc[: self.Uc.shape[0]] = self.Uc
        for _ in range(2):  # against U, in coordinates
            C = C - Uc @ (Uc.T @ C)
        Ub, sb, _ = np.linalg.svd(C, full_matrices=False)
        Cq = Ub[:, sb > _IN_BASIS]
        Cq = Cq - Uc @ (Uc.T @ Cq)
        Cq, _ = np.linalg.qr(Cq)
        return Cq

    def _range(self, Z: np.ndarray, V: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Return the block from the sketch ``X = E Omega``: ``power`` subspace iterations."""
        for _ in range(self.power):
            X = X / np.maximum(np.linalg.norm(X, axis=0), np.finfo(float).tiny)
            X = self._sketch(Z, V, self._adjoint(Z, V, X))
        return self._block_coordinates(X)

    # ------------------------------------------------------------------ the rule
    def _wants_block(self, Z: np.ndarray, V: np.ndarray) -> tuple[bool, np.ndarray | None]:
        """Apply the enrichment rule; return (enrich?, the sketch it computed, if any)."""
        if self.Uc.shape[1] == 0 or self.enrich == "always":
            return True, None
        if self.enrich == "stall":
            return len(self._etas) >= 2 and self._etas[-1] > self.enrich_tol * self._etas[
                -2], None
        # "departure": E Omega estimates ||E||_M (E[||E omega||^2] = ||E||^2 for a
        # standard Gaussian omega); ||E||_M / D bounds the indicator's change
        Omega = self.rng.standard_normal((Z.shape[1], min(self.block, _RULE_COLUMNS)))
        X = self._sketch(Z, V, Omega)
        dep = float(np.sqrt(np.sum(X * (self.M @ X)) / Omega.shape[1]))
        if not self._etas:
            return True, X
        return dep > self.enrich_tol * self._etas[-1] * self._dens[-1], X

    # ------------------------------------------------------------------ one stage
    def update(self, Z: np.ndarray) -> np.ndarray:
        """Run the global stage for ``Z``; return the contact displacements."""
        self._work = 0
        V = self._time_functions(Z)
        wanted, X = self._wants_block(Z, V)
        if wanted:
            more = self.block - (0 if X is None else X.shape[1])
            if X is None or more > 0:
                Y = self._sketch(Z, V, self.rng.standard_normal((Z.shape[1], max(more, 0))))
                X = Y if X is None else np.column_stack([X, Y])
            if self.compressor is None or self.W.shape[1] + self.block > self.cap:
                self._restart(self.block)
            Cq = self._range(Z, V, X)
            if Cq.shape[1]:
                self._enrich(Cq, Z)
                V = self._time_functions(Z)
        self.V = V
        self.nf_columns.append(self._work)
        return self.CU @ V.T + self.stage.w_lift

    def _enrich(self, C: np.ndarray, Z: np.ndarray) -> None:
        """Add the block of coordinates ``C`` (in ``W``) to the basis, then compress."""
        b = C.shape[1]
        self.enrichments += 1
        self.pairs_added += b
        w1 = self.W.shape[1]
        p, w = self.Uc.shape[1], self.Uc.shape[0]
        Uc = np.zeros((w1, p + b))
        Uc[:w, :p] = self.Uc
        Uc[:, p:] = C
        self.Uc = Uc
        self._project()
        Vn = self._time_functions(Z)
        coords = np.zeros((self.cap, b))
        coords[:w1] = C
        if self.compressor.rank == 0:
            full = np.zeros((self.cap, p + b))
            full[:w1] = Uc
            self.compressor.add(full, Vn)
        else:
            self.compressor.add(coords, Vn[:, p:], coefficients=Vn[:, :p] - self.V_c)
        e = self.compressor.expansion
        self.Uc = np.array(e.U[: self.W.shape[1]])
        self.V_c = np.array(e.V)
        self._project()
        log.debug("enrichment %d: %d directions, basis %d -> %d", self.enrichments, b, p,
                  self.Uc.shape[1])

    def _restart(self, b: int) -> None:
        """Compact ``W`` and continue with a new compressor with room for ``b`` more."""
        if self.compressor is not None:
            self._error_bound += float(self.compressor.error_bound)
            self._discarded += float(self.compressor.discarded_energy)
            self._updates.extend(self.compressor.history)
            self._compact()
        p = self.Uc.shape[1]
        self.cap = min(max(3 * p // 2 + 2 * b + 16, p + b), self.W.shape[0])
        self.compressor = StreamCompressor(self.cap, rtol=self.trunc, sweeps=1,
                                           rule="paper")
        self.V_c = np.zeros((self.V.shape[0], 0))

    def finish(self) -> dict[str, Any]:
        """Return the counters and the final expansion (embedded in all dofs).

        The last time functions go to the compressor as an in-basis increment, then
        :meth:`streamsvd.StreamCompressor.finalize` converges its core (Jacobi sweeps)
        and cuts it at the truncation: the final expansion is the SVD of the last
        iterate ``U V^T`` truncated at ``trunc``, in ``M``.
        """
        s = self.stage
        iterations_basis = self.Uc.shape[1]
        if self.compressor is not None and self.compressor.rank:
            self.compressor.add(np.zeros((self.cap, 0)), np.zeros((self.V.shape[0], 0)),
                                coefficients=self.V - self.V_c)
            self.compressor.finalize()
            e = self.compressor.expansion
            self.Uc = np.array(e.U[: self.W.shape[1]])
            self.V = np.array(e.V)
        U = np.zeros((s.problem.n, self.Uc.shape[1]))
        U[s.free] = self.W @ self.Uc
        info: dict[str, Any] = {
            "expansion": Expansion(U, self.V, inner=full_metric(s, self.M)),
            "iteration_basis_size": iterations_basis,
            "enrichments": self.enrichments,
            "pairs_added": self.pairs_added,
            "solves": self.solves,
            "compactions": self.compactions,
            "nf_columns": np.array(self.nf_columns, dtype=int),
        }
        if self.compressor is not None:
            info["error_bound"] = self._error_bound + float(self.compressor.error_bound)
            info["discarded_energy"] = self._discarded + float(
                self.compressor.discarded_energy)
            info["compressor_history"] = tuple(self._updates) + self.compressor.history
        return info


def _svqb(X: np.ndarray, M: Any, *, cut: float) -> np.ndarray:
    """Return an M-orthonormal basis of ``span X`` (SVQB twice: eigenvectors of the Gram).

    The first pass drops the directions whose Gram eigenvalue is below ``cut`` (the
    columns of ``X`` being of unit scale), the second those below ``1e-14`` of the
    largest.
    """
    for i in range(2):
        if X.shape[1] == 0:
            break
        S = X.T @ (M @ X)
        lam, E = np.linalg.eigh(0.5 * (S + S.T))
        if lam[-1] <= 0:
            return X[:, :0]
        good = lam > (cut if i == 0 else 1e-14 * lam[-1])
        X = X @ (E[:, good] / np.sqrt(lam[good]))
    return X
