"""Fig. 1 of the paper: the rank-2 dynamics of eq. (14), checked against F itself.

For several starting points ``(eta_0, alpha_0)`` with ``0 <= alpha_0^2 < eta_0 <= 1``
(inequality 13) the script iterates the recursion (14) with
``streamsvd.pair_dynamics`` and marks each trajectory's asymptotic rate
``eta = delta - sqrt(delta^2 - 1)``. On top it applies ``streamsvd.rotate_pair`` (F,
eqs 5-11) to random rank-2 expansions ``u1 v1^T + u2 v2^T`` (``u1, u2`` orthonormal) built
with exactly that ``(eta_0, alpha_0)``, and records ``eta = ||v2||^2 / ||v1||^2`` and
``alpha = (v1|v2) / (v1|v1)`` after each application: the marks fall on the recursion.
A second set of fully random expansions (random ``v1, v2`` with ``||v1|| >= ||v2||``, signs
chosen so that ``(v1|v2) >= 0`` as eq. 12 assumes) gives the largest deviation between
recursion and iterates.

Writes ``fig1_pair_dynamics.png`` and ``fig1_pair_dynamics.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, print_table, pyplot

import streamsvd as ss

# (eta_0, alpha_0) starting points: equal amplitudes with strong to weak coupling,
# intermediate ratios, and a nearly-orthogonal pair of close amplitudes (the slow case)
STARTS = (
    (1.0, 0.9),
    (1.0, 0.5),
    (0.95, 0.1),
    (0.7, 0.6),
    (0.6, 0.3),
    (0.3, 0.5),
    (0.2, 0.1),
)


def rank2_expansion(
    rng: np.random.Generator, n: int, m: int, eta0: float, alpha0: float
) -> tuple[np.ndarray, ...]:
    """Random ``(u1, v1, u2, v2)`` with orthonormal ``u`` and the given ``(eta_0, alpha_0)``."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, 2)))
    W, _ = np.linalg.qr(rng.standard_normal((m, 2)))
    scale = float(np.exp(rng.uniform(-3.0, 3.0)))
    v1 = scale * W[:, 0]
    v2 = scale * (alpha0 * W[:, 0] + math.sqrt(eta0 - alpha0 * alpha0) * W[:, 1])
    return Q[:, 0], v1, Q[:, 1], v2


def random_rank2(rng: np.random.Generator, n: int, m: int) -> tuple[np.ndarray, ...]:
    """Random ``(u1, v1, u2, v2)``: orthonormal ``u``, ``||v1|| >= ||v2||``, ``(v1|v2) >= 0``."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, 2)))
    u1, u2 = Q[:, 0], Q[:, 1]
    v1 = rng.standard_normal(m) * np.exp(rng.uniform(-1.0, 1.0))
    # correlated v2 of random relative size, so that alpha_0 covers (0, sqrt(eta_0))
    v2 = rng.uniform(0.0, 1.0) * v1 + rng.standard_normal(m) * np.exp(rng.uniform(-1.0, 1.0))
    if v2 @ v2 > v1 @ v1:
        u1, u2, v1, v2 = u2, u1, v2, v1
    if v1 @ v2 < 0.0:
        u2, v2 = -u2, -v2
    return u1, v1, u2, v2


def iterate_f(
    u1: np.ndarray, v1: np.ndarray, u2: np.ndarray, v2: np.ndarray, steps: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """Apply F ``steps`` times; return ``eta_xi``, ``alpha_xi`` and the loss of ``U V^T``."""
    A0 = np.outer(u1, v1) + np.outer(u2, v2)
    eta = np.empty(steps + 1)
    alpha = np.empty(steps + 1)
    for k in range(steps + 1):
        w11, w22, w12 = float(v1 @ v1), float(v2 @ v2), float(v1 @ v2)
        eta[k], alpha[k] = w22 / w11, w12 / w11
        if k < steps:
            r = ss.rotate_pair(u1, v1, u2, v2)
            u1, v1, u2, v2 = r.u1, r.v1, r.u2, r.v2
    A1 = np.outer(u1, v1) + np.outer(u2, v2)
    return eta, alpha, float(np.linalg.norm(A1 - A0) / np.linalg.norm(A0))


def main(argv: Sequence[str] | None = None) -> dict:
    record = Run("fig1_pair_dynamics", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=None, help="output directory (default bench/results)")
    parser.add_argument("--steps", type=int, default=40, help="iterations xi per trajectory")
    parser.add_argument("--n", type=int, default=50, help="size of u1, u2")
    parser.add_argument("--m", type=int, default=30, help="size of v1, v2")
    parser.add_argument("--random", type=int, default=200,
                        help="number of fully random rank-2 expansions for the deviation")
    parser.add_argument("--seed", type=int, default=20261122)
    args = parser.parse_args(argv)
    out = out_dir(args.out)
    rng = np.random.default_rng(args.seed)
    t_start = time.perf_counter()

    trajectories: list[dict[str, Any]] = []
    for eta0, alpha0 in STARTS:
        dyn = ss.pair_dynamics(eta0, alpha0, args.steps)
        u1, v1, u2, v2 = rank2_expansion(rng, args.n, args.m, eta0, alpha0)
        eta_f, alpha_f, loss = iterate_f(u1, v1, u2, v2, args.steps)
        invariant = dyn.eta[:-1] + 1.0 / dyn.eta[1:]
        trajectories.append({
            "eta0": eta0, "alpha0": alpha0,
            "eta": dyn.eta, "alpha": dyn.alpha,
            "delta": dyn.delta, "eta_limit": dyn.eta_limit,
            "eta_F": eta_f, "alpha_F": alpha_f,
            "max_dev_eta": float(np.max(np.abs(eta_f - dyn.eta))),
            "max_dev_alpha": float(np.max(np.abs(alpha_f - dyn.alpha))),
            "product_change": loss,
            "invariant_max_dev": float(np.max(np.abs(invariant - 2.0 * dyn.delta))),
            # observed rate alpha_{xi+1}/alpha_xi at the last step with alpha above 1e-150
            "observed_rate": _last_ratio(dyn.alpha),
        })

    dev_eta, dev_alpha, dev_prod = 0.0, 0.0, 0.0
    for _ in range(args.random):
        u1, v1, u2, v2 = random_rank2(rng, args.n, args.m)
        eta0 = float(v2 @ v2) / float(v1 @ v1)
        alpha0 = float(v1 @ v2) / float(v1 @ v1)
        if not (alpha0 * alpha0 < eta0):
            continue
        dyn = ss.pair_dynamics(eta0, alpha0, args.steps)
        eta_f, alpha_f, loss = iterate_f(u1, v1, u2, v2, args.steps)
        dev_eta = max(dev_eta, float(np.max(np.abs(eta_f - dyn.eta))))
        dev_alpha = max(dev_alpha, float(np.max(np.abs(alpha_f - dyn.alpha))))
        dev_prod = max(dev_prod, loss)

    max_dev = max(max(float(t["max_dev_eta"]), float(t["max_dev_alpha"])) for t in trajectories)
    result = {
        "steps": args.steps, "n": args.n, "m": args.m, "seed": args.seed,
        "trajectories": trajectories,
        "max_deviation_plotted": max_dev,
        "random_expansions": args.random,
        "max_deviation_random": {"eta": dev_eta, "alpha": dev_alpha,
                                 "relative_product_change": dev_prod},
        "seconds": time.perf_counter() - t_start,
        "machine": machine_info(),
    }

    _plot(trajectories, out / "fig1_pair_dynamics.png")
    record.write(out / "fig1_pair_dynamics.json", result)
    print_table(
        ["eta0", "alpha0", "delta", "eta_limit", "observed", "dev_eta", "dev_alpha"],
        [[t["eta0"], t["alpha0"], t["delta"], t["eta_limit"], t["observed_rate"],
          t["max_dev_eta"], t["max_dev_alpha"]] for t in trajectories],
        title=f"Fig. 1: recursion (14) vs {args.steps} applications of F",
    )
    print(f"random expansions ({args.random}): max |eta_F - eta| = {dev_eta:.2e}, "
          f"max |alpha_F - alpha| = {dev_alpha:.2e}, "
          f"max ||dA||/||A|| = {dev_prod:.2e}")
    print(f"wrote {out / 'fig1_pair_dynamics.png'} and {out / 'fig1_pair_dynamics.json'}")
    return result


def _last_ratio(alpha: np.ndarray) -> float:
    ok = np.nonzero(np.abs(alpha[:-1]) > 1e-150)[0]
    if ok.size == 0:
        return float("nan")
    k = int(ok[-1])
    return float(alpha[k + 1] / alpha[k])


def _plot(trajectories: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5.2))
    colors = plt.get_cmap("tab10")
    grid = np.linspace(0.0, 1.0, 200)
    ax1.fill_between(grid, np.sqrt(grid), 1.0, color="0.92", label=r"excluded: $\alpha^2>\eta$")
    ax1.plot(grid, np.sqrt(grid), color="0.6", lw=0.8)
    for c, t in enumerate(trajectories):
        col = colors(c)
        lab = rf"$(\eta_0,\alpha_0)=({t['eta0']:g},{t['alpha0']:g})$"
        ax1.plot(t["eta"], t["alpha"], "-o", color=col, ms=3.5, lw=1.0, label=lab)
        ax1.plot(t["eta_F"], t["alpha_F"], "x", color="k", ms=5, mew=0.8)
        ax1.plot([t["eta_limit"]], [0.0], marker="v", color=col, ms=10, mec="k",
                 clip_on=False)
        xi = np.arange(len(t["alpha"]))
        ax2.semilogy(xi, np.abs(t["alpha"]), "-o", color=col, ms=3, lw=1.0)
        ax2.semilogy(xi, np.abs(t["alpha_F"]), "x", color="k", ms=4, mew=0.7)
        ax2.semilogy(xi, t["alpha0"] * t["eta_limit"] ** xi, ":", color=col, lw=1.0)
    ax1.plot([], [], "x", color="k", label="iterates of F (rotate_pair)")
    ax1.plot([], [], "v", color="0.5", mec="k", label=r"asymptotic $\eta=\delta-\sqrt{\delta^2-1}$")
    ax1.set_xlim(0.0, 1.02)
    ax1.set_ylim(0.0, 1.0)
    ax1.set_xlabel(r"$\eta_\xi=\|v_2\|^2/\|v_1\|^2$")
    ax1.set_ylabel(r"$\alpha_\xi=(v_1|v_2)/(v_1|v_1)$")
    ax1.set_title(r"Trajectories of recursion (14), $\xi = 0, 1, \dots$")
    ax1.legend(fontsize=7.5, loc="upper left")
    ax2.plot([], [], "-o", color="0.4", ms=3, label=r"recursion (14): $|\alpha_\xi|$")
    ax2.plot([], [], "x", color="k", label="iterates of F")
    ax2.plot([], [], ":", color="0.4", label=r"$\alpha_0\,\eta^\xi$ (asymptotic rate)")
    ax2.set_xlabel(r"iteration $\xi$")
    ax2.set_ylabel(r"$|\alpha_\xi|$")
    ax2.set_ylim(1e-17, 2.0)
    ax2.set_title(r"Coupling $\alpha_\xi$ along iterations (log scale)")
    ax2.grid(True, which="major", alpha=0.3)
    ax2.legend(fontsize=8, loc="lower left")
    fig.suptitle("Fig. 1: rank-2 compression F, recursion (14) and its asymptotic rate")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
