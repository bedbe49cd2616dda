"""The paper's application: the billet pushed into a conical die, Figs. 5-9.

Runs the reference solver and LATIN, LATIN-P3 and LATIN-PGD, then writes the figures
(PNG) and the numbers (summary.json) into the output directory::

    python examples/billet.py --out out/billet
    python examples/billet.py --out out/small --dt 0.02 --max-iter 150   # a quick look

The same study is the console command ``contact billet --out DIR``.
"""

from __future__ import annotations

import argparse
import json

import contact


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out/billet")
    parser.add_argument("--dt", type=float, default=5e-3)
    parser.add_argument("--refine", type=int, default=1)
    parser.add_argument("--max-iter", type=int, default=400)
    args = parser.parse_args(argv)
    summary = contact.billet_study(args.out, dt=args.dt, refine=args.refine,
                                   max_iter=args.max_iter)
    rows = {r["method"]: r for r in summary["table"]}
    print(json.dumps(rows, indent=1))
    return summary


if __name__ == "__main__":
    main()
