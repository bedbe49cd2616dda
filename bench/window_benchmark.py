"""Sliding windows and forgetting: accuracy against LAPACK, cost per update.

The stream: ``m`` snapshots of size ``n`` in a rank-20 subspace that rotates slowly,
``U(t) = P1 cos(theta t) + P2 sin(theta t)`` (``P1``, ``P2`` orthonormal and orthogonal
to each other), with amplitudes in four groups of five (1, 0.05, 0.0025, 1.25e-4, each spread over
1 to 0.8), plus white noise (``--noise``, 1e-12 by default). The rotation within a window
adds a second set of 20 directions (a window of the data spans up to 40), so a window's
spectrum has 40 terms above the noise. Blocks of ``b`` columns enter a
``StreamCompressor(window=W, max_rank=40, oversampling=10, sweeps=None, rule="jacobi")``,
and, for the exact window, the same without ``max_rank``: it truncates nothing. (With
``sweeps=None`` the Jacobi rule converges in a few sweeps; the paper's rule converges
linearly, and on the clustered amplitudes of the noise took the 200 sweeps allowed.)

* **accuracy** (window ``W``): over the last ``--check`` updates, the batch SVD of the
  window (LAPACK, QR first) against the streamed one: the principal angles of the leading
  ``i`` modes for every ``i <= max_rank`` with ``sigma_i / sigma_(i+1) >= 10``, the
  relative error of the 20 leading singular values, and ``||U^T U - I||`` measured on
  the factor;
* **exact window**: the same checks for the stream that truncates nothing (the SVD of
  the whole window), where nothing discarded separates the two;
* **cost**: seconds per update (absorb and removal) at ``W = 100`` and ``W = 1000``, and
  over the first and last tenths of the stream;
* **forget**: ``forget=gamma`` with random block sizes against the SVD of the weighted
  matrix ``[gamma^(m-1) a_1, ..., a_m]`` (untruncated, ``--forget-m`` snapshots).

Writes ``window_benchmark.json`` and ``.png``. Only ratios measured in the same run mean
anything on a shared machine (the load is recorded).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

import numpy as np
from _common import Run, machine_info, out_dir, pyplot

import streamsvd as ss

GROUPS = (1.0, 0.05, 0.0025, 0.000125)


class RotatingStream:
    """Snapshots of a slowly rotating rank-20 subspace plus noise (module docstring)."""

    def __init__(self, n: int, m: int, *, noise: float, seed: int) -> None:
        rng = np.random.default_rng(seed)
        P = np.linalg.qr(rng.standard_normal((n, 40)))[0]
        self.P1, self.P2 = P[:, :20], P[:, 20:]
        self.sigma = np.repeat(GROUPS, 5) * np.tile(np.linspace(1.0, 0.8, 5), 4)
        self.theta = 0.5 * np.pi / m  # a quarter turn over the stream
        self.noise = noise
        self.rng = rng

    def block(self, start: int, b: int) -> np.ndarray:
        t = np.arange(start, start + b)
        C = self.sigma[:, None] * self.rng.standard_normal((20, b))
        X = self.P1 @ (np.cos(self.theta * t) * C) + self.P2 @ (np.sin(self.theta * t) * C)
        return X + self.noise * self.rng.standard_normal(X.shape)


def _angles(U_ref: np.ndarray, U: np.ndarray, s_ref: np.ndarray, limit: int
            ) -> dict[int, float]:
    """``sin`` of the largest principal angle of the leading ``i <= limit`` modes, at each gap."""
    out = {}
    for i in range(1, min(U.shape[1], s_ref.size - 1, limit) + 1):
        if s_ref[i - 1] >= 10 * s_ref[i]:
            A, B = U_ref[:, :i], U[:, :i]
            out[str(i)] = float(np.linalg.norm(B - A @ (A.T @ B), 2))
    return out


def run_window(n: int, m: int, W: int, b: int, *, rank: int | None, check: int,
               noise: float, seed: int) -> dict[str, Any]:
    """Stream with a window ``W``; time every update; check the last ``check`` ones.

    ``rank=None`` keeps every term: the SVD of the whole window, nothing truncated.
    """
    limit = W if rank is None else rank
    stream = RotatingStream(n, m, noise=noise, seed=seed)
    sc = ss.StreamCompressor(n, window=W, max_rank=rank, oversampling=10, sweeps=None,
                             rule="jacobi")
    buf = np.zeros((n, 0))
    times, checks = [], []
    updates = m // b
    for u in range(updates):
        X = stream.block(u * b, b)
        t0 = time.perf_counter()
        sc.absorb(X)
        times.append(time.perf_counter() - t0)
        if u >= updates - check:
            buf = np.concatenate([buf, X], axis=1)[:, -W:]
            Q, Rw = np.linalg.qr(buf)
            Ur, s_ref, _ = np.linalg.svd(Rw)
            U_ref = Q @ Ur
            U = sc.left_vectors
            amps = sc.amplitudes
            k = 20
            checks.append({
                "update": u,
                "angles": _angles(U_ref, U, s_ref, limit),
                "sv_rel": float(np.max(np.abs(amps[:k] - s_ref[:k]) / s_ref[:k])),
                "s_ref": s_ref[: limit + 1],
                "orthogonality": float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2)),
                "bound": sc.error_bound,
                "true_error": float(np.linalg.norm(buf - sc.expansion.to_dense())),
            })
        elif u >= updates - check - W // b:
            buf = np.concatenate([buf, X], axis=1)[:, -W:]
        if u % 100 == 0:
            print(f"  W={W}: update {u}/{updates}", file=sys.stderr, flush=True)
    t = np.array(times)
    tenth = max(len(t) // 10, 1)
    return {
        "W": W, "b": b, "n": n, "m": m, "seconds_per_update": float(np.median(t)),
        "first_tenth": float(np.median(t[:tenth])), "last_tenth": float(np.median(t[-tenth:])),
        "times": t, "checks": checks, "rewrites": sc._life.state.rows.rewrites,
        "stored_rows": sc._life.state.rows.m,
    }


def run_forget(n: int, m: int, gamma: float, *, seed: int) -> dict[str, Any]:
    """``forget=gamma`` with random block sizes against the weighted matrix's SVD."""
    stream = RotatingStream(n, m, noise=1e-6, seed=seed)
    rng = np.random.default_rng(seed + 1)
    A = stream.block(0, m)
    sc = ss.StreamCompressor(n, forget=gamma, sweeps=None)
    start = 0
    while start < m:
        b = int(rng.integers(1, 40))
        sc.absorb(A[:, start : start + b])
        start += b
    sc.finalize()
    Wt = A * gamma ** np.arange(m - 1, -1, -1, dtype=float)
    s = np.linalg.svd(Wt, compute_uv=False)
    err = np.abs(sc.amplitudes - s[: sc.rank])
    return {
        "gamma": gamma, "n": n, "m": m, "max_sv_error_over_s1": float(err.max() / s[0]),
        "reconstruction_over_norm": float(
            np.linalg.norm(sc.expansion.to_dense() - Wt) / np.linalg.norm(Wt)),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("window_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=50_000)
    ap.add_argument("--m", type=int, default=10_000)
    ap.add_argument("--window", type=int, default=200)
    ap.add_argument("--block", type=int, default=10)
    ap.add_argument("--cost-windows", default="100,1000")
    ap.add_argument("--check", type=int, default=100)
    ap.add_argument("--rank", type=int, default=40)
    ap.add_argument("--noise", type=float, default=1e-12)
    ap.add_argument("--forget-m", type=int, default=400)
    ap.add_argument("--gamma", type=float, default=0.99)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = out_dir(args.out)
    load_start = os.getloadavg()
    runs = [run_window(args.n, args.m, args.window, args.block, rank=args.rank,
                       check=args.check, noise=args.noise, seed=0)]
    for W in (int(w) for w in args.cost_windows.split(",")):
        runs.append(run_window(args.n, args.m, W, args.block, rank=args.rank, check=0,
                               noise=args.noise, seed=0))
    exact = run_window(args.n, args.m, args.window, args.block, rank=None,
                       check=args.check, noise=args.noise, seed=0)
    forget = run_forget(args.n, args.forget_m, args.gamma, seed=2)
    acc = runs[0]["checks"]
    report: dict[str, Any] = {
        "machine": machine_info(), "load_start": list(load_start),
        "load_end": list(os.getloadavg()), "args": vars(args), "runs": runs,
        "exact": exact, "forget": forget,
        "summary": {
            "max_angle": max(max(c["angles"].values()) for c in acc),
            "max_angle_by_gap": {i: max(c["angles"].get(i, 0.0) for c in acc)
                                 for i in sorted({i for c in acc for i in c["angles"]}, key=int)},
            "gap_sigma": {i: acc[-1]["s_ref"][int(i) - 1] for i in acc[-1]["angles"]},
            "gaps": sorted({int(i) for c in acc for i in c["angles"]}),
            "max_sv_rel": max(c["sv_rel"] for c in acc),
            "max_orthogonality": max(c["orthogonality"] for c in acc),
            "bound_over_true": [min(c["bound"] / c["true_error"] for c in acc),
                                max(c["bound"] / c["true_error"] for c in acc)],
            "cost_ratio_large_over_small": (runs[-1]["seconds_per_update"]
                                            / runs[1]["seconds_per_update"]),
            "flat": {f"W={r['W']}": r["last_tenth"] / r["first_tenth"] for r in runs},
            "forget_sv_error": forget["max_sv_error_over_s1"],
            "exact_window": {
                "max_angle_by_gap": {
                    i: max(c["angles"].get(i, 0.0) for c in exact["checks"])
                    for i in sorted({i for c in exact["checks"] for i in c["angles"]}, key=int)
                },
                "max_sv_rel": max(c["sv_rel"] for c in exact["checks"]),
                "max_orthogonality": max(c["orthogonality"] for c in exact["checks"]),
                "seconds_per_update": exact["seconds_per_update"],
            },
        },
    }
    record.write(out / "window_benchmark.json", report)
    _figure(report, out / "window_benchmark.png")
    for k, v in report["summary"].items():
        print(f"{k:30s} {v}")
    return report


def _figure(report: dict[str, Any], path: Any) -> None:
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    acc = report["runs"][0]["checks"]
    u = [c["update"] for c in acc]
    for i in report["summary"]["gaps"]:
        a1.semilogy(u, [max(c["angles"].get(str(i), np.nan), 1e-17) for c in acc],
                    label=f"leading {i} modes")
    a1.semilogy(u, [c["sv_rel"] for c in acc], "k--", label="singular values (relative)")
    a1.semilogy(u, [c["orthogonality"] for c in acc], "k:", label="||U^T U - I||")
    a1.set_xlabel(f"update (blocks of {report['args']['block']} snapshots)")
    a1.set_ylabel("sin(principal angle), relative error (-)")
    a1.set_title(f"window {report['args']['window']} against the batch SVD")
    a1.legend(fontsize=7)
    for r in report["runs"][1:]:
        t = np.asarray(r["times"]) * 1e3
        a2.plot(np.arange(t.size), t, lw=0.5, label=f"W = {r['W']}")
    a2.set_xlabel("update")
    a2.set_ylabel("time per update (ms)")
    a2.set_yscale("log")
    a2.set_title(f"cost per update, n = {report['args']['n']}")
    a2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
