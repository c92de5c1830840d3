"""Benchmark: evaluations per second of every evaluation path, each with its max abs error
against the float64 numpy reference on a sample.  ``scripts/bench.py`` and ``pbrdf-cl bench``
run :func:`main`; it prints a table and writes the same rows as JSON.

Rates are medians over ``--repeats`` runs.  "kernel" rows time the device work alone
(queue finished, outputs left on the device, as in reductions and the objective);
"end-to-end" rows include building tables and copying results to the host.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from . import dense, engine as _engine, reference
from .api import dop as api_dop

INPUTS = _engine.POINT_INPUTS


def random_points(rng, size):
    return dict(theta_i=rng.uniform(0, 89.9, size), theta_r=rng.uniform(0, 89.9, size), phi=rng.uniform(0, 360, size),
                n=rng.uniform(1, 5, size), k=rng.uniform(0, 10, size), sigma=rng.uniform(0.05, 1, size),
                ks=np.ones(size), kd=rng.uniform(0, 5, size), c=rng.uniform(-1, 0, size))


def reference_dop(pts, chunk=1 << 15, threads=2):
    """The float64 reference over ``pts`` in chunks on ``threads`` threads (numpy releases the GIL)."""
    size = pts["theta_i"].size
    out = np.empty(size)

    def work(start):
        sl = slice(start, start + chunk)
        out[sl] = reference.evaluate("dop", *(pts[n][sl] for n in INPUTS))
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(work, range(0, size, chunk)))
    return out


def median_rate(func, work, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        func()
        times.append(time.perf_counter() - t)
    return work / float(np.median(times)), float(np.median(times))


def bench_points(eng, rows, rng, size, repeats, sample):
    pts = random_points(rng, size)
    ref_sample = reference_dop({n: v[:sample] for n, v in pts.items()})
    rate, sec = median_rate(lambda: reference_dop(pts), size, max(1, repeats - 2))
    rows.append(dict(path="numpy reference (32K chunks, 2 threads)", dtype="float64", rate=rate, unit="evals/s",
                     seconds=sec, max_abs_err=0.0, n=size))
    if eng.is_numpy:
        return  # no kernel to time
    for dtype in ("float32", "float64"):
        npdt = _engine.DTYPES[dtype]
        lanes = _engine.VECTOR_WIDTH[dtype]
        kern = eng.kernel("dop_points_vec", dtype, "paper")
        bufs = [eng.to_device(pts[n], dtype) for n in INPUTS]
        out = eng.empty(size * np.dtype(npdt).itemsize)
        args = [out, np.int32(size // lanes)]
        for b in bufs:
            args += [b, np.int32(1)]
        args.append(eng.to_device(np.zeros(1, np.int32), np.int32))  # the out-of-domain flag

        def run():
            eng.launch(kern, (size // lanes,), *args, local_size=(_engine.VECTOR_LOCAL_SIZE,))
            eng.queue.finish()
        run()
        rate, sec = median_rate(run, size // lanes * lanes, repeats)
        got = api_dop(*(pts[n][:sample] for n in ("theta_i", "theta_r", "phi")),
                      **{n: pts[n][:sample] for n in INPUTS[3:]}, dtype=dtype, engine=eng)
        rows.append(dict(path="per-point kernel (kernel)", dtype=dtype, rate=rate, unit="evals/s", seconds=sec,
                         max_abs_err=float(np.max(np.abs(got - ref_sample))), n=size))


GRID_AXES = dict(theta_i=np.linspace(10, 80, 16), theta_r=np.linspace(0, 85, 64), n=np.linspace(1, 3, 16),
                 k=np.linspace(0, 5, 16), sigma=np.linspace(0.05, 1, 32), kd=np.linspace(0, 1, 16),
                 c=np.linspace(-1, 0, 2))  # 268M points


def _grid_sample_error(da, axes, rng, count=2000):
    names = list(da.dims)
    idx = [rng.integers(0, da.sizes[n], count) for n in names]
    got = da.values[tuple(idx)]
    kw = {n: np.asarray(axes[n])[i] for n, i in zip(names, idx)}
    want = api_dop(kw.pop("theta_i"), kw.pop("theta_r"), 180.0, backend="numpy", **kw)
    return float(np.max(np.abs(got - want)))


def bench_grid(eng, rows, rng, scale, repeats):
    axes = dict(GRID_AXES)
    if scale < 1:
        axes["theta_r"] = axes["theta_r"][::4]
        axes["sigma"] = axes["sigma"][::4]
    plan = dense.GridPlan(axes, {})
    ng, nnk, nm, ni = dense._family_sizes(plan)
    if eng.is_numpy:  # the reference computes in float64 whatever the dtype
        da = dense.grid(axes, {}, dtype="float64", engine=eng)
        err = _grid_sample_error(da, axes, rng)
        rate, sec = median_rate(lambda: dense.grid(axes, {}, dtype="float64", engine=eng), plan.size,
                                max(1, repeats - 2))
        rows.append(dict(path="pbrdf_cl.grid -> host DataArray (end-to-end, numpy backend)", dtype="float64",
                         rate=rate, unit="grid points/s", seconds=sec, max_abs_err=err, n=plan.size))
        return
    for dtype in ("float32", "float64"):
        npdt = _engine.DTYPES[dtype]
        level, row_len = dense._row_level(nnk, nm, ni, ng, 1 << 30)
        prog = dense._grid_program(eng, dtype, (nnk, nm, ni), "uint", "dop", PB_ROW_LEVEL=level, PB_ROW_LEN=row_len)
        tables = dense._Tables(eng, dtype, "paper", "dop", *dense._geometry_list(plan, 0, ng), plan.values)
        chunk_rows = max(1, (1 << 24) // row_len)
        total_rows = plan.size // row_len
        out = eng.empty(chunk_rows * row_len * np.dtype(npdt).itemsize)

        def run():
            for r0 in range(0, total_rows, chunk_rows):
                cnt = min(chunk_rows, total_rows - r0)
                eng.launch(prog["grid_rows"], (cnt,), out, np.uint32(r0), np.uint32(cnt), np.uint32(0), *tables.args())
            eng.queue.finish()
        run()
        rate, sec = median_rate(run, plan.size, repeats)
        da = dense.grid(axes, {}, dtype=dtype, engine=eng)
        err = _grid_sample_error(da, axes, rng)
        rows.append(dict(path="factorised grid (kernel)", dtype=dtype, rate=rate, unit="grid points/s", seconds=sec,
                         max_abs_err=err, n=plan.size))
        rate, sec = median_rate(lambda: dense.grid(axes, {}, dtype=dtype, engine=eng), plan.size, max(1, repeats - 2))
        rows.append(dict(path="pbrdf_cl.grid -> host DataArray (end-to-end)", dtype=dtype, rate=rate,
                         unit="grid points/s", seconds=sec, max_abs_err=err, n=plan.size))


def bench_objective(eng, rows, rng, scale, repeats):
    ti = np.repeat([30.0, 40.0, 50.0], 10)
    tr = np.tile(np.arange(20.0, 66.0, 5.0), 3)
    truth = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15 / 0.9, c=-0.3)
    dop = api_dop(ti, tr, 180.0, backend="numpy", **truth) + rng.normal(0, 0.002, ti.size)
    data = dict(theta_i=ti, theta_r=tr, dop=np.clip(dop, 0, 1))
    grid = dict(n=np.linspace(1, 5, 64), k=np.linspace(0, 10, 64), sigma=np.linspace(0.05, 1, 32),
                kd=np.linspace(0, 5, 32), c=np.linspace(-1, 0, 16))
    if scale < 1:
        grid["n"], grid["k"] = grid["n"][::4], grid["k"][::4]
    for dtype in ("float64",) if eng.is_numpy else ("float32", "float64"):
        res = dense.objective(data, grid=grid, dtype=dtype, engine=eng)
        # error: the objective of a sample of parameter vectors against numpy
        idx = rng.integers(0, res.sse.size, 500)
        unr = np.unravel_index(idx, res.sse.shape)
        params = {n: np.asarray(grid[n])[i] for n, i in zip(res.sse.dims, unr)}
        d = api_dop(ti[:, None], tr[:, None], 180.0, backend="numpy", **{n: v[None, :] for n, v in params.items()})
        want = ((d - data["dop"][:, None]) ** 2).sum(axis=0)
        err = float(np.max(np.abs(res.sse.values.ravel()[idx] - want)))
        rate, sec = median_rate(lambda: dense.objective(data, grid=grid, dtype=dtype, engine=eng, return_sse=False),
                                res.n_pairs, repeats)
        label = ", numpy backend" if eng.is_numpy else ""
        rows.append(dict(path=f"objective, grid x 30 measurements (end-to-end, top-10{label})", dtype=dtype, rate=rate,
                         unit="pairs/s", seconds=sec, max_abs_err=err, n=res.n_pairs))


SWEEP_AXES = dict(theta_i=np.linspace(10, 80, 8), theta_r=np.linspace(0, 85, 32), n=np.linspace(1, 3, 16),
                  k=np.linspace(0, 5, 16), sigma=np.linspace(0.05, 1, 16), kd=np.linspace(0, 1, 8),
                  c=np.linspace(-1, 0, 2))  # 16.8M points: 67 MB of float32, 16x a 4 MiB budget


def bench_sweep(eng, device, rows, rng, scale, repeats, workers=2, backend="auto"):
    """pbrdf_cl.sweep into a Zarr store (Zarr writes and the done record included) of a sweep at
    least 10x its memory budget: here, and on a ``workers``-process LocalCluster (0: skipped)."""
    import shutil
    import tempfile

    import xarray as xr

    from .sweep import SweepSpec, sweep
    axes, budget = dict(SWEEP_AXES), 4 << 20
    if scale < 1:
        axes["theta_r"], axes["sigma"], budget = axes["theta_r"][::4], axes["sigma"][::4], 256 << 10
    spec = SweepSpec(dict(axes={n: a.tolist() for n, a in axes.items()}, memory_budget=budget))
    assert spec.points * spec.itemsize >= 10 * spec.memory_budget
    folder = tempfile.mkdtemp(prefix="pbrdf-bench-sweep-")
    runs = iter(range(1 << 30))

    def run(**kw):
        store = os.path.join(folder, f"s{next(runs)}.zarr")
        res = sweep(spec, store, progress=False, **kw)
        assert res.complete and res.chunks_computed == spec.n_chunks
        return store

    def measure(label, **kw):
        store = run(**kw)  # warm-up: kernels built (on every worker), store layout checked
        ds = xr.open_zarr(store)
        idx = {n: xr.DataArray(rng.integers(0, ds.sizes[n], 2000), dims="sample") for n in ds[spec.quantity].dims}
        got = ds[spec.quantity].isel(idx).values
        kw_ref = {n: axes[n][idx[n].values] for n in idx}
        want = api_dop(kw_ref.pop("theta_i"), kw_ref.pop("theta_r"), 180.0, backend="numpy", **kw_ref)
        err = float(np.max(np.abs(got - want)))
        shutil.rmtree(store)

        def timed():
            shutil.rmtree(run(**kw))
        rate, sec = median_rate(timed, spec.points, max(1, repeats - 2))
        label += ", numpy backend" if eng.is_numpy else ""
        rows.append(dict(path=f"sweep -> Zarr store, {label} (end-to-end)", dtype=spec.dtype, rate=rate,
                         unit="grid points/s", seconds=sec, max_abs_err=err, n=spec.points,
                         memory_budget=spec.memory_budget, chunks=spec.n_chunks))
    try:
        measure("here", engine=eng)
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            if workers:
                print("note: the LocalCluster sweep row is skipped: dask.distributed is not installed "
                      "(pip install 'pbrdf-cl[cluster]')")
            workers = 0
        if workers:
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
                    Client(cl) as client:
                measure(f"{workers}-worker LocalCluster", client=client, device=device, backend=backend)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def main(argv=None):
    p = argparse.ArgumentParser(prog="pbrdf-cl bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--device", help="OpenCL device (P:D or a name substring); default as pbrdf_cl.Engine()")
    p.add_argument("--backend", choices=_engine.BACKENDS, default="auto",
                   help="auto (default: the OpenCL device, or numpy without one), opencl, or numpy (the "
                        "reference; kernel rows are skipped and the grid sizes reduced)")
    p.add_argument("--points", type=int, default=1 << 23, help="points for the per-point rows (default 8.4M)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="small sizes, for a smoke test")
    p.add_argument("--json", default="bench.json", help="where to write the JSON (default bench.json)")
    p.add_argument("--sweep-workers", type=int, default=2,
                   help="LocalCluster processes for the sweep row (default 2; 0 skips it; --quick skips it)")
    args = p.parse_args(argv)
    size, repeats, scale = args.points, args.repeats, 1.0
    if args.quick:
        size, repeats, scale = 1 << 16, 2, 0.25
    eng = _engine.resolve_engine(_engine.Engine(args.device) if args.device and args.backend != "numpy" else None,
                                 args.backend)
    sweep_scale = scale
    if eng.is_numpy:
        scale = min(scale, 0.25)  # the per-point reference is ~100x slower than a device: smaller grids
    rng = np.random.default_rng(2020)
    rows = []
    t0 = time.perf_counter()
    bench_points(eng, rows, rng, size, repeats, min(size, 1 << 18))
    bench_grid(eng, rows, rng, scale, repeats)
    bench_objective(eng, rows, rng, scale, repeats)
    bench_sweep(eng, args.device, rows, rng, sweep_scale, repeats, workers=0 if args.quick else args.sweep_workers,
                backend=args.backend)
    device = eng.description
    print(f"device: {device}; host: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus")
    print(f"{'path':58s} {'dtype':8s} {'rate':>12s} {'unit':14s} {'max |err|':>10s}")
    for r in rows:
        print(f"{r['path']:58s} {r['dtype']:8s} {r['rate'] / 1e6:10.1f} M {r['unit']:14s} {r['max_abs_err']:10.2e}")
    report = dict(device=device, cpus=os.cpu_count(), pyopencl=_engine.cl.VERSION_TEXT, seconds=time.perf_counter() - t0,
                  rows=rows)
    with open(args.json, "w") as fh:
        json.dump(report, fh, indent=2)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
