"""Sweeps larger than memory and larger than one machine: the grid engine of :mod:`pbrdf_cl.compute.dense`
chunk by chunk into a Zarr store, resumable, optionally over a ``dask.distributed`` cluster (the
store, the run and the cluster: :mod:`pbrdf_cl.store.zarr`, :mod:`pbrdf_cl.store.runner`,
:mod:`pbrdf_cl.store.cluster`; this module says what a chunk computes and writes).

A sweep is described by a spec (TOML, see ``examples/sweep_sigma_theta.toml``)::

    quantity = "dop"                 # dop | brdf (alias f00) | aop: pbrdf_cl.quantities.names("sweep")
    dtype = "float32"                # float32 | float64
    shadowing = "paper"              # paper | smith | none
    memory_budget = "256 MiB"        # one chunk in flight: its values + the device's working memory

    [axes]                           # canonical names of pbrdf_cl.compute.dense.AXES; angles in degrees
    theta_i = "10:80:10"             # start:stop:step, ends included (docs/guide/cli.md: Ranges)
    theta_r = "0:85@256"             # start:stop@count; = {start = 0, stop = 85, num = 256}
    sigma = [0.1, 0.2, 0.5]

    [fixed]                          # the other inputs; phi, ks, kd, c default to 180, 1, 0, 0
    n = 1.6
    k = 2.139

    [chunks]                         # points = N (leading axes split), or per-axis sizes
    theta_i = 1

    [reduce]                         # optional: min / mean / argmin over these axes, on the device
    over = ["theta_r"]

Layout of the store (Zarr format 2, consolidated metadata; ``xarray.open_zarr`` reads it):

- one 1-d coordinate array per axis (``units``, ``long_name``);
- the values: ``dop`` or ``f00`` over all axes, or ``min``, ``mean`` and ``argmin_<axis>`` over
  the axes not reduced; each Zarr chunk is exactly one compute chunk (a sub-box of the axes,
  evaluated as a small grid), so no two writers ever share a Zarr chunk;
- ``_sweep/done``: one uint8 per chunk, written (1) only after that chunk's values are in the
  store (write-then-mark); a resumed sweep computes the chunks not marked; ``_sweep/digest``: per
  chunk the SHA-256 of its decoded values and ``_sweep/device`` the device that computed it, both
  written before the mark (:mod:`pbrdf_cl.store.verify`: a resume recomputes the chunks that no
  longer match their digests and rewrites damaged metadata and coordinates from the spec);
- root attrs: the canonical spec as JSON (``sweep_spec``: each axis by its count, ends and
  SHA-256, :func:`axis_identity`; the values are in the coordinate arrays only), its SHA-256
  (``sweep_spec_sha256``), the TOML it came from, the SHA-256 of the OpenCL sources
  (``sweep_kernels_sha256``: a store is resumed, or written by a cluster worker, only with the
  kernels that started it), the fixed values, the devices (``store_devices``), the units
  (``store_units``), the skeleton's manifest (``store_manifest``) and ``sweep_complete`` (set
  only when every chunk is done and matches its digest).

A run holds the lock ``STORE.lock`` beside a local store (:mod:`pbrdf_cl.store.lock`).

Testing aid: ``PBRDF_SWEEP_CHUNK_DELAY=<seconds>`` sleeps that long per chunk (half before the
values are written, half between writing them and marking the chunk done), so that an
interruption reliably lands in the middle of a sweep.
"""
from __future__ import annotations

import hashlib
import json
import logging
import numbers
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from .. import ranges, sizes
from ..compute import dense, pointwise
from ..device.engine import DTYPES, kernels_sha256
from ..errors import SpecError, StoreWarning
from ..model import quantities
from ..model.reference import SHADOWING
from ..results import Result
from ..store import cluster, runner, verify
from ..store import zarr as zarr_store
from ..version import __version__

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python < 3.11
    import tomli as tomllib

log = logging.getLogger(__name__)

#: Version of the canonical spec (part of the hash).  2: each axis by its count, ends and SHA-256
#: (the values are in the coordinate arrays only); the stores' digests, devices and manifest.
SPEC_VERSION = 2
#: Values per chunk of a coordinate array (8 MiB of float64).
COORD_CHUNK = 1 << 20
#: Points of an automatic chunk at most (4 MiB of float32 values): a one-axis sweep of 10^7
#: values then runs in 10 chunks within 450 MB, where one chunk of 10^7 took 1 GB (issue 39).
MAX_CHUNK_POINTS = 1 << 20
DEFAULT_MEMORY_BUDGET = 256 << 20
#: Blosc compresses at most 2 GiB per call.
MAX_CHUNK_BYTES = (1 << 31) - 1024
DELAY_ENV = "PBRDF_SWEEP_CHUNK_DELAY"
KEYS = ("title", "quantity", "dtype", "shadowing", "memory_budget", "axes", "fixed", "chunks", "reduce")


# ---------------------------------------------------------------------------------------------
# the spec

def _fmt(v):
    return f"{v:g}" if isinstance(v, float) else repr(v)


def _number(field, v):
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise SpecError(f"{field}: {v!r} is not a number")
    return float(v)


def _range_string(field, text):
    """``"40"``, ``"20,30,45"``, ``"20:65:5"`` or ``"0:85@256"``: the grammar of :mod:`pbrdf_cl.ranges`."""
    try:
        return ranges.parse_values(text, label=f'{field} = "{text}"')
    except ranges.RangeError as exc:
        raise SpecError(str(exc)) from None


def _axis_values(field, value):
    if isinstance(value, str):
        return _range_string(field, value)
    if isinstance(value, (list, tuple, np.ndarray)):  # a TOML list, or arrays from Python
        if np.ndim(value) != 1:
            raise SpecError(f"{field}: a list of values must be 1-d, got shape {np.shape(value)}")
        if not len(value):
            raise SpecError(f"{field}: empty list")
        return np.array([_number(f"{field}[{i}]", v) for i, v in enumerate(value)])
    if isinstance(value, dict):
        keys = set(value)
        text = "{" + ", ".join(f"{k} = {_fmt(v)}" for k, v in value.items()) + "}"
        if keys not in ({"start", "stop", "num"}, {"start", "stop", "step"}):
            raise SpecError(f"{field}: a range table takes start, stop and num (or step), got {text}")
        start, stop = _number(f"{field}.start", value["start"]), _number(f"{field}.stop", value["stop"])
        try:
            if "num" in keys:
                return ranges.count_values(start, stop, value["num"], f"{field} = {text}")
            return ranges.step_values(start, stop, _number(f"{field}.step", value["step"]), f"{field} = {text}")
        except ranges.RangeError as exc:
            raise SpecError(str(exc)) from None
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        raise SpecError(f"{field}: a single value; give it under [fixed], or as a one-element list [{_fmt(value)}]")
    raise SpecError(f"{field}: {value!r} is not a list, a range string (\"10:80:10\", \"0:85@256\") or a "
                    "{start, stop, num} table")


def parse_bytes(field, value):
    """``268435456``, ``"256 MiB"``, ``"1.5GB"`` -> bytes (int): :func:`pbrdf_cl.ranges.parse_bytes`,
    refusals as :class:`SpecError`."""
    try:
        return ranges.parse_bytes(field, value)
    except ranges.RangeError as exc:
        raise SpecError(str(exc)) from None


_human = sizes.human


class SweepSpec:
    """A validated sweep.

    Attributes: ``quantity``, ``dtype``, ``shadowing``, ``memory_budget`` (bytes), ``title``,
    ``axes`` (name -> float64 array, canonical order), ``fixed`` (every other input, defaults
    filled in), ``over`` (reduced axes), ``dims`` / ``shape`` / ``chunks`` of the stored
    variables, ``n_chunks`` and the canonical form (``canonical()``, ``sha256``).

    Parameters
    ----------
    data : dict
        The spec's table (the TOML's keys: see :func:`pbrdf_cl.load_spec`).
    source : str, optional
        Where it came from (a file name), for messages.
    text : str, optional
        The spec's TOML text, kept with the store.
    """

    def __init__(self, data, source=None, text=None):
        if not isinstance(data, dict):
            raise SpecError(f"a sweep spec is a table (dict), got {type(data).__name__}")
        self.source, self.text = source, text
        for key in data:
            if key not in KEYS:
                raise SpecError(f"unknown key {key!r}; valid keys are {', '.join(KEYS)}")
        self.title = str(data.get("title", ""))
        try:
            self.quantity = quantities.canonical(data.get("quantity", "dop"), "sweep")
        except ValueError as exc:
            raise SpecError(str(exc)) from None
        self.dtype = data.get("dtype", "float32")
        if self.dtype not in DTYPES:
            raise SpecError(f"dtype: must be float32 or float64, got {self.dtype!r}")
        self.shadowing = data.get("shadowing", "paper")
        if self.shadowing not in SHADOWING:
            raise SpecError(f"shadowing: must be one of {', '.join(sorted(SHADOWING))}, got {self.shadowing!r}")
        self.memory_budget = parse_bytes("memory_budget", data.get("memory_budget", DEFAULT_MEMORY_BUDGET))
        self.itemsize = np.dtype(DTYPES[self.dtype]).itemsize

        axes_in = data.get("axes")
        if not isinstance(axes_in, dict) or not axes_in:
            raise SpecError("axes: name at least one axis, e.g. [axes] theta_r = \"0:85:5\"")
        fixed_in = data.get("fixed", {})
        if not isinstance(fixed_in, dict):
            raise SpecError(f"fixed: must be a table of name = value, got {fixed_in!r}")
        for where, d in (("axes", axes_in), ("fixed", fixed_in)):
            for name in d:
                if name not in dense.AXES:
                    raise SpecError(f"{where}.{name}: unknown axis; valid names are {', '.join(dense.AXES)}")
        for name in fixed_in:
            if name in axes_in:
                raise SpecError(f"fixed.{name}: {name} is also an axis; give it in one place only")
        axes = {}
        for name in dense.AXES:
            if name not in axes_in:
                continue
            field = f"axes.{name}"
            a = _axis_values(field, axes_in[name])
            try:
                a = pointwise.check_values(name, a)
            except ValueError as exc:
                raise SpecError(f"{field}: {exc}") from None
            if a.size > 1 and not (np.all(a[1:] > a[:-1]) or np.all(a[1:] < a[:-1])):  # 1 byte a value, not 8
                raise SpecError(f"{field}: values must be strictly increasing or decreasing, got "
                                f"{', '.join(_fmt(float(v)) for v in a[:6])}{', ...' if a.size > 6 else ''}")
            axes[name] = a
        fixed = {}
        for name, v in fixed_in.items():
            v = _number(f"fixed.{name}", v)
            try:
                pointwise.check_values(name, v)
            except ValueError as exc:
                raise SpecError(f"fixed.{name}: {exc}") from None
            fixed[name] = v
        try:
            self.plan = dense.GridPlan(axes, fixed)
        except ValueError as exc:  # a required input given nowhere
            raise SpecError(f"fixed: {exc}") from None
        self.plan.check_degrees("spec: ")
        self.axes = {n: self.plan.values[n] for n in self.plan.axis_names}
        self.fixed = self.plan.fixed_values()

        red = data.get("reduce", {})
        if isinstance(red, list):
            red = {"over": red}
        if not isinstance(red, dict) or set(red) - {"over"}:
            raise SpecError(f"reduce: must be a table with over = [axis names], got {red!r}")
        over = red.get("over", [])
        if isinstance(over, str):
            over = [over]
        if not isinstance(over, list) or not all(isinstance(n, str) for n in over):
            raise SpecError(f"reduce.over: must be a list of axis names, got {over!r}")
        for n in over:
            if n not in self.axes:
                raise SpecError(f"reduce.over: {n!r} is not an axis of this sweep ({', '.join(self.axes)})")
        if "reduce" in data and not over:
            raise SpecError("reduce.over: name at least one axis to reduce")
        self.over = tuple(n for n in self.axes if n in over)
        self.dims = tuple(n for n in self.axes if n not in self.over)
        self.shape = tuple(self.axes[n].size for n in self.dims)
        self.reduced_points = int(np.prod([self.axes[n].size for n in self.over], dtype=np.int64))
        self.chunks = self._chunk_shape(data.get("chunks"))
        self._check_budget()
        self.chunk_grid = tuple(-(-s // c) for s, c in zip(self.shape, self.chunks))
        self.n_chunks = int(np.prod(self.chunk_grid, dtype=np.int64))
        self.points = int(np.prod([a.size for a in self.axes.values()], dtype=np.int64))
        self.canonical_json = json.dumps(self.canonical(), separators=(",", ":"))
        self.sha256 = hashlib.sha256(self.canonical_json.encode()).hexdigest()

    # -- construction -------------------------------------------------------------------------
    @classmethod
    def from_toml(cls, text, source=None):
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise SpecError(f"{source or 'spec'}: not valid TOML: {exc}") from None
        return cls(data, source=source, text=text)

    # -- chunks -------------------------------------------------------------------------------
    def _chunk_shape(self, spec):
        spec = {} if spec is None else spec
        if not isinstance(spec, dict):
            raise SpecError(f"chunks: must be a table (points = N, or axis = size), got {spec!r}")
        half = self.memory_budget // 2
        if "points" in spec:
            if len(spec) > 1:
                raise SpecError("chunks: give either points = N or per-axis sizes, not both")
            target = spec["points"]
            if isinstance(target, bool) or not isinstance(target, int) or target < 1:
                raise SpecError(f"chunks.points: {target!r} is not a positive integer")
            if not self.over and target * self.itemsize > half:
                raise SpecError(
                    f"chunks.points: a chunk of {target} points x {self.itemsize} bytes = "
                    f"{_human(target * self.itemsize)} is larger than the budget for one chunk's values, "
                    f"half of memory_budget = {_human(self.memory_budget)} (the other half is the device's "
                    f"working memory); use fewer points per chunk or a larger memory_budget")
        elif spec:
            out = []
            for name, size in spec.items():
                field = f"chunks.{name}"
                if name not in self.axes:
                    raise SpecError(f"{field}: not an axis of this sweep ({', '.join(self.axes)})")
                if isinstance(size, bool) or not isinstance(size, int) or size < 1:
                    raise SpecError(f"{field}: {size!r} is not a positive integer")
                if name in self.over and size < self.axes[name].size:
                    raise SpecError(f"{field}: {name} is reduced (reduce.over), so it is never split")
            for n in self.dims:
                out.append(min(int(spec.get(n, self.axes[n].size)), self.axes[n].size))
            return tuple(out)
        else:  # at most MAX_CHUNK_POINTS: the device's working memory and Zarr's buffers follow the chunk
            target = max(1, min(half // self.itemsize, MAX_CHUNK_POINTS))
        # leading axes split, trailing ones whole (reduced axes are whole inside every chunk)
        per, out = self.reduced_points, [1] * len(self.dims)
        for j in range(len(self.dims) - 1, -1, -1):
            size = self.shape[j]
            if per * size <= target:
                out[j], per = size, per * size
            else:
                out[j] = int(max(1, target // per))
                break
        return tuple(out)

    @property
    def chunk_points(self):
        """Grid points evaluated for one (full-size) chunk."""
        return int(np.prod(self.chunks, dtype=np.int64)) * self.reduced_points

    def _box_family_sizes(self):
        s = dict.fromkeys(dense.AXES, 1)
        s.update({n: self.axes[n].size for n in self.over})
        s.update(zip(self.dims, self.chunks))
        return (s["theta_i"] * s["theta_r"] * s["phi"], s["n"] * s["k"], s["sigma"] * s["ks"], s["kd"] * s["c"])

    def _check_budget(self):
        ng, nnk, nm, ni = self._box_family_sizes()
        budget, isz = self.memory_budget, self.itemsize
        shape = " x ".join(str(c) for c in self.chunks) or "1"
        if self.over:
            tables = dense.table_bytes(ng, nnk, nm, ni, isz)
            if tables > budget // 2:
                raise SpecError(
                    f"chunks: the model's tables for a chunk of {shape} (times the reduced axes "
                    f"{', '.join(self.over)}) need {_human(tables)}, more than half of memory_budget = "
                    f"{_human(budget)}; use smaller chunks of the geometry axes or a larger memory_budget")
            return
        values = self.chunk_points * isz
        if values > budget // 2:
            raise SpecError(
                f"chunks: a chunk of {shape} = {self.chunk_points} points x {isz} bytes = {_human(values)} is "
                f"larger than the budget for one chunk's values, half of memory_budget = {_human(budget)} "
                f"(the other half is the device's working memory); use smaller chunks or a larger memory_budget")
        if values > MAX_CHUNK_BYTES:
            raise SpecError(f"chunks: a chunk of {_human(values)} is over the 2 GiB a Zarr/Blosc chunk can hold; "
                            "use smaller chunks")
        row = dense.table_bytes(1, nnk, nm, ni, isz)
        if budget // 2 < 2 * row + 64 * isz:
            raise SpecError(f"memory_budget: {_human(budget)} is too small for one geometry row's tables "
                            f"({_human(row)}) of a chunk; raise it")

    def chunk_index(self, i):
        return np.unravel_index(int(i), self.chunk_grid) if self.dims else ()

    def region(self, i):
        """The slices (over :attr:`dims`) of chunk ``i``."""
        return tuple(slice(j * c, min((j + 1) * c, s)) for j, c, s in zip(self.chunk_index(i), self.chunks, self.shape))

    def box(self, i):
        """The axes (name -> values) of chunk ``i``: a sub-box of the sweep, itself a small grid."""
        sub = dict(zip(self.dims, self.region(i)))
        return {n: (a[sub[n]] if n in sub else a) for n, a in self.axes.items()}

    def box_points(self, i):
        return int(np.prod([r.stop - r.start for r in self.region(i)], dtype=np.int64)) * self.reduced_points

    # -- identity -----------------------------------------------------------------------------
    def canonical(self):
        """Everything that determines the stored bytes (not the memory budget or the title); each
        axis by :func:`axis_identity` (its values are in the store's coordinate arrays)."""
        return {"pbrdf_sweep": SPEC_VERSION, "quantity": self.quantity, "dtype": self.dtype,
                "shadowing": self.shadowing, "axes": {n: axis_identity(a) for n, a in self.axes.items()},
                "fixed": self.fixed, "reduce_over": list(self.over), "chunks": dict(zip(self.dims, self.chunks))}

    @property
    def variables(self):
        if not self.over:
            return (self.quantity,)
        return ("min", "mean") + tuple(f"argmin_{n}" for n in self.over)

    def __repr__(self):
        kind = f"reduced over {', '.join(self.over)}" if self.over else self.quantity
        return (f"SweepSpec({self.points} points of {self.quantity} ({self.dtype}) over "
                f"{' x '.join(f'{n}[{a.size}]' for n, a in self.axes.items())}, {kind}, "
                f"{self.n_chunks} chunks of {' x '.join(map(str, self.chunks)) or '1'}, sha256 {self.sha256[:12]})")


def axis_identity(values):
    """An axis in the canonical spec: ``{"count", "first", "last", "sha256"}`` (SHA-256 of its
    float64 bytes, little-endian), a few bytes whatever its length.

    Examples
    --------
    >>> d = axis_identity(np.linspace(0, 85, 18))
    >>> d["count"], d["first"], d["last"], len(d["sha256"])
    (18, 0.0, 85.0, 64)
    """
    a = np.ascontiguousarray(values, "<f8")
    return {"count": int(a.size), "first": float(a[0]), "last": float(a[-1]),
            "sha256": hashlib.sha256(memoryview(a).cast("B")).hexdigest()}


def load_spec(spec):
    """The validated sweep of a spec.

    Parameters
    ----------
    spec : str or path, dict or SweepSpec
        A TOML file (see ``examples/sweep_sigma_theta.toml``), the same keys as a dict, or a
        SweepSpec (returned as is).

    Returns
    -------
    SweepSpec
        Its axes, chunks (within the memory budget), points and store layout.

    Raises
    ------
    SpecError
        A ``ValueError`` naming the field, the value and the right spelling.

    Examples
    --------
    >>> spec = load_spec("examples/sweep_sigma_theta.toml")  # doctest: +SKIP
    >>> spec.points, spec.n_chunks  # doctest: +SKIP
    (176128, 32)
    """
    if isinstance(spec, SweepSpec):
        return spec
    if isinstance(spec, dict):
        return SweepSpec(spec)
    if isinstance(spec, (str, os.PathLike)):
        path = Path(spec)
        try:
            text = path.read_text()
        except OSError as exc:
            raise SpecError(f"cannot read the spec {str(path)!r}: {exc.strerror or exc}") from None
        return SweepSpec.from_toml(text, source=str(path))
    raise SpecError(f"spec must be a TOML file path, a dict or a SweepSpec, got {type(spec).__name__}")


# ---------------------------------------------------------------------------------------------
# the store (the Zarr layer: pbrdf_cl.store.zarr)

def _root_attrs(spec, complete=False):
    q = quantities.get(spec.quantity)
    attrs = dict(title=spec.title or f"pbrdf-cl sweep of {spec.quantity}", quantity=spec.quantity,
                 long_name=q.long_name, units=q.units,
                 shadowing=spec.shadowing, dtype=spec.dtype, **spec.plan.fixed_attrs())
    if spec.over:
        attrs["reduced_over"] = list(spec.over)
    attrs.update(pbrdf_cl_version=__version__, sweep_spec=spec.canonical_json, sweep_spec_sha256=spec.sha256,
                 sweep_spec_toml=spec.text or "", sweep_kernels_sha256=kernels_sha256(), sweep_chunks=spec.n_chunks,
                 sweep_complete=complete)
    attrs[verify.UNITS] = {"count": spec.n_chunks, "variables": list(spec.variables), "job": "sweep_spec",
                           "complete": "sweep_complete"}
    return attrs


#: Root attrs that runs change, or that are not the spec's identity: not rewritten on resuming.
VOLATILE = ("sweep_complete", "pbrdf_cl_version", "title", "sweep_spec_toml", zarr_store.DEVICES)


def _write_skeleton(spec, store):
    """Coordinates, empty variables, the done record, then (last: the commit point) the root attrs."""
    g = zarr_store.open_group(store, "w")
    for n, a in spec.axes.items():
        c = zarr_store.create_array(g, n, a.shape, (min(a.size, COORD_CHUNK),), "f8", None, None,
                                    {"_ARRAY_DIMENSIONS": [n], "units": dense.UNITS[n],
                                     "long_name": dense.LONG_NAMES[n]})
        for j in range(0, a.size, COORD_CHUNK):  # a chunk at a time: zarr 3 writes one call's chunks at once
            c[j:j + COORD_CHUNK] = a[j:j + COORD_CHUNK]
    npdt = np.dtype(DTYPES[spec.dtype])
    dims = list(spec.dims)
    q = quantities.get(spec.quantity)
    units = q.units
    if spec.over:
        over = ", ".join(spec.over)
        var_attrs = {"min": dict(long_name=f"minimum of {spec.quantity} over {over}", units=units),
                     "mean": dict(long_name=f"mean of {spec.quantity} over {over}", units=units)}
        var_attrs.update({f"argmin_{n}": dict(long_name=f"{n} at the minimum of {spec.quantity}", units=dense.UNITS[n])
                          for n in spec.over})
    else:
        var_attrs = {spec.quantity: dict(long_name=q.long_name, units=units)}
    for name, attrs in var_attrs.items():
        dt = "f8" if name.startswith("argmin_") else npdt
        zarr_store.create_array(g, name, spec.shape, spec.chunks, dt, np.nan, zarr_store.compressor(),
                                {"_ARRAY_DIMENSIONS": dims, **attrs})
    sub = g.require_group("_sweep")
    sub.attrs.update(description="done[i] = 1 once chunk i (C order over the chunk grid) is in the store",
                     chunk_grid=list(spec.chunk_grid))
    zarr_store.create_done(g, spec.n_chunks)
    verify.seal(store, _root_attrs(spec))


def open_store(spec, store):
    """Create the store for ``spec``, or check that an existing one was started with the same
    spec (and kernels) and rewrite from the spec whatever of its skeleton is missing or altered
    (:func:`pbrdf_cl.store.verify.repair_skeleton`, said in one warning line); returns (absolute
    store name, whether it existed before)."""
    name, attrs = zarr_store.create_or_read(
        store, lambda where: _write_skeleton(spec, where),
        not_a_store=lambda name: SpecError(f"{name} exists and is not a pbrdf-cl sweep store; choose another "
                                           "--out or delete it"))
    if attrs is None:
        return name, False
    if not attrs and zarr_store.Files(name).get(".zattrs") is not None:
        verify.refuse_unidentified(name, None, "sweep_spec_sha256", "a pbrdf-cl sweep store")
    if not attrs or "sweep_spec_sha256" not in attrs:
        raise SpecError(f"{name} exists and is not a pbrdf-cl sweep store (or its creation was interrupted); "
                        "choose another --out or delete it")
    if attrs["sweep_spec_sha256"] != spec.sha256:
        diffs = zarr_store.stored_differences(attrs, "sweep_spec", spec.canonical())
        raise SpecError(f"{name} was started with a different spec ({'; '.join(diffs) or 'sha256 differs'}); "
                        f"choose another --out, or delete {name} to start over")
    zarr_store.check_kernels(name, attrs)
    verify.refuse_unidentified(name, attrs, "sweep_spec_sha256", "a pbrdf-cl sweep store")
    fixed = verify.repair_skeleton(name, lambda where: _write_skeleton(spec, where), VOLATILE)
    if fixed:
        warnings.warn(StoreWarning(f"{name}: rewrote from the spec what was missing or altered: "
                                   f"{verify.first(fixed)}"), stacklevel=3)
    return name, True


def read_done(spec, store):
    """Boolean array: which chunks of ``spec`` are marked done in the store
    (:func:`pbrdf_cl.store.zarr.read_done`)."""
    return zarr_store.read_done(store, spec.n_chunks)


# ---------------------------------------------------------------------------------------------
# one chunk: compute, write, then mark

#: This process's writers, by (store, spec's SHA-256): opened once per worker.
_RUNNERS = {}


def compute_chunk(spec, eng, i):
    """The values of chunk ``i``: variable name -> array of the chunk's region shape."""
    box = spec.box(i)
    with eng.lock:  # one chunk in flight per engine: the memory budget is per chunk
        if not spec.over:
            plan = dense.GridPlan(box, spec.fixed)
            out = np.empty(plan.size, DTYPES[spec.dtype])
            for _ in dense.grid_blocks(eng, plan, spec.quantity, spec.dtype, spec.shadowing,
                                        spec.memory_budget // 2, out=out):
                pass
            return {spec.quantity: out.reshape(plan.shape)}
        ds = dense.reduce_grid(box, spec.fixed, over=spec.over, quantity=spec.quantity, dtype=spec.dtype,
                               shadowing=spec.shadowing, engine=eng, memory_budget=spec.memory_budget)
        return {v: ds[v].values for v in spec.variables}


class _Runner(runner.Writer):
    """Writes chunks of one spec into one store (:class:`pbrdf_cl.store.runner.Writer`)."""

    delay_env = DELAY_ENV

    def __init__(self, spec, name):
        super().__init__(name, "sweep_spec_sha256", spec.sha256)  # a worker with another pbrdf-cl would mix values
        self.spec = spec

    def compute(self, eng, i):
        return compute_chunk(self.spec, eng, i)

    def pieces(self, i, values):
        region = self.spec.region(i)
        return [(v, region, values[v]) for v in self.spec.variables]  # each one whole Zarr chunk

    def result(self, eng, i, values, seconds):
        return int(i), self.spec.box_points(i), seconds, eng.description


def _runner(spec, name):
    return cluster.per_process(_RUNNERS, (name, spec.sha256), lambda: _Runner(spec, name))


def run_chunk(spec, name, i, device=None, backend="auto"):
    """Dask task: compute chunk ``i`` of ``spec`` with this worker's engine and write it into the
    store ``name``; returns (i, points, seconds, device description)."""
    return _runner(spec, name).run(cluster.worker_engine(device, backend), i)


# ---------------------------------------------------------------------------------------------
# the driver

class SweepResult(Result):
    """Result of :func:`sweep` (attribute access).

    store : the store's path or URL;  spec : the :class:`SweepSpec`
    chunks_total, chunks_computed (this run), chunks_skipped (already done), points_computed,
    seconds, points_per_s : this run's work and throughput (Zarr writes included);
    complete : every chunk is in the store.  ``open()`` returns the ``xarray.Dataset``.
    """

    def open(self):
        import xarray as xr
        return xr.open_zarr(self["store"])

    def summary(self):
        return (f"sweep: {self['chunks_computed']} of {self['chunks_total']} chunks computed "
                f"({self['chunks_skipped']} already done), {self['points_computed']:.4g} points in "
                f"{self['seconds']:.3g} s, {self['points_per_s']:.4g} points/s -> {self['store']}")

    def __repr__(self):
        return f"SweepResult({self.summary()})"


def store_bytes(spec):
    """The uncompressed size of a spec's stored values (an upper bound of the store: Blosc compresses)."""
    cells = int(np.prod(spec.shape, dtype=np.int64))
    if spec.over:
        return cells * (2 * spec.itemsize + 8 * len(spec.over))
    return cells * spec.itemsize


def sweep(spec, store, *, engine=None, device=None, backend="auto", workers=None, scheduler=None, client=None,
          progress=True, allow_large=False):
    """Evaluate a sweep into a Zarr store, computing only the chunks not already there.

    Parameters
    ----------
    spec : str or path, dict or SweepSpec
        See :func:`load_spec`.
    store : path (or URL of an fsspec store) of the Zarr store; created if absent, resumed if
        it holds the same spec, refused if it holds another.
    engine, device : the engine (or device, see :func:`pbrdf_cl.select_device`) for a local run;
        ``device`` is also what every cluster worker builds its own engine for (``engine`` with a
        cluster is refused: ``pbrdf_cl.store.runner.check_cluster``).
    backend : "auto" (the OpenCL device, or the numpy reference where none is usable), "opencl"
        or "numpy", here and on every worker.
    workers : start a local ``dask.distributed`` cluster of this many processes (1 thread each; an
        int, Python's or numpy's).
    scheduler : address of a running scheduler (``tcp://host:8786``); or pass ``client``.
    client : a ``dask.distributed.Client`` to run the chunks on, instead of ``workers`` or
        ``scheduler``.
    progress : a tqdm bar (chunks, points/s, ETA), after a line with the sweep's size and, once the
        first chunk is done, its estimated time.
    allow_large : start even if the store (uncompressed) would not fit on the free disk.

    Returns
    -------
    SweepResult
        Chunks computed and skipped, points, seconds, ``complete``; ``.open()`` gives the
        ``xarray.Dataset``.

    Examples
    --------
    >>> res = pbrdf_cl.sweep("examples/sweep_sigma_theta.toml", "sigma_theta.zarr")  # doctest: +SKIP
    >>> res.open().dop.sel(theta_i=40, phi=180).plot()  # doctest: +SKIP
    """
    spec = load_spec(spec)
    runner.check_cluster(workers, scheduler, client, engine, "sweep")
    runner.check_free_disk(store, store_bytes(spec), f"{spec.points} points, uncompressed; Blosc usually saves a "
                           "factor 1.5-3", allow_large, "sweep", hint="reduce axes with [reduce], ")
    with runner.session(store, zarr_store.store_name(store)):
        return _run(spec, store, dict(engine=engine, device=device, backend=backend, workers=workers,
                                      scheduler=scheduler, client=client), progress)


def _run(spec, store, where, progress):
    """:func:`sweep` under the store's lock: create or resume (checked against the digests), run
    the chunks not done, then mark the store complete if every chunk is there and intact."""
    name, existed = open_store(spec, store)
    done = zarr_store.resume(store, name, spec.n_chunks, existed)
    if existed:
        done = runner.resume_units(name, spec.n_chunks, spec.variables, "chunks")
    todo = np.flatnonzero(~done)
    skipped = spec.n_chunks - todo.size
    stats = dict(chunks=0, points=0)
    if progress and todo.size:
        print(f"sweep: {spec.points} points in {spec.n_chunks} chunks ({todo.size} to compute), up to "
              f"{_human(store_bytes(spec))} stored uncompressed", file=sys.stderr)
    bar = runner.progress_bar(progress and todo.size > 0, total=spec.n_chunks, initial=skipped, unit="chunk",
                              desc="sweep")
    t0 = time.perf_counter()
    devices = set()

    def finished(result):
        stats["chunks"] += 1
        stats["points"] += result[1]
        if result[3] not in devices:
            devices.add(result[3])
            runner.note_device(name, result[3], "chunks")
        if stats["chunks"] == 1:
            stats["first"] = time.perf_counter()
        if stats["chunks"] == 2 and progress and todo.size > 2:  # the first chunk also built the kernels
            took = time.perf_counter() - stats["first"]
            eta = took * (todo.size - 2)
            msg = f"sweep: a chunk takes about {took:.3g} s here; about {_eta(eta)} for the rest"
            (bar.write(msg, file=sys.stderr) if bar is not None else print(msg, file=sys.stderr))
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"{stats['points'] / max(time.perf_counter() - t0, 1e-9):.3g} points/s", refresh=False)

    with runner.discard_if_empty(store, name, not existed, spec.n_chunks, ("sweep_spec_sha256", spec.sha256)):
        runner.run_units(todo, lambda: _Runner(spec, name), finished, task=run_chunk, shared=spec,
                         args_of=lambda i: (name, i, where["device"], where["backend"]), key="pbrdf-sweep",
                         bar=bar, **where)
    seconds = time.perf_counter() - t0
    bad = verify.complete(name, spec.n_chunks, "sweep_complete", spec.variables)
    if bad:
        warnings.warn(StoreWarning(f"{name}: {len(bad)} chunks were damaged after they were written (chunks "
                                   f"{verify.first(bad)}); run the same command again to compute them"), stacklevel=3)
    complete = skipped + stats["chunks"] == spec.n_chunks and not bad
    res = SweepResult(store=name, spec=spec, chunks_total=spec.n_chunks, chunks_computed=stats["chunks"],
                      chunks_skipped=int(skipped), points_computed=stats["points"], seconds=seconds,
                      points_per_s=stats["points"] / seconds if stats["points"] else 0.0, complete=complete)
    log.info(res.summary())
    return res


def _eta(seconds):
    """``5400`` -> ``"1.5 h"``."""
    for unit, size in (("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"
