"""Figures of two-axis maps (:func:`pbrdf_cl.analysis.maps.make_map`, ``pbrdf-cl map``): the quantity
with labelled contour lines and a colour bar, and its derivative in a second panel
(:func:`plot_map`); the contour levels and labels the paper's maps use too."""
from __future__ import annotations

import numpy as np

from ..model import quantities
from .common import LABELS, figure, save, width_inches

#: Colour-bar labels of the quantities that have maps (from the registry).
QUANTITY_LABELS = {n: quantities.REGISTRY[n].label for n in quantities.names("map")}


def _fixed_text(attrs, skip=()):
    items = [(k[6:], v) for k, v in attrs.items() if k.startswith("fixed_") and k[6:] not in skip]
    return ", ".join(f"{k}={v:g}" for k, v in items)


#: A log-scaled BRDF map shows at most this many decades below its maximum: lower values (F00
#: with kd = 0 falls to 1e-12 and below off the specular peak) take the lowest colour, and the
#: colour bar says so.
LOG_DECADES = 5
#: Contour labels keep at least this far from the axes' edges, from each other and from the
#: lines of other levels (fractions of the axes' width and height).
LABEL_MARGIN = 0.06
LABEL_SPACING = 0.12
LABEL_CLEARANCE = 0.03


def _norm_for(values, quantity):
    """(norm, note) for the quantity's panel: a log scale for a BRDF spanning more than two decades,
    floored at max / 10**LOG_DECADES; (None, "") for a linear scale.  ``note`` says what the
    colour bar shows ("log scale", and the floor where values lie below it)."""
    from matplotlib import colors
    finite = values[np.isfinite(values)]
    if quantity != "brdf" or not finite.size or finite.max() <= 0:
        return None, ""
    top = float(finite.max())
    positive = finite[finite > 0]
    low = float(positive.min())
    if top / low <= 100:
        return None, ""
    floor = top / 10.0 ** LOG_DECADES
    if low >= floor and positive.size == finite.size:
        return colors.LogNorm(low, top), "log scale"
    return colors.LogNorm(floor, top), f"log scale, clipped below max/1e{LOG_DECADES} = {floor:.2g}"


def contour_levels(z, norm=None, n=8):
    """At most ``n`` round contour levels strictly inside the finite range of ``z``: decades for a
    log norm (within its range), else nice linear steps."""
    from matplotlib import ticker
    finite = z[np.isfinite(z)]
    if norm is not None and hasattr(norm, "vmin") and type(norm).__name__ == "LogNorm":
        lo, hi = np.log10(norm.vmin), np.log10(norm.vmax)
        levels = 10.0 ** np.arange(np.ceil(lo), np.floor(hi) + 1)
    else:
        levels = ticker.MaxNLocator(n, steps=[1, 2, 2.5, 5, 10]).tick_values(finite.min(), finite.max())
    return levels[(levels > finite.min()) & (levels < finite.max())]


def label_contours(ax, cs, fmt="%.3g", fontsize=7, margin=LABEL_MARGIN, spacing=LABEL_SPACING,
                   clearance=LABEL_CLEARANCE):
    """Label each level of the contour set ``cs`` at most once, inside the axes and readable: at
    least ``margin`` from the edges, ``spacing`` from the other labels and ``clearance`` from the
    lines of other levels (fractions of the axes); the line is broken under its label.  A level
    with no such place (a short line in a corner, lines crowded together) stays unlabelled.
    Returns the labels (matplotlib Text objects)."""
    from scipy.spatial import cKDTree
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()

    def unit(v):  # data -> fractions of the axes
        return np.column_stack([(v[:, 0] - x0) / (x1 - x0), (v[:, 1] - y0) / (y1 - y0)])
    lines = [unit(np.concatenate(segs)) if segs and sum(len(sg) for sg in segs) else np.empty((0, 2))
             for segs in cs.allsegs]
    placed, chosen, data_points = [], [], []
    for i, pts in enumerate(lines):
        if not len(pts):
            continue
        edge = np.minimum(np.minimum(pts[:, 0], 1 - pts[:, 0]), np.minimum(pts[:, 1], 1 - pts[:, 1]))
        others = [p for j, p in enumerate(lines) if j != i and len(p)]
        d_other = cKDTree(np.concatenate(others)).query(pts)[0] if others else np.full(len(pts), np.inf)
        d_label = cKDTree(np.array(placed)).query(pts)[0] if placed else np.full(len(pts), np.inf)
        ok = (edge >= margin) & (d_other >= clearance) & (d_label >= spacing)
        if not ok.any():
            continue
        score = np.minimum.reduce([edge / margin, d_other / clearance, d_label / spacing])
        score[~ok] = -np.inf
        k = int(np.argmax(score))
        placed.append(pts[k])
        chosen.append(cs.levels[i])
        data_points.append((x0 + pts[k, 0] * (x1 - x0), y0 + pts[k, 1] * (y1 - y0)))
    if not data_points:
        return []
    return ax.clabel(cs, chosen, inline=True, inline_spacing=3, fontsize=fontsize, fmt=fmt,
                          manual=data_points)


def _title(text, inches, fontsize):
    """``text`` wrapped to ``inches`` of width (about 0.55 em per character)."""
    import textwrap
    width = max(30, int(inches * 72 / (0.55 * fontsize)) - 4)
    return "\n".join(textwrap.fill(line, width, break_long_words=False) for line in text.split("\n"))


def _symlog_ticks(norm, lim, min_gap=0.07):
    """Ticks of a symmetric-log colour bar: 0 and +-decades, none closer than ``min_gap`` (of the
    bar's length) to one already kept, the largest magnitudes first."""
    lo = np.floor(np.log10(norm.linthresh))
    hi = np.floor(np.log10(lim))
    mags = 10.0 ** np.arange(lo, hi + 1)[::-1]
    kept, pos = [0.0], [float(norm(0.0))]
    for m in mags:
        for v in (m, -m):
            p = float(norm(v))
            if all(abs(p - q) >= min_gap for q in pos):
                kept.append(v)
                pos.append(p)
    return sorted(kept)


def plot_map(ds, path=None, title=None, dpi=120, *, fig=None):
    """Draw a map: the quantity with labelled contour lines and a colour bar, and the derivative
    (diverging colours, zero-centred) in a second panel when present.

    A BRDF over more than two decades is on a log scale of at most ``LOG_DECADES`` decades
    (the colour bar says where it is clipped).

    Parameters
    ----------
    ds : xarray.Dataset
        From :func:`pbrdf_cl.analysis.maps.make_map`.
    path : str or path, optional
        The PNG to write (``pbrdf-cl map --out``; another suffix, another format); None: nothing
        is written.
    title : str, optional
        Instead of the quantity, axes and fixed inputs.
    dpi : int, default 120
        Resolution of the file written.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into (a panel per variable, side by side); default a new figure 6.2 inches wide per
        panel and 5 high, with constrained layout.

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Examples
    --------
    >>> from pbrdf_cl.analysis.maps import make_map
    >>> ds = make_map("theta_r=0:85@64", "sigma=0.05:1@32", dict(theta_i=40, n=1.6, k=2.1))  # doctest: +SKIP
    >>> plot_map(ds, "map.png")  # doctest: +SKIP

    In a notebook, into a figure of one's own; or the DOP and the AoP side by side, each in a
    subfigure:

    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> fig = plot_map(ds, fig=plt.figure(figsize=(6.2, 5), layout="constrained"))  # doctest: +SKIP
    >>> aop = make_map("theta_r=0:85@64", "sigma=0.05:1@32", dict(theta_i=40, n=1.6, k=2.1),
    ...                quantity="aop")  # doctest: +SKIP
    >>> left, right = plt.figure(figsize=(12.4, 5), layout="constrained").subfigures(1, 2)  # doctest: +SKIP
    >>> _ = plot_map(ds, fig=left), plot_map(aop, fig=right)  # doctest: +SKIP
    """
    from matplotlib import colors
    xname, yname = ds.attrs["x"], ds.attrs["y"]
    quantity = ds.attrs["quantity"]
    deriv = ds.attrs.get("derivative")
    panels = [quantity] + ([f"d{quantity}_d{deriv}"] if deriv else [])
    fig = figure(fig, figsize=(6.2 * len(panels), 5.0), layout="constrained")
    axs = fig.subplots(1, len(panels), squeeze=False)
    x, y = ds[xname].values, ds[yname].values
    suptitle = title or (f"{QUANTITY_LABELS[quantity]} over ({xname}, {yname}); "
                         f"{_fixed_text(ds.attrs)}; shadowing {ds.attrs['shadowing']}")
    fig.suptitle(_title(suptitle, width_inches(fig), 10), fontsize=10)
    contours = []
    for ax, var in zip(axs[0], panels):
        z = ds[var].values
        extend = "neither"
        if var == quantity:
            q = quantities.get(quantity)
            norm, note = _norm_for(z, quantity)
            if norm is not None and np.nanmin(z) < norm.vmin:
                extend = "min"
            mesh = ax.pcolormesh(x, y, z, shading="auto", cmap=q.cmap, norm=norm,
                                 **({} if norm is not None else dict(vmin=q.vmin, vmax=q.vmax)))
            if q.period is None and np.isfinite(z).any() and np.ptp(z[np.isfinite(z)]) > 0:
                levels = contour_levels(z, norm)
                if levels.size:
                    cs = ax.contour(x, y, z, levels=levels, colors="white", linewidths=0.7)
                    contours.append((ax, cs, "%g" if norm is not None else "%.3g"))
            label = QUANTITY_LABELS[quantity] + (f", {note}" if note else "")
        else:
            # derivatives often span decades (steep where sigma -> 0): a symmetric-log scale, linear
            # within the median |derivative|, keeps the rest of the map readable
            mag = np.abs(z[np.isfinite(z)])
            lim = float(mag.max()) or 1.0
            thresh = float(np.median(mag))
            if thresh > 0 and lim / thresh > 30:
                norm = colors.SymLogNorm(linthresh=thresh, vmin=-lim, vmax=lim)
            else:
                norm = colors.Normalize(-lim, lim)
            mesh = ax.pcolormesh(x, y, z, shading="auto", cmap="RdBu_r", norm=norm)
            label = f"d{QUANTITY_LABELS[quantity].split()[0]} / d{deriv}"
            if isinstance(norm, colors.SymLogNorm):
                label += ", symmetric log scale"
            if (z > 0).any() and (z < 0).any():
                ax.contour(x, y, z, levels=[0.0], colors="k", linewidths=0.8)
                label += " (black line: 0)"
        cb = fig.colorbar(mesh, ax=ax, extend=extend)
        if isinstance(norm, colors.SymLogNorm):
            cb.set_ticks(_symlog_ticks(norm, lim))
        elif var == quantity and q.period is not None:
            cb.set_ticks(np.linspace(q.vmin, q.vmax, 5))  # an angle: -90, -45, 0, 45, 90
        cb.set_label(label)
        ax.set_xlabel(LABELS[xname])
        ax.set_ylabel(LABELS[yname])
        ax.set_title(_title(label, 4.6, 10), fontsize=10)
    fig.figure.draw_without_rendering()  # the layout first: labels are placed in the axes' final shape
    for ax, cs, fmt in contours:
        label_contours(ax, cs, fmt=fmt)
    save(fig, path, dpi=dpi)
    return fig
