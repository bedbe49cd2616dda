"""Command line: ``contact billet --out DIR`` runs the paper's study of the billet.

Progress goes to stderr: log messages (INFO by default, DEBUG with ``--verbose``, only
warnings with ``--quiet``) and a tqdm bar per method. stdout receives only the final
summary table.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from .result import IterationState

__all__ = ["main"]

log = logging.getLogger(__name__)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="contact",
        description="Space-time LATIN solvers for the billet pushed into a conical die.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser(
        "billet",
        help="run LATIN, LATIN-P3 and LATIN-PGD against the reference solver and write "
        "Figs. 5-9 (PNG) and summary.json",
    )
    b.add_argument("--out", required=True, help="output directory")
    b.add_argument("--refine", type=int, default=1, help="mesh refinement factor (1)")
    b.add_argument("--dt", type=float, default=5e-3, help="time step (5e-3 s)")
    b.add_argument("--tol", type=float, default=1e-6, help="stopping indicator (1e-6)")
    b.add_argument("--level", type=float, default=1e-4,
                   help="indicator level of the CPU-time comparison (1e-4)")
    b.add_argument("--trunc", type=float, default=None,
                   help="relative truncation of LATIN-PGD, in the indicator's metric "
                        "(default: tol / 10, with which it reaches tol)")
    b.add_argument("--fine-trunc", type=float, default=1e-5,
                   help="second LATIN-PGD run with this truncation; 0 to skip (1e-5)")
    b.add_argument("--max-iter", type=int, default=400, help="iterations per method (400)")
    b.add_argument("--quiet", action="store_true",
                   help="only warnings on stderr (no progress messages, no progress bar) "
                   "and no table on stdout")
    b.add_argument("--verbose", action="store_true",
                   help="also log debug messages (the indicator every 50 iterations)")
    return parser


class _Bar:
    """Per-iteration callback drawing one method's tqdm bar on stderr.

    The bar appears at the first iteration, after the messages of the solver's setup.
    """

    def __init__(self, label: str, total: int) -> None:
        self._label = label
        self._total = total
        self._bar: Any = None

    def __call__(self, state: IterationState) -> None:
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=self._total, desc=f"{self._label:>28s}", unit="it",
                             leave=True, file=sys.stderr)
        self._bar.set_postfix(indicator=f"{state.indicator:.2e}", basis=state.basis_size,
                              refresh=False)
        self._bar.update(1)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


@contextmanager
def _logging(level: int, *, bars: bool) -> Iterator[None]:
    """Send the ``contact`` loggers to stderr at ``level`` for the duration of a command.

    With ``bars``, records are written through ``tqdm.write`` so that they do not break a
    progress bar. The handler and the level are removed again on exit.
    """
    logger = logging.getLogger("contact")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s",
                                           datefmt="%H:%M:%S"))
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        if bars:
            from tqdm.contrib.logging import logging_redirect_tqdm

            with logging_redirect_tqdm(loggers=[logger]):
                yield
        else:
            yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``contact`` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    if args.quiet:
        level = logging.WARNING
    else:
        level = logging.DEBUG if args.verbose else logging.INFO
    from .errors import ContactError

    with _logging(level, bars=not args.quiet):
        log.info("contact billet: writing Figs. 5-9 and summary.json into %s", args.out)
        from .study import billet_study  # imports matplotlib

        try:
            summary = billet_study(
                args.out,
                refine=args.refine,
                dt=args.dt,
                tol=args.tol,
                level=args.level,
                trunc=args.trunc,
                fine_trunc=args.fine_trunc or None,
                max_iter=args.max_iter,
                progress=None if args.quiet else _Bar,
            )
        except ContactError as exc:
            sys.stderr.write(f"contact: error: {exc}\n")
            return 2
    if not args.quiet:
        sys.stdout.write(_table(summary) + "\n")
    return 0


def _table(summary: dict[str, Any]) -> str:
    """Return the summary table printed by ``contact billet``.

    Where a number does not exist, a word stands in its place and a note under the table
    says why: ``never`` for a method that did not reach the indicator level, ``full``
    for the basis of the full-field method.
    """
    head = (f"{'method':<28s} {'iter':>5s} {'it@lvl':>6s} {'cpu@lvl(s)':>10s} "
            f"{'basis':>5s} {'opt':>4s} {'mem(kB)':>8s} {'err u':>9s} {'err f':>9s}")
    lines = [head, "-" * len(head)]
    never, full = [], []
    for r in summary["table"]:
        it_lvl = r["iterations_to_level"]
        cpu = r["cpu_time_to_level_s"]
        basis = r["final_basis_size"]
        if it_lvl is None:
            never.append(r["method"])
        if basis is None:
            full.append(r["method"])
        lines.append(
            f"{r['method']:<28s} {r['iterations']:>5d} "
            f"{'never' if it_lvl is None else str(it_lvl):>6s} "
            f"{'-' if cpu is None else f'{cpu:.3f}':>10s} "
            f"{'full' if basis is None else str(basis):>5s} "
            f"{r['optimal_svd_size']:>4d} {r['memory_bytes'] / 1e3:>8.1f} "
            f"{r['error_u_vs_reference']:>9.2e} {r['error_lambda_vs_reference']:>9.2e}"
        )
    lines.append(f"full space-time field: {summary['full_field_bytes'] / 1e3:.1f} kB")
    lines.append(f"iter: iterations run (to --tol {summary['tol']:g} or --max-iter); it@lvl, "
                 f"cpu@lvl: to indicator {summary['level']:g} (process time, setup "
                 "included); basis: final space modes; opt: optimal SVD size of the "
                 "reference correction at the method's truncation (in the indicator "
                 "metric); mem: displacement representation; err u, err f: relative "
                 "errors of the displacements and contact forces against the reference")
    for method in never:
        lines.append(f"{method}: it@lvl 'never', cpu@lvl '-': the indicator did not reach "
                     f"the level {summary['level']:g} within the iterations run")
    for method in full:
        lines.append(f"{method}: basis 'full': no basis, the full space-time field is "
                     "solved for")
    return "\n".join(lines)
