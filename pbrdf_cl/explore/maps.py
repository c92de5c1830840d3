"""Two-axis maps of the model from the dense-grid engine: values, derivatives, figures, data.

A map is the model (any quantity of the registry with a map path: DOP, F00, AoP) over the Cartesian product of two axes ``x`` and ``y`` with
every other input fixed, computed on the OpenCL device by :func:`pbrdf_cl.grid`.  A derivative,
along one of the map's axes or along a fixed input, is a finite difference of step h = 1e-4
deg (angles), 1e-4 |value| (n, sigma, ks) or 1e-4 max(1, |value|) (k, kd, c) at every node
(:func:`stencil`): central, and second-order one-sided at a bound of
the model's domain (theta = 0, k = 0, kd = 0), from one float64 device grid over the stencils'
points.  (Differences on the map's own grid were wrong where the quantity changes by decades
between nodes: at sigma = 0.05 their one-sided edge form gave dDOP/dsigma < 0 where the DOP rises.)
"""
from __future__ import annotations

import json

import numpy as np

from ..compute import pointwise
from ..compute import dense
from ..model import quantities
from .. import ranges
from .. import sizes
from ..device.engine import resolve_engine
from ..plots.fit import _pyplot

#: Axis labels with units for figures.
LABELS = {"theta_i": "incidence zenith angle theta_i (deg)", "theta_r": "reflection zenith angle theta_r (deg)",
          "phi": "relative azimuth phi (deg, 180 = in plane)", "n": "refractive index n",
          "k": "extinction coefficient k", "sigma": "per-axis rms slope sigma", "ks": "specular weight ks",
          "kd": "diffuse weight kd", "c": "Minnaert exponent c"}
#: Colour-bar labels of the quantities that have maps (from the registry).
QUANTITY_LABELS = {n: quantities.REGISTRY[n].label for n in quantities.names("map")}
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
             engine=None, backend="auto"):
    """The model over (y, x) with ``fixed`` inputs; optionally its derivative along ``derivative``.

    Parameters
    ----------
    x, y : ``"name=values"`` strings (``"theta_r=0:85@256"``: README, "Ranges and name=value") or
        (name, values) pairs (degrees for angles)
    fixed : dict name -> value for the other inputs (phi, ks, kd, c default to 180, 1, 0, 0)
    quantity : "dop", "brdf" (alias "f00") or "aop": :func:`pbrdf_cl.quantities.names` ("map")
    derivative : None, or the name of x, y or a fixed input: finite differences of step
        h = :data:`FD_STEP` x :func:`step_scale` at every node, central, or second-order one-sided
        at a bound of the model's domain (:func:`stencil`), in float64 (where the device has it)
    dtype, shadowing, engine, backend : as for :func:`pbrdf_cl.grid` (dtype defaults to float64 here)

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
    check_map_size(xv.size, yv.size, derivative is not None)
    fixed = dict(fixed or {})
    for name in (xname, yname):
        if name in fixed:
            raise ValueError(f"{name} is both a map axis and a fixed value")
    axes = {xname: xv, yname: yv}
    kw = dict(quantity=quantity, dtype=dtype, shadowing=shadowing, engine=resolve_engine(engine, backend))
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
    forward = ~central & ok(v + 2 * h)
    backward = ~central & ~forward
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
    points of every node are one axis of one float64 device grid (:func:`stencil`); an angle's
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


def check_map_size(nx, ny, derivative, what="the map"):
    """Refuse (:class:`pbrdf_cl.sizes.TooLargeError`) a map that cannot fit in memory, before any work."""
    sizes.check_memory(map_bytes(nx, ny, derivative), f"{what} of {nx} x {ny} points",
                       "use fewer points per axis (a PNG shows a few thousand at most); pbrdf-cl sweep writes "
                       "larger grids chunk by chunk into a Zarr store")


#: Why a quantity may not depend on an input: (quantity, input, condition on the fixed inputs, reason).
_FLAT_REASONS = (
    ("dop", ("sigma", "ks"), lambda f: f.get("kd", 0.0) == 0.0,
     "with kd = 0 the DOP is the specular term's alone, whose scale (sigma, ks, the shadowing) cancels"),
    ("dop", ("c",), lambda f: f.get("kd", 0.0) == 0.0, "with kd = 0 there is no diffuse term"),
    ("brdf", ("c",), lambda f: f.get("kd", 0.0) == 0.0, "with kd = 0 there is no diffuse term"),
    ("aop", ("n", "k", "sigma", "ks", "kd", "c"), lambda f: True,
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


def plot_map(ds, path, title=None, dpi=120):
    """Write a map as a PNG: the quantity with labelled contour lines and a colour bar, and the
    derivative (diverging colours, zero-centred) in a second panel when present.

    A BRDF over more than two decades is on a log scale of at most :data:`LOG_DECADES` decades
    (the colour bar says where it is clipped).

    Parameters
    ----------
    ds : xarray.Dataset
        From :func:`make_map`.
    path : str or path
        The PNG to write.
    title : str, optional
        Instead of the quantity, axes and fixed inputs.
    dpi : int, default 120

    Returns
    -------
    matplotlib.figure.Figure
        The figure (closed).

    Examples
    --------
    >>> plot_map(make_map("theta_r=0:85@64", "sigma=0.05:1@32", dict(theta_i=40, n=1.6, k=2.1)), "map.png")  # doctest: +SKIP
    """
    from matplotlib import colors
    plt = _pyplot()
    xname, yname = ds.attrs["x"], ds.attrs["y"]
    quantity = ds.attrs["quantity"]
    deriv = ds.attrs.get("derivative")
    panels = [quantity] + ([f"d{quantity}_d{deriv}"] if deriv else [])
    fig, axs = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 5.0), squeeze=False, layout="constrained")
    x, y = ds[xname].values, ds[yname].values
    suptitle = title or (f"{QUANTITY_LABELS[quantity]} over ({xname}, {yname}); "
                         f"{_fixed_text(ds.attrs)}; shadowing {ds.attrs['shadowing']}")
    fig.suptitle(_title(suptitle, fig.get_figwidth(), 10), fontsize=10)
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
    fig.draw_without_rendering()  # the layout first: labels are placed in the axes' final shape
    for ax, cs, fmt in contours:
        label_contours(ax, cs, fmt=fmt)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return fig


def save_npz(ds, path):
    """The map's arrays beside the picture: x, y (coordinates), the quantity, the derivative if
    any, their names, and the attrs as JSON; ``path`` ends in ``.npz`` (numpy would append it to
    any other name, writing a file other than the one named)."""
    from pathlib import Path
    if Path(path).suffix.lower() != ".npz":
        raise ValueError(f"{path}: numpy's archive is named .npz; write e.g. {Path(path).with_suffix('.npz')}")
    xname, yname = ds.attrs["x"], ds.attrs["y"]
    arrays = {"x": ds[xname].values, "y": ds[yname].values, "x_name": np.array(xname), "y_name": np.array(yname),
              "attrs": np.array(json.dumps(ds.attrs, default=str))}
    for var in ds.data_vars:
        arrays[var] = ds[var].values
    np.savez_compressed(path, **arrays)
