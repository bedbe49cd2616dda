"""How the ``streamsvd`` command prints its results on stdout.

A command's result is the only thing written to stdout (see :mod:`streamsvd.cli`): the
JSON summary of ``ingest`` and ``info --json`` (:func:`print_json`), the text report of
``info`` (:func:`print_info`) and the verdict of ``check`` (:func:`print_check`).

Only the standard library is imported here (see :mod:`streamsvd.cli`).
"""

from __future__ import annotations

import json
from typing import Any

from streamsvd.cli.types import CONVERGE
from streamsvd.cli.wording import in_cli_words

__all__ = ["print_check", "print_info", "print_json"]


def print_json(summary: dict[str, Any]) -> None:
    """Print a store's summary (:func:`streamsvd.stream.summary_of`) as indented JSON."""
    print(json.dumps(summary, indent=2))


def print_info(summary: dict[str, Any]) -> None:
    """Print the text report of ``streamsvd info`` from a store's summary."""
    opts = summary["options"]
    sweeps = CONVERGE if opts["sweeps"] is None else opts["sweeps"]
    print(f"store         {summary['store']}")
    source = summary["source"]
    if source is not None:
        n, m = source["shape"]
        where = "" if source["resolved"] in (None, source["path"]) else f", {source['resolved']}"
        print(f"source        {source['description']} ({n} x {m}){where}")
    print(f"inner product {summary['inner']}")
    print(f"snapshots     n = {summary['n']}, absorbed {summary['n_seen']} "
          f"(source offset {summary['source_offset']}) in {summary['updates']} "
          f"update{'' if summary['updates'] == 1 else 's'}")
    print(f"rank          {summary['rank']}  (rule {opts['rule']}, sweeps {sweeps}, "
          f"eps {opts['eps']}, rtol {opts['rtol']}, max_rank {opts['max_rank']}, "
          f"oversampling {opts['oversampling']})")
    if opts.get("window") is not None or opts.get("forget", 1.0) != 1.0:
        print(f"window        {opts.get('window') or 'all'} snapshots (forget "
              f"{opts.get('forget', 1.0)}); {summary['n_absorbed']} absorbed, "
              f"{summary['n_absorbed'] - summary['n_seen']} removed")
    print("final sweeps  " + (
        "converged: the expansion is the SVD of what was absorbed" if summary["finalized"]
        else "not run: the expansion is as streamed (`streamsvd ingest --resume` without "
        "--final-sweeps none converges it)"))
    print(f"error bound   ||A - U V^T||_F <= {summary['error_bound']:.3e}")
    if opts.get("target_error") is not None:
        met = "met" if summary["target_met"] else "NOT met (" + {
            "max_rank": "--max-rank cuts more than the target allows",
            "earlier_updates": "what earlier updates discarded exceeds the budget now: "
            "removed, windowed-out or forgotten snapshots shrank it",
        }[summary["target_missed_by"]] + ")"
        print(f"target error  {opts['target_error']:.3e} ({opts['error_measure']}): bound "
              f"{summary['error_in_measure']:.3e} in that measure, {met}")
    print(f"orthogonality ||U^T M U - I||_2 = {summary['orthogonality']:.2e}")
    dyn = summary.get("dynamics") or {}
    starts = len(dyn.get("trajectory_starts", []))
    print("dynamics      " + (
        f"recorded ({starts} trajector{'y' if starts == 1 else 'ies'}): `streamsvd dmd "
        "STORE`" if dyn.get("recorded") else
        "not recorded" + ("; `streamsvd dmd STORE` reads the right vectors"
                          if summary["options"].get("right_vectors") else "")))
    head = ", ".join(f"{a:.4g}" for a in summary["amplitudes_head"])
    print(f"amplitudes    {head}{', ...' if summary['rank'] > 10 else ''}")


def print_check(report: Any) -> None:
    """Print the verdict of ``streamsvd check``: each problem, or what verified.

    Parameters
    ----------
    report : streamsvd.store.CheckReport
        What :func:`streamsvd.parallel.cluster.check_store` found.
    """
    for problem in report.problems:
        print(f"damaged: {in_cli_words(problem)}")
    if report.problems:
        return
    for line in report.verified:
        print(f"STORE {report.store}: {line}")
