"""What the LATIN solver returns: the state after each iteration, and the outcome."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streamsvd import Expansion

__all__ = ["IterationState", "LatinResult"]


@dataclass(frozen=True, eq=False)
class IterationState:
    """What a callback receives after every iteration.

    Attributes
    ----------
    iteration : int
        1 for the first iteration.
    indicator : float
        Error indicator ``eta`` between the global and local states.
    basis_size : int
        Number of space modes (``m`` for the full-field method).
    cpu_time : float
        Process time of this iteration (s).
    basis : ndarray or None
        Space modes of this iteration on the free dofs (nf x p, read-only) for the
        separated methods; formed when first read (``O(nf w p)``, see
        :mod:`contact.pgd`), so a callback that does not read it costs nothing.
    """

    iteration: int
    indicator: float
    basis_size: int
    cpu_time: float
    modes: Callable[[], np.ndarray | None] = field(repr=False)

    @property
    def basis(self) -> np.ndarray | None:
        """Space modes of this iteration (formed on the first read, then kept)."""
        if "_basis" not in self.__dict__:
            object.__setattr__(self, "_basis", self.modes())
        out: np.ndarray | None = self.__dict__["_basis"]
        return out


@dataclass(frozen=True, eq=False)
class LatinResult:
    """Outcome of :func:`solve`.

    The displacement is ``u = u_lift + y`` (see :mod:`contact.globalstage`): ``lift`` is
    the elastic response to the prescribed displacements, ``y`` is ``field`` (n x m) for
    ``"latin"`` and ``correction`` (a :class:`streamsvd.Expansion`, U orthonormal) for the
    separated methods.

    Attributes
    ----------
    method : str
    k : float
        Search direction used.
    converged : bool
        Whether ``indicator[-1] <= tol``.
    indicator, basis_size, cpu_time, wall_time : ndarray, shape (iterations,)
        Per-iteration history (times in s, per iteration, not cumulative).
    setup_time : float
        Process time of the factorisation and the lift (s).
    w, lam : ndarray, shape (2 nc, m)
        Contact displacements and tractions of the last global stage.
    w_hat, lam_hat : ndarray, shape (2 nc, m)
        The last local stage (satisfies the contact laws exactly).
    lift : streamsvd.Expansion
    field : ndarray or None
    correction : streamsvd.Expansion or None
    info : dict
        Method-specific counters (enrichments, truncations, compressor history).
    """

    method: str
    k: float
    converged: bool
    indicator: np.ndarray
    basis_size: np.ndarray
    cpu_time: np.ndarray
    wall_time: np.ndarray
    setup_time: float
    w: np.ndarray
    lam: np.ndarray
    w_hat: np.ndarray
    lam_hat: np.ndarray
    lift: Expansion
    field: np.ndarray | None
    correction: Expansion | None
    info: dict[str, Any]

    @property
    def iterations(self) -> int:
        """Number of iterations run."""
        return int(self.indicator.size)

    def displacement(self) -> np.ndarray:
        """Return the displacement ``u`` (n x m) as a dense array."""
        return self.lift.to_dense() + self.correction_dense()

    def correction_dense(self) -> np.ndarray:
        """Return ``y = u - u_lift`` (n x m) as a dense array."""
        if self.correction is not None:
            return self.correction.to_dense()
        return np.asarray(self.field)

    def memory(self) -> int:
        """Return the bytes of the displacement representation (lift included)."""
        lift = self.lift.U.nbytes + self.lift.V.nbytes
        if self.correction is not None:
            return int(self.correction.U.nbytes + self.correction.V.nbytes + lift)
        return int(np.asarray(self.field).nbytes + lift)

    def cpu_time_to(self, level: float) -> float:
        """Return the cumulated CPU time (setup included) until ``indicator <= level``.

        ``nan`` when the level was not reached.
        """
        hit = np.flatnonzero(self.indicator <= level)
        if hit.size == 0:
            return float("nan")
        return float(self.setup_time + np.sum(self.cpu_time[: hit[0] + 1]))

    def iterations_to(self, level: float) -> int | None:
        """Return the first iteration (1-based) with ``indicator <= level``, or None."""
        hit = np.flatnonzero(self.indicator <= level)
        return int(hit[0] + 1) if hit.size else None
