"""``streamsvd dmd STORE``: the certified DMD of a store's snapshots.

Opens STORE read-only (:func:`~streamsvd.cli.reading.open_readonly`), answers its
``dmd`` (:mod:`streamsvd.stream.dynamics`) and prints the eigenvalues with their residual
bounds (text, or ``--json``); ``--modes OUT`` writes the modes, ``--forecast N OUT`` the
next ``N`` snapshots, to ``.npz``. A store that keeps no right vectors is refused, naming
the option that records them.

Only the standard library is imported at module level (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from streamsvd.cli.parsing import add_json, add_rtol, load_inner
from streamsvd.cli.types import nonnegative_float, positive_float, positive_int
from streamsvd.errors import InputError

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``streamsvd dmd`` to its parser (STORE, --inner are there)."""
    cut = parser.add_mutually_exclusive_group()
    cut.add_argument("--rank", metavar="K", type=positive_int,
                     help="keep at most K directions of the pairs' first snapshots "
                     "(default: their numerical rank)")
    add_rtol(cut, help="keep the directions with singular value > R times the largest "
             "(default: the numerical rank)")
    parser.add_argument("--model-error", metavar="D", type=nonnegative_float, default=0.0,
                        help="model error D >= ||A X0 - X1||_F of the operators A the "
                        "bounds are about, in the norm of --inner; measurement noise "
                        "belongs here (default: 0, data exactly linear)")
    parser.add_argument("--dt", metavar="DT", type=positive_float,
                        help="time step between snapshots: also print the continuous-time "
                        "eigenvalues log(lambda)/DT (default: none)")
    add_json(parser, what="the result", otherwise="a text table")
    parser.add_argument("--modes", metavar="OUT",
                        help="write the modes (n x r, complex) and eigenvalues to OUT, "
                        ".npz (default: none)")
    parser.add_argument("--forecast", metavar=("N", "OUT"), nargs=2,
                        help="write the N snapshots after the last one absorbed "
                        "(n x N) to OUT, .npz (default: none)")


def run(args: Any) -> int:
    """Run ``streamsvd dmd``: print the eigenvalues and bounds, write what is asked."""
    from streamsvd.cli.printing import print_json
    from streamsvd.cli.reading import open_readonly

    steps = None
    if args.forecast is not None:
        count, out = args.forecast
        try:
            steps = int(count)
        except ValueError:
            steps = -1
        if steps < 1:
            raise InputError(f"--forecast N OUT needs a positive integer N; got {count!r}.")
        _check_npz(out, "--forecast")
    if args.modes is not None:
        _check_npz(args.modes, "--modes")
    want_basis = args.modes is not None or steps is not None
    with open_readonly(args.store, inner=load_inner(args)) as sc:
        if not sc.options.right_vectors:
            raise InputError(
                f"STORE {args.store} keeps no right vectors, from which `dmd` reads the "
                "snapshot pairs; write it with `streamsvd ingest --dynamics`."
            )
        res = sc.dmd(rank=args.rank, rtol=args.rtol, model_error=args.model_error,
                     dt=args.dt, modes=want_basis)
        recorded = bool(sc.options.dynamics)
    import numpy as np

    if args.modes is not None:
        np.savez(args.modes, modes=res.modes, eigenvalues=res.eigenvalues,
                 residual_bounds=res.residual_bounds, amplitudes=res.amplitudes)
    if steps is not None:
        np.savez(args.forecast[1], forecast=res.forecast(np.arange(1, steps + 1)))
    if args.json:
        print_json({"store": str(args.store), "dynamics_recorded": recorded,
                    **res.to_dict()})
        return 0
    print(f"DMD of {args.store}: {res.pairs} pairs, rank {res.rank}, error bound "
          f"{res.error_bound:.3e}, model error {res.model_error:.3e}")
    cont = res.continuous_eigenvalues if res.dt is not None else None
    head = "   |lambda|   lambda                      eta"
    print(head + ("        log(lambda)/dt" if cont is not None else ""))
    for i, (lam, eta) in enumerate(zip(res.eigenvalues, res.residual_bounds, strict=True)):
        line = (f"{i:3d} {abs(lam):9.6f}  {lam.real:+.6e} {lam.imag:+.6e}i  "
                f"{eta:.2e}")
        if cont is not None:
            line += f"  {cont[i].real:+.4e} {cont[i].imag:+.4e}i"
        print(line)
    for what, path in (("modes", args.modes),
                       ("forecast", None if steps is None else args.forecast[1])):
        if path is not None:
            print(f"wrote {path} ({what})")
    return 0


def _check_npz(path: str, flag: str) -> None:
    """Refuse an output that is not .npz."""
    if Path(path).suffix != ".npz":
        raise InputError(f"{flag} writes a .npz file; got {Path(path).name!r}.")
