"""streamsvd side by side with pyMOR's HAPOD (and Brand's incremental SVD) in one run.

Three cases, each contender in its own process (a spawned worker per contender, reused
across the runs of a case), the runs interleaved (repeat r of every contender before
repeat r + 1 of any), medians of ``--repeat`` wall times, one BLAS thread per worker
(threadpoolctl and the ``*_NUM_THREADS`` variables) unless a row says otherwise, and
``os.getloadavg()`` recorded before and after every case:

* ``burgers``: pyMOR's own HAPOD demo (``pymordemos/hapod.py``): the 2-D Burgers problem
  ``burgers_problem_2d()`` discretised by ``discretize_instationary_fv`` on a ``RectGrid``
  of diameter ``sqrt(2)/60`` (7200 dofs) with ``nt=100``, 20 trajectories at parameters
  ``p.parameter_space.sample_randomly(20)`` (101 snapshots each, 2020 in all), the
  model's ``l2_product`` as inner product. One trajectory per update.
* ``heat``: pyMOR's ``heat_equation_example()`` (``pymor.models.examples``: P1 finite
  elements, 5101 dofs, ``nt=50``), 20 trajectories of 51 snapshots at
  ``fom.parameters.space(1, 100).sample_randomly(20)``, its ``l2_product``; one trajectory
  per update. pyMOR ships no HAPOD demo for it; the setup mirrors the Burgers demo.
* ``synthetic``: ``A = Q1 diag(s) Q2^T`` (n = 20000, m = 2000, ``s`` log-spaced from 1 to
  1e-10 over 300 values, random orthonormal factors, seed 0), blocks of 100 and of 10,
  a rank cap of 60.

The snapshots are generated once (with pyMOR for the first two) and cached under
``--cache`` (``.npy`` snapshots, the inner product as a ``scipy.sparse`` ``.npz``, the
LAPACK singular values of the synthetic matrix), so every contender reads the same data,
each in its own layout made outside the timed region: contiguous vectors for pyMOR (a
``NumpyVectorArray``), contiguous columns for streamsvd and Brand.

Contenders at a target mean-l2 error ``eps`` (``burgers``, ``heat``):
``inc_vectorarray_hapod(steps, U, eps, omega, product=l2)`` and
``dist_vectorarray_hapod(steps, U, eps, omega, product=l2)`` as the demo calls them,
``pod(U, l2_err=eps*sqrt(m), product=l2)`` (the optimum: the fewest modes; one run,
not timed against the others), streamsvd (:func:`run_streamsvd`) and its tree mode
(:func:`run_streamsvd_tree`, one trajectory per leaf, against ``dist_hapod``). For each the true
error ``sqrt(sum_j ||a_j - P a_j||_M^2 / m)`` with ``P`` the M-orthogonal projection on
the returned modes (through their Gram matrix: exact also for modes that are not quite
orthonormal), the modes and the time.

Contenders at the rank cap (``synthetic``): streamsvd, pyMOR's incremental HAPOD tree
with ``pod(modes=60)`` at every step (``hapod(inc_hapod_tree(steps), ...)`` with a
``pod_method``: the HAPOD functions take no rank cap themselves), ``BrandSVD`` and
``TunedBrandSVD`` (``bench/brand.py``). Reported: time, ``sv_err = max_i<60
|s_i - s_i(LAPACK)| / s_i``, and ``err/opt = ||A - Q Q^T A||_F / ||A - A_60||_F``.
``--variants`` adds contenders that keep ``K`` more terms (``NAME_oK``): streamsvd with
``oversampling=K`` (10 by default), the HAPOD tree with ``pod(modes=60 + K)`` at every
step and the root's first 60 modes returned; each contender's variants are drawn as one
line of time against error, so that the two are compared at equal accuracy.

The ``threads`` row: streamsvd on ``burgers`` at ``--threads-target`` with the default
BLAS threads against one thread.

``--quick`` runs every case on a tiny size (for the smoke test).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import REPO_ROOT, Run, machine_info, out_dir, print_table, pyplot  # noqa: E402

DEFAULT_CACHE = REPO_ROOT / "bench" / "data" / "hapod"
TARGETS = (1e-2, 1e-3, 1e-4)
OMEGA = 0.9


# --------------------------------------------------------------------------- the streamsvd route


def run_streamsvd(blocks: Any, opts: dict[str, Any]) -> tuple[np.ndarray, float]:
    """Stream ``blocks`` through streamsvd; return the left vectors and the error bound.

    ``opts``: ``n``, ``inner`` and either ``target`` (a mean-l2 error: the compressor's
    ``target_error`` with ``error_measure="mean_l2"``) or ``max_rank``. The core is
    converged at every update (Jacobi rule) and ``finalize()`` makes the last cut. Like
    pyMOR's HAPOD, it returns the modes and forms no right vectors (``right_vectors=False``).
    """
    import streamsvd as ss

    kw: dict[str, Any] = {"inner": opts.get("inner"), "rule": "jacobi", "sweeps": None,
                          "right_vectors": False}
    if opts.get("oversampling") is not None:
        kw["oversampling"] = opts["oversampling"]
    target = opts.get("target")
    if target is None:
        sc = ss.StreamCompressor(opts["n"], max_rank=opts["max_rank"], **kw)
    else:
        sc = ss.StreamCompressor(opts["n"], target_error=target, error_measure="mean_l2", **kw)
    for block in blocks:
        sc.absorb(block)
    sc.finalize()
    return sc.left_vectors, sc.error_bound


def run_streamsvd_tree(X: np.ndarray, leaf: int, opts: dict[str, Any]) -> tuple[np.ndarray, float]:
    """``tree_compress`` with one trajectory (``leaf`` columns) per leaf, then ``finalize``.

    As ``dist_vectorarray_hapod``: the leaves spend the streaming share of the target,
    the merges none, the root's final cut the rest (dask's threaded scheduler).
    """
    from streamsvd.parallel.cluster import tree_compress

    root = tree_compress(X, block=leaf, leaf_columns=leaf, inner=opts.get("inner"),
                            target_error=opts["target"], error_measure="mean_l2",
                            rule="jacobi", sweeps=None)
    root.finalize()
    return root.left_vectors, root.error_bound


# --------------------------------------------------------------------------- data


def _cache_names(case: str, quick: bool) -> dict[str, str]:
    tag = f"{case}_quick" if quick else case
    return {"X": f"{tag}_snapshots.npy", "M": f"{tag}_l2.npz", "s": f"{tag}_svals.npy",
            "meta": f"{tag}_meta.npy"}


def _size(case: str, quick: bool) -> dict[str, int]:
    if case == "burgers":
        return {"grid": 8, "nt": 20, "snap": 4} if quick else {"grid": 60, "nt": 100, "snap": 20}
    if case == "heat":
        return {"grid": 8, "nt": 10, "snap": 4} if quick else {"grid": 50, "nt": 50, "snap": 20}
    return ({"n": 600, "m": 200, "rank": 40, "cap": 10, "blocks": (20, 5)} if quick
            else {"n": 20000, "m": 2000, "rank": 300, "cap": 60, "blocks": (100, 10)})


def generate(case: str, cache: Path, quick: bool) -> dict[str, Path]:
    """Write the snapshots of ``case`` to ``cache`` once; return the file paths."""
    cache.mkdir(parents=True, exist_ok=True)
    names = {k: cache / v for k, v in _cache_names(case, quick).items()}
    size = _size(case, quick)
    if case == "synthetic":
        if not names["X"].is_file():
            rng = np.random.default_rng(0)
            n, m, r = size["n"], size["m"], size["rank"]
            Q1, _ = np.linalg.qr(rng.standard_normal((n, r)))
            Q2, _ = np.linalg.qr(rng.standard_normal((m, r)))
            s = np.logspace(0, -10, r)
            np.save(names["X"], np.asfortranarray((Q1 * s) @ Q2.T))
        if not names["s"].is_file():
            import scipy.linalg as sla

            X = np.load(names["X"])
            np.save(names["s"], sla.svd(X, compute_uv=False, check_finite=False))
        return names
    if names["X"].is_file() and names["M"].is_file() and names["meta"].is_file():
        return names
    _quiet_pymor()
    if case == "burgers":  # pymordemos/hapod.py, verbatim but for the sizes
        from pymor.analyticalproblems.burgers import burgers_problem_2d
        from pymor.discretizers.builtin import RectGrid, discretize_instationary_fv

        p = burgers_problem_2d()
        m, _ = discretize_instationary_fv(p, grid_type=RectGrid,
                                          diameter=np.sqrt(2) / size["grid"], nt=size["nt"])
        mus = p.parameter_space.sample_randomly(size["snap"])
    else:
        from pymor.models.examples import heat_equation_example

        m = heat_equation_example(grid_intervals=size["grid"], nt=size["nt"])
        mus = m.parameters.space(1, 100).sample_randomly(size["snap"])
    U = m.solution_space.empty()
    lengths = []
    for mu in mus:
        Ui = m.solve(mu)
        lengths.append(len(Ui))
        U.append(Ui)
    np.save(names["X"], np.asfortranarray(U.to_numpy()))
    sp.save_npz(names["M"], sp.csr_matrix(m.l2_product.matrix))
    np.save(names["meta"], np.array(lengths))
    return names


# --------------------------------------------------------------------------- in the workers

_DATA: dict[str, Any] = {}
_LIMITS: dict[str, int | None] = {"threads": None}


def _quiet_pymor() -> None:
    from pymor.core.logger import set_log_levels

    set_log_levels({"pymor": "WARN"})


def _init_worker(threads: int | None, contender: str) -> None:
    """Limit the BLAS threads; warm the contender up (imports, numba's cache) untimed."""
    if threads is not None:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=threads)
    _LIMITS["threads"] = threads
    rng = np.random.default_rng(1)
    X = rng.standard_normal((50, 12)) @ np.diag(np.logspace(0, -6, 12))
    M = sp.identity(50, format="csr")
    contender = _variant(contender)[0]
    if contender in ("streamsvd", "streamsvd_tree"):
        for opts in ({"n": 50, "m": 12, "inner": M, "target": 1e-3},
                     {"n": 50, "max_rank": 4}):
            run_streamsvd((X[:, j : j + 4] for j in range(0, 12, 4)), opts)
    elif contender in ("pod", "inc_hapod", "dist_hapod"):
        _quiet_pymor()
        from pymor.algorithms.hapod import inc_vectorarray_hapod

        U, prod = _pymor_space(X, M)
        inc_vectorarray_hapod(3, U, 1e-3, OMEGA, product=prod)
        _pymor_capped_hapod([U[j : j + 4] for j in range(0, 12, 4)], 4)


def _load(names: dict[str, str]) -> dict[str, Any]:
    key = names["X"]
    if _DATA.get("key") != key:
        _DATA.clear()
        _DATA["key"] = key
        _DATA["X"] = np.load(names["X"])
        if Path(names["M"]).is_file():
            _DATA["M"] = sp.load_npz(names["M"]).tocsr()
        if Path(names["meta"]).is_file():
            _DATA["lengths"] = np.load(names["meta"])
        if Path(names["s"]).is_file():
            _DATA["s"] = np.load(names["s"])
    return _DATA


def _columns(d: dict[str, Any]) -> np.ndarray:
    """The snapshots with contiguous columns (streamsvd's layout), made once, untimed.

    pyMOR's contenders get theirs as a ``NumpyVectorArray`` (contiguous vectors), also
    made outside the timed region (:func:`_pymor_space`).
    """
    if "XF" not in d:
        d["XF"] = np.asfortranarray(d["X"])
    return d["XF"]


def _projection_error2(X: np.ndarray, Q: np.ndarray, M: Any) -> np.ndarray:
    """``||x_j - P x_j||_M^2`` per column, ``P`` the M-orthogonal projection on span(Q)."""
    if Q.shape[1] == 0:
        R = X
    else:
        MQ = M @ Q if M is not None else Q
        G = Q.T @ MQ
        C = np.linalg.solve(G, MQ.T @ X)
        R = X - Q @ C
    MR = M @ R if M is not None else R
    return np.einsum("ij,ij->j", R, MR)


def _pymor_space(X: np.ndarray, M: Any) -> tuple[Any, Any]:
    from pymor.operators.numpy import NumpyMatrixOperator
    from pymor.vectorarrays.numpy import NumpyVectorSpace

    U = NumpyVectorSpace(X.shape[0]).from_numpy(X)
    return U, (NumpyMatrixOperator(M) if M is not None else None)


def task_target(names: dict[str, str], contender: str, target: float,
                measure: bool) -> dict[str, Any]:
    """One run of ``contender`` at a target mean-l2 error on a cached trajectory set."""
    d = _load(names)
    X, M, lengths = d["X"], d["M"], d["lengths"]
    n, m = X.shape
    steps = len(lengths)
    bound = None
    if contender == "streamsvd_tree":
        Xf = _columns(d)
        t0 = time.perf_counter()
        Q, bound = run_streamsvd_tree(Xf, int(lengths[0]), {"inner": M, "target": target})
        seconds = time.perf_counter() - t0
    elif contender == "streamsvd":
        starts = np.concatenate([[0], np.cumsum(lengths)])
        opts = {"n": n, "m": m, "inner": M, "target": target}
        Xf = _columns(d)
        t0 = time.perf_counter()
        Q, bound = run_streamsvd((Xf[:, a:b] for a, b in zip(starts[:-1], starts[1:],
                                                             strict=True)), opts)
        seconds = time.perf_counter() - t0
    else:
        from pymor.algorithms.hapod import dist_vectorarray_hapod, inc_vectorarray_hapod
        from pymor.algorithms.pod import pod

        U, prod = _pymor_space(X, M)
        t0 = time.perf_counter()
        if contender == "inc_hapod":
            modes = inc_vectorarray_hapod(steps, U, target, OMEGA, product=prod)[0]
        elif contender == "dist_hapod":
            modes = dist_vectorarray_hapod(steps, U, target, OMEGA, product=prod)[0]
        else:
            modes = pod(U, l2_err=target * np.sqrt(len(U)), product=prod)[0]
        seconds = time.perf_counter() - t0
        Q = modes.to_numpy()
    out: dict[str, Any] = {"seconds": seconds, "modes": int(Q.shape[1]), "bound": bound,
                           "load": os.getloadavg()[0], "threads": _LIMITS["threads"]}
    if measure:
        out["error"] = float(np.sqrt(np.sum(_projection_error2(X, Q, M)) / m))
        G = Q.T @ (M @ Q)
        out["orthogonality"] = float(np.linalg.norm(G - np.eye(Q.shape[1]), 2)) if Q.size else 0.0
        if bound is not None:
            out["bound_mean_l2"] = bound / math.sqrt(m)
    return out


# terms kept beyond the cap by default: streamsvd's oversampling, none for HAPOD
_DEFAULT_EXTRA = {"streamsvd": 10, "inc_hapod": 0}


def _variant(contender: str) -> tuple[str, int | None]:
    """Split ``"name_oK"`` into ``("name", K)``: the contender with ``K`` extra terms kept."""
    name, sep, extra = contender.rpartition("_o")
    if sep and extra.isdigit():
        return name, int(extra)
    return contender, None


def _pymor_capped_hapod(blocks: list[Any], cap: int) -> Any:
    """pyMOR's incremental HAPOD tree with ``pod(modes=cap)`` at every step."""
    from pymor.algorithms.hapod import hapod, inc_hapod_tree
    from pymor.algorithms.pod import pod

    it = iter(blocks)

    def pod_method(U: Any, eps: float, is_root: bool, product: Any) -> Any:
        return pod(U, modes=cap, atol=0.0, rtol=0.0, l2_err=eps, product=product,
                   orth_tol=None if is_root else np.inf)

    # a zero eps skips the POD of a node (hapod: `if eps:`): the leaves are passed on
    # whole, every other node gets an eps far below any singular value
    return hapod(inc_hapod_tree(len(blocks)), lambda node: next(it),
                 lambda node, snap_count, input_count: 0.0 if node.is_leaf else 1e-300,
                 pod_method=pod_method)[0]


def task_cap(names: dict[str, str], contender: str, block: int, cap: int,
             measure: bool) -> dict[str, Any]:
    """One run of ``contender`` with a rank cap on the synthetic stream."""
    import brand

    d = _load(names)
    X, s = d["X"], d["s"]
    n, m = X.shape
    cols = [slice(j, min(j + block, m)) for j in range(0, m, block)]
    base, extra = _variant(contender)
    if base == "streamsvd":
        Xf = _columns(d)
        t0 = time.perf_counter()
        Q, _ = run_streamsvd((Xf[:, c] for c in cols),
                             {"n": n, "max_rank": cap, "oversampling": extra})
        seconds = time.perf_counter() - t0
    elif base == "inc_hapod":
        U, _ = _pymor_space(X, None)
        blocks = [U[c] for c in cols]
        t0 = time.perf_counter()
        # with extra terms, every step keeps cap + extra modes and the root's first cap
        # are returned (the modes come sorted by singular value)
        modes = _pymor_capped_hapod(blocks, cap + (extra or 0))[:cap]
        seconds = time.perf_counter() - t0
        Q = modes.to_numpy()
    else:
        cls = brand.BrandSVD if contender == "brand" else brand.TunedBrandSVD
        Xf = _columns(d)
        t0 = time.perf_counter()
        svd = cls(n, rank=cap, max_columns=m, max_block=max(block, cap))
        for c in cols:
            svd.absorb(Xf[:, c])
        seconds = time.perf_counter() - t0
        Q = svd.U.copy()
    out: dict[str, Any] = {"seconds": seconds, "modes": int(Q.shape[1]),
                           "load": os.getloadavg()[0]}
    if measure:
        C = Q.T @ X
        err = float(np.linalg.norm(X - Q @ C))
        amps = np.linalg.svd(C, compute_uv=False)[:cap]
        k = min(cap, amps.size)
        out["sv_err"] = float(np.max(np.abs(amps[:k] - s[:k]) / s[:k]))
        out["err_opt"] = err / float(np.linalg.norm(s[cap:]))
        out["rel_error"] = err / float(np.linalg.norm(s))
        out["orthogonality"] = float(np.linalg.norm(Q.T @ Q - np.eye(Q.shape[1]), 2))
    return out


# --------------------------------------------------------------------------- the driver


class Workers:
    """One spawned worker process per contender (and thread setting), created on demand."""

    def __init__(self) -> None:
        self._pools: dict[tuple[str, int | None], ProcessPoolExecutor] = {}

    def run(self, contender: str, threads: int | None, fn: Any, *args: Any) -> Any:
        res = self._run(contender, threads, fn, *args)
        print(f"  {contender} ({threads or 'default'} thread) {args[2:]}: "
              f"{res['seconds']:.3f} s, load {res['load']:.1f}", flush=True)
        return res

    def _run(self, contender: str, threads: int | None, fn: Any, *args: Any) -> Any:
        self.start([(contender, threads)])
        return self._pools[(contender, threads)].submit(fn, *args).result()

    def start(self, keys: list[tuple[str, int | None]]) -> None:
        """Start the workers of ``keys`` not yet running, all at once (untimed)."""
        started = []
        for key in keys:
            if key in self._pools:
                continue
            contender, threads = key
            env = {k: os.environ.get(k) for k in _THREAD_VARS}
            for k in _THREAD_VARS:
                if threads is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = str(threads)
            try:
                self._pools[key] = ProcessPoolExecutor(
                    1, mp_context=get_context("spawn"), initializer=_init_worker,
                    initargs=(threads, contender))
                started.append(self._pools[key].submit(int, 0))  # spawns it with this env
            finally:
                for k, v in env.items():
                    if v is None:
                        os.environ.pop(k, None)
                    else:
                        os.environ[k] = v
        for f in started:
            f.result()

    def close(self) -> None:
        for pool in self._pools.values():
            pool.shutdown()
        self._pools.clear()


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    first = dict(runs[0])
    first["seconds_all"] = [r["seconds"] for r in runs]
    first["seconds"] = statistics.median(first["seconds_all"])
    first["load_runs"] = [r["load"] for r in runs]
    return first


def run_target_case(case: str, names: dict[str, str], workers: Workers, targets: tuple,
                    repeat: int) -> dict[str, Any]:
    timed = ("inc_hapod", "dist_hapod", "streamsvd", "streamsvd_tree")
    runs: dict[str, list] = {f"{c}@{t:g}": [] for c in timed for t in targets}
    workers.start([(c, 1) for c in (*timed, "pod")])
    load0 = os.getloadavg()
    for r in range(repeat):
        for t in targets:
            for c in timed:
                runs[f"{c}@{t:g}"].append(workers.run(c, 1, task_target, names, c, t, r == 0))
    for t in targets:  # the optimum, once
        runs[f"pod@{t:g}"] = [workers.run("pod", 1, task_target, names, "pod", t, True)]
    res = {k: _summary(v) for k, v in runs.items()}
    return {"results": res, "load_before": load0, "load_after": os.getloadavg()}


def run_threads_row(names: dict[str, str], workers: Workers, target: float,
                    repeat: int) -> dict[str, Any]:
    runs: dict[str, list] = {"1": [], "default": []}
    workers.start([("streamsvd", 1), ("streamsvd", None)])
    load0 = os.getloadavg()
    for r in range(repeat):
        for key, threads in (("1", 1), ("default", None)):
            runs[key].append(workers.run("streamsvd", threads, task_target, names,
                                         "streamsvd", target, r == 0))
    return {"target": target, "results": {k: _summary(v) for k, v in runs.items()},
            "load_before": load0, "load_after": os.getloadavg()}


def run_cap_case(names: dict[str, str], workers: Workers, blocks: tuple, cap: int,
                 repeat: int, variants: tuple[str, ...] = ()) -> dict[str, Any]:
    contenders = ("streamsvd", "inc_hapod", "brand", "brand_tuned", *variants)
    runs: dict[str, list] = {f"{c}@{b}": [] for c in contenders for b in blocks}
    workers.start([(c, 1) for c in contenders])
    load0 = os.getloadavg()
    for r in range(repeat):
        for b in blocks:
            for c in contenders:
                runs[f"{c}@{b}"].append(workers.run(c, 1, task_cap, names, c, b, cap, r == 0))
    return {"cap": cap, "results": {k: _summary(v) for k, v in runs.items()},
            "load_before": load0, "load_after": os.getloadavg()}


def _plot(out: Path, data: dict[str, Any]) -> Path:
    plt = pyplot()
    cases = [c for c in ("burgers", "heat", "synthetic") if c in data["cases"]]
    fig, axes = plt.subplots(1, len(cases), figsize=(5.2 * len(cases), 4.2), squeeze=False)
    for ax, case in zip(axes[0], cases, strict=True):
        res = data["cases"][case]["results"]
        series: dict[str, list] = {}
        for key, r in res.items():
            name, arg = key.split("@")
            x = r.get("error")
            note = ""
            if case == "synthetic":  # the excess over the optimal rank-k error
                x = r["err_opt"] - 1.0 if r.get("err_opt") is not None else None
                name, extra = _variant(name)  # a contender's variants on one line
                if name in ("streamsvd", "inc_hapod"):
                    note = f"+{extra if extra is not None else _DEFAULT_EXTRA[name]}"
                name = f"{name}, block {arg}"
            series.setdefault(name, []).append((x, r["seconds"], note))
        for i, (label, pts) in enumerate(sorted(series.items())):
            pts = sorted(p for p in pts if p[0] is not None and p[0] > 0.0)
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], "os^vD<>p"[i % 8] + "-",
                      label=label, alpha=0.8)
            for x, y, note in pts:
                if note and len(pts) > 1:
                    ax.annotate(note, (x, y), fontsize=6, xytext=(3, 3),
                                textcoords="offset points")
        if case != "synthetic":
            for t in data["targets"]:
                ax.axvline(t, color="0.85", lw=0.8, zorder=0)
        ax.set_xlabel("err/opt - 1 (error over the optimal; +K: K more terms kept)"
                      if case == "synthetic" else "true mean-l2 error (in M)")
        ax.set_ylabel("time (s), median")
        load = data["cases"][case]["load_before"][0]
        ax.set_title(f"{case} (load {load:.1f})")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "hapod_benchmark.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _print_tables(data: dict[str, Any]) -> None:
    for case in ("burgers", "heat"):
        if case not in data["cases"]:
            continue
        c = data["cases"][case]
        rows = []
        for t in data["targets"]:
            hap = c["results"][f"inc_hapod@{t:g}"]["seconds"]
            for name in ("pod", "inc_hapod", "dist_hapod", "streamsvd", "streamsvd_tree"):
                r = c["results"][f"{name}@{t:g}"]
                rows.append([f"{t:g}", name, r["seconds"], r["seconds"] / hap, r["modes"],
                             r.get("error"), r.get("bound_mean_l2") or float("nan")])
        print_table(["target", "contender", "time s", "/inc_hapod", "modes", "true error",
                     "bound"], rows,
                    title=f"\n{case}: {c['shape']}, load {c['load_before'][0]:.2f} -> "
                          f"{c['load_after'][0]:.2f}")
    if "synthetic" in data["cases"]:
        c = data["cases"]["synthetic"]
        rows = []
        for key, r in c["results"].items():
            name, b = key.split("@")
            hap = c["results"][f"inc_hapod@{b}"]["seconds"]
            rows.append([b, name, r["seconds"], r["seconds"] / hap, r["modes"], r.get("sv_err"),
                         f"{r.get('err_opt', float('nan')):.6f}"])
        rows.sort(key=lambda x: (-int(x[0]), x[1]))
        print_table(["block", "contender", "time s", "/inc_hapod", "modes", "sv_err",
                     "err/opt"], rows,
                    title=f"\nsynthetic: {c['shape']}, cap {c['cap']}, load "
                          f"{c['load_before'][0]:.2f} -> {c['load_after'][0]:.2f}")
    if "threads" in data:
        c = data["threads"]
        rows = [[k, r["seconds"], r["modes"], r.get("error")] for k, r in c["results"].items()]
        print_table(["BLAS threads", "time s", "modes", "true error"], rows,
                    title=f"\nstreamsvd on burgers at {c['target']:g}, load "
                          f"{c['load_before'][0]:.2f} -> {c['load_after'][0]:.2f}")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    record = Run("hapod_benchmark", argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="directory for the PNG and JSON")
    ap.add_argument("--cache", default=str(DEFAULT_CACHE), help="snapshot cache directory")
    ap.add_argument("--cases", default="burgers,heat,synthetic")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads-target", type=float, default=1e-3)
    ap.add_argument("--no-threads", action="store_true", help="skip the BLAS-threads row")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    ap.add_argument("--variants", default="streamsvd_o2,streamsvd_o6,inc_hapod_o10",
                    help="synthetic case: more contenders, NAME_oK keeping K extra terms "
                         "(streamsvd's oversampling; for inc_hapod, cap + K modes per step, "
                         "the first cap returned); empty for none")
    args = ap.parse_args(argv)
    out = out_dir(args.out)
    cache = Path(args.cache)
    cases = [c for c in args.cases.split(",") if c]
    repeat = 1 if args.quick else args.repeat
    data: dict[str, Any] = {"machine": machine_info(), "targets": list(TARGETS),
                            "omega": OMEGA, "repeat": repeat,
                            "quick": args.quick, "cases": {}}
    try:
        import pymor

        data["pymor"] = pymor.__version__
    except ImportError as e:
        raise SystemExit("pyMOR is needed: pip install -e '.[bench]'") from e
    workers = Workers()
    try:
        for case in cases:
            t0 = time.perf_counter()
            names = {k: str(v) for k, v in generate(case, cache, args.quick).items()}
            shape = list(np.load(names["X"], mmap_mode="r").shape)
            print(f"{case}: data {shape} ready in {time.perf_counter() - t0:.1f} s", flush=True)
            if case == "synthetic":
                size = _size(case, args.quick)
                variants = tuple(v for v in args.variants.split(",") if v)
                res = run_cap_case(names, workers, size["blocks"], size["cap"], repeat,
                                   variants)
            else:
                res = run_target_case(case, names, workers, TARGETS, repeat)
            res["shape"] = shape
            data["cases"][case] = res
            if case == "burgers" and not args.no_threads:
                data["threads"] = run_threads_row(names, workers, args.threads_target, repeat)
    finally:
        workers.close()
    data["machine"]["load_average_end"] = list(os.getloadavg())
    record.write(out / "hapod_benchmark.json", data)
    _plot(out, data)
    _print_tables(data)
    return data


if __name__ == "__main__":
    main()
