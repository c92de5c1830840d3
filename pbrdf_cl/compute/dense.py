"""Dense grids: the model over Cartesian products of angles and parameters, on-device
reductions, and the least-squares objective used by the inversion.

The Cartesian product is never materialised on the host.  The model factorises as

    DOP = (Rs - Rp) / (Rs + Rp + 2 fd / K),    F00 = K (Rs + Rp) / 2 + fd,

with Rs +- Rp depending on (geometry, n, k), K on (geometry, sigma, ks) and fd on
(geometry, kd, c); AoP and the Stokes vector also need the outgoing frame's rotation, which
depends on the geometry alone.  These tables are computed once by ``kernels/pbrdf_tables.cl``
(with the device functions of ``pbrdf.h``) and combined per grid point by
``kernels/pbrdf_grid.cl`` (``pb_grid_<quantity>``), which decodes the flat grid index itself.
What each quantity needs (which tables, its width, units) is its record in
:mod:`pbrdf_cl.model.quantities`.  Grids whose device memory would exceed
``memory_budget`` bytes run in chunks.

On the numpy backend (:class:`pbrdf_cl.device.engine.NumpyEngine`) the same tables are built with the
functions of ``reference.py`` (:class:`NumpyTables`, the mirror of ``pbrdf_tables.cl``) and
combined with ``reference.grid_<quantity>`` over boxes of the grid, each within
the same ``memory_budget``; values are float64 whatever ``dtype`` asks for, then cast to it.
Each computation that differs between the backends is an operation with one implementation per
backend (:mod:`pbrdf_cl.device.ops`: ``grid_blocks``, ``reduce_grid``, ``objective_blocks``,
``objective_points``, ``outer``), which the public functions run with ``eng.call``.  The objective
of several data sets measured at one geometry (:func:`objective_sets`, for the joint fits) makes
each block's tables once and combines each grid point's DOP once for all of them.

Axes are ordered canonically: theta_i, theta_r, phi, n, k, sigma, ks, kd, c.
"""
from __future__ import annotations

import time

import numpy as np

from .. import sizes
from ..device import engine as _engine
from ..device import ops
from ..device.engine import DTYPES, VECTOR_LOCAL_SIZE, aligned_empty, resolve_engine
from ..model import inputs, quantities, reference
from ..model.measurables import Channels
from . import channels, pointwise
from .tables import factor_table, row_blocks, summed_over_rows

#: The grid's canonical axes: every input of the model (:mod:`pbrdf_cl.model.inputs`), in its order.
AXES = inputs.NAMES
PARAMETERS = inputs.PARAMETERS
UNITS, LONG_NAMES, DEFAULTS = inputs.UNITS, inputs.LONG_NAMES, inputs.DEFAULTS
#: The quantities with a grid path: name -> long name (the registry, :mod:`pbrdf_cl.quantities`, says more).
QUANTITIES = {n: quantities.REGISTRY[n].long_name for n in quantities.names("grid")}
DEFAULT_BUDGET = 1 << 30
#: Family (0 geometry, 1 n-k, 2 sigma-ks, 3 kd-c) of each canonical axis.
FAMILY = {n: inputs.family_index(n) for n in AXES}
#: The model's parameters that a grid or a list of points may leave out, with their values then.
PARAMETER_DEFAULTS = {n: v for n, v in DEFAULTS.items() if n in PARAMETERS}


def family_strides(counts):
    """The stride of each canonical axis within its family's factor table (row-major over the
    family's axes in canonical order: theta_i's stride is the count of theta_r times phi's)."""
    return {n: int(np.prod([counts[m] for m in AXES[i + 1:] if FAMILY[m] == FAMILY[n]], dtype=np.int64))
            for i, n in enumerate(AXES)}


class GridPlan:
    """Validated axes (every canonical axis as a 1-d float64 array, fixed ones of length 1)."""

    def __init__(self, axes, fixed=None, names=AXES, defaults=DEFAULTS):
        axes = dict(axes or {})
        fixed = dict(fixed or {})
        for where, d in (("axes", axes), ("fixed", fixed)):
            for name in d:
                if name not in names:
                    raise ValueError(f"{where}: unknown axis {name!r}; valid names are {', '.join(names)}")
        both = set(axes) & set(fixed)
        if both:
            raise ValueError(f"{sorted(both)[0]!r} is given both as an axis and as a fixed value")
        self.names = tuple(names)
        self.axis_names = tuple(n for n in names if n in axes)
        self.values = {}
        for name in names:
            if name in axes:
                a = axes[name]  # a numeric array as is (an object copy of 10^7 values is 320 MB)
                a = a if isinstance(a, np.ndarray) and a.dtype.kind in "fiu" else np.asarray(a, dtype=object)
                if a.ndim != 1:
                    raise ValueError(f"axis {name} must be a 1-d array, got shape {a.shape}")
                if a.size == 0:
                    raise ValueError(f"axis {name} is empty")
                a = pointwise.check_values(name, axes[name])
                up = a[1:] > a[:-1]  # 1 byte a value, where np.diff takes 8
                if a.size > 1 and not (np.all(up) or np.all(a[1:] < a[:-1])):
                    bad = int(np.argmax(~up) if up[0] else np.argmax(a[1:] >= a[:-1])) + 1
                    raise ValueError(f"axis {name} must be strictly increasing or decreasing; "
                                     f"value {float(a[bad])!r} at index {bad} breaks it")
            elif name in fixed:
                a = pointwise.check_values(name, fixed[name])
                if a.ndim != 0:
                    raise ValueError(f"fixed value {name} must be a scalar, got shape {a.shape}; "
                                     f"give it as an axis instead")
                a = a.reshape(1)
            elif name in defaults:
                a = np.array([defaults[name]])
            else:
                raise ValueError(f"{name} is required: give it as an axis or a fixed value")
            self.values[name] = a
        self.sizes = {name: self.values[name].size for name in names}

    def check_degrees(self, where=""):
        """Warn (:class:`pbrdf_cl.compute.pointwise.UnitsWarning`) when the zenith angles, axes or fixed values,
        all look like radians (:func:`pbrdf_cl.compute.pointwise.check_degrees`)."""
        if "theta_i" in self.values and "theta_r" in self.values:
            pointwise.check_degrees(self.values["theta_i"], self.values["theta_r"], where)

    @property
    def shape(self):
        return tuple(self.sizes[n] for n in self.axis_names)

    @property
    def size(self):
        return int(np.prod([self.sizes[n] for n in self.names], dtype=np.int64))

    def fixed_values(self):
        return {n: float(self.values[n][0]) for n in self.names if n not in self.axis_names}

    def fixed_attrs(self):
        """The fixed values as DataArray attrs, ``fixed_<name>``."""
        return {f"fixed_{k}": v for k, v in self.fixed_values().items()}

    def coords(self):
        import xarray as xr
        return {n: xr.Variable((n,), self.values[n], {"units": UNITS[n], "long_name": LONG_NAMES[n]})
                for n in self.axis_names}


class Tables:
    """Device tables of the factorised model for a geometry list and parameter axes."""

    def __init__(self, engine, dtype, shadowing, quantity, ti, tr, ph, v):
        """Tables laid out geometry by geometry: table[g * n_params + param]; the factors and
        the frame table as the registry's record of ``quantity`` says."""
        q = quantities.get(quantity)
        kern = engine.program("pbrdf_tables.cl", dtype, {"PBRDF_SHADOWING": pointwise.reference.SHADOWING[shadowing]})
        npdt = DTYPES[dtype]
        ng = ti.size
        geo = [engine.to_device(a, dtype) for a in (ti, tr, ph)]

        def table(kname, outs, p1, p2, *extra):
            return factor_table(engine, kern, kname, outs, geo, ng, p1, p2, npdt, *extra)

        self.sum, self.diff = table("fresnel_table", 2, v["n"], v["k"])
        self.scale, = table("scale_table", 1, v["sigma"], v["ks"], npdt(q.scale_sign))
        self.dif, = table("diffuse_table", 1, v["kd"], v["c"], npdt(q.diffuse_factor))
        self.frame = engine.empty(2 * ng * np.dtype(npdt).itemsize if q.frame else 1)
        if q.frame:
            engine.launch(kern["frame_table"], (ng,), self.frame, np.int32(ng), *geo)

    def args(self):
        return self.sum, self.diff, self.scale, self.dif, self.frame


class NumpyTables:
    """The tables of :class:`Tables` computed with ``reference.py`` in float64 (the mirror of
    ``kernels/pbrdf_tables.cl``): ``sum``, ``diff`` (ng, n_n * n_k), ``scale`` (ng, n_sigma * n_ks),
    ``dif`` (ng, n_kd * n_c), and :meth:`combine`, the per-point step of ``pbrdf_grid.cl``.

    Package-internal interface (the numpy backend's grids here, and the per-pixel fit's grid
    stage): ``NumpyTables(shadowing, quantity, ti, tr, ph, values)`` over the geometry list
    ``ti, tr, ph`` and the parameter axes ``values`` (name -> 1-d array), then :meth:`box` or
    :meth:`combine` of the tables reshaped as the caller needs."""

    #: float64 bytes per table entry and per grid point of a box (the values and ~3 temporaries)
    BYTES_PER_POINT = 32

    def __init__(self, shadowing, quantity, ti, tr, ph, v):
        q = quantities.get(quantity)
        self.combine_fn = getattr(reference, f"grid_{q.name}")
        variant = reference.SHADOWING[shadowing]
        g = reference.geometry(np.asarray(ti, float)[:, None], np.asarray(tr, float)[:, None],
                               np.asarray(ph, float)[:, None])
        ng = len(ti)

        def pairs(first, second):  # the parameter pairs i_first * n_second + i_second
            return np.repeat(first, second.size)[None, :], np.tile(second, first.size)[None, :]

        def full(a, n2):
            return np.ascontiguousarray(np.broadcast_to(a, (ng, n2)))
        nn, kk = pairs(v["n"], v["k"])
        f = reference.fresnel(nn, kk, g.cb, g.sb)
        self.sum, self.diff = full(f.Rs + f.Rp, nn.size), full(f.diff, nn.size)
        sigma, ks = pairs(v["sigma"], v["ks"])
        log_k = reference.log_specular_scale(g, sigma, ks, reference.shadowing_factor(g, sigma, variant))
        with np.errstate(over="ignore"):
            self.scale = full(np.exp(q.scale_sign * log_k), sigma.size)
        kd, c = pairs(v["kd"], v["c"])
        self.dif = full(q.diffuse_factor * reference.diffuse(g, kd, c), kd.size)
        self.C, self.S = reference.out_rotation2(g, np.asarray(ph, float)[:, None]) if q.frame else (1.0, 0.0)

    def combine(self, sum_, diff, dif, scale, C=1.0, S=0.0):
        return self.combine_fn(sum_, diff, dif, scale, C, S)

    def box(self, geo_shape, sizes, box):
        """Values over ``box`` (slices over the geometry dims ``geo_shape`` then n, k, sigma, ks,
        kd, c, of ``sizes``): an array of the box's shape, float64."""
        n_n, n_k, n_s, n_ks, n_kd, n_c = sizes
        ng = len(geo_shape)
        gsl, psl = tuple(box[:ng]), box[ng:]

        def part(table, a, b, first):  # the table over the box, its two axes at first, first + 1
            t = table.reshape(tuple(geo_shape) + (a, b))[gsl + (psl[first], psl[first + 1])]
            dims = [1] * 6
            dims[first:first + 2] = t.shape[ng:]
            return t.reshape(t.shape[:ng] + tuple(dims))
        sum_ = part(self.sum, n_n, n_k, 0)
        diff = part(self.diff, n_n, n_k, 0)
        scale = part(self.scale, n_s, n_ks, 2)
        dif = part(self.dif, n_kd, n_c, 4)
        C, S = self.C, self.S
        if not np.isscalar(C):  # (ng, 1) over the geometry dims of the box
            C, S = (t.reshape(tuple(geo_shape) + (1,) * 6)[gsl] for t in (C, S))
        return self.combine(sum_, diff, dif, scale, C, S)


def _boxes(shape, max_elems):
    """Boxes (tuples of slices) covering an array of ``shape`` in C order, each of at most
    ``max_elems`` elements and contiguous in the flattened array: trailing axes whole, one axis
    split into ranges, leading axes one index at a time.  Yields ``(flat start, box)``."""
    shape = tuple(int(n) for n in shape)
    max_elems = max(1, int(max_elems))
    tail, split = 1, None
    for i in range(len(shape) - 1, -1, -1):
        if tail * shape[i] > max_elems:
            split = i
            break
        tail *= shape[i]
    if split is None:
        yield 0, tuple(slice(0, n) for n in shape)
        return
    step = max(1, max_elems // tail)
    whole = tuple(slice(0, n) for n in shape[split + 1:])
    for lead in np.ndindex(*shape[:split]):
        for a in range(0, shape[split], step):
            start = int(np.ravel_multi_index(lead + (a,) + (0,) * len(whole), shape))
            yield start, tuple(slice(i, i + 1) for i in lead) + (slice(a, min(a + step, shape[split])),) + whole


def _param_sizes(plan):
    return tuple(plan.sizes.get(n, 1) for n in PARAMETERS)


@ops.implements("grid_blocks", "numpy")
def _numpy_grid_blocks(eng, plan, quantity, dtype, shadowing, memory_budget, progress, out):
    """:func:`grid_blocks` on the numpy backend: geometry rows in blocks whose float64 tables
    take at most half of ``memory_budget``, each block's grid in boxes within the other half."""
    ng, nnk, nm, ni = family_sizes(plan)
    sizes = _param_sizes(plan)
    per_g = nnk * nm * ni
    table_row, rows = _geometry_rows(plan, memory_budget, 8, NumpyTables.BYTES_PER_POINT)
    bar = progress_bar(plan.size, progress, f"grid {quantity} (numpy)")
    width = quantities.get(quantity).width
    for g0 in range(0, ng, rows):
        g1 = min(ng, g0 + rows)
        tables = NumpyTables(shadowing, quantity, *geometry_list(plan, g0, g1), plan.values)
        room = (memory_budget - (g1 - g0) * table_row) // (NumpyTables.BYTES_PER_POINT * width)
        for start, box in _boxes((g1 - g0,) + sizes, room):
            values = tables.box((g1 - g0,), sizes, box)
            count = values.size // width
            start += g0 * per_g
            host = (out[start * width:(start + count) * width] if out is not None
                    else np.empty(count * width, dtype=DTYPES[dtype]))
            host[...] = values.reshape(-1)
            if bar is not None:
                bar.update(count)
            yield start, host
    if bar is not None:
        bar.close()


def _geometry_rows(plan, memory_budget, itemsize, point_bytes):
    """(bytes of one geometry row's tables, geometry rows per block): the tables of a block take at
    most half of ``memory_budget``, the other half holds at least 64 points of ``point_bytes``."""
    ng, nnk, nm, ni = family_sizes(plan)
    table_row = table_bytes(1, nnk, nm, ni, itemsize)
    if memory_budget < 2 * table_row + 64 * point_bytes:
        raise ValueError(f"memory_budget={memory_budget} bytes is too small for one geometry row's tables "
                         f"({table_row} bytes); raise it")
    return table_row, int(max(1, min(ng, (memory_budget // 2) // table_row)))


def table_bytes(n_geometries, nnk, nm, ni, itemsize):
    """Bytes of the factor tables for ``n_geometries`` geometries (or measurements) and family sizes
    nnk (n x k), nm (sigma x ks), ni (kd x c): the Fresnel sum and difference, the scale, the diffuse
    term and the frame rotation (C, S) per geometry."""
    return int(n_geometries) * (2 * nnk + nm + ni + 2) * int(itemsize)


def _table_itemsize(eng, dtype):
    """Bytes per table entry: those of the precision the engine computes ``dtype`` in (float64 on
    the numpy backend)."""
    return np.dtype(DTYPES[eng.compute_dtype(dtype)]).itemsize


def geometry_list(plan, g0, g1):
    """The (theta_i, theta_r, phi) triples of geometry rows g0..g1 (row-major over the three axes)."""
    g = np.arange(g0, g1)
    n_tr, n_ph = plan.sizes["theta_r"], plan.sizes["phi"]
    return (plan.values["theta_i"][g // (n_tr * n_ph)], plan.values["theta_r"][(g // n_ph) % n_tr],
            plan.values["phi"][g % n_ph])


def family_sizes(plan):
    """Sizes of the families (geometry, n-k, sigma-ks, kd-c); an axis the plan lacks counts 1."""
    s = {n: plan.sizes.get(n, 1) for n in AXES}
    return (s["theta_i"] * s["theta_r"] * s["phi"], s["n"] * s["k"], s["sigma"] * s["ks"], s["kd"] * s["c"])


def grid_program(eng, dtype, sizes, idx_name, quantity, prefix="", **extra):
    """The kernels of pbrdf_grid.cl for family sizes (nnk, nm, ni), index type and quantity (its
    registry record's defines); ``extra`` are further -D defines (None: defined without a value)."""
    nnk, nm, ni = sizes
    defines = {"PB_NNK": nnk, "PB_NM": nm, "PB_NI": ni, "PB_INDEX": idx_name,
               **quantities.get(quantity).defines(), **extra}
    return eng.program("pbrdf_grid.cl", dtype, defines, prefix)


#: Grids (and reductions, objectives) of this many points or more use 64-bit indices in the kernels.
INDEX32_LIMIT = 2 ** 32 - 2


def _index_type(total):
    return ("uint", np.uint32) if total < INDEX32_LIMIT else ("ulong", np.uint64)


def _check_quantity(quantity, path="grid"):
    """The registry's record of ``quantity`` (name or alias), or a ``ValueError`` unless it has ``path``."""
    return quantities.get(quantity, path)


def progress_bar(total, enabled, desc, unit="pt"):
    """A tqdm progress bar of ``total`` units, shown once the work takes more than a second, or
    None when not ``enabled`` (or without tqdm).  Package-internal: the grids here, the sensitivity
    analyses."""
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        return None
    return tqdm(total=total, desc=desc, unit=unit, unit_scale=True, leave=False, delay=1.0)  # only if > 1 s


@_engine.falls_back
def grid(axes, fixed=None, quantity="dop", dtype="float32", shadowing="paper", *, engine=None, backend="auto",
         memory_budget=DEFAULT_BUDGET, progress=False, allow_large=False):
    """Evaluate ``quantity`` ("dop", "brdf" (alias "f00"), "aop" or "stokes") over the Cartesian
    product of ``axes``.

    Parameters
    ----------
    axes : dict
        Name -> 1-d strictly monotonic array, for any of theta_i, theta_r, phi (degrees), n, k,
        sigma, ks, kd, c.
    fixed : dict
        Name -> scalar for the remaining inputs; phi, ks, kd, c default to 180, 1, 0, 0.
    memory_budget : int or str
        Bytes of device memory a chunk may use (tables plus output), or a size such as "64 MiB"
        or "1 GB" (:func:`pbrdf_cl.ranges.parse_bytes`); larger grids run in chunks.
    engine, backend : the engine, or "auto" / "opencl" / "numpy" (see :func:`pbrdf_cl.device.engine.resolve_engine`)
    quantity : {"dop", "brdf", "aop", "stokes"}, default "dop"
        See :mod:`pbrdf_cl.quantities` ("f00" is "brdf").
    dtype : {"float32", "float64"}, default "float32"
    shadowing : {"paper", "smith", "none"}, default "paper"
    progress : bool, default False
        A progress bar (tqdm) when the grid takes more than a second.
    allow_large : bool, default False
        Return a result larger than ``pbrdf_cl.sizes.LARGE_RESULT`` (2 GiB); without it such a
        grid is refused before any work (:func:`reduce_grid` and ``pbrdf-cl sweep`` run in chunks).
        A result larger than the available memory is refused either way.

    Returns
    -------
    xarray.DataArray with the axes as dimensions in canonical order (then "stokes", S0..S3, for
    the Stokes vector), labelled coordinates with units, and the fixed values, quantity,
    shadowing and dtype in ``attrs``.  The AoP is NaN where it is undefined (DOP = 0).

    Raises
    ------
    ValueError
        Naming the axis and the bad value; :class:`pbrdf_cl.TooLargeError` when the result
        cannot fit in memory, or exceeds 2 GiB without ``allow_large`` (found before any work).

    Warns
    -----
    pbrdf_cl.compute.pointwise.UnitsWarning
        When theta_i and theta_r all lie below 1.6 degrees: radians, most likely.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> da = pbrdf_cl.grid(dict(theta_r=np.linspace(0, 85, 86), sigma=[0.1, 0.3, 0.5]),
    ...                    dict(theta_i=40, n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3))
    >>> da.dims, da.shape
    (('theta_r', 'sigma'), (86, 3))
    """
    import xarray as xr

    from ..ranges import parse_bytes
    memory_budget = parse_bytes("memory_budget", memory_budget)
    q = _check_quantity(quantity)
    dtype = pointwise.check_options(shadowing, dtype)
    plan = GridPlan(axes, fixed)
    plan.check_degrees()
    sizes.check_result(plan.size * q.width * np.dtype(DTYPES[dtype]).itemsize,
                       f"the grid of {' x '.join(map(str, plan.shape + q.trailing))} = {plan.size} points",
                       "use fewer values per axis, pbrdf_cl.reduce_grid (reductions on the device), or pbrdf-cl "
                       "sweep (chunk by chunk into a Zarr store)", allow_large)
    eng = resolve_engine(engine, backend)
    out = aligned_empty(plan.size * q.width, DTYPES[dtype])  # page-aligned: written in place by any CPU driver
    for _ in grid_blocks(eng, plan, q.name, dtype, shadowing, memory_budget, progress, out=out):
        pass  # each block is copied straight into its slice of out
    attrs = dict(quantity=q.name, long_name=q.long_name, units=q.units, shadowing=shadowing, dtype=dtype,
                 **plan.fixed_attrs())
    coords, dims = plan.coords(), plan.axis_names
    if q.components:
        coords[q.name] = list(q.components)
        dims = dims + (q.name,)
    return xr.DataArray(out.reshape(plan.shape + q.trailing), coords=coords, dims=dims, name=q.name, attrs=attrs)


#: Rows shorter than this leave the vector units idle; longer ones than ROW_MAX use too much
#: private memory (objective) or too few work-items.
ROW_MIN, ROW_MAX = 16, 4096


def row_level(nnk, nm, ni, ng, chunk, max_level=3):
    """(level, row length) for the row kernels, or (0, 1) for the one-point-per-work-item kernels."""
    for level, length, n_rows in ((1, ni, ng * nnk * nm), (2, nm * ni, ng * nnk), (3, nnk * nm * ni, ng)):
        if level > max_level:
            break
        if length >= ROW_MIN:
            if length <= min(ROW_MAX, chunk) and n_rows >= 8:
                return level, length
            break
    return 0, 1


@_engine.falls_back
def grid_blocks(eng, plan, quantity, dtype, shadowing, memory_budget, progress=False, out=None):
    """Yield (flat start, values) chunks of the grid in order, each within ``memory_budget``;
    with ``out`` (the whole flat grid) the values land in, and are views of, its slices.  The
    engine's operation ``"grid_blocks"``: the factor tables and ``pbrdf_grid.cl`` on a device, the
    same tables with ``reference.py`` on the numpy backend."""
    yield from eng.call("grid_blocks", plan, quantity, dtype, shadowing, memory_budget, progress, out)


@ops.implements("grid_blocks", "opencl")
def _device_grid_blocks(eng, plan, quantity, dtype, shadowing, memory_budget, progress, out):
    """:func:`grid_blocks` on an OpenCL device: geometry rows in blocks whose tables take at most
    half of ``memory_budget``, their grid in chunks of the rest (two, read back in turn, on a
    device with its own memory)."""
    width = quantities.get(quantity).width
    itemsize = np.dtype(DTYPES[dtype]).itemsize
    ng, nnk, nm, ni = family_sizes(plan)
    per_g = nnk * nm * ni  # grid points per geometry row
    table_row, rows = _geometry_rows(plan, memory_budget, itemsize, itemsize * width)
    chunk = int(max(64, min((memory_budget - rows * table_row) // (itemsize * width), 2 ** 31 // width - 1)))
    idx_name, idx_np = _index_type(plan.size)
    level, row_len = row_level(nnk, nm, ni, ng, chunk)
    prog = grid_program(eng, dtype, (nnk, nm, ni), idx_name, quantity, PB_ROW_LEVEL=level, PB_ROW_LEN=row_len)
    kern = prog["grid_rows" if level else "grid_values"]
    overlap = eng.overlaps_transfers  # a GPU: two output buffers, one read back while the other is computed
    if overlap:
        chunk = max(row_len, chunk // 2)
    chunk = chunk // row_len * row_len
    bufs = [eng.empty(chunk * width * itemsize) for _ in range(2)] if overlap else None
    bar = progress_bar(plan.size, progress, f"grid {quantity}")
    pending, k = None, 0
    for g0 in range(0, ng, rows):
        g1 = min(ng, g0 + rows)
        tables = Tables(eng, dtype, shadowing, quantity, *geometry_list(plan, g0, g1), plan.values)
        for start in range(g0 * per_g, g1 * per_g, chunk):
            count = min(chunk, g1 * per_g - start)
            host = (out[start * width:(start + count) * width] if out is not None
                    else np.empty(count * width, dtype=DTYPES[dtype]))
            if overlap:
                buf = bufs[k % 2]  # free: its read was waited for before the previous chunk was yielded
            else:
                buf, done = eng.output(host)  # on a CPU device the kernel writes into host itself
            if level:
                ran = eng.launch(kern, (count // row_len,), buf, idx_np(start // row_len), idx_np(count // row_len),
                                 idx_np(g0), *tables.args())
            else:
                ran = eng.launch(kern, (count,), buf, idx_np(start), idx_np(count), idx_np(g0), *tables.args())
            k += 1
            if bar is not None:
                bar.update(count)
            if not overlap:
                done()
                yield start, host
                continue
            read = eng.read_later(buf, host, [ran])
            if pending is not None:
                pending[2].wait()
                yield pending[:2]
            pending = (start, host, read)
    if pending is not None:
        pending[2].wait()
        yield pending[:2]
    if bar is not None:
        bar.close()


@_engine.falls_back
def reduce_grid(axes, fixed=None, over=(), quantity="dop", dtype="float32", shadowing="paper", *,
                engine=None, backend="auto", memory_budget=DEFAULT_BUDGET):
    """Min, argmin and mean of ``quantity`` over the axes ``over``, computed on the device
    without materialising the grid.

    Parameters
    ----------
    axes, fixed, dtype, shadowing, engine, backend, memory_budget
        As for :func:`grid`.
    over : str or sequence of str
        The axes to reduce (at least one of ``axes``).
    quantity : {"dop", "brdf"}, default "dop"
        The quantities whose registry record allows reductions ("f00" is "brdf").

    Returns
    -------
    xarray.Dataset
        Over the remaining axes: ``min``, ``mean`` and, for each reduced axis, ``argmin_<axis>``
        (that axis' coordinate value at the minimum).

    Raises
    ------
    ValueError
        For the AoP (an angle: its mean and minimum mean nothing) and the Stokes vector, saying
        why, and for bad axes.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> ds = pbrdf_cl.reduce_grid(dict(theta_i=[30, 40, 50], theta_r=np.linspace(0, 85, 86)),
    ...                           dict(n=1.6, k=2.1, sigma=0.3), over="theta_r")
    >>> sorted(ds.data_vars)
    ['argmin_theta_r', 'mean', 'min']
    """
    from ..ranges import parse_bytes
    memory_budget = parse_bytes("memory_budget", memory_budget)
    quantity = _check_quantity(quantity, "reduce").name
    dtype = pointwise.check_options(shadowing, dtype)
    plan = GridPlan(axes, fixed)
    plan.check_degrees()
    over = (over,) if isinstance(over, str) else tuple(over)
    if not over:
        raise ValueError("over: name at least one axis to reduce")
    for name in over:
        if name not in plan.axis_names:
            raise ValueError(f"over: {name!r} is not one of the grid's axes {plan.axis_names}")
    eng = resolve_engine(engine, backend)
    itemsize = _table_itemsize(eng, dtype)
    ng, nnk, nm, ni = family_sizes(plan)
    tables_size = table_bytes(ng, nnk, nm, ni, itemsize)
    if tables_size > memory_budget // 2:
        raise ValueError(f"the model's tables for this grid need {tables_size} bytes, more than half of "
                         f"memory_budget={memory_budget}; raise the budget or split the geometry axes")
    kept = [n for n in AXES if n not in over]
    red = [n for n in AXES if n in over]
    vmin, vmean, varg = eng.call("reduce_grid", plan, kept, red, quantity, dtype, shadowing, memory_budget,
                                 tables_size)
    return _reduce_result(plan, over, kept, red, vmin, vmean, varg, quantity, shadowing, dtype)


@ops.implements("reduce_grid", "opencl")
def _device_reduce(eng, plan, kept, red, quantity, dtype, shadowing, memory_budget, tables_size):
    """min (of ``dtype``), mean (float64) and flat argmin over the axes ``red`` on an OpenCL device
    (the ``grid_reduce`` kernel over the whole grid's tables, the kept points in chunks within
    half of ``memory_budget``), as flat arrays over the ``kept`` axes (canonical order)."""
    npdt = DTYPES[dtype]
    itemsize = np.dtype(npdt).itemsize
    ng, nnk, nm, ni = family_sizes(plan)
    s = plan.sizes
    coef = family_strides(s)
    red_total = int(np.prod([s[n] for n in red], dtype=np.int64))
    out_total = int(np.prod([s[n] for n in kept], dtype=np.int64))
    idx_name, idx_np = _index_type(max(plan.size, red_total))

    def arr(name, vals):
        return f"__constant {idx_name} {name}[] = {{{', '.join(str(int(v)) for v in vals)}}};\n"
    prefix = ("#define PB_REDUCE\n" + f"#define PB_NKEPT {len(kept)}\n#define PB_NRED {len(red)}\n"
              f"#define PB_RED_TOTAL (({idx_name}){red_total})\n"
              + arr("PB_KEPT_SIZE", [s[n] for n in kept]) + arr("PB_KEPT_FAM", [FAMILY[n] for n in kept])
              + arr("PB_KEPT_COEF", [coef[n] for n in kept]) + arr("PB_RED_SIZE", [s[n] for n in red])
              + arr("PB_RED_FAM", [FAMILY[n] for n in red]) + arr("PB_RED_COEF", [coef[n] for n in red]))
    prog = grid_program(eng, dtype, (nnk, nm, ni), idx_name, quantity, prefix)
    tables = Tables(eng, dtype, shadowing, quantity, *geometry_list(plan, 0, ng), plan.values)
    n_part = int(min(red_total, max(1, 16384 // max(out_total, 1))))
    per_out = n_part * (2 * itemsize + np.dtype(idx_np).itemsize)
    o_chunk = int(max(1, min(out_total, (memory_budget // 2) // per_out, 2 ** 31 // n_part)))
    vmin = np.empty(out_total, npdt)
    vmean = np.empty(out_total, np.float64)
    varg = np.empty(out_total, np.int64)
    for o0 in range(0, out_total, o_chunk):
        cnt = min(o_chunk, out_total - o0)
        bmin, barg, bsum = (eng.empty(cnt * n_part * sz) for sz in (itemsize, np.dtype(idx_np).itemsize, itemsize))
        eng.launch(prog["grid_reduce"], (cnt, n_part), bmin, barg, bsum, idx_np(o0), idx_np(cnt), idx_np(n_part),
                   *tables.args())
        hmin = eng.read(bmin, np.empty((cnt, n_part), npdt))
        harg = eng.read(barg, np.empty((cnt, n_part), idx_np))
        hsum = eng.read(bsum, np.empty((cnt, n_part), npdt))
        best = np.argmin(hmin, axis=1)
        rows = np.arange(cnt)
        vmin[o0:o0 + cnt] = hmin[rows, best]
        varg[o0:o0 + cnt] = harg[rows, best]
        vmean[o0:o0 + cnt] = hsum.astype(np.float64).sum(axis=1) / red_total
    return vmin, vmean, varg


@ops.implements("reduce_grid", "numpy")
def _numpy_reduce(eng, plan, kept, red, quantity, dtype, shadowing, memory_budget, tables_size):
    """min (computed in float64, returned as ``dtype``), mean (float64) and flat argmin over the
    axes ``red`` on the numpy backend, as flat arrays over the kept axes (canonical order): the
    grid in boxes of the 9-d canonical layout within ``memory_budget - tables_size``, each reduced
    and merged."""
    room = memory_budget - tables_size
    s = plan.sizes
    shape = tuple(s[n] for n in AXES)
    red_ax = tuple(AXES.index(n) for n in red)
    kept_ax = tuple(i for i in range(len(AXES)) if i not in red_ax)
    red_shape = tuple(shape[i] for i in red_ax)
    tables = NumpyTables(shadowing, quantity, *geometry_list(plan, 0, family_sizes(plan)[0]), plan.values)
    kept_shape = tuple(shape[i] for i in kept_ax)
    vmin = np.full(kept_shape, np.inf)
    vsum = np.zeros(kept_shape)
    varg = np.zeros(kept_shape, np.int64)
    for _, box in _boxes(shape, max(64, room // NumpyTables.BYTES_PER_POINT)):
        v = tables.box(shape[:3], shape[3:], box)
        moved = np.moveaxis(v, red_ax, tuple(range(len(kept_ax), len(shape))))
        flat = moved.reshape(moved.shape[:len(kept_ax)] + (-1,))
        local = np.argmin(flat, axis=-1)
        bmin = np.take_along_axis(flat, local[..., None], axis=-1)[..., 0]
        # the reduced coordinates of the box's minimum, moved to the whole grid's
        coords = np.unravel_index(local, tuple(v.shape[i] for i in red_ax))
        glob = np.ravel_multi_index(tuple(c + box[i].start for c, i in zip(coords, red_ax)), red_shape)
        ksl = tuple(box[i] for i in kept_ax)
        better = bmin < vmin[ksl]
        vmin[ksl] = np.where(better, bmin, vmin[ksl])
        varg[ksl] = np.where(better, glob, varg[ksl])
        vsum[ksl] += flat.sum(axis=-1)
    total = int(np.prod(red_shape, dtype=np.int64))
    return vmin.reshape(-1).astype(DTYPES[dtype]), vsum.reshape(-1) / total, varg.reshape(-1)


def _reduce_result(plan, over, kept, red, vmin, vmean, varg, quantity, shadowing, dtype):
    import xarray as xr
    npdt = DTYPES[dtype]
    s = plan.sizes
    kept_axes = [n for n in kept if n in plan.axis_names]
    shape = tuple(s[n] for n in kept_axes)
    coords = {n: c for n, c in plan.coords().items() if n in kept_axes}
    data = {"min": (kept_axes, vmin.reshape(shape)), "mean": (kept_axes, vmean.astype(npdt).reshape(shape))}
    red_idx = np.unravel_index(varg, [s[n] for n in red])
    for n, ix in zip(red, red_idx):
        data[f"argmin_{n}"] = (kept_axes, plan.values[n][ix].reshape(shape), {"units": UNITS[n]})
    attrs = dict(quantity=quantity, reduced_over=list(over), shadowing=shadowing, dtype=dtype,
                 **plan.fixed_attrs())
    return xr.Dataset(data, coords=coords, attrs=attrs)


from ..results import ObjectiveResult, Result  # noqa: E402,F401 (moved; importable from here too)


def _update_best(best_idx, best_sse, start, sse, k):
    """The ``k`` best (flat index, SSE) of the best so far and the block ``sse`` that starts at
    flat index ``start``: only the block's own best are indexed (an index array of a whole block
    of millions was most of the objective's host time), its first minimum where ``k`` is 1."""
    if sse.size > k:
        keep = np.array([np.argmin(sse)]) if k == 1 else None
        if keep is None or np.isnan(sse[keep[0]]):  # argmin stops at a NaN; a partition puts NaNs last
            keep = np.argpartition(sse, k - 1)[:k]
    else:
        keep = np.arange(sse.size)
    idx = np.concatenate([best_idx, start + keep])
    sse = np.concatenate([best_sse, sse[keep]])
    if sse.size > k:
        keep = np.argsort(sse, kind="stable")[:k]
        idx, sse = idx[keep], sse[keep]
    return idx, sse


@_engine.falls_back
def objective(data, grid=None, points=None, *, k_best=10, dtype="float32", shadowing="paper", engine=None,
              backend="auto", memory_budget=DEFAULT_BUDGET, return_sse=True, progress=False):
    """Weighted sum of squared residuals over the measurements for many parameter vectors, on the
    device: the engine of :func:`pbrdf_cl.objective` (which reads the data and documents the
    arguments and the result).  ``data`` is checked :class:`~pbrdf_cl.io.measurements.Measurements`
    (their DOP: theta_i, theta_r, phi, dop, dop_std) or polarimetric
    :class:`~pbrdf_cl.model.measurables.Channels`."""
    t0 = time.perf_counter()
    from ..ranges import parse_bytes
    memory_budget = parse_bytes("memory_budget", memory_budget)
    if (grid is None) == (points is None):
        raise ValueError("give exactly one of grid= (parameter axes) or points= (explicit parameter vectors)")
    dtype = pointwise.check_options(shadowing, dtype)
    if isinstance(data, Channels):  # polarimetric channels (pbrdf_cl.model.measurables), checked by the caller
        ti, tr, ph, obs, w = data.theta_i, data.theta_r, data.phi, data.obs, None
        op, payload, what = "objective_channel_blocks", data, "channels"
    else:  # checked measurements (pbrdf_cl.objective reads them)
        ti, tr, ph, obs = data.theta_i, data.theta_r, data.phi, data.dop
        w = dop_weights(data)
        op, payload, what = "objective_blocks", (ti, tr, ph, obs, w), "DOP"
    eng = resolve_engine(engine, backend)
    npdt = DTYPES[dtype]
    itemsize = _table_itemsize(eng, dtype)
    M = ti.size
    if points is not None:
        if w is None:
            raise ValueError("points= takes DOP data; channels take grid=")
        return _objective_points(eng, points, payload, k_best, dtype, shadowing, return_sse, t0, memory_budget)
    plan = parameter_plan(grid)
    v = plan.values
    rows, tables_size = objective_rows(plan, M, memory_budget, itemsize)
    P = plan.size
    sse = np.empty(P, npdt) if return_sse else None
    best_idx, best_sse = np.empty(0, np.int64), np.empty(0, npdt)
    bar = progress_bar(P, progress, "objective")
    blocks = eng.call(op, plan, payload, dtype, shadowing, memory_budget - tables_size, sse, rows)
    for start, host in blocks:  # host: the block's slice of sse (or a temporary without it)
        count = host.size
        best_idx, best_sse = _update_best(best_idx, best_sse, start, host, k_best)
        if bar is not None:
            bar.update(count)
    if bar is not None:
        bar.close()
    order = np.argsort(best_sse, kind="stable")
    best_idx, best_sse = best_idx[order], best_sse[order]
    unr = np.unravel_index(best_idx, [plan.sizes[n] for n in PARAMETERS])
    best = {n: v[n][i] for n, i in zip(PARAMETERS, unr)}
    best["sse"] = best_sse
    best["index"] = best_idx
    sse_da = None
    if sse is not None:
        import xarray as xr
        sse_da = xr.DataArray(sse.reshape(plan.shape), coords=plan.coords(), dims=plan.axis_names, name="sse",
                              attrs=dict(long_name=f"weighted sum of squared {what} residuals", n_measurements=M,
                                         shadowing=shadowing, dtype=dtype, **plan.fixed_attrs()))
    return ObjectiveResult(sse=sse_da, best=best, n_pairs=P * M, seconds=time.perf_counter() - t0)


def parameter_plan(grid):
    """The :class:`GridPlan` of a parameter grid (name -> nodes, or a value held) of :func:`objective`."""
    return GridPlan({n: v for n, v in grid.items() if np.ndim(v) > 0},
                    {n: v for n, v in grid.items() if np.ndim(v) == 0}, names=PARAMETERS, defaults=PARAMETER_DEFAULTS)


def dop_weights(data):
    """The weights of checked DOP measurements' squared residuals: 1 / dop_std^2, or 1 without it."""
    return 1.0 / data.dop_std ** 2 if data.dop_std is not None else np.ones(data.theta_i.size)


#: Data sets whose objective one launch of the objective kernels sums (:func:`objective_sets`;
#: ``PB_SETS``): each set's sums take private memory (PB_QB values each, objective_rows' tail).
OBJECTIVE_SETS = 8


@_engine.falls_back
def objective_sets(datas, grid, *, dtype="float32", shadowing="paper", engine=None, backend="auto",
                   memory_budget=DEFAULT_BUDGET, progress=False):
    """The objective of several DOP data sets measured at one geometry, on the parameter grid
    ``grid``: ``datas`` are checked :class:`~pbrdf_cl.io.measurements.Measurements` with the same
    theta_i, theta_r and phi, in the same order (the sets of :func:`pbrdf_cl.fit_joint` at several
    wavelengths); returns (the grid's axis names, in order; one SSE array per set over them),
    each set's SSE that of :func:`objective` bit for bit.  On an OpenCL device each block of
    measurements' tables is made once and each grid point's DOP combined once for
    :data:`OBJECTIVE_SETS` sets at a time (the residuals and sums per set); on the numpy backend
    the sets one after another."""
    from ..ranges import parse_bytes
    memory_budget = parse_bytes("memory_budget", memory_budget)
    dtype = pointwise.check_options(shadowing, dtype)
    ti, tr, ph = datas[0].theta_i, datas[0].theta_r, datas[0].phi
    for i, d in enumerate(datas[1:], 1):
        if not all(np.array_equal(a, b) for a, b in zip((d.theta_i, d.theta_r, d.phi), (ti, tr, ph))):
            raise ValueError(f"datas: set {i} is not measured at set 0's angles (theta_i, theta_r, phi, in order)")
    obs = np.stack([d.dop for d in datas], axis=1)
    w = np.stack([dop_weights(d) for d in datas], axis=1)
    eng = resolve_engine(engine, backend)
    plan = parameter_plan(grid)
    rows, tables_size = objective_rows(plan, ti.size, memory_budget, _table_itemsize(eng, dtype))
    out = np.empty((len(datas), plan.size), DTYPES[dtype])
    bar = progress_bar(plan.size * len(datas), progress, "objective")
    for g0 in range(0, len(datas), OBJECTIVE_SETS):
        g = slice(g0, min(len(datas), g0 + OBJECTIVE_SETS))
        for _, host in eng.call("objective_blocks", plan, (ti, tr, ph, obs[:, g], w[:, g]), dtype, shadowing,
                                memory_budget - tables_size, out[g], rows):
            if bar is not None:
                bar.update(host.size)
    if bar is not None:
        bar.close()
    return plan.axis_names, [o.reshape(plan.shape) for o in out]


#: Bytes of the factor tables of one block of measurements of the objective on an OpenCL device
#: (at least OBJECTIVE_BLOCK_ROWS measurements, where the memory budget allows them): a block's
#: tables stay in the caches while every parameter vector goes through it (at 20,000 measurements
#: ten times the pairs per second of one launch over all), the sums running on from block to block.
OBJECTIVE_BLOCK_BYTES, OBJECTIVE_BLOCK_ROWS = 1 << 18, 32


def objective_rows(plan, n_rows, memory_budget, itemsize):
    """(measurements per block, bytes of a block's tables) of the objective over ``n_rows``
    measurements (or channels) and the parameter grid ``plan`` within ``memory_budget``: a block's
    tables take at most half of it, the rest the sums (64 at least).  A
    :class:`pbrdf_cl.RangeError` naming the least budget where one measurement does not fit."""
    from ..errors import RangeError
    _, nnk, nm, ni = family_sizes(plan)
    row = table_bytes(1, nnk, nm, ni, itemsize)
    least = 2 * row + 64 * itemsize
    if memory_budget < least:
        raise RangeError(f"a memory budget of {memory_budget} bytes is too small for the objective of this grid: one "
                         f"measurement's tables need {row} bytes; give at least {least} bytes (or fewer n, k values)")
    rows = int(min(n_rows, (memory_budget // 2) // row))
    return rows, rows * row


@ops.implements("objective_blocks", "numpy")
def _numpy_objective_blocks(eng, plan, meas, dtype, shadowing, room, out, rows):
    """(flat start, SSE) of the parameter grid in boxes, on the numpy backend, written into
    ``out`` when given: the measurements are the tables' geometry list, and a box holds every
    measurement of its parameter vectors; where the tables of all measurements do not fit
    (``rows`` fewer), block by block (:func:`summed_over_rows`).  Observations and weights of
    several sets ((M, S): :func:`objective_sets`): set by set, each into its row of ``out``."""
    npdt = DTYPES[dtype]
    ti, tr, ph, obs, w = meas
    M = ti.size
    if np.ndim(obs) == 2:
        for t in range(obs.shape[1]):
            yield from _numpy_objective_blocks(eng, plan, (ti, tr, ph, obs[:, t], w[:, t]), dtype, shadowing, room,
                                               None if out is None else out[t], rows)
        return
    if rows < M:
        yield from summed_over_rows(plan.size, M, rows, lambda m0, m1: _numpy_objective_blocks(
            eng, plan, [a[m0:m1] for a in meas], "float64", shadowing, room, None, m1 - m0), out, dtype)
        return
    tables = NumpyTables(shadowing, "dop", ti, tr, ph, plan.values)
    sizes = _param_sizes(plan)
    obs = obs.reshape((M,) + (1,) * 6)
    w = w.reshape((M,) + (1,) * 6)
    for start, box in _boxes(sizes, max(1, room // (M * NumpyTables.BYTES_PER_POINT))):
        r = tables.box((M,), sizes, (slice(None),) + box) - obs
        values = np.sum(w * r * r, axis=0).reshape(-1)
        host = out[start:start + values.size] if out is not None else np.empty(values.size, npdt)
        host[...] = values
        yield start, host


@ops.implements("objective_blocks", "opencl")
def _device_objective_blocks(eng, plan, meas, dtype, shadowing, room, out, rows):
    """(flat start, SSE) of the parameter grid in chunks, on the device, read straight into
    ``out`` when given; the measurements in blocks of at most ``rows``.  Observations and weights
    of several sets ((M, S): :func:`objective_sets`): each block's tables made once and each DOP
    combined once for every set (``PB_SETS``), the SSE (S, chunk) and ``out`` (S, P)."""
    ti, tr, ph, obs, w = meas

    def tables(m0, m1):
        t = Tables(eng, dtype, shadowing, "dop", ti[m0:m1], tr[m0:m1], ph[m0:m1], plan.values)
        return (*t.args(), eng.to_device(obs[m0:m1], dtype), eng.to_device(w[m0:m1], dtype), np.int32(m1 - m0))
    yield from _objective_chunks(eng, plan, dtype, room, out, ("objective_rows", "objective_grid"), tables,
                                 (ti.size, rows), sets=1 if np.ndim(obs) == 1 else obs.shape[1])


@ops.implements("objective_channel_blocks", "opencl")
def _device_channel_blocks(eng, plan, ch, dtype, shadowing, room, out, rows):
    """As ``objective_blocks`` for polarimetric channels (:mod:`pbrdf_cl.compute.channels`)."""
    def tables(m0, m1):
        return channels.device_channel_tables(eng, ch.take(slice(m0, m1)), plan.values, dtype, shadowing)
    yield from _objective_chunks(eng, plan, dtype, room, out, ("objective_channel_rows", "objective_channels"),
                                 tables, (len(ch), rows), PB_CHANNELS=None)


def _objective_chunks(eng, plan, dtype, room, out, kernels, make_args, n_rows, sets=1, **defines):
    """(flat start, SSE) of the grid ``plan`` in chunks of ``room`` bytes: the row kernel
    ``kernels[0]`` (or, where rows would be too long, the per-vector ``kernels[1]``) of
    ``pbrdf_grid.cl`` with the tables and data of measurements m0..m1 that ``make_args(m0, m1)``
    returns (made once the program is built: its trial comes first).  ``n_rows``: (measurements,
    most per block); blocks of :data:`OBJECTIVE_BLOCK_BYTES` of tables (OBJECTIVE_BLOCK_ROWS at least), each launch
    adding to the sums of the blocks before it, in the same order as one launch over all (the
    same sums, bit for bit); with several chunks, the tables of several blocks are made again
    for each chunk.  ``sets`` > 1: the data of that many sets (``PB_SETS``), the chunks' SSE
    (sets, chunk) and ``out`` (sets, P)."""
    npdt = DTYPES[dtype]
    itemsize = np.dtype(npdt).itemsize
    _, nnk, nm, ni = family_sizes(plan)
    P = plan.size
    idx_name, idx_np = _index_type(P * sets)
    chunk = int(max(64, min(room // (itemsize * sets), 2 ** 31 - 1)))
    level, row_len = row_level(nnk, nm, ni, 1, chunk, max_level=2)
    if sets > 1:
        defines["PB_SETS"] = int(sets)
    prog = grid_program(eng, dtype, (nnk, nm, ni), idx_name, "dop", PB_OBJECTIVE=None, PB_ROW_LEVEL=level,
                        PB_ROW_LEN=row_len, **defines)
    chunk = max(row_len, chunk // row_len * row_len)
    M, rows = n_rows
    per_block = max(OBJECTIVE_BLOCK_ROWS, OBJECTIVE_BLOCK_BYTES // table_bytes(1, nnk, nm, ni, itemsize))
    blocks = row_blocks(M, min(rows, per_block))
    args = make_args(*blocks[0]) if len(blocks) == 1 else None
    for start in range(0, P, chunk):
        count = min(chunk, P - start)
        shape = (sets, count) if sets > 1 else (count,)
        view = out[..., start:start + count] if out is not None else None
        host = view if view is not None and view.flags.c_contiguous else np.empty(shape, npdt)
        buf, done = eng.output(host, accumulate=len(blocks) > 1)
        ran = None
        for b, (m0, m1) in enumerate(blocks):
            if ran is not None and b % 2 == 0:
                ran.wait()  # the tables of two blocks at most at a time (launches are queued)
            more = (*(args or make_args(m0, m1)), np.int32(b > 0))
            if level:
                ran = eng.launch(prog[kernels[0]], (count // row_len,), buf, idx_np(start // row_len),
                                 idx_np(count // row_len), *more)
            else:
                ran = eng.launch(prog[kernels[1]], (count,), buf, idx_np(start), idx_np(count), *more)
        done()
        if view is not None and host is not view:  # a chunk of several sets' rows
            view[...] = host
        yield start, host


def _objective_points(eng, points, meas, k_best, dtype, shadowing, return_sse, t0, memory_budget):
    ti, tr, ph, obs, w = meas
    unknown = set(points) - set(PARAMETERS)
    if unknown:
        raise ValueError(f"points: unknown parameter {sorted(unknown)[0]!r}; valid names are {', '.join(PARAMETERS)}")
    defaults = PARAMETER_DEFAULTS
    vals = {}
    for n in PARAMETERS:
        if n not in points and n not in defaults:
            raise ValueError(f"points: {n} is required")
        vals[n] = np.atleast_1d(pointwise.check_values(n, points.get(n, defaults.get(n))))
    try:
        arrays = np.broadcast_arrays(*(vals[n] for n in PARAMETERS))
    except ValueError:
        raise ValueError("points: parameter arrays differ in length") from None
    arrays = [a.reshape(-1) for a in arrays]
    P = arrays[0].size
    sse = eng.call("objective_points", arrays, meas, dtype, shadowing, memory_budget)
    order = np.argsort(sse, kind="stable")[:k_best]
    best = {n: a[order] for n, a in zip(PARAMETERS, arrays)}
    best["sse"] = sse[order]
    best["index"] = order
    return ObjectiveResult(sse=sse if return_sse else None, best=best, n_pairs=P * ti.size,
                           seconds=time.perf_counter() - t0)


@ops.implements("objective_points", "numpy")
def _numpy_objective_points(eng, arrays, meas, dtype, shadowing, memory_budget):
    """The SSE of each parameter vector (``arrays``: n, k, sigma, ks, kd, c, each of P values) over
    the measurements ``meas``: the reference over (vectors, measurements), a bounded number of rows
    at a time."""
    ti, tr, ph, obs, w = meas
    P = arrays[0].size
    sse = np.empty(P, DTYPES[dtype])
    step = max(1, memory_budget // (ti.size * 8 * 16))
    for a in range(0, P, step):
        par = [x[a:a + step, None] for x in arrays]
        r = reference.evaluate("dop", ti, tr, ph, *par, shadowing=shadowing) - obs
        sse[a:a + step] = np.sum(w * r * r, axis=1)
    return sse


@ops.implements("objective_points", "opencl")
def _device_objective_points(eng, arrays, meas, dtype, shadowing, memory_budget):
    """As the numpy backend's, in one launch of the ``objective_points`` kernel (a parameter vector per
    work-item)."""
    ti, tr, ph, obs, w = meas
    P = arrays[0].size
    kern = eng.kernel("objective_points", dtype, shadowing)
    buf = eng.empty(P * np.dtype(DTYPES[dtype]).itemsize)
    eng.launch(kern, (P,), buf, np.int32(P), *(eng.to_device(a, dtype) for a in arrays),
               *(eng.to_device(a, dtype) for a in (ti, tr, ph, obs, w)), np.int32(ti.size))
    return eng.read(buf, np.empty(P, DTYPES[dtype]))


#: Geometry x parameter-set pairs per launch of ``quantity_outer`` (one launch's output at most).
OUTER_LAUNCH_PAIRS = 1 << 22
#: float64 bytes per pair of a numpy-backend block of :func:`outer` (the values and temporaries).
OUTER_NUMPY_BYTES = 160


@_engine.falls_back
def outer(eng, quantity, geometry, params, dtype="float64", shadowing="paper", out=None, rows=None):
    """``quantity`` at every pair of a geometry list and a list of parameter sets, without forming
    the pairs: the sample sets of a sensitivity analysis, or a Jacobian's finite-difference
    steps, over every candidate geometry.  Package-internal: the inputs are checked by the caller.

    geometry : dict theta_i, theta_r, phi -> 1-d arrays of G values (degrees)
    params : dict n, k, sigma, ks, kd, c -> 1-d arrays of S values
    out : optional array of shape (G, S) + the quantity's trailing axes, of ``dtype``, written in place
    rows : optional (g0, g1): only geometries g0..g1 (out then has g1 - g0 rows)

    Returns ``out``: ``out[g, s]`` is the quantity at geometry g for parameter set s.  On a CPU
    device the kernel writes straight into ``out``, launch by launch."""
    q = quantities.get(quantity, "points")
    npdt = np.dtype(DTYPES[dtype])
    geo = [np.ascontiguousarray(geometry[n], np.float64).reshape(-1) for n in AXES[:3]]
    par = [np.ascontiguousarray(params[n], np.float64).reshape(-1) for n in PARAMETERS]
    g0, g1 = rows if rows is not None else (0, geo[0].size)
    S = par[0].size
    if out is None:
        out = aligned_empty((g1 - g0) * S * q.width, npdt).reshape((g1 - g0, S) + q.trailing)
    if g1 <= g0 or S == 0:
        return out
    eng.call("outer", q, geo, par, (g0, g1), dtype, shadowing, out.reshape(g1 - g0, S * q.width))
    return out


@ops.implements("outer", "numpy")
def _numpy_outer(eng, q, geo, par, rows, dtype, shadowing, flat):
    """:func:`outer`'s values, with the reference, into ``flat`` (rows g0..g1 of the geometries,
    each the S parameter sets' values side by side): a bounded number of geometries at a time."""
    g0, g1 = rows
    S = par[0].size
    per = max(1, int(DEFAULT_BUDGET // 4 // (OUTER_NUMPY_BYTES * S * q.width)))
    for a in range(g0, g1, per):
        b = min(g1, a + per)
        v = reference.evaluate(q.name, *(x[a:b, None] for x in geo), *(p[None, :] for p in par),
                               shadowing=shadowing)
        flat[a - g0:b - g0] = np.asarray(v).reshape(b - a, -1)


@ops.implements("outer", "opencl")
def _device_outer(eng, q, geo, par, rows, dtype, shadowing, flat):
    """:func:`outer`'s values on an OpenCL device: the ``*_outer_vec`` kernels (N parameter sets per
    work-item) or ``quantity_outer``, launch by launch, written straight into ``flat`` on a CPU
    device."""
    g0, g1 = rows
    S = par[0].size
    npdt = np.dtype(DTYPES[dtype])
    vec = q.vector and eng.vectorise  # N parameter sets per work-item, the sets padded to a multiple of N
    lanes = eng.vector_width[dtype] if vec else 1
    Sp = -(-S // lanes) * lanes
    if Sp != S:
        par = [np.concatenate([p, np.full(Sp - S, p[-1])]) for p in par]
    kern = (eng.kernel(f"{q.name}_outer_vec", dtype, shadowing) if vec
            else eng.kernel("quantity_outer", dtype, shadowing, q.name))
    gbuf = [eng.to_device(x, dtype) for x in geo]
    pbuf = [eng.to_device(p, dtype) for p in par]
    per = max(1, OUTER_LAUNCH_PAIRS // (Sp * q.width))
    tmp = None if Sp == S else aligned_empty(min(per, g1 - g0) * Sp * q.width, npdt)
    for a in range(g0, g1, per):
        b = min(g1, a + per)
        view = flat[a - g0:b - g0].reshape(-1) if tmp is None else tmp[:(b - a) * Sp * q.width]
        buf, done = eng.output(view)
        if vec:
            eng.launch(kern, (Sp // lanes, b - a), buf, np.int32(Sp // lanes), np.int32(b - a), np.int32(a),
                       *gbuf, *pbuf, local_size=(VECTOR_LOCAL_SIZE, 1))
        else:
            eng.launch(kern, (S, b - a), buf, np.int32(S), np.int32(b - a), np.int32(a), *gbuf, *pbuf)
        done()
        if tmp is not None:  # the padded sets dropped
            flat[a - g0:b - g0] = view.reshape(b - a, Sp * q.width)[:, :S * q.width]
