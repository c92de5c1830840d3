"""The figure of a joint fit (``pbrdf-cl fit a.csv b.csv --plot``): one panel per set, its measured
DOP and the joint fit's curve per incidence angle (the separate fit's dashed beside it), the shared
values in the title (matplotlib; no display needed)."""
from __future__ import annotations

import numpy as np

from .common import figure, save


def plot_joint(result, path=None, *, fig=None):
    """One figure of a joint fit: a panel per set with its data (error bars: +-1 ``dop_std``) and
    the joint fit's DOP curve per incidence angle (solid; the set's separate fit dashed), the
    shared parameters' values in the title.

    Parameters
    ----------
    result : JointResult
        What :func:`pbrdf_cl.fit_joint` returned (its ``measurements`` are the data drawn).
    path : str or path, optional
        Where the figure is written (the suffix says the format: .png, .pdf, .svg); None: nothing
        is written.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into (a panel per set, side by side); default a new figure 4.2 inches wide per set
        and 4.6 high, with constrained layout.

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Examples
    --------
    >>> plot_joint(pbrdf_cl.fit_joint(sets), "joint.png")  # doctest: +SKIP
    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> fig = plot_joint(pbrdf_cl.fit_joint(sets), fig=plt.figure(layout="constrained"))  # doctest: +SKIP
    """
    from matplotlib import rcParams

    from ..compute import pointwise
    names = list(result.sets)
    fig = figure(fig, figsize=(4.2 * len(names), 4.6), layout="constrained")
    axes = fig.subplots(1, len(names), sharey=True, squeeze=False)
    colors = rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, s in zip(axes[0], names):
        m = result.measurements[s]
        for ci, ti in enumerate(np.unique(np.round(m.theta_i, 6))):
            sel = np.isclose(m.theta_i, ti)
            col = colors[ci % len(colors)]
            ax.errorbar(m.theta_r[sel], m.dop[sel], yerr=None if m.dop_std is None else m.dop_std[sel], fmt="o",
                        color=col, ms=3.5, capsize=2, elinewidth=0.8, label=f"theta_i = {ti:g} deg")
            phi = float(np.median(m.phi[sel]))
            tr = np.linspace(max(0.0, m.theta_r[sel].min() - 5), min(89.0, m.theta_r[sel].max() + 5), 200)
            for x, style in ((result.x[s], "-"), (result.separate[s].x, "--")):
                kw = dict(model="specular") if result.model == "specular" else {}
                ax.plot(tr, pointwise.dop(ti, tr, phi, shadowing=result.shadowing, backend="numpy", **kw, **x),
                        style, color=col, lw=1.1)
        own = ", ".join(f"{p}={result.x[s][p]:.3g}" for p in result.ci95[s] if p not in result.shared)
        ax.set_title(f"set {s}: {own}\nSSE {result.set_sse[s]:.3g} (separate {result.separate[s].sse:.3g})",
                     fontsize=8)
        ax.set_xlabel("reflection zenith angle theta_r (deg)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, title="solid: joint, dashed: separate", title_fontsize=7)
    axes[0][0].set_ylabel("degree of polarization")
    shared = ", ".join(f"{p} = {v:.4g}" for p, v in result.shared_x.items()) or "none"
    fig.suptitle(f"joint fit ({result.model}, shadowing {result.shadowing}); shared: {shared}; "
                 f"AIC {result.aic:.1f} (separate {result.separate_aic:.1f})", fontsize=9)
    save(fig, path, dpi=110)
    return fig
