"""The figure of a joint fit (``pbrdf-cl fit a.csv b.csv --plot``): one panel per set, its measured
DOP and the joint fit's curve per incidence angle (the separate fit's dashed beside it), or, for a
set of polarimetric data, the model's value of every measured number against the measurement; the
shared values in the title (matplotlib; no display needed)."""
from __future__ import annotations

import numpy as np

from .common import figure, save


def plot_joint(result, path=None, *, fig=None):
    """One figure of a joint fit: a panel per set with its data (error bars: +-1 ``dop_std``) and
    the joint fit's DOP curve per incidence angle (solid; the set's separate fit dashed), the
    shared parameters' values in the title.  A set of polarimetric data (Stokes parameters, Mueller
    elements, ...) gets a panel of the fits' values of each measured number against the
    measurement (filled: joint, open: separate; a colour per quantity and source state), on the
    line model = data.

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
    polar = [result.measurements[s].polarimetric for s in names]
    axes = fig.subplots(1, len(names), sharey=not any(polar), squeeze=False)
    colors = rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, s in zip(axes[0], names):
        m = result.measurements[s]
        if m.polarimetric:
            _parity(ax, result, s, colors)
            continue
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
    for ax, p in zip(axes[0], polar):
        if not p:
            ax.set_ylabel("degree of polarization")
            break
    shared = ", ".join(f"{p} = {v:.4g}" for p, v in result.shared_x.items()) or "none"
    fig.suptitle(f"joint fit ({result.model}, shadowing {result.shadowing}); shared: {shared}; "
                 f"AIC {result.aic:.1f} (separate {result.separate_aic:.1f})", fontsize=9)
    save(fig, path, dpi=110)
    return fig


def _parity(ax, result, s, colors):
    """Set ``s``'s panel for polarimetric data: the joint and the separate fits' values of every
    number fitted (the set's normalised channels: absolute Stokes parameters and Mueller elements
    divided by their row's S0 or M00) against the measurement, a colour per quantity and source
    state."""
    from ..compute.measured import label, state_text
    from ..fitting.channels import ChannelModel
    from ..fitting.sample.polarimetric import normalised_channels
    from ..fitting.setup import MODEL_FIXED
    m = result.measurements[s]
    ch = normalised_channels(m, result.separate[s].free)[1]
    model = ChannelModel(ch, result.shadowing)
    fits = {kind: model.rows({**MODEL_FIXED[result.model], **x})
            for kind, x in (("joint", result.x[s]), ("separate", result.separate[s].x))}
    stokes = np.array([not str(n).startswith("m") for n in ch.name])  # a Mueller element's u is its column
    inc = np.where(stokes[:, None], np.round(ch.u[:, 1:], 6), 0.0)
    keys = list(dict.fromkeys(zip(ch.name, map(tuple, inc))))
    for gi, (name, state) in enumerate(keys):
        sel = (ch.name == name) & np.all(inc == state, axis=1)
        col = colors[gi % len(colors)]
        text = label(name)[0].split(" = ")[0] + (f", source {state_text(state)}" if any(state) else "")
        for kind, values in fits.items():
            ax.plot(ch.obs[sel], values[sel], "o", color=col, ms=3.5 if kind == "joint" else 5.5,
                    mfc=col if kind == "joint" else "none", label=text if kind == "joint" else None)
    both = np.concatenate([ch.obs, *fits.values()])
    lo, hi = np.nanmin(both), np.nanmax(both)
    ax.plot([lo, hi], [lo, hi], color="0.5", lw=0.8)
    ax.set_xlabel("measured (normalised quantities; AoP in deg)")
    ax.set_ylabel("model")
    ax.set_title(f"set {s}: polarimetric data\nSSE {result.set_sse[s]:.3g} (separate {result.separate[s].sse:.3g})",
                 fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, title="filled: joint, open: separate", title_fontsize=7, ncol=2 if len(keys) > 8 else 1)
