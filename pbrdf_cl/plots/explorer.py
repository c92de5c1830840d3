"""The explorer's current view as one PNG (its *view as PNG* export): the curves of the shown sets
with the measurements, their polar plot, the map with its colour bar (and the AoP's orientation
ticks), and the residuals, drawn from the view's Dataset
(:func:`pbrdf_cl.app.state.view_dataset`) with matplotlib."""
from __future__ import annotations

import numpy as np

from .common import figure, save

#: The explorer's parameter sets and their colours, on the page (``pbrdf_cl.app.state``: SET_NAMES,
#: COLOURS) and in its PNG.
SET_COLOURS = {"A": "#1f77b4", "B": "#d62728", "C": "#2ca02c", "D": "#9467bd"}


def _each_curve(c):
    """(set, theta_i, values, matplotlib style) of every curve of ``c``: a colour per set, a line
    style per incidence, as the page draws them."""
    styles = ("-", "--", ":", "-.")
    for s in c["set"].values:
        for j, ti in enumerate(c["theta_i"].values):
            yield s, ti, c.sel(set=s, theta_i=ti).values, dict(color=SET_COLOURS.get(str(s), "k"),
                                                                linestyle=styles[j % len(styles)])


def _curves(ax, ds):
    c = ds["curve"]
    for s, ti, values, style in _each_curve(c):
        ax.plot(c["theta_r"], values, label=f"set {s}, theta_i {ti:g}°", **style)
    data = f"data_{ds.attrs['quantity']}"  # the measurements of the view's quantity (and source)
    if data in ds:
        std = ds[f"{data}_std"].values if f"{data}_std" in ds else None
        ax.errorbar(ds["data_theta_r"], ds[data], yerr=std, fmt="o", color="k", ms=3, label="data")
    ax.set_xlabel("theta_r (deg)")
    ax.set_ylabel(f"{c.attrs['long_name']} ({c.attrs['units']})")
    source = f", source {ds.attrs['source']}" if "source" in ds.attrs else ""
    ax.set_title(f"{c.attrs['long_name']} at phi = {ds.attrs['phi_curves']:g}°{source}")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)


def _map(fig, ax, ds):
    m = ds["map"]
    values = np.ma.masked_invalid(m.values)
    if ds.attrs["map_kind"] == "incidence":
        x, y = m["map_theta_r"].values, m["map_theta_i"].values
        ax.set_xlabel("theta_r (deg)")
        ax.set_ylabel("theta_i (deg)")
        ax.set_title(f"set {ds.attrs['active_set']} over (theta_i, theta_r), phi = {m.attrs['phi']:g}°")
    else:
        x, y = m["map_x"].values, m["map_y"].values
        ax.set_xlabel("x = (theta_r / 90°) cos(phi_r) (1)")
        ax.set_ylabel("y = (theta_r / 90°) sin(phi_r) (1)")
        ax.set_title(f"set {ds.attrs['active_set']}: hemisphere from above, theta_i = {m.attrs['theta_i']:g}°")
    aop = ds.attrs["quantity"] == "aop"  # an angle: a cyclic colour map, as the maps of pbrdf-cl map draw it
    mesh = ax.pcolormesh(x, y, values, shading="nearest", cmap="twilight" if aop else "viridis",
                         **(dict(vmin=-90, vmax=90) if aop else {}))
    if "tick_x0" in ds:  # the page's orientation ticks: the AoP's direction at each lattice node
        from matplotlib.collections import LineCollection
        ends = np.stack([np.stack([ds["tick_x0"], ds["tick_y0"]], -1), np.stack([ds["tick_x1"], ds["tick_y1"]], -1)], 1)
        ax.add_collection(LineCollection(ends, colors="k", linewidths=1.2, label="AoP orientation"),
                          autolim=False)  # the map sets the limits; edge ticks are clipped
        ax.legend(loc="upper right", fontsize=7)
    ax.set_aspect("equal")
    cax = ax.inset_axes([1.04, 0.0, 0.04, 1.0])  # beside the map and as tall as it, not the figure's height
    fig.colorbar(mesh, cax=cax, label=f"{m.attrs['long_name']} ({m.attrs['units']})")


def _polar(ax, ds):
    """The curves as the page's polar plot: radius |value|, angle theta_r from the normal (up)."""
    c = ds["curve"]
    rad = np.radians(c["theta_r"].values)
    for _, _, values, style in _each_curve(c):
        ax.plot(rad, np.abs(values), **style)
    top = float(np.nanmax(np.abs(c.values), initial=0.0)) if c.size else 0.0
    ax.set_ylim(0.0, top * 1.05 if top > 0 else 1.0)
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    ax.set_thetamin(0)
    ax.set_thetamax(90)
    ax.set_xlabel("theta_r (deg) from the normal")
    ax.set_title(f"polar: radius |{c.attrs['long_name']}| ({c.attrs['units']})", fontsize=10)


def plot_view(ds, path=None, *, fig=None):
    """Draw the explorer's view.

    Parameters
    ----------
    ds : xarray.Dataset
        The view's numbers, as :func:`pbrdf_cl.app.state.view_dataset` returns them.
    path : str, path or file object, optional
        Where to write the PNG; None: nothing is written.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into; default a new figure 17 inches wide, with constrained layout.

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Examples
    --------
    >>> import io, pbrdf_cl
    >>> from pbrdf_cl.app import state
    >>> view = state.State()
    >>> view.settings.resolution = 32
    >>> fig = plot_view(state.view_dataset(pbrdf_cl.get_default_engine(), view), io.BytesIO())
    >>> len(fig.axes) >= 3  # curves, polar plot, map (and its colour bar)
    True
    """
    rows = 2 if "residual" in ds else 1
    fig = figure(fig, figsize=(17, 5.5 + 2.5 * (rows - 1)), layout="constrained")
    grid = fig.add_gridspec(rows, 3, height_ratios=[3, 1.5][:rows], width_ratios=[3, 2, 3])
    ax = fig.add_subplot(grid[0, 0])
    _curves(ax, ds)
    _polar(fig.add_subplot(grid[0, 1], projection="polar"), ds)
    _map(fig, fig.add_subplot(grid[:, 2]), ds)
    if rows == 2:
        axr = fig.add_subplot(grid[1, 0], sharex=ax)
        std_name = f"data_{ds.attrs['quantity']}_std"
        std = ds[std_name].values if std_name in ds else None
        axr.errorbar(ds["data_theta_r"], ds["residual"], yerr=std, fmt="o", color="k", ms=3)
        axr.axhline(0, color="grey", lw=0.8)
        axr.set_xlabel("theta_r (deg)")
        axr.set_ylabel(f"{ds['curve'].attrs['long_name']} residual ({ds['curve'].attrs['units']})")
        axr.set_title(f"data - set {ds.attrs['active_set']}")
        axr.grid(alpha=0.3)
    save(fig, path, dpi=110, format="png")
    return fig
