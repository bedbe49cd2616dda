"""Sliding-window POD of a heat equation whose source moves: the modes follow it.

A rod of length 1 m, ``u_t = kappa u_xx + q(x, t)`` (temperature ``u`` in K above the
ends, which are held at 0 K; ``kappa = 1e-3 m^2/s``), heated by a Gaussian source of
width 0.03 m that travels from x = 0.15 m to x = 0.85 m over the run and pulses in
strength. Finite differences on ``n`` interior nodes, implicit Euler with a step of
``dt`` s. Every step's temperature enters a ``StreamCompressor(window=W)``: its modes are
those of the last ``W`` steps, the dominant ones moving with the source, which a POD of
the whole run would smear out. At a few times the windowed modes are compared with the
batch SVD (LAPACK) of the same window: principal angles of the leading modes after each
gap ``sigma_i / sigma_(i+1) >= 10``, and the singular values.

Run: ``python examples/moving_source.py [--n 400] [--steps 1500] [--window 150]
[--block 10] [--out out/moving_source]``; writes ``moving_source.png`` (modes against
the batch modes, spectra on a log scale) and ``summary.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.linalg

import streamsvd as ss

KAPPA = 1e-3  # m^2 / s


def heat_steps(n: int, steps: int, dt: float) -> np.ndarray:
    """Return the temperatures (``n x steps``, K) of the rod heated by the moving source."""
    h = 1.0 / (n + 1)
    x = np.linspace(h, 1 - h, n)
    r = KAPPA * dt / h**2
    # (I + r L) u_new = u + dt q, L the second difference: a tridiagonal solve per step
    ab = np.zeros((3, n))
    ab[0, 1:], ab[1], ab[2, :-1] = -r, 1 + 2 * r, -r
    u = np.zeros(n)
    out = np.empty((n, steps))
    for k in range(steps):
        s = k / max(steps - 1, 1)
        centre = 0.15 + 0.7 * s
        strength = 2.0 + np.sin(12 * np.pi * s)  # K/s
        q = strength * np.exp(-(((x - centre) / 0.03) ** 2))
        u = scipy.linalg.solve_banded((1, 1), ab, u + dt * q)
        out[:, k] = u
    return out


def _angles(U_ref: np.ndarray, U: np.ndarray, s_ref: np.ndarray, top: int) -> dict[int, float]:
    """``sin`` of the largest principal angle of the leading ``i`` modes at each gap."""
    out = {}
    for i in range(1, min(top, U.shape[1], s_ref.size - 1) + 1):
        if s_ref[i - 1] >= 10 * s_ref[i]:
            A, B = U_ref[:, :i], U[:, :i]
            out[i] = float(np.linalg.norm(B - A @ (A.T @ B), 2))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--dt", type=float, default=0.5)
    ap.add_argument("--window", type=int, default=150)
    ap.add_argument("--block", type=int, default=10)
    ap.add_argument("--rank", type=int, default=20)
    ap.add_argument("--out", default="out/moving_source")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    A = heat_steps(args.n, args.steps, args.dt)
    x = np.linspace(0, 1, args.n + 2)[1:-1]
    sc = ss.StreamCompressor(args.n, window=args.window, max_rank=args.rank,
                             oversampling=10, sweeps=None)
    blocks = range(0, args.steps, args.block)
    shown = {blocks[len(blocks) // 4], blocks[len(blocks) // 2], blocks[-1]}
    checks = []
    for start in blocks:
        stop = min(start + args.block, args.steps)
        sc.absorb(A[:, start:stop])
        if start in shown:
            W = A[:, max(0, stop - args.window) : stop]
            U_ref, s_ref, _ = np.linalg.svd(W, full_matrices=False)
            U, amps = sc.left_vectors, sc.amplitudes
            k = min(5, U.shape[1])
            shown_ref = U_ref[:, :3] * np.sign(np.sum(U_ref[:, :3] * U[:, :3], axis=0))
            checks.append({
                "time_s": stop * args.dt, "U": U[:, :3], "U_ref": shown_ref,
                "s": amps, "s_ref": s_ref[: args.rank + 10],
                "angles": _angles(U_ref, U, s_ref, args.rank),
                "sv_rel_top5": float(np.max(np.abs(amps[:k] - s_ref[:k]) / s_ref[:k])),
                "orthogonality": float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2)),
            })
    summary = {
        "n": args.n, "steps": args.steps, "window": args.window, "block": args.block,
        "n_seen": sc.n_seen, "n_absorbed": sc.n_absorbed, "rank": sc.rank,
        "error_bound": sc.error_bound,
        "max_angle": max((a for c in checks for a in c["angles"].values()), default=0.0),
        "gaps": sorted({i for c in checks for i in c["angles"]}),
        "max_sv_rel_top5": max(c["sv_rel_top5"] for c in checks),
        "max_orthogonality": max(c["orthogonality"] for c in checks),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    _figure(x, checks, out / "moving_source.png")
    print(json.dumps(summary, indent=1), file=sys.stderr)
    return 0


def _figure(x: np.ndarray, checks: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(checks), figsize=(4 * len(checks), 6.5), squeeze=False)
    for j, c in enumerate(checks):
        ax = axes[0, j]
        for i in range(c["U"].shape[1]):
            line, = ax.plot(x, c["U_ref"][:, i], lw=3, alpha=0.35)
            ax.plot(x, c["U"][:, i], "--", color=line.get_color(), label=f"mode {i + 1}")
        ax.set_title(f"t = {c['time_s']:.0f} s (batch: thick, window: dashed)", fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("mode shape (-, unit 2-norm over the nodes)")
        ax.legend(fontsize=7)
        ax = axes[1, j]
        for key, style, label in (("s_ref", "o", "batch SVD of the window"),
                                  ("s", "x", "streamed window")):
            ax.semilogy(np.arange(1, c[key].size + 1), c[key], style, mfc="none", label=label)
        ax.set(xlabel="mode index", ylabel="singular value (K)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
