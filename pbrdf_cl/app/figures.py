"""The explorer's Bokeh figures and how each is redrawn from the numbers of :mod:`.state`: the
in-plane curves, the residuals, the polar plot, the map (with AoP ticks, the measurements and a
design's geometries) and the Sobol' maps.  Every renderer reads a named ``ColumnDataSource``
(``curve_A``, ``map``, ``fit_table``, ...), which the browser tests read back."""
from __future__ import annotations

import numpy as np
from bokeh.models import (
    ColorBar,
    ColumnDataSource,
    DataTable,
    HoverTool,
    LinearColorMapper,
    LogColorMapper,
    Range1d,
    TableColumn,
    Whisker,
)
from bokeh.plotting import figure

from .state import COLOURS, MAP_KINDS, QUANTITIES, SET_NAMES, THETA_MAX, number_text

TOOLS = "pan,wheel_zoom,box_zoom,reset,save"
#: The fit table's columns: the numbers (as the fit gave them) and their text (six significant digits).
FIT_COLUMNS = ("parameter", "value", "low", "high", "value_text", "low_text", "high_text")
#: The curves' end labels: at least this share of the curves' value range apart.
LABEL_GAP = 0.05
PALETTE = "Viridis256"


def axis_label(quantity):
    label, units, _, _ = QUANTITIES[quantity]
    return f"{label} ({units})"


def _figure(title, x_label, y_label, **kw):
    fig = figure(title=title, tools=TOOLS, x_axis_label=x_label, y_axis_label=y_label, **kw)
    fig.toolbar.logo = None
    return fig


def nice_limits(lo, hi, log=False):
    """Colour limits around [lo, hi] rounded outwards to round numbers (half decades on a log
    scale), so that they, and the colour bar, change only when the values cross one."""
    if log:
        return float(10 ** (np.floor(2 * np.log10(lo)) / 2)), float(10 ** (np.ceil(2 * np.log10(hi)) / 2))
    span = hi - lo
    if not span > 0:
        return lo - 0.5, lo + 0.5
    step = 10 ** np.floor(np.log10(span)) / 2
    return float(np.floor(lo / step) * step), float(np.ceil(hi / step) * step)


def spread(y, gap):
    """Label heights near ``y`` at least ``gap`` apart, in the same order: overlapping labels are
    gathered in groups, each centred on the mean of its labels' own heights."""
    y = np.asarray(y, dtype=float)
    order = np.argsort(y, kind="stable")
    groups = []  # [sum of the heights, count], bottom to top
    for v in y[order]:
        groups.append([v, 1])
        while len(groups) > 1:
            (s0, n0), (s1, n1) = groups[-2], groups[-1]
            if (s1 / n1 - (n1 - 1) * gap / 2) - (s0 / n0 + (n0 - 1) * gap / 2) >= gap:
                break
            groups[-2:] = [[s0 + s1, n0 + n1]]
    out = np.empty_like(y)
    out[order] = np.concatenate([s / n + (np.arange(n) - (n - 1) / 2) * gap for s, n in groups]) if groups else []
    return out


def same_axes(data, theta_r, theta_i):
    """Whether a curves' source (``data``: its xs, ys, ti) holds curves at ``theta_i`` over
    ``theta_r`` already, so that new values need send only its ``ys``."""
    ti = data["ti"]
    return (len(ti) == len(theta_i) and all(float(a) == float(b) for a, b in zip(ti, theta_i))
            and all(np.array_equal(x, theta_r) for x in data["xs"]))


class Figures:
    """The page's figures and their sources; ``update_*`` methods take numbers and write them."""

    def __init__(self, width=560, height=360):
        self.curves_fig = _figure("DOP vs theta_r", "theta_r (deg)", axis_label("dop"),
                                  width=width, height=height, name="curves_fig")
        self.curve_src = [ColumnDataSource(dict(xs=[], ys=[], ti=[]), name=f"curve_{n}") for n in SET_NAMES]
        self.label_src = ColumnDataSource(dict(x=[], y=[], text=[], colour=[]), name="curve_labels")
        self.fit_src = ColumnDataSource(dict(xs=[], ys=[]), name="fit_curve")
        self.data_src = ColumnDataSource(dict(x=[], y=[], lo=[], hi=[], ti=[], res=[], res_lo=[], res_hi=[]),
                                         name="data_points")
        for name, colour, src in zip(SET_NAMES, COLOURS, self.curve_src):
            self.curves_fig.multi_line("xs", "ys", source=src, line_color=colour, line_width=2,
                                       legend_label=f"set {name}")
        self.curves_fig.multi_line("xs", "ys", source=self.fit_src, line_color="black", line_dash="dashed",
                                   line_width=2, legend_label="fit")
        self.curves_fig.text("x", "y", "text", source=self.label_src, text_color="colour", text_font_size="9pt",
                             x_offset=3, text_baseline="middle")
        self.curves_fig.add_layout(Whisker(base="x", lower="lo", upper="hi", source=self.data_src,
                                           line_color="black"))
        self.curves_fig.scatter("x", "y", source=self.data_src, color="black", size=5, legend_label="data")
        self.curves_fig.legend.location = "top_left"
        self.curves_fig.legend.background_fill_alpha = 0.7
        self.curves_fig.legend.click_policy = "hide"
        self.curves_fig.x_range = Range1d(0, THETA_MAX + 8)
        # the value axis follows the curves in the browser (Bokeh's DataRange1d); its bounds need not
        # travel back to the server after every update: nothing there reads them
        self.curves_fig.y_range.syncable = False
        self.curves_fig.add_tools(HoverTool(tooltips=[("theta_r", "$x{0.0}"), ("value", "$y{0.0000}")]))

        self.res_fig = _figure("Residuals: data - set shown in the sliders (DOP)", "theta_r (deg)",
                               "DOP residual (1)", width=width, height=200, name="res_fig")
        self.res_fig.add_layout(Whisker(base="x", lower="res_lo", upper="res_hi", source=self.data_src,
                                        line_color="grey"))
        self.res_fig.scatter("x", "res", source=self.data_src, color="black", size=5)
        self.res_fig.line([0, THETA_MAX], [0, 0], line_color="grey", line_dash="dotted")
        self.res_fig.x_range = self.curves_fig.x_range
        self.res_fig.y_range.syncable = False

        self.polar_fig = _figure("Polar: radius = |value|, angle = theta_r from the normal",
                                 "|DOP| sin(theta_r) (1)", "|DOP| cos(theta_r) (1)", width=height + 40, height=height,
                                 match_aspect=True,
                                 name="polar_fig")
        self.polar_src = [ColumnDataSource(dict(xs=[], ys=[]), name=f"polar_{n}") for n in SET_NAMES]
        self.polar_grid = ColumnDataSource(dict(xs=[], ys=[]), name="polar_grid")
        self.polar_text = ColumnDataSource(dict(x=[], y=[], text=[]), name="polar_text")
        self.polar_fig.multi_line("xs", "ys", source=self.polar_grid, line_color="#cccccc")
        self.polar_fig.text("x", "y", "text", source=self.polar_text, text_font_size="8pt", text_color="grey")
        self.polar_fig.x_range, self.polar_fig.y_range = Range1d(-0.1, 1.0), Range1d(-0.1, 1.0)
        for colour, src in zip(COLOURS, self.polar_src):
            self.polar_fig.multi_line("xs", "ys", source=src, line_color=colour, line_width=2)

        self._build_map(width, height)
        self._build_sobol(width)
        self.fit_table_src = ColumnDataSource({k: [] for k in FIT_COLUMNS}, name="fit_table")
        self.fit_table = DataTable(source=self.fit_table_src, width=420, height=170, index_position=None, visible=False,
                                   columns=[TableColumn(field="parameter", title="parameter"),  # the numbers
                                            TableColumn(field="value_text", title="fitted value"),  # as text, to
                                            TableColumn(field="low_text", title="95% low"),  # significant
                                            TableColumn(field="high_text", title="95% high")])  # digits

    def _build_map(self, width, height):
        self.map_fig = _figure("Map", "theta_r (deg)", "theta_i (deg)", frame_width=height, frame_height=height,
                               name="map_fig", match_aspect=True)
        self.map_src = ColumnDataSource(dict(image=[np.zeros((2, 2), np.float32)], x=[0.0], y=[0.0],
                                             dw=[THETA_MAX], dh=[THETA_MAX]), name="map")
        self.linear = LinearColorMapper(palette=PALETTE, nan_color=(0, 0, 0, 0))
        self.log = LogColorMapper(palette=PALETTE, nan_color=(0, 0, 0, 0))
        self.map_image = self.map_fig.image("image", x="x", y="y", dw="dw", dh="dh", source=self.map_src,
                                            color_mapper=self.linear)
        self.colour_bar = ColorBar(color_mapper=self.linear, title="DOP (1)", width=12)
        self.map_fig.add_layout(self.colour_bar, "right")
        self.tick_src = ColumnDataSource(dict(x0=[], y0=[], x1=[], y1=[]), name="aop_ticks")
        self.map_fig.segment("x0", "y0", "x1", "y1", source=self.tick_src, line_color="white", line_width=1.5)
        self.rim_src = ColumnDataSource(dict(x=[], y=[]), name="rim")
        self.map_fig.line("x", "y", source=self.rim_src, line_color="grey")
        self.design_src = ColumnDataSource(dict(x=[], y=[]), name="design_points")
        self.map_fig.scatter("x", "y", source=self.design_src, marker="x", size=9, line_width=2, color="red",
                             legend_label="design: chosen geometries")
        self.map_data_src = ColumnDataSource(dict(x=[], y=[]), name="map_data")
        self.map_fig.scatter("x", "y", source=self.map_data_src, marker="circle", size=5, fill_color=None,
                             line_color="white", legend_label="measurements")
        self.map_fig.legend.location = "bottom_right"
        self.map_fig.legend.background_fill_alpha = 0.6
        self.map_fig.x_range, self.map_fig.y_range = Range1d(0, THETA_MAX), Range1d(0, THETA_MAX)

    def _build_sobol(self, width):
        self.sobol_figs, self.sobol_src = [], []
        self.sobol_mapper = LinearColorMapper(palette="Magma256", low=0, high=1, nan_color=(0, 0, 0, 0))
        for index in ("S1", "ST"):
            fig = _figure(f"Sobol' {index}: press the button", "theta_r (deg)", "theta_i (deg)",
                          width=width // 2 + 40, height=300,
                          name=f"sobol_{index}", match_aspect=True)
            src = ColumnDataSource(dict(image=[np.full((2, 2), np.nan, np.float32)], x=[0.0], y=[0.0], dw=[85.0],
                                        dh=[85.0]), name=f"sobol_{index}_src")
            fig.image("image", x="x", y="y", dw="dw", dh="dh", source=src, color_mapper=self.sobol_mapper)
            fig.x_range, fig.y_range = Range1d(0, 85), Range1d(0, 85)
            self.sobol_figs.append(fig)
            self.sobol_src.append(src)
        self.sobol_figs[1].add_layout(ColorBar(color_mapper=self.sobol_mapper, title="index (1)", width=10), "right")

    # ---- updates ------------------------------------------------------------------------------------

    def sync_legends(self):
        """Legend entries only for what is drawn (the fit, the data, a design, the measurements)."""
        items = self.curves_fig.legend[0].items
        for item, src, key in ((items[-2], self.fit_src, "xs"), (items[-1], self.data_src, "x")):
            item.visible = bool(len(src.data[key]))
        for item, src in zip(self.map_fig.legend[0].items, (self.design_src, self.map_data_src)):
            item.visible = bool(len(src.data["x"]))

    def update_curves(self, theta_r, theta_i, values, quantity, phi=180.0, source=""):
        """``values``: set index -> (len(theta_i), len(theta_r)) at azimuth ``phi``; the others
        are emptied; ``source``: the incident state in words, for the title (:func:`.state.source_text`)."""
        self.curves_fig.yaxis.axis_label = axis_label(quantity)
        self.curves_fig.title.text = f"{QUANTITIES[quantity][0]} vs theta_r at phi = {phi:g}°" + (
            " (in plane)" if phi == 180 else "") + (source or ", one curve per theta_i")  # the title's room
        label, units = QUANTITIES[quantity][:2]
        self.polar_fig.xaxis.axis_label = f"|{label}| sin(theta_r) ({units})"
        self.polar_fig.yaxis.axis_label = f"|{label}| cos(theta_r) ({units})"
        labels = dict(x=[], y=[], text=[], colour=[])
        for i, src in enumerate(self.curve_src):
            v = values.get(i)
            if v is None:
                if len(src.data["ys"]):  # an empty one stays as it is: nothing to send
                    src.data = dict(xs=[], ys=[], ti=[])
                    self.polar_src[i].data = dict(xs=[], ys=[])
                continue
            if same_axes(src.data, theta_r, theta_i):  # only the values change: send only them
                src.data["ys"] = list(v)
            else:
                src.data = dict(xs=[theta_r] * len(theta_i), ys=list(v), ti=list(theta_i))
            rad = np.radians(theta_r)
            self.polar_src[i].data = dict(xs=[np.abs(row) * np.sin(rad) for row in v],
                                          ys=[np.abs(row) * np.cos(rad) for row in v])
            for t, row in zip(theta_i, v):
                finite = np.flatnonzero(np.isfinite(row))  # at the curve's last drawn point
                labels["x"].append(theta_r[-1])
                labels["y"].append(float(row[finite[-1]]) if finite.size else 0.0)
                labels["text"].append(f"{SET_NAMES[i]} {t:g}°")
                labels["colour"].append(COLOURS[i])
        finite = [row[np.isfinite(row)] for v in values.values() for row in v]
        finite = np.concatenate(finite) if finite else np.zeros(1)
        span = float(finite.max() - finite.min()) if finite.size else 0.0
        labels["y"] = list(spread(labels["y"], LABEL_GAP * (span if span > 0 else 1.0)))
        self.label_src.data = labels
        for i, item in enumerate(self.curves_fig.legend[0].items[:len(SET_NAMES)]):
            item.visible = i in values
        self._polar_grid(values)

    def _polar_grid(self, values):
        finite = [np.nanmax(np.abs(v)) for v in values.values() if np.isfinite(v).any()]
        top = max(finite) if finite else 1.0
        top = top if top > 0 else 1.0
        step = 10 ** np.floor(np.log10(top / 2))
        rings = np.arange(step, top * 1.05 + step, step)[:8]
        if getattr(self, "_rings", None) == tuple(rings):
            return  # the same grid: nothing to send
        self._rings = tuple(rings)
        a = np.radians(np.linspace(0, 90, 46))
        spokes = np.radians([0, 30, 60, 90])
        xs = [r * np.sin(a) for r in rings] + [np.array([0, rings[-1] * np.sin(d)]) for d in spokes]
        ys = [r * np.cos(a) for r in rings] + [np.array([0, rings[-1] * np.cos(d)]) for d in spokes]
        text = dict(x=[float(r) * 0.02 for r in rings], y=[float(r) for r in rings], text=[f"{r:.3g}" for r in rings])
        for d in (30, 60, 90):
            text["x"].append(float(rings[-1] * np.sin(np.radians(d))))
            text["y"].append(float(rings[-1] * np.cos(np.radians(d))))
            text["text"].append(f"theta_r {d}°")
        self.polar_grid.data = dict(xs=xs, ys=ys)
        self.polar_text.data = text
        edge = float(rings[-1])
        self.polar_fig.x_range.start, self.polar_fig.x_range.end = -0.15 * edge, 1.45 * edge
        self.polar_fig.y_range.start, self.polar_fig.y_range.end = -0.15 * edge, 1.1 * edge

    def update_data(self, points, theta_i, phi, res, quantity="dop", title=""):
        """The measured points of the view (``points``: :func:`.state.view_points`'s, or None) at the
        curves' incidences and azimuth, with error bars and residuals (``res``) in units of
        ``quantity``; ``title``: the residuals' title (default: data - the set shown)."""
        label, units = QUANTITIES[quantity][:2]
        self.res_fig.yaxis.axis_label = f"{label} residual ({units})"
        self.res_fig.title.text = title or f"Residuals: data - set shown in the sliders ({label})"
        if points is None:
            if not len(self.data_src.data["x"]) and not len(self.map_data_src.data["x"]):
                return
            self.data_src.data = dict(x=[], y=[], lo=[], hi=[], ti=[], res=[], res_lo=[], res_hi=[])
            self.map_data_src.data = dict(x=[], y=[])
            return
        value = points.value
        std = points.std if points.std is not None else np.zeros_like(value)
        keep = np.isin(np.round(points.theta_i, 6), np.round(theta_i, 6)) & np.isclose(points.phi, phi)
        self.data_src.data = dict(x=points.theta_r[keep], y=value[keep], lo=(value - std)[keep],
                                  hi=(value + std)[keep], ti=points.theta_i[keep], res=res[keep],
                                  res_lo=(res - std)[keep], res_hi=(res + std)[keep])

    def update_map(self, kind, a, b, v, quantity, log=False, set_name="A"):
        """The image of the map: ``kind`` "incidence" (a: theta_i rows, b: theta_r columns) or
        "hemisphere" (a: x, b: y in [-1, 1])."""
        img = np.asarray(v, dtype=np.float32)
        h = (float(b[-1]) - float(b[0])) / (img.shape[1] - 1)  # the nodes are the cells' centres
        if kind == MAP_KINDS[0]:
            self._map_data(img, -h / 2, THETA_MAX + h)
            self.map_fig.title.text = f"Set {set_name} over (theta_i, theta_r) at the curves' phi"
            self.map_fig.xaxis.axis_label, self.map_fig.yaxis.axis_label = "theta_r (deg)", "theta_i (deg)"
            lim = (0.0, THETA_MAX)
            if len(self.rim_src.data["x"]):
                self.rim_src.data = dict(x=[], y=[])
        else:
            self._map_data(img, -1.0 - h / 2, 2.0 + h)
            self.map_fig.title.text = f"Set {set_name}: hemisphere from above at the first theta_i (source left)"
            self.map_fig.xaxis.axis_label = "x = (theta_r / 90°) cos(phi_r) (1)"
            self.map_fig.yaxis.axis_label = "y = (theta_r / 90°) sin(phi_r) (1)"
            lim = (-1.0, 1.0)
            if not len(self.rim_src.data["x"]):
                t = np.linspace(0, 2 * np.pi, 181)
                self.rim_src.data = dict(x=np.cos(t) * THETA_MAX / 90, y=np.sin(t) * THETA_MAX / 90)
        for rng in (self.map_fig.x_range, self.map_fig.y_range):
            rng.start, rng.end = lim
        finite = img[np.isfinite(img)]
        mapper = self.log if log and finite.size and finite.max() > 0 else self.linear
        if finite.size:
            hi = float(finite.max())
            lo = max(float(finite[finite > 0].min()) if (finite > 0).any() else 1e-12, hi * 1e-5) if mapper is \
                self.log else float(finite.min())
            low, high = nice_limits(lo, hi, mapper is self.log)
            if (mapper.low, mapper.high) != (low, high):  # the colour bar moves only when a limit does
                mapper.low, mapper.high = low, high
        self.map_image.glyph.color_mapper = mapper
        self.colour_bar.color_mapper = mapper
        self.colour_bar.title = axis_label(quantity) + (" (log scale)" if mapper is self.log else "")

    def _map_data(self, img, corner, width):
        """The map's image, its lower left corner at (corner, corner) and ``width`` wide and high;
        only the image is sent where the rest stays."""
        d = self.map_src.data
        if (list(d["x"]), list(d["y"]), list(d["dw"]), list(d["dh"])) == ([corner], [corner], [width], [width]) \
                and d["image"][0].shape == img.shape:
            d["image"] = [img]
        else:
            self.map_src.data = dict(image=[img], x=[corner], y=[corner], dw=[width], dh=[width])

    def update_ticks(self, ticks):
        if ticks is None and not len(self.tick_src.data["x0"]):
            return  # nothing drawn, nothing to draw: no message
        x0, y0, x1, y1 = ticks if ticks is not None else ([], [], [], [])
        self.tick_src.data = dict(x0=x0, y0=y0, x1=x1, y1=y1)

    def update_design(self, theta_i, theta_r):
        self.design_src.data = dict(x=list(theta_r), y=list(theta_i))
        self.sync_legends()

    def update_sobol(self, ds, parameter):
        """The S1 and ST maps of ``parameter`` from ``pbrdf_cl.sobol``'s Dataset (theta_i x theta_r)."""
        ti, tr = ds["theta_i"].values, ds["theta_r"].values
        for index, fig, src in zip(("S1", "ST"), self.sobol_figs, self.sobol_src):
            v = ds[index].sel(parameter=parameter).transpose("theta_i", "theta_r").values.astype(np.float32)
            hx, hy = (tr[-1] - tr[0]) / (tr.size - 1), (ti[-1] - ti[0]) / (ti.size - 1)  # nodes: cell centres
            src.data = dict(image=[v], x=[float(tr[0] - hx / 2)], y=[float(ti[0] - hy / 2)],
                            dw=[float(tr[-1] - tr[0] + hx)], dh=[float(ti[-1] - ti[0] + hy)])
            fig.title.text = f"Sobol' {index} of {parameter} ({'first order' if index == 'S1' else 'total'})"
            fig.x_range.start, fig.x_range.end = float(tr[0]), float(tr[-1])
            fig.y_range.start, fig.y_range.end = float(ti[0]), float(ti[-1])

    def update_fit(self, result, theta_r, theta_i, fitted):
        """The fitted values with their intervals (``result``: a FitResult or None) and the fitted
        curves (len(theta_i), len(theta_r)) dashed."""
        self.fit_table.visible = result is not None  # no empty table (and band) before a fit
        if result is None:
            if len(self.fit_table_src.data["parameter"]) or len(self.fit_src.data["xs"]):
                self.fit_table_src.data = {k: [] for k in FIT_COLUMNS}
                self.fit_src.data = dict(xs=[], ys=[])
            return
        names = list(result.free)
        table = dict(parameter=names, value=[float(result.x[p]) for p in names],
                     low=[float(result.ci95[p][0]) for p in names], high=[float(result.ci95[p][1]) for p in names])
        for key in ("value", "low", "high"):
            table[f"{key}_text"] = [number_text(v) for v in table[key]]
        self.fit_table_src.data = table
        self.fit_src.data = dict(xs=[theta_r] * len(theta_i), ys=list(fitted)) if fitted is not None else \
            dict(xs=[], ys=[])
