"""Figures of sensitivity maps (:func:`pbrdf_cl.sobol`, ``pbrdf-cl sobol --png``): which
parameter controls the DOP (or F00) where.

* Two geometry axes: one panel per parameter over the two axes (theta_i horizontal where it is
  one of them, as in the design figure), two rows (Sobol': S1 and ST; Morris: mu* and ee_std),
  one colour scale per row (0..1 for Sobol' indices) with its colour bar.
* One geometry axis: S1 and ST (mu* and ee_std) of every parameter as lines, with the 95%
  bootstrap intervals as bands.

Geometries where the output does not vary over the box (``constant``: every index is 0 there and
means nothing) are hatched grey and named in a legend.  For the DOP with ks fixed, kd is labelled
kd/ks, the only combination the DOP depends on.
"""
from __future__ import annotations

import numpy as np

from ..io.results import compatible
from .common import LABELS, figure, save

#: What each drawn variable is called on a figure.
NAMES = {"S1": "first-order index S1", "ST": "total index ST", "mu_star": "mu* (mean |elementary effect|)",
         "ee_std": "sd of the elementary effects (SALib's sigma)"}
#: Their short names in panel titles.
SHORT = {"S1": "S1", "ST": "ST", "mu_star": "mu*", "ee_std": "sd of the effects"}
#: How geometries where the output is constant over the box are drawn.
CONSTANT_STYLE = dict(facecolor="0.85", edgecolor="0.45", hatch="xxx", linewidth=0.0)
#: The bootstrap interval drawn with a variable (1-d figures).
CONF = {"S1": "S1_conf", "ST": "ST_conf", "mu_star": "mu_star_conf"}


def _range_text(ds, p):
    """``"k in [0.01, 3] (log)"`` from the attributes :func:`pbrdf_cl.sobol` writes; for the DOP
    with ks fixed, kd is named kd/ks (ks = 1) or given its kd/ks range too."""
    r = ds.attrs.get(f"range_{p}")
    if r is None or len(np.ravel(r)) != 2:
        return str(p)
    lo, hi = np.ravel(r)
    log = " (log)" if ds.attrs.get(f"scale_{p}") == "log" else ""
    ks = ds.attrs.get("fixed_ks")
    if p == "kd" and ds.attrs.get("quantity") == "dop" and ks is not None:
        ks = float(ks)
        if ks == 1.0:
            return f"kd/ks in [{lo:g}, {hi:g}]{log} (ks = 1)"
        return f"kd in [{lo:g}, {hi:g}]{log}: kd/ks in [{lo / ks:g}, {hi / ks:g}]"
    return f"{p} in [{lo:g}, {hi:g}]{log}"


def _edges(v):
    """Cell edges around the centres ``v`` (as pcolormesh's nearest shading draws them)."""
    v = np.asarray(v, float)
    if v.size == 1:
        return np.array([v[0] - 0.5, v[0] + 0.5])
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[2 * v[0] - mid[0]], mid, [2 * v[-1] - mid[-1]]])


def _constant_legend(ds):
    from matplotlib.patches import Patch
    what = "DOP" if ds.attrs.get("quantity") == "dop" else str(ds.attrs.get("quantity", "the output"))
    return Patch(**CONSTANT_STYLE, label=f"{what} constant over the box here: indices undefined (0)")


def _title(ds, geo):
    a = ds.attrs
    method = a.get("method", "sobol")
    what = "Sobol' indices" if method == "sobol" else "Morris screening"
    q = str(a.get("quantity", "")).upper() if a.get("quantity") == "dop" else a.get("quantity", "")
    fixed = ", ".join(f"{k[6:]}={v:g}" for k, v in a.items() if k.startswith("fixed_"))
    scalars = ", ".join(f"{n}={float(ds[n]):g} deg" for n in ("theta_i", "theta_r", "phi")
                        if n in ds.coords and ds[n].ndim == 0)
    size = "N" if method == "sobol" else "trajectories"
    parts = [f"{what} of {q} over {' x '.join(geo)}", f"{size}={a.get('N', '?')}",
             f"{a.get('runs_per_geometry', '?')} runs per geometry"]
    if scalars:
        parts.append(scalars)
    if fixed:
        parts.append(f"fixed {fixed}")
    return ", ".join(parts)


def _rows(ds):
    if "S1" in ds:
        return ("S1", "ST")
    if "mu_star" in ds:
        return ("mu_star", "ee_std")
    raise ValueError("plot_sensitivity: the dataset has neither S1/ST nor mu_star/ee_std: not a result of "
                     "pbrdf_cl.sobol")


def check_axes(axes, what="plot_sensitivity"):
    """A ``ValueError`` unless ``axes`` (name -> values: the geometry axes of a result) are one or
    two, the figure's layouts; it suggests how to get there."""
    geo = list(axes)
    if len(geo) in (1, 2):
        return
    if geo:
        order = [g for g in ("theta_i", "theta_r", "phi") if g in geo] + [g for g in geo if g not in
                                                                          ("theta_i", "theta_r", "phi")]
        drop = order[2:]  # keep theta_i and theta_r where they are axes
        first = np.ravel(axes[drop[0]])[0]
        hint = f"; select a value of {', '.join(drop)} first, e.g. ds.sel({drop[0]}={float(first):g})"
    else:
        hint = "; compute it over one or two geometry axes with more than one value (e.g. theta_r = \"0:85@64\")"
    raise ValueError(f"{what}: draws one or two geometry axes, got {len(geo)}"
                     f"{' (' + ', '.join(geo) + ')' if geo else ''}{hint}")


def plot_sensitivity(ds, path=None, *, title=None, dpi=110, fig=None):
    """Draw a sensitivity map (a result of :func:`pbrdf_cl.sobol`).

    Parameters
    ----------
    ds : xarray.Dataset
        ``S1``, ``ST`` (and ``S1_conf``, ``ST_conf``) or ``mu_star``, ``ee_std`` (and
        ``mu_star_conf``; a result with Morris' old ``sigma`` is read too) over ``parameter`` and
        one or two geometry axes (theta_i, theta_r, phi; degrees), and ``constant`` where
        present.  Select a value of a third axis first (``ds.sel(phi=180)``).
    path : str or path, optional
        The PNG to write (``pbrdf-cl sobol --png``; another suffix, another format); None:
        nothing is written.
    title : str, optional
        The figure's title (default: the method, quantity, axes, N, runs and fixed values).
    dpi : int, default 110
        Resolution of the PNG.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into; default a new figure with constrained layout (two axes: 3.1 inches wide per
        parameter plus 1.4, and 6.8 high; one axis: 11 x 4.6 inches).

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Raises
    ------
    ValueError
        A dataset without the indices, or with no geometry axis or more than two.

    Examples
    --------
    >>> import os, tempfile, pbrdf_cl
    >>> ds = pbrdf_cl.sobol({"n": (1.2, 2.5), "k": (0.01, 3, "log"), "sigma": (0.1, 0.6)},
    ...                     {"theta_i": "0:80@5", "theta_r": "0:85@6"}, N=64, seed=1)
    >>> png = os.path.join(tempfile.mkdtemp(), "s.png")
    >>> fig = plot_sensitivity(ds, png)
    >>> os.path.exists(png), len(fig.axes)  # S1 and ST of 3 parameters, 2 colour bars
    (True, 8)

    In a notebook, into a figure of one's own (shown there; no file):

    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> fig = plot_sensitivity(ds, fig=plt.figure(figsize=(10.7, 6.8), layout="constrained"))  # doctest: +SKIP
    """
    ds = compatible(ds)
    rows = _rows(ds)
    geo = [d for d in ds[rows[0]].dims if d != "parameter"]
    check_axes({d: ds[d].values for d in geo})
    if len(geo) == 2:
        fig = _maps(fig, ds, rows, geo)
    else:
        fig = _lines(fig, ds, rows, geo[0])
    fig.suptitle(title or _title(ds, geo), fontsize=10, wrap=True)
    save(fig, path, dpi=dpi)
    return fig


def _units(ds, var):
    u = ds[var].attrs.get("units", "1")
    return "" if u in ("", "1") else f" ({u})"


def _constant_cells(ds, names):
    """The ``constant`` flags over ``names`` (the figure's geometry axes, in that order), or None."""
    if "constant" not in ds:
        return None
    c = ds["constant"]
    if not set(names) <= set(c.dims):
        return None
    c = c.transpose(*names).values.astype(bool)
    return c if c.any() else None


def _maps(fig, ds, rows, geo):
    from matplotlib import colors
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle
    params = [str(p) for p in ds.parameter.values]
    xname, yname = geo
    x, y = ds[xname].values, ds[yname].values
    ncol = len(params)
    fig = figure(fig, figsize=(3.1 * ncol + 1.4, 6.8), layout="constrained")
    axs = fig.subplots(2, ncol, sharex=True, sharey=True, squeeze=False)
    sobol = rows[0] == "S1"
    const = _constant_cells(ds, (yname, xname))
    xe, ye = _edges(x), _edges(y)
    for r, var in enumerate(rows):
        z_all = ds[var].transpose("parameter", yname, xname).values
        if sobol:
            norm = colors.Normalize(0.0, 1.0)
        else:
            finite = z_all[np.isfinite(z_all)]
            top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
            norm = colors.Normalize(0.0, top)
        for c, p in enumerate(params):
            ax = axs[r, c]
            mesh = ax.pcolormesh(x, y, z_all[c], shading="auto", cmap="viridis", norm=norm)
            if const is not None:
                iy, ix = np.nonzero(const)
                cells = [Rectangle((xe[i], ye[j]), xe[i + 1] - xe[i], ye[j + 1] - ye[j]) for j, i in zip(iy, ix)]
                ax.add_collection(PatchCollection(cells, match_original=False, **CONSTANT_STYLE))
            vals = z_all[c] if const is None else z_all[c][~const]
            mean = np.nanmean(vals)
            ax.set_title(f"{_range_text(ds, p)}\n{SHORT[var]}, mean {mean:.2g}", fontsize=9)
            if r == 1:
                ax.set_xlabel(LABELS.get(xname, f"{xname} (deg)"), fontsize=8)
            if c == 0:
                ax.set_ylabel(LABELS.get(yname, f"{yname} (deg)"), fontsize=8)
        label = NAMES[var] + ("" if sobol else _units(ds, var))
        cb = fig.colorbar(mesh, ax=list(axs[r]), shrink=0.9, extend="both" if sobol else "neither")
        cb.set_label(label)
    if const is not None:
        fig.legend(handles=[_constant_legend(ds)], loc="outside lower center", fontsize=8, frameon=False)
    return fig


def _lines(fig, ds, rows, xname):
    params = [str(p) for p in ds.parameter.values]
    x = ds[xname].values
    fig = figure(fig, figsize=(11.0, 4.6), layout="constrained")
    axs = fig.subplots(1, 2, sharex=True)
    sobol = rows[0] == "S1"
    const = _constant_cells(ds, (xname,))
    xe = _edges(x)
    for ax, var in zip(axs, rows):
        for i, p in enumerate(params):
            v = ds[var].sel(parameter=p).values
            ax.plot(x, v, "-", color=f"C{i}", lw=1.5, label=_range_text(ds, p))
            conf = CONF.get(var)
            if conf in ds:
                half = ds[conf].sel(parameter=p).values
                ax.fill_between(x, v - half, v + half, color=f"C{i}", alpha=0.2, lw=0)
        if const is not None:
            for i in np.nonzero(const)[0]:
                ax.axvspan(xe[i], xe[i + 1], zorder=0, **CONSTANT_STYLE)
        ax.set_xlabel(LABELS.get(xname, f"{xname} (deg)"))
        ax.set_ylabel(NAMES[var] + ("" if sobol else _units(ds, var)))
        if sobol:
            ax.set_ylim(-0.05, 1.05)
        else:
            ax.set_ylim(bottom=0.0)
        band = " (bands: 95% bootstrap intervals)" if CONF.get(var) in ds else ""
        ax.set_title(f"{NAMES[var]}{band}", fontsize=9)
        ax.grid(alpha=0.3)
    handles, labels = axs[0].get_legend_handles_labels()
    if const is not None:
        handles.append(_constant_legend(ds))
    axs[0].legend(handles=handles, fontsize=8)
    return fig
