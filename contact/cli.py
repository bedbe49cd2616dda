"""Command line: ``contact billet --out DIR`` runs the paper's study of the billet."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from typing import Any

from .latin import IterationState

__all__ = ["main"]


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
    b.add_argument("--trunc", type=float, default=1e-4,
                   help="relative truncation of LATIN-PGD (1e-4)")
    b.add_argument("--fine-trunc", type=float, default=1e-6,
                   help="second LATIN-PGD run with this truncation; 0 to skip (1e-6)")
    b.add_argument("--max-iter", type=int, default=400, help="iterations per method (400)")
    b.add_argument("--quiet", action="store_true", help="no progress bar and no table")
    b.add_argument("--verbose", action="store_true", help="log the solvers' progress")
    return parser


def _progress_factory() -> Callable[[str, int], Callable[[IterationState], Any]]:
    from tqdm.auto import tqdm

    def factory(label: str, total: int) -> Callable[[IterationState], Any]:
        bar = tqdm(total=total, desc=f"{label:>28s}", unit="it", leave=True)

        def update(state: IterationState) -> None:
            bar.update(1)
            bar.set_postfix(indicator=f"{state.indicator:.2e}", basis=state.basis_size)
            if state.iteration >= total:
                bar.close()

        return update

    return factory


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``contact`` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.verbose:
        logging.getLogger("contact").setLevel(logging.INFO)
    from .errors import ContactError
    from .study import billet_study

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
            progress=None if args.quiet else _progress_factory(),
        )
    except ContactError as exc:
        sys.stderr.write(f"contact: error: {exc}\n")
        return 2
    if not args.quiet:
        sys.stdout.write(_table(summary) + "\n")
    return 0


def _table(summary: dict[str, Any]) -> str:
    head = (f"{'method':<28s} {'iter':>5s} {'it@lvl':>6s} {'cpu@lvl(s)':>10s} "
            f"{'basis':>5s} {'opt':>4s} {'mem(kB)':>8s} {'err u':>9s}")
    lines = [head, "-" * len(head)]
    for r in summary["table"]:
        cpu = r["cpu_time_to_level_s"]
        cpu_text = "-" if cpu is None else f"{cpu:.3f}"
        lines.append(
            f"{r['method']:<28s} {r['iterations']:>5d} {str(r['iterations_to_level']):>6s} "
            f"{cpu_text:>10s} {str(r['final_basis_size']):>5s} "
            f"{r['optimal_svd_size']:>4d} {r['memory_bytes'] / 1e3:>8.1f} "
            f"{r['error_u_vs_reference']:>9.2e}"
        )
    lines.append(f"full space-time field: {summary['full_field_bytes'] / 1e3:.1f} kB")
    return "\n".join(lines)
