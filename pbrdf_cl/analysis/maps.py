"""Two-axis maps of the model from the dense-grid engine: values, derivatives, data (their figures:
:func:`pbrdf_cl.plots.maps.plot_map`).

A map is the model (any quantity of the registry with a map path: DOP, F00, AoP) over the Cartesian
product of two axes ``x`` and ``y`` with every other input fixed, computed on the OpenCL device by
:func:`pbrdf_cl.grid`.  A derivative, along one of the map's axes or along a fixed input, is a
finite difference of step h = 1e-4 deg (angles), 1e-4 |value| (n, sigma, ks) or 1e-4 max(1,
|value|) (k, kd, c) at every node (``stencil``): central, and second-order one-sided at a bound of
the model's domain (theta = 0, k = 0, kd = 0), from one float64 device grid over the stencils'
points.  (Differences on the map's own grid were wrong where the quantity changes by decades
between nodes: at sigma = 0.05 their one-sided edge form gave dDOP/dsigma < 0 where the DOP rises.)
"""
from __future__ import annotations

import json

import numpy as np

from .. import ranges, sizes
from ..compute import dense, pointwise
from ..device.engine import resolve_engine
from ..model import inputs, quantities

#: Relative step of the finite differences of a derivative: h = FD_STEP times 1 degree (angles),
#: |value| (n, sigma, ks) or max(1, |value|) (k, kd, c) (:func:`step_scale`).
FD_STEP = 1e-4


def parse_axis(option, text):
    """``"theta_r=0:85@256"``, ``"theta_r=0:85:5"`` or ``"sigma=0.35,0.5,0.65"`` (the grammar of
    :mod:`pbrdf_cl.ranges`) -> (name, float64 values), checked against the model's rules.
    :class:`pbrdf_cl.ranges.RangeError` (a ``ValueError``) names the option and the text."""
    return ranges.parse_assignment(text, dense.AXES, "values", option, check=True)


def parse_fixed(option, items):
    """``["theta_i=40", "n=1.6"]`` -> {"theta_i": 40.0, "n": 1.6}, checked against the model's rules."""
    return ranges.parse_assignments(items, dense.AXES, "value", option, check=True)


def _axis(option, value):
    if isinstance(value, str):
        return parse_axis(option, value)
    name, values = value
    return name, np.asarray(values, dtype=np.float64)


def make_map(x, y, fixed=None, quantity="dop", derivative=None, *, dtype="float64", shadowing="paper",
             engine=None, backend="auto", memory_budget=dense.DEFAULT_BUDGET):
    """The model over (y, x) with ``fixed`` inputs; optionally its derivative along ``derivative``.

    Parameters
    ----------
    x, y : ``"name=values"`` strings (``"theta_r=0:85@256"``: docs/guide/cli.md) or
        (name, values) pairs (degrees for angles)
    fixed : dict name -> value for the other inputs (phi, ks, kd, c default to 180, 1, 0, 0)
    quantity : "dop", "brdf" (alias "f00") or "aop": :func:`pbrdf_cl.quantities.names` ("map")
    derivative : None, or the name of x, y or a fixed input: finite differences of step
        h = ``FD_STEP`` x ``step_scale`` at every node, central, or second-order one-sided
        at a bound of the model's domain (``stencil``), in float64 (where the device has it)
    dtype, shadowing, engine, backend : as for :func:`pbrdf_cl.grid` (dtype defaults to float64 here)
    memory_budget : int or str, default "1 GiB"
        The memory the map may take (its arrays and its figure, ``map_bytes``: about 144 bytes a
        point, 400 with a derivative); a larger map is refused before any work.

    Returns
    -------
    xarray.Dataset with dims (y, x): the quantity and, with ``derivative``, ``d<quantity>_d<name>``;
    the fixed inputs, quantity, shadowing and dtype in ``attrs``.  Derivatives of an angle (the
    AoP) are taken of its differences wrapped into one period.  ``attrs["notes"]`` names an axis
    the quantity does not depend on over the map.

    Examples
    --------
    >>> ds = make_map("theta_r=0:85@64", "sigma=0.05:1@32", dict(theta_i=40, n=1.6, k=2.139, kd=0.15),
    ...               derivative="sigma")
    >>> sorted(ds.data_vars)
    ['ddop_dsigma', 'dop']
    """
    q = quantities.get(quantity, "map")
    quantity = q.name
    xname, xv = _axis("x", x)
    yname, yv = _axis("y", y)
    if xname == yname:
        raise ValueError(f"x and y are both {xname!r}; choose two different axes")
    for option, name, v in (("x", xname, xv), ("y", yname, yv)):
        if v.size < 2:
            raise ValueError(f"{option}: {name} has one value ({float(v[0]):g}); a map axis needs at least 2 "
                             f"(e.g. {name}=<start>:<stop>@256), or fix it with --fix {name}={float(v[0]):g}")
    check_map_size(xv.size, yv.size, derivative is not None,
                   memory_budget=ranges.parse_bytes("memory_budget", memory_budget))
    fixed = dict(fixed or {})
    for name in (xname, yname):
        if name in fixed:
            raise ValueError(f"{name} is both a map axis and a fixed value")
    axes = {xname: xv, yname: yv}
    kw = dict(quantity=quantity, dtype=dtype, shadowing=shadowing, engine=resolve_engine(engine, backend),
              allow_large=True)  # within the map's own budget, checked above
    da = dense.grid(axes, fixed, **kw).transpose(yname, xname)
    ds = da.to_dataset(name=quantity)
    ds.attrs = dict(da.attrs)
    ds.attrs.update(x=xname, y=yname)
    notes = flat_axis_notes(da, q, (yname, xname))
    if notes:
        ds.attrs["notes"] = notes
    if derivative is not None:
        if derivative not in dense.AXES:
            raise ValueError(f"derivative: unknown input {derivative!r}; valid names are {', '.join(dense.AXES)}")
        dname = f"d{quantity}_d{derivative}"
        if derivative in (xname, yname):
            nodes = xv if derivative == xname else yv
        else:
            nodes = np.array([float(da.attrs[f"fixed_{derivative}"])])  # the grid's value, defaults included
        d, method = _derivative(derivative, nodes, axes, fixed, kw, (yname, xname), q.period)
        if derivative not in (xname, yname):
            d = d[0]
        elif derivative == xname:
            d = np.moveaxis(d, 0, 1)
        ds[dname] = ((yname, xname), d, {"long_name": f"d {quantity} / d {derivative}", "method": method})
        ds.attrs["derivative"] = derivative
    return ds


#: The scale of each input's finite-difference step (:func:`step_scale`), in words.
_SCALE_TEXT = {"angle": "1 deg", "positive": "|{name}|", "other": "max(1, |{name}|)"}


def _scale_kind(name):
    if name in ("theta_i", "theta_r", "phi"):
        return "angle"
    return "positive" if not bool(pointwise.RULES[name][0](np.array(0.0))) else "other"


def step_scale(name, values):
    """The scale of the finite-difference step of d/d``name`` at ``values``: 1 degree for an angle
    (its value says nothing of its scale: phi = 360 is phi = 0), |value| for an input that must be
    positive (n, sigma, ks), max(1, |value|) for k, kd and c, which reach 0."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    kind = _scale_kind(name)
    return np.ones_like(v) if kind == "angle" else v if kind == "positive" else np.maximum(1.0, v)


def stencil(name, nodes, step=None):
    """Finite-difference stencils of d/d``name`` at ``nodes``: (points (N, 3), weights (N, 3)),
    the derivative at node i being sum_j weights[i, j] f(points[i, j]).

    The step is h = ``step`` (default :data:`FD_STEP`) times :func:`step_scale`, and at most a
    tenth of the distance to an open bound of the domain (theta < 90, where the model may be
    singular).  Central, (f(v + h) -
    f(v - h)) / 2h, where both points lie in the model's domain (``pointwise.RULES``); at a bound of the
    domain (theta = 0, k = 0, kd = 0; theta below 90) the second-order one-sided form, (-3 f(v) +
    4 f(v + h) - f(v + 2h)) / 2h forward or its mirror backward, whose error is O(h^2) as the
    central one's.  A central stencil's third point repeats its first with weight 0."""
    ok = pointwise.RULES[name][0]
    v = np.asarray(nodes, dtype=np.float64).reshape(-1)
    h = (FD_STEP if step is None else step) * step_scale(name, v)
    # an open bound of the domain (theta < 90, sigma > 0) may be singular: keep 10 steps from it
    if getattr(ok, "hi", None) is not None and not ok.hi_included:
        h = np.minimum(h, (ok.hi - v) / 10)
    if getattr(ok, "lo", None) is not None and not ok.lo_included:
        h = np.minimum(h, (v - ok.lo) / 10)
    central = ok(v - h) & ok(v + h)
    forward = ~central & ok(v + 2 * h)  # else backward
    pts = np.where(central[:, None], np.stack([v - h, v + h, v - h], 1),
                   np.where(forward[:, None], np.stack([v, v + h, v + 2 * h], 1),
                            np.stack([v, v - h, v - 2 * h], 1)))
    w = np.where(central[:, None], np.array([-1.0, 1.0, 0.0]),
                 np.where(forward[:, None], np.array([-3.0, 4.0, -1.0]), np.array([3.0, -4.0, 1.0])))
    w = w / (2 * h[:, None])
    if not np.all(ok(pts)):
        bad = v[~np.all(ok(pts), axis=1)][0]
        raise ValueError(f"derivative: {name} = {bad:g} leaves no finite-difference step of {FD_STEP:g} inside "
                         f"the model's domain ({name} must be {pointwise.RULES[name][1]})")
    return pts, w


def _derivative(name, nodes, axes, fixed, kw, dims, period):
    """d(quantity)/d(name) at ``nodes`` (an axis of the map, or the one fixed value) over the map's
    other axis or axes: (array (nodes, *the map's dims without name), method text).  The stencil
    points of every node are one axis of one float64 device grid (``stencil``); an angle's
    differences are wrapped into one period first."""
    import warnings
    pts, w = stencil(name, nodes)
    values, inverse = np.unique(pts, return_inverse=True)
    inverse = inverse.reshape(pts.shape)
    grid_axes = {n: v for n, v in axes.items() if n != name}
    grid_axes[name] = values
    others = tuple(d for d in dims if d != name)
    with warnings.catch_warnings():  # the map's own grid has given any radians warning already
        warnings.simplefilter("ignore", pointwise.UnitsWarning)
        dtype = "float64" if getattr(kw["engine"], "fp64", True) else kw["dtype"]  # float64 where the device has it
        g = dense.grid(grid_axes, {n: v for n, v in fixed.items() if n != name}, **{**kw, "dtype": dtype})
    g = g.transpose(name, *others).values.astype(np.float64)  # (points, others...)
    f = g[inverse]  # (nodes, 3, others...)
    diff = quantities.wrap(f - f[:, :1], period)  # relative to the first point: the weights sum to 0
    wb = w.reshape(w.shape + (1,) * (f.ndim - 2))
    d = np.sum(wb * diff, axis=1)
    kinds = []
    central = w[:, 2] == 0
    if central.any():
        kinds.append("central differences")
    if (~central).any():
        kinds.append("second-order one-sided differences at the model's domain bound")
    scale = _SCALE_TEXT[_scale_kind(name)].format(name=name)
    actual = np.abs(pts[:, 1] - pts[:, 0]) / np.where(central, 2.0, 1.0)
    if np.any(actual < FD_STEP * step_scale(name, nodes) * (1 - 1e-9)):
        scale += ", at most a tenth of the distance to the domain's open bound"
    method = (f"{' and '.join(kinds)} of {dtype} device grids at {name} +- h, h = {FD_STEP:g} x {scale}"
              + (f" ({name} = {float(nodes[0]):.8g})" if len(nodes) == 1 else ""))
    return d, method


def map_bytes(nx, ny, derivative):
    """An estimate of the memory a map of nx x ny points takes: its float64 arrays (values, and with
    a derivative its grid of up to three stencil points per node, their gathered copy, the
    differences and the panel) and the figure's meshes (~128 bytes a cell per panel)."""
    panels = 2 if derivative else 1
    return int(nx) * int(ny) * (8 * (2 + 12 * (panels - 1)) + 128 * panels)


def check_map_size(nx, ny, derivative, what="the map", memory_budget=None):
    """Refuse (:class:`pbrdf_cl.sizes.TooLargeError`) a map that cannot fit in memory, or in
    ``memory_budget`` bytes where one is given, before any work."""
    advice = ("use fewer points per axis (a PNG shows a few thousand at most); pbrdf-cl sweep writes larger grids "
              "chunk by chunk into a Zarr store")
    nbytes, what = map_bytes(nx, ny, derivative), f"{what} of {nx} x {ny} points"
    if memory_budget is None:
        sizes.check_memory(nbytes, what, advice)
    else:
        sizes.check_budget(nbytes, what, memory_budget, advice, "raise memory_budget (pbrdf-cl map --memory-budget)")


#: Why a quantity may not depend on an input: (quantity, input, condition on the fixed inputs, reason).
_FLAT_REASONS = (
    ("dop", ("sigma", "ks"), lambda f: f.get("kd", 0.0) == 0.0,
     "with kd = 0 the DOP is the specular term's alone, whose scale (sigma, ks, the shadowing) cancels"),
    ("dop", ("c",), lambda f: f.get("kd", 0.0) == 0.0, "with kd = 0 there is no diffuse term"),
    ("brdf", ("c",), lambda f: f.get("kd", 0.0) == 0.0, "with kd = 0 there is no diffuse term"),
    ("aop", inputs.PARAMETERS, lambda f: True,
     "the AoP depends on the geometry alone wherever it is defined"),
)


def flat_axis_notes(da, q, dims):
    """Notes for the axes of ``da`` (dims) along which the quantity does not change at all (up to
    1e-12 of its scale), with the reason where one is known."""
    values = np.asarray(da.transpose(*dims).values, dtype=np.float64)
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return []
    scale = max(float(np.abs(finite).max()), 1e-300)
    fixed = {k[6:]: v for k, v in da.attrs.items() if k.startswith("fixed_")}
    notes = []
    for axis, name in enumerate(dims):
        with np.errstate(invalid="ignore"):
            spread = np.nanmax(values, axis=axis) - np.nanmin(values, axis=axis)
        spread = spread[np.isfinite(spread)]
        if spread.size and float(spread.max()) <= 1e-12 * scale:
            why = next((r for qn, names, cond, r in _FLAT_REASONS if qn == q.name and name in names and cond(fixed)),
                       None)
            notes.append(f"{q.name} does not depend on {name} over this map" + (f": {why}" if why else ""))
    return notes


def save_npz(ds, path):
    """The map's arrays beside the picture: x, y (coordinates), the quantity, the derivative if
    any, their names, and the attrs as JSON.

    Parameters
    ----------
    ds : xarray.Dataset
        From :func:`make_map`.
    path : str or path
        Ends in ``.npz`` (numpy would append it to any other name, writing a file other than the
        one named).

    Returns
    -------
    None"""
    from pathlib import Path
    if Path(path).suffix.lower() != ".npz":
        raise ValueError(f"{path}: numpy's archive is named .npz; write e.g. {Path(path).with_suffix('.npz')}")
    xname, yname = ds.attrs["x"], ds.attrs["y"]
    arrays = {"x": ds[xname].values, "y": ds[yname].values, "x_name": np.array(xname), "y_name": np.array(yname),
              "attrs": np.array(json.dumps(ds.attrs, default=str))}
    for var in ds.data_vars:
        arrays[var] = ds[var].values
    np.savez_compressed(path, **arrays)
