"""How much of the budget a block may set aside before the cut.

An exact update with a ``mean_l2`` or ``relative`` target rejects the weakest directions
of its block's residual on the residual's Gram
(:func:`streamsvd.linalg.blocks.set_aside`) while their energy, rounding counted, fits a
share of the growth of the squared budget in this update: :func:`set_aside_budget`
sizes it (the theory page ``docs/theory/gram-path.md``, "At tight targets").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from streamsvd._util.scaling import pow2_exponent, safe_m_norms
from streamsvd.engine.state import State, StepOptions
from streamsvd.linalg.slices import SLICE

__all__ = ["UNIT_FLOAT64", "set_aside_budget", "sets_aside"]

# the share of the budget's growth in an update that a block may spend on directions set
# aside on its residual's Gram (streamsvd.linalg.blocks.set_aside), before the cut; for
# snapshots stored coarser than float64 whose rounding (u^2 of their energy) reaches
# _NEAR_PRECISION of that growth, _ROUNDED_ASIDE_SHARE (heat in float32 at mean_l2 1e-6,
# where the rounding is 0.24-0.4 of it: HAPOD's modes at 0.1 with updates of 10, 91 or
# 668 columns since a cut's cross term with what was set aside counts only the cut's part
# in the columns before the update (streamsvd.engine.bound), one more at 0.2 with one
# trajectory per update, and at 0.1 with updates of 10 before that; Burgers at relative
# 1e-6, where it is 0.019, took one more mode than HAPOD's at 0.05)
_ASIDE_SHARE = 0.003
_ROUNDED_ASIDE_SHARE = 0.1
_NEAR_PRECISION = 0.1
# a block taken in slices (streamsvd.linalg.slices: at least two, of SLICE columns) is
# near its precision from a hundredth of the growth on: its rounding spans up to b
# directions, set aside or cut in the update that brought it. Such a block sets aside
# the share its rounding takes (at most _ROUNDED_ASIDE_SHARE): what is set aside beyond
# the rounding is budget the final cut no longer has (Burgers at relative 1e-6, where the
# rounding is 0.019 of the growth, updates of 674 columns: a tenth kept 146 modes
# against HAPOD's 145, the rounding's share 145 in 0.66-0.81x HAPOD's time; at mean_l2 1e-6,
# 0.011, 140 against 141; heat at relative 1e-6, 26 against 27; updates of 10 or 101
# columns took two more modes at the tenth, so narrower blocks are near only from a
# tenth on, where the share is the tenth)
_NEAR_PRECISION_WIDE = 0.01
_WIDE = 2 * SLICE
#: The unit roundoff of float64, the compressor's working precision
UNIT_FLOAT64 = float(np.finfo(np.float64).eps) / 2


def set_aside_budget(opts: StepOptions, b: int, *, unit: float = UNIT_FLOAT64,
                     state: State | None = None, X: np.ndarray | None = None
                     ) -> tuple[float, float]:
    """Return the energy ``(e0, e1)`` a block of ``b`` snapshots may set aside.

    With a ``mean_l2`` or ``relative`` target the squared budget grows in this update by
    ``(share target)^2 b`` or ``(share target)^2 ||X||^2``; ``_ASIDE_SHARE`` of it may be
    rejected on the residual's Gram (:func:`streamsvd.linalg.extend.extend_basis`), its
    rounding counted, so that directions far below the target are never orthonormalised.
    What is set aside is discarded like any rejected residual (its norm enters ``d_t``)
    and the cut that follows is sized after it. The share is small because what is set
    aside is paid again in later bounds (the cross term ``o_t rho`` of
    :mod:`streamsvd.engine.bound`, ``o_t`` a later cut's norm in the columns before it).

    Snapshots whose source has a unit roundoff ``u = unit`` above float64's (float32)
    carry their rounding in every direction of the block, of energy up to about
    ``u^2 ||X||_M^2``, which the cut would discard after orthonormalising it. When that
    energy reaches ``_NEAR_PRECISION`` of the growth (the target is near the data's own
    precision; ``u^2 / (share target)^2`` for a relative target, and for ``mean_l2``
    with ``||X||_M^2 / b`` taken as the mean energy of the snapshots absorbed before,
    ``||R||^2 / m`` of ``state``, or of the block ``X`` in the first update), or
    ``_NEAR_PRECISION_WIDE`` of it for a block wide enough to be taken in slices, the
    share is the rounding's own share of the growth, at most ``_ROUNDED_ASIDE_SHARE``
    (setting aside more than the rounding spends budget that the final cut then lacks).
    An absolute target, a rank cap alone and no cut set nothing aside.
    """
    trunc = opts.truncation
    if trunc.target is None or not sets_aside(opts):
        return (0.0, 0.0)
    se = trunc.share * trunc.target
    share = _ASIDE_SHARE
    if unit > UNIT_FLOAT64:
        rounding = _rounding_share(trunc.measure, unit, se, state, X, opts.inner)
        if rounding >= (_NEAR_PRECISION_WIDE if b >= _WIDE else _NEAR_PRECISION):
            share = min(_ROUNDED_ASIDE_SHARE, rounding)
    rate = share * se * se
    return (rate * b, 0.0) if trunc.measure == "mean_l2" else (0.0, rate)


def sets_aside(opts: StepOptions) -> bool:
    """Whether a block may set anything aside under ``opts`` (:func:`set_aside_budget`).

    A ``mean_l2`` or ``relative`` target whose streaming share squares within the range.
    """
    trunc = opts.truncation
    if trunc.target is None or trunc.measure not in ("relative", "mean_l2"):
        return False
    return 0.0 < trunc.share * trunc.target < 2.0**400


def _rounding_share(measure: str, unit: float, se: float, state: State | None,
                    X: np.ndarray | None, inner: Any) -> float:
    """Return ``u^2 ||X||_M^2`` over the budget's growth (:func:`set_aside_budget`), 0 when unknown.

    With ``mean_l2`` the snapshots' mean energy is the state's, ``||R||^2 / m``; before
    the first update, the block's (its ``M``-norms: one product with ``M``, once).
    """
    if measure == "relative":
        return (unit / se) ** 2
    if state is not None and state.m > 0 and state.R.size:
        e = pow2_exponent(state.R)  # ||R||^2 / m against se^2, scaled: any amplitude
        mean = float(np.linalg.norm(np.ldexp(state.R, -e))) ** 2 / state.m
        scaled = math.ldexp(se, -e)
        ratio = mean * (unit / scaled) ** 2 if scaled > 0 else math.inf
    elif X is not None and X.size:
        with np.errstate(over="ignore", invalid="ignore"):
            ratio = float(np.mean((safe_m_norms(X, inner) * (unit / se)) ** 2))
    else:
        return 0.0
    return ratio if math.isfinite(ratio) else math.inf
