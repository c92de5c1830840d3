#!/usr/bin/env python
"""Record the outputs of a fixed set of calls, or check that they are unchanged, bit for bit.

For refactorings that must not change a single value (issue #27: the package rearranged into
subpackages): record before, check after, on the same machine and device::

    python scripts/check_behaviour.py --record before.npz      # on the old code
    python scripts/check_behaviour.py --check before.npz       # on the new code: exit 1 on any change

The calls cover every path that computes: per-point evaluation (every quantity, both dtypes,
broadcast inputs), grids, reductions, the objective, ``fit`` and ``compare_models`` (with and
without intensities), ``fit_batch`` (shared and per-pixel geometry, in memory and into a Zarr
store), Sobol' and Morris maps, designs (one material and a box), sweeps into a Zarr store, and
maps with derivatives, each on the default OpenCL device and on the numpy backend
(``--backends``).  Outputs are compared with ``numpy.array_equal`` (NaN equal to NaN); timings,
dates and paths are not recorded.  The file also holds the device it was recorded on: checking on
another device is refused.
"""
import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import pbrdf_cl  # noqa: E402

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
CSV = ROOT / "examples" / "steel_435nm.csv"
CSV_F00 = ROOT / "examples" / "steel_435nm_with_f00.csv"
#: attributes that hold how long something took (never the same twice)
TIMINGS = ("seconds", "pixels_per_s", "points_per_s")


def _arrays(prefix, value, out):
    """Flatten a result into named arrays: numbers, arrays, DataArrays, Datasets, dicts, lists."""
    import xarray as xr
    if isinstance(value, xr.Dataset):
        for name in sorted(map(str, value.variables)):
            _arrays(f"{prefix}.{name}", value[name].values, out)
        for name in sorted(value.attrs):
            a = value.attrs[name]
            if name in TIMINGS:
                continue
            if isinstance(a, (int, float, np.number, np.ndarray)) and not isinstance(a, bool):
                _arrays(f"{prefix}.attrs.{name}", a, out)
        return
    if isinstance(value, xr.DataArray):
        return _arrays(prefix, value.values, out)
    if isinstance(value, dict):
        for k in sorted(value, key=str):
            _arrays(f"{prefix}.{k}", value[k], out)
        return
    if isinstance(value, (list, tuple)) and value and not isinstance(value[0], str):
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            for i, v in enumerate(value):
                _arrays(f"{prefix}[{i}]", v, out)
            return
        out[prefix] = arr
        return
    if isinstance(value, (int, float, np.number, np.ndarray, bool, np.bool_)):
        arr = np.asarray(value)
        if arr.dtype.kind in "biufc":
            out[prefix] = arr


def _fit_arrays(prefix, r, out):
    _arrays(f"{prefix}.x", r.x, out)
    _arrays(f"{prefix}.stderr", r.stderr, out)
    _arrays(f"{prefix}.ci95", {k: list(v) for k, v in r.ci95.items()}, out)
    for name in ("sse", "chi2", "aic", "bic"):
        _arrays(f"{prefix}.{name}", r[name], out)
    out[f"{prefix}.residuals"] = np.asarray(r.residuals)


def calls(backend, tmp):
    """(name, function) of every recorded call on ``backend`` ("opencl" or "numpy")."""
    kw = dict(backend=backend)
    rng = np.random.default_rng(27)
    n = 4099
    pts = dict(theta_i=rng.uniform(0, 89, n), theta_r=rng.uniform(0, 89, n), phi=rng.uniform(0, 360, n))
    par = dict(n=rng.uniform(1.1, 4, n), k=rng.uniform(0, 6, n), sigma=rng.uniform(0.05, 1, n),
               ks=rng.uniform(0.2, 2, n), kd=rng.uniform(0, 2, n), c=rng.uniform(-1, 0, n))
    geo = dict(theta_i=np.repeat([30.0, 40, 50], 10), theta_r=np.tile(np.arange(20.0, 66, 5), 3))
    stack = pbrdf_cl.dop(geo["theta_i"], geo["theta_r"], n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3,
                         backend="numpy") + rng.normal(0, 0.003, (6, 7, 30))
    per_pixel = dict(dop=stack[:3, :4], theta_i=np.broadcast_to(geo["theta_i"] + rng.uniform(-2, 2, (3, 4, 1)),
                                                              (3, 4, 30)).copy(), theta_r=geo["theta_r"], dop_std=0.003)
    box = dict(theta_r=np.linspace(0, 85, 18), sigma=np.linspace(0.05, 1, 11), n=np.linspace(1.2, 3, 5))
    obj_grid = dict(n=np.linspace(1, 5, 17), k=np.linspace(0, 10, 17), sigma=np.linspace(0.05, 1, 9),
                    kd=np.linspace(0, 1, 5), c=np.linspace(-1, 0, 3))
    spec = Path(tmp) / f"sweep_{backend}.toml"
    spec.write_text('[axes]\ntheta_r = "0:85@24"\nsigma = "0.05:1@12"\n[fixed]\ntheta_i = 40\nn = 1.6\nk = 2.1\n'
                    'kd = 0.1\n[chunks]\ntheta_r = 8\n')

    def sweep_arrays():
        import xarray as xr
        store = Path(tmp) / f"sweep_{backend}.zarr"
        pbrdf_cl.sweep(spec, store, **kw)
        return xr.open_zarr(store).load()

    def batch_store():
        import xarray as xr
        store = Path(tmp) / f"batch_{backend}.zarr"
        pbrdf_cl.fit_batch(dict(dop=stack, **geo, dop_std=0.003), store=store, memory_budget="64 MiB", **kw)
        return xr.open_zarr(store).load()

    yield "dop", lambda: {dt: pbrdf_cl.dop(**pts, **par, dtype=dt, **kw) for dt in ("float32", "float64")}
    for q in ("brdf", "aop", "stokes", "mueller"):
        yield q, lambda q=q: {dt: pbrdf_cl.evaluate(q, **pts, **par, dtype=dt, **kw) for dt in ("float32", "float64")}
    yield "broadcast", lambda: {dt: pbrdf_cl.dop(np.linspace(0, 80, 33)[:, None], np.linspace(0, 85, 37)[None, :], 150,
                                                  n=1.6, k=2.1, sigma=0.3, kd=0.2, c=-0.3, dtype=dt, **kw)
                                for dt in ("float32", "float64")}
    yield "grid", lambda: {dt: pbrdf_cl.grid(box, dict(theta_i=40, k=2.1, kd=0.1), dtype=dt, **kw)
                           for dt in ("float32", "float64")}
    yield "reduce_grid", lambda: pbrdf_cl.reduce_grid(box, dict(theta_i=40, k=2.1, kd=0.1), over=("n",), **kw)
    yield "objective", lambda: {dt: pbrdf_cl.objective(CSV, grid=obj_grid, dtype=dt, **kw).sse
                                for dt in ("float32", "float64")}
    yield "fit", lambda: pbrdf_cl.fit(CSV, **kw)
    yield "fit_f00", lambda: pbrdf_cl.fit(CSV_F00, **kw)
    yield "fit_fixed", lambda: pbrdf_cl.fit(CSV, fixed=dict(sigma=0.45), bounds=dict(n=(1, 3)), shadowing="smith", **kw)
    yield "compare_models", lambda: pbrdf_cl.compare_models(CSV, **kw).fits
    yield "fit_batch", lambda: pbrdf_cl.fit_batch(dict(dop=stack, **geo), **kw)
    yield "fit_batch_per_pixel", lambda: pbrdf_cl.fit_batch(per_pixel, **kw)
    yield "fit_batch_store", batch_store
    yield "sobol", lambda: pbrdf_cl.sobol(dict(n=(1.2, 2.5), k=(0.01, 3.0, "log"), sigma=(0.1, 0.6), kd=(0, 0.5)),
                                          dict(theta_i=np.linspace(10, 70, 4), theta_r=np.linspace(0, 80, 5)),
                                          N=256, seed=1, **kw)
    yield "morris", lambda: pbrdf_cl.morris(dict(n=(1.2, 2.5), sigma=(0.1, 0.6)),
                                            dict(theta_i=[30.0, 50.0], theta_r=np.linspace(0, 80, 5)),
                                            dict(k=2.1, kd=0.1), N=32, seed=1, **kw)
    yield "design", lambda: pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), **kw).to_dataset()
    yield "design_box", lambda: pbrdf_cl.design(dict(n=(1.2, 2.5), k=(1.0, 3.0), sigma=0.5, kd=0.15, c=-0.3),
                                                materials=4, n_measurements=12, **kw).to_dataset()
    yield "sweep", sweep_arrays

    def a_map():
        from pbrdf_cl.analysis import maps
        return maps.make_map(("theta_r", np.linspace(0, 85, 24)), ("sigma", np.linspace(0.05, 1, 16)),
                             dict(theta_i=40, n=1.6, k=2.1, kd=0.2), derivative="sigma", **kw)
    yield "map", a_map


def _result(name, value, out):
    if hasattr(value, "x") and hasattr(value, "ci95") and hasattr(value, "residuals"):
        return _fit_arrays(name, value, out)
    if isinstance(value, dict) and value and all(hasattr(v, "ci95") for v in value.values()):
        for k, v in value.items():
            _fit_arrays(f"{name}.{k}", v, out)
        return
    if hasattr(value, "to_dataset") and not hasattr(value, "dims"):
        value = value.to_dataset()
    _arrays(name, value, out)


def run(backends, only=None):
    out, seconds = {}, {}
    warnings.simplefilter("ignore")
    with tempfile.TemporaryDirectory() as tmp:
        for backend in backends:
            for name, call in calls(backend, tmp):
                if only and name not in only:
                    continue
                t0 = time.perf_counter()
                _result(f"{backend}/{name}", call(), out)
                seconds[f"{backend}/{name}"] = time.perf_counter() - t0
                print(f"  {backend}/{name}: {seconds[f'{backend}/{name}']:.1f} s", file=sys.stderr)
    return out, seconds


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--record", metavar="NPZ", help="write the outputs here")
    g.add_argument("--check", metavar="NPZ", help="compare the outputs with this recording")
    p.add_argument("--backends", default="opencl,numpy", help="comma-separated: opencl, numpy")
    p.add_argument("--only", nargs="+", help="only these calls (names as printed)")
    args = p.parse_args(argv)
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    device = pbrdf_cl.get_default_engine().description if "opencl" in backends else "numpy"
    if args.check:
        with np.load(args.check, allow_pickle=False) as f:
            want = {k: f[k] for k in f.files}
        meta = json.loads(str(want.pop("__meta__")))
        if meta["device"] != device:
            sys.exit(f"check_behaviour: recorded on {meta['device']!r}, this run would use {device!r}: "
                     "record and check on one device (PYOPENCL_CTX)")
    got, _ = run(backends, args.only)
    if args.record:
        np.savez_compressed(args.record, __meta__=json.dumps(dict(device=device, backends=backends)), **got)
        print(f"recorded {len(got)} arrays from {device} into {args.record}")
        return 0
    prefixes = tuple(f"{b}/" for b in backends)
    want = {k: v for k, v in want.items() if k.startswith(prefixes)
            and (not args.only or k.split("/", 1)[1].split(".", 1)[0] in args.only)}
    missing, extra = sorted(set(want) - set(got)), sorted(set(got) - set(want))
    changed = []
    for k in sorted(set(want) & set(got)):
        a, b = want[k], got[k]
        same = a.shape == b.shape and (np.array_equal(a, b, equal_nan=a.dtype.kind in "fc" and b.dtype.kind in "fc")
                                       if a.dtype.kind in "fc" else np.array_equal(a, b))
        if not same:
            diff = ""
            if a.shape == b.shape and a.dtype.kind in "fc":
                diff = f", max |diff| {np.nanmax(np.abs(a.astype(float) - b.astype(float))):.3g}"
            changed.append(f"{k}: {a.shape} {a.dtype} -> {b.shape} {b.dtype}{diff}")
    for line in [f"missing: {k}" for k in missing] + [f"new: {k}" for k in extra] + [f"changed: {c}" for c in changed]:
        print(line)
    ok = not (missing or changed)
    print(f"{'unchanged' if ok else 'CHANGED'}: {len(set(want) & set(got)) - len(changed)} of {len(want)} arrays "
          f"bit for bit on {device}" + (f"; {len(extra)} new arrays not in the recording" if extra else ""))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
