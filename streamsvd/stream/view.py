"""What a compressor exposes of its expansion: factors, amplitudes, bound, history.

:class:`ExpansionView` reads the state of a :class:`~streamsvd.StreamCompressor` (its
:class:`~streamsvd.stream.lifecycle.Lifecycle`: state, history, options and inner
product) and never changes it; the facade forwards its attributes, so they are the
compressor's own.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from streamsvd._util.scaling import safe_column_norms, safe_norm
from streamsvd._util.scheduling import execute
from streamsvd.algebra.panels.backend import PanelBackend
from streamsvd.algebra.panels.basis import PanelBasis
from streamsvd.engine.record import UpdateRecord
from streamsvd.errors import InputError
from streamsvd.linalg.compress import fix_signs
from streamsvd.linalg.expansion import Expansion

if TYPE_CHECKING:
    from streamsvd.algebra.inner import InnerProduct
    from streamsvd.stream.lifecycle import Lifecycle
    from streamsvd.stream.options import CompressorOptions

__all__ = ["ExpansionView"]

logger = logging.getLogger("streamsvd.stream")


class ExpansionView:
    """The read-only attributes of a compressor's expansion (see the module docstring).

    Parameters
    ----------
    life : Lifecycle
        The compressor's lifecycle, whose state this part reads.
    """

    def __init__(self, life: Lifecycle) -> None:
        self._life = life
        # (state version, order, signs) of the terms last exposed: the coordinates of `add`
        self._exposure: tuple[int, np.ndarray, np.ndarray] | None = None

    @property
    def n(self) -> int:
        """Size of one snapshot."""
        return self._life.n

    @property
    def inner(self) -> InnerProduct:
        """The inner product ``M`` in which ``U`` is orthonormal."""
        return self._life.inner

    @property
    def options(self) -> CompressorOptions:
        """The compressor's options (each is also a read-only attribute of its own)."""
        return self._life.options

    @property
    def source_offset(self) -> int:
        """Position in the source just after the last block absorbed."""
        return self._life.source_offset

    @property
    def store_path(self) -> str | None:
        """Path of the store, or None."""
        p = self._life.persistence
        return None if p is None else p.path

    @property
    def chunk_rows(self) -> int | None:
        """Rows per chunk of the panels in the tall mode (None: the basis is in memory)."""
        return getattr(self._life.backend, "chunk_rows", None)

    @property
    def client(self) -> Any:
        """The cluster the tall mode's row-chunk products run on (None: none)."""
        return getattr(self._life.backend, "client", None)

    @property
    def n_seen(self) -> int:
        """Number of snapshots (columns) in the expansion."""
        return self._life.state.m

    @property
    def rank(self) -> int:
        """Current number of terms."""
        return self._life.state.rank

    def _order(self, V: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``U`` of the exposed terms with its sort order and signs.

        Terms are sorted by the norms of ``V`` when it is given, else of the core ``R``
        (equal up to rounding).
        """
        s = self._life.state
        coords, _, R = s.settled()
        U = s.basis.lincomb(coords)
        perm = np.argsort(-safe_column_norms(R if V is None else V), kind="stable")
        U = U[:, perm]
        signs = fix_signs(U, np.zeros((0, U.shape[1])))
        return U, perm, signs

    @property
    def left_vectors(self) -> np.ndarray:
        """``U`` (``n x p``, ``M``-orthonormal), terms sorted by decreasing amplitude.

        Signed so that the largest entry of each ``u_i`` is positive. Costs
        ``O(n w p)``, nothing in the number of snapshots; available in every mode.
        """
        return self._order()[0]

    @property
    def expansion(self) -> Expansion:
        """The current expansion ``U V^T`` (formed from the stored factors, signs fixed).

        Terms are sorted by decreasing amplitude and signed so that the largest entry of
        each ``u_i`` is positive; ``add(..., coefficients=dV)`` takes ``dV`` in the
        coordinates of this ``U``. Needs ``right_vectors=True``.
        """
        V = self.right_factor()
        U, perm, signs = self._order(V)
        self._exposure = (self._life.version, perm, signs)  # the coordinates of `add`
        return Expansion(U, V[:, perm] * signs, inner=self._life.inner)

    def factors(self) -> tuple[Any, np.ndarray]:
        """Return the expansion as ``(U, V)``, terms sorted and signed as in :attr:`expansion`.

        In the tall mode (a basis in panels) ``U`` is lazy (dask, over the panels) and its
        signs (the largest-modulus entry of each ``u_i`` positive) are found by a
        reduction over the row chunks, so neither this call nor computing ``U`` chunk by
        chunk holds ``n x p``; :attr:`left_vectors` and :attr:`expansion` do gather
        ``U``. In memory, ``U`` and ``V`` are :attr:`expansion`'s. Needs
        ``right_vectors=True``.
        """
        s = self._life.state
        if not isinstance(s.basis, PanelBasis):
            e = self.expansion
            return e.U, e.V
        V = self.right_factor()
        perm = np.argsort(-safe_column_norms(V), kind="stable")
        U = s.basis.lazy(s.settled()[0][:, perm])
        backend = cast(PanelBackend, self._life.backend)
        top, bottom = execute([U.max(axis=0), U.min(axis=0)], client=backend.client,
                              overlap_io=True)
        signs = np.where(np.asarray(top) >= -np.asarray(bottom), 1.0, -1.0)
        self._exposure = (self._life.version, perm, signs)  # the coordinates of `add`
        return U * signs, V[:, perm] * signs

    @property
    def stored_width(self) -> int:
        """Number of stored columns of the basis (the rank plus those awaiting compaction)."""
        return self._life.state.basis.width

    def right_factor(self) -> np.ndarray:
        """``V = Y R`` (``m x p``) in the stored term order, unsorted and unsigned.

        ``Y`` is kept orthonormal (:mod:`streamsvd.engine.update`), so the right vectors
        ``v_i / ||v_i||`` are orthonormal to rounding at convergence, whatever the spread
        of the amplitudes. Needs ``right_vectors=True``.
        """
        rows = self._life.state.rows
        if rows is None:
            raise InputError(
                "this StreamCompressor keeps no right vectors (`right_vectors=False`); use "
                "`left_vectors` and `amplitudes`, or create it with `right_vectors=True`."
            )
        R = self._life.state.settled()[2]
        return rows.value() @ R if self.rank else np.zeros((self.n_seen, 0))

    @property
    def amplitudes(self) -> np.ndarray:
        """``||v_i||``, computed on the small core (``||v_i|| = ||r_i||``), sorted."""
        return np.sort(safe_column_norms(self._life.state.settled()[2]))[::-1]

    @property
    def discarded_energy(self) -> float:
        """Sum of the energies ``||D_t||_F^2`` discarded by every update.

        ``inf`` above about 1e154 (never an exception); :attr:`discarded_norm` is its square
        root, always finite.
        """
        d = self._life.state.bound.discarded
        return d * d

    @property
    def discarded_norm(self) -> float:
        """``sqrt(sum_t ||D_t||_F^2)``, kept as a norm (finite for amplitudes to 1e300)."""
        return self._life.state.bound.discarded

    @property
    def error_bound(self) -> float:
        """Guaranteed bound on ``||A - U V^T||_F`` (theorem in :mod:`streamsvd.engine.bound`)."""
        return self._life.state.bound.bound

    @property
    def error_in_measure(self) -> float:
        """:attr:`error_bound` in the ``error_measure`` of the target (a guaranteed bound).

        ``"absolute"``: the bound itself; ``"mean_l2"``: ``bound / sqrt(m)``;
        ``"relative"``: ``bound / (||U V^T||_F - bound)``, which bounds
        ``||A - U V^T|| / ||A||`` since ``||A|| >= ||U V^T|| - bound`` (``inf`` when the
        bound is not below the expansion's norm).
        """
        b = self.error_bound
        if self._life.options.error_measure == "absolute":
            return b
        if self._life.options.error_measure == "mean_l2":
            return b / math.sqrt(self.n_seen) if self.n_seen else 0.0
        norm = safe_norm(self.amplitudes)
        return b / (norm - b) if norm > b else (0.0 if b == 0.0 else math.inf)

    @property
    def target_met(self) -> bool | None:
        """Whether :attr:`error_in_measure` is within ``target_error`` (None without one)."""
        if self._life.options.target_error is None:
            return None
        return self.error_in_measure <= self._life.options.target_error

    @property
    def history(self) -> tuple[UpdateRecord, ...]:
        """One :class:`UpdateRecord` per update, oldest first."""
        return tuple(self._life.history)

    def orthogonality_error(self) -> float:
        """Return ``||U^T M U - I||_2`` from the small Gram matrices."""
        return self._life.state.orthogonality()

    @property
    def finalized(self) -> bool:
        """Whether the expansion is its own SVD, truncated by the rules without oversampling.

        True when the last update was :meth:`finalize`, or nothing was absorbed yet.
        """
        return not self._life.history or self._life.history[-1].kind == "finalize"

    def internal_coefficients(self, dV: np.ndarray) -> np.ndarray:
        """Map coefficients on the exposed basis (sorted, signed) to the stored terms."""
        if self._exposure is None or self._exposure[0] != self._life.version:
            _ = self.expansion  # computes and caches the exposure of this state
        assert self._exposure is not None
        _, perm, signs = self._exposure
        out = np.empty_like(dV)
        out[:, perm] = dV * signs
        return out

    @property
    def streaming_rank(self) -> int | None:
        """Most terms kept between updates: ``max_rank + oversampling`` (None: no cap)."""
        return self._life.options.streaming_rank

    @property
    def target_missed_by(self) -> str | None:
        """Why the target error is missed (None when it is met, or without a target).

        ``"max_rank"``: the rank cap cut more than the target allows.
        ``"earlier_updates"``: what was discarded before already exceeds the target's
        budget, so no rank meets it now; the cut of every update is sized to stay within
        the budget, but the budget of a ``"relative"`` target shrinks when snapshots
        that carried much of the norm leave a window (or are forgotten), and a
        ``"mean_l2"`` budget when snapshots are removed.
        """
        if self.target_met is not False:
            return None
        cap = self._life.options.max_rank
        capped = cap is not None and self.rank >= cap
        return "max_rank" if capped else "earlier_updates"

    def warn_if_target_missed(self) -> None:
        """Log a warning when the target error is not met, with its cause."""
        options = self._life.options
        cause = {
            None: None,
            "max_rank": f"max_rank={options.max_rank} cuts more than the target allows",
            "earlier_updates": "what earlier updates discarded already exceeds the "
            "target's budget (removed, windowed-out or forgotten snapshots shrank the budget)",
        }[self.target_missed_by]
        if cause is not None:
            logger.warning(
                "the target error %.3g (%s) is not met: the bound is %.3g in that measure "
                "(%s)", options.target_error, options.error_measure, self.error_in_measure,
                cause,
            )
