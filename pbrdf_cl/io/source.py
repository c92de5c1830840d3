"""The input of an image fit: a stack (a Dataset, a dict of arrays or a ``.npz``/``.nc``/``.zarr``
path, :func:`open_stack`) as a :class:`Source` that reads blocks of rows one at a time, with the
measurement axis found from the geometry (ambiguous layouts refused), the checks of each block's
values (:func:`check_block`) and the conventions the data show (:func:`data_notes`)."""
from __future__ import annotations

import numpy as np

from ..compute import pointwise
from ..model import measurables
from . import files

ANGLES = ("theta_i", "theta_r", "phi")
#: The incident light's normalised Stokes vector per measurement (shared (M,) or per pixel; absent:
#: 0, unpolarised light).
INCIDENT = measurables.INCIDENT
#: The polarimetric quantities a stack may hold over the measurements (normalised: S1..S3 over S0,
#: M_ij over M00; the AoP in degrees), fitted as channels (:mod:`pbrdf_cl.model.measurables`).
POLARIMETRIC = ("aop", "s1", "s2", "s3") + tuple(m for m in measurables.MUELLER if m != "m00")
#: Every measured quantity a stack may hold (NaN: not measured at that pixel and measurement).
MEASURED = ("dop",) + POLARIMETRIC
VARIABLES = (MEASURED + ANGLES + tuple(f"{n}_std" for n in MEASURED) + INCIDENT
             + ("f00", "s0", "f00_std", "mask"))
#: Variables that may be shared over the pixels, shape (M,).
SHARED = ANGLES + INCIDENT
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


def _axis_of_lengths(shape, lengths, dims=None, ref="dop"):
    """The axis of ``shape`` (dop's, or the measured variable ``ref``'s) holding the measurements,
    from the lengths of the shared (1-d) angles ``lengths`` (name -> length); None without any.  The
    last axis when its length matches (the documented layout), else the one axis that does;
    one-line errors for lengths that differ, match no axis, or match several (ambiguous)."""
    if not lengths:
        return None
    if len(set(lengths.values())) > 1:
        given = ", ".join(f"{n} {m}" for n, m in lengths.items())
        raise ValueError(f"data: the shared angles differ in length ({given}); give each one value per measurement")
    (name, m), = list(lengths.items())[:1]
    axes = [a for a, size in enumerate(shape) if size == m]
    named = (lambda a: f"{dims[a]!r}") if dims else (lambda a: str(a))
    if not axes:
        raise ValueError(f"data: {name} has {m} values (one per measurement) but no axis of {ref} {tuple(shape)} has "
                         f"{m}; give {ref}'s measurements along one axis (last: shape (..., {m}))")
    if len(shape) - 1 in axes:
        return len(shape) - 1
    if len(axes) > 1:
        which = ", ".join(map(named, axes))
        raise ValueError(f"data: {ref} {tuple(shape)} has {len(axes)} axes of length {m} ({which}), the number of "
                         f"{name} values: which holds the measurements is ambiguous; put them last ({ref} of shape "
                         f"(..., {m}))")
    return axes[0]


def _check_measurement_axis(samples, axis, dims, shape, ref="dop"):
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
            f"data: {ref}'s {name(axis)} is taken for the measurements, but the per-pixel angles change along it as "
            f"across an image's pixels (neighbours differ by {steps[axis]:.2g} degrees, median) and along "
            f"{name(worst)} as between measurements ({steps[worst]:.3g} degrees); put the measurements last: "
            f"{fix} for {ref} and the per-pixel angles (or give the angles shared, shape (M,))")


def measured_of(names):
    """The measured quantities among ``names`` (:data:`MEASURED`), in that order."""
    return [n for n in MEASURED if n in names]


#: The variables of a stack, for messages.
VARIABLES_TEXT = ("dop, aop, s1, s2, s3, m01 .. m33 (each with its optional <name>_std), theta_i, theta_r, phi, "
                  "in_s1, in_s2, in_s3, f00 or s0, f00_std, mask")


class Source:
    """The input stack: variables as arrays (numpy or lazy xarray/dask) of the shape of its first
    measured quantity ``ref`` (``dop``, or ``s1``, ...: :data:`MEASURED`; leading pixel dimensions,
    then M measurements) or, for the angles and the incident state, shared (M,).

    The measurement axis of ``ref`` is the one the shared (1-d) angles run along (a Dataset's
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
            self._read_dataset(data)
        elif isinstance(data, dict):
            self._read_dict(data)
        else:
            raise ValueError(f"data must be an xarray.Dataset, a dict of arrays or a path to a stack, got "
                             f"{type(data).__name__}")
        self._check_variables()

    def _read_dataset(self, data):
        """The variables of a Dataset, the measurement dimension moved last (lazy where they are)."""
        measured = measured_of(data.data_vars)
        if not measured:
            raise ValueError(f"data: no measured variable ({', '.join(MEASURED[:5])}, ...); the dataset has "
                             f"{', '.join(map(str, data.data_vars))}")
        self.ref = ref = measured[0]
        dop = data[ref]
        if dop.ndim < 2:
            raise ValueError(f"data: {ref} must have pixel dimensions and a measurement dimension, got dims "
                             f"{dop.dims}")
        for name in VARIABLES:
            if name in data and name != ref:
                extra = set(data[name].dims) - set(dop.dims)
                if extra:
                    raise ValueError(f"data: {name} has dimensions {sorted(extra)} that {ref} does not have")
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
            _check_measurement_axis(samples, dims.index(mdim), dims, tuple(dop.shape), ref)
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
            v = dop if name == ref else data[name]
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

            from ..errors import DataWarning
            warnings.warn(f"data: variable{'s' if len(unread) > 1 else ''} {', '.join(unread)} "
                          f"over the measurements not read (fit_batch reads {VARIABLES_TEXT})",
                          DataWarning, stacklevel=5)
        self.shape = tuple(dop.shape[:-1])
        self.M = int(dop.shape[-1])

    def _read_dict(self, data):
        """The arrays of a dict, the measurement axis moved last."""
        unknown = set(data) - set(VARIABLES) - set(ACCEPTED) - {"mdim", "dims"}
        if unknown:
            from ..ranges import did_you_mean
            bad = sorted(unknown)[0]
            near = did_you_mean(bad, VARIABLES)
            raise ValueError(f"data: unknown variable {bad!r}" + (f" (did you mean {near!r}?)" if near else "")
                             + f"; variables are {VARIABLES_TEXT}")
        measured = measured_of(data)
        if not measured:
            raise ValueError(f"data: no measured array ({', '.join(MEASURED[:5])}, ...)")
        self.ref = ref = measured[0]
        arrays = {}
        for name in VARIABLES:
            v = data.get(name)
            if v is not None:
                arrays[name] = v if hasattr(v, "shape") else np.asarray(v, float)
        dop = arrays[ref]
        if len(dop.shape) < 2:
            raise ValueError(f"data: {ref} must have shape (..., M): pixel dimensions then M measurements, "
                             f"got shape {tuple(dop.shape)}")
        nd = len(dop.shape)
        lengths = {a: int(arrays[a].shape[0]) for a in ANGLES
                   if a in arrays and len(arrays[a].shape) == 1 and arrays[a].shape[0] > 1}
        axis = _axis_of_lengths(tuple(dop.shape), lengths, ref=ref)
        if axis is None:
            axis = nd - 1
            samples = {a: np.asarray(arrays[a][(slice(0, AXIS_SAMPLE),) * len(arrays[a].shape)], float)
                       .reshape((1,) * (nd - len(arrays[a].shape)) + tuple(min(s, AXIS_SAMPLE)
                                                                           for s in arrays[a].shape))
                       for a in ANGLES if a in arrays and 1 < len(arrays[a].shape) <= nd}
            _check_measurement_axis(samples, axis, None, tuple(dop.shape), ref)
        if axis != nd - 1:  # the measurements last; every array over dop's axes moved alike
            for name, v in list(arrays.items()):
                if name == "mask" or (name in SHARED and len(v.shape) == 1) or len(v.shape) == 0:
                    continue
                if len(v.shape) > nd:
                    continue  # refused below, with its shape
                v = v.reshape((1,) * (nd - len(v.shape)) + tuple(v.shape))
                arrays[name] = np.moveaxis(v, axis, -1)
            dop = arrays[ref]
        self.shape, self.M = tuple(dop.shape[:-1]), int(dop.shape[-1])
        nd = len(self.shape)
        self.dims = tuple(data.get("dims") or (("y", "x") if nd == 2 else ("pixel",) if nd == 1
                                                else tuple(f"dim_{i}" for i in range(nd))))
        self.mdim = data.get("mdim", "measurement")
        self.vars = {ref: dop}
        for name in VARIABLES:
            v = arrays.get(name)
            if v is None or name == ref:
                continue
            full = self.shape if name == "mask" else tuple(dop.shape)
            if name != "mask" and tuple(v.shape) in ((self.M,), ()) and name in SHARED:
                v = np.broadcast_to(np.asarray(v, float), (self.M,))
            else:
                try:
                    np.broadcast_shapes(tuple(v.shape), full)
                except ValueError:
                    raise ValueError(f"data: {name} of shape {tuple(v.shape)} does not broadcast to "
                                     f"{'the pixel shape' if name == 'mask' else ref}'s shape {full}") from None
            self.vars[name] = v

    def _check_variables(self):
        """The checks of the variables every kind of input has once read."""
        if 0 in self.shape:
            raise ValueError(f"data: {self.ref} has no pixels (shape {self.shape + (self.M,)}: pixel dimensions "
                             f"{self.shape}); give a stack with at least one pixel")
        if self.M < 2:
            raise ValueError(f"data: {self.ref} has {self.M} measurement{'' if self.M == 1 else 's'} per pixel; "
                             "a fit needs several")
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
        for name in tuple(f"{n}_std" for n in MEASURED) + ("f00_std",):
            v = self.vars.get(name)
            if v is not None and name != "f00_std" and name[:-4] not in self.vars:
                raise ValueError(f"data: {name} is given without {name[:-4]}")
            if v is not None and np.ndim(v) == 0 and np.isnan(float(np.asarray(v))):
                raise ValueError(f"data: {name} is NaN (one value for every measurement): give the noise std (> 0)"
                                 + (f", or leave {name} out to estimate each pixel's noise from its residuals"
                                    if name != "f00_std" else ""))
        if len(self.dims) != len(self.shape):
            raise ValueError(f"data: dims {self.dims} do not match {self.ref}'s pixel dimensions {self.shape}")
        #: the measured quantities of the stack (:data:`MEASURED`), in that order
        self.measured = measured_of(self.vars)
        self.shared = all(np.ndim(self.vars[a]) == 1 for a in SHARED if a in self.vars)
        self.n_pixels = int(np.prod(self.shape, dtype=np.int64))

    def rows(self, r0, r1):
        """The pixels of rows r0..r1 of the first pixel dimension, flat: dict name -> (p, M) float64
        (angles (M,) when shared; mask (p,))."""
        import xarray as xr
        out = {}
        for name, v in self.vars.items():
            if np.ndim(v) == 1 and name in SHARED:
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
    """An image stack from a file, as the ``xarray.Dataset`` :func:`pbrdf_cl.fit_batch` takes.

    Parameters
    ----------
    path : str or path
        ``.npz`` (arrays named as :func:`pbrdf_cl.fit_batch`'s variables: ``dop`` of shape (y, x, M), the
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
    >>> pbrdf_cl.io.source.open_stack(path).dop.dims
    ('y', 'x', 'm')
    """
    import pathlib

    import xarray as xr
    p = pathlib.Path(path)
    if not p.exists():
        raise ValueError(f"stack {str(p)!r} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        arrays = files.read_npz(p)
        if any(k.endswith(".dims") for k in arrays):  # written by pbrdf_cl.io.imagestack.save_stack
            from .imagestack import load_stack
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

            from ..errors import DataWarning
            warnings.warn(f"{p}: arrays not read (their shapes fit neither dop {shape}, its pixels "
                          f"nor its measurements): {', '.join(skipped)}", DataWarning, stacklevel=2)
        return ds
    if suffix in (".nc", ".h5", ".netcdf"):
        # lazily, and without keeping what is read: a block of rows read is dropped once used,
        # never the whole variable loaded (xarray's cache would keep every variable read whole)
        return files.open_netcdf(p, cache=False)
    if suffix == ".zarr" or (p / ".zgroup").exists() or (p / "zarr.json").exists():
        try:
            return xr.open_zarr(p)
        except Exception as exc:  # noqa: BLE001 - zarr's many errors of a folder that is no store: one line of ours
            raise ValueError(f"{p}: not a readable Zarr store ({files.first_line(exc)})") from None
    raise ValueError(f"stack {str(p)!r}: unknown format {suffix!r}; use .npz, .nc or .zarr")


def open_stack_lazily(path):
    """A stack path as a Dataset read a block at a time (for a store's fit): :func:`open_stack`,
    whose ``.nc`` and ``.zarr`` stacks are read lazily, a block of rows at a time (a ``.nc`` stack
    is not made one dask chunk, which every block would read whole)."""
    return open_stack(path)

def check_block(block, r0, source):
    """Validate a block's values; errors name the variable and the first offending index (of the
    full stack)."""
    def where(name, flat_index):
        if np.ndim(block[name]) == 1 and name in SHARED:
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
    if "dop" in block:
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
    rules = [(f"{n}_std", "> 0 (NaN for a missing measurement)", lambda a: np.isnan(a) | (a > 0)) for n in MEASURED]
    rules += [("f00", ">= 0 (NaN for a missing measurement)", lambda a: np.isnan(a) | (a >= 0)),
              ("f00_std", "> 0", lambda a: np.isnan(a) | (a > 0))]
    for name, rule, ok in rules:
        if name in block:
            bad = ~ok(block[name])
            if bad.any():
                raise ValueError(f"{name} must be {rule}, got {first(name, bad)}")
    # a NaN std marks a missing measurement only where the value is missing too: a measured value
    # without its std is refused (as pbrdf_cl.fit refuses it), not silently left out
    for name, value in [(f"{n}_std", n) for n in MEASURED] + [("f00_std", "f00")]:
        if name in block and value in block:
            bad = np.isnan(block[name]) & ~np.isnan(block[value])
            if bad.any():
                i = int(np.argmax(bad.reshape(-1)))
                raise ValueError(f"{name} is NaN at index {where(name, i)} where {value} is "
                                 f"{float(block[value].reshape(-1)[i])!r}: give that measurement's std (> 0), or "
                                 f"NaN in {value} too to leave it out as missing")
    _check_polarimetric(block, where, first, source)


def _check_polarimetric(block, where, first, source):
    """The checks of a block's polarimetric values and incident states (:mod:`pbrdf_cl.io.polar`'s,
    each refusal naming the first offending index)."""
    from ..io import polar
    if "aop" in block:
        bad = np.isinf(block["aop"])
        if bad.any():
            raise ValueError(f"aop must be finite (degrees; NaN for a missing measurement), got {first('aop', bad)}")
    given = sorted((n for n in INCIDENT if n in block), key=lambda n: -np.ndim(block[n]))  # per pixel first
    if given:
        inc = [np.broadcast_to(block[n], block[given[0]].shape) for n in given]
        for n, a in zip(given, inc):
            bad = ~np.isfinite(a)
            if bad.any():
                raise ValueError(f"{n} must be finite (the incident state of every measurement; 0, 0, 0 for "
                                 f"unpolarised light), got {first(n, bad)}")
        norm2 = sum(a * a for a in inc)
        bad = norm2 > 1.0 + 1e-9
        if bad.any():
            i = int(np.argmax(bad.reshape(-1)))
            state = ", ".join(f"{n} = {float(a.reshape(-1)[i]):g}" for n, a in sorted(zip(given, inc)))
            raise ValueError(f"the incident state at index {where(given[0], i)} ({state}) is not a Stokes vector: "
                             f"in_s1^2 + in_s2^2 + in_s3^2 = {float(norm2.reshape(-1)[i]):.4g} > 1 (normalised by S0)")
    names = [n for n in POLARIMETRIC if n in block and n != "aop"]
    if names:
        cols = {k: np.broadcast_to(block[k], block[names[0]].shape).reshape(-1)
                for k in names + [f"{n}_std" for n in names if f"{n}_std" in block]}
        polar.check_normalised(cols, lambda i: f"data at index {where(names[0], int(i))}")


def data_notes(source):
    """Notes on the conventions the stack shows by itself: phi not given (every measurement in
    plane), phi = 0 and angles below 1.6 degrees in the first row of pixels (as
    :func:`pbrdf_cl.fit`'s notes)."""
    from .measurements import PHI_DEFAULT_NOTE
    notes = [] if source.phi_given else [PHI_DEFAULT_NOTE]
    raw = source.rows(0, 1)
    hi = pointwise.radians_suspect(raw["theta_i"], raw["theta_r"])
    if hi is not None:
        notes.append(f"every theta_i and theta_r of the first row lies below {pointwise.RADIANS_HINT} degrees (the "
                     f"largest is {hi:.4g}): radians? pbrdf-cl takes degrees")
    if source.phi_given and np.all(np.asarray(raw["phi"]) == 0.0):
        notes.append("phi = 0 for every measurement of the first row: that is the plane of incidence on the source's "
                     "side (back-scattering); in-plane specular data have phi = 180 here (SCATMECH's phi = 0 is our "
                     "180)")
    dup = repeated_measurements_note(raw, source.M)
    if dup:
        notes.append(dup)
    return notes


def repeated_measurements_note(raw, M):
    """A note where measurements of the stack repeat an earlier one exactly (the geometry, the
    incident state and every measured value of every pixel of the rows ``raw``), else None: each
    pixel's fit counts every measurement as an independent one (its chi2, p-value and intervals),
    as :func:`pbrdf_cl.io.measurements.duplicates_note` says of a CSV's rows."""
    cols = [np.asarray(a, np.float64).reshape(-1, M).T for name, a in raw.items() if name != "mask"]
    table = np.ascontiguousarray(np.concatenate(cols, axis=1))  # (M, values per measurement)
    _, first, counts = np.unique(table, axis=0, return_index=True, return_counts=True)
    repeats = M - first.size
    if not repeats:
        return None
    j = int(np.flatnonzero(np.isin(np.arange(M), first, invert=True))[0])
    same = (table == table[j]) | (np.isnan(table) & np.isnan(table[j]))
    i = int(np.flatnonzero(same.all(axis=1))[0])
    return (f"{repeats} of the {M} measurements repeat an earlier one exactly (geometry and the values of every pixel "
            f"of the first row; e.g. measurement {j} repeats {i}), up to {int(counts.max())} copies: each pixel's fit "
            "counts each as an independent measurement (in its chi2, p-value and intervals); if they are copies of one "
            "measurement, remove them (the intervals are otherwise too narrow)")
