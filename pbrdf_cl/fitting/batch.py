"""Per-pixel inversion of polarization image stacks: :func:`fit_batch`.

Every pixel of a stack has its own M measurements of DOP (and optionally intensity) and is
fitted on its own, by the stages of :func:`pbrdf_cl.fit` reshaped for many pixels at once:

(a) the objective on a coarse grid for every pixel, on the device, keeping the minimum of each
    region of the grid (the grid split in halves along every free parameter): with shared
    geometry the DOP table of the grid is computed once and each pixel's SSE is its product with
    the pixel's data; with per-pixel geometry the factor tables of ``pbrdf_tables.cl`` are built
    per pixel and combined (``kernels/pbrdf_batch.cl``);
(b) a bounded Levenberg-Marquardt run on the device from each pixel's best region minima, the
    algorithm of :func:`pbrdf_cl.fitting.inversion._lm_batch` (float32), the best of them polished in
    float64, derivatives by forward differences of the device functions of ``kernels/pbrdf.h``;
    with intensities (``f00``/``s0``) a last float64 run adds ks (as log ks) and the intensity
    residuals, as :func:`pbrdf_cl.fit`'s intensity stage;
(c) the best start per pixel, covariance from J^T J, 95% intervals (the central 95% of the
    Gaussian, or Student's t, truncated to the bounds), and a status per pixel.

On the numpy backend the same stages run with ``reference.py`` (the grid from
``dense._NumpyTables``, the descent by ``_lm_batch`` itself): slower, for machines without a
usable OpenCL driver and for tests.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..compute import pointwise
from ..compute import dense
from ..model import reference
from ..device import engine as _engine
from ..device.engine import DTYPES, resolve_engine
from .common import (DOP_NOISE_FLOOR, GOODNESS_P, GOODNESS_R2, MISTAKE_CAUSES, X_RESOLUTION, dop_resolution,
                     fd_jacobian, lm_batch)
from .setup import DEFAULT_BOUNDS, MODEL_FIXED, FitSetup, check_model

#: Grid nodes per free parameter of the batched grid stage (coarser than :func:`fit`'s: the
#: regions' minima only seed the descents).
BATCH_GRID = {"n": 12, "k": 12, "sigma": 8, "kd": 8, "c": 4}
BATCH_SPECULAR_GRID = {"n": 48, "k": 48}
#: Starts per pixel: the best region minima of the grid.
N_STARTS = 32
#: Geodesic acceleration of the descents (Transtrum and Sethna 2012) without intensities.
GEODESIC = True
#: The float32 descents: (how many of the best starts, iterations), in turn, each continuing the
#: best of the previous; then the float64 polish of the best POLISH_STARTS.
SCREEN_SCHEDULE = ((32, 12), (8, 30))
SCREEN_ITERATIONS = 42  # the numpy backend's one descent of every start: the schedule's iterations
POLISH_STARTS = 1
POLISH_ITERATIONS = 20
#: Descents not settled after the polish continue alone, up to this many runs of this many iterations.
EXTRA_ROUNDS = 3
EXTRA_ITERATIONS = 60
#: Coordinates of the best polished point within this fraction of the bound range from a bound are
#: moved closer to it for one more polished descent (:func:`_towards_bounds`).
SNAP = 0.05
#: Iterations of the float64 run with intensities (ks free).
INTENSITY_ITERATIONS = 40
#: A parameter counts as determined by a pixel's data where its 95% interval is narrower than
#: this fraction of its bound range.
DETERMINED_FRACTION = 0.5
#: Default relative uncertainty of intensities without f00_std (as :func:`pbrdf_cl.fit`).
F00_REL_STD = 0.05
DEFAULT_BUDGET = "512 MiB"
#: Work-group size of the batch kernels: each work-item holds a few kB of private arrays, which
#: PoCL's CPU driver allocates for a whole work-group at once (a large group overflows its stack).
LOCAL_SIZE = 4

#: status code -> (name, meaning)
STATUS = {
    1: ("converged", "the descent converged inside the bounds"),
    2: ("on_bound", "converged with a parameter on a bound"),
    3: ("ambiguous", "another start ended within one unit of chi2 of the best, more than 2 standard errors "
                     "away in some parameter: the data cannot decide between them"),
    4: ("underdetermined", "a parameter's 95% interval spans more than half its bounds: the pixel's data do not "
                           "determine it (see `determined`)"),
    0: ("not_converged", "the descent was still improving when its iterations ran out"),
    -1: ("masked", "not fitted: masked"),
    -2: ("too_few", "not fitted: fewer valid measurements (distinct geometries) than needed for the free "
                    "parameters"),
    -3: ("failed", "the model's residuals are not finite at any start"),
}


def _status_attrs():
    return {"status_codes": "; ".join(f"{c}: {n} ({m})" for c, (n, m) in STATUS.items()),
            "flag_values": list(STATUS), "flag_meanings": " ".join(n for n, _ in STATUS.values())}


VARIABLES = ("dop", "theta_i", "theta_r", "phi", "dop_std", "f00", "s0", "f00_std", "mask")
ANGLES = ("theta_i", "theta_r", "phi")
#: Variables over the measurements that fit_batch does not read and accepts without a warning:
#: :func:`pbrdf_cl.io.camera.camera_dataset`'s raw S0 (``intensity``; the fit reads ``s0``, S0 /
#: irradiance, which is proportional to F00).
ACCEPTED = ("intensity",)
#: Names of the measurement dimension in the stacks pbrdf-cl makes (``open_stack``,
#: ``imagestack.synthetic_stack``, ``camera.camera_dataset``; a dict's default ``mdim``).
MEASUREMENT_DIMS = ("m", "measurement")
#: An image's measurement axis, found without a shared angle to show it, is refused when the
#: per-pixel angles change between neighbours along another axis at least AXIS_STEP_RATIO times
#: more (and by AXIS_STEP_MIN degrees or more) than along it: neighbouring pixels see nearly the
#: same geometry, successive measurements do not (:func:`_check_measurement_axis`).
AXIS_STEP_RATIO = 10.0
AXIS_STEP_MIN = 1.0
#: Neighbours per axis of the corner of the stack that check reads.
AXIS_SAMPLE = 9


def _axis_of_lengths(shape, lengths, dims=None):
    """The axis of ``shape`` (dop's) holding the measurements, from the lengths of the shared
    (1-d) angles ``lengths`` (name -> length); None without any.  The last axis when its length
    matches (the documented layout), else the one axis that does; one-line errors for lengths
    that differ, match no axis, or match several (ambiguous)."""
    if not lengths:
        return None
    if len(set(lengths.values())) > 1:
        given = ", ".join(f"{n} {m}" for n, m in lengths.items())
        raise ValueError(f"data: the shared angles differ in length ({given}); give each one value per measurement")
    (name, m), = list(lengths.items())[:1]
    axes = [a for a, size in enumerate(shape) if size == m]
    named = (lambda a: f"{dims[a]!r}") if dims else (lambda a: str(a))
    if not axes:
        raise ValueError(f"data: {name} has {m} values (one per measurement) but no axis of dop {tuple(shape)} has "
                         f"{m}; give dop's measurements along one axis (last: shape (..., {m}))")
    if len(shape) - 1 in axes:
        return len(shape) - 1
    if len(axes) > 1:
        which = ", ".join(map(named, axes))
        raise ValueError(f"data: dop {tuple(shape)} has {len(axes)} axes of length {m} ({which}), the number of "
                         f"{name} values: which holds the measurements is ambiguous; put them last (dop of shape "
                         f"(..., {m}))")
    return axes[0]


def _check_measurement_axis(samples, axis, dims, shape):
    """Refuse a measurement axis (``axis`` of dop's ``dims``/``shape``) that the per-pixel angles
    contradict: ``samples`` maps each angle to a corner of it (up to AXIS_SAMPLE values per
    axis, dop's axes in order, size 1 where the angle does not vary).  Only for images (two or
    more pixel axes), whose neighbouring pixels see nearly the same geometry."""
    if len(shape) < 3:
        return
    steps = np.zeros(len(shape))
    for name, a in samples.items():
        for ax in range(a.ndim):
            if a.shape[ax] < 2:
                continue
            d = np.abs(np.diff(a, axis=ax))
            if name == "phi":
                d = np.minimum(d % 360.0, 360.0 - d % 360.0)
            steps[ax] = max(steps[ax], float(np.median(d)))
    worst = max((ax for ax in range(len(shape)) if ax != axis), key=lambda ax: steps[ax])
    if steps[worst] >= AXIS_STEP_MIN and steps[worst] >= AXIS_STEP_RATIO * steps[axis]:
        def name(ax):
            return f"axis {ax} ({f'{dims[ax]!r}, ' if dims else ''}{shape[ax]} values)"
        fix = f"np.moveaxis(a, {worst}, -1)" + (f" (ds.transpose(..., {dims[worst]!r}) for a Dataset)" if dims else "")
        raise ValueError(
            f"data: dop's {name(axis)} is taken for the measurements, but the per-pixel angles change along it as "
            f"across an image's pixels (neighbours differ by {steps[axis]:.2g} degrees, median) and along "
            f"{name(worst)} as between measurements ({steps[worst]:.3g} degrees); put the measurements last: "
            f"{fix} for dop and the per-pixel angles (or give the angles shared, shape (M,))")


class _Source:
    """The input stack: variables as arrays (numpy or lazy xarray/dask) of the shape of ``dop``
    (leading pixel dimensions, then M measurements) or, for the angles, shared (M,).

    The measurement axis of ``dop`` is the one the shared (1-d) angles run along (a Dataset's
    dimension, or an array's axis of their length: the last when it has it); without shared
    angles, a Dataset's dimension named ``m`` or ``measurement``, else the last; images whose
    per-pixel angles contradict it are refused (:func:`_check_measurement_axis`).  It is moved
    last; the pixel dimensions keep their order."""

    def __init__(self, data):
        import xarray as xr
        if isinstance(data, (str,)) or hasattr(data, "__fspath__"):
            data = open_stack(data)
        self.coords = {}  # name -> (dims, values, attrs): the coordinates over pixel dimensions only
        if isinstance(data, xr.Dataset):
            if "dop" not in data:
                raise ValueError(f"data: no 'dop' variable; the dataset has {', '.join(map(str, data.data_vars))}")
            dop = data["dop"]
            if dop.ndim < 2:
                raise ValueError(f"data: dop must have pixel dimensions and a measurement dimension, got dims "
                                 f"{dop.dims}")
            for name in VARIABLES[1:]:
                if name in data:
                    extra = set(data[name].dims) - set(dop.dims)
                    if extra:
                        raise ValueError(f"data: {name} has dimensions {sorted(extra)} that dop does not have")
            shared = {a: str(data[a].dims[0]) for a in ANGLES if a in data and data[a].ndim == 1
                      and data[a].size > 1}
            if len(set(shared.values())) > 1:
                given = ", ".join(f"{a} over {d!r}" for a, d in shared.items())
                raise ValueError(f"data: the shared angles lie along different dimensions ({given}); give them "
                                 "along the one measurement dimension")
            dims = tuple(map(str, dop.dims))
            if shared:
                mdim = next(iter(shared.values()))
            else:
                named = [d for d in dims if d in MEASUREMENT_DIMS]
                mdim = named[0] if len(named) == 1 else dims[-1]
                samples = {}
                for a in ANGLES:
                    if a in data and data[a].ndim >= 1:
                        v = data[a].isel({d: slice(0, AXIS_SAMPLE) for d in data[a].dims})
                        v = v.transpose(*[d for d in dims if d in v.dims])
                        samples[a] = np.asarray(v.values, float).reshape([v.sizes.get(d, 1) for d in dims])
                _check_measurement_axis(samples, dims.index(mdim), dims, tuple(dop.shape))
            if mdim != dims[-1]:
                dop = dop.transpose(*[d for d in dims if d != mdim], mdim)
            self.dims = tuple(map(str, dop.dims[:-1]))
            self.mdim = str(dop.dims[-1])
            for cname, c in data.coords.items():
                if c.ndim and set(c.dims) <= set(self.dims):
                    self.coords[str(cname)] = (tuple(map(str, c.dims)), np.asarray(c.values), dict(c.attrs))
            vars_ = {}
            for name in VARIABLES:
                if name not in data:
                    continue
                v = dop if name == "dop" else data[name]
                if name != "mask" and v.dims == (self.mdim,):
                    vars_[name] = v.values
                else:  # kept lazy: rows() reads a block of rows at a time
                    vars_[name] = v
            self._full_dims = {"mask": self.dims}
            self._dop_dims = tuple(map(str, dop.dims))
            self.vars = vars_
            unread = [str(n) for n, v in data.data_vars.items()
                      if n not in VARIABLES and n not in ACCEPTED and self.mdim in v.dims]
            if unread:
                import warnings
                from ..io.measurements import DataWarning
                warnings.warn(f"data: variable{'s' if len(unread) > 1 else ''} {', '.join(unread)} "
                              f"over the measurements not read (fit_batch reads {', '.join(VARIABLES)})",
                              DataWarning, stacklevel=4)
            self.shape = tuple(dop.shape[:-1])
            self.M = int(dop.shape[-1])
        elif isinstance(data, dict):
            unknown = set(data) - set(VARIABLES) - set(ACCEPTED) - {"mdim", "dims"}
            if unknown:
                raise ValueError(f"data: unknown variable {sorted(unknown)[0]!r}; variables are {', '.join(VARIABLES)}")
            if "dop" not in data:
                raise ValueError("data: no 'dop' array")
            arrays = {}
            for name in VARIABLES:
                v = data.get(name)
                if v is not None:
                    arrays[name] = v if hasattr(v, "shape") else np.asarray(v, float)
            dop = arrays["dop"]
            if len(dop.shape) < 2:
                raise ValueError(f"data: dop must have shape (..., M): pixel dimensions then M measurements, "
                                 f"got shape {tuple(dop.shape)}")
            nd = len(dop.shape)
            lengths = {a: int(arrays[a].shape[0]) for a in ANGLES
                       if a in arrays and len(arrays[a].shape) == 1 and arrays[a].shape[0] > 1}
            axis = _axis_of_lengths(tuple(dop.shape), lengths)
            if axis is None:
                axis = nd - 1
                samples = {a: np.asarray(arrays[a][(slice(0, AXIS_SAMPLE),) * len(arrays[a].shape)], float)
                           .reshape((1,) * (nd - len(arrays[a].shape)) + tuple(min(s, AXIS_SAMPLE)
                                                                               for s in arrays[a].shape))
                           for a in ANGLES if a in arrays and 1 < len(arrays[a].shape) <= nd}
                _check_measurement_axis(samples, axis, None, tuple(dop.shape))
            if axis != nd - 1:  # the measurements last; every array over dop's axes moved alike
                for name, v in list(arrays.items()):
                    if name == "mask" or (name in ANGLES and len(v.shape) == 1) or len(v.shape) == 0:
                        continue
                    if len(v.shape) > nd:
                        continue  # refused below, with its shape
                    v = v.reshape((1,) * (nd - len(v.shape)) + tuple(v.shape))
                    arrays[name] = np.moveaxis(v, axis, -1)
                dop = arrays["dop"]
            self.shape, self.M = tuple(dop.shape[:-1]), int(dop.shape[-1])
            nd = len(self.shape)
            self.dims = tuple(data.get("dims") or (("y", "x") if nd == 2 else ("pixel",) if nd == 1
                                                    else tuple(f"dim_{i}" for i in range(nd))))
            self.mdim = data.get("mdim", "measurement")
            self.vars = {"dop": dop}
            for name in VARIABLES[1:]:
                v = arrays.get(name)
                if v is None:
                    continue
                full = self.shape if name == "mask" else tuple(dop.shape)
                if name != "mask" and tuple(v.shape) in ((self.M,), ()) and name in ANGLES:
                    v = np.broadcast_to(np.asarray(v, float), (self.M,))
                else:
                    try:
                        np.broadcast_shapes(tuple(v.shape), full)
                    except ValueError:
                        raise ValueError(f"data: {name} of shape {tuple(v.shape)} does not broadcast to "
                                         f"{'the pixel shape' if name == 'mask' else 'dop'}'s shape {full}") from None
                self.vars[name] = v
        else:
            raise ValueError(f"data must be an xarray.Dataset, a dict of arrays or a path to a stack, got "
                             f"{type(data).__name__}")
        for a in ANGLES[:2]:
            if a not in self.vars:
                raise ValueError(f"data: no {a!r} (degrees): give it shared, shape ({self.M},), or per pixel")
        #: whether phi was given (without it every measurement is taken in plane, phi = 180)
        self.phi_given = "phi" in self.vars
        if not self.phi_given:
            self.vars["phi"] = np.full(self.M, 180.0)
        if "s0" in self.vars:
            if "f00" in self.vars:
                raise ValueError("data: give f00 or s0, not both")
            self.vars["f00"] = self.vars.pop("s0")
        if "f00_std" in self.vars and "f00" not in self.vars:
            raise ValueError("data: f00_std is given without f00")
        for name in ("dop_std", "f00_std"):
            v = self.vars.get(name)
            if v is not None and np.ndim(v) == 0 and np.isnan(float(np.asarray(v))):
                raise ValueError(f"data: {name} is NaN (one value for every measurement): give the noise std (> 0)"
                                 + (", or leave dop_std out to estimate each pixel's noise from its residuals"
                                    if name == "dop_std" else ""))
        if len(self.dims) != len(self.shape):
            raise ValueError(f"data: dims {self.dims} do not match dop's pixel dimensions {self.shape}")
        self.shared = all(np.ndim(self.vars[a]) == 1 for a in ANGLES)
        self.n_pixels = int(np.prod(self.shape, dtype=np.int64))
        if self.M < 2:
            raise ValueError(f"data: dop has {self.M} measurement per pixel; a fit needs several")

    def rows(self, r0, r1):
        """The pixels of rows r0..r1 of the first pixel dimension, flat: dict name -> (p, M) float64
        (angles (M,) when shared; mask (p,))."""
        import xarray as xr
        out = {}
        for name, v in self.vars.items():
            if np.ndim(v) == 1 and name in ANGLES:
                out[name] = np.asarray(v, float)
                continue
            full = self.shape if name == "mask" else self.shape + (self.M,)
            a0, a1 = r0, r1
            if isinstance(v, xr.DataArray):  # read only these rows, then broadcast
                dims = self.dims if name == "mask" else self._dop_dims
                part = v.isel({dims[0]: slice(r0, r1)}) if dims[0] in v.dims else v
                a = np.asarray(part.transpose(*[d for d in dims if d in part.dims]).values)
                v = a.reshape([part.sizes[d] if d in part.dims else 1 for d in dims])
                a0, a1 = 0, r1 - r0
            if len(v.shape) < len(full):
                v = v.reshape((1,) * (len(full) - len(v.shape)) + tuple(v.shape))
            part = v[a0:a1] if v.shape[0] != 1 else v
            part = np.asarray(part)
            block = (r1 - r0,) + full[1:]
            part = np.broadcast_to(part, block)
            out[name] = (part.reshape(-1) if name == "mask" else part.reshape(-1, self.M))
            out[name] = out[name].astype(bool if name == "mask" else np.float64, copy=False)
        return out


def open_stack(path):
    """An image stack from a file, as the ``xarray.Dataset`` :func:`fit_batch` takes.

    Parameters
    ----------
    path : str or path
        ``.npz`` (arrays named as :func:`fit_batch`'s variables: ``dop`` of shape (y, x, M), the
        angles of shape (M,) or dop's, scalars or pixel maps for the rest; with shared angles of
        shape (M,) the measurements may lie along any one axis of dop of length M, which is
        named ``m``), ``.nc`` (netCDF, opened lazily) or ``.zarr`` (opened lazily: blocks of
        rows are read one at a time).

    Returns
    -------
    xarray.Dataset

    Raises
    ------
    ValueError
        A missing file, an unknown format or no ``dop``; arrays of no usable shape in an ``.npz``
        (coordinates, light positions) are left out with a :class:`pbrdf_cl.DataWarning`.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl, tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "stack.npz")
    >>> np.savez(path, dop=np.full((4, 5, 30), 0.2), theta_i=np.full(30, 40.0), theta_r=np.linspace(5, 80, 30))
    >>> pbrdf_cl.fitting.batch.open_stack(path).dop.dims
    ('y', 'x', 'm')
    """
    import pathlib
    import xarray as xr
    p = pathlib.Path(path)
    if not p.exists():
        raise ValueError(f"stack {str(p)!r} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        if any(k.endswith(".dims") for k in arrays):  # written by pbrdf_cl.io.imagestack.save_stack
            from ..io.imagestack import load_stack
            return load_stack(p)
        if "dop" not in arrays:
            raise ValueError(f"{p}: no 'dop' array (found {', '.join(arrays)})")
        shape = arrays["dop"].shape
        nd = len(shape)
        if nd < 2:
            raise ValueError(f"{p}: dop must have pixel axes and a measurement axis, got shape {shape}")
        # the measurement axis: the one the shared angles' length names (the last by default)
        axis = _axis_of_lengths(shape, {a: arrays[a].size for a in ANGLES
                                        if a in arrays and arrays[a].ndim == 1 and arrays[a].size > 1})
        axis = nd - 1 if axis is None else axis
        lead = ("y", "x") if nd == 3 else tuple(f"dim_{i}" for i in range(nd - 1))
        dims = lead[:axis] + ("m",) + lead[axis:]
        pixels = tuple(n for i, n in enumerate(shape) if i != axis)
        ds = xr.Dataset()
        skipped = []
        for k, a in arrays.items():
            if a.shape == shape:
                ds[k] = (dims, a)
            elif a.ndim == 1 and a.size == shape[axis]:
                ds[k] = (("m",), a)
            elif a.shape == pixels:
                ds[k] = (lead, a)
            elif a.ndim == 0:
                ds[k] = ((), a)
            else:
                skipped.append(f"{k} {a.shape}")
        if skipped:  # coordinates, light positions, ...: not inputs of the fit
            import warnings
            from ..io.measurements import DataWarning
            warnings.warn(f"{p}: arrays not read (their shapes fit neither dop {shape}, its pixels "
                          f"nor its measurements): {', '.join(skipped)}", DataWarning, stacklevel=2)
        return ds
    if suffix in (".nc", ".h5", ".netcdf"):
        return xr.open_dataset(p)
    if suffix == ".zarr" or (p / ".zgroup").exists() or (p / "zarr.json").exists():
        return xr.open_zarr(p)
    raise ValueError(f"stack {str(p)!r}: unknown format {suffix!r}; use .npz, .nc or .zarr")


def _check_block(block, r0, source):
    """Validate a block's values; errors name the variable and the first offending index (of the
    full stack)."""
    def where(name, flat_index):
        if np.ndim(block[name]) == 1 and name in ANGLES:
            return f"[{flat_index}]"
        pix, m = divmod(int(flat_index), source.M) if name != "mask" else (int(flat_index), None)
        idx = list(np.unravel_index(pix, (block[name].shape[0] // max(1, int(np.prod(source.shape[1:]))),)
                                    + source.shape[1:]))
        idx[0] += r0
        if m is not None:
            idx.append(m)
        return str([int(i) for i in idx])

    def first(name, bad):
        i = int(np.argmax(bad.reshape(-1)))
        return f"{float(block[name].reshape(-1)[i])!r} at index {where(name, i)}"
    dop = block["dop"]
    bad = ~(np.isnan(dop) | ((dop >= 0) & (dop <= 1)))
    if bad.any():
        raise ValueError(f"dop must be in [0, 1] (NaN for a missing measurement), got {first('dop', bad)}")
    for name in ("theta_i", "theta_r"):
        a = block[name]
        bad = ~(np.isfinite(a) & (a >= 0) & (a < 90))
        if bad.any():
            raise ValueError(f"{name} must be in [0, 90) degrees, got {first(name, bad)}")
    a = block["phi"]
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(f"phi must be finite, got {first('phi', bad)}")
    for name, rule, ok in (("dop_std", "> 0 (NaN for a missing measurement)", lambda a: np.isnan(a) | (a > 0)),
                           ("f00", ">= 0 (NaN for a missing measurement)", lambda a: np.isnan(a) | (a >= 0)),
                           ("f00_std", "> 0", lambda a: np.isnan(a) | (a > 0))):
        if name in block:
            bad = ~ok(block[name])
            if bad.any():
                raise ValueError(f"{name} must be {rule}, got {first(name, bad)}")
    # a NaN std marks a missing measurement only where the value is missing too: a measured value
    # without its std is refused (as pbrdf_cl.fit refuses it), not silently left out
    for name, value in (("dop_std", "dop"), ("f00_std", "f00")):
        if name in block and value in block:
            bad = np.isnan(block[name]) & ~np.isnan(block[value])
            if bad.any():
                i = int(np.argmax(bad.reshape(-1)))
                raise ValueError(f"{name} is NaN at index {where(name, i)} where {value} is "
                                 f"{float(block[value].reshape(-1)[i])!r}: give that measurement's std (> 0), or "
                                 f"NaN in {value} too to leave it out as missing")


@dataclass
class _Setup:
    """The checked fit settings of :func:`fit_batch`."""
    model: str
    shadowing: str
    free: list
    lo: np.ndarray
    hi: np.ndarray
    base: dict
    fixed: dict
    axes: dict
    use_f00: bool
    ks_bounds: tuple
    n_starts: int
    sigma_known: bool
    noise_floor: float


def _regions(axes, free):
    """The grid points (flat index over (n, k, sigma, ks, kd, c) of ``axes``, ks of size 1) ordered
    region by region, a region being one half of every free axis (2^d boxes); returns (order,
    rstart), region r holding order[rstart[r]:rstart[r + 1]]."""
    names = ("n", "k", "sigma", "ks", "kd", "c")
    sizes = [axes[n].size for n in names]
    idx = np.indices(sizes).reshape(6, -1)
    region = np.zeros(idx.shape[1], np.int64)
    for axis, name in enumerate(names):
        if name in free and sizes[axis] > 1:
            region = region * 2 + (idx[axis] >= sizes[axis] // 2)
    counts = np.bincount(region)
    rstart = np.concatenate([[0], np.cumsum(counts[counts > 0])])
    return np.argsort(region, kind="stable").astype(np.int32), rstart.astype(np.int32)


def _grid_values(setup):
    """The grid's parameter values (every parameter: free on its axis, the others fixed) as arrays
    for the tables: dict name -> 1-d array."""
    v = {}
    for name in ("n", "k", "sigma", "ks", "kd", "c"):
        v[name] = setup.axes[name] if name in setup.axes else np.array([setup.base[name]], float)
    return v


def _grid_points(setup, order, flat):
    """Parameter vectors (over ``setup.free``) of region-ordered grid indices ``flat``."""
    v = _grid_values(setup)
    sizes = [v[n].size for n in ("n", "k", "sigma", "ks", "kd", "c")]
    unr = np.unravel_index(order[flat], sizes)
    names = ("n", "k", "sigma", "ks", "kd", "c")
    return np.stack([v[n][unr[names.index(n)]] for n in setup.free], axis=-1)


class _Block:
    """One block of pixels prepared for the stages: flat (p, M) arrays, weights, validity."""

    def __init__(self, raw, setup, lanes):
        self.raw, self.setup, self.lanes = raw, setup, lanes
        self.p = raw["dop"].shape[0]
        self.P = -(-self.p // lanes) * lanes  # padded
        dop = raw["dop"]
        mask = raw.get("mask", np.ones(self.p, bool))
        std = raw.get("dop_std")
        valid = np.isfinite(dop) & mask[:, None]
        if std is not None:
            valid &= np.isfinite(std)
        if setup.use_f00:
            valid &= np.isfinite(raw["f00"])
        self.mask = mask
        self.valid = valid
        self.shared = all(raw[a].ndim == 1 for a in ANGLES)
        self.angles = [raw[a] if self.shared else np.broadcast_to(raw[a], dop.shape) for a in ANGLES]
        self.obs = np.where(valid, dop, 0.0)
        w = valid / (std ** 2 if std is not None else 1.0)
        self.w = np.where(valid, w, 0.0)
        if setup.use_f00:
            f00 = raw["f00"]
            fstd = raw.get("f00_std")
            if fstd is None:
                fstd = F00_REL_STD * np.maximum(np.where(valid, f00, 1.0), 1e-300)
            self.fobs = np.where(valid, f00, 0.0)
            self.fw = np.where(valid, 1.0 / np.where(valid, fstd, 1.0) ** 2, 0.0)
        else:
            self.fobs = self.fw = None
        self.count = valid.sum(axis=1)
        self.distinct = self._distinct_geometries()
        self.noise_floor = self._noise_floor(setup.noise_floor)

    def _noise_floor(self, floor):
        """Each pixel's floor of the noise estimate without dop_std, as :func:`pbrdf_cl.fit`'s
        (:func:`pbrdf_cl.fitting.inversion.dop_noise_floor`): the rounding error of the DOP resolution
        of its valid values (invalid ones are 0 in ``obs``, exact at any resolution), at least
        ``floor``."""
        return np.maximum(floor, dop_resolution(self.obs, axis=1) / np.sqrt(12.0))

    def _distinct_geometries(self):
        """Distinct valid (theta_i, theta_r, phi) per pixel."""
        ti, tr, ph = (np.broadcast_to(a, self.valid.shape) for a in self.angles)
        key = np.stack([ti, tr, ph], axis=-1)
        key = np.where(self.valid[..., None], key, np.nan)
        s = np.ascontiguousarray(key).view(np.dtype((np.void, 24)))[..., 0]
        s = np.sort(s, axis=1)
        distinct = 1 + (s[:, 1:] != s[:, :-1]).sum(axis=1)
        return distinct - (~self.valid).any(axis=1)

    def subset(self, idx):
        """The block of pixels ``idx`` (repeats allowed) of this one."""
        raw = {k: (v if (v.ndim == 1 and k in ANGLES) else v[idx]) for k, v in self.raw.items()}
        return _Block(raw, self.setup, self.lanes)

    def padded(self, a, fill=0.0):
        """(p, ...) -> (P, ...) padded with ``fill``."""
        out = np.full((self.P,) + a.shape[1:], fill, a.dtype if a.dtype != bool else float)
        out[:self.p] = a
        return out

    def pixel_major(self, a, dtype):
        """(p, M) -> (M, P) contiguous in ``dtype`` (the kernels' layout)."""
        return np.ascontiguousarray(self.padded(a).T, dtype=dtype)


# ---- grid stage -------------------------------------------------------------------------------

def _device_grid(eng, setup, blk, order, rstart):
    """(best (R, p), arg (R, p)): each region's minimum and its region-ordered grid index."""
    v = _grid_values(setup)
    if blk.shared:
        return _table_minima(eng, blk, _table_dop(eng, setup, blk.angles, v, order), rstart)
    shadow = reference.SHADOWING[setup.shadowing]
    dtype = "float32"
    npdt = DTYPES[dtype]
    R = rstart.size - 1
    P, M = blk.P, blk.valid.shape[1]
    w = blk.pixel_major(blk.w, npdt)
    obs = blk.pixel_major(blk.obs, npdt)
    best = np.empty((R, P), npdt)
    arg = np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size * v["ks"].size, v["kd"].size * v["c"].size
    ng = M * P
    if ng * max(nnk, nm, ni) >= 2 ** 31:
        raise ValueError("internal: a block of pixels too large for 32-bit table indices")
    tab = eng.program("pbrdf_tables.cl", dtype, {"PBRDF_SHADOWING": shadow})
    geo = [eng.to_device(blk.pixel_major(a, np.float64), npdt) for a in blk.angles]

    def table(kname, outs, p1, p2, *extra):
        np_ = p1.size * p2.size
        bufs = [eng.empty(ng * np_ * np.dtype(npdt).itemsize) for _ in range(outs)]
        eng.launch(tab[kname], (ng, np_), *bufs, np.int32(ng), np.int32(1), np.int32(ng), *geo,
                   eng.to_device(p1, npdt), eng.to_device(p2, npdt), np.int32(p2.size), *extra)
        return bufs
    s_, d_ = table("fresnel_table", 2, v["n"], v["k"])
    sc, = table("scale_table", 1, v["sigma"], v["ks"], npdt(-1))
    fd, = table("diffuse_table", 1, v["kd"], v["c"], npdt(2))
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": shadow, "PB_NNK": nnk, "PB_NM": nm,
                                                 "PB_NI": ni})
    eng.launch(prog["batch_grid_factors"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P), np.int32(M),
               s_, d_, sc, fd, eng.to_device(order, np.int32), eng.to_device(rstart, np.int32), np.int32(R),
               eng.to_device(obs, npdt), eng.to_device(w, npdt), local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p], arg[:, :blk.p].astype(np.int64)


def _table_minima(eng, blk, T, rstart):
    """Each region's least objective over the points of a DOP table ``T`` (G, M) at the shared
    geometry, for every pixel of ``blk``: (best (R, p), arg (R, p), the index into T), region r
    holding T[rstart[r]:rstart[r + 1]].  The objective is expanded as sum w obs^2 - 2 sum w obs T
    + sum w T^2: on a device a float32 kernel (batch_grid_table) that streams T past the pixels'
    data; on the numpy backend one float64 matrix product."""
    R = rstart.size - 1
    if eng.is_numpy:
        w, obs = blk.w, blk.obs
        part = np.concatenate([w * obs, w], axis=1) @ np.concatenate([-2.0 * T, T * T], axis=1).T
        part += np.einsum("pm,pm->p", w, obs * obs)[:, None]
        arg = np.stack([rstart[r] + np.argmin(part[:, rstart[r]:rstart[r + 1]], axis=1) for r in range(R)])
        return np.take_along_axis(part.T, arg, axis=0), arg
    dtype = "float32"
    npdt = DTYPES[dtype]
    P, M = blk.P, blk.valid.shape[1]
    w, obs = blk.pixel_major(blk.w, npdt), blk.pixel_major(blk.obs, npdt)
    best, arg = np.empty((R, P), npdt), np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    a2 = np.ascontiguousarray(-2.0 * w * obs, npdt)
    c = np.ascontiguousarray(np.einsum("mp,mp->p", w.astype(float), obs.astype(float) ** 2), npdt)
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": reference.SHADOWING[blk.setup.shadowing]})
    eng.launch(prog["batch_grid_table"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P), np.int32(M),
               eng.to_device(np.ascontiguousarray(T, npdt), npdt), eng.to_device(rstart, np.int32), np.int32(R),
               eng.to_device(a2, npdt), eng.to_device(w, npdt), eng.to_device(c, npdt), local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p].astype(float), arg[:, :blk.p].astype(np.int64)


def _table_dop(eng, setup, angles, v, order):
    """DOP of every grid point at the shared geometry, (G, M) in region order (the engine's
    per-point path: pbrdf.h)."""
    ti, tr, ph = angles
    sizes = [v[n].size for n in ("n", "k", "sigma", "ks", "kd", "c")]
    unr = np.unravel_index(order, sizes)
    p = {n: v[n][unr[i]][:, None] for i, n in enumerate(("n", "k", "sigma", "ks", "kd", "c"))}
    out = pointwise.dop(ti[None, :], tr[None, :], ph[None, :], shadowing=setup.shadowing, dtype="float32", engine=eng,
                  **p)
    return np.ascontiguousarray(out, np.float32)


def _numpy_grid(setup, blk, order, rstart):
    """:func:`_device_grid` with ``reference.py`` (dense._NumpyTables, float64), pixel by pixel."""
    from ..compute.dense import _NumpyTables
    v = _grid_values(setup)
    R = rstart.size - 1
    sizes = [v[n].size for n in ("n", "k", "sigma", "ks", "kd", "c")]
    nnk, nm, ni = sizes[0] * sizes[1], sizes[2] * sizes[3], sizes[4] * sizes[5]
    best = np.full((R, blk.p), np.inf)
    arg = np.zeros((R, blk.p), np.int64)
    M = blk.valid.shape[1]
    shared = None
    for i in range(blk.p):
        if blk.count[i] == 0:
            continue
        if blk.shared and shared is None or not blk.shared:
            ang = [a if blk.shared else a[i] for a in blk.angles]
            t = _NumpyTables(setup.shadowing, "dop", *ang, v)
            T = t.combine(t.sum.reshape(M, nnk, 1, 1), t.diff.reshape(M, nnk, 1, 1), t.dif.reshape(M, 1, 1, ni),
                          t.scale.reshape(M, 1, nm, 1)).reshape(M, -1)[:, order]
            if blk.shared:
                shared = T
        T = shared if blk.shared else T
        sse = blk.w[i] @ (T - blk.obs[i][:, None]) ** 2
        for r in range(R):
            part = sse[rstart[r]:rstart[r + 1]]
            j = int(np.argmin(part))
            best[r, i], arg[r, i] = part[j], rstart[r] + j
    return best, arg


# ---- LM stage -----------------------------------------------------------------------------------

def _map_ks(X, names, func):
    """A copy of the parameter vectors X with ``func`` applied to their ks coordinate (if any)."""
    X = np.array(X, float)
    if "ks" in names:
        j = names.index("ks")
        X[..., j] = func(X[..., j])
    return X


def _internal(X, names):
    """Parameter vectors to the descent's coordinates (ks as log ks)."""
    return _map_ks(X, names, np.log)


def _external(X, names):
    """The descent's coordinates back to parameter vectors."""
    return _map_ks(X, names, np.exp)


def _bounds(setup, names):
    lo = [np.log(setup.ks_bounds[0]) if n == "ks" else setup.lo[setup.free.index(n)] for n in names]
    hi = [np.log(setup.ks_bounds[1]) if n == "ks" else setup.hi[setup.free.index(n)] for n in names]
    return np.array(lo), np.array(hi)


def _device_lm(eng, setup, blk, X0, names, dtype, iterations, intensity, corner=None):
    """The LM kernel from starts X0 (S, p, D) (external coordinates); returns (X (S, p, D), sse (S, p),
    JtJ (S, p, D, D) in internal coordinates, settled (S, p)).  ``corner`` (one of
    :data:`CORNERS`): descend in the corner's coordinates (:func:`_corner_polish`; JtJ then in those)."""
    npdt = DTYPES[dtype]
    S, p, D = X0.shape
    P = blk.P
    Q = S * P
    lanes = eng.lm_lanes[dtype]
    if corner:
        lo, hi = _corner_bounds(setup, names, corner)
        to_internal, to_external = (lambda X, nm: _to_corner(X, nm, corner)), (lambda U, nm: _from_corner(U, nm, corner))
    else:
        lo, hi = _bounds(setup, names)
        to_internal, to_external = _internal, _external
    slot = {n: (names.index(n) if n in names else -1) for n in ("n", "k", "sigma", "kd", "c", "ks")}
    defines = {"PB_VECTOR_REAL": lanes, "PB_D": D, "PBRDF_SHADOWING": reference.SHADOWING[setup.shadowing],
               **{f"PB_X_{n.upper()}": s for n, s in slot.items()}}
    geodesic = GEODESIC and not intensity
    if intensity:
        defines["PB_INTENSITY"] = None
    if geodesic:
        defines["PB_GEODESIC"] = None

    for n in (corner.logged if corner else ()):
        defines[f"PB_LOG_{n.upper()}"] = None
    if not blk.shared:
        defines["PB_PIXEL_GEOMETRY"] = None
    prog = eng.program("pbrdf_batch.cl", dtype, defines)
    Xi = np.zeros((D, S, P))
    Xi[:, :, :p] = np.moveaxis(to_internal(X0, names), -1, 0)
    Xi[:, :, p:] = ((lo + hi) / 2)[:, None, None]
    Xi = np.ascontiguousarray(Xi.reshape(D, Q), npdt)
    base = np.array([setup.base.get(n, 0.0) for n in ("n", "k", "sigma", "ks", "kd", "c")], npdt)
    import pyopencl as cl
    bX = cl.Buffer(eng.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=Xi)  # in and out
    sse, jtj, settled = np.empty(Q, npdt), np.empty((D * D, Q), npdt), np.empty(Q, npdt)
    bsse, bjtj, bset = eng.empty(sse.nbytes), eng.empty(jtj.nbytes), eng.empty(settled.nbytes)
    # the geometry of every measurement once (reference.geometry: the mirror of pb_geometry)
    g = reference.geometry(*(blk.angles if blk.shared else [blk.pixel_major(a, np.float64) for a in blk.angles]))
    geo = eng.to_device(np.stack([g.cti, g.sti, g.ctr, g.str, g.cb, g.sb, g.tan2a]), npdt)
    obs, w = eng.to_device(blk.pixel_major(blk.obs, npdt), npdt), eng.to_device(blk.pixel_major(blk.w, npdt), npdt)
    if intensity:
        fobs = eng.to_device(blk.pixel_major(blk.fobs, npdt), npdt)
        fw = eng.to_device(blk.pixel_major(blk.fw, npdt), npdt)
    else:
        fobs = fw = eng.to_device(np.zeros(1, npdt), npdt)
    M = blk.valid.shape[1]
    eng.launch(prog["batch_lm"], (Q // lanes,), bX, bsse, bjtj, bset, np.int32(Q), np.int32(P), np.int32(M),
               np.int32(iterations), eng.to_device(base, npdt), eng.to_device(lo, npdt), eng.to_device(hi, npdt),
               geo, obs, w, fobs, fw, eng.empty(2 * M * (D + 1) * Q * np.dtype(npdt).itemsize if geodesic else 1),
               local_size=(LOCAL_SIZE,))
    eng.read(bX, Xi)
    eng.read(bsse, sse)
    eng.read(bjtj, jtj)
    eng.read(bset, settled)
    X = to_external(np.moveaxis(Xi.reshape(D, S, P)[:, :, :p], 0, -1), names)
    jtj = np.moveaxis(jtj.reshape(D, D, S, P)[..., :p], (0, 1), (-2, -1)).astype(float)
    return X, sse.reshape(S, P)[:, :p].astype(float), jtj, settled.reshape(S, P)[:, :p] > 0


class _PixelResiduals:
    """Weighted residual rows of the reference model for many pixels (the numpy backend): rows
    of a (B, D) batch belong to pixels ``pix`` repeated ``B // len(pix)`` times each, as
    :func:`fd_jacobian` lays them out."""

    def __init__(self, setup, blk, names, pix, intensity, weights=None):
        self.setup, self.blk, self.names, self.pix, self.intensity = setup, blk, names, pix, intensity
        self.w = blk.w if weights is None else weights  # of the DOP residuals

    def rows(self, X):
        rep = X.shape[0] // self.pix.size
        pix = np.repeat(self.pix, rep)
        blk, setup = self.blk, self.setup
        ang = [a[None, :] if blk.shared else a[pix] for a in blk.angles]
        g = reference.geometry(*ang)
        p = dict(setup.base)
        ext = _external(X, self.names)
        for j, n in enumerate(self.names):
            p[n] = ext[:, j:j + 1]
        if self.intensity:
            p["kd"] = p["kd"] * p["ks"]
        f = reference.fresnel(p["n"], p["k"], g.cb, g.sb)
        variant = reference.SHADOWING[setup.shadowing]
        log_k = reference.log_specular_scale(g, p["sigma"], p["ks"], reference.shadowing_factor(g, p["sigma"], variant))
        fd = reference.diffuse(g, p["kd"], p["c"])
        r = (reference.dop(f, log_k, fd) - blk.obs[pix]) * np.sqrt(self.w[pix])
        if self.intensity:
            r = np.concatenate([r, (reference.brdf(f, log_k, fd) - blk.fobs[pix]) * np.sqrt(blk.fw[pix])], axis=1)
        return np.where(np.isfinite(r), r, 1e150)


def _numpy_lm(setup, blk, X0, names, iterations, intensity):
    """:func:`_device_lm` on the numpy backend: :func:`_lm_batch` over every pixel x start."""
    S, p, D = X0.shape
    lo, hi = _bounds(setup, names)
    pix = np.tile(np.arange(p), S)
    res = _PixelResiduals(setup, blk, names, pix, intensity)
    Xi = _internal(X0, names).reshape(S * p, D)
    X, sse, _ = lm_batch(res.rows, Xi, lo, hi, iterations)
    r, J = fd_jacobian(res.rows, X, lo, hi)
    sse = np.einsum("pm,pm->p", r, r)
    jtj = np.einsum("pim,pjm->pij", J, J)
    return (_external(X, names).reshape(S, p, D), sse.reshape(S, p), jtj.reshape(S, p, D, D),
            np.ones((S, p), bool))


#: Two corners of the model where a descent in the parameters crawls along a valley onto bounds:
#:
#: - "index": n -> 1, k -> 0, kd -> 0, an index-matched surface where the Fresnel terms and the
#:   diffuse term vanish together and the DOP depends on their ratio (and on sigma and c); pixels
#:   of nearly unpolarised light fall into it.
#: - "mirror": sigma at its lower bound with kd -> 0, a near-mirror with a faint diffuse term: off
#:   the specular direction the specular lobe falls as exp(-tan^2(alpha) / (2 sigma^2)) and the
#:   DOP there depends on log kd against 1 / sigma^2, so the fit drives kd towards 0 by decades.
#:
#: Pixels whose best point lies within CORNER of the range from the lower bound of each of a
#: corner's ``near`` parameters (at the mirror corner only kd: at kd = 0 the DOP does not depend on
#: sigma, so a descent that reached it cannot move sigma) continue with the corner's ``logged``
#: parameters as log(p - corner) (floored at CORNER_FLOOR of the ranges), where
#: the valley is nearly a straight line: the corner's ``iterations`` Levenberg-Marquardt iterations (the
#: PB_LOG_* build of the descent; the reference on the numpy backend), kept where they lower the
#: pixel's objective.
CORNER = 0.01
CORNER_FLOOR = 1e-12
#: On the numpy backend a corner's descent (the reference's plain Levenberg-Marquardt, without the
#: device kernel's geodesic acceleration) crawls further down the valley: it runs the corner's
#: iterations again, up to this many rounds, while some pixel's objective still fell by more than
#: NUMPY_CORNER_RTOL in the last round (measured on the index-corner test pixels on a Zen 4: pixel
#: 0 stops 2.8e-6 above fit's objective after 200 iterations, reaches it after 1000).
NUMPY_CORNER_ROUNDS = 8
NUMPY_CORNER_RTOL = 1e-9
#: With shared geometry, every pixel's objective is also evaluated on a small table of each
#: corner's points (one DOP table, then a product with the pixels' data as in the grid stage): a
#: pixel whose best corner point comes within CORNER_TRIGGER of its best objective so far descends
#: from there too (the valleys are too narrow for the grid's nodes and the descents' starts).
#: The index corner's table: (n - 1, k) of CORNER_EPS, kd/ks of CORNER_KD (four steps a decade:
#: the DOP there depends on kd / |n + ik - 1|^2, and half a decade misses the valley), the grid's
#: sigma and c nodes.  The mirror corner's: sigma at its lower bound, kd/ks of MIRROR_KD, the
#: grid's n, k and c nodes.
CORNER_TRIGGER = 1.05
CORNER_KD = np.logspace(-9.0, -2.0, 29)
CORNER_EPS = ((1e-3, 0.0), (0.0, 1e-3), (1e-3, 1e-3))
MIRROR_KD = np.logspace(-9.0, -2.0, 15)


class _Corner(NamedTuple):
    name: str
    at: tuple       # the parameters at their lower bound in the corner
    near: tuple     # those a pixel's best point must be near to descend there
    logged: tuple   # the parameters descended as log(p - offset) there
    offset: tuple   # of the logged parameters (their lower bounds, which the kernel assumes)
    iterations: int  # of the descent there (the mirror's valley is short: 60 do what 200 do)


CORNERS = (_Corner("index", ("n", "k", "kd"), ("n", "k", "kd"), ("n", "k", "kd"), (1.0, 0.0, 0.0), 200),
           _Corner("mirror", ("sigma", "kd"), ("kd",), ("kd",), (0.0,), 60))


def _corner_table(setup, names, corner):
    """The table points of ``corner``: name -> values (a fixed parameter's one value)."""
    def nodes(n):
        if n not in names:
            return np.array([setup.base[n]], float)
        j = names.index(n)
        return np.linspace(setup.lo[j], setup.hi[j], BATCH_GRID[n])
    if corner.name == "index":
        E, KD, SG, C = np.meshgrid(np.arange(len(CORNER_EPS)), CORNER_KD, nodes("sigma"), nodes("c"), indexing="ij")
        eps = np.array(CORNER_EPS)[E.ravel()]
        return {"n": 1.0 + eps[:, 0], "k": eps[:, 1], "kd": KD.ravel(), "sigma": SG.ravel(), "c": C.ravel()}
    N, K, KD, C = np.meshgrid(nodes("n"), nodes("k"), MIRROR_KD, nodes("c"), indexing="ij")
    return {"n": N.ravel(), "k": K.ravel(), "kd": KD.ravel(), "sigma": np.full(N.size, setup.lo[names.index("sigma")]),
            "c": C.ravel()}


def _corner_table_starts(eng, setup, blk, names, corner, sb):
    """The shared-geometry table's best point of ``corner`` per pixel, for the pixels where it
    comes within CORNER_TRIGGER of ``sb``: (pixels, their starts (q, D))."""
    if not blk.shared:
        return np.empty(0, int), np.empty((0, len(names)))
    pts = _corner_table(setup, names, corner)
    q = next(iter(pts.values())).size
    par = {n: pts.get(n, np.full(q, setup.base[n])) for n in ("n", "k", "sigma", "ks", "kd", "c")}
    # float32 as the grid stage's table: it only ranks starts for the float64 descent
    T = dense.outer(eng, "dop", dict(zip(ANGLES, blk.angles)), par, "float32" if not eng.is_numpy else "float64",
                    setup.shadowing).T
    T = np.where(np.isfinite(T), T, 1e3)
    best, arg = _table_minima(eng, blk, T, np.array([0, q], np.int32))
    j = arg[0]
    pix = np.flatnonzero(best[0] < CORNER_TRIGGER * sb)
    return pix, np.stack([pts[n][j[pix]] for n in names], axis=1)


def _corner_slots(names, corner):
    return [names.index(n) for n in corner.logged], np.array(corner.offset)


def _to_corner(X, names, corner):
    j, off = _corner_slots(names, corner)
    U = np.array(X, float)
    U[..., j] = np.log(np.maximum(U[..., j] - off, CORNER_FLOOR))
    return U


def _from_corner(U, names, corner):
    j, off = _corner_slots(names, corner)
    X = np.array(U, float)
    X[..., j] = off + np.exp(X[..., j])
    return X


def _corner_bounds(setup, names, corner):
    lo, hi = _bounds(setup, names)
    j, off = _corner_slots(names, corner)
    lo, hi = lo.copy(), hi.copy()
    lo[j], hi[j] = np.log(CORNER_FLOOR * (hi[j] - lo[j])), np.log(hi[j] - off)
    return lo, hi


def _corner_applies(setup, names, corner):
    """Whether ``corner`` is a corner of this fit's box: its parameters free, the logged ones
    bounded below by the offsets the kernel assumes."""
    if not set(corner.at) <= set(names):
        return False
    j, off = _corner_slots(names, corner)
    return bool(np.array_equal(np.asarray(setup.lo, float)[j], off))


def _corner_polish(eng, setup, blk, xb, sb, jb, nfev):
    """For each of :data:`CORNERS`: the pixels at it (:data:`CORNER`), and those whose table
    point comes close to their objective, descended in the corner's coordinates (on the device;
    with the reference on the numpy backend); ``xb`` (p, D), ``sb`` (p,) and ``jb`` (p, D, D: JtJ
    in the descent's coordinates) updated in place where the objective falls."""
    names = list(setup.free)
    for corner in CORNERS:
        if _corner_applies(setup, names, corner):
            _descend_corner(eng, setup, blk, names, corner, xb, sb, jb, nfev)


def _descend_corner(eng, setup, blk, names, corner, xb, sb, jb, nfev):
    lo, hi = np.asarray(setup.lo, float), np.asarray(setup.hi, float)
    j = [names.index(n) for n in corner.near]
    near = np.all(xb[:, j] - lo[j] < CORNER * (hi - lo)[j], axis=1) & np.isfinite(sb)
    extra, X_extra = _corner_table_starts(eng, setup, blk, names, corner, np.where(near, -np.inf, sb))
    pix = np.concatenate([np.flatnonzero(near), extra])  # distinct: the table skips the pixels near
    if not pix.size:
        return
    logged, _ = _corner_slots(names, corner)
    X0 = np.clip(np.concatenate([xb[near], X_extra]), _corner_floor(lo, hi, logged), hi)
    if eng.is_numpy:
        ulo, uhi = _corner_bounds(setup, names, corner)
        res = _PixelResiduals(setup, blk, names, pix, False)
        U, sse = _to_corner(X0, names, corner), np.full(pix.size, np.inf)
        for _ in range(NUMPY_CORNER_ROUNDS):  # rounds while an objective still falls (see NUMPY_CORNER_ROUNDS)
            U, new, evals = lm_batch(lambda V: res.rows(_from_corner(V, names, corner)), U, ulo, uhi,
                                      corner.iterations)
            nfev[pix] += evals // pix.size
            falling = np.any(new < sse * (1 - NUMPY_CORNER_RTOL))
            sse = new
            if not falling:
                break
        X = _from_corner(U, names, corner)
    else:
        dtype = "float64" if eng.fp64 else "float32"
        X, sse, _, _ = _device_lm(eng, setup, blk.subset(pix), X0[None], names, dtype, corner.iterations, False,
                                  corner=corner)
        X, sse = X[0], sse[0]
        nfev[pix] += (len(names) + 1) * (corner.iterations + 1)
    better = np.flatnonzero(sse < sb[pix])
    if not better.size:
        return
    X = np.clip(X[better], lo, hi)
    won = pix[better]
    # the objective and JtJ at the new points in the usual coordinates (no iteration)
    if eng.is_numpy:
        _, s_new, j_new, _ = _numpy_lm(setup, blk.subset(won), X[None], names, 0, False)
    else:
        _, s_new, j_new, _ = _device_lm(eng, setup, blk.subset(won), X[None], names, dtype, 0, False)
    s_new, j_new = s_new[0], j_new[0]
    keep = s_new < sb[won]
    xb[won[keep]], sb[won[keep]], jb[won[keep]] = X[keep], s_new[keep], j_new[keep]


def _corner_floor(lo, hi, logged):
    """The lower bounds with the corner's coordinates at their floor above the corner."""
    out = np.array(lo, float)
    out[logged] = lo[logged] + CORNER_FLOOR * (hi - lo)[logged]
    return out


# ---- uncertainties, status ----------------------------------------------------------------------

def _truncated_interval(x, se, lo, hi, dof):
    """The central 95% of N(x, se) (Student's t with ``dof`` where given) truncated to [lo, hi],
    elementwise."""
    from scipy import special
    if dof is None:
        cdf, ppf = special.ndtr, special.ndtri
    else:
        def cdf(z):
            return special.stdtr(dof, z)

        def ppf(q):
            return special.stdtrit(dof, q)
    with np.errstate(all="ignore"):
        a, b = cdf((lo - x) / se), cdf((hi - x) / se)
        span = b - a
        lo95 = x + se * ppf(np.clip(a + 0.025 * span, 1e-300, 1 - 1e-16))
        hi95 = x + se * ppf(np.clip(a + 0.975 * span, 1e-300, 1 - 1e-16))
    # where the truncated mass is numerically nothing (x far outside +- many se of both bounds)
    lo95 = np.where(np.isfinite(lo95), np.clip(lo95, lo, hi), lo)
    hi95 = np.where(np.isfinite(hi95), np.clip(hi95, lo, hi), hi)
    return lo95, hi95


def _covariances(jtj, s2, span):
    """Covariance (p, D, D) from J^T J in internal coordinates (pseudo-inverse in coordinates
    scaled to the bounds: a direction the data do not see gets an infinite variance)."""
    A = jtj * span[None, :, None] * span[None, None, :]
    eigval, eigvec = np.linalg.eigh(A)
    top = np.maximum(eigval.max(axis=1, keepdims=True), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(eigval > 1e-12 * top, 1.0 / eigval, np.inf)
    # infinite variance along a null direction: var_i = sum_k v_ik^2 / l_k (inf where v_ik != 0)
    with np.errstate(invalid="ignore"):
        cov = np.einsum("pik,pk,pjk->pij", eigvec, np.where(np.isinf(inv), 0.0, inv), eigvec)
        null = np.einsum("pik,pk->pi", eigvec ** 2 > 1e-12, np.isinf(inv).astype(float)) > 0
    cov = cov * span[None, :, None] * span[None, None, :] * s2[:, None, None]
    var = np.where(null, np.inf, np.einsum("pii->pi", cov))
    return cov, var


def fit_batch(data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, memory_budget=DEFAULT_BUDGET,
              progress=False, n_starts=N_STARTS, grid_shape=None, engine=None, backend="auto", store=None,
              workers=None, scheduler=None, client=None):
    """Fit the model to every pixel of a polarization image stack, batched on the device.

    Parameters
    ----------
    data : xarray.Dataset, dict of arrays or path
        ``dop`` of shape ``(..., M)`` (pixel dimensions, then M measurements; NaN marks a missing
        measurement of that pixel); ``theta_i``, ``theta_r`` and optionally ``phi`` (degrees,
        default 180) shared, shape ``(M,)``, or per pixel, broadcastable to ``dop``; optional
        ``dop_std`` (broadcastable; NaN only where ``dop`` is NaN), ``f00`` or ``s0``
        intensities (then ks and kd are separated, as in :func:`pbrdf_cl.fit`), ``f00_std`` and
        a boolean ``mask`` over the pixel dimensions (False: skip the pixel).  A path to a
        ``.npz``, ``.nc`` or ``.zarr`` stack with those variables.  The measurements may lie
        along another axis where the geometry says which (the shared angles' axis or
        dimension, or a Dataset dimension named ``m``; see :class:`_Source`); ambiguous layouts
        are refused.  Without ``phi`` every measurement is in plane (``attrs["data_notes"]``).
    model, bounds, fixed, shadowing
        As for :func:`pbrdf_cl.fit`.
    memory_budget : int or str, default "512 MiB"
        Bounds the memory of one block of pixels (host and device); larger stacks are fitted
        block by block.
    progress : bool, default False
        A progress bar in pixels, with pixels/s and the time left.
    n_starts : int, default 32
        Descents per pixel, from the best region minima of the grid stage.
    grid_shape : dict, optional
        Grid nodes per free parameter (default :data:`BATCH_GRID`).
    engine, backend
        Where to compute (as for :func:`pbrdf_cl.dop`); the numpy backend runs the same stages
        with the float64 reference, much slower.
    store : str or path, optional
        Write the result to this Zarr store block by block, resumable (see
        :func:`pbrdf_cl.fitting.batch_store.fit_batch_to_store`); the result is then opened from it.
    workers, scheduler, client : optional, with ``store`` only
        Fit the blocks on a local ``dask.distributed`` cluster of this many processes, on the
        cluster of this scheduler address, or through this client (each worker builds its own
        engine and writes its blocks into the store).

    Returns
    -------
    xarray.Dataset
        Over the pixel dimensions: one variable per fitted parameter (``n``, ``k``, ``sigma``,
        ``kd``, ``c``, and ``ks`` with intensities; kd is kd/ks without them), ``sse`` (sum of
        squared DOP residuals), ``chi2`` (weighted), ``<name>_stderr``, ``<name>_ci95`` (a
        trailing ``bound`` dimension: low, high), ``determined`` (per parameter: the 95%
        interval is narrower than half the bounds), ``r2``, ``p_value`` and ``fits_data`` (the
        goodness-of-fit test of each pixel, as :func:`pbrdf_cl.fit`'s), ``n_valid``
        (measurements used), ``nfev`` and ``status`` (codes in ``attrs["status_codes"]``); the
        stack's coordinates over the pixels; units, settings and the image's goodness of fit
        (:func:`goodness_summary`: ``attrs["goodness"]``, and ``attrs["goodness_warning"]``
        where too many pixels fail) in ``attrs``.

    Raises
    ------
    ValueError
        For bad input, naming the variable and the first offending index.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> truth = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, **truth), (2, 3, 30))
    >>> res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr))
    >>> res.n.shape, bool(abs(res.n - 1.6).max() < 1e-3)
    ((2, 3), True)
    """
    if store is not None:
        from .batch_store import fit_batch_to_store
        return fit_batch_to_store(data, store, model=model, bounds=bounds, fixed=fixed, shadowing=shadowing,
                                  memory_budget=memory_budget, progress=progress, n_starts=n_starts,
                                  grid_shape=grid_shape, engine=engine, backend=backend, workers=workers,
                                  scheduler=scheduler, client=client)
    if workers is not None or scheduler is not None or client is not None:
        raise ValueError("workers=, scheduler= and client= need store= (the workers write their blocks into it)")
    job = BatchJob(data, model, bounds, fixed, shadowing, memory_budget=memory_budget, n_starts=n_starts,
                   grid_shape=grid_shape)
    eng = resolve_engine(engine, backend)
    parts = []
    bar = _bar(job.source.n_pixels, progress)
    t0 = time.perf_counter()
    for r0, r1 in job.blocks():
        parts.append(job.fit_rows(eng, r0, r1))
        if bar is not None:
            bar.update(parts[-1]["sse"].size)
    if bar is not None:
        bar.close()
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    ds = job.dataset(out, seconds=time.perf_counter() - t0)
    ds.attrs.update(goodness_summary(ds))
    return ds


#: fit-image warns that the model does not describe the data when more than this share of the
#: fitted pixels fails the goodness-of-fit test (``fits_data`` 0): the chi2 test with dop_std;
#: the R^2 test without, which also fails pixels whose DOP hardly varies beyond its noise (a
#: third of random pixels in the paper's geometry at DOP noise 0.002, most of them nearly
#: unpolarised light), so there only when most pixels fail it.
GOODNESS_SHARE = {"chi2": 0.1, "r2": 0.5}
#: At most this many pixels' statistics are read for the medians of :func:`goodness_summary`
#: (every s-th pixel of a larger result).
GOODNESS_SAMPLE = 2 ** 22


def goodness_summary(ds):
    """Whether the model describes an image fit's data, over all its fitted pixels, as
    :func:`pbrdf_cl.fit` says it of one fit: the attributes :func:`fit_batch` and
    ``fit_batch_to_store`` add to their result (read block by block from a store).

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`fit_batch` (its ``fits_data``, ``chi2``, ``r2`` and ``n_valid``).

    Returns
    -------
    dict
        ``goodness_test`` ("chi2": the p-value of each pixel's chi2 below GOODNESS_P fails, with
        dop_std; "r2": R^2 below GOODNESS_R2 fails, without), ``goodness_tested`` (fitted
        pixels), ``goodness_failed``, ``goodness_share_failed``, ``goodness_fits_data`` (1
        unless more than GOODNESS_SHARE of the tested pixels fail: 10% of the chi2 test, 50% of
        the R^2 test), ``goodness`` (a line saying so, with the median and the worst pixel, by
        its indices) and, where ``goodness_fits_data`` is 0, ``goodness_warning`` (a WARNING
        line with the usual causes and the notes the data show).

    Examples
    --------
    >>> res = fit_batch(stack)  # doctest: +SKIP
    >>> res.attrs["goodness"].split("; ")[:2]  # doctest: +SKIP
    ['goodness of fit: 0 of 576 fitted pixels (0.0%) fail the chi2 test (p < 0.001 with dop_std)',
     'median chi2 22.8 for 25 degrees of freedom']
    """
    chi2_test = bool(ds.attrs.get("sigma_known", 0))
    free = len(str(ds.attrs.get("free", "")).split())
    intensity = "ks" in str(ds.attrs.get("free", "")).split()
    fits = ds["fits_data"]
    shape = fits.shape
    n_total = int(np.prod(shape, dtype=np.int64))
    step = max(1, -(-n_total // GOODNESS_SAMPLE))
    rows = fits.chunks[0] if fits.chunks else (shape[0],) if shape else (1,)
    tested = failed = 0
    sample, dofs = [], []
    worst = (None, None)  # (flat index, value): the largest reduced chi2 or the lowest R^2
    r = 0
    flat0 = 0
    for size in rows:
        part = {k: np.asarray(ds[k][r:r + size].values).ravel() for k in ("fits_data", "chi2", "r2", "n_valid")}
        r += size
        ok = part["fits_data"] >= 0
        tested += int(ok.sum())
        failed += int((part["fits_data"] == 0).sum())
        dof = np.maximum(part["n_valid"] * (2 if intensity else 1) - free, 1)
        value = part["chi2"] / dof if chi2_test else part["r2"]
        value = np.where(ok & np.isfinite(value), value, np.nan)
        if np.isfinite(value).any():
            i = int(np.nanargmax(value) if chi2_test else np.nanargmin(value))
            if worst[1] is None or (value[i] > worst[1] if chi2_test else value[i] < worst[1]):
                worst = (flat0 + i, float(value[i]))
        keep = np.arange(value.size)[(flat0 + np.arange(value.size)) % step == 0]
        keep = keep[np.isfinite(value[keep])]
        sample.append((part["chi2"] if chi2_test else value)[keep])
        dofs.append(dof[keep])
        flat0 += value.size
    out = {"goodness_test": "chi2" if chi2_test else "r2", "goodness_tested": tested, "goodness_failed": failed,
           "goodness_share_failed": failed / tested if tested else 0.0}
    share = out["goodness_share_failed"]
    out["goodness_fits_data"] = int(share <= GOODNESS_SHARE[out["goodness_test"]])
    test = (f"the chi2 test (p < {GOODNESS_P:g} with dop_std)" if chi2_test else
            f"the R^2 test (the fit explains less than {GOODNESS_R2:.0%} of the DOP's variance; no dop_std)")
    text = f"goodness of fit: {failed} of {tested} fitted pixels ({share:.1%}) fail {test}"
    sample = np.concatenate(sample) if sample else np.zeros(0)
    if sample.size:
        if chi2_test:
            text += (f"; median chi2 {np.median(sample):.3g} for {np.median(np.concatenate(dofs)):g} degrees of "
                     "freedom")
        else:
            text += f"; median R^2 {np.median(sample):.3g}"
    if worst[0] is not None:
        idx = np.unravel_index(worst[0], shape)
        where = ", ".join(f"{d}={i}" for d, i in zip(fits.dims, idx))
        text += (f"; worst at {where}: " + (f"reduced chi2 {worst[1]:.3g}" if chi2_test else f"R^2 {worst[1]:.3g}"))
    out["goodness"] = text
    if not out["goodness_fits_data"]:
        notes = "; ".join(str(ds.attrs.get("data_notes", "")).splitlines())
        out["goodness_warning"] = (f"WARNING: the model does not describe the data of {share:.0%} of the fitted "
                                   "pixels (fits_data = 0 there); their values and intervals are not to be trusted; "
                                   f"usual causes: {MISTAKE_CAUSES}" + (f"; the data show: {notes}" if notes else ""))
    return out


def _bar(total, enabled):
    if not enabled:
        return None
    from tqdm.auto import tqdm
    return tqdm(total=total, desc="fit_batch", unit="px", unit_scale=True, smoothing=0.1)


class BatchJob:
    """A checked :func:`fit_batch` job: the source stack, the settings, its blocks of rows and
    the fit of one block (:meth:`fit_rows`), so that a store or a Dask worker can run blocks on
    their own."""

    def __init__(self, data, model="six-param", bounds=None, fixed=None, shadowing="paper", *,
                 memory_budget=DEFAULT_BUDGET, n_starts=N_STARTS, grid_shape=None):
        from ..ranges import parse_bytes
        check_model(model, shadowing)
        n_starts = int(n_starts)
        if n_starts < 1:
            raise ValueError(f"n_starts must be >= 1, got {n_starts}")
        self.memory_budget = parse_bytes("memory_budget", memory_budget)
        self.source = _Source(data)
        fs = FitSetup.check(model, bounds, fixed, shadowing)
        bnds, fx, free = fs.bounds, fs.fixed, fs.free
        base = {**{n: 0.0 for n in ("n", "k", "sigma", "kd", "c")}, **MODEL_FIXED[model], **fx}
        use_f00 = "f00" in self.source.vars and model == "six-param" and "ks" not in fx and "kd" not in fx
        shape = {**(BATCH_SPECULAR_GRID if model == "specular" else BATCH_GRID), **(grid_shape or {})}
        unknown = set(grid_shape or {}) - set(free)
        if unknown:
            raise ValueError(f"grid_shape: {sorted(unknown)[0]!r} is not a free parameter ({', '.join(free)})")
        axes = fs.grid_axes(shape)
        if int(np.prod([a.size for a in axes.values()])) >= 2 ** 24:
            raise ValueError("grid_shape: at most 2**24 grid points")
        sigma_known = "dop_std" in self.source.vars
        floor = DOP_NOISE_FLOOR  # each pixel's own floor may be higher: _Block.noise_floor
        self.setup = _Setup(model, shadowing, free, np.array([bnds[n][0] for n in free]),
                            np.array([bnds[n][1] for n in free]), base, fx, axes, use_f00,
                            tuple(bnds.get("ks", DEFAULT_BOUNDS["ks"])), n_starts, sigma_known, floor)
        self.order, self.rstart = _regions(_grid_values(self.setup), free)
        #: What the data show of the usual mistakes (phi not given, phi = 0, radians), from the
        #: first row of pixels: the result's ``attrs["data_notes"]`` and the goodness summary's causes.
        self.notes = _data_notes(self.source)

    @property
    def names(self):
        """The fitted parameters, in the order of the outputs."""
        return self.setup.free + (["ks"] if self.setup.use_f00 else [])

    def pixel_bytes(self):
        """Host and device bytes one pixel of a block needs (the largest stage)."""
        M, D, S = self.source.M, len(self.names), self.setup.n_starts
        v = _grid_values(self.setup)
        # the block's data (float64 and the kernels' copies), the descents' vectors and J^T J, and
        # the geodesic acceleration's scratch (two slots of M Jacobian rows per float32 start)
        per = 8 * M * 12 + 8 * S * D * (D + 3) * 2 + (4 * 2 * M * (D + 1) * S if GEODESIC else 0)
        if not self.source.shared:
            nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size, v["kd"].size * v["c"].size
            per += 4 * M * (2 * nnk + nm + ni)
        per += 8 * (self.rstart.size - 1) * 2
        return per

    def fixed_bytes(self):
        """Bytes a block needs whatever its size: with shared geometry the grid's DOP table and its
        making (the per-point path's inputs and output; measured with tracemalloc: 26 MB at the
        default grid and 30 measurements)."""
        return 32 * len(self.order) * self.source.M if self.source.shared else 0

    def rows_per_block(self):
        """Rows of the first pixel dimension per block within the memory budget (at least one)."""
        row = int(np.prod(self.source.shape[1:], dtype=np.int64))
        fixed = self.fixed_bytes()
        need = fixed + self.pixel_bytes() * row
        if self.memory_budget < need:
            raise ValueError(f"memory_budget={self.memory_budget} bytes is too small for one row of "
                             f"{row} pixels ({need} bytes with the grid's tables); raise it")
        px = (self.memory_budget - fixed) // self.pixel_bytes()
        if not self.source.shared:  # 32-bit indices of the per-pixel tables
            v = _grid_values(self.setup)
            px = min(px, (2 ** 31 - 1) // (self.source.M * v["n"].size * v["k"].size) - 64)
        return int(max(1, min(self.source.shape[0], px // max(row, 1))))

    def blocks(self):
        """(r0, r1) row ranges of the blocks, in order."""
        step = self.rows_per_block()
        return [(r0, min(r0 + step, self.source.shape[0])) for r0 in range(0, self.source.shape[0], step)]

    def fit_rows(self, eng, r0, r1):
        """Fit the pixels of rows r0..r1: a dict of flat per-pixel result arrays."""
        raw = self.source.rows(r0, r1)
        _check_block(raw, r0, self.source)
        if r0 == 0:  # angles in radians? (the first block stands for the stack: no extra read)
            pointwise.check_degrees(raw["theta_i"], raw["theta_r"], "data: ")
        return _fit_block(eng, self.setup, raw, self.order, self.rstart, self.names)

    def dataset(self, out, seconds=None):
        """The result Dataset from the concatenated outputs of :meth:`fit_rows`."""
        return _dataset(self, out, seconds)


def _data_notes(source):
    """Notes on the conventions the stack shows by itself: phi not given (every measurement in
    plane), phi = 0 and angles below 1.6 degrees in the first row of pixels (as
    :func:`pbrdf_cl.fit`'s notes)."""
    from ..io.measurements import PHI_DEFAULT_NOTE
    notes = [] if source.phi_given else [PHI_DEFAULT_NOTE]
    raw = source.rows(0, 1)
    hi = pointwise.radians_suspect(raw["theta_i"], raw["theta_r"])
    if hi is not None:
        notes.append(f"every theta_i and theta_r of the first row lies below {pointwise.RADIANS_HINT} degrees (the largest "
                     f"is {hi:.4g}): radians? pbrdf-cl takes degrees")
    if source.phi_given and np.all(np.asarray(raw["phi"]) == 0.0):
        notes.append("phi = 0 for every measurement of the first row: that is the plane of incidence on the source's "
                     "side (back-scattering); in-plane specular data have phi = 180 here (SCATMECH's phi = 0 is our "
                     "180)")
    return notes


@_engine.falls_back
def _fit_block(eng, setup, raw, order, rstart, names):
    """The flat per-pixel results of one block of pixels (``raw``: :meth:`_Source.rows`): the
    pixels that can be fitted go through the stages, the others get their status."""
    D = len(setup.free)
    lanes = max(*eng.lm_lanes.values(), *eng.vector_width.values()) if not eng.is_numpy else 1  # every kernel's lanes divide it
    blk = _Block(raw, setup, lanes)
    p, n_out = blk.p, len(names)
    status = np.full(p, 1, np.int8)
    status[(blk.count < D + 1) | (blk.distinct < D)] = -2
    status[~blk.mask] = -1
    todo = np.flatnonzero(status > 0)
    out = _empty_outputs(p, n_out)
    out["status"], out["n_valid"] = status, blk.count.astype(np.int64)
    if todo.size:
        done = _fit_pixels(eng, setup, blk if todo.size == p else blk.subset(todo), order, rstart, names)
        for k, v in done.items():
            out[k][todo] = v
    return out


def _empty_outputs(p, n_out):
    """The per-pixel outputs of :meth:`BatchJob.fit_rows` for ``p`` pixels not fitted (keys,
    shapes and dtypes; status 0)."""
    return {"x": np.full((p, n_out), np.nan), "stderr": np.full((p, n_out), np.nan),
            "ci95": np.full((p, n_out, 2), np.nan), "determined": np.zeros((p, n_out), bool),
            "chi2": np.full(p, np.nan), "sse": np.full(p, np.nan), "r2": np.full(p, np.nan),
            "p_value": np.full(p, np.nan), "fits_data": np.full(p, -1, np.int8), "nfev": np.zeros(p, np.int64),
            "status": np.zeros(p, np.int8), "n_valid": np.zeros(p, np.int64)}


def _fit_pixels(eng, setup, blk, order, rstart, names):
    """The stages for every pixel of ``blk`` (each has enough valid measurements)."""
    D = len(setup.free)
    p = blk.p
    # (a) grid: each region's minimum; the best n_starts per pixel seed the descents
    if eng.is_numpy:
        best, arg = _numpy_grid(setup, blk, order, rstart)
    else:
        best, arg = _device_grid(eng, setup, blk, order, rstart)
    X0 = _grid_points(setup, order, _distinct_starts(best, arg, order, setup.n_starts))  # (S, p, D)
    S = X0.shape[0]
    nfev = np.zeros(p, np.int64)
    nfev += int(len(order))
    # (b) float32 descents of every start, the best continued (successive halving: a short
    # descent says which basin a start falls into), then the best few polished in float64
    if eng.is_numpy:
        X, sse, jtj, settled = _numpy_lm(setup, blk, X0, setup.free, SCREEN_ITERATIONS + POLISH_ITERATIONS, False)
        nfev += S * (D + 1) * (SCREEN_ITERATIONS + POLISH_ITERATIONS + 2)
    else:
        X, sse = X0, np.zeros((S, p))
        for count, iterations in SCREEN_SCHEDULE:
            keep = min(count, X.shape[0])
            top = np.argsort(np.where(np.isfinite(sse), sse, np.inf), axis=0, kind="stable")[:keep]
            X = np.take_along_axis(X, top[..., None], axis=0)
            X, sse, _, _ = _device_lm(eng, setup, blk, X, setup.free, "float32", iterations, False)
            nfev += keep * (D + 1) * (iterations + 1)
        T = min(POLISH_STARTS, X.shape[0])
        top = np.argsort(np.where(np.isfinite(sse), sse, np.inf), axis=0, kind="stable")[:T]
        X1 = np.take_along_axis(X, top[..., None], axis=0)
        dtype = "float64" if eng.fp64 else "float32"
        Xp, ssep, jtjp, setp = _polish(eng, setup, blk, X1, dtype, nfev)
        # towards the bounds: from the best polished point, the coordinates near a bound moved 10,
        # 100 and 1000 times closer to it (alone and together), the best of those polished too; a
        # descent into this model's corners (n = 1, k = 0, kd = 0 where the DOP is discontinuous,
        # sigma = 1) crawls geometrically, each step's move onto the bound rejected
        bt = np.argmin(np.where(np.isfinite(ssep), ssep, np.inf), axis=0)
        xb = Xp[bt, np.arange(p)]
        cand = _towards_bounds(xb, setup.lo, setup.hi)
        moved = np.flatnonzero(np.any(cand != xb[None], axis=(0, 2))) if cand is not None else np.empty(0, int)
        if moved.size:
            sub = blk.subset(moved)
            _, ssec, _, _ = _device_lm(eng, setup, sub, cand[:, moved], setup.free, "float32", 0, False)
            nfev[moved] += cand.shape[0] * (D + 1)
            c_best = np.argmin(ssec, axis=0)
            start_ = cand[c_best, moved][None]
            Xs, sses, jtjs, sets = _polish(eng, setup, sub, start_, dtype, nfev, moved)
            row = [a[bt, np.arange(p)][None].copy() for a in (Xp, ssep, jtjp, setp)]
            for r, v in zip(row, (Xs, sses, jtjs, sets)):
                r[0, moved] = v[0]
            Xp, ssep, jtjp, setp = (np.concatenate([a, r]) for a, r in zip((Xp, ssep, jtjp, setp), row))
        # the best is one of the polished; the screened starts that were not polished keep their
        # float32 result, which only the ambiguity test reads
        X_all, sse_all = X.copy(), sse.copy()
        X_all, sse_all = np.concatenate([X_all, Xp]), np.concatenate([sse_all, ssep])
        X, sse, jtj, settled = Xp, ssep, jtjp, setp
    if eng.is_numpy:
        X_all, sse_all = X, sse
    sse = np.where(np.isfinite(sse) & (sse < 1e299), sse, np.inf)
    sse_all = np.where(np.isfinite(sse_all) & (sse_all < 1e299), sse_all, np.inf)
    b = np.argmin(sse, axis=0)
    ar = np.arange(p)
    xb, sb, jb, setb = X[b, ar], sse[b, ar], jtj[b, ar], settled[b, ar]
    _corner_polish(eng, setup, blk, xb, sb, jb, nfev)
    names_out = list(setup.free)
    if setup.use_f00:
        # ks from the weighted least-squares scale of F00 at ks = 1, then every parameter with ks
        ks0 = _ks_start(eng, setup, blk, xb)
        X2 = np.concatenate([xb, ks0[:, None]], axis=1)[None]
        if eng.is_numpy:
            Xf, ssef, jtjf, setf = _numpy_lm(setup, blk, X2, names, INTENSITY_ITERATIONS, True)
            nfev += (len(names) + 1) * (INTENSITY_ITERATIONS + 1)
        else:
            Xf, ssef, jtjf, setf = _polish(eng, setup, blk, X2, "float64" if eng.fp64 else "float32", nfev,
                                           names=names, intensity=True, iterations=INTENSITY_ITERATIONS)
        xb, sb, jb, setb = Xf[0], ssef[0], jtjf[0], setf[0]
        names_out = names
    return _statistics(setup, blk, names_out, xb, sb, jb, setb, X_all, sse_all, nfev)


def _towards_bounds(x, lo, hi):
    """Candidates (K, p, D) from the points ``x`` (p, D): the coordinates on a bound moved off it
    by 0.1% and 1% of the range, and those within SNAP of the range from a bound moved 10, 100
    and 1000 times closer to it, each alone and all together (None where no coordinate of any
    point is near a bound).  The same K candidates for every point (a candidate that moves
    nothing of a point is that point), so that a pixel's candidates, and the one it keeps, do
    not depend on the other pixels of its block."""
    span = hi - lo
    near_lo, near_hi = x - lo < SNAP * span, hi - x < SNAP * span
    near = near_lo | near_hi
    if not near.any():
        return None
    out = []
    # a coordinate on a bound can hide others: at kd = 0 the DOP depends on neither sigma nor c,
    # so a descent that reached kd = 0 cannot move them; off the bound by 0.1% and 1% it can
    on_lo, on_hi = x - lo <= 1e-9 * span, hi - x <= 1e-9 * span
    for f in (1e-3, 1e-2):
        out.append(np.where(on_lo, lo + f * span, np.where(on_hi, hi - f * span, x)))
    for f in (1e-1, 1e-2, 1e-3):
        closer = np.where(near_lo, lo + (x - lo) * f, np.where(near_hi, hi - (hi - x) * f, x))
        out.append(closer)
        for j in range(x.shape[1]):
            one = x.copy()
            one[:, j] = closer[:, j]
            out.append(one)
    return np.stack(out)


def _polish(eng, setup, blk, X, dtype, nfev, pixels=None, names=None, intensity=False, iterations=None):
    """The float64 descent from the starts X (T, p, D) of ``blk`` over ``names`` (default the free
    parameters; ``intensity``: with the F00 residuals): ``iterations`` (default POLISH_ITERATIONS),
    then the descents not settled continue alone (compacted) for up to EXTRA_ROUNDS runs of
    EXTRA_ITERATIONS; adds the evaluations to ``nfev`` (of the pixels ``pixels`` of the caller's
    block, default all).  Returns (X, sse, JtJ, settled)."""
    D = X.shape[-1]
    names = setup.free if names is None else names
    iterations = POLISH_ITERATIONS if iterations is None else iterations
    pixels = np.arange(X.shape[1]) if pixels is None else pixels
    Xp, ssep, jtjp, setp = _device_lm(eng, setup, blk, X, names, dtype, iterations, intensity)
    nfev[pixels] += X.shape[0] * (D + 1) * (iterations + 1)
    for _ in range(EXTRA_ROUNDS):
        t_idx, p_idx = np.nonzero(~setp)
        if t_idx.size == 0:
            break
        Xe, ssee, jtje, sete = _device_lm(eng, setup, blk.subset(p_idx), Xp[t_idx, p_idx][None], names, dtype,
                                          EXTRA_ITERATIONS, intensity)
        Xp[t_idx, p_idx], ssep[t_idx, p_idx], jtjp[t_idx, p_idx], setp[t_idx, p_idx] = Xe[0], ssee[0], jtje[0], sete[0]
        np.add.at(nfev, pixels[p_idx], (D + 1) * (EXTRA_ITERATIONS + 1))
    return Xp, ssep, jtjp, setp


def _distinct_starts(best, arg, order, n):
    """Per pixel, the grid indices (into ``order``) of the ``n`` best region minima that are distinct
    grid points, (n, p); a pixel with fewer distinct ones repeats its best."""
    rank = np.argsort(best, axis=0, kind="stable")
    g = np.take_along_axis(order[arg], rank, axis=0)  # grid points, best region first
    a = np.take_along_axis(arg, rank, axis=0)
    dup = np.zeros(g.shape, bool)
    for r in range(1, g.shape[0]):
        dup[r] = np.any(g[:r] == g[r][None], axis=0)
    key = np.where(dup, g.shape[0], np.arange(g.shape[0])[:, None])  # distinct ones first, in rank order
    pick = np.argsort(key, axis=0, kind="stable")[:n]
    chosen = np.take_along_axis(a, pick, axis=0)
    ok = ~np.take_along_axis(dup, pick, axis=0)
    return np.where(ok, chosen, chosen[:1])


def _ks_start(eng, setup, blk, xb):
    """Per pixel, the ks that best scales the model's F00 (ks = 1) to the intensities."""
    p = dict(setup.base)
    for j, n in enumerate(setup.free):
        p[n] = xb[:, j:j + 1]
    p["ks"] = 1.0
    ang = [a[None, :] if blk.shared else a for a in blk.angles]
    m1 = pointwise.brdf(*ang, shadowing=setup.shadowing, engine=eng,
                  **{n: p[n] for n in ("n", "k", "sigma", "ks", "kd", "c")})
    w = blk.fw
    num = (w * blk.fobs * m1).sum(axis=1)
    den = np.maximum((w * m1 * m1).sum(axis=1), 1e-300)
    return np.clip(num / den, *setup.ks_bounds)


def _statistics(setup, blk, names, xb, chi2, jtj, settled, X_all, sse_all, nfev):
    p, D = xb.shape
    lo, hi = _bounds(setup, names)
    span = hi - lo
    n_valid = blk.count + (blk.valid.sum(axis=1) if setup.use_f00 else 0)
    dof = np.maximum(n_valid - D, 1)
    if setup.sigma_known:
        s2 = np.ones(p)
    else:
        s2 = np.maximum(chi2 / dof, blk.noise_floor ** 2)
    cov, var = _covariances(jtj, s2, span)
    se_int = np.sqrt(np.clip(var, 0, None))
    xi = _internal(xb, names)
    resolution = X_RESOLUTION * span
    floored = setup.sigma_known or (chi2 / dof < blk.noise_floor ** 2)
    se_i = np.maximum(se_int, resolution)
    lo95 = np.empty((p, D))
    hi95 = np.empty((p, D))
    known = floored if np.ndim(floored) else np.full(p, bool(floored))
    for kind in (True, False):
        sel = known == kind
        if not sel.any():
            continue
        l_, h_ = _truncated_interval(xi[sel], se_i[sel], lo, hi, None if kind else dof[sel][:, None])
        lo95[sel], hi95[sel] = l_, h_
    determined = (hi95 - lo95) < DETERMINED_FRACTION * span
    ci = np.stack([lo95, hi95], axis=-1)
    se = se_int.copy()
    # DOP-only SSE (unweighted) at the optimum, from the descent's parameters (kd as kd/ks with
    # intensities: it is made absolute just below)
    dop_sse = _dop_sse(setup, blk, names, xb)
    xb = xb.copy()
    if "ks" in names:  # back to ks from log ks, and kd from kd/ks (reported as in pbrdf_cl.fit)
        j = names.index("ks")
        ci[:, j] = np.exp(ci[:, j])
        se[:, j] = se_int[:, j] * xb[:, j]
        if "kd" in names:
            d, ks = names.index("kd"), xb[:, j]
            ratio = xb[:, d].copy()
            # kd = ratio ks, d kd = ks d ratio + ratio ks d(log ks)
            with np.errstate(invalid="ignore"):
                var = ks ** 2 * (cov[:, d, d] + ratio ** 2 * cov[:, j, j] + 2 * ratio * cov[:, d, j])
            var = np.where(np.isinf(se_int[:, d]) | np.isinf(se_int[:, j]), np.inf, var)
            xb[:, d] = ratio * ks
            se[:, d] = np.sqrt(np.clip(var, 0, None))
            kd_hi = setup.hi[setup.free.index("kd")] * ks
            l_, h_ = _truncated_interval(xb[:, d], np.maximum(se[:, d], resolution[d] * ks), 0.0 * ks, kd_hi,
                                         None if setup.sigma_known else dof)
            ci[:, d, 0], ci[:, d, 1] = l_, h_
    # ambiguity: another start within one unit of chi2, more than 2 standard errors away
    unit = np.where(setup.sigma_known, 1.0, s2)
    D0 = len(setup.free)
    best = chi2 if not setup.use_f00 else np.min(sse_all, axis=0)
    close = (sse_all - np.min(sse_all, axis=0)[None]) <= unit[None]
    far = np.any(np.abs(X_all - X_all[np.argmin(sse_all, axis=0), np.arange(p)][None])
                 > 2 * np.maximum(se[None, :, :D0], 1e-12), axis=-1)
    ambiguous = np.any(close & far, axis=0)
    on_bound = np.any((xi <= lo + resolution) | (xi >= hi - resolution), axis=1)
    status = np.ones(p, np.int8)
    status[on_bound] = 2
    status[ambiguous] = 3
    status[~determined.all(axis=1)] = 4
    status[~settled] = 0
    status[~np.isfinite(best)] = -3
    failed = status == -3
    r2, p_value, fits = _goodness(setup, blk, dop_sse, chi2, n_valid - D)
    out = {"x": xb, "stderr": se, "ci95": ci, "determined": determined & ~failed[:, None], "chi2": chi2,
           "sse": dop_sse, "r2": r2, "p_value": p_value, "fits_data": np.where(failed, -1, fits).astype(np.int8),
           "nfev": nfev, "status": status}
    for k in ("x", "stderr", "ci95", "chi2", "sse", "r2", "p_value"):
        out[k] = np.where(failed.reshape((-1,) + (1,) * (out[k].ndim - 1)), np.nan, out[k]).astype(float)
    return out


def _goodness(setup, blk, dop_sse, chi2, dof):
    """Per pixel, as :func:`pbrdf_cl.fit` tests a fit: (R^2 of the DOP, the p-value of chi2 with
    ``dof`` degrees of freedom (NaN without dop_std), 1 where the model describes the pixel's
    data else 0): with dop_std the p-value must reach GOODNESS_P, without it R^2 GOODNESS_R2
    (a pixel whose DOP does not vary passes)."""
    from scipy.stats import chi2 as chi2_dist
    n = np.maximum(blk.count, 1)
    mean = (blk.obs * blk.valid).sum(axis=1) / n
    sst = np.where(blk.valid, blk.obs - mean[:, None], 0.0)
    sst = np.einsum("pm,pm->p", sst, sst)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(sst > 0, 1.0 - dop_sse / sst, np.nan)
    if setup.sigma_known:
        p_value = np.where(dof > 0, chi2_dist.sf(chi2, np.maximum(dof, 1)), np.nan)
        fits = ~(p_value < GOODNESS_P)
    else:
        p_value = np.full(blk.p, np.nan)
        fits = ~(r2 < GOODNESS_R2)
    return r2, p_value, fits.astype(np.int8)


def _dop_sse(setup, blk, names, xb):
    """Sum of squared (unweighted) DOP residuals over each pixel's valid measurements, float64
    reference model."""
    res = _PixelResiduals(setup, blk, names, np.arange(blk.p), setup.use_f00, weights=blk.valid.astype(float))
    r = np.where(blk.valid, res.rows(_internal(xb, names))[:, :blk.valid.shape[1]], 0.0)
    return np.einsum("pm,pm->p", r, r)


def _dataset(job, out, seconds):
    import xarray as xr
    src, setup = job.source, job.setup
    shape, dims = src.shape, src.dims
    names = job.names
    ds = xr.Dataset(coords=dict(src.coords))  # the stack's coordinates over pixel dimensions (x_mm, y_mm, ...)
    units = {"n": "1", "k": "1", "sigma": "1", "kd": "1", "c": "1", "ks": "1"}
    long = {"n": "refractive index (real part)", "k": "extinction coefficient", "sigma": "slope std per axis",
            "kd": "diffuse coefficient" + ("" if setup.use_f00 else " relative to ks (kd/ks)"),
            "c": "Minnaert exponent", "ks": "specular coefficient"}
    for j, n in enumerate(names):
        ds[n] = (dims, out["x"][:, j].reshape(shape), {"units": units[n], "long_name": long[n]})
        ds[f"{n}_stderr"] = (dims, out["stderr"][:, j].reshape(shape),
                             {"units": units[n], "long_name": f"standard error of {n}"})
        ds[f"{n}_ci95"] = (dims + ("bound",), out["ci95"][:, j].reshape(shape + (2,)),
                           {"units": units[n], "long_name": f"95% interval of {n} (truncated to the bounds)"})
    ds["sse"] = (dims, out["sse"].reshape(shape), {"long_name": "sum of squared DOP residuals", "units": "1"})
    ds["chi2"] = (dims, out["chi2"].reshape(shape),
                  {"long_name": "weighted sum of squared residuals" + (" (chi2)" if setup.sigma_known else
                                                                     " (dop_std = 1: no uncertainties given)")})
    ds["determined"] = (dims + ("param",), out["determined"].reshape(shape + (len(names),)),
                        {"long_name": "the 95% interval is narrower than "
                                      f"{DETERMINED_FRACTION:g} of the parameter's bounds"})
    ds["r2"] = (dims, out["r2"].reshape(shape), {"units": "1", "long_name": "share of the DOP's variance the fit "
                                                                            "explains (R^2)"})
    ds["p_value"] = (dims, out["p_value"].reshape(shape),
                     {"units": "1", "long_name": "p-value of chi2 for its degrees of freedom (n_valid minus the "
                                                 "free parameters; NaN without dop_std)"})
    ds["fits_data"] = (dims, out["fits_data"].reshape(shape),
                       {"long_name": "whether the model describes the pixel's data: "
                                     + (f"p_value >= {GOODNESS_P:g}" if setup.sigma_known else f"r2 >= {GOODNESS_R2:g}")
                                     + " (as pbrdf_cl.fit tests a fit)",
                        "flag_values": [1, 0, -1], "flag_meanings": "fits does_not_fit not_fitted"})
    ds["n_valid"] = (dims, out["n_valid"].reshape(shape), {"long_name": "valid DOP measurements"})
    ds["nfev"] = (dims, out["nfev"].reshape(shape), {"long_name": "model evaluations per measurement"})
    ds["status"] = (dims, out["status"].reshape(shape), {"long_name": "fit status", **_status_attrs()})
    ds = ds.assign_coords(bound=["low", "high"], param=names)
    lo, hi = setup.lo, setup.hi
    ds.attrs.update(model=setup.model, shadowing=setup.shadowing, free=" ".join(names),
                    bounds="; ".join(f"{n} [{lo[i]:g}, {hi[i]:g}]" for i, n in enumerate(setup.free))
                    + (f"; ks [{setup.ks_bounds[0]:g}, {setup.ks_bounds[1]:g}]" if setup.use_f00 else ""),
                    grid=" x ".join(f"{n} {a.size}" for n, a in setup.axes.items()), n_starts=setup.n_starts,
                    angles_units="degrees", sigma_known=int(setup.sigma_known),
                    geometry="shared" if src.shared else "per pixel",
                    **{f"fixed_{k}": v for k, v in setup.fixed.items()})
    if setup.model == "six-param" and not setup.use_f00:
        ds.attrs["note"] = ("DOP depends on ks and kd only through kd/ks: ks is fixed at "
                            f"{setup.base['ks']:g} and kd is the ratio kd/ks")
    ds.attrs["phi_given"] = int(src.phi_given)
    if job.notes:
        ds.attrs["data_notes"] = "\n".join(job.notes)  # one note a line
    if seconds is not None:
        ds.attrs["seconds"] = float(seconds)
    return ds
