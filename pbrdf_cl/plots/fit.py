"""The figure of a fit (``pbrdf-cl fit --plot``): the measured quantities (the DOP, or what a
polarimeter measured: Stokes parameters per incident state, Mueller elements, ...) and each fitted
model's curve per incidence angle, and the residuals (matplotlib; no display needed)."""
from __future__ import annotations

import numpy as np

from .common import figure, save

#: The fitted models' line styles and residual markers, in the order of ``fits``.
FIT_STYLES = ("-", "--", ":")
FIT_MARKERS = ("o", "x", "^")


def plot_fit(meas, fits, path=None, *, fig=None):
    """Measured DOP (error bars: +-1 ``dop_std``) and each fitted model's curve per incidence
    angle (one colour per theta_i), and the residuals model - data with the same colours, one
    marker per model and the data's error bars (``pbrdf-cl fit --plot``).

    Polarimetric data (``meas.polarimetric``: Stokes parameters, Mueller elements, an AoP, or an
    incident state) draw one panel per quantity measured and incident state (``s1`` under the
    source at +45 degrees, ``m01``, ...; a Mueller element or F00 does not depend on the state),
    each with its residuals below it: the data with their ``<name>_std`` error bars and each model's
    curves, evaluated through :func:`pbrdf_cl.compute.measured.measured`.

    Parameters
    ----------
    meas : pbrdf_cl.Measurements
        The data fitted.
    fits : dict
        Model name (``"six-param"``, ``"specular"``) -> its :class:`pbrdf_cl.FitResult`, such as
        ``compare_models(...).fits``.
    path : str or path, optional
        Where the figure is written (the suffix says the format); None: nothing is written.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into (two panels, one above the other; polarimetric data: two per quantity and
        state, up to three side by side); default a new figure with constrained layout (8 x 7.5
        inches for DOP data).

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Examples
    --------
    In a notebook, into a figure of one's own (the notebook's backend is left as it is); with a
    path, into a file as ``pbrdf-cl fit --compare --plot`` writes it:

    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> data = pbrdf_cl.read_csv("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> both = pbrdf_cl.compare_models(data)  # doctest: +SKIP
    >>> fig = plot_fit(data, both.fits, fig=plt.figure(figsize=(8, 7.5), layout="constrained"))  # doctest: +SKIP
    >>> fig = plot_fit(data, both.fits, "fit.png")  # doctest: +SKIP
    """
    from matplotlib import rcParams
    from matplotlib.lines import Line2D

    from ..compute import pointwise
    if meas.polarimetric:
        return _plot_polarimetric(meas, fits, path, fig)
    fig = figure(fig, figsize=(8, 7.5), layout="constrained")
    ax, axr = fig.subplots(2, 1, sharex=True, gridspec_kw=dict(height_ratios=[3, 1.5]))
    incid = np.unique(np.round(meas.theta_i, 6))
    colors = rcParams["axes.prop_cycle"].by_key()["color"]
    has_std = meas.dop_std is not None
    shift = 0.6 * np.min(np.diff(np.unique(meas.theta_r)), initial=5.0) / max(1, len(fits))
    for ci, ti in enumerate(incid):
        sel = np.isclose(meas.theta_i, ti)
        col = colors[ci % len(colors)]
        yerr = meas.dop_std[sel] if has_std else None
        ax.errorbar(meas.theta_r[sel], meas.dop[sel], yerr=yerr, fmt="o", color=col, ms=3.5, capsize=3,
                    elinewidth=1.0, label=f"data{' ± 1 sd' if has_std else ''}, theta_i = {ti:g} deg")
        phi = float(np.median(meas.phi[sel]))
        tr = np.linspace(max(0.0, meas.theta_r[sel].min() - 5), min(89.0, meas.theta_r[sel].max() + 5), 200)
        for si, (name, r) in enumerate(fits.items()):
            x = dict(r.x)
            if name == "specular":
                curve = pointwise.dop(ti, tr, phi, n=x["n"], k=x["k"], model="specular", shadowing=r.shadowing,
                                backend="numpy")
                res = pointwise.dop(meas.theta_i[sel], meas.theta_r[sel], meas.phi[sel], n=x["n"], k=x["k"],
                              model="specular", backend="numpy") - meas.dop[sel]
            else:
                curve = pointwise.dop(ti, tr, phi, shadowing=r.shadowing, backend="numpy", **x)
                res = pointwise.dop(meas.theta_i[sel], meas.theta_r[sel], meas.phi[sel], shadowing=r.shadowing,
                              backend="numpy", **x) - meas.dop[sel]
            ax.plot(tr, curve, FIT_STYLES[si % 3], color=col, lw=1.2)
            offset = (si - (len(fits) - 1) / 2) * shift  # side by side, not on top of each other
            marker = FIT_MARKERS[si % 3]
            axr.errorbar(meas.theta_r[sel] + offset, res, yerr=yerr, fmt=marker, color=col, ms=4, capsize=2,
                         elinewidth=0.8, mfc="none" if marker == "o" else col)
    # the models' legend entries in a neutral colour: each style stands for every theta_i's colour
    model_handles = [Line2D([], [], ls=FIT_STYLES[si % 3], color="k", lw=1.2, label=f"{name} fit")
                     for si, name in enumerate(fits)]
    handles, _ = ax.get_legend_handles_labels()
    ax.legend(handles=handles + model_handles, fontsize=7, ncol=2, loc="best")
    res_handles = [Line2D([], [], ls="none", marker=FIT_MARKERS[si % 3], color="k", mfc="none" if si == 0 else "k",
                          label=name) for si, name in enumerate(fits)]
    bars = "bars: ± 1 dop_std" if has_std else "no dop_std: no error bars"
    axr.legend(handles=res_handles, fontsize=7, ncol=len(fits), loc="best",
               title=f"colour: theta_i as above; {bars}", title_fontsize=7)
    axr.axhline(0, color="0.5", lw=0.8)
    ax.set_ylabel("degree of polarization")
    axr.set_ylabel("model - data (DOP)")
    axr.set_xlabel("reflection zenith angle theta_r (deg)")
    title = "; ".join(f"{n}: n={r.x['n']:.3g}, k={r.x['k']:.3g}, BIC {r.bic:.1f}" for n, r in fits.items())
    ax.set_title(f"DOP fit ({meas.source.split('/')[-1]})\n{title}", fontsize=9)
    ax.grid(alpha=0.3)
    axr.grid(alpha=0.3)
    save(fig, path, dpi=120)
    return fig


def _plot_polarimetric(meas, fits, path, fig):
    """:func:`plot_fit` of polarimetric data: a panel and its residuals per quantity and state."""
    from matplotlib import rcParams
    from matplotlib.lines import Line2D

    from ..compute.measured import groups, label, measured, residual, state_text
    from ..fitting.setup import MODEL_FIXED
    shown = groups(meas)
    ncols = min(3, len(shown))
    nrows = -(-len(shown) // ncols)
    fig = figure(fig, figsize=(max(8.0, 5.2 * ncols), 1.2 + 4.4 * nrows), layout="constrained")
    grid = fig.add_gridspec(2 * nrows, ncols, height_ratios=[3, 1.3] * nrows)
    colors = rcParams["axes.prop_cycle"].by_key()["color"]
    incid = np.unique(np.round(meas.theta_i, 6))
    stds = {**meas.stds, **({"dop": meas.dop_std} if meas.dop_std is not None else {}),
            **({"f00": meas.f00_std} if meas.f00_std is not None else {})}
    params = {m: {**MODEL_FIXED[r.model], **r.x} for m, r in fits.items()}
    cols = meas.columns()
    for p, (name, norm, state, rows) in enumerate(shown):
        ax = fig.add_subplot(grid[2 * (p // ncols), p % ncols])
        axr = fig.add_subplot(grid[2 * (p // ncols) + 1, p % ncols], sharex=ax)
        text, units = label(name, norm)
        std = stds.get(name)
        for ci, ti in enumerate(incid):
            sel = rows & np.isclose(meas.theta_i, ti)
            if not sel.any():
                continue
            col = colors[ci % len(colors)]
            yerr = std[sel] if std is not None else None
            obs = cols[name][sel]
            ax.errorbar(meas.theta_r[sel], obs, yerr=yerr, fmt="o", color=col, ms=3.5, capsize=3, elinewidth=1.0,
                        label=f"theta_i = {ti:g} deg")
            phi = float(np.median(meas.phi[sel]))
            tr = np.linspace(max(0.0, meas.theta_r[sel].min() - 5), min(89.0, meas.theta_r[sel].max() + 5), 200)
            shift = 0.6 * np.min(np.diff(np.unique(meas.theta_r)), initial=5.0) / max(1, len(fits))
            for si, (model, r) in enumerate(fits.items()):
                kw = dict(incident=state, normalised=norm, params=params[model], shadowing=r.shadowing,
                          model=model, backend="numpy")
                ax.plot(tr, measured(name, ti, tr, phi, **kw), FIT_STYLES[si % 3], color=col, lw=1.2)
                res = residual(name, measured(name, meas.theta_i[sel], meas.theta_r[sel], meas.phi[sel], **kw), obs)
                marker = FIT_MARKERS[si % 3]
                axr.errorbar(meas.theta_r[sel] + (si - (len(fits) - 1) / 2) * shift, res, yerr=yerr, fmt=marker,
                             color=col, ms=4, capsize=2, elinewidth=0.8, mfc="none" if marker == "o" else col)
        where = "" if state is None else f", source {state_text(state)}"
        ax.set_title(f"{text}{where}", fontsize=9)
        ax.set_ylabel(f"{text} ({units})")
        axr.axhline(0, color="0.5", lw=0.8)
        axr.set_ylabel(f"model - data ({units})", fontsize=8)
        axr.set_xlabel("theta_r (deg)")
        for a in (ax, axr):
            a.grid(alpha=0.3)
        handles, _ = ax.get_legend_handles_labels()
        models = [Line2D([], [], ls=FIT_STYLES[si % 3], color="k", lw=1.2, label=f"{m} fit")
                  for si, m in enumerate(fits)]
        ax.legend(handles=handles + models, fontsize=7, loc="best",
                  title=f"bars: ± 1 {name}_std" if std is not None else f"no {name}_std: no error bars",
                  title_fontsize=7)
        if len(fits) > 1:
            axr.legend(handles=[Line2D([], [], ls="none", marker=FIT_MARKERS[si % 3], color="k",
                                       mfc="none" if si == 0 else "k", label=m) for si, m in enumerate(fits)],
                       fontsize=7, ncol=len(fits), loc="best")
    observed = next(iter(fits.values())).get("observed", "DOP")
    title = "; ".join(f"{n}: n={r.x['n']:.3g}, k={r.x['k']:.3g}, BIC {r.bic:.1f}" for n, r in fits.items())
    fig.suptitle(f"fit of {observed} ({meas.source.split('/')[-1]})\n{title}", fontsize=10)
    save(fig, path, dpi=120)
    return fig
