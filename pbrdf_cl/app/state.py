"""What the explorer shows, without the page: the parameter sets and settings (:class:`State`),
their numbers through the public API (``pbrdf_cl.evaluate`` and ``pbrdf_cl.stokes(incident=)``,
through :func:`pbrdf_cl.compute.measured.measured`, on one kept engine), the loaded measurements'
points of the view's quantity and incident state, the view's numbers as a Dataset, and the state as
a URL query.  Nothing here imports panel or bokeh, so the tests check it without a browser."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import NamedTuple
from urllib.parse import urlencode

import numpy as np

from .. import ranges
from ..compute import measured as ms
from ..compute.pointwise import check_incident
from ..fitting.setup import MODEL_FIXED
from ..io.params import NAMES
from ..model import inputs, measurables
from ..plots.explorer import SET_COLOURS

#: The paper's steel at 435 nm (Fig. 4): what "reset" returns to.
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
#: Slider ranges (the fit's default bounds; ks from 0.05).
#: The sliders' ranges: the registry's views of the parameters (:data:`pbrdf_cl.model.inputs.VIEWS`).
LIMITS = inputs.VIEWS
STEPS = {p: 0.01 for p in LIMITS}
SET_NAMES = tuple(SET_COLOURS)
COLOURS = tuple(SET_COLOURS.values())


def _quantities():
    """The views' quantities: key -> (label, units, measurable quantity, normalised), the measurable
    quantities of :mod:`pbrdf_cl.model.measurables` (what a data column of that name holds)."""
    def entry(name, norm):
        return (*ms.label(name, norm), name, norm)
    q = {"dop": entry("dop", True), "aop": entry("aop", True), "brdf": entry("f00", False)}
    q.update({f"s{j}": entry(f"s{j}", False) for j in range(4)})  # absolute: 1/sr
    q.update({f"s{j}n": entry(f"s{j}", True) for j in (1, 2, 3)})  # S_j / S0
    pairs = [f"{i}{j}" for i in range(4) for j in range(4) if i or j]
    q.update({f"m{ij}": entry(f"m{ij}", True) for ij in pairs})  # M_ij / M00
    q.update({f"M{ij}": entry(f"m{ij}", False) for ij in pairs})  # absolute: 1/sr
    return q


#: quantity -> (label, units, measurable quantity, normalised): what the views show, computed by
#: :func:`pbrdf_cl.compute.measured.measured` (``dop``, ``aop``, the Stokes parameters s0..s3 and
#: the normalised s1n..s3n under the settings' incident state; ``brdf``, the Mueller elements
#: normalised m01..m33 and absolute M01..M33, of any source).
QUANTITIES = _quantities()
#: The views whose values depend on the incident state (the others do not: F00, Mueller elements).
UNDER_SOURCE = tuple(k for k, v in QUANTITIES.items() if measurables.REGISTRY[v[2]].family in ms.STATE_DEPENDENT)
UNPOLARIZED = (0.0, 0.0, 0.0)
MAP_KINDS = ("incidence", "hemisphere")
THETA_MAX = 89.0  # the views' largest zenith angle (the model's domain is [0, 90))
PHI_LIMITS = (0.0, 359.5)  # the curves' azimuth (deg): the slider's range
DIGITS = 6  # the significant digits of the numbers the page prints (the values keep all of theirs)
#: The Bokeh session ids of the served pages alive: a page adds its own when made, and its session's
#: end removes it (a closed page's session ends once the server has seen it unused for a while).
PAGES = set()


def number_text(value):
    """A number as the page prints it: six significant digits (``1.62``, ``8.4e-07``, not ``0.00000``)."""
    return f"{value:.{DIGITS}g}"


@dataclass
class Settings:
    """The settings shared by every parameter set."""
    quantity: str = "dop"
    model: str = "six-param"
    shadowing: str = "paper"
    dtype: str = "float64"
    theta_i: tuple = (30.0, 40.0, 50.0)
    phi: float = 180.0
    map_kind: str = "incidence"
    resolution: int = 256
    #: the incident light's normalised Stokes vector (s1, s2, s3); (0, 0, 0): unpolarized
    incident: tuple = UNPOLARIZED


@dataclass
class State:
    """Up to four parameter sets (A-D), which are shown, which one is solo and which one the
    sliders edit, and the settings."""
    sets: list = field(default_factory=lambda: [dict(STEEL) for _ in SET_NAMES])
    shown: list = field(default_factory=lambda: [True, False, False, False])
    active: int = 0
    solo: int | None = None
    settings: Settings = field(default_factory=Settings)

    def visible(self):
        """The indices of the sets drawn: the solo one, else every shown one."""
        if self.solo is not None:
            return [self.solo]
        return [i for i, s in enumerate(self.shown) if s]

    def copy(self):
        return copy.deepcopy(self)


def parse_theta_i(text):
    """The incidence angles of the curves from text of the range grammar (``30,40,50``, ``20:60:10``)."""
    values = ranges.parse_values(text, where="theta_i")
    if values.size > 8:
        raise ValueError(f"theta_i = {text!r}: at most 8 incidence angles, got {values.size}")
    bad = values[(values < 0) | (values >= 90)]
    if bad.size:
        raise ValueError(f"theta_i = {text!r}: angles must be in [0, 90) degrees, got {bad[0]:g}")
    return tuple(float(v) for v in values)


def model_params(params, settings):
    """The keyword arguments of ``pbrdf_cl.evaluate`` for one set: the ref. [7] (specular) model
    has no diffuse term, so kd is 0 there."""
    kw = {k: params[k] if isinstance(params[k], np.ndarray) else float(params[k]) for k in NAMES}
    if settings.model == "specular":
        kw["kd"] = 0.0
    return kw


def quantity_values(engine, settings, params, theta_i, theta_r, phi, quantity=None):
    """``quantity`` (default: the settings') of one parameter set at broadcast geometries, under the
    settings' incident state (:func:`pbrdf_cl.compute.measured.measured`: ``pbrdf_cl.evaluate``, or
    ``pbrdf_cl.stokes`` with ``incident=``)."""
    _, _, name, norm = QUANTITIES[quantity or settings.quantity]
    return ms.measured(name, theta_i, theta_r, phi, incident=settings.incident, normalised=norm,
                       params=model_params(params, settings), shadowing=settings.shadowing, dtype=settings.dtype,
                       model=settings.model, engine=engine)


def source_text(settings, quantity=None):
    """The incident state, in words, where the quantity depends on it (``, source linear +45 (0, 1,
    0)``), else ""; unpolarized light is said only where it is not the default."""
    if (quantity or settings.quantity) not in UNDER_SOURCE or ms.unpolarized(settings.incident):
        return ""
    return f", source {ms.state_text(settings.incident)}"


def view_of(name, normalised):
    """The view's quantity (a key of :data:`QUANTITIES`) that shows the measurable quantity ``name``
    as measured (normalised or absolute); F00 and M00 are the BRDF's view."""
    if name in ("f00", "m00"):
        return "brdf"
    return next(k for k, v in QUANTITIES.items() if v[2] == name and (v[3] == normalised or name == "s0"))


class Points(NamedTuple):
    """The loaded measurements the view shows: the ``rows`` (a mask), their geometry, the measured
    ``value`` and its ``std`` (None where not given), the measurable quantity ``name``."""
    rows: np.ndarray
    theta_i: np.ndarray
    theta_r: np.ndarray
    phi: np.ndarray
    value: np.ndarray
    std: np.ndarray | None
    name: str


def _stds(meas):
    stds = dict(meas.stds)
    for name, std in (("dop", meas.dop_std), ("f00", meas.f00_std)):
        if std is not None:
            stds[name] = std
    return stds


def view_points(meas, settings, quantity=None):
    """The points of ``meas`` that the view of ``quantity`` (default: the settings') shows: the
    rows that measure that quantity (as measured: normalised or absolute) under the settings'
    incident state (a Mueller element and F00 under any); a :class:`Points` (no rows: none)."""
    key = quantity or settings.quantity
    cols = meas.columns()
    groups = [g for g in ms.groups(meas) if view_of(g[0], g[1]) == key]
    rows = np.zeros(len(meas), bool)
    name = groups[0][0] if groups else QUANTITIES[key][2]  # the BRDF's view: f00, else m00
    for g_name, _, state, g_rows in groups:
        if g_name == name and (state is None or np.allclose(state, settings.incident, rtol=0, atol=1e-9)):
            rows |= g_rows
    value = cols[name][rows] if name in cols else np.empty(0)
    std = _stds(meas).get(name)
    return Points(rows, meas.theta_i[rows], meas.theta_r[rows], meas.phi[rows], value,
                  None if std is None else std[rows], name)


def measures(meas, quantity):
    """Whether ``meas`` holds the view ``quantity``'s quantity (under any incident state)."""
    return any(view_of(g[0], g[1]) == quantity for g in ms.groups(meas))


def incident_options(extra=()):
    """The incident states a page offers: label -> (s1, s2, s3), the named ones
    (:data:`pbrdf_cl.compute.measured.NAMED_STATES`) and then the ``extra`` ones (a data set's, a
    link's) that are not among them."""
    out = {ms.state_text(v): v for v in ms.NAMED_STATES.values()}
    for state in extra:
        state = tuple(float(v) for v in state)
        if state not in out.values():
            out[ms.state_text(state)] = state
    return out


def data_states(meas):
    """The incident states of ``meas``'s rows, (s1, s2, s3) tuples in order of first appearance."""
    inc = np.zeros((len(meas), 3)) if meas.incident is None else meas.incident
    return list(dict.fromkeys(tuple(float(v) for v in row) for row in inc))


def first_view(meas):
    """(quantity, incident state) of the first view that shows points of ``meas``."""
    name, norm, state, _ = ms.groups(meas)[0]
    return view_of(name, norm), UNPOLARIZED if state is None else state


def fit_params(result):
    """Every model parameter of a :class:`pbrdf_cl.FitResult`: the fitted values and those the
    model holds (the specular model's sigma, ks, kd, c)."""
    return {**MODEL_FIXED[result.model], **result.x}


def fit_curves(engine, state, result, theta_r):
    """(len(theta_i), len(theta_r)) values of the view's quantity for the fit ``result`` (its model,
    shadowing and parameters) at the settings' theta_i, phi and incident state."""
    s = state.settings
    shown = Settings(**{**s.__dict__, "model": result.model, "shadowing": result.shadowing})
    return quantity_values(engine, shown, fit_params(result), np.asarray(s.theta_i)[:, None], theta_r[None, :], s.phi)


def theta_r_axis(step=0.5):
    """The curves' reflection angles, 0 to THETA_MAX degrees."""
    return np.arange(0.0, THETA_MAX + step / 2, step)


def curves(engine, state, theta_r=None):
    """Set index -> (len(theta_i), len(theta_r)) values of the visible sets at the settings' phi,
    all sets in one call (their parameters along a leading axis)."""
    s = state.settings
    theta_r = theta_r_axis() if theta_r is None else theta_r
    shown = state.visible()
    if not shown:
        return {}
    params = {k: np.array([float(state.sets[i][k]) for i in shown])[:, None, None] for k in NAMES}
    ti = np.asarray(s.theta_i, dtype=float)[None, :, None]
    values = quantity_values(engine, s, params, ti, theta_r[None, None, :], s.phi)
    return dict(zip(shown, values))


def same_curves(a, b, rtol=1e-6):
    """Whether two sets' curves are the same as drawn: NaN at the same points and the others equal
    to ``rtol`` of the largest magnitude of either (exactly, where both are zero everywhere)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    nan = np.isnan(a)
    if a.shape != b.shape or not np.array_equal(nan, np.isnan(b)):
        return False
    if nan.all():
        return True
    scale = max(float(np.max(np.abs(a[~nan]))), float(np.max(np.abs(b[~nan]))))
    return bool(np.max(np.abs(a[~nan] - b[~nan])) <= rtol * scale)


def _names(indices):
    names = [SET_NAMES[i] for i in indices]
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def curves_note(state, values):
    """The page's note on what the curves do not show: no set shown, or shown sets that draw the
    same curves (``values``: :func:`curves`'s), where the last drawn covers the others; "" if none."""
    if not values:
        return "no set is shown: choose one under show"
    label = QUANTITIES[state.settings.quantity][0]
    groups = []
    for i in values:
        group = next((g for g in groups if same_curves(values[g[0]], values[i])), None)
        if group is None:
            groups.append([i])
        else:
            group.append(i)
    notes = []
    for group in (g for g in groups if len(g) > 1):
        first = state.sets[group[0]]
        differ = [p for p in NAMES if any(state.sets[i][p] != first[p] for i in group[1:])]
        last, others = SET_NAMES[group[-1]], "the others" if len(group) > 2 else SET_NAMES[group[0]]
        if differ:
            notes.append(f"sets {_names(group)} give the same {label} here (they differ in {', '.join(differ)}): "
                         f"{last} is drawn over {others}")
        else:
            notes.append(f"sets {_names(group)} are equal: {last} is drawn over {others}")
    return "; ".join(notes)


def incidence_axes(resolution):
    a = np.linspace(0.0, THETA_MAX, resolution)
    return a, a.copy()


def incidence_map(engine, state, quantity=None):
    """(theta_i, theta_r, values[theta_i, theta_r]) of the active set at the settings' phi."""
    s = state.settings
    ti, tr = incidence_axes(s.resolution)
    v = quantity_values(engine, s, state.sets[state.active], ti[:, None], tr[None, :], s.phi, quantity)
    return ti, tr, v


def hemisphere_geometry(resolution):
    """The hemisphere seen from above (equidistant: radius = theta_r / 90): image x, y in [-1, 1]
    and, inside the disc, theta_r and the relative azimuth phi = 180 - phi_r (the source lies at
    azimuth 180, on the left; the in-plane specular side, phi = 180, on the right)."""
    x = np.linspace(-1.0, 1.0, resolution)
    X, Y = np.meshgrid(x, x)  # rows: y
    r = np.hypot(X, Y)
    inside = r * 90.0 <= THETA_MAX
    theta_r = r[inside] * 90.0
    phi_r = np.degrees(np.arctan2(Y[inside], X[inside]))
    phi = np.mod(180.0 - phi_r, 360.0)
    return x, inside, theta_r, phi, phi_r


def hemisphere_map(engine, state, quantity=None):
    """(x, y, values[y, x]) of the active set over the hemisphere of reflection at the first
    incidence angle; NaN outside the disc."""
    s = state.settings
    x, inside, theta_r, phi, _ = hemisphere_geometry(s.resolution)
    out = np.full(inside.shape, np.nan)
    out[inside] = quantity_values(engine, s, state.sets[state.active], s.theta_i[0], theta_r, phi, quantity)
    return x, x.copy(), out


def aop_ticks(engine, state, count=15):
    """Orientation ticks of the AoP over the map: segment ends (x0, y0, x1, y1) in the map's
    coordinates, half a cell long, at a ``count`` x ``count`` lattice (none where the AoP is
    undefined).  On the incidence map a tick's angle from the theta_r axis is the AoP; on the
    hemisphere it is the polarization's direction projected on the page (the AoP measured from
    the beam's s axis, perpendicular to the plane of reflection, towards its p axis)."""
    s = state.settings
    params = state.sets[state.active]
    if s.map_kind == "incidence":
        ti, tr = incidence_axes(count)
        cx, cy = np.meshgrid(tr, ti)  # x: theta_r, y: theta_i
        a = np.radians(quantity_values(engine, s, params, ti[:, None], tr[None, :], s.phi, "aop"))
        half = 0.4 * THETA_MAX / (count - 1)
        dx, dy = np.cos(a), np.sin(a)
    else:
        x, inside, theta_r, phi, phi_r = hemisphere_geometry(count)
        X, Y = np.meshgrid(x, x)
        cx, cy = X[inside], Y[inside]
        a = np.radians(quantity_values(engine, s, params, s.theta_i[0], theta_r, phi, "aop"))
        pr, tr = np.radians(phi_r), np.radians(theta_r)
        dx = np.cos(a) * np.sin(pr) + np.sin(a) * np.cos(tr) * np.cos(pr)  # cos A s + sin A p, seen from above
        dy = -np.cos(a) * np.cos(pr) + np.sin(a) * np.cos(tr) * np.sin(pr)
        norm = np.hypot(dx, dy)
        dx, dy = dx / np.where(norm > 0, norm, 1), dy / np.where(norm > 0, norm, 1)
        half = 0.4 * 2.0 / (count - 1)
    ok = np.isfinite(a)
    cx, cy, dx, dy = (np.ravel(v)[np.ravel(ok)] for v in (cx, cy, dx, dy))
    return cx - half * dx, cy - half * dy, cx + half * dx, cy + half * dy


def residuals(engine, state, meas, points=None):
    """(model, data - model) of the active set at the view's points of ``meas`` (``points``:
    :func:`view_points`'s, computed where not given); an AoP's residual wrapped modulo 180."""
    s = state.settings
    p = view_points(meas, s) if points is None else points
    model = quantity_values(engine, s, state.sets[state.active], p.theta_i, p.theta_r, p.phi)
    return model, -ms.residual(p.name, model, p.value)


def view_dataset(engine, state, meas=None):
    """The numbers of the current view as an ``xarray.Dataset``: the curves of the visible sets
    (set, theta_i, theta_r), the map of the active set (with the AoP's orientation ticks,
    ``tick_x0`` ... ``tick_y1``, when the quantity is the AoP), and the measurements with residuals."""
    import xarray as xr
    s = state.settings
    label, units, _, _ = QUANTITIES[s.quantity]
    tr = theta_r_axis()
    cv = curves(engine, state, tr)
    names = [SET_NAMES[i] for i in cv]
    ds = xr.Dataset(attrs=dict(quantity=s.quantity, model=s.model, shadowing=s.shadowing, dtype=s.dtype,
                               phi_curves=s.phi, map_kind=s.map_kind, units=units, active_set=SET_NAMES[state.active]))
    if s.quantity in UNDER_SOURCE:
        ds.attrs["incident"] = list(s.incident)  # (s1, s2, s3) of the source
        ds.attrs["source"] = ms.state_text(s.incident)
    ds["curve"] = xr.DataArray(np.stack([cv[i] for i in cv]) if cv else np.empty((0, len(s.theta_i), tr.size)),
                               dims=("set", "theta_i", "theta_r"),
                               coords=dict(set=names, theta_i=list(s.theta_i), theta_r=tr),
                               attrs=dict(long_name=label, units=units))
    for p in NAMES:
        ds[f"param_{p}"] = xr.DataArray([state.sets[i][p] for i in cv], dims=("set",))
    if s.map_kind == "incidence":
        a, b, v = incidence_map(engine, state)
        ds["map"] = xr.DataArray(v, dims=("map_theta_i", "map_theta_r"), coords=dict(map_theta_i=a, map_theta_r=b),
                                 attrs=dict(long_name=label, units=units, phi=s.phi))
    else:
        a, b, v = hemisphere_map(engine, state)
        ds["map"] = xr.DataArray(v, dims=("map_y", "map_x"), coords=dict(map_x=a, map_y=b),
                                 attrs=dict(long_name=label, units=units, theta_i=s.theta_i[0],
                                            projection="theta_r = 90 hypot(x, y); x towards phi = 180"))
    if s.quantity == "aop":  # the page's orientation ticks, as segments in the map's coordinates
        units = "deg" if s.map_kind == "incidence" else "1"
        for name, values in zip(("tick_x0", "tick_y0", "tick_x1", "tick_y1"), aop_ticks(engine, state)):
            ds[name] = xr.DataArray(values, dims=("tick",), attrs=dict(units=units))
    points = None if meas is None else view_points(meas, s)
    if points is not None and points.rows.any():  # the measurements of this view's quantity and source
        model, res = residuals(engine, state, meas, points)
        q = s.quantity
        for name, values in {"data_theta_i": points.theta_i, "data_theta_r": points.theta_r,
                             "data_phi": points.phi, f"data_{q}": points.value, f"model_{q}": model,
                             "residual": res}.items():
            ds[name] = xr.DataArray(values, dims=("measurement",))
        if points.std is not None:
            ds[f"data_{q}_std"] = xr.DataArray(points.std, dims=("measurement",))
    return ds


def curves_csv(ds):
    """The view's curves as CSV text, one row per (set, theta_i, theta_r)."""
    lines = [f"# {ds.attrs['quantity']} ({ds.attrs['units']}), model {ds.attrs['model']}, shadowing "
             f"{ds.attrs['shadowing']}, {ds.attrs['dtype']}, phi = {ds.attrs['phi_curves']:g}",
             "set,n,k,sigma,ks,kd,c,theta_i,theta_r,phi,value"]
    c = ds["curve"]
    for si, name in enumerate(c["set"].values):
        p = ",".join(repr(float(ds[f"param_{q}"].values[si])) for q in NAMES)
        for ti_i, ti in enumerate(c["theta_i"].values):
            for tr_i, tr in enumerate(c["theta_r"].values):
                lines.append(f"{name},{p},{ti:g},{tr:g},{ds.attrs['phi_curves']:g},{float(c.values[si, ti_i, tr_i])!r}")
    return "\n".join(lines) + "\n"


def to_query(state):
    """The state as a URL query string (``?A=1.6,2.139,...&q=dop&...``): a link reopens the view."""
    s = state.settings
    q = {name: ",".join(f"{p[k]:.6g}" for k in NAMES) for name, p in zip(SET_NAMES, state.sets)}
    q.update(show="".join(n for n, on in zip(SET_NAMES, state.shown) if on), active=SET_NAMES[state.active],
             q=s.quantity, model=s.model, shadowing=s.shadowing, dtype=s.dtype,
             ti=",".join(f"{t:g}" for t in s.theta_i), phi=f"{s.phi:g}", map=s.map_kind)
    if state.solo is not None:
        q["solo"] = SET_NAMES[state.solo]
    if not ms.unpolarized(s.incident):
        q["inc"] = ",".join(_shortest(v) for v in s.incident)
    return urlencode(q, safe=",")


def _shortest(value):
    """A float as the shortest text that reads back as it (``1``, ``0.7071067811865476``)."""
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


#: The keys of the URL's query, as :func:`to_query` writes them.
QUERY_KEYS = (*SET_NAMES, "show", "active", "solo", "q", "model", "shadowing", "dtype", "ti", "phi", "map", "inc")


def _choice(key, value, choices):
    if value not in choices:
        raise ValueError(f"URL: {key}={value!r} is not one of {_choice_text(key, choices)}")
    return value


def _parse_set(key, text):
    parts = text.split(",")
    if len(parts) != len(NAMES):
        raise ValueError(f"URL: {key}={text!r}: give the {len(NAMES)} values {','.join(NAMES)}")
    try:
        values = [float(v) for v in parts]
    except ValueError:
        raise ValueError(f"URL: {key}={text!r}: not numbers") from None
    for p, v in zip(NAMES, values):
        lo, hi = LIMITS[p]
        if not lo <= v <= hi:
            raise ValueError(f"URL: {key}: {p} = {v:g} is outside [{lo:g}, {hi:g}]")
    return dict(zip(NAMES, values))


def _parse_show(text):
    bad = sorted(set(text) - set(SET_NAMES))
    if bad:
        verb = "is not a set" if len(bad) == 1 else "are not sets"
        raise ValueError(f"URL: show={text!r}: {', '.join(map(repr, bad))} {verb}; give letters of "
                         f"{''.join(SET_NAMES)} (show=AB: sets A and B)")
    return [n in text for n in SET_NAMES]


def _parse_theta_i(text):
    try:
        return parse_theta_i(text)
    except ValueError as exc:
        raise ValueError(f"URL: ti: {exc}") from None


def _parse_phi(text):
    try:
        phi = float(text)
    except ValueError:
        raise ValueError(f"URL: phi={text!r} is not a number") from None
    lo, hi = PHI_LIMITS
    if not lo <= phi <= hi:  # NaN too
        raise ValueError(f"URL: phi = {phi:g} is outside [{lo:g}, {hi:g}] (degrees)")
    return phi


def parse_incident(text, where="inc"):
    """An incident state (s1, s2, s3) from text ``s1,s2,s3``: three numbers, a Stokes vector
    (s1^2 + s2^2 + s3^2 <= 1); one-line ``ValueError``s naming ``where`` otherwise."""
    parts = text.split(",")
    try:
        values = tuple(float(v) for v in parts)
    except ValueError:
        raise ValueError(f"{where}={text!r}: not numbers; give s1,s2,s3 of the source (0,1,0: linear at +45 "
                         "degrees)") from None
    if len(values) != 3:
        raise ValueError(f"{where}={text!r}: give the three numbers s1,s2,s3 of the source, got {len(values)}")
    try:
        check_incident(values)
    except ValueError as exc:
        raise ValueError(f"{where}={text!r}: {exc}") from None
    return tuple(v + 0.0 for v in values)  # no -0


def _choice_text(key, choices):
    if key == "q":  # forty of them: the families
        return "dop, aop, brdf, s0..s3, s1n..s3n (S_j/S0), m01..m33 (M_ij/M00), M01..M33"
    return ", ".join(choices)


def from_query(args, problems=None):
    """A :class:`State` from the query's arguments (name -> str), as :func:`to_query` writes them.

    A bad value, or an unknown key, is a one-line ``ValueError`` naming the key; with a dict
    ``problems`` it is not raised but stored there (key -> the line), and that key keeps its
    default while the others are read."""
    from ..compute.pointwise import MODELS
    from ..model.reference import SHADOWING
    state = State()
    s = state.settings

    def take(key, parse, store):
        if key not in args:
            return
        try:
            store(parse(args[key]))
        except ValueError as exc:
            if problems is None:
                raise
            problems[key] = str(exc)

    for i, name in enumerate(SET_NAMES):
        take(name, lambda text, name=name: _parse_set(name, text), lambda v, i=i: state.sets.__setitem__(i, v))
    take("show", _parse_show, lambda v: setattr(state, "shown", v))
    for key in ("active", "solo"):
        take(key, lambda text, key=key: SET_NAMES.index(_choice(key, text, SET_NAMES)),
             lambda v, key=key: setattr(state, key, v))
    for key, attr, choices in (("q", "quantity", tuple(QUANTITIES)), ("model", "model", tuple(MODELS)),
                               ("shadowing", "shadowing", tuple(sorted(SHADOWING))),
                               ("dtype", "dtype", ("float64", "float32")), ("map", "map_kind", MAP_KINDS)):
        take(key, lambda text, key=key, choices=choices: _choice(key, text, choices),
             lambda v, attr=attr: setattr(s, attr, v))
    take("ti", _parse_theta_i, lambda v: setattr(s, "theta_i", v))
    take("phi", _parse_phi, lambda v: setattr(s, "phi", v))
    take("inc", lambda text: parse_incident(text, "URL: inc"), lambda v: setattr(s, "incident", v))
    for key in args:
        if key not in QUERY_KEYS and not key.startswith("bokeh-"):  # bokeh's own arguments of an embedded page
            line = f"URL: unknown key {key!r} (the keys are {', '.join(QUERY_KEYS)})"
            if problems is None:
                raise ValueError(line)
            problems[key] = line
    return state


def sobol_box(params, share=0.1):
    """A box around one parameter set for a Sobol' map: each of n, k, sigma, kd, c within
    ``share`` of its slider range either side, clipped to the range (ks fixed: the DOP depends on
    kd/ks only)."""
    box = {}
    for p in inputs.FITTED:
        lo, hi = LIMITS[p]
        half = share * (hi - lo)
        a, b = max(lo, params[p] - half), min(hi, params[p] + half)
        if p == "sigma":
            a = max(a, 0.05)
        box[p] = (a, b)
    return box
