"""The guaranteed error bound of a compressor, kept on the scale of norms.

Let ``A_t`` be everything a compressor received after ``t`` updates, ``K_t = U V^T`` its
expansion and ``E_t = A_t - K_t`` (norms are Frobenius norms in the inner product ``M``,
``||X||^2 = trace(X^T M X)``). Update ``t`` discards ``D_t`` (truncated terms and rejected
residuals), so ``E_t = E_{t-1} + D_t`` (``E_{t-1}`` padded with zero columns) and

    ||E_t||^2 = ||E_{t-1}||^2 + ||D_t||^2 + 2 <E_{t-1}, D_t>.

Theorem. With ``d_t = ||D_t||`` (computed exactly, see below), ``o_t = ||D_t P_t|| <=
d_t`` its norm in the columns received before update ``t`` (``P_t`` keeps those columns;
``o_t = d_t`` where it is not measured) and the recursion

    b_t^2 = b_{t-1}^2 + d_t^2 + 2 min(c_{t-1}, o_t b_{t-1}, k_{t-1} + o_t rho_{t-1}),
    k_t   = k_{t-1} + ||V_kept^T V_cut||_*,
    c_t   = k_t + sum_s d_rej,s ||B_s||,
    rho_t = sqrt(rho_{t-1}^2 + d_rej,t^2),

``||E_t|| <= b_t`` for every ``t``. ``E_{t-1}`` (padded) is zero in the columns the
update appends, so ``<E_{t-1}, D_t> = <E_{t-1}, D_t P_t>`` is at most ``o_t ||E_{t-1}||``
by Cauchy-Schwarz. For an update that appends columns (``absorb``, ``merge``) split
``E_{t-1} = T + J``: ``J`` the residuals rejected so far, ``T`` the truncations. The
rejected residuals of an update live in its own new columns, where ``E_{t-1}`` is zero, so
only a truncation ``D_t = U_cut V_cut^T`` meets ``E_{t-1}``: it meets ``T`` only through
the couplings ``V_kept^T V_cut`` of the truncations before it (``k`` accumulates their
nuclear norms), and ``J`` either through the residuals rejected from earlier blocks
``B`` (at most ``sum d_rej ||B||``) or, by Cauchy-Schwarz, by at most
``||J|| ||D_t P_t|| <= rho o_t``: the rejected residuals of different updates lie in
distinct columns, so ``||J|| = rho``. Hence the cross term is at most ``c_{t-1}`` and at
most ``k_{t-1} + o_t rho_{t-1}``; the second is the smaller where truncations happen at
convergence (``k = 0``) and the rejected residuals are small beside the snapshots, as in
a stream of nearly collinear time steps.

``o_t`` is measured for an absorbed block (:func:`streamsvd.engine.update.plan_absorb`):
its right factor is ``blockdiag(Y, I_b) K`` with ``Y`` orthonormal, so a cut term, of
``M``-orthonormal left vector and right vector ``blockdiag(Y, I_b) K z_i``, has the norm
``||K_old z_i||`` in the columns before (``K_old`` the rows ``Y`` multiplies) and, the cut
terms' left vectors being orthonormal, ``o_t^2 = sum_cut ||K_old z_i||^2``: small when
the cut terms come from the block itself (the rounding of ``float32`` snapshots, cut in
the update that brought it), so that what earlier blocks set aside (``rho``) then costs
little in later bounds. A merge (whose account before the update also holds the merged
expansion's error, in its new columns), ``finalize`` and the Gram path
(:mod:`streamsvd.engine.update_gram`) take ``o_t = d_t``. An update that overlaps earlier
columns (``add``) uses the triangle inequality, ``b_t = b_{t-1} + d_t``, and sets ``c_t = k_t =
inf``; a removal sets them to ``inf`` too (the couplings are not known on the remaining
columns), and keeps ``rho`` (a restriction never increases a norm). When every
truncation happens at convergence and nothing is rejected the bound is the Pythagorean
``sqrt(sum d_t^2)``; it is never worse than ``sum d_t``. Rounding errors (of order
``eps ||A||``) are not included.

``d_t`` is exact, not an estimate: a block's rejected residuals ``r_k`` occupy distinct
columns (``d^2 = sum ||r_k||^2``); an increment's rejected residuals share the same
columns, so ``d^2 = sum_ij (R^T M R)_ij (V^T V)_ij`` from the two small Gram matrices; the
residuals are made ``M``-orthogonal to every kept direction, so the cut terms and the
rejected residuals are orthogonal and their energies add.

Every quantity is kept as a norm (``b``, ``sqrt(c)``, ``sqrt(sum d^2)``) and combined with
scaled formulas, so amplitudes up to 1e300 give a finite bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from streamsvd._util.scaling import pow2_exponent

__all__ = ["Bound"]


def _sqrt_sum_sq(*xs: float) -> float:
    """``sqrt(sum x_i^2)`` without overflow (``inf`` if any is ``inf``)."""
    return math.hypot(*xs)


@dataclass(frozen=True)
class Bound:
    """The error-bound account of a compressor (theorem in the module docstring).

    Attributes
    ----------
    bound : float
        ``b_t``, the guaranteed bound on ``||A - U V^T||``.
    coupling_root : float
        ``sqrt(c_t)``; ``inf`` once an overlapping ``add`` happened.
    discarded : float
        ``sqrt(sum_t d_t^2)``, the norm-equivalent of all discarded energy.
    cut_coupling_root : float
        ``sqrt(k_t)``, the truncations' share of ``c_t`` (``inf`` with it).
    rejected : float
        ``rho_t``, the norm of every residual rejected so far.
    """

    bound: float = 0.0
    coupling_root: float = 0.0
    discarded: float = 0.0
    cut_coupling_root: float = 0.0
    rejected: float = 0.0

    def combine(self, other: Bound) -> Bound:
        """Return the account of two expansions of disjoint column sets, side by side."""
        return Bound(*(_sqrt_sum_sq(a, b) for a, b in zip(self.to_array(), other.to_array(),
                                                           strict=True)))

    def step(
        self,
        discarded: float,
        coupling_root: float,
        *,
        overlapping: bool,
        rejection_root: float = 0.0,
        rejected: float = 0.0,
        discarded_before: float | None = None,
    ) -> Bound:
        """Advance by a discard of norm ``discarded`` (``d_t``).

        Parameters
        ----------
        discarded : float
            ``d_t = ||D_t||``.
        coupling_root : float
            ``sqrt(||V_kept^T V_cut||_*)`` of this update's truncation.
        overlapping : bool
            Whether the update touched columns received before (``add``).
        rejection_root : float
            ``sqrt(d_rej ||B||)`` for the residuals this update rejected.
        rejected : float
            ``d_rej``, the norm of the residuals this update rejected (part of
            ``discarded``).
        discarded_before : float, optional
            ``o_t = ||D_t P_t||``, the part of the discard in the columns received
            before this update (at most ``d_t``); by default ``d_t``.
        """
        d = float(discarded)
        rho = _sqrt_sum_sq(self.rejected, rejected)
        if overlapping:
            return Bound(self.bound + d, math.inf, _sqrt_sum_sq(self.discarded, d),
                         math.inf, rho)
        old = None if discarded_before is None else np.array([discarded_before])
        return Bound(
            float(self.after(np.array([d]), overlapping=False, before=old)[0]),
            _sqrt_sum_sq(self.coupling_root, coupling_root, rejection_root),
            _sqrt_sum_sq(self.discarded, d),
            _sqrt_sum_sq(self.cut_coupling_root, coupling_root),
            rho,
        )

    def uncoupled(self, bound: float) -> Bound:
        """Return the account with ``bound`` and the couplings unknown (after a removal)."""
        return Bound(bound, math.inf, self.discarded, math.inf, self.rejected)

    def after(self, discarded: np.ndarray, *, overlapping: bool,
              before: np.ndarray | None = None) -> np.ndarray:
        """Return ``b_t`` for each candidate discard norm ``d_t`` in ``discarded``.

        The bound that :meth:`step` gives, for many candidates at once: a truncation
        sizes its cut by it, so that the cut spends the budget by the rule the bound
        then follows (the triangle inequality after an ``add`` or a removal, whose
        coupling account is ``inf``; the Pythagorean rule only where the couplings of
        the cuts before vanish). Computed on a common power-of-two scale, so that
        amplitudes up to 1e300 give a finite result. ``before`` holds each candidate's
        ``o_t``, the part of the discard in the columns received before the update
        (module docstring; ``d_t`` itself when not given).
        """
        d = np.asarray(discarded, dtype=np.float64)
        b = self.bound
        if overlapping:
            return b + d
        e = pow2_exponent(np.append(d, b))
        bs, ds = math.ldexp(b, -e), np.ldexp(d, -e)
        olds = ds if before is None else np.minimum(np.ldexp(before, -e), ds)
        with np.errstate(over="ignore"):  # squares beyond the range: the other terms
            cs2 = _scaled_square(self.coupling_root, e)
            ks2 = _scaled_square(self.cut_coupling_root, e)
            rho_d = olds * math.ldexp(self.rejected, -e) if self.rejected else 0.0 * ds
            cross = np.minimum(np.minimum(cs2, olds * bs), ks2 + rho_d)
            return np.ldexp(np.sqrt(bs * bs + ds * ds + 2.0 * cross), e)

    def to_array(self) -> np.ndarray:
        """Encode as five floats (for a store)."""
        return np.array([self.bound, self.coupling_root, self.discarded,
                         self.cut_coupling_root, self.rejected])

    @classmethod
    def from_array(cls, a: np.ndarray) -> Bound:
        """Decode :meth:`to_array`, or the three floats of a store written before.

        Such a store kept ``c`` whole: ``k <= c`` and ``rho <= sqrt(sum d^2)`` stand in for
        the parts it did not keep (valid, as loose as the bound was then).
        """
        x = [float(v) for v in a[:5]]
        if len(x) == 3:
            x += [x[1], x[2]]
        return cls(*x)


def _scaled_square(root: float, e: int) -> float:
    """``(root 2^-e)^2``, ``inf`` where ``root`` is."""
    if math.isinf(root):
        return math.inf
    r = math.ldexp(root, -e)
    return r * r  # inf past the range, never an exception
