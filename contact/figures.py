"""The paper's figures 5-9, drawn with matplotlib's object API on the Agg canvas.

No global backend is changed: every figure is a :class:`matplotlib.figure.Figure` saved
to PNG by :func:`save`.

Units are those of :func:`contact.billet`: mm, MPa, N (per radian when axisymmetric)
and s. Modes are numbered from 1 in every figure, as ``s_1 >= s_2 >= ...``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.ticker import FixedLocator

from .fem import element_strains
from .post import SVDModes
from .problem import Problem
from .result import LatinResult

__all__ = ["fig5_convergence", "fig6_svd", "fig7_space_modes", "fig_mac", "save"]

_STYLE = {"latin": "k-", "latin-p3": "C0-", "latin-pgd": "C3-"}


def save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as a PNG file and return its path."""
    path = Path(path)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=130)
    return path


def fig5_convergence(
    results: Mapping[str, LatinResult], *, optimal: int | None = None, level: float = 1e-4
) -> Figure:
    """Fig. 5: indicator against iterations and CPU time, basis size against iterations."""
    fig = Figure(figsize=(13, 4), layout="constrained")
    ax1, ax2, ax3 = fig.subplots(1, 3)
    for label, r in results.items():
        style = _STYLE.get(r.method, "C2-")
        if label != r.method:
            style = style.replace("-", "--")
        it = np.arange(1, r.iterations + 1)
        cpu = r.setup_time + np.cumsum(r.cpu_time)
        ax1.semilogy(it, r.indicator, style, label=label, lw=1.2)
        ax2.loglog(cpu, r.indicator, style, label=label, lw=1.2)
        if r.method != "latin":
            ax3.plot(it, r.basis_size, style, label=label, lw=1.2)
    for ax in (ax1, ax2):
        ax.axhline(level, color="0.6", lw=0.8, ls=":")
        ax.set_ylabel("error indicator eta (dimensionless)")
        ax.grid(True, which="both", alpha=0.3)
    if optimal is not None:
        ax3.axhline(optimal, color="0.3", lw=1, ls=":", label=f"optimal SVD size ({optimal})")
    ax1.set_xlabel("iteration")
    ax2.set_xlabel("CPU time, setup included (s)")
    ax3.set_xlabel("iteration")
    ax3.set_ylabel("basis size (number of space modes)")
    ax3.grid(True, alpha=0.3)
    ax1.legend()
    ax3.legend()
    fig.suptitle("Convergence of the LATIN methods (Fig. 5)")
    return fig


def fig6_svd(svd: SVDModes, times: np.ndarray, *, modes: int = 6, rtol: float = 1e-4) -> Figure:
    """Fig. 6: singular values and the first normalised temporal modes.

    The singular values ``s_i`` of a displacement field are in mm; they are drawn relative
    to ``s_1``, whose value is in the title.
    """
    fig = Figure(figsize=(11, 4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    s = svd.values / svd.values[0]
    ax1.semilogy(np.arange(1, s.size + 1), s, "o-", ms=3)
    ax1.axhline(rtol, color="C3", lw=0.8, ls=":")
    ax1.set_title(f"singular values, s_1 = {svd.values[0]:.3g} mm "
                  f"({svd.rank(rtol)} above {rtol:g} s_1)")
    ax1.set_xlabel("mode number i")
    ax1.set_ylabel("s_i / s_1 (dimensionless)")
    ax1.xaxis.set_major_locator(FixedLocator(_mode_ticks(s.size)))
    ax1.set_xlim(0, s.size + 1)
    ax1.grid(True, which="both", alpha=0.3)
    for i in range(min(modes, svd.time.shape[1])):
        t = svd.time[:, i]
        ax2.plot(times, t / np.abs(t).max(), label=f"mode {i + 1}")
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("t_i / max |t_i| (dimensionless)")
    ax2.set_title("normalised temporal modes")
    ax2.legend(fontsize=8)
    ax2.grid(True, alpha=0.3)
    fig.suptitle("SVD of the reference solution (Fig. 6)")
    return fig


def fig7_space_modes(problem: Problem, svd: SVDModes, *, modes: int = 6) -> Figure:
    """Fig. 7: first spatial modes, deformed mesh coloured by the strain norm ``||eps||``.

    Mode ``i`` is drawn at its largest contribution to the field, the displacement
    ``a_i x_i`` (mm) with ``a_i = s_i max_t |t_i(t)|``: the colour is the norm of its
    strain ``sqrt(eps : eps)`` (dimensionless), the title gives its largest nodal
    displacement (mm), and the mesh is drawn deformed by ``a_i x_i`` magnified by the
    factor in the title. Arrows are the contact forces of that displacement: the nodal
    forces ``K a_i x_i`` at the contact nodes (the force the die must apply to hold it),
    with a key in N (per radian when axisymmetric).
    """
    P = problem
    modes = min(modes, svd.space.shape[1])
    fig = Figure(figsize=(2.5 * modes, 5.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, modes))
    X = P.mesh.coords
    size = float(np.ptp(X, axis=0).max())
    force_unit = "N/rad" if P.axisymmetric else "N"
    for i, ax in enumerate(axes):
        x = svd.values[i] * np.abs(svd.time[:, i]).max() * svd.space[:, i]  # mm
        disp = x.reshape(-1, 2)
        umax = float(np.linalg.norm(disp, axis=1).max())
        scale = 0.04 * size / max(umax, 1e-300)
        Xd = X + scale * disp
        eps = element_strains(P.mesh, x, axisymmetric=P.axisymmetric)
        pc = PolyCollection(Xd[P.mesh.quads], array=eps, cmap="viridis", edgecolors="0.3",
                            linewidths=0.2)
        ax.add_collection(pc)
        f = np.asarray(P.K @ x).reshape(-1, 2)[P.contact_nodes]
        c = Xd[P.contact_nodes]
        q = ax.quiver(c[:, 0], c[:, 1], f[:, 0], f[:, 1], color="C3", angles="xy",
                      width=0.012)
        fmax = float(np.linalg.norm(f, axis=1).max())
        if fmax > 0:
            key = float(f"{fmax:.1g}")
            ax.quiverkey(q, 0.8, 0.55, key, f"{key:g} {force_unit}", coordinates="axes",
                         labelpos="S", fontproperties={"size": 7})
        ax.set_aspect("equal")
        ax.autoscale_view()
        ax.set_xlim(-0.1 * size, 0.45 * size)
        ax.set_title(f"mode {i + 1}: max |u| {umax:.2g} mm\n(drawn x{scale:.0f})", fontsize=9)
        ax.set_xlabel("r (mm)" if P.axisymmetric else "x (mm)")
        ax.set_ylabel("z (mm)" if P.axisymmetric else "y (mm)")
        cb = fig.colorbar(pc, ax=ax, shrink=0.8, location="bottom", format="%.1e")
        cb.ax.tick_params(labelsize=6, rotation=30)
        cb.set_label("||eps|| (dimensionless, mm/mm)", fontsize=8)
    fig.suptitle("SVD spatial modes of the reference solution (Fig. 7): colour ||eps||, "
                 "arrows contact forces")
    return fig


def fig_mac(
    bases: Sequence[tuple[str, np.ndarray]], reference: np.ndarray, *, title: str
) -> Figure:
    """Figs. 8-9: MAC matrices (eq. 21) of iterated bases against the SVD basis.

    Entry ``(i, j)`` is drawn centred on the mode numbers ``(j, i)``, both counted from 1.
    """
    from .post import mac

    fig = Figure(figsize=(4.6 * len(bases), 4.4), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(bases)))
    im = None
    for ax, (label, B) in zip(axes, bases, strict=True):
        M = mac(B, reference)
        p, q = M.shape
        im = ax.imshow(M, vmin=0, vmax=1, cmap="Greys", interpolation="nearest",
                       aspect="auto", extent=(0.5, q + 0.5, p + 0.5, 0.5))
        ax.xaxis.set_major_locator(FixedLocator(_mode_ticks(q)))
        ax.yaxis.set_major_locator(FixedLocator(_mode_ticks(p)))
        ax.set_xlabel("SVD mode number of the reference")
        ax.set_ylabel("mode number of the iterated basis")
        ax.set_title(label)
    if im is not None:
        cb = fig.colorbar(im, ax=list(axes), shrink=0.8)
        cb.set_label("MAC (dimensionless)")
    fig.suptitle(title)
    return fig


def _mode_ticks(count: int, *, most: int = 8) -> list[int]:
    """Return tick positions for modes ``1..count``: 1, then multiples of a round step."""
    step = 1
    for step in (1, 2, 5, 10, 20, 25, 50, 100, 200, 250, 500, 1000):
        if count / step <= most:
            break
    return sorted({1, *range(step, count + 1, step)})
