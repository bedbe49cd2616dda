"""Certified streaming DMD against PyDMD (batch) and odmd (online): accuracy and cost.

The data: ``x_(j+1) = A x_j`` with ``A = Q D Q^T`` normal of rank ``k`` (five rotations
scaled by decays 0.999 ... 0.95, embedded in ``R^n`` by a random orthonormal ``Q``), plus
white measurement noise of standard deviation ``sigma`` per entry.

* **accuracy against noise** (``--n``, ``--m``, ``--noises``): the largest distance from
  a true eigenvalue to the nearest one found, for the stream (``StreamCompressor(
  dynamics=True, max_rank=2k)``, blocks of ``b``, ``dmd(rank=k, model_error=delta)``
  with ``delta = ||A X_0 - X_1||_F`` measured), PyDMD's ``DMD(svd_rank=k)`` on the whole
  matrix, odmd's ``OnlineDMD`` on the full state (it needs ``p >= n`` initial pairs of
  rank ``n``: refused without noise) and on the POD coordinates ``U_k^T x`` (``U_k`` the
  stream's leading ``k`` modes, given to it for free); the stream's largest bound ``eta``
  and whether every eigenvalue lies within its ``eta`` of a true one;
* **cost** (``--cost-n``, ``--cost-m``): CPU seconds per snapshot and the peak of the
  memory allocated (tracemalloc, which sees numpy's buffers) for the stream with and
  without ``dynamics`` and its query, and PyDMD on the whole matrix where it fits
  (``n m <= --pydmd-max-entries``), odmd on the full state where ``n <= --odmd-max-n``;
  snapshots are made block by block, outside the timings; contenders interleaved,
  medians of ``--repeat`` runs.

Writes ``dmd_benchmark.json`` and ``dmd_benchmark.png`` (eigenvalues in the complex plane
with their ``eta`` discs at one noise level; error against noise, log scales). Needs the
``bench`` extra (``pydmd``, ``odmd``). The load is recorded before and after.
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from _common import Run, out_dir, print_table, pyplot

import streamsvd as ss
from streamsvd.testing.systems import LinearSystem, match_eigenvalues, normal_system

RADII = np.array([0.999, 0.995, 0.99, 0.97, 0.95])
ANGLES = np.array([0.05, 0.21, 0.6, 1.3, 2.4])


def system(n: int, seed: int) -> LinearSystem:
    """Return the benchmark's normal system of rank 10 in ``R^n``."""
    return normal_system(n, RADII, ANGLES, np.random.default_rng(seed))


def blocks(sysm: LinearSystem, m: int, b: int, noise: float, seed: int
           ) -> Iterator[np.ndarray]:
    """Yield the ``m`` snapshots in blocks of ``b`` (made as they are asked for)."""
    rng = np.random.default_rng(seed + 1)
    k = sysm.D.shape[0]
    z = np.ones(k) / np.sqrt(k)
    for start in range(0, m, b):
        w = min(b, m - start)
        Z = np.empty((k, w))
        for j in range(w):
            Z[:, j] = z
            z = sysm.D @ z
        X = sysm.Q @ Z
        if noise:
            X += noise * rng.standard_normal(X.shape)
        yield X


def true_errors(found: np.ndarray, true: np.ndarray) -> float:
    """Largest distance from a true eigenvalue to the nearest one found."""
    return float(np.max(match_eigenvalues(true, found)))


def stream(sysm: LinearSystem, m: int, b: int, noise: float, seed: int, *,
           dynamics: bool = True, query: bool = True, delta: float = 0.0
           ) -> tuple[Any, Any, float]:
    """Stream the data; return the compressor, its DMD (or None) and the update CPU time."""
    k = sysm.D.shape[0]
    sc = ss.StreamCompressor(sysm.Q.shape[0], dynamics=dynamics, max_rank=2 * k,
                             oversampling=0)
    cpu = 0.0
    for X in blocks(sysm, m, b, noise, seed):
        t0 = time.process_time()
        sc.absorb(X)
        cpu += time.process_time() - t0
    res = sc.dmd(rank=k, model_error=delta, modes=False) if query else None
    return sc, res, cpu


def whole(sysm: LinearSystem, m: int, noise: float, seed: int) -> np.ndarray:
    """Return the ``n x m`` snapshot matrix (for the batch contender)."""
    return np.hstack(list(blocks(sysm, m, 500, noise, seed)))


def pydmd_eigs(X: np.ndarray, k: int) -> np.ndarray:
    """PyDMD's DMD(svd_rank=k) eigenvalues of the snapshot matrix ``X``."""
    import warnings

    from pydmd import DMD

    with warnings.catch_warnings():  # its note on the condition number of low-rank data
        warnings.simplefilter("ignore", UserWarning)
        return np.asarray(DMD(svd_rank=k).fit(X).eigs)


def odmd_full(sysm: LinearSystem, m: int, noise: float, seed: int) -> np.ndarray | None:
    """odmd's OnlineDMD on the full state (None: refused, the state is not of full rank)."""
    from odmd import OnlineDMD

    n = sysm.Q.shape[0]
    if m - 1 < n + 1:
        return None
    cols = blocks(sysm, m, 100, noise, seed)  # made as they are needed, as the stream's
    first = [next(cols)]
    while sum(x.shape[1] for x in first) < n + 1:
        first.append(next(cols))
    X = np.hstack(first)
    if np.linalg.matrix_rank(X[:, :n]) < n:
        return None
    model = OnlineDMD(n, 1.0)
    model.initialize(X[:, :n], X[:, 1:n + 1])
    prev = X[:, n]
    for B in [X[:, n + 1:], *cols]:
        for j in range(B.shape[1]):
            model.update(prev, B[:, j])
            prev = B[:, j]
    return np.asarray(np.linalg.eigvals(model.A))


def odmd_pod(sysm: LinearSystem, Uk: np.ndarray, m: int, noise: float, seed: int
             ) -> np.ndarray:
    """odmd's OnlineDMD on the POD coordinates ``U_k^T x`` (``U_k`` given)."""
    from odmd import OnlineDMD

    k = Uk.shape[1]
    Z = np.hstack([Uk.T @ X for X in blocks(sysm, m, 500, noise, seed)])
    model = OnlineDMD(k, 1.0)
    p = 4 * k
    model.initialize(Z[:, :p], Z[:, 1:p + 1])
    for j in range(p, m - 1):
        model.update(Z[:, j], Z[:, j + 1])
    return np.asarray(np.linalg.eigvals(model.A))


def accuracy(n: int, m: int, b: int, noises: list[float], seed: int) -> list[dict[str, Any]]:
    """The accuracy rows: every contender at every noise level."""
    sysm = system(n, seed)
    k = sysm.D.shape[0]
    rows = []
    for noise in noises:
        X = whole(sysm, m, noise, seed)
        delta = float(np.linalg.norm(sysm.apply(X[:, :-1]) - X[:, 1:]))
        sc, res, _ = stream(sysm, m, b, noise, seed, delta=delta)
        err = match_eigenvalues(res.eigenvalues, sysm.eigenvalues)
        Uk = sc.left_vectors[:, :k]
        full = odmd_full(sysm, m, noise, seed)
        rows.append({
            "noise": noise, "delta": delta,
            "stream": true_errors(res.eigenvalues, sysm.eigenvalues),
            "stream_max_eta": float(np.max(res.residual_bounds)),
            "stream_certified": bool(np.all(err <= res.residual_bounds)),
            "pydmd": true_errors(pydmd_eigs(X, k), sysm.eigenvalues),
            "odmd_pod": true_errors(odmd_pod(sysm, Uk, m, noise, seed), sysm.eigenvalues),
            "odmd_full": None if full is None else true_errors(full, sysm.eigenvalues),
            "eigenvalues": [[z.real, z.imag] for z in res.eigenvalues],
            "eta": res.residual_bounds.tolist(),
        })
        del X
    return rows


def measured(fn: Callable[[], Any]) -> tuple[float, float, Any]:
    """Run ``fn``; return its CPU seconds, the peak of the memory it allocated (MB), value."""
    tracemalloc.start()
    t0 = time.process_time()
    value = fn()
    cpu = time.process_time() - t0
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return cpu, peak, value


def cost(ns: list[int], m: int, b: int, noise: float, seed: int, repeat: int,
         pydmd_max: float, odmd_max_n: int) -> list[dict[str, Any]]:
    """The cost rows: per ``n``, medians over ``repeat`` interleaved runs."""
    rows = []
    for n in ns:
        sysm = system(n, seed)
        k = sysm.D.shape[0]
        runs: dict[str, list[tuple[float, float]]] = {}
        for _ in range(repeat):
            for dyn in (True, False):
                _, peak, (sc, _, cpu) = measured(
                    lambda s=sysm, d=dyn: stream(s, m, b, noise, seed, dynamics=d, query=False))
                runs.setdefault("stream_dynamics" if dyn else "stream_plain", []).append(
                    (cpu, peak))
                if dyn:
                    qcpu, qpeak, _ = measured(lambda sc=sc, k=k: sc.dmd(rank=k, modes=False))
                    runs.setdefault("stream_query", []).append((qcpu, qpeak))
            if n * m <= pydmd_max:
                X = whole(sysm, m, noise, seed)
                cpu, peak, _ = measured(lambda X=X, k=k: pydmd_eigs(X, k))
                # with the matrix it needs, made outside the measurement
                runs.setdefault("pydmd", []).append((cpu, peak + X.nbytes / 1e6))
                del X
            if n <= odmd_max_n:
                cpu, peak, _ = measured(lambda s=sysm: odmd_full(s, m, noise, seed))
                runs.setdefault("odmd_full", []).append((cpu, peak))
        row: dict[str, Any] = {"n": n, "m": m, "b": b}
        for name, vals in runs.items():
            arr = np.array(vals)
            per = m if name != "stream_query" else 1
            row[name] = {"cpu_per_snapshot": float(np.median(arr[:, 0]) / per),
                         "peak_mb": float(np.median(arr[:, 1]))}
        d, p = row["stream_dynamics"], row["stream_plain"]
        row["dynamics_over_plain"] = d["cpu_per_snapshot"] / p["cpu_per_snapshot"]
        rows.append(row)
    return rows


def memory_vs_m(n: int, ms: list[int], b: int, noise: float, seed: int
                ) -> list[dict[str, Any]]:
    """Peak of the memory the stream allocates (and its query's) against the stream's length."""
    sysm = system(n, seed)
    k = sysm.D.shape[0]
    rows = []
    for m in ms:
        cpu, peak, (sc, _, _) = measured(
            lambda m=m: stream(sysm, m, b, noise, seed, query=False))
        qcpu, qpeak, _ = measured(lambda sc=sc: sc.dmd(rank=k, modes=False))
        rows.append({"n": n, "m": m, "b": b, "peak_mb": peak, "query_peak_mb": qpeak,
                     "cpu_per_snapshot": cpu / m, "query_cpu": qcpu,
                     "n_k_plus_b_mb": n * (2 * k + b) * 8 / 1e6})
    return rows


def figure(path: Any, acc: list[dict[str, Any]], sysm: LinearSystem, shown: float) -> None:
    """Eigenvalues with their eta discs at noise ``shown``; error against noise."""
    plt = pyplot()
    fig, (a, c) = plt.subplots(1, 2, figsize=(11, 4.6))
    row = next(r for r in acc if r["noise"] == shown)
    lam = np.array([complex(*z) for z in row["eigenvalues"]])
    t = np.linspace(0, 2 * np.pi, 300)
    a.plot(np.cos(t), np.sin(t), color="0.8", lw=0.8)
    for z, e in zip(lam, row["eta"], strict=True):
        a.add_patch(plt.Circle((z.real, z.imag), min(e, 5.0), color="C0", alpha=0.25))
    a.plot(sysm.eigenvalues.real, sysm.eigenvalues.imag, "o", mfc="none", color="k", ms=8,
           label="true eigenvalues")
    a.plot(lam.real, lam.imag, "x", color="C0", label=f"stream DMD, eta discs (noise {shown:g})")
    a.set_xlabel("Re lambda (per step)")
    a.set_ylabel("Im lambda (per step)")
    a.set_aspect("equal")
    a.set_xlim(-1.1, 1.1)
    a.set_ylim(-1.1, 1.1)
    a.legend(fontsize=8, loc="lower left")
    noise = np.array([r["noise"] for r in acc])
    ok = noise > 0
    for key, label in (("stream", "stream (streamsvd)"), ("pydmd", "PyDMD batch"),
                       ("odmd_pod", "odmd online, POD coordinates"),
                       ("odmd_full", "odmd online, full state"),
                       ("stream_max_eta", "stream: largest eta")):
        y = np.array([np.nan if r[key] is None else r[key] for r in acc], dtype=float)
        c.loglog(noise[ok], np.maximum(y[ok], 1e-17), "o-" if key != "stream_max_eta"
                 else "k--", label=label)
    c.set_xlabel("measurement noise (std per entry)")
    c.set_ylabel("largest eigenvalue error (per step)")
    c.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the benchmark, print its tables and write its files."""
    record = Run("dmd_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--m", type=int, default=2000)
    ap.add_argument("--block", type=int, default=100)
    ap.add_argument("--noises", default="0,1e-10,1e-8,1e-6,1e-4,1e-2")
    ap.add_argument("--cost-n", default="1000,10000,100000")
    ap.add_argument("--cost-m", type=int, default=4000)
    ap.add_argument("--cost-noise", type=float, default=1e-6)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pydmd-max-entries", type=float, default=4e7)
    ap.add_argument("--odmd-max-n", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--memory-m", default=None,
                    help="only measure the stream's peak memory at --cost-n's first n for "
                    "these stream lengths (comma-separated); writes dmd_benchmark_memory.json")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = out_dir(args.out)
    if args.memory_m is not None:
        rows = memory_vs_m(int(args.cost_n.split(",")[0]),
                           [int(x) for x in args.memory_m.split(",")], args.block,
                           args.cost_noise, args.seed)
        print_table(["n", "m", "peak MB", "query peak MB", "n (2k + b) 8 bytes, MB"],
                    [[r["n"], r["m"], f"{r['peak_mb']:.1f}", f"{r['query_peak_mb']:.2f}",
                      f"{r['n_k_plus_b_mb']:.1f}"] for r in rows], title="peak memory")
        record.write(out / "dmd_benchmark_memory.json", {"memory": rows})
        return {"memory": rows}
    noises = [float(x) for x in args.noises.split(",")]
    acc = accuracy(args.n, args.m, args.block, noises, args.seed)
    print_table(["noise", "delta", "stream", "max eta", "certified", "PyDMD", "odmd POD",
                 "odmd full"],
                [[r["noise"], f"{r['delta']:.2e}", f"{r['stream']:.2e}",
                  f"{r['stream_max_eta']:.2e}", r["stream_certified"], f"{r['pydmd']:.2e}",
                  f"{r['odmd_pod']:.2e}",
                  "refused" if r["odmd_full"] is None else f"{r['odmd_full']:.2e}"]
                 for r in acc], title="largest eigenvalue error")
    costs = cost([int(x) for x in args.cost_n.split(",")], args.cost_m, args.block,
                 args.cost_noise, args.seed, args.repeat, args.pydmd_max_entries,
                 args.odmd_max_n)
    names = ("stream_dynamics", "stream_plain", "stream_query", "pydmd", "odmd_full")
    print_table(["n", "m"] + [f"{x} ms/snap | MB" for x in names] + ["dyn / plain"],
                [[r["n"], r["m"]] + [
                    f"{r[x]['cpu_per_snapshot'] * 1e3:.3g} | {r[x]['peak_mb']:.4g}"
                    if x in r else "-" for x in names] + [f"{r['dynamics_over_plain']:.2f}"]
                 for r in costs], title="cost (CPU ms per snapshot; query: ms per query)")
    shown = 1e-4 if 1e-4 in noises else noises[-1]
    figure(out / "dmd_benchmark.png", acc, system(args.n, args.seed), shown)
    payload = {"accuracy": acc, "cost": costs}
    record.write(out / "dmd_benchmark.json", payload)
    return payload


if __name__ == "__main__":
    main(sys.argv[1:])
    sys.exit(0)
