"""What the explorer shows, without the page: the parameter sets and settings (:class:`State`),
their numbers through the public API (``pbrdf_cl.evaluate`` on one kept engine), the view's
numbers as a Dataset, and the state as a URL query.  Nothing here imports panel or bokeh, so the
tests check it without a browser."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from urllib.parse import urlencode

import numpy as np

from .. import ranges
from ..compute.pointwise import evaluate
from ..io.params import NAMES
from ..model import inputs
from ..plots.explore import SET_COLOURS

#: The paper's steel at 435 nm (Fig. 4): what "reset" returns to.
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
#: Slider ranges (the fit's default bounds; ks from 0.05).
#: The sliders' ranges: the registry's views of the parameters (:data:`pbrdf_cl.model.inputs.VIEWS`).
LIMITS = inputs.VIEWS
STEPS = {p: 0.01 for p in LIMITS}
SET_NAMES = tuple(SET_COLOURS)
COLOURS = tuple(SET_COLOURS.values())
#: quantity -> (label, units, what pbrdf_cl.evaluate computes, Stokes component or None)
QUANTITIES = {"dop": ("DOP", "1", "dop", None), "aop": ("AoP", "deg", "aop", None),
              "brdf": ("BRDF F00", "1/sr", "brdf", None), "s0": ("S0", "1/sr", "stokes", 0),
              "s1": ("S1", "1/sr", "stokes", 1), "s2": ("S2", "1/sr", "stokes", 2)}
MAP_KINDS = ("incidence", "hemisphere")
THETA_MAX = 89.0  # the views' largest zenith angle (the model's domain is [0, 90))
PHI_LIMITS = (0.0, 359.5)  # the curves' azimuth (deg): the slider's range
DIGITS = 6  # the significant digits of the numbers the page prints (the values keep all of theirs)


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
    """``quantity`` (default: the settings') of one parameter set at broadcast geometries."""
    _, _, name, component = QUANTITIES[quantity or settings.quantity]
    out = evaluate(name, theta_i, theta_r, phi, shadowing=settings.shadowing, dtype=settings.dtype,
                   model=settings.model, engine=engine, **model_params(params, settings))
    return out if component is None else out[..., component]


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


def residuals(engine, state, meas):
    """(model DOP, data - model) of the active set at the measurements' geometries."""
    s = state.settings
    model = quantity_values(engine, s, state.sets[state.active], meas.theta_i, meas.theta_r, meas.phi, "dop")
    return model, meas.dop - model


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
    if meas is not None:
        model, res = residuals(engine, state, meas)
        for name, values in dict(data_theta_i=meas.theta_i, data_theta_r=meas.theta_r, data_phi=meas.phi,
                                 data_dop=meas.dop, model_dop=model, residual=res).items():
            ds[name] = xr.DataArray(values, dims=("measurement",))
        if meas.dop_std is not None:
            ds["data_dop_std"] = xr.DataArray(meas.dop_std, dims=("measurement",))
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
    return urlencode(q, safe=",")


#: The keys of the URL's query, as :func:`to_query` writes them.
QUERY_KEYS = (*SET_NAMES, "show", "active", "solo", "q", "model", "shadowing", "dtype", "ti", "phi", "map")


def _choice(key, value, choices):
    if value not in choices:
        raise ValueError(f"URL: {key}={value!r} is not one of {', '.join(choices)}")
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
