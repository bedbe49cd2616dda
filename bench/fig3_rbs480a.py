"""Figs 2 and 3 of the paper: convergence of the rotation sweeps on rbs480a.

The SVD ``A = Uref diag(s) Vref^T`` of rbs480a (Matrix Market) is computed with LAPACK;
three matrices ``A_mod = Uref diag(s_mod) Vref^T`` share its singular vectors and differ
only by their singular values (Fig. 2):

* ``original``: ``s_mod = s``.
* ``medium slope``: log-linear, ``s_mod_i = s_1 * 10^(-D i / (N - 1))``, ``i = 0 .. N-1``,
  with ``D = --medium-decades`` (8: from ``s_1`` down to ``1e-8 s_1``; successive ratio
  ``10^(-8/479) = 0.962`` for N = 480).
* ``strong initial slope``: the first ``K = --steep-modes`` (20) values drop by the factor
  ``--steep-ratio`` (0.5) each, ``s_mod_i = s_1 0.5^i`` for ``i < K``; the rest decay
  log-linearly by ``--tail-decades`` (2) decades from ``s_1 0.5^K`` to the last mode
  (successive ratio 0.990).

Each matrix starts from its canonical expansion ``U = I, V = A_mod^T``
(``streamsvd.Expansion.canonical``) and is compressed with ``streamsvd.linalg.compress`` for
both rules (``"paper"``, ``"jacobi"``). The result after ``k`` sweeps is obtained by a
separate deterministic run with ``max_sweeps=k`` for ``k`` in a geometric list (sweep
``k`` of a longer run is the same computation); once a run reports convergence the larger
``k`` give the same expansion and are not rerun. The default stopping threshold
``tol = sqrt(m) eps`` is kept.

The error of eq. (20) is ``E = ||eps||_F`` with ``eps_i = uref_i s_mod_i vref_i^T - u_i v_i^T``
for every mode ``1 <= i <= p``, read as ``E^2 = sum_i ||eps_i||_F^2`` (the sum of the
``eps_i`` themselves is ``A_mod - U V^T = 0`` for every iterate). Singular vectors are
defined up to a common sign of ``(u_i, v_i)``; each computed pair is flipped so that
``(uref_i | u_i) >= 0`` and then ``||eps_i||_F^2`` is evaluated without cancellation as
``||x||^2 ||b||^2 + ||c||^2 ||y||^2 + 2 (x|c)(b|y)`` with ``a = uref_i``,
``b = s_mod_i vref_i``, ``c = u_i``, ``d = v_i``, ``x = a - c``, ``y = b - d``
(no ``n x m`` matrix is formed). The indicator ``I`` (root mean square of the sweep's
``alpha_ij``) comes from ``CompressResult.indicator`` of the longest run.

Writes ``fig2_rbs480a_spectra.png``, ``fig3_rbs480a.png`` and ``fig3_rbs480a.json``.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import scipy.linalg as sla
from _common import Run, load_rbs480a, machine_info, out_dir, print_table, pyplot

import streamsvd as ss

SWEEP_LIST = (1, 2, 3, 5, 8, 13, 20, 30, 50, 80, 120, 200, 300, 500, 800)
RULES = ("paper", "jacobi")


def configurations(s: np.ndarray, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """The three spectra of Fig. 2 (see the module docstring)."""
    N = s.size
    i = np.arange(N, dtype=float)
    medium = s[0] * 10.0 ** (-args.medium_decades * i / max(N - 1, 1))
    K = min(args.steep_modes, N - 1)
    strong = np.empty(N)
    strong[: K + 1] = s[0] * args.steep_ratio ** i[: K + 1]
    tail = N - 1 - K
    if tail > 0:
        strong[K:] = strong[K] * 10.0 ** (-args.tail_decades * (i[K:] - K) / tail)
    return {"original": s.copy(), "medium slope": medium, "strong initial slope": strong}


def eq20_error(Uref: np.ndarray, s_mod: np.ndarray, Vref: np.ndarray,
               U: np.ndarray, V: np.ndarray) -> float:
    """``E = sqrt(sum_i ||uref_i s_i vref_i^T - u_i v_i^T||_F^2)`` (eq. 20), sign-aligned."""
    p = min(U.shape[1], s_mod.size)
    a, b = Uref[:, :p], Vref[:, :p] * s_mod[:p]
    sign = np.where(np.einsum("ij,ij->j", a, U[:, :p]) < 0.0, -1.0, 1.0)
    c, d = U[:, :p] * sign, V[:, :p] * sign
    x, y = a - c, b - d
    sq = (np.einsum("ij,ij->j", x, x) * np.einsum("ij,ij->j", b, b)
          + np.einsum("ij,ij->j", c, c) * np.einsum("ij,ij->j", y, y)
          + 2.0 * np.einsum("ij,ij->j", x, c) * np.einsum("ij,ij->j", b, y))
    # modes beyond the expansion's rank (none here) would count in full
    missing = float(np.sum(s_mod[p:] ** 2))
    return math.sqrt(max(float(np.sum(sq)), 0.0) + missing)


def run_configuration(A_mod: np.ndarray, Uref: np.ndarray, s_mod: np.ndarray,
                      Vref: np.ndarray, rule: str, sweeps: list[int]) -> dict:
    """Errors E(k) for the runs ``max_sweeps = k`` and the indicator of the longest run."""
    norm = float(np.linalg.norm(s_mod))
    rows = []
    last: ss.CompressResult | None = None
    for k in sweeps:
        if last is not None and last.converged:
            res, seconds = last, float("nan")
        else:
            e = ss.Expansion.canonical(A_mod)
            t0 = time.perf_counter()
            res = ss.compress(e, rule=rule, max_sweeps=k)
            seconds = time.perf_counter() - t0
        E = eq20_error(Uref, s_mod, Vref, res.expansion.U, res.expansion.V)
        amp = res.expansion.amplitudes
        rows.append({
            "max_sweeps": k, "sweeps": res.sweeps, "converged": res.converged,
            "E": E, "E_rel": E / norm,
            "sv_error_rel": float(np.max(np.abs(amp - s_mod[: amp.size]))) / s_mod[0],
            "seconds": seconds,
        })
        last = res
    return {
        "rule": rule,
        "runs": rows,
        "indicator": last.indicator if last is not None else np.zeros(0),
        "max_cosine": last.max_cosine if last is not None else np.zeros(0),
        "converged_after": int(last.sweeps) if last is not None and last.converged else None,
    }


def main(argv: Sequence[str] | None = None) -> dict:
    record = Run("fig3_rbs480a", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="output directory (default bench/results)")
    parser.add_argument("--data", default=None,
                        help="path of rbs480a.mtx (default ../shared/data/rbs480a.mtx)")
    parser.add_argument("--max-sweeps", type=int, default=200,
                        help="largest number of sweeps (runs at 1, 2, 3, 5, 8, ... up to it)")
    parser.add_argument("--size", type=int, default=None,
                        help="use the leading SIZE x SIZE block of the matrix (quick checks)")
    parser.add_argument("--rules", default=",".join(RULES), help="comma-separated rules")
    parser.add_argument("--medium-decades", type=float, default=8.0)
    parser.add_argument("--steep-modes", type=int, default=20)
    parser.add_argument("--steep-ratio", type=float, default=0.5)
    parser.add_argument("--tail-decades", type=float, default=2.0)
    args = parser.parse_args(argv)
    if args.max_sweeps < 1:
        parser.error(f"--max-sweeps must be >= 1; got {args.max_sweeps}")
    if args.size is not None and args.size < 4:
        parser.error(f"--size must be >= 4; got {args.size}")
    out = out_dir(args.out)
    rules = [r.strip() for r in args.rules.split(",") if r.strip()]
    t_start = time.perf_counter()

    A = load_rbs480a(args.data)
    if args.size is not None:
        A = A[: args.size, : args.size]
    Uref, s, Vt = sla.svd(A, lapack_driver="gesdd")
    Vref = Vt.T
    configs = configurations(s, args)
    sweeps = sorted({k for k in SWEEP_LIST if k < args.max_sweeps} | {args.max_sweeps})
    # first call compiles (or loads) the numba kernels; keep it out of the timings
    ss.compress(ss.Expansion.canonical(A[:8, :8]), max_sweeps=1)

    results: dict[str, dict] = {}
    for name, s_mod in configs.items():
        A_mod = (Uref * s_mod) @ Vref.T
        results[name] = {
            "s_mod": s_mod,
            "E0": eq20_error(Uref, s_mod, Vref, np.eye(A.shape[0]), A_mod.T),
            "rules": {rule: run_configuration(A_mod, Uref, s_mod, Vref, rule, sweeps)
                      for rule in rules},
        }

    data = {
        "matrix": str(args.data) if args.data else "../shared/data/rbs480a.mtx",
        "shape": A.shape,
        "sweep_list": sweeps,
        "configuration_parameters": {
            "medium_decades": args.medium_decades, "steep_modes": args.steep_modes,
            "steep_ratio": args.steep_ratio, "tail_decades": args.tail_decades,
        },
        "E_definition": "sqrt(sum_i ||uref_i s_mod_i vref_i^T - u_i v_i^T||_F^2), "
                        "signs of (u_i, v_i) aligned with (uref_i, vref_i); "
                        "E_rel = E / ||s_mod||_2",
        "configurations": results,
        "seconds": time.perf_counter() - t_start,
        "machine": machine_info(),
    }
    _plot_spectra(configs, out / "fig2_rbs480a_spectra.png")
    _plot_convergence(results, out / "fig3_rbs480a.png")
    record.write(out / "fig3_rbs480a.json", data)

    table = []
    for name, r in results.items():
        for rule, rr in r["rules"].items():
            runs = rr["runs"]
            pick = {row["max_sweeps"]: row for row in runs}
            table.append([name, rule, r["E0"] / float(np.linalg.norm(r["s_mod"])),
                          *(pick[k]["E_rel"] if k in pick else float("nan")
                            for k in (1, 5, 20)),
                          runs[-1]["E_rel"], runs[-1]["sweeps"],
                          "yes" if rr["converged_after"] else "no",
                          rr["indicator"][-1] if len(rr["indicator"]) else float("nan")])
    print_table(["configuration", "rule", "E0/|s|", "E(1)", "E(5)", "E(20)", "E(last)",
                 "sweeps", "conv", "I(last)"], table,
                title=f"Fig. 3: relative error E/||s_mod|| of eq. (20) after k sweeps "
                      f"(max_sweeps = {args.max_sweeps}), {A.shape[0]} x {A.shape[1]}")
    print(f"wrote {out / 'fig2_rbs480a_spectra.png'}, {out / 'fig3_rbs480a.png'}, "
          f"{out / 'fig3_rbs480a.json'} in {data['seconds']:.1f} s")
    return data


def _plot_spectra(configs: dict[str, np.ndarray], path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, s_mod in configs.items():
        ax.semilogy(np.arange(1, s_mod.size + 1), s_mod, label=name)
    ax.set_xlabel("mode i")
    ax.set_ylabel(r"singular value $\sigma_i^{\mathrm{mod}}$")
    ax.set_title("Fig. 2: singular values of the three rbs480a configurations")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_convergence(results: dict[str, dict], path: Path) -> None:
    plt = pyplot()
    names = list(results)
    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.8), sharey=True)
    axes = np.atleast_1d(axes)
    styles = {"paper": ("C0", "o"), "jacobi": ("C3", "s")}
    for ax, name in zip(axes, names, strict=True):
        r = results[name]
        norm = float(np.linalg.norm(r["s_mod"]))
        for rule, rr in r["rules"].items():
            col, mk = styles.get(rule, ("C2", "^"))
            k = [0] + [row["sweeps"] for row in rr["runs"]]
            E = [r["E0"] / norm] + [row["E_rel"] for row in rr["runs"]]
            ax.semilogy(k, np.maximum(E, 1e-17), "-", color=col, marker=mk, ms=4,
                        label=rf"$\mathcal{{E}}/\|\sigma\|$, rule={rule}")
            ind = np.asarray(rr["indicator"])
            ax.semilogy(np.arange(1, ind.size + 1), np.maximum(ind, 1e-17), ":", color=col,
                        lw=1.2, label=rf"indicator $\mathcal{{I}}$, rule={rule}")
        ax.set_title(name)
        ax.set_xlabel("sweeps")
        ax.grid(True, which="major", alpha=0.3)
        ax.set_ylim(1e-17, 10.0)
    axes[0].set_ylabel(r"relative error $\mathcal{E}/\|\sigma^{\mathrm{mod}}\|_2$ (eq. 20), "
                       r"indicator $\mathcal{I}$")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9,
               frameon=False)
    fig.suptitle("Fig. 3: convergence of the rotation sweeps on rbs480a "
                 "(canonical start U = I, V = A^T)")
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
