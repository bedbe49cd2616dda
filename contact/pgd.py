r"""LATIN-P3's separated global stage, and the indicator metric shared with LATIN-PGD.

The correction ``y = u - u_lift`` on the free dofs is kept as ``Y = U V^T``: ``U``
(nf x p) space modes, orthonormal in the *indicator metric* ``M`` below, and ``V``
(m x p) time functions. With the right-hand side ``B = G Z`` of :mod:`contact.globalstage`,
the global stage minimises the energy ``J(Y) = sum_t (y_t^T A y_t / 2 - y_t^T b_t)`` in
two steps:

1. *preliminary step*: new time functions on the current basis,
   ``V^T = (U^T A U)^{-1} U^T B`` (a p x p solve for all instants);
2. *enrichment*, only when step 1 left the residual ``R = B - A U V^T`` above
   ``enrich_ratio`` times the residual of the previous iterate against the new ``B``
   (comparing with ``||B||`` instead would stall LATIN): a new pair by the alternating
   fixed point ``u = A^{-1} R v / (v^T v)``, ``v = R^T u / (u^T A u)``, started from
   ``v = R^T R 1``; ``u`` is orthonormalised (CGS2, in ``M``) against ``U`` and step 1 is
   redone on the enlarged basis.

The indicator metric
--------------------
The indicator (:func:`contact.globalstage.indicator`) compares the global state
``s = (w, lam)`` with the local one. Changing the correction by ``-d`` (a truncation)
moves the global state along its search direction ``E^-``: ``w -> w - C_f d``,
``lam -> lam + k C_f d``. Its distance to ``s_hat`` changes by at most the norm of that
move,

.. math:: \|(C_f d, k C_f d)\|_k^2 = \sum_t 2k\, d_t^T C_f^T L C_f\, d_t
          = \|d\|_{M_c}^2, \qquad M_c = 2k\, C_f^T L C_f,

so, to first order, ``|Delta eta| <= ||d||_{M_c} / D`` with ``D = ||(s + s_hat)/2||_k``
the indicator's denominator (the relation is an equality when ``s = s_hat``, and it is
checked on the converged billet in ``tests/contact/test_latin.py``). ``M_c`` is only
semi-definite (it sees the contact dofs), so the modes are orthonormal in

.. math:: M = 2k\, C_f^T L C_f + \beta A, \qquad \beta = 10^{-6},

where the energy term only makes ``M`` definite: every iterate lies in the range of
``A^{-1} G`` (the responses to contact data), on which ``||y||_A`` and ``||y||_{M_c}`` are
of the same order (``||y||_A = 0.76 ||y||_{M_c}`` for the billet's correction,
``bench/bench_contact_subspace.py``), so ``beta A`` changes these norms by about 1e-6.

In ``M`` the compressor's relative rule (cut the terms with ``||v_i|| < trunc ||v_1||``)
changes the indicator by at most ``trunc sqrt(q_cut) sigma_1 / D``, ``q_cut`` the number
of terms cut and ``sigma_1 = ||v_1||_M``; ``sigma_1 / D`` is 0.21 for the billet (same
script), so a truncation at ``trunc`` changes the indicator by a fraction of ``trunc``.
That is the change per iteration. LATIN on a basis of ``p`` modes levels off at an
indicator set by the basis, far above the indicator of the reference truncated to the
same modes; reaching an indicator ``eta`` takes a truncation of about ``eta / 10`` on the
billet (see ``contact/README.md``). In the Euclidean norm of ``y``, the modes cut were
small but concentrated at the contact nodes, which the indicator weighs.

Cost of an iteration
--------------------
The solver keeps its own ``M``-orthonormal basis ``W`` (nf x w, ``w >= p``) with the
projections ``W^T A W``, ``W^T A^2 W``, ``G^T A W`` and ``C_f W``; the space modes are
``U = W U_c`` with ``U_c`` (w x p) orthonormal, and ``U`` is never formed during the
iteration. Everything the preliminary step, the residual norms and the contact
displacements need is a product of these small projections with ``U_c`` and ``V``:
``O(w^2 p + nc w p + nc m p + p^2 m)`` per iteration, nothing proportional to the number
of free dofs ``nf``. Only a new pair touches nf-sized vectors: its fixed point (sparse
products and back-substitutions), its CGS2 against ``W`` (``O(nf w)``) and its
projections. :attr:`SeparatedField.nf_columns` records, per iteration, how many nf-sized
vectors went through a product (a product with an ``nf x j`` matrix counts ``j``).

``"latin-pgd"`` keeps the same representation but enriches it by blocks and compresses
it with a :class:`streamsvd.StreamCompressor` (:mod:`contact.blockpgd`), which reuses the
metric functions of this module.

Residual norms are computed from the small matrices, or block of instants by block when
cancellation requires it (the residual below ``1e-5 ||G Z||``; counted in
``nf_columns``), so that no ``nf x m`` array is formed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from streamsvd import Expansion

from .errors import SolverOptionError
from .globalstage import GlobalStage, default_search_direction
from .problem import Problem

__all__ = ["METRIC_BETA", "SeparatedField", "indicator_metric"]

log = logging.getLogger(__name__)

_BLOCK = 64
METRIC_BETA = 1e-6
# residuals below sqrt(_CANCEL) ||G Z|| are recomputed directly (see _residual_norm)
_CANCEL = 1e-10


def indicator_metric(problem: Problem, *, k: float | None = None) -> sp.csr_matrix:
    """Return the metric ``M`` of the indicator on every dof of ``problem`` (n x n).

    ``M = 2k C_f^T L C_f + beta A`` on the free dofs (see the module docstring): the
    change of the correction ``y`` by ``d`` changes the indicator's numerator by at most
    ``||d||_M`` (to the relative ``beta = METRIC_BETA``). On the prescribed dofs, where
    ``y`` and every mode vanish, ``M`` is the identity scaled to its mean diagonal (only to
    make it definite). ``k`` defaults to :func:`contact.default_search_direction`.
    """
    if not isinstance(problem, Problem):
        raise SolverOptionError(
            f"`problem` must be a contact.Problem; got {type(problem).__name__}."
        )
    if k is None:
        k = default_search_direction(problem)
    elif not (isinstance(k, (int, float)) and k > 0):
        raise SolverOptionError(f"`k` must be a positive number; got {k!r}.")
    stage = GlobalStage(problem, float(k))
    return full_metric(stage, free_metric(stage))


def free_metric(stage: GlobalStage) -> sp.csr_matrix:
    """Return ``M = 2k C_f^T L C_f + beta A`` on the free dofs."""
    contact_part = 2.0 * stage.k * (stage.G @ stage.Cf)
    return sp.csr_matrix(contact_part + METRIC_BETA * stage.A)



def mode_former(W: np.ndarray, Uc: np.ndarray) -> Callable[[], np.ndarray]:
    """Return a function forming the modes ``W Uc`` (read-only) of one iteration.

    The solvers replace ``W`` and ``Uc`` rather than modify them, so the function keeps
    giving the modes of the iteration it was made in.
    """

    def form() -> np.ndarray:
        b = W @ Uc
        b.setflags(write=False)
        return b

    return form

class SeparatedField:
    """Separated global stage of ``"latin-p3"`` (one pair per enrichment, no truncation).

    Parameters
    ----------
    stage : GlobalStage
    enrich_ratio : float
        Residual reduction below which the preliminary step is enough.
    fixed_point : int
        Alternating iterations for a new pair.

    Attributes
    ----------
    nf_columns : list of int
        Per iteration, the nf-sized vectors that went through a product.
    """

    def __init__(
        self,
        stage: GlobalStage,
        *,
        enrich_ratio: float,
        fixed_point: int,
    ) -> None:
        self.stage = stage
        self.enrich_ratio = enrich_ratio
        self.fixed_point = fixed_point
        nf, m = len(stage.free), stage.problem.m
        self.M = free_metric(stage)
        self.GtG = sp.csr_matrix(stage.G.T @ stage.G)
        # the solver's basis W (M-orthonormal) and its projections
        self.W = np.zeros((nf, 0))
        self.WAW = np.zeros((0, 0))
        self.WAAW = np.zeros((0, 0))
        self.GtAW = np.zeros((self.GtG.shape[0], 0))
        self.CW = np.zeros((self.GtG.shape[0], 0))
        # the modes U = W Uc and their time functions
        self.Uc = np.zeros((0, 0))
        self.V = np.zeros((m, 0))
        self.enrichments = 0
        self.direct_residuals = 0
        self.nf_columns: list[int] = []
        self._work = 0
        self._project()

    # ------------------------------------------------------------------ helpers
    @property
    def basis_size(self) -> int:
        """Number of space modes."""
        return int(self.Uc.shape[1])

    @property
    def basis(self) -> np.ndarray:
        """Current space modes on the free dofs (read-only; formed on request, ``O(nf w p)``)."""
        return self.modes()()

    def modes(self) -> Callable[[], np.ndarray]:
        """Return a function forming the current modes.

        ``W`` and ``Uc`` are replaced, never modified in place, so it keeps giving this
        iteration's modes.
        """
        return mode_former(self.W, self.Uc)

    def _project(self) -> None:
        """Projections of the modes ``U = W Uc`` (small products only)."""
        Uc, s = self.Uc, self.stage
        self.UAU = Uc.T @ self.WAW @ Uc
        self.AtA = Uc.T @ self.WAAW @ Uc
        self.GtAU = self.GtAW @ Uc
        self.CU = self.CW @ Uc
        self.GtU = s.Lw[:, None] * self.CU  # G^T U = L C_f U

    def _append(self, q: np.ndarray) -> None:
        """Append the M-unit vector ``q``, M-orthogonal to ``W``, to ``W``."""
        s = self.stage
        Aq = s.A @ q
        AAq = s.A @ Aq
        self._work += 2 * self.W.shape[1] + 4
        waq = np.append(self.W.T @ Aq, q @ Aq)
        waaq = np.append(self.W.T @ AAq, Aq @ Aq)
        self.W = np.column_stack([self.W, q])
        self.WAW = _bordered(self.WAW, waq)
        self.WAAW = _bordered(self.WAAW, waaq)
        self.GtAW = np.column_stack([self.GtAW, s.G.T @ Aq])
        self.CW = np.column_stack([self.CW, s.Cf @ q])

    def _time_functions(self, Z: np.ndarray) -> np.ndarray:
        if self.Uc.shape[1] == 0:
            return np.zeros((Z.shape[1], 0))
        rhs = self.GtU.T @ Z  # U^T G Z, p x m
        return sla.cho_solve(sla.cho_factor(self.UAU), rhs).T

    def _residual_norm(self, Z: np.ndarray, V: np.ndarray) -> float:
        """Return ``||G Z - A U V^T||_F``.

        Expanded as ``||G Z||^2 - 2 <G Z, A U V^T> + ||A U V^T||^2`` with small
        matrices only. The rounding error of this sum is ``c eps ||G Z||^2`` (``c`` a
        small multiple of the inner dimensions), a relative error ``c eps ||G Z||^2 /
        (2 r^2)`` on ``r``: below ``r = 1e-5 ||G Z||`` (where it could exceed 1e-3) the
        norm is recomputed directly, block of instants by block.
        """
        a = float(np.sum(Z * (self.GtG @ Z)))
        b = float(np.sum((Z.T @ self.GtAU) * V)) if V.shape[1] else 0.0
        c = float(np.sum(self.AtA * (V.T @ V))) if V.shape[1] else 0.0
        r2 = a - 2.0 * b + c
        if r2 > _CANCEL * a:
            return float(np.sqrt(r2))
        self.direct_residuals += 1
        G, A, U = self.stage.G, self.stage.A, self.W @ self.Uc
        self._work += self.W.shape[1] + 2 * Z.shape[1]
        total = 0.0
        for j in range(0, Z.shape[1], _BLOCK):
            R = G @ Z[:, j : j + _BLOCK] - A @ (U @ V[j : j + _BLOCK].T)
            total += float(np.sum(R * R))
        return float(np.sqrt(total))

    def _new_pair(self, Z: np.ndarray, V: np.ndarray) -> np.ndarray | None:
        """Return the new space mode, M-orthonormal to ``U``, or None."""
        s = self.stage
        G, A, W, Uc = s.G, s.A, self.W, self.Uc

        def R(v: np.ndarray) -> np.ndarray:
            return G @ (Z @ v) - A @ (W @ (Uc @ (V.T @ v)))

        def Rt(u: np.ndarray) -> np.ndarray:
            return Z.T @ (G.T @ u) - V @ (Uc.T @ (W.T @ (A @ u)))

        v = Rt(R(np.ones(Z.shape[1])))
        self._work += 2 * W.shape[1] + 4
        if not np.any(v):
            return None
        v /= np.linalg.norm(v)
        u = np.zeros(W.shape[0])
        for _ in range(self.fixed_point):
            u = s.solve(R(v)) / (v @ v)
            Au = A @ u
            uAu = u @ Au
            self._work += 2 * W.shape[1] + 6
            if uAu <= 0:
                return None
            v = Rt(u) / uAu
        norm0 = np.sqrt(u @ (self.M @ u))
        for _ in range(2):  # CGS2 against U = W Uc, in M
            u = u - W @ (Uc @ (Uc.T @ (W.T @ (self.M @ u))))
        norm = np.sqrt(u @ (self.M @ u))
        self._work += 4 * W.shape[1] + 6
        if norm <= 1e-10 * norm0 or norm == 0:
            return None
        return u / norm

    def _coordinates(self, u: np.ndarray) -> np.ndarray:
        """Coordinates of the M-unit ``u`` in ``W``, extended by one column when needed."""
        c = np.zeros(self.W.shape[1])
        r = u
        for _ in range(2):  # CGS2 against W, in M
            d = self.W.T @ (self.M @ r)
            c += d
            r = r - self.W @ d
        norm = np.sqrt(r @ (self.M @ r))
        self._work += 4 * self.W.shape[1] + 4
        if norm <= 1e-10:  # u lies in span W (up to rounding)
            return c
        self._append(r / norm)
        return np.append(c, norm)

    # ------------------------------------------------------------------ one stage
    def update(self, Z: np.ndarray) -> np.ndarray:
        """Run the separated global stage for ``Z``; return the contact displacements."""
        self._work = 0
        V_old = self.V
        p = self.Uc.shape[1]
        r_before = self._residual_norm(Z, V_old)
        V = self._time_functions(Z)
        r_after = self._residual_norm(Z, V) if p else r_before
        new = None
        if p == 0 or r_after > self.enrich_ratio * r_before:
            new = self._new_pair(Z, V)
        if new is not None:
            self.enrichments += 1
            c = self._coordinates(new)
            Uc = np.zeros((self.W.shape[1], p + 1))
            Uc[: self.Uc.shape[0], :p] = self.Uc
            Uc[: c.size, p] = c
            self.Uc = Uc
            self._project()
            V = self._time_functions(Z)
        self.V = V
        self.nf_columns.append(self._work)
        return self.CU @ self.V.T + self.stage.w_lift

    def finish(self) -> dict[str, Any]:
        """Return the counters and the final expansion (embedded in all dofs)."""
        s = self.stage
        n = s.problem.n
        U = np.zeros((n, self.Uc.shape[1]))
        U[s.free] = self.basis
        info: dict[str, Any] = {
            "expansion": Expansion(U, self.V, inner=full_metric(s, self.M)),
            "enrichments": self.enrichments,
            "direct_residuals": self.direct_residuals,
            "nf_columns": np.array(self.nf_columns, dtype=int),
        }
        return info


def full_metric(stage: GlobalStage, M: sp.spmatrix) -> sp.csr_matrix:
    """Return ``M`` (free dofs) extended to every dof.

    On the prescribed dofs, where the correction and every mode vanish, it is the
    identity scaled to ``M``'s mean diagonal.
    """
    n = stage.problem.n
    fixed = stage.problem.dirichlet_dofs
    P = sp.csr_matrix((np.ones(len(stage.free)), (stage.free, np.arange(len(stage.free)))),
                      shape=(n, len(stage.free)))
    scale = float(M.diagonal().mean()) if M.shape[0] else 1.0
    D = sp.csr_matrix((np.full(len(fixed), scale), (fixed, fixed)), shape=(n, n))
    return sp.csr_matrix(P @ M @ P.T + D)


def _bordered(S: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Return the symmetric ``S`` bordered by the column ``col`` (its last entry the corner)."""
    w = S.shape[0]
    out = np.empty((w + 1, w + 1))
    out[:w, :w] = S
    out[:w, w] = out[w, :w] = col[:w]
    out[w, w] = col[w]
    return out
