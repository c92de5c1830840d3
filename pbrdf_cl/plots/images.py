"""Figures of per-pixel fits (:func:`pbrdf_cl.fitting.images.batch.fit_batch`, ``pbrdf-cl fit-image --png``):
the parameter maps with the widths of their 95% intervals, and the fit status of every pixel;
in the stack's coordinates, robust colour scales, undetermined, not-converged and missing pixels
marked (:func:`plot_batch_maps`)."""
from __future__ import annotations

import textwrap

import numpy as np

from .common import figure, save

#: Largest side, in pixels, of a map drawn (larger images are drawn every s-th pixel).
MAX_SIDE = 1024

#: Colours of the status codes (``pbrdf_cl.fitting.images.dataset.PIXEL_STATUS``).
STATUS_COLOURS = {1: "#2ca02c", 2: "#bcbd22", 3: "#ff7f0e", 4: "#9467bd", 0: "#d62728", -1: "#7f7f7f",
                  -2: "#c7c7c7", -3: "#000000"}


def _units(attrs):
    u = attrs.get("units", "")
    return "dimensionless" if u in ("", "1") else u


#: Colour scales of the maps run over these percentiles of the values drawn (with arrows where
#: values lie beyond), so that one outlier does not flatten a map.
PERCENTILES = (2.0, 98.0)
#: Fill of the pixels a map has no value for (not fitted: masked, too few measurements, failed).
MISSING_COLOUR = "#d0d0d0"
#: Hatching of the value maps: (status code or "undetermined", hatch, legend label).
MARKS = (("undetermined", "///", "this parameter undetermined (95% interval over half its bounds)"),
         (0, "xxx", "not converged (status 0)"))
#: Characters of a panel title per line (titles are wrapped to their panel, not cut by its colour bar).
TITLE_WIDTH = 34


def _ordinal(x):
    n = int(round(x))
    return f"{x:g}" + ("th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th"))


def _image(da, step):
    """A 2-d numpy image of a (y, x) or (pixel,) variable, every ``step``-th pixel (read lazily)."""
    if da.ndim == 1:
        return np.asarray(da[::step].values)[None, :]
    return np.asarray(da[::step, ::step].values)


def _axis_coordinate(ds, dim, step):
    """(label, values) of the coordinate to draw pixel dimension ``dim`` in: a numeric, evenly
    spaced 1-d coordinate over it (the dimension's own, else one such as ``x_mm``, units in the
    label); (dim, None) for pixel indices."""
    names = [dim] + sorted(str(c) for c in ds.coords if str(c) != dim)
    for name in names:
        if name not in ds.coords or ds[name].dims != (dim,):
            continue
        v = np.asarray(ds[name].values)
        if not np.issubdtype(v.dtype, np.number) or v.size < 1 or not np.all(np.isfinite(v)):
            continue
        v = v[::step].astype(float)
        d = np.diff(v)
        if v.size > 1 and (d[0] == 0 or not np.allclose(d, d[0], rtol=1e-6, atol=0)):
            continue
        units = ds[name].attrs.get("units")
        return (f"{name} ({units})" if units else name), v
    return f"{dim} (index)", None


def _extent(cx, cy, shape):
    """imshow's extent for pixel centres at the coordinates ``cx``, ``cy`` (None: indices)."""
    def edges(c, n):
        if c is None:
            return -0.5, n - 0.5
        h = (c[1] - c[0]) / 2 if c.size > 1 else 0.5
        return c[0] - h, c[-1] + h
    x0, x1 = edges(cx, shape[1])
    y0, y1 = edges(cy, shape[0])
    return (x0, x1, y1, y0)  # row 0 at the top, at the first y value


def _limits(values):
    """(vmin, vmax, extend, robust): the PERCENTILES of the finite ``values`` (a list of arrays),
    the colour bar's arrows for values beyond them, and whether any value lies beyond."""
    finite = np.concatenate([np.asarray(a, float)[np.isfinite(a)].ravel() for a in values])
    if not finite.size:
        return 0.0, 1.0, "neither", False
    lo, hi = (float(v) for v in np.percentile(finite, PERCENTILES))
    if hi <= lo:
        lo, hi = float(finite.min()), float(finite.max())
    if hi - lo <= 1e-9 * max(abs(lo), abs(hi)) or hi <= lo:  # a flat map (to rounding): 1% either side
        mid = (lo + hi) / 2
        lo, hi = mid - max(abs(mid) * 0.01, 1e-12), mid + max(abs(mid) * 0.01, 1e-12)
    below, above = bool((finite < lo).any()), bool((finite > hi).any())
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}
    return lo, hi, extend[(below, above)], below or above


def _hatch(ax, mask, extent, hatch):
    """Hatch the pixels of ``mask`` (2-d bool) over an image drawn with ``extent``: one
    rectangle per run of marked pixels along a row, so that the pattern follows pixel edges."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle
    ny, nx = mask.shape
    x0, x1, y1, y0 = extent
    dx, dy = (x1 - x0) / nx, (y1 - y0) / ny
    rects = []
    for r in range(ny):
        row = np.concatenate([[False], mask[r], [False]])
        starts = np.flatnonzero(row[1:] & ~row[:-1])
        ends = np.flatnonzero(~row[1:] & row[:-1])
        for a, b in zip(starts, ends):
            rects.append(Rectangle((x0 + a * dx, y0 + r * dy), (b - a) * dx, dy))
    if rects:  # black hatching over a white veil: visible on light and dark colours alike
        ax.add_collection(PatchCollection(rects, facecolor=(1.0, 1.0, 1.0, 0.3), edgecolor="black", hatch=hatch,
                                          linewidth=0.0))


def plot_batch_maps(ds, path=None, *, truth=None, max_side=MAX_SIDE, fig=None):
    """Draw the maps of a per-pixel fit: per fitted parameter, its value and the width
    of its 95% interval (and, given the truth, the true map beside the fitted one on the same
    colour scale, with the share of pixels whose interval covers it), and a panel of the fit
    status.

    The maps are drawn in the stack's coordinates where the result has evenly spaced numeric
    ones over its pixel dimensions (``x_mm``, ``y_mm``: equal units, equal scales), else in
    pixel indices.  Each colour scale runs over the 2nd to 98th percentile of the values drawn
    (widened to the truth's range beside it), said on its colour bar, with arrows where values
    lie beyond.  On the value and width maps, pixels where that parameter is undetermined
    (``determined`` False) are hatched ``///``, pixels whose descent did not converge (status 0)
    ``xxx``, and pixels without a value (not fitted) are grey; a legend beside the status panel
    says so.

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.fitting.images.batch.fit_batch` (in memory or with ``store=``)
        over one or two pixel dimensions (``attrs["free"]`` names the fitted parameters).
    path : str or path, optional
        The PNG to write (``pbrdf-cl fit-image --png``; another suffix, another format); None:
        nothing is written.
    truth : xarray.Dataset, optional
        Maps ``true_<name>`` over the same pixels (a synthetic stack of
        :func:`pbrdf_cl.io.imagestack.synthetic_stack`).
    max_side : int, default 1024
        Images with more pixels along a side are drawn every s-th pixel (said in the title), so
        that a store of any size is read only in part.
    fig : matplotlib.figure.Figure, optional
        Drawn into, its size set to fit the panels (a subfigure keeps its size); default a new
        figure of that size.

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Raises
    ------
    ValueError
        A result without ``status`` or parameters, or with more than two pixel dimensions.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl, tempfile, os
    >>> from pbrdf_cl.fitting.images.batch import fit_batch
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), (2, 3, 30))
    >>> res = fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr))
    >>> png = os.path.join(tempfile.mkdtemp(), "maps.png")
    >>> fig = plot_batch_maps(res, png)
    >>> os.path.exists(png), len(fig.axes) > 6
    (True, True)

    In a notebook, into a figure of one's own (shown there; no file):

    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> fig = plot_batch_maps(res, fig=plt.figure())  # doctest: +SKIP
    """
    fig = _figure(ds, truth, max_side, fig)
    save(fig, path, dpi=100)
    return fig


def _figure(ds, truth, max_side, fig=None):
    """The matplotlib figure of :func:`plot_batch_maps`."""
    names = _check(ds)
    side = max(ds["status"].shape)
    step = max(1, -(-side // int(max_side)))
    sub = "" if step == 1 else f" (every {step}th pixel)"
    status = _image(ds["status"], step).astype(int)
    sheet = _Sheet(ds, step, status.shape, 3 if truth is not None else 2, len(names) + 1, fig)
    not_converged = status == 0
    marked = {"undetermined": False, 0: bool(not_converged.any())}
    for row, n in enumerate(names):
        marked["undetermined"] |= _parameter_row(sheet, ds, truth, n, row, step, sub, status)
    _status_row(sheet, status, sub, marked)
    model = ds.attrs.get("model", "")
    shape = ds["status"].shape
    sheet.fig.suptitle(f"per-pixel fit{f' ({model} model)' if model else ''}: {' x '.join(map(str, shape))} pixels",
                       fontsize=11, y=1 - 0.12 / sheet.fig_h, va="top")
    return sheet.fig


def _check(ds):
    """The fitted parameters of a result to draw; a ValueError for what cannot be drawn."""
    if "status" not in ds:
        raise ValueError("plot_batch_maps: the dataset has no 'status': not a result of fit_batch")
    names = str(ds.attrs.get("free", "")).split() or [str(p) for p in ds.coords.get("param", [])]
    names = [n for n in names if n in ds]
    if not names:
        raise ValueError("plot_batch_maps: the dataset has no fitted parameter maps")
    dims = ds["status"].dims
    if len(dims) > 2:
        raise ValueError(f"plot_batch_maps: maps need one or two pixel dimensions, got {dims}")
    return names


def _image_size(extent, shape, aspect):
    """(width, height) in inches of each panel's image: its aspect that of the map when drawn in
    equal units; 3 inches wide, 2 to 4 high (a colour bar shorter than 2 inches has no room for
    its label), up to 6 wide where the map is wide; beyond that (and for one pixel dimension)
    stretched."""
    if aspect == "equal":
        ratio = abs((extent[2] - extent[3]) / (extent[1] - extent[0]))
    else:
        ratio = (shape[0] / shape[1]) if len(shape) == 2 else 0.25
    img_w = 3.0
    img_h = img_w * ratio
    if img_h < 2.0:
        img_w = min(6.0, 2.0 / ratio) if aspect == "equal" else img_w
        img_h = max(2.0, img_w * ratio) if aspect == "equal" else 2.0
    if img_h > 4.0:
        img_h, img_w = 4.0, (4.0 / ratio if aspect == "equal" else img_w)
    return img_w, img_h


class _Sheet:
    """The figure's grid of panels (an image and its colour bar each), in the stack's coordinates,
    and the drawing of one map into a panel."""

    #: Margins in inches: left of an image, image to bar, the bar, right of it, above, below.
    LEFT, GAP, BAR, RIGHT, TOP, BOTTOM = 0.95, 0.08, 0.14, 1.15, 0.62, 0.58
    #: Height of the legends in the status row (of the statuses and of the marks on the maps).
    LEGEND_H = 2.9

    def __init__(self, ds, step, image_shape, ncol, nrow, fig=None):
        dims = self.dims = ds["status"].dims
        if len(dims) == 2:
            (ylab, cy), (xlab, cx) = _axis_coordinate(ds, dims[0], step), _axis_coordinate(ds, dims[1], step)
        else:
            (ylab, cy), (xlab, cx) = ("", None), _axis_coordinate(ds, dims[0], step)
        self.xlab, self.ylab = xlab, ylab
        extent = self.extent = _extent(cx, cy, image_shape)
        same_units = len(dims) == 2 and (cx is None) == (cy is None) and (
            cx is None or ds[xlab.split(" (")[0]].attrs.get("units") == ds[ylab.split(" (")[0]].attrs.get("units"))
        # the layout, in inches: each panel an image, its colour bar against it, the bar's labels,
        # and room for the title and axis labels
        img_w, img_h = _image_size(extent, ds["status"].shape, "equal" if same_units else "auto")
        self.panel_w, panel_h = self.LEFT + img_w + self.GAP + self.BAR + self.RIGHT, self.TOP + img_h + self.BOTTOM
        self.heights = [panel_h] * (nrow - 1) + [max(panel_h, self.TOP + self.LEGEND_H + self.BOTTOM)]
        self.fig_w, self.fig_h = ncol * self.panel_w + 0.2, sum(self.heights) + 0.45
        if fig is not None and hasattr(fig, "set_size_inches"):
            fig.set_size_inches(self.fig_w, self.fig_h)
        fig = self.fig = figure(fig, figsize=(self.fig_w, self.fig_h))
        self.axes = np.empty((nrow, ncol), object)
        self.caxes = np.empty((nrow, ncol), object)
        for r in range(nrow):
            for c in range(ncol):
                x0 = 0.1 + c * self.panel_w + self.LEFT
                y0 = self.fig_h - 0.45 - sum(self.heights[:r]) - self.TOP - img_h
                self.axes[r, c] = fig.add_axes([x0 / self.fig_w, y0 / self.fig_h, img_w / self.fig_w,
                                                img_h / self.fig_h])
                self.caxes[r, c] = fig.add_axes([(x0 + img_w + self.GAP) / self.fig_w, y0 / self.fig_h,
                                                 self.BAR / self.fig_w, img_h / self.fig_h])
                self.caxes[r, c].set_axis_off()
        self.missing = False  # a map has pixels without a value

    def label_axes(self, ax):
        ax.set_xlabel(self.xlab)
        ax.set_ylabel(self.ylab)
        if len(self.dims) == 1:
            ax.set_yticks([])

    def draw(self, at, img, title, cmap, label, limits, marks=None):
        """Map ``img`` into panel ``at`` on the colour scale ``limits`` (:func:`_limits`, and
        "truth" fifth where the scale was widened to the truth's), hatched where ``marks`` say."""
        from matplotlib import colormaps
        ax, cax = self.axes[at], self.caxes[at]
        lo, hi, extend, robust = limits[:4]
        cm = colormaps[cmap].with_extremes(bad=MISSING_COLOUR)
        im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, vmin=lo, vmax=hi, interpolation="nearest", aspect="auto",
                       extent=self.extent)
        self.missing = self.missing or bool(np.isnan(img).any())
        for mask, hatch in marks or ():
            _hatch(ax, mask, self.extent, hatch)
        ax.set_title(textwrap.fill(title, TITLE_WIDTH), fontsize=9)
        self.label_axes(ax)
        if robust:  # (short: the label must not run past the bar into the title)
            label += f"\nscale: {_ordinal(PERCENTILES[0])}-{_ordinal(PERCENTILES[1])} percentile" + (
                ", truth" if len(limits) > 4 else "")
        cax.set_axis_on()
        cb = self.fig.colorbar(im, cax=cax, extend=extend)
        cb.set_label(label, fontsize=8)
        if hasattr(cb.formatter, "set_useOffset"):
            cb.formatter.set_useOffset(False)  # no "1e-8+5e-2" above the bar, into the title


def _truth_limits(value, true, limits):
    """The value map's colour scale widened to the truth's range (the truth drawn whole on it)."""
    lo, hi = limits[:2]
    finite = true[np.isfinite(true)]
    if not finite.size:
        return limits
    lo, hi = min(lo, float(finite.min())), max(hi, float(finite.max()))
    below, above = bool((value < lo).any()), bool((value > hi).any())
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max"}.get((below, above), "both")
    return (lo, hi, extend, below or above, "truth")


def _parameter_row(sheet, ds, truth, n, row, step, sub, status):
    """The row of parameter ``n``: its truth (given one), its value and the width of its 95%
    interval; returns whether any pixel was hatched as undetermined."""
    value = _image(ds[n], step)
    ci = ds[f"{n}_ci95"] if f"{n}_ci95" in ds else None
    long = ds[n].attrs.get("long_name", "")
    label = f"{n} ({_units(ds[n].attrs)})"
    undetermined = np.zeros(value.shape, bool)
    if "determined" in ds and "param" in ds["determined"].dims and n in list(ds["determined"].param.values):
        undetermined = ~_image(ds["determined"].sel(param=n), step).astype(bool) & (status >= 0) & (status != 0) \
            & np.isfinite(value)
    marks = [(undetermined, MARKS[0][1]), (status == 0, MARKS[1][1])]
    limits = _limits([value])
    true = None
    if truth is not None and f"true_{n}" in truth:
        true = _image(truth[f"true_{n}"], step)
        limits = _truth_limits(value, true, limits)
    col = 0
    if truth is not None:
        if true is not None:
            cover = ""
            if ci is not None:
                l_, h_ = _image(ci.isel(bound=0), step), _image(ci.isel(bound=1), step)
                fitted = np.isfinite(l_)
                cover = (f"; 95% intervals cover it in {np.mean(((l_ <= true) & (true <= h_))[fitted]):.1%} "
                         "of pixels")
            sheet.draw((row, 0), true, f"{n}: truth{cover}{sub}", "viridis", label, limits)
        else:
            sheet.axes[row, 0].set_axis_off()
        col = 1
    sheet.draw((row, col), value, f"{n}: {long}{sub}" if long else f"{n}{sub}", "viridis", label, limits, marks)
    if ci is not None:
        width = _image(ci.isel(bound=1), step) - _image(ci.isel(bound=0), step)
        sheet.draw((row, col + 1), width, f"{n}: width of the 95% interval (high - low){sub}", "magma",
                   f"width of {n} ({_units(ds[n].attrs)})", _limits([width]), marks)
    else:
        sheet.axes[row, col + 1].set_axis_off()
    return bool(undetermined.any())


def _status_row(sheet, status, sub, marked):
    """The last row: the status of every pixel (one colour per code) and, beside it, the legends of
    the statuses (with each code's pixels) and of the marks on the maps."""
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    from ..fitting.images.dataset import PIXEL_STATUS as STATUS
    codes = sorted(STATUS)
    colours = [STATUS_COLOURS.get(c, "#ffffff") for c in codes]
    cmap = ListedColormap(colours)
    norm = BoundaryNorm([c - 0.5 for c in codes] + [codes[-1] + 0.5], cmap.N)
    ax = sheet.axes[-1, 0]
    ax.imshow(status, cmap=cmap, norm=norm, interpolation="nearest", aspect="auto", extent=sheet.extent)
    ax.set_title(f"fit status{sub}", fontsize=9)
    sheet.label_axes(ax)
    counts = {c: int((status == c).sum()) for c in codes}
    handles = [Patch(color=STATUS_COLOURS.get(c, "#ffffff"), label=f"{c}: {STATUS[c][0]} ({counts[c]})")
               for c in codes if counts[c]]
    for ax in sheet.axes[-1, 1:]:
        ax.set_axis_off()
    # the legends in the rest of the last row
    x0 = (0.1 + sheet.panel_w) / sheet.fig_w
    legend_ax = sheet.fig.add_axes([x0, (sheet.fig_h - 0.45 - sum(sheet.heights[:-1]) - sheet.TOP - sheet.LEGEND_H)
                                    / sheet.fig_h, 0.98 - x0, sheet.LEGEND_H / sheet.fig_h])
    legend_ax.set_axis_off()
    legend_ax.legend(handles=handles, loc="upper left", title="status (pixels drawn)", fontsize=9,
                     title_fontsize=10, frameon=False, alignment="left")
    maps = [Patch(facecolor=(1.0, 1.0, 1.0, 0.3), edgecolor="black", hatch=hatch, linewidth=0.0, label=text)
            for key, hatch, text in MARKS if marked[key]]
    if sheet.missing:
        maps.append(Patch(facecolor=MISSING_COLOUR, label="no value: not fitted (see the status)"))
    if maps:
        legend_ax.add_artist(legend_ax.get_legend())
        legend_ax.legend(handles=maps, loc="lower left", title="on the maps", fontsize=9, title_fontsize=10,
                         frameon=False, alignment="left", handleheight=1.6, handlelength=2.4)
