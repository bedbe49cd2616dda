import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.quiver import QuiverKey

import contact
from contact import figures


@pytest.fixture(scope="module")
def billet_modes():
    P = contact.billet(dt=0.125)
    rng = np.random.default_rng(7)
    Y = np.zeros((P.n, P.m))
    Y[P.free_dofs] = 1e-3 * rng.standard_normal((len(P.free_dofs), P.m))
    return P, contact.svd_modes(Y)


def drawn(fig):
    FigureCanvasAgg(fig).draw()
    return fig


def visible_ticks(axis, lo, hi):
    """Tick labels drawn inside the view interval [lo, hi]."""
    return [t.get_text() for t, v in zip(axis.get_ticklabels(), axis.get_ticklocs(),
                                         strict=True) if lo <= v <= hi]


def test_mac_figures_count_modes_from_1():
    rng = np.random.default_rng(3)
    ref = np.linalg.qr(rng.standard_normal((40, 12)))[0]
    basis = ref[:, :7] @ np.linalg.qr(rng.standard_normal((7, 7)))[0]
    fig = drawn(figures.fig_mac([("a", ref[:, :7]), ("b", basis)], ref, title="t"))
    ax = fig.axes[0]
    # entry (i, j) of the MAC matrix sits on mode numbers (j + 1, i + 1)
    assert ax.get_xlim() == (0.5, 12.5) and ax.get_ylim() == (7.5, 0.5)
    assert visible_ticks(ax.xaxis, 0.5, 12.5)[0] == "1"
    assert visible_ticks(ax.yaxis, 0.5, 7.5)[0] == "1"
    assert "0" not in visible_ticks(ax.xaxis, 0.5, 12.5)
    assert ax.images[0].get_array()[0, 0] == pytest.approx(1.0)  # mode 1 against mode 1
    (cbar,) = [im.colorbar for a in fig.axes for im in a.images if im.colorbar]
    assert cbar.ax.get_ylabel() == "MAC (dimensionless)"


def test_mode_ticks_start_at_1_and_stay_in_range():
    assert figures._mode_ticks(1) == [1]
    assert figures._mode_ticks(7) == [1, 2, 3, 4, 5, 6, 7]
    assert figures._mode_ticks(28) == [1, 5, 10, 15, 20, 25]
    assert figures._mode_ticks(201) == [1, 50, 100, 150, 200]


def test_fig7_labels_its_axes_and_colour_bars_with_units(billet_modes):
    P, svd = billet_modes
    fig = drawn(figures.fig7_space_modes(P, svd, modes=3))
    axes = [ax for ax in fig.axes if ax.collections and ax.collections[0].colorbar]
    assert len(axes) == 3
    for i, ax in enumerate(axes):
        assert ax.get_xlabel() == "r (mm)" and ax.get_ylabel() == "z (mm)"
        assert ax.get_title().startswith(f"mode {i + 1}: max |u| ")
        assert " mm\n" in ax.get_title()
        cbar = ax.collections[0].colorbar
        assert cbar.ax.get_xlabel() == "||eps|| (dimensionless, mm/mm)"
        # the force key of the arrows carries its unit
        (key,) = [a for a in ax.artists if isinstance(a, QuiverKey)]
        assert key.text.get_text().endswith(" N/rad")
    # the mode is drawn at its largest contribution s_i max|t_i| x_i (mm)
    a = svd.values[0] * np.abs(svd.time[:, 0]).max()
    umax = np.linalg.norm((a * svd.space[:, 0]).reshape(-1, 2), axis=1).max()
    assert axes[0].get_title().startswith(f"mode 1: max |u| {umax:.2g} mm")


def test_fig5_and_fig6_label_every_axis_with_a_unit(billet_modes):
    P, svd = billet_modes
    fig6 = drawn(figures.fig6_svd(svd, P.times, modes=3))
    ax1, ax2 = fig6.axes
    assert ax1.get_xlabel() == "mode number i"
    assert visible_ticks(ax1.xaxis, *ax1.get_xlim())[0] == "1"
    assert ax1.get_ylabel() == "s_i / s_1 (dimensionless)"
    assert f"s_1 = {svd.values[0]:.3g} mm" in ax1.get_title()
    assert ax2.get_xlabel() == "time (s)"
    assert ax2.get_ylabel() == "t_i / max |t_i| (dimensionless)"
    assert [t.get_text() for t in ax2.get_legend().get_texts()] == ["mode 1", "mode 2",
                                                                     "mode 3"]
    res = {"latin": contact.solve(P, "latin", max_iter=3),
           "latin-p3": contact.solve(P, "latin-p3", max_iter=3)}
    fig5 = drawn(figures.fig5_convergence(res, optimal=2))
    for ax in fig5.axes:
        assert ax.get_xlabel() in ("iteration", "CPU time, setup included (s)")
        assert ax.get_ylabel().endswith(("(dimensionless)", "(number of space modes)"))
