"""Streaming benchmark: streamsvd against IncrementalPCA, Brand's SVD and numpy's SVD.

    python bench/stream_benchmark.py                  # default run (about 15 min on 2 cores)
    python bench/stream_benchmark.py --long           # adds 10^5 updates of the long stream
    python bench/stream_benchmark.py --n 2000 --m 400 --rank 100 --target 20   # smaller

Data
----
``A = Q1 diag(s) Q2^T`` (``n x m``, default 20000 x 2000), ``s`` log-spaced from 1 to
1e-10 over ``--rank`` (300) modes, ``Q1``, ``Q2`` orthonormal (CholeskyQR2 of seeded
Gaussian matrices, orthonormal to ~1e-15). The snapshots are the columns of ``A``. The
SVD of every prefix ``A_k = A[:, :k]`` is known exactly from the small matrix
``diag(s) Q2[:k]^T`` (``rank x k``), which is the reference ("the batch SVD").

Configurations
--------------
Target rank ``t`` (``--target``, 60). For each block width ``b`` (``--blocks``,
100, 10, 1) every method receives the same stream: a first block of ``max(b, t)`` columns
(IncrementalPCA needs at least ``t`` samples in its first call), then blocks of ``b``.
Block 100 runs on the whole stream; blocks 10 and 1 run on a prefix (``--prefix``,
1000 and 200 columns) so that the slowest method finishes. A method whose update time
exceeds ``--budget`` seconds in the first run of the stream stops early (and is not
repeated); its total time is then extrapolated (mean of its last 5 updates times the
updates left) and marked ``extrapolated``, and its accuracy refers to the columns it
absorbed.

Methods
-------
* ``streamsvd``: ``StreamCompressor(n, max_rank=t, oversampling=0, rule=...,
  sweeps=...)`` for both rules and ``sweeps`` = 1, 2 and converged (``None``): truncated
  to ``t`` at every update, as the baselines are;
* ``brand``: Brand's incremental SVD (``bench/brand.py``: block CGS2, Householder QR of
  the residual, LAPACK SVD of the ``(p + b)`` core, truncation to ``t``);
* ``ipca``: ``sklearn.decomposition.IncrementalPCA(n_components=t).partial_fit`` on the
  rows of ``A^T`` (samples = snapshots). IncrementalPCA always centres its data (it
  models ``mean + P_U (a - mean)``), so it is measured against the batch SVD of what it
  models, the centred prefix ``A_k - mean 1^T`` (exact from ``diag(s) Q2[:k]^T`` with
  its row means removed); its reconstruction is its projection
  (``inverse_transform(transform(.))``), since it keeps no per-sample coefficients;
* ``numpy svd``: ``np.linalg.svd(A[:, :k], full_matrices=False)`` of everything seen so
  far, timed at a few ``k`` (``--svd-k``); its cost per update grows as ``n k^2``, and
  its totals over a stream are the sum of a fit ``c1 k + c2 k^2`` to the measured times
  (marked ``extrapolated``).

Measures
--------
* time of every update (wall clock around the call). Each (method, configuration) runs
  alone in a fresh subprocess (``--isolation subprocess``), ``--repeats`` (3) times; the
  repeats alternate between the methods (forward, then backward order) so that a slow
  spell of a shared machine does not fall on every run of one method, and an update's
  time is the best over the repeats. Reported: every update's time, the total, the mean
  and median of updates 2..N, and flatness: mean of the last 5 updates over mean of
  updates 2..6 (also with medians);
* peak memory, in the same runs: the subprocess loads the data, warms the method up on a
  tiny problem (numba, imports), resets the kernel's high-water mark
  (``/proc/self/clear_refs``) and reads ``VmHWM`` after the stream; the figure is
  ``VmHWM`` minus the resident size just before the method was built, i.e. what the
  method adds on top of the data (a psutil sampling thread replaces the high-water mark
  where ``clear_refs`` is unavailable); the largest over the repeats;
* accuracy against the reference of what the method models (above): the largest relative
  error of the top ``t`` singular values ``max_i |s_i - sigma_i| / sigma_i``; the relative
  reconstruction error ``||A_k - U V^T||_F / ||A_k||_F`` and its ratio to the optimal
  (Eckart-Young) ``sqrt(sum_{i > t} sigma_i^2) / ||A_k||_F``; the projection error
  ``||A_k - U U^T A_k||_F / ||A_k||_F``; the error bound (streamsvd's guaranteed bound;
  Brand's discarded energy) and ``||U^T U - I||_2``.

Long stream (orthogonality)
---------------------------
A separate stream of ``--long-n`` (1000) sized snapshots ``Q1 diag(s) z_j`` (``z_j``
Gaussian, same spectrum shape) absorbed one column at a time by
``StreamCompressor(max_rank=--long-target)`` (20), recording ``orthogonality`` and the
update time of every update: ``--ortho-updates`` (10^4) updates by default, ``--long``
for ``--long-updates`` (10^5). The JSON keeps, per chunk of updates, the largest and mean
orthogonality and the mean update time (the largest is over every update).

Profiles
--------
One ``cProfile`` run per block width of ``streamsvd`` (jacobi and paper rules, one sweep
and converged) on a few updates after the first ones, reporting the time spent in
Gram-Schmidt (``extend_basis``), the rotation sweeps (``sweep_core``), the QR of the core,
the compaction of the basis, the new rows of ``V`` and the rest.

Targets
-------
* 10x faster per update than IncrementalPCA (ratio of the means of updates 2..N) at equal
  or better accuracy: the singular value error and the projection error over its optimum
  at most ``--accuracy-slack`` (1.01) times IncrementalPCA's (each method against its own
  reference), and, read the second way, at most that times Brand's (the exact SVD update
  on the same, uncentred, data: IncrementalPCA's update without the centring);
* flat time per update: flatness ratio at most 1.2 (block 100: updates 16..20 against
  updates 2..6);
* orthogonality of the long stream below ``50 n eps`` at every update.

Writes ``stream_benchmark.json`` and ``stream_benchmark.png`` to ``--out``.
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import json
import math
import os
import pstats
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg as sla

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

from _common import Run, machine_info, out_dir, print_table, pyplot, write_json  # noqa: E402
from brand import BrandSVD  # noqa: E402

EPS = float(np.finfo(np.float64).eps)
RULES = ("paper", "jacobi")
SWEEPS: tuple[int | None, ...] = (1, 2, None)
PROFILE_PARTS = (
    ("Gram-Schmidt (extend_basis)", ("extend_basis",)),
    ("rotation sweeps (sweep_core)", ("sweep_core",)),
    ("QR of the core", ("r_factor", "_r_factor", "qr")),
    ("coupling norm (svdvals)", ("svdvals",)),
    ("compaction (compact_planned)", ("compact_planned",)),
    ("new rows of V (stage)", ("stage",)),
    ("orthogonality check", ("_orthogonality", "_extended_gram")),
    ("input validation", ("as_float_array",)),
)
SWEEP_LABEL = {1: "1", 2: "2", None: "conv"}


# ---------------------------------------------------------------------------- data
def orthonormal(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Orthonormal ``rows x cols`` matrix: CholeskyQR2 of a Gaussian matrix (rows >= cols)."""
    Q = rng.standard_normal((rows, cols))
    for _ in range(2):
        L = np.linalg.cholesky(Q.T @ Q)
        Q = sla.solve_triangular(L, Q.T, lower=True).T
    return np.ascontiguousarray(Q)


def spectrum(rank: int) -> np.ndarray:
    """Singular values log-spaced from 1 to 1e-10."""
    return np.logspace(0.0, -10.0, rank)


def make_data(n: int, m: int, rank: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``A`` (Fortran order: column blocks are contiguous), ``s`` and ``Q2``."""
    rng = np.random.default_rng(seed)
    r = min(rank, n, m)
    Q1 = orthonormal(rng, n, r)
    Q2 = orthonormal(rng, m, r)
    s = spectrum(r)
    A = np.asfortranarray((Q1 * s) @ Q2.T)
    return A, s, Q2


def reference(s: np.ndarray, Q2: np.ndarray, k: int, *, centered: bool) -> dict[str, Any]:
    """Exact singular values and Frobenius norm of ``A[:, :k]`` (centred or not)."""
    B = s[:, None] * Q2[:k].T
    if centered:
        B = B - B.mean(axis=1, keepdims=True)
    sigma = sla.svdvals(B)
    return {"sigma": sigma, "fro": float(np.linalg.norm(B))}


def block_schedule(m_use: int, b: int, target: int) -> list[tuple[int, int]]:
    """Column ranges: a first block of ``max(b, target)`` columns, then blocks of ``b``."""
    first = min(max(b, target), m_use)
    out = [(0, first)]
    j = first
    while j < m_use:
        out.append((j, min(j + b, m_use)))
        j += b
    return out


# ---------------------------------------------------------------------------- memory
def _proc_status_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for ln in f:
                if ln.startswith(key + ":"):
                    return int(ln.split()[1])
    except OSError:
        return None
    return None


class PeakRSS:
    """Peak resident size of this process during a ``with`` block, above its start value.

    Uses the kernel's high-water mark (``VmHWM``, reset through ``/proc/self/clear_refs``)
    where available, else a psutil thread sampling every millisecond.
    """

    def __enter__(self) -> PeakRSS:
        gc.collect()
        self.method = "VmHWM"
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            start = _proc_status_kb("VmRSS")
            if start is None:
                raise OSError("no VmRSS")
            self.start_mb = start / 1024.0
        except OSError:
            import psutil

            self.method = "psutil sampling (1 ms)"
            proc = psutil.Process()
            self.start_mb = proc.memory_info().rss / 2**20
            self._peak = self.start_mb

            def sample() -> None:
                while not self._stop.is_set():
                    self._peak = max(self._peak, proc.memory_info().rss / 2**20)
                    time.sleep(0.001)

            self._thread = threading.Thread(target=sample, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self.peak_mb = self._peak
        else:
            hwm = _proc_status_kb("VmHWM")
            self.peak_mb = (hwm or 0) / 1024.0
        self.extra_mb = max(self.peak_mb - self.start_mb, 0.0)


# ---------------------------------------------------------------------------- methods
def _warm_up(method: str, rule: str | None, sweeps: int | None) -> None:
    """Run the method once on a tiny problem (numba compilation, imports, BLAS threads)."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((64, 40))
    if method == "streamsvd":
        import streamsvd as ss

        sc = ss.StreamCompressor(64, max_rank=6, oversampling=0, rule=rule or "paper",
                                 sweeps=sweeps)
        sc.absorb(X[:, :10])
        sc.absorb(X[:, 10:20])
        sc.absorb(X[:, 20:21])
        _ = sc.expansion
    elif method == "brand":
        br = BrandSVD(64, rank=6, max_columns=40, max_block=10)
        br.absorb(X[:, :10])
        br.absorb(X[:, 10:11])
    elif method == "ipca":
        from sklearn.decomposition import IncrementalPCA

        ip = IncrementalPCA(n_components=6)
        ip.partial_fit(X.T[:10])
        ip.partial_fit(X.T[10:11])
    else:
        np.linalg.svd(X, full_matrices=False)


def _frob_errors(A: np.ndarray, U: np.ndarray, V: np.ndarray | None,
                 mean: np.ndarray | None, chunk: int = 256) -> tuple[float, float]:
    """``||A - U V^T||_F`` (or, without ``V``, the projection) and ``||(I - UU^T)(A - mean)||_F``.

    ``mean`` (a column) is subtracted from ``A`` first when given. Computed by column
    chunks so that no ``n x m`` temporary is formed.
    """
    model2 = 0.0
    proj2 = 0.0
    for j in range(0, A.shape[1], chunk):
        X = np.array(A[:, j : j + chunk])
        if mean is not None:
            X -= mean[:, None]
        P = X - U @ (U.T @ X)
        proj2 += float(np.sum(P * P))
        if V is not None:
            E = X - U @ V[j : j + chunk].T
            model2 += float(np.sum(E * E))
    proj = math.sqrt(proj2)
    return (math.sqrt(model2) if V is not None else proj), proj


def _summarise_times(times: list[float]) -> dict[str, Any]:
    t = np.asarray(times)
    rest = t[1:] if t.size > 1 else t
    first5 = rest[:5]
    last5 = rest[-5:]
    return {
        "mean_update_s": float(rest.mean()) if rest.size else math.nan,
        "median_update_s": float(np.median(rest)) if rest.size else math.nan,
        "first_update_s": float(t[0]) if t.size else math.nan,
        "flat_ratio": float(last5.mean() / first5.mean()) if rest.size >= 2 else math.nan,
        "flat_ratio_median": (float(np.median(last5) / np.median(first5)) if rest.size >= 2
                              else math.nan),
        "last_over_second": float(t[-1] / t[1]) if t.size >= 2 else math.nan,
    }


def make_method(spec: dict[str, Any], n: int, columns: int) -> Any:
    """Construct the estimator of one method (see the module notes)."""
    method, b, target = spec["method"], int(spec["block"]), int(spec["target"])
    if method == "streamsvd":
        import streamsvd as ss

        return ss.StreamCompressor(n, max_rank=target, oversampling=0, rule=spec["rule"],
                                   sweeps=spec["sweeps"])
    if method == "brand":
        return BrandSVD(n, rank=target, max_columns=columns, max_block=max(b, target))
    if method == "ipca":
        from sklearn.decomposition import IncrementalPCA

        return IncrementalPCA(n_components=target)
    raise ValueError(f"`method` must be streamsvd, brand or ipca; got {method!r}.")


def update(obj: Any, method: str, A: np.ndarray, a: int, c: int) -> None:
    """Feed columns ``a:c`` (IncrementalPCA: rows ``a:c`` of ``A^T``, C-contiguous)."""
    if method == "ipca":
        obj.partial_fit(A.T[a:c])
    else:
        obj.absorb(A[:, a:c])


def evaluate(obj: Any, spec: dict[str, Any], A: np.ndarray, s: np.ndarray, Q2: np.ndarray,
             done: int) -> dict[str, Any]:
    """Accuracy on the ``done`` columns absorbed, against the reference of what the
    method models (batch SVD; centred batch SVD for IncrementalPCA)."""
    method, target = spec["method"], int(spec["target"])
    n = A.shape[0]
    mean = None
    V = None
    bound = math.nan
    extra: dict[str, Any] = {}
    if method == "streamsvd":
        e = obj.expansion
        U, V = e.U, e.V
        svals = np.asarray(e.amplitudes)
        bound = obj.error_bound
        hist = obj.history
        extra = {
            "sweeps_per_update": [h.sweeps for h in hist],
            "orthogonality_monitored": [h.orthogonality for h in hist],
            "rank": obj.rank,
        }
    elif method == "brand":
        U = obj.U.copy()
        V = obj.V * obj.s
        svals = obj.s.copy()
        bound = obj.error_bound
    else:
        U = obj.components_.T.copy()
        mean = np.asarray(obj.mean_)
        svals = np.asarray(obj.singular_values_)
    ref = reference(s, Q2, done, centered=method == "ipca")
    sigma = ref["sigma"]
    kk = min(target, svals.size, sigma.size)
    sv = np.sort(svals)[::-1][:kk]
    sv_rel = np.abs(sv - sigma[:kk]) / sigma[:kk]
    model_err, proj_err = _frob_errors(A[:, :done], U, V, mean)
    opt = math.sqrt(float(np.sum(sigma[target:] ** 2)))
    fro = ref["fro"]
    orth = float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2))
    return {
        "reference": "centred batch SVD" if method == "ipca" else "batch SVD",
        "sv_rel_err": float(sv_rel.max()) if kk else math.nan,
        "sv_rel_err_top10": float(sv_rel[:10].max()) if kk else math.nan,
        "sv_rel_err_per_index": sv_rel,
        "recon_rel_err": model_err / fro,
        "proj_rel_err": proj_err / fro,
        "opt_rel_err": opt / fro,
        "recon_over_opt": model_err / opt if opt > 0 else math.nan,
        "proj_over_opt": proj_err / opt if opt > 0 else math.nan,
        "error_bound": bound,
        "error_bound_rel": bound / fro,
        "bound_over_error": bound / model_err if model_err > 0 else math.nan,
        "orthogonality": orth,
        "orthogonality_over_n_eps": orth / (n * EPS),
        **extra,
    }


def run_isolated(spec: dict[str, Any], A: np.ndarray, s: np.ndarray,
                 Q2: np.ndarray) -> dict[str, Any]:
    """One run of one method on one configuration: times, peak memory and accuracy.

    Meant to run alone in a fresh process (``--isolation subprocess``). The method is
    warmed up on a tiny problem, the kernel's high-water mark is reset, then the estimator
    is built and fed the stream; the run stops early when its update time passes
    ``spec["budget"]``. The accuracy is measured when ``spec["evaluate"]`` is set or the
    run stopped early.
    """
    method, columns = spec["method"], int(spec["columns"])
    sched = block_schedule(columns, int(spec["block"]), int(spec["target"]))
    budget = float(spec["budget"])
    _warm_up(method, spec.get("rule"), spec.get("sweeps"))
    times: list[float] = []
    done = 0
    load0 = list(os.getloadavg())
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        obj = make_method(spec, A.shape[0], columns)
        construct = time.perf_counter() - t0
        for a, c in sched:
            t0 = time.perf_counter()
            update(obj, method, A, a, c)
            times.append(time.perf_counter() - t0)
            done = c
            if sum(times) > budget and c < columns:
                break
    res: dict[str, Any] = {
        "times": times, "construct_s": construct, "columns_processed": done,
        "cut": len(times) < len(sched),
        "peak_extra_mb": mem.extra_mb, "peak_rss_mb": mem.peak_mb,
        "rss_before_mb": mem.start_mb, "memory_method": mem.method,
        "load_average": [load0, list(os.getloadavg())],
    }
    if spec.get("evaluate") or res["cut"]:
        res["accuracy"] = evaluate(obj, spec, A, s, Q2, done)
    return res


def run_config(specs: list[dict[str, Any]], runner: Any, *, repeats: int) -> dict[str, Any]:
    """Run every method of a configuration ``repeats`` times, alternating the methods.

    Repeat ``r`` runs the methods one after the other (in reverse order on odd repeats),
    each alone (``runner`` starts a fresh process), so that a slow spell of the machine
    does not fall on every run of one method. An update's time is the best over the
    repeats; the peak memory is the largest. A method stopped by the budget in its first
    run is not repeated; its total is extrapolated from the mean of its last 5 updates.
    """
    runs: dict[str, list[dict[str, Any]]] = {sp["label"]: [] for sp in specs}
    for rep in range(repeats):
        order = specs if rep % 2 == 0 else specs[::-1]
        for sp in order:
            lab = sp["label"]
            if runs[lab] and runs[lab][0]["cut"]:
                continue
            runs[lab].append(runner({**sp, "evaluate": rep == repeats - 1}))
    out: dict[str, Any] = {}
    for sp in specs:
        lab = sp["label"]
        rr = runs[lab]
        sched = block_schedule(int(sp["columns"]), int(sp["block"]), int(sp["target"]))
        n_up = min(len(r["times"]) for r in rr)
        best = np.min(np.array([r["times"][:n_up] for r in rr]), axis=0)
        left = len(sched) - n_up
        construct = min(r["construct_s"] for r in rr)
        measured_total = construct + float(best.sum())
        acc = next(r["accuracy"] for r in rr[::-1] if "accuracy" in r)
        out[lab] = {
            **{k: sp.get(k) for k in ("method", "rule", "sweeps", "block", "label")},
            "columns_planned": int(sp["columns"]),
            "columns_processed": rr[0]["columns_processed"],
            "updates_planned": len(sched),
            "updates_done": n_up,
            "repeats_done": len(rr),
            "extrapolated": left > 0,
            "times": best,
            "times_repeats": [r["times"] for r in rr],
            "construct_s": construct,
            "total_s": measured_total + left * float(np.mean(best[-5:])),
            "total_measured_s": measured_total,
            "totals_of_repeats_s": [r["construct_s"] + float(sum(r["times"])) for r in rr],
            **_summarise_times(list(best)),
            "peak_extra_mb": max(r["peak_extra_mb"] for r in rr),
            "peak_rss_mb": max(r["peak_rss_mb"] for r in rr),
            "rss_before_mb": rr[0]["rss_before_mb"],
            "memory_method": rr[0]["memory_method"],
            "load_average_runs": [r["load_average"] for r in rr],
            **acc,
        }
    return out


def run_numpy_svd(spec: dict[str, Any], A: np.ndarray, s: np.ndarray,
                  Q2: np.ndarray) -> dict[str, Any]:
    """Time ``np.linalg.svd(A[:, :k])`` at the requested ``k`` (skipping those predicted
    to exceed the budget), and measure the largest one against the exact reference."""
    ks = sorted(int(k) for k in spec["ks"])
    target, budget = int(spec["target"]), float(spec["budget"])
    _warm_up("numpy", None, None)
    measured: list[dict[str, Any]] = []
    skipped: list[int] = []
    last = None
    with PeakRSS() as mem:
        for k in ks:
            if measured:
                k0, t0_ = measured[-1]["k"], measured[-1]["seconds"]
                if t0_ * (k / k0) ** 2 > budget:
                    skipped.append(k)
                    continue
            t0 = time.perf_counter()
            U, S, _ = np.linalg.svd(A[:, :k], full_matrices=False)
            measured.append({"k": k, "seconds": time.perf_counter() - t0})
            last = (k, U[:, :target].copy(), S.copy())
            del U, _
    if last is None:
        raise ValueError(f"`ks` must list at least one prefix width; got {ks!r}.")
    k, U, S = last
    sigma = reference(s, Q2, k, centered=False)["sigma"]
    kk = min(target, sigma.size)
    sv_rel = np.abs(S[:kk] - sigma[:kk]) / sigma[:kk]
    Ak = A[:, :k]
    V = Ak.T @ U
    model_err, proj_err = _frob_errors(Ak, U, V, None)
    fro = float(np.linalg.norm(s[:, None] * Q2[:k].T))
    opt = math.sqrt(float(np.sum(sigma[target:] ** 2)))
    ks_m = np.array([d["k"] for d in measured], dtype=float)
    ts_m = np.array([d["seconds"] for d in measured])
    basis = np.stack([ks_m, ks_m**2], axis=1)
    coef = np.maximum(np.linalg.lstsq(basis, ts_m, rcond=None)[0], 0.0)
    return {
        "method": "numpy_svd", "label": "numpy svd (all seen)",
        "measured": measured, "skipped_k": skipped, "fit_c1_c2": coef,
        "k_evaluated": k, "peak_extra_mb": mem.extra_mb, "peak_rss_mb": mem.peak_mb,
        "memory_method": mem.method,
        "sv_rel_err": float(sv_rel.max()), "recon_rel_err": model_err / fro,
        "proj_rel_err": proj_err / fro, "opt_rel_err": opt / fro,
        "recon_over_opt": model_err / opt if opt > 0 else math.nan,
        "orthogonality": float(np.linalg.norm(U.T @ U - np.eye(U.shape[1]), 2)),
    }


def numpy_svd_for_stream(svd: dict[str, Any], sched: list[tuple[int, int]]) -> dict[str, Any]:
    """Per-update times of recomputing the SVD of everything seen, from the fitted model."""
    c1, c2 = svd["fit_c1_c2"]
    ks = np.array([c for _, c in sched], dtype=float)
    times = c1 * ks + c2 * ks**2
    return {"method": "numpy_svd", "label": "numpy svd (all seen)", "extrapolated": True,
            "times": times, "total_s": float(times.sum()), **_summarise_times(list(times))}


# ---------------------------------------------------------------------------- orchestration
def _run_job_here(job: dict[str, Any], data: tuple[np.ndarray, np.ndarray, np.ndarray]
                  ) -> dict[str, Any]:
    if job["method"] == "numpy_svd":
        return run_numpy_svd(job, *data)
    return run_isolated(job, *data)


def _run_job_subprocess(job: dict[str, Any], datadir: Path) -> dict[str, Any]:
    spec_path = datadir / "job.json"
    res_path = datadir / "result.json"
    spec_path.write_text(json.dumps({**job, "datadir": str(datadir)}))
    if res_path.exists():
        res_path.unlink()
    proc = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", str(spec_path),
         str(res_path)],
        capture_output=True, text=True, check=False,
    )
    if proc.returncode != 0 or not res_path.exists():
        raise RuntimeError(
            f"benchmark job {job.get('label')} failed (exit {proc.returncode}):\n"
            f"{proc.stderr[-4000:]}"
        )
    return dict(json.loads(res_path.read_text()))


def _worker(spec_path: str, res_path: str) -> None:
    job = json.loads(Path(spec_path).read_text())
    d = Path(job["datadir"])
    data = (np.load(d / "A.npy"), np.load(d / "s.npy"), np.load(d / "Q2.npy"))
    res = _run_job_here(job, data)
    write_json(Path(res_path), res)


def _in_package(fname: str, name: str | None = None) -> bool:
    """Whether a profiled function's file is a module of the streamsvd package."""
    path = Path(fname)
    return "streamsvd" in path.parent.parts and (name is None or path.name == name)


def _profile_parts(stats: dict[Any, Any]) -> tuple[float, dict[str, float]]:
    """Total ``absorb`` time and the time of each part of :data:`PROFILE_PARTS`.

    A function counts towards its part for the calls made from a ``streamsvd`` function
    that is not itself a part (so that nested parts are not counted twice, and a library
    function such as ``qr`` counts only where the package calls it directly).
    """
    part_of = {name: label for label, names in PROFILE_PARTS for name in names}
    absorb = 0.0
    parts: dict[str, float] = {}
    for (fname, _line, func), (_cc, _nc, _tt, ct, callers) in stats.items():
        if func == "absorb" and _in_package(fname, "updates.py"):
            absorb += ct
        label = part_of.get(func)
        if label is None:
            continue
        parts[label] = parts.get(label, 0.0) + sum(
            v[3] for c, v in callers.items()
            if _in_package(c[0]) and c[2] not in part_of
        )
    return absorb, parts


def profile_streamsvd(A: np.ndarray, *, block: int, target: int, rule: str,
                      sweeps: int | None, skip: int, updates: int,
                      repeats: int = 2) -> dict[str, Any]:
    """``cProfile`` of ``updates`` absorbs after ``skip`` unprofiled ones (fastest of
    ``repeats`` runs)."""
    import streamsvd as ss

    _warm_up("streamsvd", rule, sweeps)
    sched = block_schedule(A.shape[1], block, target)
    done = sched[skip : skip + updates]
    runs: list[tuple[float, float, dict[str, float]]] = []
    for _ in range(max(repeats, 1)):
        sc = ss.StreamCompressor(A.shape[0], max_rank=target, oversampling=0, rule=rule,
                                 sweeps=sweeps)
        for a, c in sched[:skip]:
            sc.absorb(A[:, a:c])
        prof = cProfile.Profile()
        t0 = time.perf_counter()
        prof.enable()
        for a, c in done:
            sc.absorb(A[:, a:c])
        prof.disable()
        wall = time.perf_counter() - t0
        absorb, cum = _profile_parts(pstats.Stats(prof).stats)  # type: ignore[attr-defined]
        runs.append((wall, absorb, cum))
    wall, absorb, cum = min(runs, key=lambda r: r[1])
    parts = {k: v / len(done) for k, v in cum.items()}
    per = absorb / len(done)
    parts["other (the update's own code: K, small matrices)"] = max(per - sum(parts.values()), 0.0)
    return {
        "block": block, "rule": rule, "sweeps": sweeps, "updates": len(done),
        "skip": skip, "repeats": repeats, "wall_per_update_s": wall / len(done),
        "profiled_per_update_s": per, "parts_s": parts,
        "parts_share": {k: v / per for k, v in parts.items()} if per > 0 else {},
    }


def long_stream(*, n: int, rank: int, target: int, updates: int, rule: str,
                sweeps: int | None, seed: int, chunk: int) -> dict[str, Any]:
    """Absorb ``updates`` single columns; record orthogonality and time of every update."""
    import streamsvd as ss

    rng = np.random.default_rng(seed + 1)
    r = min(rank, n)
    Q1s = orthonormal(rng, n, r) * spectrum(r)
    _warm_up("streamsvd", rule, sweeps)
    sc = ss.StreamCompressor(n, max_rank=target, oversampling=0, rule=rule, sweeps=sweeps)
    orth = np.empty(updates)
    secs = np.empty(updates)
    ranks = np.empty(updates, dtype=np.int64)
    t_start = time.perf_counter()
    i = 0
    while i < updates:
        w = min(chunk, updates - i)
        Z = np.asfortranarray(Q1s @ rng.standard_normal((r, w)))
        for j in range(w):
            t0 = time.perf_counter()
            rec = sc.absorb(Z[:, j : j + 1])
            secs[i] = time.perf_counter() - t0
            orth[i] = rec.orthogonality
            ranks[i] = rec.rank
            i += 1
    wall = time.perf_counter() - t_start
    nb = max(1, math.ceil(updates / chunk))
    edges = [min(k * chunk, updates) for k in range(nb + 1)]
    tol = 50 * n * EPS
    first = orth[: max(1, updates // 10)]
    last = orth[-max(1, updates // 10) :]
    reorth_tol = 10 * n * EPS
    return {
        "n": n, "modes": r, "target": target, "updates": updates, "rule": rule,
        "sweeps": sweeps, "wall_s": wall, "chunk": chunk,
        "n_eps": n * EPS, "limit_50_n_eps": tol, "reorth_tol_default": reorth_tol,
        "max_orthogonality": float(orth.max()),
        "final_orthogonality": float(orth[-1]),
        "max_first_10pct": float(first.max()), "max_last_10pct": float(last.max()),
        "mean_first_10pct": float(first.mean()), "mean_last_10pct": float(last.mean()),
        "below_limit": bool(orth.max() < tol),
        "updates_above_reorth_tol": int(np.count_nonzero(orth > reorth_tol)),
        "chunk_start": edges[:-1],
        "chunk_max_orth": [float(orth[a:c].max()) for a, c in zip(edges, edges[1:], strict=False)],
        "chunk_mean_orth": [float(orth[a:c].mean()) for a, c in zip(edges, edges[1:],
                                                                     strict=False)],
        "chunk_mean_update_s": [float(secs[a:c].mean()) for a, c in zip(edges, edges[1:],
                                                                         strict=False)],
        "first_chunk_mean_update_s": float(secs[:chunk].mean()),
        "last_chunk_mean_update_s": float(secs[-chunk:].mean()),
        "final_rank": int(ranks[-1]),
        "error_bound": sc.error_bound,
    }


# ---------------------------------------------------------------------------- reading
def _label(method: str, rule: str | None = None, sweeps: int | None = None) -> str:
    if method == "streamsvd":
        return f"streamsvd {rule} sweeps={SWEEP_LABEL[sweeps]}"
    return {"brand": "Brand (CGS2+QR+gesdd)", "ipca": "IncrementalPCA",
            "numpy_svd": "numpy svd (all seen)"}[method]


def assess_targets(results: dict[str, Any], ortho: dict[str, Any] | None,
                   *, slack: float) -> dict[str, Any]:
    """Read the measurements against the three targets of the benchmark.

    Speed: IncrementalPCA's mean time per update (updates 2..N) over each streamsvd
    configuration's. "At equal or better accuracy" is read two ways, both reported:
    against IncrementalPCA's own errors (each method measured against the batch SVD of
    what it models), and against Brand's (the exact SVD of [kept factors, block] at every
    update, which is IncrementalPCA's update without the centring, on the same data as
    streamsvd). A configuration is as accurate when its singular value error and its
    projection error over the optimum are at most ``slack`` times the reference's.
    """
    speed: dict[str, Any] = {}
    flat: dict[str, Any] = {}

    def as_good(r: dict[str, Any], ref: dict[str, Any] | None) -> bool | None:
        if ref is None:
            return None
        return bool(r["sv_rel_err"] <= ref["sv_rel_err"] * slack
                    and r["proj_over_opt"] <= ref["proj_over_opt"] * slack)

    for cname, conf in results.items():
        methods = conf["methods"]
        ip = next((r for r in methods.values() if r["method"] == "ipca"), None)
        br = next((r for r in methods.values() if r["method"] == "brand"), None)
        if ip is not None:
            rows = []
            for lab, r in methods.items():
                if r["method"] != "streamsvd":
                    continue
                rows.append({
                    "label": lab,
                    "speedup_per_update": ip["mean_update_s"] / r["mean_update_s"],
                    "speedup_median": ip["median_update_s"] / r["median_update_s"],
                    "speedup_total": ip["total_s"] / r["total_s"],
                    "as_accurate_as_ipca": as_good(r, ip),
                    "as_accurate_as_exact_update": as_good(r, br),
                })
            verdict: dict[str, Any] = {"rows": rows}
            for key in ("as_accurate_as_ipca", "as_accurate_as_exact_update"):
                ok = [x for x in rows if x[key]]
                best = max(ok, key=lambda x: x["speedup_per_update"]) if ok else None
                verdict[f"best_{key}"] = best
                verdict[f"met_{key}"] = bool(best is not None
                                             and best["speedup_per_update"] >= 10.0)
            speed[cname] = verdict
        flat[cname] = {
            lab: {"flat_ratio": r["flat_ratio"], "flat_ratio_median": r["flat_ratio_median"],
                  "last_over_second": r["last_over_second"],
                  "met": bool(r["flat_ratio"] <= 1.2)}
            for lab, r in methods.items() if r["method"] in ("streamsvd", "brand")
        }
    out: dict[str, Any] = {
        "speed_10x_ipca": speed,
        "flat_time_1.2x": flat,
        "accuracy_slack": slack,
    }
    if ortho is not None:
        out["orthogonality_50_n_eps"] = {
            "updates": ortho["updates"], "max": ortho["max_orthogonality"],
            "limit": ortho["limit_50_n_eps"], "met": ortho["below_limit"],
            "max_first_10pct": ortho["max_first_10pct"],
            "max_last_10pct": ortho["max_last_10pct"],
        }
    return out


def plot(results: dict[str, Any], ortho: dict[str, Any] | None, path: Path,
         *, title: str) -> None:
    plt = pyplot()
    from matplotlib.ticker import NullFormatter

    confs = list(results)
    ncol = max(len(confs), 3)
    fig, axes = plt.subplots(2, ncol, figsize=(5.2 * ncol, 9.0))
    styles = {
        ("paper", 1): ("C0", "-"), ("paper", 2): ("C0", "--"), ("paper", None): ("C0", ":"),
        ("jacobi", 1): ("C1", "-"), ("jacobi", 2): ("C1", "--"), ("jacobi", None): ("C1", ":"),
    }
    for ax, cname in zip(axes[0], confs, strict=False):
        conf = results[cname]
        for lab, r in conf["methods"].items():
            t = np.asarray(r["times"])
            idx = np.arange(1, t.size + 1)
            if r["method"] == "streamsvd":
                c, ls = styles[(r["rule"], r["sweeps"])]
                ax.plot(idx, t, color=c, ls=ls, lw=1.2, label=lab)
            elif r["method"] == "brand":
                ax.plot(idx, t, color="k", lw=1.5, label=lab)
            elif r["method"] == "ipca":
                ax.plot(idx, t, color="C3", lw=1.2, label=lab)
        svd = conf.get("numpy_svd")
        if svd is not None:
            t = np.asarray(svd["times"])
            ax.plot(np.arange(1, t.size + 1), t, color="C2", lw=1.0, ls="-.",
                    label="numpy svd of all seen (fit)")
        ax.set_yscale("log")
        ax.set_xlabel("update")
        ax.set_ylabel("seconds per update")
        ax.set_title(f"block {conf['block']}: {conf['columns']} columns, "
                     f"{conf['updates']} updates", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=6.5, loc="best")
    for ax in axes[0][len(confs):]:
        ax.axis("off")
    markers = {100: "o", 10: "s", 1: "^"}
    for ax, key, xl in (
        (axes[1][0], "sv_rel_err", "max relative error of the top singular values"),
        (axes[1][1], "recon_over_opt",
         "reconstruction error / optimal (IncrementalPCA: projection, centred)"),
    ):
        for cname in confs:
            conf = results[cname]
            mk = markers.get(conf["block"], "D")
            for lab, r in conf["methods"].items():
                if r["method"] == "streamsvd":
                    c = styles[(r["rule"], r["sweeps"])][0]
                else:
                    c = {"brand": "k", "ipca": "C3"}[r["method"]]
                face = "none" if r["method"] == "streamsvd" and r["sweeps"] is not None else c
                ax.scatter(r[key], r["total_s"], marker=mk, edgecolors=c, facecolors=face,
                           s=40)
                if conf is results[confs[0]]:
                    ax.annotate(lab.replace("streamsvd ", ""), (r[key], r["total_s"]),
                                fontsize=6, xytext=(3, 2), textcoords="offset points")
        if key == "sv_rel_err":
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_yscale("log")
        ax.set_xlabel(xl, fontsize=8)
        ax.set_ylabel("total seconds")
        ax.set_title("Pareto (o block 100, s block 10, ^ block 1; filled = converged)",
                     fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
    ax = axes[1][2]
    if ortho is not None:
        x = np.asarray(ortho["chunk_start"]) + ortho["chunk"]
        ax.plot(x, ortho["chunk_max_orth"], color="C0", label="max over chunk")
        ax.plot(x, ortho["chunk_mean_orth"], color="C0", ls="--", lw=0.8, label="mean")
        ax.axhline(ortho["limit_50_n_eps"], color="C3", lw=0.8, label="50 n eps")
        ax.axhline(ortho["reorth_tol_default"], color="gray", lw=0.8, ls=":",
                   label="re-orth. threshold 10 n eps")
        ax.set_yscale("log")
        ax.set_xlabel("update")
        ax.set_ylabel("||U^T U - I||_2")
        ax2 = ax.twinx()
        ax2.plot(x, np.asarray(ortho["chunk_mean_update_s"]) * 1e3, color="C2", lw=0.8)
        ax2.set_ylabel("ms per update (green)")
        ax.legend(fontsize=7, loc="lower right")
        ax.set_title(f"long stream: n={ortho['n']}, rank {ortho['target']}, "
                     f"{ortho['updates']} single-column updates", fontsize=9)
    else:
        ax.axis("off")
    for ax in axes[1][3:]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------- main
def _parse_prefix(text: str) -> dict[int, int]:
    out: dict[int, int] = {}
    for item in filter(None, text.split(",")):
        b, k = item.split(":")
        out[int(b)] = int(k)
    return out


def _parse_sweeps(text: str) -> list[int | None]:
    return [None if x.strip().lower() in ("none", "conv") else int(x) for x in text.split(",")]


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    record = Run("stream_benchmark", argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=None, help="output directory (default bench/results)")
    p.add_argument("--n", type=int, default=20000, help="snapshot size")
    p.add_argument("--m", type=int, default=2000, help="snapshots in the stream")
    p.add_argument("--rank", type=int, default=300, help="modes of the data (s: 1 .. 1e-10)")
    p.add_argument("--target", type=int, default=60, help="rank kept by every method")
    p.add_argument("--blocks", default="100,10,1", help="block widths")
    p.add_argument("--prefix", default="10:1000,1:200",
                   help="b:k, run block width b on the first k columns only")
    p.add_argument("--rules", default="paper,jacobi")
    p.add_argument("--sweeps", default="1,2,none", help="sweeps per update (none: converged)")
    p.add_argument("--methods", default="streamsvd,brand,ipca,numpy_svd")
    p.add_argument("--budget", type=float, default=150.0,
                   help="seconds of updates per method and configuration before stopping")
    p.add_argument("--svd-k", default="100,200,400,800,2000",
                   help="prefix widths at which numpy's SVD is timed")
    p.add_argument("--repeats", type=int, default=3,
                   help="runs of each stream; an update's time is the best of them")
    p.add_argument("--isolation", choices=("subprocess", "inprocess"), default="subprocess",
                   help="run each method alone in a fresh process, or all in this one")
    p.add_argument("--accuracy-slack", type=float, default=1.01,
                   help="'as accurate as IncrementalPCA' means errors <= slack * its errors")
    p.add_argument("--no-profile", action="store_true")
    p.add_argument("--profile-updates", default="100:5,10:30,1:100",
                   help="b:count of updates profiled per block width")
    p.add_argument("--ortho-updates", type=int, default=10000)
    p.add_argument("--long", action="store_true", help="long stream of --long-updates")
    p.add_argument("--long-updates", type=int, default=100000)
    p.add_argument("--long-n", type=int, default=1000)
    p.add_argument("--long-target", type=int, default=20)
    p.add_argument("--long-rule", default="paper")
    p.add_argument("--long-sweeps", default="1")
    p.add_argument("--long-chunk", type=int, default=1000)
    p.add_argument("--seed", type=int, default=20261122)
    p.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        _worker(*args.worker)
        return {}
    out = out_dir(args.out)
    t_start = time.perf_counter()
    load_before = list(os.getloadavg())
    blocks = [int(x) for x in args.blocks.split(",") if x]
    prefix = _parse_prefix(args.prefix)
    rules = [r for r in args.rules.split(",") if r]
    sweeps_list = _parse_sweeps(args.sweeps)
    methods = [x for x in args.methods.split(",") if x]
    t0 = time.perf_counter()
    A, s, Q2 = make_data(args.n, args.m, args.rank, args.seed)
    gen_s = time.perf_counter() - t0
    n, m = A.shape
    data = (A, s, Q2)
    tmp = tempfile.TemporaryDirectory(prefix="stream_bench_")
    datadir = Path(tmp.name)
    if args.isolation == "subprocess":
        np.save(datadir / "A.npy", A)
        np.save(datadir / "s.npy", s)
        np.save(datadir / "Q2.npy", Q2)

    def run(job: dict[str, Any]) -> dict[str, Any]:
        t = time.perf_counter()
        res = (_run_job_subprocess(job, datadir) if args.isolation == "subprocess"
               else _run_job_here(job, data))
        print(f"    {job['label']:<34s} block {job.get('block', '-')!s:>4}: "
              f"{time.perf_counter() - t:6.1f} s", flush=True)
        return res

    svd_res = None
    if "numpy_svd" in methods:
        ks = sorted({min(int(k), m) for k in args.svd_k.split(",") if k})
        svd_res = run({"method": "numpy_svd", "label": _label("numpy_svd"), "ks": ks,
                       "target": args.target, "budget": args.budget})
    results: dict[str, Any] = {}
    for b in blocks:
        m_use = min(prefix.get(b, m), m)
        sched = block_schedule(m_use, b, args.target)
        specs: list[dict[str, Any]] = []
        if "streamsvd" in methods:
            for rule in rules:
                for sw in sweeps_list:
                    specs.append({"method": "streamsvd", "rule": rule, "sweeps": sw})
        for meth in ("brand", "ipca"):
            if meth in methods:
                specs.append({"method": meth})
        for sp in specs:
            sp.update(block=b, columns=m_use, target=args.target,
                      label=_label(sp["method"], sp.get("rule"), sp.get("sweeps")))
        for sp in specs:
            sp["budget"] = args.budget
        t = time.perf_counter()
        load0 = list(os.getloadavg())
        res = run_config(specs, run, repeats=args.repeats)
        print(f"  block {b}: {len(specs)} methods x {len(sched)} updates x "
              f"{args.repeats} repeats: {time.perf_counter() - t:.1f} s", flush=True)
        conf: dict[str, Any] = {"block": b, "columns": m_use, "updates": len(sched),
                                "first_block": sched[0][1], "methods": res,
                                "load_average_before": load0,
                                "load_average_after": list(os.getloadavg())}
        if svd_res is not None:
            conf["numpy_svd"] = numpy_svd_for_stream(svd_res, sched)
        results[f"block{b}"] = conf
    profiles = []
    if not args.no_profile and "streamsvd" in methods:
        counts = _parse_prefix(args.profile_updates)
        for b in blocks:
            m_use = min(prefix.get(b, m), m)
            sched = block_schedule(m_use, b, args.target)
            cnt = min(counts.get(b, 10), max(len(sched) - 1, 1))
            skip = min(1, len(sched) - 1)
            for rule, sw in (("jacobi", 1), ("paper", None)):
                if rule in rules and sw in sweeps_list:
                    profiles.append(profile_streamsvd(
                        A[:, :m_use], block=b, target=args.target, rule=rule, sweeps=sw,
                        skip=skip, updates=cnt))
    ortho = None
    n_ortho = args.long_updates if args.long else args.ortho_updates
    if n_ortho > 0:
        t = time.perf_counter()
        ortho = long_stream(n=args.long_n, rank=args.rank, target=args.long_target,
                            updates=n_ortho, rule=args.long_rule,
                            sweeps=_parse_sweeps(args.long_sweeps)[0], seed=args.seed,
                            chunk=min(args.long_chunk, n_ortho))
        print(f"  long stream ({n_ortho} updates): {time.perf_counter() - t:.1f} s",
              flush=True)
    tmp.cleanup()
    targets = assess_targets(results, ortho, slack=args.accuracy_slack)
    report: dict[str, Any] = {
        "machine": machine_info(),
        "load_average_before": load_before,
        "load_average_after": list(os.getloadavg()),
        "args": vars(args),
        "data": {"n": n, "m": m, "modes": s.size, "target": args.target, "seed": args.seed,
                 "generation_s": gen_s, "sigma_top": s[: args.target]},
        "isolation": args.isolation,
        "numpy_svd": svd_res,
        "configurations": results,
        "profiles": profiles,
        "long_stream": ortho,
        "targets": targets,
        "wall_s": time.perf_counter() - t_start,
    }
    record.write(out / "stream_benchmark.json", report)
    plot(results, ortho, out / "stream_benchmark.png",
         title=f"stream n={n}, m={m}, {s.size} modes (1..1e-10), target rank {args.target}")
    _print_summary(report)
    return report


def _print_summary(report: dict[str, Any]) -> None:
    rows = []
    for conf in report["configurations"].values():
        for lab, r in conf["methods"].items():
            rows.append([conf["block"], lab, r["mean_update_s"], r["total_s"],
                         "x" if r["extrapolated"] else "", r["peak_extra_mb"], r["sv_rel_err"],
                         r["recon_rel_err"], r["recon_over_opt"], r["error_bound_rel"],
                         r["orthogonality"], r["flat_ratio"]])
    print_table(["block", "method", "s/update", "total s", "extr", "peak MB", "sv err",
                 "recon err", "/opt", "bound", "orth", "flat"], rows,
                title="streaming benchmark")
    for cname, v in report["targets"]["speed_10x_ipca"].items():
        print_table(["streamsvd", "x IPCA /update", "median", "total", "acc>=IPCA",
                     "acc>=exact"],
                    [[x["label"], x["speedup_per_update"], x["speedup_median"],
                      x["speedup_total"], x["as_accurate_as_ipca"],
                      x["as_accurate_as_exact_update"]] for x in v["rows"]],
                    title=f"{cname}: speed-up over IncrementalPCA")
    svd = report["numpy_svd"]
    if svd is not None:
        print_table(["k", "seconds"], [[d["k"], d["seconds"]] for d in svd["measured"]],
                    title="numpy svd of the first k columns")
    for prof in report["profiles"]:
        print(f"profile block {prof['block']} {prof['rule']} sweeps={prof['sweeps']}: "
              f"{prof['profiled_per_update_s']:.4f} s/update; "
              + ", ".join(f"{k} {v:.0%}" for k, v in prof["parts_share"].items()))
    lo = report["long_stream"]
    if lo is not None:
        print(f"long stream: {lo['updates']} updates, max ||U^T U - I|| = "
              f"{lo['max_orthogonality']:.2e} (50 n eps = {lo['limit_50_n_eps']:.2e}), "
              f"{lo['first_chunk_mean_update_s'] * 1e3:.2f} -> "
              f"{lo['last_chunk_mean_update_s'] * 1e3:.2f} ms/update")


if __name__ == "__main__":
    main()
