"""The explorer's page (Panel): the controls, the views of :mod:`.figures`, the measurements and
the fit, the Sobol' map and the design on demand, the exports and the state in the URL.

One :class:`Explorer` per browser session; all of them share the server's engine (one device
context, queue and compiled programs, kept alive) for the live views, and a second engine on the
same device for the background jobs (fit, Sobol' map, design), which run in a thread so that the
sliders stay live while they run."""
from __future__ import annotations

import asyncio
import html
import io
import os
import tempfile
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlencode

import numpy as np
import panel as pn
from panel.io import hold

from ..analysis.designs import design
from ..analysis.sensitivity import sobol
from ..compute import measured as ms
from ..compute.pointwise import MODELS, check_degrees
from ..device.engine import get_default_engine
from ..errors import UnitsWarning
from ..fitting.sample.inversion import fit
from ..io.measurements import read_csv
from ..io.params import NAMES, params_text
from ..model import inputs
from ..model.reference import SHADOWING
from ..plots.explorer import plot_view
from . import state as st
from .entries import NumberEntry
from .figures import Figures
from .upload import MAX_UPLOAD, Upload, upload_refusal

#: Background jobs (fit, Sobol', design) of every session: one at a time per server, in a thread.
POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pbrdf-explore")
_BACKGROUND = {}
#: How long the views stay still before the URL and the timing line follow them (ms).
SETTLE_MS = 250
#: The Sobol' map's choices of N (base samples per node; the middle one is the default).
SOBOL_N = (64, 256, 1024)
#: The design's defaults: DOP noise (std) and number of measurements (both editable on the page).
DESIGN_NOISE, DESIGN_COUNT = 0.005, 30
#: The design's instruments (explore.instruments.REGISTRY): the geometries are chosen for the one
#: picked on the page, and all of them are compared at those and at the paper's geometries.
DESIGN_INSTRUMENTS = {"DOP, unpolarised source": "dop", "camera s1, s2, source at 45 deg": "camera45",
                      "camera s1, s2, 4 linear + circular sources": "camera4",
                      "Mueller polarimeter (15 m_ij)": "mueller"}


def design_table(r):
    """A design's instruments compared (:func:`pbrdf_cl.design`'s ``instrument_comparisons``): the
    predicted 95% widths of n and k at the chosen and at the paper's geometries, as an HTML table."""
    comp = r.instrument_comparisons
    head = "".join(f"<th>{p}, {s}</th>" for s in ("chosen", "paper") for p in ("n", "k"))
    rows = "".join(f"<tr><td>{html.escape(name)}</td>" + "".join(
        f"<td>{'undet.' if p in comp[s][name]['undetermined'] else format(comp[s][name]['widths'][p], '.3g')}</td>"
        for s in ("chosen", "reference") for p in ("n", "k")) + "</tr>" for name in comp["chosen"])
    return (f'<table class="design-instruments" style="font-size:90%"><tr><th>instrument</th>{head}</tr>{rows}'
            "</table>")


def background_engine(engine):
    """An engine on the same device as ``engine`` for the background thread (its own queue), made
    once per device; the numpy backend is shared as it is."""
    device = getattr(engine, "device", None)
    if device is None:
        return engine
    key = id(engine)
    if key not in _BACKGROUND:
        _BACKGROUND[key] = type(engine)(device)
    return _BACKGROUND[key]


def quantity_groups():
    """The quantity menu's groups: what depends on the source's state, and what does not."""
    under = {st.QUANTITIES[k][0]: k for k in st.UNDER_SOURCE}
    other = {v[0]: k for k, v in st.QUANTITIES.items() if k not in st.UNDER_SOURCE}
    return {"under the source": under, "of any source": other}


def one_line(exc):
    """An error as the CLI prints it: one line, ``error: ...``."""
    return "error: " + str(exc).splitlines()[0] if str(exc) else f"error: {type(exc).__name__}"


class Explorer:
    """One page of the explorer.

    Parameters
    ----------
    engine : pbrdf_cl.Engine, optional
        The engine of the live views (default: the default engine).
    data : str or path, optional
        A measurement CSV to load at the start.
    query : dict, optional
        The URL's query (name -> str), as :func:`pbrdf_cl.app.state.to_query` writes it.
    """

    def __init__(self, engine=None, data=None, query=None):
        self.engine = engine if engine is not None else get_default_engine()
        self.meas, self.fit_result, self.sobol_ds, self.design_result = None, None, None, None
        self.last_ms, self._quiet, self._generation, self._pending = float("nan"), False, 0, False
        self.refused = {}  # the URL's refused keys -> their lines: those keys keep their defaults
        self.state = st.from_query(query, self.refused) if query else st.State()
        self.figs = Figures()
        self.doc = pn.state.curdoc  # the session's document: background results are drawn under its lock
        self.closed = False
        if self.doc is not None and self.doc.session_context is not None:  # served: released with the session
            st.PAGES.add(self.doc.session_context.id)
            pn.state.on_session_destroyed(self._session_destroyed)
        self._widgets()
        self.layout = self._layout()
        self.refresh()
        if data:
            self.load_path(data, str(data))
        if self.refused:
            self.say(one_line("; ".join(self.refused.values())), error=True)
            if self.doc is not None and self.doc.session_context is not None:
                kept = {k: v for k, v in query.items() if k not in self.refused}
                pn.state.onload(lambda: self._set_url(urlencode(kept, safe=",")))

    # ---- widgets ----------------------------------------------------------------------------------

    def _widgets(self):
        s, p = self.state.settings, self.state.sets[self.state.active]
        self.sliders = {}
        for name in NAMES:
            w = NumberEntry(name, name, st.LIMITS[name], p[name], self._complain, step=st.STEPS[name], slider=True)
            w.param.watch(lambda event, name=name: self._on_slider(name, event.new), "value")
            self.sliders[name] = w
        self.reset = pn.widgets.Button(label="Reset to the paper's steel", color="light", width=260)
        self.reset.on_click(self._on_reset)
        self.active = pn.widgets.RadioButtonGroup(label="edit set", options=list(st.SET_NAMES),
                                                  value=st.SET_NAMES[self.state.active], color="primary")
        self.shown = pn.widgets.CheckButtonGroup(label="show", options=list(st.SET_NAMES), color="success",
                                                 value=[n for n, on in zip(st.SET_NAMES, self.state.shown) if on])
        self.solo = pn.widgets.RadioButtonGroup(label="solo", options=["-"] + list(st.SET_NAMES), color="warning",
                                                value="-" if self.state.solo is None else st.SET_NAMES[self.state.solo])
        self.copy_to = pn.widgets.Button(label="Copy this set to the next hidden one", width=260)
        self.copy_to.on_click(self._on_copy)
        self.quantity = pn.widgets.Select(label="quantity", groups=quantity_groups(), value=s.quantity, width=125)
        self.model = pn.widgets.Select(label="model", options=list(MODELS), value=s.model, width=125)
        self.shadowing = pn.widgets.Select(label="shadowing", options=sorted(SHADOWING), value=s.shadowing, width=125)
        self.dtype = pn.widgets.Select(label="dtype", options=["float64", "float32"], value=s.dtype, width=125)
        self.theta_i = pn.widgets.TextInput(label="theta_i of the curves (deg)", value=",".join(f"{t:g}" for t in
                                                                                             s.theta_i), width=260)
        self.phi = NumberEntry("phi", "phi (deg; 180 = in plane)", st.PHI_LIMITS, s.phi, self._complain, step=0.5,
                               slider=True, units="degrees")
        self.map_kind = pn.widgets.RadioButtonGroup(label="map", options={"theta_i x theta_r": "incidence",
                                                                         "hemisphere": "hemisphere"},
                                                    value=s.map_kind)
        self.incident = pn.widgets.Select(label="source: incident light (s1, s2, s3)", width=260,
                                          options=st.incident_options([s.incident]), value=s.incident)
        for w in (self.active, self.shown, self.solo, self.quantity, self.model, self.shadowing, self.dtype,
                  self.theta_i, self.phi, self.map_kind, self.incident):
            w.param.watch(self._on_setting, "value")
        self.status = pn.pane.HTML("", width=900, height=24, name="status")
        self.timing = pn.pane.HTML("", name="timing", width=700, height=24)
        self._data_widgets()
        self._export_widgets()

    def _data_widgets(self):
        self.upload = Upload(self._refuse_upload, accept=".csv,.txt,.tsv", limit=MAX_UPLOAD, width=260, height=30)
        self.upload.param.watch(self._on_upload, ["value", "filename"])  # an empty file changes only the name
        self.data_info = pn.pane.HTML("no measurements loaded", width=420)
        self.fit_button = pn.widgets.Button(label="Fit", color="primary", width=120, disabled=True)
        self.fit_button.on_click(self._on_fit)
        self.use_fit = pn.widgets.Button(label="Move the sliders to the fit", width=220, disabled=True)
        self.use_fit.on_click(self._on_use_fit)
        self.progress = pn.indicators.Progress(active=False, value=0, width=200, visible=False)
        self.fit_notes = pn.pane.HTML("", width=560, name="fit_notes")
        self.sobol_button = pn.widgets.Button(label="Sobol' map around this set", width=220)
        self.sobol_button.on_click(self._on_sobol)
        self.sobol_param = pn.widgets.Select(label="parameter", options=list(inputs.FITTED), value="n",
                                             width=120)
        self.sobol_param.param.watch(lambda e: self._draw_sobol(), "value")
        self.sobol_share = NumberEntry("the box's share", "box: +- share of each range", (0.01, 0.5), 0.1,
                                       self._complain_job, step=0.05, width=200)
        self.sobol_n = pn.widgets.Select(label="N (base samples)", options=list(SOBOL_N), value=SOBOL_N[1], width=120)
        self.design_button = pn.widgets.Button(label="Design geometries for n, k", width=220)
        self.design_button.on_click(self._on_design)
        self.design_noise = NumberEntry("DOP noise", "DOP noise (std)", (1e-4, 0.1), DESIGN_NOISE, self._complain_job,
                                        step=0.001, width=120)
        self.design_count = NumberEntry("measurements", "measurements", (5, 200), DESIGN_COUNT, self._complain_job,
                                        step=5, integer=True, width=110)
        self.design_instrument = pn.widgets.Select(label="design for the instrument (all compared)",
                                                   options=DESIGN_INSTRUMENTS, value="dop", width=300)
        self.jobs = pn.pane.HTML("", width=560, name="jobs")

    def _export_widgets(self):
        def download(label, filename, make):
            return pn.widgets.FileDownload(callback=make, filename=filename, label=label, color="light",
                                           width=130)
        self.exports = [download("view as PNG", "pbrdf-view.png", self._png),
                        download("view as CSV", "pbrdf-view.csv", self._csv),
                        download("view as NetCDF", "pbrdf-view.nc", self._netcdf),
                        download("set as JSON", "pbrdf-params.json", lambda: self._params("json")),
                        download("set as TOML", "pbrdf-params.toml", lambda: self._params("toml"))]

    def _layout(self):
        f = self.figs
        controls = pn.Column(
            pn.pane.HTML("<b>Parameter sets</b> (sliders edit the chosen one)"),
            pn.Row(pn.pane.HTML("edit", width=40), self.active), pn.Row(pn.pane.HTML("show", width=40), self.shown),
            pn.Row(pn.pane.HTML("solo", width=40), self.solo), self.copy_to,
            *self.sliders.values(), self.reset,
            pn.Row(self.quantity, self.model), pn.Row(self.shadowing, self.dtype), self.incident,
            self.theta_i, self.phi, pn.pane.HTML("<b>Map</b>"), self.map_kind, width=290)
        data = pn.Column(pn.pane.HTML("<b>Measurements</b> (CSV: theta_i, theta_r, and dop or what a polarimeter "
                                      "measures: aop, s0..s3, m00..m33; optionally phi, &lt;name&gt;_std, "
                                      "in_s1..in_s3: the source's state)", width=420),
                         self.upload, self.data_info, pn.Row(self.fit_button, self.progress), self.use_fit,
                         pn.pane.Bokeh(f.fit_table), self.fit_notes)
        jobs = pn.Column(pn.pane.HTML("<b>On demand</b>"), pn.Row(self.sobol_button, self.sobol_share),
                         pn.Row(self.sobol_param, self.sobol_n),
                         pn.Row(self.design_button, self.design_noise, self.design_count), self.design_instrument,
                         self.jobs,
                         pn.pane.HTML("<b>Export</b> (one plot as PNG: its toolbar's save tool)"),
                         pn.Row(*self.exports[:3]), pn.Row(*self.exports[3:]))
        # two columns under the curves, each as tall as its own content: no empty band above the Sobol' maps
        views = pn.Column(self.status, pn.Row(pn.pane.Bokeh(f.curves_fig), pn.pane.Bokeh(f.polar_fig)),
                          pn.Row(pn.Column(pn.pane.Bokeh(f.res_fig), data, jobs),
                                 pn.Column(pn.pane.Bokeh(f.map_fig),
                                           pn.Row(pn.pane.Bokeh(f.sobol_figs[0]), pn.pane.Bokeh(f.sobol_figs[1])))),
                          self.timing)
        return pn.Row(controls, views, name="pbrdf-cl explore")

    # ---- the live views ---------------------------------------------------------------------------

    def say(self, text, error=False):
        colour = "#b00020" if error else "#333333"
        self.status.object = f'<span style="color:{colour}">{html.escape(text, quote=False)}</span>' if text else ""

    def _complain(self, text):
        """A refused entry (:class:`.entries.NumberEntry`): its one line in the status line."""
        self.say(one_line(text), error=True)

    def _complain_job(self, text):
        """A refused entry of the jobs (Sobol' map, design): its one line beside them."""
        self.jobs.object = f'<span style="color:#b00020">{html.escape(one_line(text), quote=False)}</span>'

    def refresh(self):
        """Recompute and redraw every live view from the state, as one message to the browser.  The
        URL and the timing line follow once the views have been still for SETTLE_MS (each costs
        the browser a layout or a history entry: not while a slider moves)."""
        t0 = time.perf_counter()
        with hold(self.doc):
            ok = self._redraw()
        if ok:
            self.last_ms = 1e3 * (time.perf_counter() - t0)
            self._generation += 1
            if self.doc is not None and self.doc.session_context is not None:
                generation = self._generation
                self.doc.add_timeout_callback(lambda: self._settled(generation), SETTLE_MS)
            else:
                self._settled(self._generation)

    def _settled(self, generation):
        if generation != self._generation:
            return  # another update came since: wait for its own
        self.timing.object = f"<small>views updated in {self.last_ms:.0f} ms on {self.engine!r}</small>"
        self._sync_url()

    def _redraw(self):
        s, f = self.state.settings, self.figs
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the page shows errors; warnings go to the server's log
                tr = st.theta_r_axis()
                values = st.curves(self.engine, self.state, tr)
                f.update_curves(tr, s.theta_i, values, s.quantity, s.phi, st.source_text(s))
                shown = "dop" if s.quantity == "aop" else s.quantity  # AoP: ticks over the DOP
                if s.map_kind == "incidence":
                    a, b, v = st.incidence_map(self.engine, self.state, shown)
                else:
                    a, b, v = st.hemisphere_map(self.engine, self.state, shown)
                f.update_map(s.map_kind, a, b, v, shown, log=shown in ("brdf", "s0"),
                             set_name=st.SET_NAMES[self.state.active])
                f.update_ticks(st.aop_ticks(self.engine, self.state) if s.quantity == "aop" else None)
                self._draw_data()
                self._draw_fit()
                f.sync_legends()
        except (ValueError, FloatingPointError) as exc:
            self.say(one_line(exc), error=True)
            return False
        self.say(st.curves_note(self.state, values))  # clears an error line that no longer holds
        return True

    def _draw_data(self):
        f, s = self.figs, self.state.settings
        r = self.design_result  # the design's geometries are (theta_i, theta_r): on that map only
        design = ([], []) if r is None or s.map_kind != "incidence" else (list(r.theta_i), list(r.theta_r))
        if len(f.design_src.data["x"]) != len(design[0]):
            f.update_design(*design)
        if self.meas is None:
            f.update_data(None, s.theta_i, s.phi, None, s.quantity)
            return
        points = st.view_points(self.meas, s)
        _, res = st.residuals(self.engine, self.state, self.meas, points)
        f.update_data(points, s.theta_i, s.phi, res, s.quantity, self._residual_title(points))
        if s.map_kind == "incidence":
            f.map_data_src.data = dict(x=self.meas.theta_r, y=self.meas.theta_i)
        else:
            f.map_data_src.data = dict(x=[], y=[])

    def _residual_title(self, points):
        """The residuals' title: what they are of, or why the view shows no measurements."""
        s = self.state.settings
        label = st.QUANTITIES[s.quantity][0]
        if points.rows.any():
            return f"Residuals: data - set {st.SET_NAMES[self.state.active]} ({label}{st.source_text(s)})"
        held = ", ".join(dict.fromkeys(st.QUANTITIES[st.view_of(g[0], g[1])][0] for g in ms.groups(self.meas)))
        if st.measures(self.meas, s.quantity):
            return f"No {label} measured under this source: choose one of the data's states"
        return f"No {label} measured: the data hold {held}"

    def _draw_fit(self):
        r, s = self.fit_result, self.state.settings
        if r is None:
            self.figs.update_fit(None, None, None, None)
            return
        tr = st.theta_r_axis()
        fitted = None
        if self.meas is not None and st.measures(self.meas, s.quantity):  # in the views of what it fitted
            fitted = st.fit_curves(self.engine, self.state, r, tr)
        self.figs.update_fit(r, tr, s.theta_i, fitted)

    def _sync_url(self):
        self._set_url(st.to_query(self.state))

    def _set_url(self, query):
        loc = pn.state.location
        if loc is not None:
            loc.search = "?" + query if query else ""

    # ---- callbacks --------------------------------------------------------------------------------

    def _on_slider(self, name, value):
        if self._quiet:
            return
        self.state.sets[self.state.active][name] = float(value)
        if self.doc is None or self.doc.session_context is None:
            self.refresh()
        elif not self._pending:  # served: redrawn on the next tick, once for every move until then
            self._pending = True
            self.doc.add_next_tick_callback(self._refresh_pending)

    def _refresh_pending(self):
        """The views after the slider moves since the last redraw.  Run as a callback of its own,
        after the server has answered the slider's message: its reply has usually been written
        by then, and the views go out at once (built while the reply is being written, Panel
        finds the connection busy and sends them 10 ms later or more, after the browser's next
        message)."""
        self._pending = False
        if not self.closed:
            self.refresh()

    def _set_sliders(self, values):
        self._quiet = True
        try:
            for name, w in self.sliders.items():
                w.value = float(values[name])
        finally:
            self._quiet = False

    def _on_reset(self, event):
        self.state.sets[self.state.active] = dict(st.STEEL)
        self._set_sliders(st.STEEL)
        self.refresh()

    def _on_copy(self, event):
        hidden = [i for i, on in enumerate(self.state.shown) if not on]
        if not hidden:
            self.say("every set is shown already; hide one to copy into it", error=True)
            return
        self.state.sets[hidden[0]] = dict(self.state.sets[self.state.active])
        self._quiet = True
        self.shown.value = self.shown.value + [st.SET_NAMES[hidden[0]]]
        self.active.value = st.SET_NAMES[hidden[0]]
        self._quiet = False
        self._read_settings()

    def _on_setting(self, event):
        if not self._quiet:
            self._read_settings()

    def _read_settings(self):
        state, s = self.state, self.state.settings
        try:
            s.theta_i = st.parse_theta_i(self.theta_i.value)
        except ValueError as exc:  # one line, and the entry back to the angles in use
            in_use = ",".join(f"{t:g}" for t in s.theta_i)
            self.say(one_line(f"{exc}; it stays {in_use}"), error=True)
            self._quiet = True
            try:
                self.theta_i.value = in_use
            finally:
                self._quiet = False
            return
        s.quantity, s.model, s.shadowing, s.dtype = (self.quantity.value, self.model.value, self.shadowing.value,
                                                     self.dtype.value)
        s.phi, s.map_kind, s.incident = float(self.phi.value), self.map_kind.value, tuple(self.incident.value)
        active = st.SET_NAMES.index(self.active.value)
        state.shown = [n in self.shown.value for n in st.SET_NAMES]
        state.solo = None if self.solo.value == "-" else st.SET_NAMES.index(self.solo.value)
        if active != state.active:
            state.active = active
            self._set_sliders(state.sets[active])
        self.refresh()

    # ---- measurements and the fit -----------------------------------------------------------------

    def load_path(self, path, shown_name):
        """Read a measurement CSV; a bad file is one line in the page, as ``pbrdf-cl fit`` says it."""
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                meas = read_csv(path)
                meas.source = shown_name  # the fit's messages name the user's file, not a temporary copy
                check_degrees(meas.theta_i, meas.theta_r, f"{shown_name}: ")  # radians: said now, not at Fit
        except (OSError, ValueError) as exc:
            text = str(exc).replace(str(path), shown_name)
            self.data_info.object = f'<span style="color:#b00020">{html.escape(one_line(text), quote=False)}</span>'
            self.say(one_line(text), error=True)
            return False
        self.meas, self.fit_result = meas, None
        said = [str(w.message).replace(str(path), shown_name) for w in caught]
        notes = "".join(f'<br><small style="color:#a05a00">warning: {html.escape(text, quote=False)}</small>'
                        for text in said)
        self.data_info.object = (f"{html.escape(shown_name, quote=False)}: {self._holds(meas)}, theta_i "
                                 f"{', '.join(f'{t:g}' for t in np.unique(meas.theta_i))}{notes}")
        self.fit_button.disabled = False
        self.use_fit.disabled = True
        self.fit_notes.object = ""
        if meas.dop_std is not None and np.isfinite(meas.dop_std).any():  # the data's noise: the design's default
            self.design_noise.value = float(np.round(np.nanmedian(meas.dop_std), 6))
        self._show_data_view(meas)
        units = [text for text, w in zip(said, caught) if issubclass(w.category, UnitsWarning)]
        if units:  # radians: one red line, as the other inputs' refusals
            self.say("warning: " + units[0].splitlines()[0], error=True)
        return True

    @staticmethod
    def _holds(meas):
        """What a data set holds, in words: DOP points, or its quantities and incident states."""
        if not meas.polarimetric:
            return f"{meas.theta_i.size} measurements"
        quantities = ", ".join(dict.fromkeys(st.QUANTITIES[st.view_of(g[0], g[1])][0] for g in ms.groups(meas)))
        states = "; ".join(ms.state_text(v) for v in st.data_states(meas))
        return f"{meas.theta_i.size} rows of {quantities} under {states}"

    def _show_data_view(self, meas):
        """Offer the data's incident states, and turn to a view that shows the data's points where the
        one shown has none (the quantity they measure, at their first state); then redraw."""
        s = self.state.settings
        self._quiet = True
        try:
            self.incident.options = st.incident_options([s.incident, *st.data_states(meas)])
            if not st.view_points(meas, s).rows.any():
                s.quantity, s.incident = st.first_view(meas)
                self.quantity.value, self.incident.value = s.quantity, s.incident
        finally:
            self._quiet = False
        self.refresh()

    def _refuse_upload(self, name, size):
        """A file above the upload limit (not sent by the browser): one line, as a bad file's."""
        line = one_line(upload_refusal(os.path.basename(name), size, self.upload.limit))
        self.data_info.object = f'<span style="color:#b00020">{html.escape(line, quote=False)}</span>'
        self.say(line, error=True)

    def _on_upload(self, *events):
        if self.upload.filename is None:
            return
        name = os.path.basename(self.upload.filename)
        with tempfile.TemporaryDirectory() as folder:
            path = os.path.join(folder, name)
            with open(path, "wb") as fh:
                fh.write(self.upload.value or b"")  # Panel gives None for an empty file: read_csv says so
            self.load_path(path, name)

    def _later(self, fn, *args):
        """Call ``fn(*args)`` with the document's lock (next tick) in a served session, else now:
        the figures' Bokeh sources may change only under it."""
        doc = self.doc
        if self.closed:  # the page has closed: nothing to draw into
            return
        if doc is not None and doc.session_context is not None:
            doc.add_next_tick_callback(lambda: fn(*args))
        else:
            fn(*args)

    def _session_destroyed(self, session_context):
        st.PAGES.discard(session_context.id)
        self.close()

    def close(self):
        """Let go of what the page holds (its data, results and upload): its session has ended.  A
        background job still running finishes, and its result is dropped."""
        self.closed = True
        self.meas, self.fit_result, self.sobol_ds, self.design_result = None, None, None, None
        self.upload.param.update(filename=None, value=None)

    async def _background(self, button, label, job, *args):
        """Run ``job(*args)`` in the background thread with the progress bar shown; returns its
        result, or None after showing its error in one line."""
        button.disabled = True
        self.progress.visible, self.progress.active = True, True
        self.jobs.object = f"{label}: running ..."
        t0 = time.perf_counter()
        try:
            result = await asyncio.get_running_loop().run_in_executor(POOL, job, *args)
        except (ValueError, FloatingPointError, RuntimeError) as exc:
            self.jobs.object = f'<span style="color:#b00020">{label}: {html.escape(one_line(exc), quote=False)}</span>'
            return None
        finally:
            button.disabled = False
            self.progress.visible, self.progress.active = False, False
        self.jobs.object = f"{label}: done in {time.perf_counter() - t0:.1f} s"
        return result

    # The jobs leave the warning filters alone (catch_warnings is not thread-safe): their warnings
    # go to the server's log.
    def _fit_job(self, meas, model, shadowing):
        return fit(meas, model=model, shadowing=shadowing, engine=background_engine(self.engine))

    async def _on_fit(self, event):
        if self.meas is None:
            return
        s = self.state.settings
        r = await self._background(self.fit_button, "fit", self._fit_job, self.meas, s.model, s.shadowing)
        if r is not None:
            self._later(self._show_fit, r)

    def _show_fit(self, r):
        self.fit_result = r
        self.use_fit.disabled = False
        notes = "".join(f"<li>{html.escape(n, quote=False)}</li>" for n in r.notes)
        bad = "" if r.fits_data else " <b>(the model does not describe these data)</b>"
        observed = r.get("observed", "DOP")
        of = "" if observed == "DOP" else f" ({html.escape(observed, quote=False)})"
        head = f"{r.model}, shadowing {r.shadowing}: SSE {r.sse:.4g}{of}{bad}"
        self.fit_notes.object = f"{head}<ul>{notes}</ul>"
        self.refresh()

    def _on_use_fit(self, event):
        if self.fit_result is None:
            return
        fitted = st.fit_params(self.fit_result)  # the specular model's held values too
        values = {p: float(np.clip(fitted[p], *st.LIMITS[p])) for p in NAMES}
        self.state.sets[self.state.active] = values
        self._set_sliders(values)
        self.refresh()

    # ---- Sobol' map and design --------------------------------------------------------------------

    def _sobol_job(self, params, share, settings, n_base=SOBOL_N[1]):
        return sobol(st.sobol_box(params, share), {"theta_i": "0:85@24", "theta_r": "0:85@24"},
                     fixed=dict(ks=params["ks"]), N=n_base, seed=1, shadowing=settings.shadowing,
                     engine=background_engine(self.engine))

    async def _on_sobol(self, event):
        share = float(self.sobol_share.value)
        ds = await self._background(self.sobol_button, "Sobol' map", self._sobol_job,
                                    dict(self.state.sets[self.state.active]), share, self.state.settings,
                                    int(self.sobol_n.value))
        if ds is not None:
            self.sobol_ds = ds
            self._later(self._draw_sobol)

    def _draw_sobol(self):
        if self.sobol_ds is not None:
            self.figs.update_sobol(self.sobol_ds, self.sobol_param.value)

    def _design_job(self, params, settings, noise=DESIGN_NOISE, count=DESIGN_COUNT, instrument="dop"):
        others = [i for i in DESIGN_INSTRUMENTS.values() if i != instrument]
        return design(params, {"theta_i": "10:80:5", "theta_r": "0:85:5"}, noise=noise, n_measurements=count,
                      shadowing=settings.shadowing, instrument=[instrument, *others],
                      engine=background_engine(self.engine))

    async def _on_design(self, event):
        noise = self.design_noise.value  # checked by its entry, and by design() (one line on the page)
        chosen = self.design_instrument.value
        r = await self._background(self.design_button, "design", self._design_job,
                                   dict(self.state.sets[self.state.active]), self.state.settings, noise,
                                   self.design_count.value, chosen)
        if r is not None:
            self.design_result = r
            self._later(self.figs.update_design, r.theta_i, r.theta_r)
            widths = ", ".join(f"{p} {r.ci95_width[p]:.3g}" for p in ("n", "k"))
            label = "DOP" if chosen == "dop" else chosen
            self.jobs.object += (f"; predicted 95% widths at the {len(r.theta_i)} chosen geometries ({label} noise "
                                 f"{noise:g}): {widths} (x on the map)" + design_table(r))

    # ---- exports ----------------------------------------------------------------------------------

    def dataset(self):
        return st.view_dataset(self.engine, self.state, self.meas)

    def _png(self):
        buffer = io.BytesIO()
        plot_view(self.dataset(), buffer)
        buffer.seek(0)
        return buffer

    def _csv(self):
        return io.StringIO(st.curves_csv(self.dataset()))

    def _netcdf(self):
        return io.BytesIO(self.dataset().to_netcdf())

    def _params(self, fmt):
        return io.StringIO(params_text(self.state.sets[self.state.active], fmt))
