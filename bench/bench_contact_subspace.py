"""How low can LATIN's indicator go on a space basis of p modes? (billet, paper size)

    python bench/bench_contact_subspace.py --out bench/results/contact
    python bench/bench_contact_subspace.py --quick --out /tmp/contact-subspace

Two measurements against the basis size ``p``:

* **LATIN on the optimal subspace**: the separated global stage of ``"latin-p3"`` with
  its basis fixed to the ``p`` leading SVD modes of the reference correction in the
  indicator metric (no enrichment), iterated ``--iterations`` times; the lowest
  indicator reached and the one of the last iteration;
* **LATIN-PGD** at several truncations ``trunc``: the lowest indicator, the median basis
  size of the last 50 iterations, and the optimal SVD sizes at ``trunc`` (both
  definitions: singular-value ratio and tail energy).

The indicator of the reference correction *truncated* to ``p`` modes (no iteration) is
recorded beside them, with ``sigma_1 / D`` (``D`` the indicator's denominator at the
reference), ``||y||_A / ||y||_{M_c}`` and the median norm (in ``M``) that LATIN-PGD's
compressor discarded per update over the last 50, relative to ``D``. Writes
``subspace.json`` and ``subspace.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from _common import Run
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import contact
from contact.globalstage import GlobalStage
from contact.pgd import SeparatedField


class _FixedBasis(SeparatedField):
    """The separated global stage on a given basis, never enriched."""

    def _new_pair(self, Z, V):
        return None


def fixed_subspace_floor(P, modes, iterations):
    """Iterate LATIN with the separated global stage on ``modes`` (free dofs, M-orthonormal)."""
    k = contact.default_search_direction(P)
    stage = GlobalStage(P, k)
    field = _FixedBasis(stage, enrich_ratio=0.5, fixed_point=4)
    for j in range(modes.shape[1]):
        field._append(modes[:, j])
    field.Uc = np.eye(modes.shape[1])
    field._project()
    Lc = np.concatenate([P.weights, P.weights])
    w = stage.w_lift.copy()
    lam = np.zeros_like(w)
    etas = []
    for _ in range(iterations):
        w_hat, lam_hat = contact.local_stage(w, lam, k=k, gaps=P.gaps, mu=P.mu)
        w = field.update(stage.rhs_data(w_hat, lam_hat))
        lam = stage.tractions(w, w_hat, lam_hat)
        etas.append(contact.indicator(w, lam, w_hat, lam_hat, Lc, k))
    return np.array(etas), lam_hat


def truncated_indicator(P, R, svd, r):
    """Indicator of the reference correction truncated to ``r`` modes (one local stage)."""
    k = contact.default_search_direction(P)
    Lc = np.concatenate([P.weights, P.weights])
    d = svd.space[:, r:] * svd.values[r:] @ svd.time[:, r:].T
    w = P.C @ R.u - P.C @ d
    lam = R.lam + k * (P.C @ d)
    w_hat, lam_hat = contact.local_stage(w, lam, k=k, gaps=P.gaps, mu=P.mu)
    return contact.indicator(w, lam, w_hat, lam_hat, Lc, k)


def main(argv=None):
    record = Run("bench_contact_subspace", argv)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/contact")
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--quick", action="store_true", help="dt x10, 100 iterations")
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    P = contact.billet(dt=5e-2 if args.quick else 5e-3)
    iterations = 100 if args.quick else args.iterations
    R = contact.reference_solve(P)
    stage = GlobalStage(P, contact.default_search_direction(P))
    M = contact.indicator_metric(P)
    y = R.u - stage.lift()
    svd = contact.svd_modes(y, inner=M)
    free = stage.free
    sizes = [p for p in (10, 20, 35, 45, 52, 64, 74) if p <= svd.values.size]
    k = stage.k
    Lc = np.concatenate([P.weights, P.weights])
    D = float(np.sqrt(np.sum(Lc[:, None] * (k * (P.C @ R.u) ** 2 + R.lam**2 / k))))
    A = stage.A
    y_f = y[free]
    norm_A = float(np.sqrt(np.sum(y_f * (A @ y_f))))
    norm_c = float(np.sqrt(np.sum(2 * k * Lc[:, None] * (P.C @ y) ** 2)))
    result = {"problem": P.summary(), "iterations": iterations, "fixed": [], "pgd": [],
              "sigma_1_over_D": float(svd.values[0]) / D,
              "energy_over_contact_norm": norm_A / norm_c}
    print(f"sigma_1 / D = {result['sigma_1_over_D']:.3f}; ||y||_A / ||y||_Mc = "
          f"{result['energy_over_contact_norm']:.3f}")
    print(f"{'p':>4s} {'truncated ref':>14s} {'LATIN on SVD modes: min':>24s} "
          f"{'last':>9s} {'forces':>9s}")
    for p in sizes:
        etas, lam_hat = fixed_subspace_floor(P, svd.space[free, :p], iterations)
        row = {"p": p, "truncated_reference": truncated_indicator(P, R, svd, p),
               "min_indicator": float(etas.min()), "last_indicator": float(etas[-1]),
               "error_lam": float(np.linalg.norm(lam_hat - R.lam) / np.linalg.norm(R.lam))}
        result["fixed"].append(row)
        print(f"{p:4d} {row['truncated_reference']:14.2e} {row['min_indicator']:24.2e} "
              f"{row['last_indicator']:9.2e} {row['error_lam']:9.1e}", flush=True)
    print(f"{'trunc':>6s} {'PGD: min indicator':>19s} {'median p':>9s} "
          f"{'optimal (ratio, tail)':>22s} {'cut / D':>8s} {'CPU s':>6s}")
    for trunc in (1e-4, 3e-5, 1e-5, 1e-6):
        c0 = time.process_time()
        L = contact.solve(P, "latin-pgd", tol=1e-7, max_iter=iterations, trunc=trunc)
        row = {"trunc": trunc, "min_indicator": float(L.indicator.min()),
               "median_basis_size": float(np.median(L.basis_size[-50:])),
               "optimal": svd.sizes(trunc), "cpu_s": time.process_time() - c0,
               "iterations_to_1e-4": L.iterations_to(1e-4),
               "discarded_per_update_over_D": float(np.median(
                   [h.discarded for h in L.info["compressor_history"][-50:]])) / D}
        result["pgd"].append(row)
        print(f"{trunc:6.0e} {row['min_indicator']:19.2e} {row['median_basis_size']:9.1f} "
              f"{str(tuple(row['optimal'].values())):>22s} "
              f"{row['discarded_per_update_over_D']:8.1e} {row['cpu_s']:6.2f}", flush=True)
    record.write(out / "subspace.json", result)
    fig = Figure(figsize=(6, 4), layout="constrained")
    ax = fig.subplots()
    f = result["fixed"]
    ax.semilogy([r["p"] for r in f], [r["truncated_reference"] for r in f], "s--",
                label="reference truncated to p SVD modes")
    ax.semilogy([r["p"] for r in f], [r["min_indicator"] for r in f], "o-",
                label="LATIN on the p leading SVD modes (lowest)")
    g = result["pgd"]
    ax.semilogy([r["median_basis_size"] for r in g], [r["min_indicator"] for r in g], "^-",
                label="LATIN-PGD (lowest), at its median basis size")
    for r in g:
        ax.annotate(f"trunc {r['trunc']:g}", (r["median_basis_size"], r["min_indicator"]),
                    fontsize=7)
    ax.set_xlabel("space modes p")
    ax.set_ylabel("indicator eta (dimensionless)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    FigureCanvasAgg(fig)
    fig.savefig(out / "subspace.png", dpi=120)
    return result


if __name__ == "__main__":
    main()
