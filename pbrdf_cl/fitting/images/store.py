"""Per-pixel fits of image stacks of any size into a Zarr store, block by block, resumable, on one
machine or a ``dask.distributed`` cluster: :func:`write_store`, what ``pbrdf_cl.fit_batch(...,
store=...)`` (``pbrdf-cl fit-image``) runs.  It takes a checked job and never imports the front
door (:mod:`pbrdf_cl.fitting.images.batch`).

The unit of work is :class:`pbrdf_cl.fitting.images.job.BatchJob`'s block of rows of the first pixel
dimension (sized by ``memory_budget``); each block is read from the stack on its own, fitted,
written, and marked done by the runner sweeps use for their chunks (:mod:`pbrdf_cl.store.runner`:
the checks before any work, write-then-mark, the loop here or on a cluster, progress, Ctrl-C);
this module says what a block computes and writes.

Layout of the store (Zarr format 2, consolidated metadata; ``xarray.open_zarr`` reads it as the
Dataset :func:`pbrdf_cl.fit_batch` returns in memory):

- the variables of that Dataset (``n``, ``n_stderr``, ``n_ci95``, ..., ``sse``, ``chi2``,
  ``determined``, ``n_valid``, ``nfev``, ``status``) with their attrs, and its coordinates
  (``bound``, ``param``, the stack's pixel coordinates); each Zarr chunk is exactly one block of
  rows (the whole of the other dimensions), so no two writers ever share a Zarr chunk;
- ``_sweep/done``: one uint8 per block, set (1) only after that block's values are in the store
  (write-then-mark: a block without its mark is computed again), the record of a sweep store,
  read by :func:`pbrdf_cl.store.zarr.read_done`; ``_sweep/input_sha256``: per block, the SHA-256 of
  the input rows it was fitted from; ``_sweep/digest`` and ``_sweep/device``: the SHA-256 of the
  block's values and the device that fitted it (all three written before the mark;
  :mod:`pbrdf_cl.store.verify`); ``status`` has the fill value ``NOT_COMPUTED`` (-128), never a status;
- root attrs: the Dataset's attrs (model, bounds, grid, ...), the canonical job settings as JSON
  (``batch_settings``) and their SHA-256 (``batch_settings_sha256``), the SHA-256 of the OpenCL
  sources (``sweep_kernels_sha256``, checked as a sweep's: :func:`pbrdf_cl.store.zarr.check_kernels`), the memory budget
  that chose the blocks (``batch_memory_budget``, not part of the settings: the block size is),
  the devices that computed blocks (``batch_devices``, ``store_devices``), ``batch_complete`` (set
  only when every block is done and matches its digest) and then the whole input's SHA-256
  (``batch_input_sha256``, from the blocks').

No timing is stored, so that a resumed store is byte for byte the store of an uninterrupted run
(on the same device); the returned Dataset carries this run's ``seconds`` in its attrs.

Testing aid: ``PBRDF_BATCH_BLOCK_DELAY=<seconds>`` sleeps that long per block (half before the
values are written, half between writing them and marking the block done).
"""
from __future__ import annotations

import copy
import gc
import hashlib
import json
import re
import time
import warnings

import numpy as np

from ... import sizes
from ...device.engine import kernels_sha256
from ...errors import StoreError, StoreWarning
from ...store import cluster, lock, runner, verify
from ...store import zarr as zarr_store
from ...store.cluster import local_engine  # noqa: F401 (store.local_engine: the image fit's local engine)
from ...version import __version__
from .dataset import NOT_COMPUTED, PIXEL_STATUS, goodness_summary, interval_summary

#: Version of the canonical settings (part of their hash).
SETTINGS_VERSION = 3  # 2: the goodness-of-fit variables (r2, p_value, fits_data); 3: digests, status fill
DELAY_ENV = "PBRDF_BATCH_BLOCK_DELAY"
DONE = zarr_store.DONE
HASHES = "_sweep/input_sha256"
#: Rows of the stack read for the settings' sample hash (spread evenly, first and last included).
SAMPLE_ROWS = 5


# ---------------------------------------------------------------------------------------------
# identity: the job's settings and its input

def _rows_sha256(raw):
    """SHA-256 of the arrays :meth:`pbrdf_cl.io.source.Source.rows` returns (names, shapes,
    dtypes, bytes)."""
    h = hashlib.sha256()
    for name in sorted(raw):
        a = np.ascontiguousarray(raw[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape}\0".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def _sample_sha256(source):
    """SHA-256 of SAMPLE_ROWS rows of the stack (every variable), read one row at a time."""
    n0 = source.shape[0]
    rows = sorted({int(r) for r in np.linspace(0, n0 - 1, min(n0, SAMPLE_ROWS)).round()})
    h = hashlib.sha256()
    for r in rows:
        h.update(f"{r}:{_rows_sha256(_read(source, r, r + 1))}\0".encode())
    return h.hexdigest()


def settings(job, block_rows):
    """The canonical settings of a store for ``job`` in blocks of ``block_rows`` rows: everything
    that determines the stored values, as a JSON-ready dict.

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.job.BatchJob
        The checked job.
    block_rows : int
        Rows of the first pixel dimension per block (one Zarr chunk).

    Returns
    -------
    dict
        ``model``, ``shadowing``, ``free``, ``bounds``, ``fixed``, ``n_starts``, ``grid`` (the grid
        axes' values), ``intensity``, ``sigma_known``, ``noise_floor``, ``block_rows``, the
        kernels' SHA-256 is not in it (stored beside), and ``stack``: shape, dims, measurements,
        variables, geometry and ``sample_sha256`` (SHA-256 of SAMPLE_ROWS rows of every
        variable; the whole input is checked block by block, see :func:`write_store`).

    Examples
    --------
    >>> import numpy as np, pbrdf_cl
    >>> from pbrdf_cl.fitting.images.job import BatchJob
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), (2, 3, 30))
    >>> s = settings(BatchJob(dict(dop=dop, theta_i=ti, theta_r=tr)), 1)
    >>> s["model"], s["block_rows"], s["stack"]["shape"]
    ('six-param', 1, [2, 3])
    """
    setup, src = job.setup, job.source
    bounds = {n: [float(setup.lo[i]), float(setup.hi[i])] for i, n in enumerate(setup.free)}
    if setup.use_f00:
        bounds["ks"] = [float(v) for v in setup.ks_bounds]
    return {"pbrdf_batch": SETTINGS_VERSION, "model": setup.model, "shadowing": setup.shadowing,
            "free": list(job.names), "bounds": bounds, "fixed": {k: float(v) for k, v in sorted(setup.fixed.items())},
            "n_starts": int(setup.n_starts), "grid": {n: [float(v) for v in a] for n, a in setup.axes.items()},
            "intensity": bool(setup.use_f00), "sigma_known": bool(setup.sigma_known),
            "noise_floor": float(setup.noise_floor), "block_rows": int(block_rows),
            "stack": {"shape": [int(s) for s in src.shape], "dims": list(src.dims), "measurements": int(src.M),
                      "variables": sorted(src.vars), "geometry": "shared" if src.shared else "per pixel",
                      "sample_sha256": _sample_sha256(src)}, **job.store_settings()}


def _canonical(d):
    text = json.dumps(d, separators=(",", ":"), sort_keys=True)
    return text, hashlib.sha256(text.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------
# reading and fitting one block

def _read(source, r0, r1):
    """Rows r0..r1 of the stack, read without a distributed client (a block is read inside a task,
    or on the driver: dask's synchronous scheduler, one block in memory)."""
    try:
        import dask
    except ImportError:  # pragma: no cover - no dask: the stack is numpy
        return source.rows(r0, r1)
    with dask.config.set(scheduler="synchronous"):
        return source.rows(r0, r1)


def _fit(job, eng, r0, r1):
    try:
        import dask
    except ImportError:  # pragma: no cover
        return job.fit_rows(eng, r0, r1)
    with dask.config.set(scheduler="synchronous"), eng.lock:  # one block in flight per engine
        return job.fit_rows(eng, r0, r1)


def _block_dataset(job, out, r0, r1):
    """The result Dataset of rows r0..r1 (``job.dataset`` of a job cut down to those rows)."""
    part = copy.copy(job)
    src = part.source = copy.copy(job.source)
    src.shape = (r1 - r0,) + tuple(job.source.shape[1:])
    first = src.dims[0]
    src.coords = {name: (cd, (v[(slice(None),) * cd.index(first) + (slice(r0, r1),)] if first in cd else v), attrs)
                  for name, (cd, v, attrs) in job.source.coords.items()}
    return part.dataset(out)


class _Writer(runner.Writer):
    """Writes blocks of one job's store (:class:`pbrdf_cl.store.runner.Writer`; opened once per
    process); the job comes with each block."""

    delay_env = DELAY_ENV

    def __init__(self, name, digest):
        # a worker with other kernels would mix values; a store of another job is never written into
        super().__init__(name, "batch_settings_sha256", digest, error=StoreError)
        g = self.group
        self.all = json.loads(g.attrs["batch_variables"])
        whole = json.loads(g.attrs.get("batch_whole_variables", "[]"))
        self.variables = [v for v in self.all if v not in whole]  # written block by block

    def compute(self, eng, i, job, r0, r1):
        """Fit block ``i`` (rows r0..r1): (its input's SHA-256, the fit's outputs, their Dataset)."""
        digest = _rows_sha256(_read(job.source, r0, r1))
        out = _fit(job, eng, r0, r1)
        ds = _block_dataset(job, out, r0, r1)
        if sorted(ds.data_vars) != sorted(self.all):
            raise RuntimeError(f"internal: the fit gives variables {sorted(ds.data_vars)}, the store holds "
                               f"{sorted(self.all)}")
        return digest, out, ds

    def pieces(self, i, values, job, r0, r1):
        """Each variable's rows r0..r1 (one whole Zarr chunk), then the input's SHA-256 (:data:`HASHES`)."""
        digest, _, ds = values
        out = []
        for v in self.variables:
            a = ds[v].values
            if a.dtype != self.group[v].dtype:
                raise RuntimeError(f"internal: the fit gives {v} as {a.dtype}, the store holds {self.group[v].dtype}")
            out.append((v, (slice(r0, r1),), a))
        return out + [(HASHES, (slice(int(i), int(i) + 1),), np.frombuffer(bytes.fromhex(digest), np.uint8)[None])]

    def result(self, eng, i, values, seconds):
        """(i, pixels, seconds, device)."""
        # a lazy stack's reads build dask graphs whose reference cycles wait for the cyclic
        # collector, which in a long-lived process runs rarely: 7 MB of them after a dozen blocks
        # of a 16 MB stack with it held off; collected here they stay one block's worth
        gc.collect()
        return int(i), int(values[1]["status"].size), seconds, eng.description


_WRITERS = {}


def run_block(job, name, digest, i, r0, r1, device=None, backend="auto"):
    """Dask task: fit block ``i`` (rows r0..r1) of ``job`` with this worker's engine and write it
    into the store ``name``.

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.job.BatchJob
        The job (scattered to every worker).
    name : str
        The store (a path every worker sees, or a URL).
    digest : str
        The SHA-256 of the job's settings (``attrs["batch_settings_sha256"]`` of the store).
    i, r0, r1 : int
        The block and its rows.
    device, backend
        The engine each worker builds once (``pbrdf_cl.store.cluster.worker_engine``).

    Returns
    -------
    tuple
        (i, pixels, seconds, device description).

    Examples
    --------
    >>> client.submit(run_block, job_future, "fit.zarr", digest, 0, 0, 8)  # doctest: +SKIP
    """
    writer = cluster.per_process(_WRITERS, (name, digest), lambda: _Writer(name, digest))
    return writer.run(cluster.worker_engine(device, backend), i, job, r0, r1)


# ---------------------------------------------------------------------------------------------
# the store

def _write_skeleton(job, blocks, block_rows, the_settings, memory_budget, store):
    """Coordinates, empty variables, the done record, then (last: the commit point) the root attrs."""
    template = _block_dataset(job, job.empty_outputs(1), 0, 1)
    g = zarr_store.open_group(store, "w")
    first = job.source.dims[0]
    n0 = job.source.shape[0]
    for cname, c in template.coords.items():
        full = job.source.coords.get(cname)  # the stack's own coordinates, whole (the template has one row)
        values = np.asarray(full[1]) if full is not None else np.asarray(c.values)
        arr = zarr_store.create_array(g, cname, values.shape, values.shape or (1,), values.dtype, None, None,
                                      {"_ARRAY_DIMENSIONS": list(c.dims), **c.attrs})
        arr[...] = values
    variables = list(template.data_vars)
    # the stack's coordinates that are not dimensions (x_mm, y_mm, ...): named in each variable's
    # "coordinates" attribute (CF), as xarray writes them, so that open_zarr reads them as coordinates
    aux = [str(c) for c in template.coords if c not in template.dims]
    whole = [v for v in variables if template[v].dims[0] != first]  # over labels, not rows: written now
    for v in variables:
        var = template[v]
        if v in whole:
            arr = zarr_store.create_array(g, v, var.shape, var.shape, var.dtype, None, None,
                                          {"_ARRAY_DIMENSIONS": list(var.dims), **var.attrs})
            arr[...] = var.values
            continue
        shape = (n0,) + var.shape[1:]
        # no _FillValue on other integers; status: NOT_COMPUTED, never a status, where no block was written
        fill = np.nan if var.dtype.kind == "f" else (NOT_COMPUTED[0] if v == "status" else None)
        mine = [c for c in aux if set(template[c].dims) <= set(var.dims)]
        zarr_store.create_array(g, v, shape, (block_rows,) + var.shape[1:], var.dtype, fill, zarr_store.compressor(),
                             {"_ARRAY_DIMENSIONS": list(var.dims), **var.attrs,
                              **({"coordinates": " ".join(mine)} if mine else {})})
    sub = g.require_group("_sweep")
    sub.attrs.update(description=f"done[i] = 1 once block i (rows i*{block_rows} to (i+1)*{block_rows} of "
                                 f"{first}) is in the store; input_sha256[i]: SHA-256 of those rows of the input",
                     block_rows=int(block_rows))
    zarr_store.create_done(g, len(blocks))
    zarr_store.create_array(sub, "input_sha256", (len(blocks), 32), (1, 32), "u1", 0, None, {})
    text, digest = _canonical(the_settings)
    units = {"count": len(blocks), "variables": [v for v in variables if v not in whole] + [HASHES],
             "job": "batch_settings", "complete": "batch_complete"}
    verify.seal(store, {**template.attrs, "title": "pbrdf-cl per-pixel fit", "pbrdf_cl_version": __version__,
                        "batch_settings": text, "batch_settings_sha256": digest,
                        "sweep_kernels_sha256": kernels_sha256(), "batch_variables": json.dumps(variables),
                        "batch_whole_variables": json.dumps(whole), "batch_blocks": len(blocks),
                        "batch_block_rows": int(block_rows), "batch_memory_budget": int(memory_budget),
                        "batch_devices": [], "batch_complete": False, verify.UNITS: units})


#: Root attrs that runs change (or that are not the settings): not rewritten on resuming.
VOLATILE = ("batch_complete", "batch_devices", "pbrdf_cl_version", "batch_memory_budget", zarr_store.DEVICES)


def _open_store(job, blocks, block_rows, the_settings, memory_budget, store):
    """Create the store, or check that an existing one holds this job; returns (name, existed)."""
    _, digest = _canonical(the_settings)
    name, attrs = zarr_store.create_or_read(
        store, lambda where: _write_skeleton(job, blocks, block_rows, the_settings, memory_budget, where),
        not_a_store=lambda name: StoreError(f"{name} exists and is not a pbrdf-cl fit store; choose another --out "
                                            "or delete it"),
        unreadable=lambda name: StoreError(f"{name} exists and is not a readable Zarr store; choose another --out "
                                           "or delete it"))
    if attrs is None:
        return name, False
    if "batch_settings_sha256" not in attrs:
        what = "a pbrdf-cl sweep store" if "sweep_spec_sha256" in attrs else "not a pbrdf-cl fit store"
        raise StoreError(f"{name} exists and is {what}; choose another --out or delete it")
    if attrs["batch_settings_sha256"] != digest:
        _refuse_other_settings(name, attrs, zarr_store.stored_differences(attrs, "batch_settings", the_settings))
    _check_kernels(name, attrs)
    verify.refuse_unidentified(name, attrs, "batch_settings_sha256", "a pbrdf-cl fit store")
    fixed = verify.repair_skeleton(
        name, lambda where: _write_skeleton(job, blocks, block_rows, the_settings, memory_budget, where), VOLATILE)
    if fixed:
        warnings.warn(StoreWarning(f"{name}: rewrote from the settings what was missing or altered: "
                                   f"{verify.first(fixed)}"), stacklevel=3)
    return name, True


def _refuse_other_settings(name, attrs, diffs):
    """The :class:`StoreError` of a store started with other settings (``diffs``, the
    differences :func:`pbrdf_cl.store.zarr.differences` lists)."""
    diffs = [re.sub(r'"([0-9a-f]{12})[0-9a-f]{52}"', r"\1...", d) for d in diffs]  # SHA-256s shortened
    hint = ""
    if any(d.startswith("block_rows") for d in diffs):
        hint = (f" (the blocks follow the memory budget: the store's was "
                f"{sizes.human(int(attrs.get('batch_memory_budget', 0)))})")
    raise StoreError(f"{name} was started with other settings ({'; '.join(diffs) or 'sha256 differs'}){hint}; "
                     f"choose another --out, or delete {name} to start over")


def check_before_stage(job, store, allow_large=False):
    """What :func:`write_store` refuses that a job's preparing stage (a ``LabelJob``'s label
    stage, which can take long) does not change, checked before it runs: the free disk, another
    run holding the store's lock, a store started with other settings (all but the label stage's
    values, which :func:`write_store` checks after it).

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.job.BatchJob
        The checked job, not yet prepared.
    store : str or path
        The Zarr store :func:`write_store` will write.
    allow_large : bool, default False
        As :func:`write_store`'s.

    Returns
    -------
    None
        Nothing to refuse (yet).

    Raises
    ------
    StoreError
        As :func:`write_store`.

    Examples
    --------
    >>> check_before_stage(LabelJob(stack, labels=L), "fit.zarr")  # doctest: +SKIP
    """
    blocks = job.blocks()
    runner.check_free_disk(store, store_bytes(job), f"{job.source.n_pixels} pixels, uncompressed", allow_large,
                           "fit-image")
    name = zarr_store.store_name(store)
    with lock.holding(name, zarr_store.is_local(store)):
        pass  # another run holds it: refused here
    attrs = zarr_store.read_root_attrs(name)
    if not attrs or "batch_settings_sha256" not in attrs:
        return  # none yet, or not a fit store: write_store's
    the_settings = settings(job, blocks[0][1] - blocks[0][0])
    try:
        stored = json.loads(attrs.get("batch_settings", "{}"))
    except ValueError:
        return  # damaged: write_store's
    the_settings["label_values"] = stored.get("label_values")  # the stage's: checked after it
    diffs = zarr_store.differences(stored, the_settings)
    if diffs:
        _refuse_other_settings(name, attrs, diffs)


def _check_kernels(name, attrs):
    """:func:`pbrdf_cl.store.zarr.check_kernels`, refusing with a :class:`StoreError`."""
    zarr_store.check_kernels(name, attrs, error=StoreError)


def _check_inputs(job, name, blocks, done):
    """The blocks marked done were fitted from these rows of the stack: compare each one's
    SHA-256 (read one block at a time; every row of every done block, not only the settings'
    sample rows).  Returns the SHA-256 of the input's done blocks (:func:`input_sha256`)."""
    hashes = zarr_store.open_group(name, "r")[HASHES]
    first = job.source.dims[0]
    for i in np.flatnonzero(done):
        r0, r1 = blocks[i]
        stored = bytes(np.asarray(hashes[int(i)], np.uint8)).hex()
        now = _rows_sha256(_read(job.source, r0, r1))
        if stored != now:
            raise StoreError(f"{name}: the stack's rows {r0}..{r1 - 1} of {first} differ from those the store's "
                             f"block {i} was fitted from (input SHA-256 {stored[:12]} in the store, {now[:12]} now); "
                             f"choose another --out, or delete {name} to start over")


def _mark_complete(name, n_blocks, variables):
    """Mark the store complete if every block is done and intact (:func:`pbrdf_cl.store.verify.complete`)."""
    bad = verify.complete(name, n_blocks, "batch_complete", variables)
    g = zarr_store.open_group(name, "r+")
    if g.attrs.get("batch_complete") and "batch_input_sha256" not in g.attrs:
        # the whole input, from its blocks' SHA-256s (each checked against the stack when it was fitted)
        g.attrs["batch_input_sha256"] = hashlib.sha256(np.asarray(g[HASHES][:], np.uint8).tobytes()).hexdigest()
        zarr_store.consolidate(name)
    if bad:
        warnings.warn(StoreWarning(f"{name}: {len(bad)} blocks were damaged after they were written (blocks "
                                   f"{verify.first(bad)}); run the same command again to fit them"), stacklevel=3)


def _add_goodness(name, ds):
    """The goodness-of-fit summary of a complete store (:func:`pbrdf_cl.fitting.images.dataset.goodness_summary`,
    read block by block) and where best values lie outside their intervals
    (:func:`pbrdf_cl.fitting.images.dataset.interval_summary`) written into its attrs; returns them."""
    summary = {**goodness_summary(ds), **interval_summary(ds)}
    g = zarr_store.open_group(name, "r+")
    g.attrs.update(summary)
    zarr_store.consolidate(name)
    return summary


def _add_devices(name, found):
    g = zarr_store.open_group(name, "r+")
    known = list(g.attrs.get("batch_devices", []))
    new = sorted(set(known) | set(found))
    if new != known:
        g.attrs["batch_devices"] = new
        zarr_store.consolidate(name)


def read_progress(store):
    """How far a store's fit is: (blocks done, blocks in all).

    Parameters
    ----------
    store : str or path
        A store of :func:`pbrdf_cl.fit_batch` (``store=``).

    Returns
    -------
    tuple of int
        (blocks marked done, blocks).

    Examples
    --------
    >>> read_progress("params.zarr")  # doctest: +SKIP
    (3, 8)
    """
    name = zarr_store.store_name(store)
    total = int(zarr_store.open_group(name, "r").attrs["batch_blocks"])
    return int(zarr_store.read_done(name, total).sum()), total


def store_bytes(job):
    """Uncompressed bytes of the store of ``job`` (an upper bound: Blosc compresses).

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.job.BatchJob
        The job.

    Returns
    -------
    int
        Bytes per pixel of the result times the pixels.

    Examples
    --------
    >>> store_bytes(job)  # doctest: +SKIP
    53248
    """
    D = len(job.names)
    per = 8 * D * 4 + D + 8 * 4 + 1
    return int(per * job.source.n_pixels)


def status_counts(ds):
    """Pixels per status code of a result (read block by block from a store).

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.fit_batch` (in memory or from a store).

    Returns
    -------
    dict
        Status name (``pbrdf_cl.fitting.images.dataset.PIXEL_STATUS``) -> pixels, for the codes present, in
        the order of ``PIXEL_STATUS``; then ``not_computed``, the pixels of a store's blocks not
        written (``pbrdf_cl.fitting.images.dataset.NOT_COMPUTED``, the status array's fill value).

    Examples
    --------
    >>> status_counts(ds)  # doctest: +SKIP
    {'converged': 200, 'underdetermined': 56}
    """
    st = ds["status"]
    if st.dtype.kind == "f":  # a store opened by xarray.open_zarr itself: its fill value read as NaN
        st = st.fillna(NOT_COMPUTED[0]).astype(np.int8)
    counts = np.zeros(256, np.int64)
    if st.chunks:
        first = st.chunks[0]
        r = 0
        for size in first:
            counts += np.bincount(np.asarray(st[r:r + size].values, np.int64).ravel() + 128, minlength=256)
            r += size
    else:
        counts += np.bincount(np.asarray(st.values, np.int64).ravel() + 128, minlength=256)
    out = {PIXEL_STATUS[c][0]: int(counts[c + 128]) for c in PIXEL_STATUS if counts[c + 128]}
    if counts[NOT_COMPUTED[0] + 128]:  # the store's fill value: blocks not written (or lost)
        out[NOT_COMPUTED[1]] = int(counts[NOT_COMPUTED[0] + 128])
    other = int(counts.sum()) - sum(out.values())
    if other:
        out["unknown"] = other
    return out


def check_cluster(workers=None, scheduler=None, client=None, engine=None):
    """Check the cluster options of a store's fit before any work; returns how many were given.

    Parameters
    ----------
    workers, scheduler, client : optional
        As for :func:`write_store`: at most one of them (``pbrdf_cl.store.runner.check_cluster``,
        the sweeps' check too).
    engine : pbrdf_cl.Engine, optional
        A local run's engine: refused with a cluster (every worker builds its own).

    Returns
    -------
    int
        0 (a local run) or 1.

    Raises
    ------
    ValueError
        More than one of them, ``workers`` not a positive integer, or ``engine`` with a cluster.
    RuntimeError
        A cluster without ``dask.distributed`` installed.

    Examples
    --------
    >>> check_cluster(workers=2)  # doctest: +SKIP
    1
    """
    return runner.check_cluster(workers, scheduler, client, engine, "fit")


def write_store(job, store, *, progress=False, engine=None, backend="auto", device=None, workers=None, scheduler=None,
                client=None, allow_large=False):
    """Fit every pixel of a checked job into a Zarr store, block by block; resumable (what
    ``pbrdf_cl.fit_batch(..., store=...)`` runs).

    A store that already holds this job (same settings, input and kernels) is resumed: only the
    blocks not marked done are fitted, and the finished store is byte for byte the store of an
    uninterrupted run on the same device (the fits are deterministic, and nothing run-dependent
    is stored).  A store started with other settings, another input or other kernels is refused
    with a one-line :class:`StoreError` naming what differs.

    What is checked on resuming: the settings (model, bounds, fixed values, shadowing, n_starts,
    the grid's values, whether intensities are fitted, dop_std given, the noise floor, the block
    size in rows), the stack's shape, dims, measurements per pixel, variable names and geometry,
    a SHA-256 of 5 of its rows (every variable; at the start, before any work), and then, for
    every block already done, the SHA-256 of its rows of the input against the one recorded when
    it was fitted (this reads the done part of the stack once more, one block at a time; a
    changed value anywhere in it is found); every done block's values against their digest (a
    damaged block is fitted again, said in one :class:`pbrdf_cl.StoreWarning` line), and the
    store's metadata against a fresh skeleton (rewritten where missing or altered).  A store
    resumed on another device is allowed and said in one warning line: it mixes both devices'
    last bits (``_sweep/device`` records each block's, ``attrs["store_devices"]`` and
    ``attrs["batch_devices"]`` list them).  The run holds the store's lock
    (``pbrdf_cl.store.lock``; a second run is refused).

    Memory: one block in flight per engine, sized by ``memory_budget``: the input is read a block
    of rows at a time (with the chunks of a lazy stack that hold them), the outputs written a
    block at a time.  Nothing here reads the whole stack; ``pbrdf_cl.fitting.images.job.BatchJob``'s
    check of the angles reads the first measurement of per-pixel ``theta_i`` and ``theta_r`` of
    every pixel (1/M of those variables), and a block is never smaller than one row.  (How much
    one block takes is BatchJob's estimate.)  With a cluster the job is sent to each worker
    once: an in-memory (numpy) stack goes with it whole, a lazy one (``xarray.open_zarr``, or a
    path to a ``.zarr``/``.nc`` stack) as its recipe, each worker reading its blocks itself.

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.job.BatchJob
        The checked job (the stack, its settings and blocks); with a path to a ``.nc`` stack,
        opened by ``pbrdf_cl.io.source.open_stack_lazily`` so that it is read a block at
        a time.
    store : str or path
        The Zarr store (a local path, or the URL of an fsspec store that every worker reaches);
        created if absent, resumed if it holds this job, refused otherwise.
    progress : bool, default False
        A tqdm bar in pixels (pixels/s, the time left) on stderr.
    engine, backend
        Where a local run computes (as for :func:`pbrdf_cl.fit_batch`); ``backend`` (and
        ``device``) is also what every cluster worker builds its own engine for.
    device : str, optional
        The OpenCL device (see :func:`pbrdf_cl.select_device`) for a local run without
        ``engine``, and for every worker.
    workers : int, optional
        Fit on a local ``dask.distributed`` cluster of this many processes (1 thread each).
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``).
    client : distributed.Client, optional
        A client of a running cluster.  The workers write their blocks into the store
        themselves (as sweep workers do): it must be a path or URL they all reach.
    allow_large : bool, default False
        Start even if the store (uncompressed) would not fit on the free disk.

    Returns
    -------
    xarray.Dataset
        The result opened from the store (``xarray.open_zarr``: lazy), with the variables of
        :func:`pbrdf_cl.fit_batch`; ``attrs`` add ``seconds`` (this run), ``blocks_computed``
        and ``blocks_skipped`` (this run) to the store's.

    Raises
    ------
    StoreError
        The store holds another job, or another input, or its root attributes are damaged;
        another run holds its lock; the disk is full (a ``ValueError``; one line naming the
        store and how to resume).
    ValueError
        More than one of ``workers``, ``scheduler`` and ``client`` (:func:`check_cluster`).
    RuntimeError
        A cluster without ``dask.distributed`` installed.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl, tempfile, os
    >>> from pbrdf_cl.fitting.images.job import BatchJob
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), (2, 3, 30))
    >>> out = os.path.join(tempfile.mkdtemp(), "fit.zarr")
    >>> ds = write_store(BatchJob(dict(dop=dop, theta_i=ti, theta_r=tr)), out)
    >>> ds.n.shape, ds.attrs["batch_complete"], bool(abs(ds.n - 1.6).max() < 1e-3)
    ((2, 3), True, True)
    """
    check_cluster(workers, scheduler, client, engine)
    blocks = job.blocks()
    block_rows = blocks[0][1] - blocks[0][0]
    runner.check_free_disk(store, store_bytes(job), f"{job.source.n_pixels} pixels, uncompressed", allow_large,
                           "fit-image")
    the_settings = settings(job, block_rows)  # reads the sample rows: a refused input leaves no store
    with runner.session(store, zarr_store.store_name(store)):
        return _run(job, store, blocks, block_rows, the_settings, progress,
                    dict(engine=engine, device=device, backend=backend, workers=workers, scheduler=scheduler,
                         client=client))


def _run(job, store, blocks, block_rows, the_settings, progress, where):
    """:func:`write_store` under the store's lock: create or resume (checked against the digests and
    the input), fit the blocks not done, mark the store complete if every block is there and intact."""
    digest = _canonical(the_settings)[1]
    name, existed = _open_store(job, blocks, block_rows, the_settings, job.memory_budget, store)
    done = zarr_store.resume(store, name, len(blocks), existed)
    variables = zarr_store.read_root_attrs(name)[verify.UNITS]["variables"]
    if existed:
        done = runner.resume_units(name, len(blocks), variables, "blocks")
    if existed and done.any():
        _check_inputs(job, name, blocks, done)
    todo = np.flatnonzero(~done)
    skipped_px = sum(_pixels(job, *blocks[i]) for i in np.flatnonzero(done))
    bar = runner.progress_bar(progress and todo.size > 0, total=job.source.n_pixels, initial=skipped_px,
                              desc="fit_batch", unit="px", unit_scale=True, smoothing=0.1)
    stats = dict(blocks=0, pixels=0, devices=set())
    t0 = time.perf_counter()

    def finished(result):
        _, pixels, _, dev = result
        stats["blocks"] += 1
        stats["pixels"] += pixels
        if dev not in stats["devices"]:
            stats["devices"].add(dev)
            runner.note_device(name, dev, "blocks")
        if bar is not None:
            bar.update(pixels)
    try:
        with runner.discard_if_empty(store, name, not existed, len(blocks), ("batch_settings_sha256", digest)):
            runner.run_units(todo, lambda: _Writer(name, digest), finished, task=run_block, shared=job,
                             args_of=lambda i: (name, digest, i, *blocks[i], where["device"], where["backend"]),
                             key="pbrdf-fit", local_args=lambda i: (job, *blocks[i]), bar=bar,
                             started=lambda eng: _add_devices(name, [eng.description]), **where)
    finally:
        if stats["devices"] and zarr_store.Files(name).get(".zattrs") is not None:
            _add_devices(name, stats["devices"])
    seconds = time.perf_counter() - t0
    _mark_complete(name, len(blocks), variables)
    ds = open_result(name)
    if ds.attrs.get("batch_complete") and "goodness" not in ds.attrs:
        ds.attrs.update(_add_goodness(name, ds))
    ds.attrs.update(seconds=seconds, blocks_computed=stats["blocks"], blocks_skipped=int(len(blocks) - todo.size),
                    pixels_computed=stats["pixels"], store=name)
    return ds


def open_result(store):
    """The Dataset of a fit store as :func:`pbrdf_cl.fit_batch` returns it.

    ``xarray.open_zarr`` reads ``status`` as floats, its fill value (``NOT_COMPUTED``, -128: the
    pixels of blocks not written) as NaN; here it stays an integer as in memory, and the
    variables are in :func:`pbrdf_cl.fit_batch`'s order.

    Parameters
    ----------
    store : str or path
        A store of :func:`pbrdf_cl.fit_batch` (``store=``).

    Returns
    -------
    xarray.Dataset
        Lazy (dask), ``status`` an ``int8``.

    Examples
    --------
    >>> open_result("params.zarr").status.dtype  # doctest: +SKIP
    dtype('int8')
    """
    import xarray as xr
    ds = xr.open_zarr(store, mask_and_scale={"status": False})
    ds = ds[[v for v in json.loads(ds.attrs["batch_variables"]) if v in ds]]  # fit_batch's order
    ds["status"].attrs.pop("_FillValue", None)
    return ds


def _pixels(job, r0, r1):
    return (r1 - r0) * int(np.prod(job.source.shape[1:], dtype=np.int64))
