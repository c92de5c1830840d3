"""Command line interface: ``pbrdf-cl devices|eval|fit|fit-image|reproduce|map|sweep|sobol|design|bench``.

Every problem a user can meet, bad input or a broken environment (no OpenCL, an unusable
device, an unwritable cache or output folder), ends in one line on stderr, ``pbrdf-cl: error:
...`` saying what is wrong and what to do, and a non-zero exit status; never a traceback.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from .compute import pointwise
from .device import drivers
from .device import engine as _engine
from .model import quantities
from . import ranges
from . import sizes
from .device import trials
from .model.reference import SHADOWING
from .errors import CommandError

PARAMS = (("theta_i", None), ("theta_r", None), ("phi", "180"), ("n", None), ("k", None),
          ("sigma", None), ("ks", "1"), ("kd", "0"), ("c", "0"))


def parse_values(option: str, text: str) -> np.ndarray:
    """``"40"``, ``"20,30,45"``, ``"20:65:5"`` or ``"0:85@256"`` -> 1-d float array (:mod:`pbrdf_cl.ranges`)."""
    return ranges.parse_values(text, option)


def _error(exc) -> int:
    """Report an input or device error the way every subcommand does; exit status 1."""
    print(f"pbrdf-cl: error: {exc}", file=sys.stderr)
    return 1


def _engine_for(args):
    """The engine of a subcommand from its ``--backend`` and ``--device``; an unusable explicit
    device, ``--backend opencl`` without a usable device, or a fallback to numpy caused by an
    unwritable PoCL cache raise :class:`CommandError`."""
    backend = getattr(args, "backend", "auto")
    device = getattr(args, "device", None)
    try:
        if backend == "numpy":
            return _engine.NumpyEngine()
        if device:
            return _engine.Engine(device)
        eng = _engine.get_default_engine(backend)
    except (ValueError, _engine.OpenCLUnavailableError) as exc:
        raise CommandError(str(exc)) from None
    if eng.is_numpy:
        problem = drivers.pocl_cache_problem()
        if problem:
            raise CommandError(f"{problem}; or pass --backend numpy")
    return eng


def _check_output(option, path, folder=False):
    """Refuse an output that cannot be written before any work is done (:class:`CommandError`)."""
    if path is None or "://" in str(path):
        return
    target = Path(path) if folder else (Path(path).parent if str(Path(path).parent) else Path("."))
    if target.exists() and not target.is_dir():
        raise CommandError(f"{option} {path}: {target} is a file, not a folder; choose another {option}")
    why = drivers.writable_dir(target)
    if why is not None:
        raise CommandError(f"{option} {path}: cannot write into {target} ({why}); choose a writable {option}")


def _suffix(path):
    """The lower-case suffix of a path or URL (``""`` for none)."""
    return Path(str(path).split("://", 1)[-1]).suffix.lower()


def figure_formats():
    """The file suffixes matplotlib writes figures as (``.png``, ``.pdf``, ``.svg``, ...)."""
    from matplotlib.backend_bases import FigureCanvasBase
    return tuple(sorted("." + f for f in FigureCanvasBase.get_supported_filetypes()))


def check_suffix(option, path, suffixes, what, allow_none=False):
    """Refuse before any work (:class:`CommandError`) an output whose suffix is not one of ``suffixes``
    (the format it will be written in): ``--out params.npz`` for a Zarr store, ``--out m.txt`` for
    a figure.  ``what`` says what is written there.  ``allow_none``: a path without a suffix is
    written as that format (a store's folder, a JSON file); where a writer would append a suffix of
    its own (matplotlib, numpy's savez) it is refused too, so that the file written is the one named."""
    if path is None:
        return
    suffix = _suffix(path)
    if suffix in suffixes or (allow_none and not suffix):
        return
    name = Path(str(path).split("://", 1)[-1]).name
    stem = name[: len(name) - len(suffix)] if suffix else name
    names = ", ".join(suffixes[:3]) + (", ..." if len(suffixes) > 3 else "") + (" or none" if allow_none else "")
    raise CommandError(f"{option} {path}: {what}, named with the suffix {names}, not "
                   f"{repr(suffix) if suffix else 'without one'}; write e.g. {option} {stem}{suffixes[0]}")


def check_figure(option, path):
    """Refuse before any work a figure path matplotlib cannot write as its suffix says."""
    if path is not None:
        formats = figure_formats()
        order = [".png", ".pdf", ".svg"] + [f for f in formats if f not in (".png", ".pdf", ".svg")]
        check_suffix(option, path, tuple(order), "a figure is written here in the format its suffix names")


def check_json(option, path, prog="pbrdf-cl"):
    """For the scripts: refuse a JSON output with another suffix, or that cannot be written, before
    their work, in one line on stderr (``SystemExit``)."""
    try:
        check_suffix(option, path, (".json",), "JSON is written here", allow_none=True)
        _check_output(option, path)
    except CommandError as exc:
        raise SystemExit(f"{prog}: error: {exc}") from None


def check_store(option, path):
    """Refuse before any work a Zarr store path with another format's suffix (``params.npz``)."""
    check_suffix(option, path, (".zarr",), "a Zarr store (a folder that xarray.open_zarr reads) is written here",
                 allow_none=True)


def _device_type(bits: int) -> str:
    dt = _engine.cl.device_type
    names = [name for name in ("CPU", "GPU", "ACCELERATOR") if bits & getattr(dt, name)]
    return "/".join(names) or "OTHER"


def _verdict_lines(verdicts):
    """What ``pbrdf-cl devices`` says of one device's stored trial verdicts."""
    if not verdicts:
        return []
    bad = [v for v in verdicts if not v.usable]
    lines = [f"trials: {len(verdicts) - len(bad)} of {len(verdicts)} programs built and ran in the trial process"]
    for v in bad:
        lines.append(f"  UNUSABLE {v.program}: {v.reason} ({v.when.replace('T', ' ')})")
    return lines


def cmd_devices(args) -> int:
    if args.forget:
        _engine.clear_probe_cache(disk=True)
        trials.forget(disk=True)
    try:
        found = _engine.list_devices()
    except _engine.OpenCLUnavailableError as exc:
        return _error(exc)
    default, why_none = None, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", _engine.DeviceWarning)  # the list says it all
        try:
            default = _engine.select_device(args.device)
        except (_engine.OpenCLUnavailableError, ValueError) as exc:
            why_none = str(exc)
    rows = []
    dev_of = {f"{ip}:{idev}": dev for ip, idev, _, dev in found}
    for ip, idev, plat, dev in found:
        result = _engine.probe(dev)
        rows.append(dict(id=f"{ip}:{idev}", platform=plat.name.strip(), device=dev.name.strip(),
                         type=_device_type(dev.type), fp64=_engine.has_fp64(dev),
                         compute_units=dev.max_compute_units, version=dev.version.strip(),
                         driver=dev.driver_version.strip(), usable=result.usable, probe=result.reason,
                         probe_seconds=round(result.seconds, 4), probe_cached=result.cached,
                         simulator=_engine._is_simulator(plat),
                         default=default is not None and dev.int_ptr == default.int_ptr,
                         vector_width=_engine.vector_widths(dev)[0], narrow_vectors=_engine.narrow_reason(dev),
                         trials=[dict(program=v.program, usable=v.usable, reason=v.reason,
                                      seconds=round(v.seconds, 3), when=v.when)
                                 for v in trials.stored_verdicts(dev)]))
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        mark = "*" if r["default"] else " "
        print(f"{mark} {r['id']:5s} {r['platform']} / {r['device']}  [{r['type']}, "
              f"{r['compute_units']} CUs, fp64={'yes' if r['fp64'] else 'no'}, {r['version']}, driver {r['driver']}]")
        state = "usable" if r["usable"] else "UNUSABLE"
        extra = "; a simulator, never the default" if r["simulator"] else ""
        when = "probe cached" if r["probe_cached"] else f"probe {r['probe_seconds']:.2f} s"
        print(f"        {state}: {r['probe']} ({when}{extra})")
        if r["narrow_vectors"]:
            print(f"        256-bit vectors in every vector program: {r['narrow_vectors']}")
        for line in _verdict_lines(trials.stored_verdicts(dev_of[r['id']])):
            print(f"        {line}")
    if _engine.DRIVER_MESSAGES:
        print("the drivers printed, while listed and probed:")
        for line in _engine.DRIVER_MESSAGES[:20]:
            print(f"        {line}")
    if default is not None:
        print("* = the default device (choose another with --device P:D or PYOPENCL_CTX=P:D)")
    elif args.device or os.environ.get("PYOPENCL_CTX"):
        print(f"the chosen device cannot be used: {why_none}")
    else:
        problem = drivers.pocl_cache_problem()
        if problem:
            print(f"PoCL's devices are hidden: {problem}")
        print("no usable OpenCL device: every command computes on the numpy backend (the float64 reference, "
              f"slower) until one is installed; remedies: {drivers.REMEDIES}")
    return 0


def cmd_eval(args) -> int:
    values = {}
    for name, default in PARAMS:
        text = getattr(args, name)
        if text is None:
            text = default
        if text is None and not (name == "sigma" and args.model == "specular" and args.quantity == "dop"):
            print(f"pbrdf-cl: error: --{name.replace('_', '-')} is required", file=sys.stderr)
            return 2
        values[name] = parse_values(f"--{name.replace('_', '-')}", text) if text is not None else None
    names = [n for n, _ in PARAMS if values[n] is not None]
    shape = tuple(values[n].size for n in names)
    total = int(np.prod(shape, dtype=np.int64))
    width = quantities.get(args.quantity, "points", "--quantity").width
    sizes.check_memory(total * (16 * len(names) + 16 * width + (400 if args.json else 0)),
                       f"pbrdf-cl eval of {' x '.join(map(str, shape))} = {total} rows",
                       "give fewer values per option; for large Cartesian products use pbrdf-cl map or "
                       "pbrdf-cl sweep (a Zarr store)")
    # the rows of the Cartesian product (the last option varies fastest), as columns: no Python list
    idx = np.unravel_index(np.arange(total), shape) if total else [np.zeros(0, int)] * len(names)
    cols = {n: values[n][i] for n, i in zip(names, idx)}
    rows = range(total)
    kw = dict(shadowing=args.shadowing, dtype=args.dtype, model=args.model, engine=_engine_for(args))
    pos = {n: cols[n] for n in ("theta_i", "theta_r", "phi")}
    par = {n: cols[n] for n in ("n", "k", "sigma", "ks", "kd", "c") if n in cols}
    try:
        q = quantities.get(args.quantity, "points", "--quantity")
        result = pointwise.evaluate(q.name, pos["theta_i"], pos["theta_r"], pos["phi"], **par, **kw)
    except (ValueError, FloatingPointError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    out_name = q.name
    if args.json:
        records = [{**{n: float(cols[n][i]) for n in names},
                    out_name: result[i].tolist() if q.trailing else float(result[i])}
                   for i in range(len(rows))]
        print(json.dumps(dict(quantity=out_name, shadowing=args.shadowing, dtype=args.dtype,
                              backend="numpy" if kw["engine"].is_numpy else "opencl",
                              device=kw["engine"].description, model=args.model, rows=records), indent=2))
        return 0
    header = [n for n in names]
    what = {"mueller": "mueller (row-major, 16 values)", "stokes": "stokes (S0 S1 S2 S3)"}.get(out_name, out_name)
    print("  ".join(f"{h:>8s}" for h in header) + f"  {what}" + (f" ({q.units})" if q.units != "1" else ""))
    for i in range(len(rows)):
        lead = "  ".join(f"{cols[n][i]:8.4g}" for n in names)
        if q.trailing:
            val = " ".join(f"{v: .6e}" for v in result[i].ravel())
        else:
            val = f"{result[i]:.8g}"
        print(f"{lead}  {val}")
    return 0


def _fit_json(r):
    corr = np.asarray(r.corr, dtype=float)
    return dict(model=r.model, shadowing=r.shadowing, success=bool(r.success), status=r.status, message=r.message,
                fits_data=bool(r.fits_data), x=r.x, kd_ratio=r.get("kd_ratio"),
                kd_fitted_as=("kd/ks" if "ks" in r.free and "kd" in r.free else "kd") if "kd" in r.free else None,
                free=r.free, stderr=r.stderr,
                ci95={k: list(v) for k, v in r.ci95.items()}, sse=r.sse, rmse=r.rmse, chi2=r.chi2,
                reduced_chi2=r.reduced_chi2 if r.sigma_known else None, p_value=r.p_value, r2=r.r2, aic=r.aic,
                bic=r.bic, dof=r.dof, residuals=r.residuals.tolist(),
                corr=np.where(np.isfinite(corr), corr, None).tolist(), condition_number=r.condition_number,
                nfev=r.nfev, seconds=r.seconds, ambiguous=r.ambiguous, notes=r.notes)


def _fit_brief(r):
    """One line per fitted parameter and a first line with the model, for --quiet."""
    from .io.measurements import PHI_DEFAULT_NOTE
    lines = [f"{r.model}: SSE {r.sse:.4g}" + ("" if r.fits_data else " (the model does not describe these data)")]
    ratio = "ks" in r.free and "kd" in r.free  # intensities: the interval under "kd" is that of kd/ks
    for name in r.free:
        lo, hi = r.ci95[name]
        if name == "kd" and ratio:
            lines.append(f"  kd/ks = {r.kd_ratio:.5g}  [{lo:.4g}, {hi:.4g}]  (kd = {r.x['kd']:.5g})")
        else:
            lines.append(f"  {name} = {r.x[name]:.5g}  [{lo:.4g}, {hi:.4g}]")
    if PHI_DEFAULT_NOTE in r.notes:
        lines.append(f"  note: {PHI_DEFAULT_NOTE}")
    return "\n".join(lines)


def _fit_assignments(args):
    """(fixed, bounds) from --fix and --bounds (_fit_settings), checked against the parameters."""
    from .fitting.inversion import DEFAULT_BOUNDS
    return (ranges.parse_assignments(args.fix, tuple(DEFAULT_BOUNDS), "value", "--fix", check=True),
            ranges.parse_assignments(args.bounds, tuple(DEFAULT_BOUNDS), "bounds", "--bounds"))


def cmd_fit(args) -> int:
    from .fitting import inversion as _fit
    from .io.measurements import read_csv
    fixed, bounds = _fit_assignments(args)
    check_suffix("--json", args.json, (".json",), "JSON is written here", allow_none=True)
    check_figure("--plot", args.plot)
    _check_output("--json", args.json)
    _check_output("--plot", args.plot)
    try:
        meas = read_csv(args.data)
        engine = _engine_for(args)
        kw = dict(shadowing=args.shadowing, bounds=bounds, fixed=fixed, engine=engine, progress=not args.quiet)
        if args.compare:
            both = _fit.compare_models(meas, **kw)
            other = "specular" if args.model == "six-param" else "six-param"
            fits, best = {args.model: both[args.model], other: both[other]}, both["preferred"]
        else:
            if args.model == "specular":
                kw["fixed"] = {k: v for k, v in fixed.items() if k in ("n", "k")}
                kw["bounds"] = {k: v for k, v in bounds.items() if k in ("n", "k")}
            fits, best = {args.model: _fit.fit(meas, args.model, **kw)}, None
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    if not args.quiet:
        print(f"data: {meas.source} ({len(meas)} points)")
    for r in fits.values():
        print(_fit_brief(r) if args.quiet else r.summary())
        if not args.quiet:
            print()
    if best is not None:
        print(f"preferred by BIC: {best}" if args.quiet else both.summary())
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(data=meas.source, n_points=len(meas), fits={k: _fit_json(v) for k, v in fits.items()},
                           preferred=best), fh, indent=2)
        print(f"wrote {args.json}")
    if args.plot:
        from .plots.fit import plot_fit
        plot_fit(meas, fits, args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_sweep(args) -> int:
    from .explore.sweeps import load_spec, read_done, sweep
    check_store("--out", args.out)
    _check_output("--out", str(Path(args.out).parent), folder=True)
    try:
        spec = load_spec(args.spec)
        engine = _engine_for(args) if not (args.workers or args.scheduler) else None
        res = sweep(spec, args.out, engine=engine, device=args.device, backend=args.backend, workers=args.workers,
                    scheduler=args.scheduler, progress=not args.quiet, allow_large=args.allow_large)
    except KeyboardInterrupt:
        try:
            done = int(read_done(spec, args.out).sum())
            where = f"{done} of {spec.n_chunks} chunks are in {args.out}"
        except Exception:  # noqa: BLE001 - the store may not exist yet
            where = "nothing was written"
        print(f"pbrdf-cl: interrupted; {where}; run the same command again to resume", file=sys.stderr)
        return 130
    except (OSError, ValueError, RuntimeError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    print(res.summary())
    return 0


def cmd_fit_image(args) -> int:
    import time
    from .fitting import batch_store
    fixed, bounds = _fit_assignments(args)
    check_store("--out", args.out)
    check_figure("--png", args.png)
    _check_output("--out", str(Path(args.out).parent), folder=True)
    _check_output("--png", args.png)
    cluster = bool(args.workers or args.scheduler)
    t0 = time.perf_counter()
    try:
        engine = _engine_for(args) if not cluster else None
        ds = batch_store.fit_batch_to_store(
            args.stack, args.out, model=args.model, bounds=bounds or None, fixed=fixed or None,
            shadowing=args.shadowing, memory_budget=args.memory_budget, progress=not args.no_progress, engine=engine, backend=args.backend,
            device=args.device, workers=args.workers, scheduler=args.scheduler, allow_large=args.allow_large)
        counts = batch_store.status_counts(ds)
        if args.png:
            from .plots.images import plot_batch_maps
            plot_batch_maps(ds, args.png)
    except KeyboardInterrupt:
        try:
            done, total = batch_store.read_progress(args.out)
            where = f"{done} of {total} blocks are in {args.out}"
        except Exception:  # noqa: BLE001 - the store may not exist yet
            where = "nothing was written"
        print(f"pbrdf-cl: interrupted; {where}; run the same command again to resume", file=sys.stderr)
        return 130
    except (OSError, ValueError, RuntimeError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    seconds = time.perf_counter() - t0
    px, fit_s = ds.attrs["pixels_computed"], ds.attrs["seconds"]
    total = int(np.prod(ds["status"].shape, dtype=np.int64))
    rate = f", {px / fit_s:.4g} pixels/s" if px and fit_s > 0 else ""
    print(f"fit-image: {px} of {total} pixels fitted in {fit_s:.3g} s{rate} ({total - px} already in the store; "
          f"{seconds:.3g} s in all)")
    print("status: " + ", ".join(f"{n} {c}" for n, c in counts.items()))
    if "goodness" in ds.attrs:
        print(ds.attrs["goodness"])
    if "goodness_warning" in ds.attrs:
        print(ds.attrs["goodness_warning"])
    for note in str(ds.attrs.get("data_notes", "")).splitlines():
        print(f"note: {note}")
    print(f"store: {ds.attrs['store']}" + (f"; maps: {args.png}" if args.png else ""))
    return 0


def _check_result_outputs(args):
    """Refuse before any work (:class:`CommandError`) a ``--out`` that is neither .nc nor .zarr, and an
    ``--out`` or ``--png`` that cannot be written (the sobol and design commands)."""
    if args.out and Path(args.out).suffix.lower() not in (".nc", ".zarr"):
        raise CommandError(f"--out {args.out}: write the result as .nc (netCDF) or .zarr (a Zarr store)")
    check_figure("--png", args.png)
    _check_output("--out", args.out)
    _check_output("--png", args.png)


def cmd_sobol(args) -> int:
    """`pbrdf-cl sobol SPEC.toml`: a Sobol' (or Morris) sensitivity map, its file, figure and summary."""
    from .explore import sensitivity
    _check_result_outputs(args)
    try:
        settings = sensitivity.load_sobol_spec(args.spec)
        if args.png:  # refused before the work, not after it
            from .plots.sensitivity import check_axes
            check_axes(sensitivity.check_geometry(settings["geometry"])[0], "--png")
        with warnings.catch_warnings():  # the summary below prints the result's notes
            warnings.simplefilter("ignore", sensitivity.SensitivityWarning)
            ds = sensitivity.sobol(**settings, progress=not args.no_progress, engine=_engine_for(args))
        if args.out:
            sensitivity.write_result(ds, args.out)
        if args.png:
            from .plots.sensitivity import plot_sensitivity
            plot_sensitivity(ds, args.png)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    print(sensitivity.summary(ds))
    wrote = [p for p in (args.out, args.png) if p]
    if wrote:
        print(f"wrote {' and '.join(wrote)}")
    return 0


def cmd_bench(args) -> int:
    from . import bench
    return bench.main(args.rest)


def cmd_reproduce(args) -> int:
    from .explore import paper
    try:
        paper.check_resolution(args.resolution)
    except ValueError as exc:
        return _error(exc)
    _check_output("--out", args.out, folder=True)
    try:
        engine = _engine_for(args)
        files = paper.reproduce(args.out, resolution=args.resolution, engine=engine,
                                log=(lambda *a: None) if args.quiet else print)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    print(f"wrote {len(files)} files to {args.out}/ (list: {args.out}/summary.md):")
    for name in files:
        print(f"  {args.out}/{name}")
    return 0


def cmd_map(args) -> int:
    from .explore import maps
    from .plots.maps import plot_map
    try:
        x = maps.parse_axis("--x", args.x)
        y = maps.parse_axis("--y", args.y)
        fixed = maps.parse_fixed("--fix", args.fix)
        check_figure("--out", args.out)
        check_suffix("--npz", args.npz, (".npz",), "numpy's archive of the arrays is written here")
        _check_output("--out", args.out)
        _check_output("--npz", args.npz)
        engine = _engine_for(args)
        ds = maps.make_map(x, y, fixed, quantity=args.quantity, derivative=args.derivative, dtype=args.dtype,
                           shadowing=args.shadowing, engine=engine)
        plot_map(ds, args.out)
        if args.npz:
            maps.save_npz(ds, args.npz)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    for note in ds.attrs.get("notes", []):
        print(f"pbrdf-cl: note: {note}", file=sys.stderr)
    v = ds[ds.attrs["quantity"]].values
    print(f"{ds.attrs['quantity']} over {x[0]} ({x[1].size} points) x {y[0]} ({y[1].size} points): "
          f"min {np.nanmin(v):.6g}, max {np.nanmax(v):.6g}")
    print(f"wrote {args.out}" + (f" and {args.npz}" if args.npz else ""))
    return 0


_SHADOWING_HELP = "shadowing function: paper (the paper's eq. 7-9), smith (Smith's), or none"


def _items(values):
    """NAME=VALUE items given space- or comma-separated (``n=1.6,k=2.139 sigma=0.5``)."""
    return [t for v in values or [] for t in v.split(",") if t.strip()]


def cmd_design(args) -> int:
    from .explore.designs import GEOMETRY, design, plot_design
    from .compute.dense import PARAMETERS
    from .explore.sensitivity import write_result
    from .fitting.inversion import DEFAULT_BOUNDS
    params = ranges.parse_assignments(_items(args.params), PARAMETERS, "value", "--params", check=True)
    box = ranges.parse_assignments(_items(args.box), PARAMETERS, "bounds", "--box")
    both = sorted(set(params) & set(box))
    if both:
        return _error(f"--box {both[0]}: also given in --params; give it once")
    params.update(box)
    cand = ranges.parse_assignments(args.candidates, GEOMETRY, "values", "--candidates") if args.candidates else None
    ref = ranges.parse_assignments(args.reference, GEOMETRY, "values", "--reference") if args.reference else None
    fixed = ranges.parse_assignments(args.fix, tuple(DEFAULT_BOUNDS), "value", "--fix", check=True)
    bounds = ranges.parse_assignments(args.bounds, tuple(DEFAULT_BOUNDS), "bounds", "--bounds")
    target = tuple(t.strip() for t in args.target.split(",") if t.strip())
    _check_result_outputs(args)
    try:
        res = design(params, cand, noise=args.noise, n_measurements=args.n, target=target, intensity=args.intensity,
                     fixed=fixed, criterion=args.criterion, reference=ref, intensity_noise=args.intensity_noise,
                     bounds=bounds, materials=args.materials, repeats=args.repeats, seed=args.seed,
                     shadowing=args.shadowing, engine=_engine_for(args))
    except (ValueError, _engine.OpenCLUnavailableError) as exc:
        return _error(exc)
    print(res.summary())
    try:
        if args.out:
            write_result(res.to_dataset(), args.out)
        if args.png:
            plot_design(res, args.png)
    except (OSError, ValueError) as exc:  # e.g. a .zarr path that is something else
        return _error(exc)
    wrote = [p for p in (args.out, args.png) if p]
    if wrote:
        print(f"wrote {' and '.join(wrote)}")
    return 0


def _quantity_choices(path):
    """The quantity names for ``path``, canonical and aliases (the registry, pbrdf_cl.quantities)."""
    names = quantities.names(path)
    return names + tuple(a for a, c in quantities.ALIASES.items() if c in names)


def _device_options(parser, where=""):
    parser.add_argument("--device", help=f"OpenCL device{where}: P:D as `pbrdf-cl devices` lists them, or a name "
                        "substring (default: PYOPENCL_CTX, else the first usable device)")
    parser.add_argument("--backend", choices=_engine.BACKENDS, default="auto",
                        help="auto (default): the OpenCL device, or the numpy reference when no device is usable; "
                        "opencl: the device or an error; numpy: the float64 reference")


class _HelpFormatter(argparse.HelpFormatter):
    """Shows each option's default after its help (not for None/False defaults, nor where the help
    says it already)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (action.option_strings and action.default not in (None, False, argparse.SUPPRESS)
                and "default" not in text):
            text += " (default: %(default)s)"
        return text


class _Parser(argparse.ArgumentParser):
    """argparse with a suggestion for a misspelt option: ``unrecognized arguments: --sigmaa; did you
    mean --sigma?``."""

    def __init__(self, *args, **kw):
        kw.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kw)

    def error(self, message):
        import difflib
        if "unrecognized arguments" in message:
            known = sorted({o for parser in _all_parsers(self) for a in parser._actions for o in a.option_strings})
            for token in message.split(":", 1)[1].split():
                if token.startswith("--"):
                    close = difflib.get_close_matches(token.split("=")[0], known, n=1, cutoff=0.6)
                    if close:
                        message += f"; did you mean {close[0]}?"
                        break
        super().error(message)


def _all_parsers(parser):
    """``parser`` and the parser of the sub-command given on this command line, if any."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = getattr(parser, "_chosen", None)
            found += [action.choices[chosen]] if chosen in action.choices else list(action.choices.values())
    return found


#: Options that take a list of NAME=VALUE items: a token without "=" after them is not theirs.
_ITEM_OPTIONS = ("--fix", "--bounds")


def _positionals_first(argv):
    """Move file names that follow a NAME=VALUE list option (``fit --fix sigma=0.45 data.csv``) in front
    of it, so that the list does not swallow the positional argument."""
    out, moved, in_items = [], [], False
    for token in argv:
        if token in _ITEM_OPTIONS:
            in_items = True
        elif token.startswith("-"):
            in_items = False
        elif in_items and "=" not in token and (os.path.exists(token) or "/" in token or "." in token.lstrip(".")):
            moved.append(token)  # a file name, not a malformed item (those get their own message)
            continue
        out.append(token)
    return out[:1] + moved + out[1:] if moved else out


def _eval_parser(sub):
    """The `pbrdf-cl eval` sub-command."""
    e = sub.add_parser("eval", help="evaluate DOP, F00, AoP, the Stokes vector or the Mueller matrix",
                       description=f"Each value option takes {ranges.GRAMMAR}; see the README, Ranges "
                       "and name=value. The output has one row per combination.")
    for name, default in PARAMS:
        unit = " (degrees)" if name in ("theta_i", "theta_r", "phi") else ""
        e.add_argument(f"--{name.replace('_', '-')}", dest=name, metavar="V",
                       help=f"{name}{unit}" + (f", default {default}" if default else ", required"))
    e.add_argument("--quantity", choices=_quantity_choices("points"), default="dop", type=str.lower,
                   help="AoP in degrees (NaN where undefined), F00 and Stokes in 1/sr")
    e.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=_SHADOWING_HELP)
    e.add_argument("--model", choices=pointwise.MODELS, default="six-param",
                   help="six-param, or specular: the ref. [7] model (kd = 0; the DOP then needs no --sigma)")
    e.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision")
    _device_options(e)
    e.add_argument("--json", action="store_true", help="JSON output")
    e.set_defaults(func=cmd_eval)


def _sweep_parser(sub):
    """The `pbrdf-cl sweep` sub-command."""
    s = sub.add_parser("sweep", help="a sweep of any size into a Zarr store (resumable; dask cluster)",
                       description="Evaluate the sweep described by a TOML spec (axes, fixed values, quantity, "
                       "dtype, chunks, optional reductions; see examples/sweep_sigma_theta.toml) chunk by chunk "
                       "into a Zarr store. Run the same command again after an interruption: only the missing "
                       "chunks are computed.")
    s.add_argument("spec", help="TOML spec")
    s.add_argument("--out", required=True, metavar="STORE", help="Zarr store to create or resume (e.g. result.zarr)")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="run on a local dask cluster of N processes")
    where.add_argument("--scheduler", metavar="ADDR", help="run on a dask.distributed cluster (tcp://host:8786)")
    _device_options(s, " here or on every worker")
    s.add_argument("--quiet", action="store_true", help="no progress bar; one summary line at the end")
    s.add_argument("--allow-large", action="store_true",
                   help="start even when the store (uncompressed) would not fit on the free disk")
    s.set_defaults(func=cmd_sweep)


def _model_option(f):
    """--model of `fit` and `fit-image`."""
    f.add_argument("--model", choices=("six-param", "specular"), default="six-param",
                   help="the model to fit (specular: ref. [7], n and k only)")


def _fit_settings(f):
    """--fix, --bounds and --shadowing of `fit` and `fit-image`."""
    f.add_argument("--fix", nargs="*", metavar="NAME=VALUE", help="hold parameters fixed, e.g. sigma=0.45")
    f.add_argument("--bounds", nargs="*", metavar="NAME=LO:HI", help="search bounds, e.g. n=1:3 k=0:5")
    f.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=_SHADOWING_HELP)


def _fit_parser(sub):
    """The `pbrdf-cl fit` sub-command."""
    f = sub.add_parser("fit", help="invert n, k, sigma, kd/ks, c from measured DOP (CSV)",
                       description="Fit the six-parameter model (or, with --model specular, the ref. [7] "
                       "specular model; --compare: both) to a CSV of measurements (columns theta_i, theta_r, "
                       "dop[, phi, dop_std, f00|s0, f00_std]).")
    f.add_argument("data", help="measurement CSV")
    _model_option(f)
    f.add_argument("--compare", action="store_true",
                   help="fit both models and compare them by AIC/BIC (--model's is listed first)")
    _fit_settings(f)
    _device_options(f, " for the grid stage")
    f.add_argument("--json", metavar="OUT", help="write both fits as JSON")
    f.add_argument("--plot", metavar="PNG", help="plot data, both models and residuals")
    f.add_argument("--quiet", action="store_true",
                   help="no progress bar; only each fitted value with its 95%% interval")
    f.set_defaults(func=cmd_fit)


def _fit_image_parser(sub):
    """The `pbrdf-cl fit-image` sub-command."""
    from .fitting.batch import DEFAULT_BUDGET
    f = sub.add_parser("fit-image", help="fit every pixel of a DOP image stack into a Zarr store (resumable; dask)",
                       description="Fit the model to every pixel of a polarization image stack (.npz, .nc or "
                       ".zarr with dop (y, x, m), theta_i, theta_r[, phi, dop_std, f00|s0, f00_std, mask]; angles "
                       "shared (m) or per pixel) block by block into a Zarr store. Run the same command again "
                       "after an interruption: only the missing blocks are fitted.")
    f.add_argument("stack", help="image stack: .npz, .nc or .zarr")
    f.add_argument("--out", required=True, metavar="STORE", help="Zarr store to create or resume (e.g. params.zarr)")
    _model_option(f)
    _fit_settings(f)
    f.add_argument("--memory-budget", default=DEFAULT_BUDGET, metavar="SIZE",
                   help="memory of one block of pixels in flight (host and device), e.g. 256MiB")
    where = f.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help="fit on a local dask cluster of N processes")
    where.add_argument("--scheduler", metavar="ADDR", help="fit on a dask.distributed cluster (tcp://host:8786)")
    _device_options(f, " here or on every worker")
    f.add_argument("--png", metavar="PNG", help="also draw the parameter maps, their 95%% interval widths and the "
                   "fit status")
    f.add_argument("--no-progress", action="store_true", help="no progress bar")
    f.add_argument("--allow-large", action="store_true",
                   help="start even when the store (uncompressed) would not fit on the free disk")
    f.set_defaults(func=cmd_fit_image)


def _reproduce_parser(sub):
    """The `pbrdf-cl reproduce` sub-command."""
    r = sub.add_parser("reproduce", help="reproduce the paper's figures and Table 1, plus roughness maps",
                       description="Writes Fig. 2 (aluminum, black paint: synthetic data, both models fitted), "
                       "Table 1, Fig. 4, Fig. 5, two dense DOP maps, a Sobol' map of the DOP and a measurement design "
                       "for the steel (.png, .nc), the arrays of each figure (.npz) and summary.md into one folder.")
    r.add_argument("--out", default="paper-figures", help="output folder (default: paper-figures)")
    r.add_argument("--resolution", type=int, default=256, help="points per map axis (default 256)")
    _device_options(r)
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.set_defaults(func=cmd_reproduce)


def _map_parser(sub):
    """The `pbrdf-cl map` sub-command."""
    m = sub.add_parser("map", help="a dense map of DOP, F00 or AoP over any two axes (PNG + optional .npz)",
                       description=f"Axes: NAME=VALUES, VALUES being {ranges.GRAMMAR}; see the README, "
                       "Ranges and name=value. Angles in degrees. Inputs not on an axis are fixed with --fix (phi, ks, kd, "
                       "c default to 180, 1, 0, 0). Example: pbrdf-cl map --x theta_r=0:85@256 --y sigma=0.05:1@256 "
                       "--fix theta_i=40 n=1.6 k=2.139 ks=0.9 kd=0.15 c=-0.3 --derivative sigma --out map.png")
    m.add_argument("--x", required=True, metavar="NAME=VALUES", help="horizontal axis, e.g. theta_r=0:85@256")
    m.add_argument("--y", required=True, metavar="NAME=VALUES", help="vertical axis, e.g. sigma=0.05:1:0.05")
    m.add_argument("--fix", nargs="*", metavar="NAME=VALUE", help="the other inputs, e.g. theta_i=40 n=1.6")
    m.add_argument("--quantity", choices=_quantity_choices("map"), default="dop", type=str.lower,
                   help="what to map: dop, brdf (alias f00; 1/sr, log colours when it spans decades), aop (deg)")
    m.add_argument("--derivative", metavar="NAME",
                   help="add a panel with d(quantity)/d(NAME): finite differences of step 1e-4 at every node, "
                   "one-sided at a bound of the domain, on float64 device grids")
    m.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision")
    m.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=_SHADOWING_HELP)
    _device_options(m)
    m.add_argument("--out", default="map.png", help="PNG to write (default map.png)")
    m.add_argument("--npz", metavar="NPZ", help="also save the arrays (coordinates, values, derivative)")
    m.set_defaults(func=cmd_map)


def _sobol_parser(sub):
    """The `pbrdf-cl sobol` sub-command."""
    s = sub.add_parser("sobol", help="Sobol' indices (or Morris screening) of DOP/F00 over geometry axes (TOML spec)",
                       description="Which parameters control the DOP (or F00), and where: Sobol' first-order and "
                       "total indices (or Morris mu*, sigma) at every geometry of a grid, for the parameter box of a "
                       "TOML spec (quantity, method, N, seed, dtype, [ranges], [geometry], [fixed]; see "
                       "examples/sobol.toml and docs/sensitivity.md). Prints the model runs, the seconds and which "
                       "parameter dominates where.")
    s.add_argument("spec", help="TOML spec")
    s.add_argument("--out", metavar="FILE", help="write the result: .nc (netCDF) or .zarr (a Zarr store)")
    s.add_argument("--png", metavar="PNG", help="draw the maps (one or two geometry axes)")
    _device_options(s)
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_sobol)


def _design_parser(sub):
    """The `pbrdf-cl design` sub-command."""
    from .fitting.inversion import F00_REL_STD
    d = sub.add_parser("design", help="choose measurement geometries from the Fisher information (predicted "
                       "95%% interval widths)",
                       description="For a hypothesised material (--params) or a box of materials (--box), "
                       "choose the --n geometries out of the candidates that make the target parameters' "
                       "predicted 95% intervals narrowest, and compare with the paper's geometry (theta_i "
                       "30/40/50 x theta_r 20..65 step 5). Example: pbrdf-cl design --params n=1.6,k=2.139,"
                       "sigma=0.5,kd=0.15,c=-0.3 --noise 0.005 --n 30 --out design.nc --png design.png")
    d.add_argument("--params", nargs="+", metavar="NAME=VALUE", required=True,
                   help="the material: n, k, sigma (and kd, c, ks; defaults 0, 0, 1), e.g. n=1.6,k=2.139,sigma=0.5")
    d.add_argument("--box", nargs="+", metavar="NAME=LO:HI", help="parameters ranging over a box (instead of "
                   "a value in --params), e.g. n=1.2:2.5; the criterion is averaged over --materials draws")
    d.add_argument("--candidates", nargs="+", action="extend", metavar="NAME=VALUES",
                   help="candidate grid axes (degrees), e.g. theta_i=10:80:5 theta_r=0:85:5 (default; phi 180)")
    d.add_argument("--reference", nargs="+", action="extend", metavar="NAME=VALUES",
                   help="the grid to compare with (default the paper's: theta_i=30,40,50 theta_r=20:65:5)")
    d.add_argument("--noise", type=float, default=0.005, help="standard deviation of each DOP measurement")
    d.add_argument("--n", type=int, default=30, help="how many measurements to choose")
    d.add_argument("--target", default="n,k", help="the parameters to determine best, comma-separated")
    d.add_argument("--intensity", action="store_true", help="each geometry also measures F00 (ks free, kd as kd/ks)")
    d.add_argument("--intensity-noise", type=float, default=F00_REL_STD, help="relative standard deviation of F00")
    d.add_argument("--criterion", choices=("A", "D"), default="A",
                   help="A: sum of the targets' variances / bound range^2; D: log det of their covariance")
    d.add_argument("--materials", type=int, default=16, help="materials drawn from --box")
    d.add_argument("--seed", type=int, default=0, help="seed of the materials drawn from --box")
    d.add_argument("--repeats", action="store_true", help="allow a geometry to be chosen more than once")
    _fit_settings(d)
    _device_options(d)
    d.add_argument("--out", metavar="FILE", help="write the design: .nc (netCDF) or .zarr (a Zarr store)")
    d.add_argument("--png", metavar="PNG", help="draw the information map and the predicted widths")
    d.set_defaults(func=cmd_design)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    p = _Parser(prog="pbrdf-cl", description="The six-parameter pBRDF model on OpenCL. "
                "Angles in degrees; phi = 180 is the in-plane geometry. `pbrdf-cl COMMAND --help` for each.")
    p.add_argument("--version", action="version", version=f"pbrdf-cl {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    d = sub.add_parser("devices", help="list OpenCL platforms and devices, their probe results and the verdicts "
                       "of their programs' trial builds")
    d.add_argument("--device", help="mark this device as the one chosen (P:D or a name substring)")
    d.add_argument("--json", action="store_true", help="JSON output")
    d.add_argument("--forget", action="store_true", help="forget the stored probe results and trial verdicts "
                   "first (each is made again when next needed)")
    d.set_defaults(func=cmd_devices)
    _eval_parser(sub)
    _sweep_parser(sub)
    _fit_parser(sub)
    _fit_image_parser(sub)
    _reproduce_parser(sub)
    _map_parser(sub)
    _sobol_parser(sub)
    _design_parser(sub)
    b = sub.add_parser("bench", help="benchmark every evaluation path (options: pbrdf-cl bench --help)",
                       add_help=False)
    b.add_argument("rest", nargs=argparse.REMAINDER)
    b.set_defaults(func=cmd_bench)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings as one line each, ``pbrdf-cl: warning: ...``."""
    print(f"pbrdf-cl: warning: {message}", file=sys.stderr if file is None else file)


def _environment_error(exc):
    """The one-line report of an environment problem met while working."""
    cl = _engine.cl
    if isinstance(exc, _engine.OpenCLUnavailableError):
        return str(exc)
    if cl is not None and isinstance(exc, cl.Error):
        return (f"OpenCL: {_engine.first_error_line(exc)}; try another device (`pbrdf-cl devices`) or "
                "--backend numpy")
    if isinstance(exc, sizes.TooLargeError):
        return str(exc)  # the estimate, found before any work
    if isinstance(exc, MemoryError):
        return "out of memory; use smaller sizes (fewer points per axis, a smaller memory_budget)"
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        return f"cannot access{where}: {exc.strerror or exc}; check the path and its permissions"
    return None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["bench"]:  # its options are bench.main's own (argparse's REMAINDER drops "--x" ones)
        args = argparse.Namespace(func=cmd_bench, rest=argv[1:])
    else:
        parser = build_parser()
        if not argv:
            parser.print_help()
            return 0
        parser._chosen = argv[0]
        args = parser.parse_args(_positionals_first(argv))
    saved = warnings.showwarning
    warnings.showwarning = _show_warning
    try:
        return args.func(args)
    except (CommandError, ranges.RangeError) as exc:
        return _error(exc)
    except KeyboardInterrupt:
        print("pbrdf-cl: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - environment faults get one line, anything else a traceback
        text = _environment_error(exc)
        if text is None:
            raise
        return _error(text)
    finally:
        warnings.showwarning = saved


if __name__ == "__main__":
    sys.exit(main())
