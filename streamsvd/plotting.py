"""Figures of a compressor: what ``streamsvd plot`` draws.

matplotlib is imported when a figure is drawn (it is needed by nothing else), and the
figure is a :class:`matplotlib.figure.Figure` that is not attached to pyplot, so drawing
works without a display and leaves pyplot's state alone.
"""

from __future__ import annotations

from typing import Any

__all__ = ["compressor_figure"]


def compressor_figure(sc: Any, *, name: str) -> Any:
    """Draw the amplitudes, the error bound against k and the orthogonality history.

    Parameters
    ----------
    sc : StreamCompressor or TallCompressor
        An open compressor.
    name : str
        How the store is named in the title.

    Returns
    -------
    matplotlib.figure.Figure
        Three panels; every x axis counts terms or updates and has integer ticks.
    """
    import numpy as np
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    amps = np.asarray(sc.amplitudes)
    hist = sc.history
    terms = np.arange(1, amps.size + 1)
    fig = Figure(figsize=(14, 4.4))
    ax = fig.subplots(1, 3)
    fig.suptitle(
        f"{name}: n = {sc.n}, rank {sc.rank}, {sc.n_seen} snapshots in {len(hist)} "
        f"update{'' if len(hist) == 1 else 's'}, ||A - U V^T||_F <= {sc.error_bound:.2e}"
    )
    ax[0].semilogy(terms, amps, "k.-", ms=4)
    ax[0].set(xlabel="term i", ylabel="amplitude ||v_i|| (units of the data)",
              title="amplitudes")
    # the bound after cutting to k terms (the terms are orthogonal at convergence):
    # hypot(bound, ||amplitudes k+1 ...||), in the measure of the target
    scale = float(amps.max()) if amps.size else 1.0
    a = amps / scale if scale > 0 else amps
    tail = np.sqrt(np.append(np.cumsum((a**2)[::-1])[::-1], 0.0))[1:] * scale
    bound_k = np.hypot(sc.error_bound, tail)
    measure = sc.error_measure if sc.target_error is not None else "relative"
    if measure == "mean_l2":
        shown, label = bound_k / np.sqrt(max(sc.n_seen, 1)), "bound on the mean l2 error"
    elif measure == "absolute":
        shown, label = bound_k, "bound on ||A - U_k V_k^T||_F"
    else:
        kept = np.sqrt(np.cumsum(a**2)) * scale
        with np.errstate(divide="ignore", invalid="ignore"):
            shown = np.where(kept > bound_k, bound_k / (kept - bound_k), np.inf)
        label = "bound on ||A - U_k V_k^T||_F / ||A||_F"
    ax[1].semilogy(terms, np.maximum(shown, 1e-300), "b.-", ms=4, label="cut to k terms")
    if sc.target_error is not None:
        ax[1].axhline(sc.target_error, color="0.3", ls="--", lw=1,
                      label=f"target {sc.target_error:.1e}")
    ax[1].set(xlabel="terms kept k", ylabel=f"{label} (dimensionless)" if measure != "absolute"
              else f"{label} (units of the data)", title="error bound against k")
    if amps.size:
        ax[1].legend(loc="best", fontsize="small")
    updates = np.arange(1, len(hist) + 1)
    orth = [max(h.orthogonality, 1e-18) for h in hist]
    # an update by the Gram path in memory records its basis before the Gram is measured
    # (corrected when read, UpdateRecord): the U read now is drawn beside the history
    ax[2].semilogy(updates, orth, "r.-", ms=8, label="recorded after each update")
    reorth = sc.reorth_tol
    if reorth:
        ax[2].axhline(reorth, color="0.5", ls="--", lw=1, label="re-orthonormalisation threshold")
    if hist:
        now = sc.orthogonality_error()
        ax[2].axhline(max(now, 1e-18), color="g", ls=":", lw=1.5,
                      label=f"U as read now ({now:.1e})")
    ax[2].set(xlabel="update", ylabel="||U^T M U - I||_2 (dimensionless)",
              title="orthogonality of U")
    if hist:
        ax[2].legend(loc="best", fontsize="small")
    for a, count, what in ((ax[0], amps.size, "no terms"), (ax[1], amps.size, "no terms"),
                           (ax[2], len(hist), "no updates")):
        # counts: integer ticks, and limits wide enough for them even with one point
        a.set_xlim(0.5, max(count, 1) + 0.5)
        a.xaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
        if not count:
            a.text(0.5, 0.5, what, transform=a.transAxes, ha="center", va="center")
    fig.tight_layout()
    return fig

