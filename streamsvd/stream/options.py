"""The options of a compressor, defined once.

:class:`CompressorOptions` is the single list of what a :class:`~streamsvd.StreamCompressor`
can be told: it validates them (:meth:`CompressorOptions.validated`), is what a store
records (:meth:`CompressorOptions.as_dict`, :meth:`CompressorOptions.from_stored`), and
derives the step's options (:meth:`CompressorOptions.step_options`). The tree's option
names (:data:`TREE_OPTIONS`) and the compressor's attributes (:func:`option_properties`)
come from its fields, and so do the command line's options (:meth:`CompressorOptions.flag`).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the numerical modules load when options are validated, not imported
    from streamsvd.algebra.inner import InnerProduct
    from streamsvd.engine.state import StepOptions
    from streamsvd.engine.truncation import Truncation

__all__ = [
    "STREAMING_SHARE",
    "TREE_OPTIONS",
    "CompressorOptions",
    "option_properties",
]

_EPS = 2.0**-52  # float64 machine epsilon
# the target error's budget spent while streaming: HAPOD's split at omega = 0.9, whose
# root (here: finalize) spends omega of the budget and the updates before it the rest
STREAMING_SHARE = math.sqrt(1.0 - 0.9**2)
# what a store written before an option existed did (see `from_stored`)
_BEFORE_THE_OPTION = {
    "oversampling": 0, "target_error": None, "error_measure": "relative",
    "streaming_share": 0.9, "dynamics": False,
}


@dataclasses.dataclass(frozen=True)
class CompressorOptions:
    """Options of a :class:`~streamsvd.StreamCompressor` (documented there), validated.

    Build it with :meth:`validated`, which checks every value and resolves the defaults
    that depend on the snapshot size ``n`` (``reject_tol``, ``reorth_tol``).
    """

    eps: float = 0.0
    rtol: float | None = None
    max_rank: int | None = None
    oversampling: int = 10
    rule: str = "paper"
    sweeps: int | None = 1
    reject_tol: float | None = None
    reorth_tol: float | None = None
    right_vectors: bool = True
    commit_every: int | str = 1
    target_error: float | None = None
    error_measure: str = "relative"
    streaming_share: float = STREAMING_SHARE
    window: int | None = None
    forget: float = 1.0
    dynamics: bool = False

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """Return the option names, in the order of the fields."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @staticmethod
    def flag(name: str) -> str:
        """Return the command-line option of the option ``name`` (``max_rank``: ``--max-rank``)."""
        return "--" + name.replace("_", "-")

    @classmethod
    def validated(cls, n: int, **values: Any) -> CompressorOptions:
        """Check ``values`` (option names to values) for snapshots of size ``n``.

        Raises :class:`~streamsvd.errors.InputError` naming the option, what it must be
        and what it got; an unknown name is refused with the known ones.
        """
        import numpy as np

        from streamsvd._util.validation import (
            check_choice,
            check_forget,
            check_nonnegative,
            check_nonnegative_int,
            check_positive_int,
            check_target,
        )
        from streamsvd.errors import InputError
        from streamsvd.linalg.rejection import default_reject_tol
        from streamsvd.linalg.rotations import RULES

        unknown = sorted(set(values) - set(cls.names()))
        if unknown:
            raise InputError(
                f"unknown option {', '.join(f'`{u}`' for u in unknown)}; the options are "
                f"{', '.join(cls.names())}."
            )
        v = {**dataclasses.asdict(cls()), **values}
        eps = check_nonnegative(v["eps"], "eps")
        rtol = None if v["rtol"] is None else check_nonnegative(v["rtol"], "rtol")
        target, measure, share = check_target(
            v["target_error"], v["error_measure"], v["streaming_share"], eps=eps, rtol=rtol
        )
        if not isinstance(v["right_vectors"], bool | np.bool_):
            raise InputError(
                f"`right_vectors` must be True or False; got {v['right_vectors']!r}."
            )
        window = check_positive_int(v["window"], "window", allow_none=True)
        if window is not None and not v["right_vectors"]:
            raise InputError(
                f"`window` needs the right vectors to remove the snapshots that leave it; "
                f"got window={window} with right_vectors=False. Pass "
                "`right_vectors=True`, or use `forget` (which needs none)."
            )
        if not isinstance(v["dynamics"], bool | np.bool_):
            raise InputError(f"`dynamics` must be True or False; got {v['dynamics']!r}.")
        if v["dynamics"] and not v["right_vectors"]:
            raise InputError(
                "`dynamics=True` reads the snapshot pairs from the right vectors; got "
                "right_vectors=False. Pass `right_vectors=True`, or drop `dynamics`."
            )
        return cls(
            eps=eps, rtol=rtol,
            max_rank=check_positive_int(v["max_rank"], "max_rank", allow_none=True),
            oversampling=check_nonnegative_int(v["oversampling"], "oversampling"),
            rule=check_choice(v["rule"], "rule", RULES),
            sweeps=check_positive_int(v["sweeps"], "sweeps", allow_none=True),
            reject_tol=(default_reject_tol(n) if v["reject_tol"] is None
                        else check_nonnegative(v["reject_tol"], "reject_tol")),
            reorth_tol=(10 * n * _EPS if v["reorth_tol"] is None
                        else check_nonnegative(v["reorth_tol"], "reorth_tol")),
            right_vectors=bool(v["right_vectors"]),
            commit_every=_commit_every(v["commit_every"]),
            target_error=target, error_measure=measure, streaming_share=share,
            window=window, forget=check_forget(v["forget"]),
            dynamics=bool(v["dynamics"]),
        )

    @classmethod
    def from_stored(cls, n: int, stored: dict[str, Any]) -> CompressorOptions:
        """Return the options a store recorded (its attribute ``options``), validated.

        Stores written before ``oversampling`` existed truncated to ``max_rank`` at every
        update: they continue so; stores written before ``target_error`` existed have none,
        and those written before ``window`` and ``forget`` take the defaults (no window,
        nothing forgotten).
        """
        return cls.validated(n, **{**_BEFORE_THE_OPTION, **stored})

    def as_dict(self) -> dict[str, Any]:
        """Return the options by name (what a store records, JSON-able)."""
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> CompressorOptions:
        """Return these options with ``changes`` (not validated again: pass valid values)."""
        return dataclasses.replace(self, **changes)

    @property
    def streaming_rank(self) -> int | None:
        """Most terms kept between updates: ``max_rank + oversampling`` (None: no cap)."""
        return None if self.max_rank is None else self.max_rank + self.oversampling

    def truncation(self, *, max_rank: int | None = None, share: float | None = None
                   ) -> Truncation:
        """Return the cut of an update (``max_rank``, ``share``: the streaming ones by default)."""
        from streamsvd.engine.truncation import Truncation

        return Truncation(
            self.eps, self.rtol, self.streaming_rank if max_rank is None else max_rank,
            self.target_error, self.error_measure,
            self.streaming_share if share is None else share,
        )

    def step_options(self, inner: InnerProduct) -> StepOptions:
        """Return the options of the update step (:mod:`streamsvd.engine.update`) in ``inner``."""
        from streamsvd.engine.state import StepOptions

        assert self.reject_tol is not None and self.reorth_tol is not None
        return StepOptions(
            inner=inner, rule=self.rule, sweeps=self.sweeps, truncation=self.truncation(),
            reject_tol=self.reject_tol, reorth_tol=self.reorth_tol,
        )


def _commit_every(value: Any) -> int | str:
    """Return ``commit_every`` validated: an int >= 1, or ``"auto"``."""
    from streamsvd.stream.commits import AUTO

    if isinstance(value, str) and value == AUTO:
        return AUTO
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        from streamsvd.errors import InputError

        raise InputError(
            f"`commit_every` must be an integer >= 1 (updates per commit) or {AUTO!r} "
            f"(commits timed to take about a tenth of the time); got {value!r}."
        )
    return int(value)


TREE_OPTIONS = ("inner",) + tuple(
    name for name in CompressorOptions.names()
    if name not in ("right_vectors", "commit_every", "window", "forget", "dynamics")
)
"""Options forwarded to every compressor of :func:`streamsvd.parallel.tree_compress`."""


def option_properties(cls: type) -> type:
    """Class decorator: a read-only attribute per option, read from ``self.options``."""
    for name in CompressorOptions.names():
        setattr(cls, name, _option_property(name))
    return cls


def _option_property(name: str) -> property:
    """Return the read-only attribute of the option ``name``."""

    def read(self: Any) -> Any:
        return getattr(self.options, name)

    return property(read, doc=f"The ``{name}`` option (see the class's parameters); read-only.")
