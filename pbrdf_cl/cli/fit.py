"""``pbrdf-cl fit`` (one set of measurements, a CSV) and ``pbrdf-cl fit-image`` (every pixel of an
image stack, into a Zarr store)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..device import engine as _engine
from ..io import files
from ..outputs import check_figure, check_output, check_store, check_suffix
from ..ranges import parse_bytes
from .common import (
    cluster_options,
    device_options,
    engine_for,
    error,
    fit_assignments,
    fit_settings,
    interrupted,
    model_option,
)


def _finite(d):
    """``d`` with None for its values that are not finite (JSON has no NaN)."""
    return {k: (v if np.isfinite(v) else None) for k, v in d.items()}


def _fit_json(r):
    corr = np.asarray(r.corr, dtype=float)
    return dict(model=r.model, shadowing=r.shadowing, success=bool(r.success), status=r.status, message=r.message,
                fits_data=bool(r.fits_data), x=r.x, kd_ratio=r.get("kd_ratio"),
                kd_fitted_as=("kd/ks" if "ks" in r.free and "kd" in r.free else "kd") if "kd" in r.free else None,
                free=r.free, stderr=_finite(r.stderr), outside_ci95=r.outside_ci95,
                ci95={k: list(v) for k, v in r.ci95.items()}, sse=r.sse, rmse=r.rmse, chi2=r.chi2,
                reduced_chi2=r.reduced_chi2 if r.sigma_known else None, p_value=r.p_value, r2=r.r2, aic=r.aic,
                bic=r.bic, dof=r.dof, residuals=r.residuals.tolist(),
                corr=np.where(np.isfinite(corr), corr, None).tolist(), condition_number=r.condition_number,
                nfev=r.nfev, seconds=r.seconds, ambiguous=r.ambiguous, notes=r.notes)


def _fit_brief(r):
    """One line per fitted parameter and a first line with the model, for --quiet."""
    from ..io.measurements import PHI_DEFAULT_NOTE
    lines = [f"{r.model}: SSE {r.sse:.4g}" + ("" if r.fits_data else " (the model does not describe these data)")]
    ratio = "ks" in r.free and "kd" in r.free  # intensities: the interval under "kd" is that of kd/ks
    for name in r.free:
        lo, hi = r.ci95[name]
        mark = _mark(r.fitted_value(name), lo, hi)
        if name == "kd" and ratio:
            lines.append(f"  kd/ks = {r.kd_ratio:.5g}  [{lo:.4g}, {hi:.4g}]{mark}  (kd = {r.x['kd']:.5g})")
        else:
            lines.append(f"  {name} = {r.x[name]:.5g}  [{lo:.4g}, {hi:.4g}]{mark}")
    if PHI_DEFAULT_NOTE in r.notes:
        lines.append(f"  note: {PHI_DEFAULT_NOTE}")
    return "\n".join(lines + _footnote(lines))


def _mark(x, lo, hi):
    """" (*)" where ``x`` lies outside its 95% interval [lo, hi] (:data:`OUTSIDE_FOOTNOTE` says why)."""
    from ..fitting.common import OUTSIDE_MARK, outside_interval
    return f" {OUTSIDE_MARK}" if outside_interval(x, lo, hi) else ""


def _footnote(lines, indent="  "):
    """The footnote of the marks in ``lines`` (none without a mark)."""
    from ..fitting.common import OUTSIDE_FOOTNOTE, OUTSIDE_MARK
    return [indent + OUTSIDE_FOOTNOTE] if any(OUTSIDE_MARK in ln for ln in lines) else []


def _joint_json(r):
    return dict(model=r.model, shadowing=r.shadowing, success=bool(r.success), status=r.status, message=r.message,
                fits_data=bool(r.fits_data), sets=r.sets, shared=r.shared, shared_x=r.shared_x, free=r.free, x=r.x,
                stderr={s: _finite(e) for s, e in r.stderr.items()}, outside_ci95=r.outside_ci95,
                ci95={s: {p: list(v) for p, v in c.items()} for s, c in r.ci95.items()},
                sse=r.sse, set_sse=r.set_sse, chi2=r.chi2, dof=r.dof, p_value=r.p_value, r2=r.r2, aic=r.aic,
                bic=r.bic, separate_aic=r.separate_aic, separate_bic=r.separate_bic, width_ratio=r.width_ratio,
                n_points=r.n_points, seconds=r.seconds, notes=r.notes, exchanged=[list(m) for m in r.exchanged],
                separate={s: _fit_json(f) for s, f in r.separate.items()})


def _joint_brief(r):
    """--quiet: the shared values, then each set's own, with their 95% intervals."""
    lines = [f"joint {r.model}: SSE {r.sse:.4g}, shared: {', '.join(r.shared) or 'none'}"
             + ("" if r.fits_data else " (the model does not describe these data)")]
    first = r.sets[0]
    for p in r.shared:
        ci = r.ci95[first].get(p)
        lines.append(f"  {p} = {r.shared_x[p]:.5g}" + (f"  [{ci[0]:.4g}, {ci[1]:.4g}]{_mark(r.shared_x[p], *ci)}"
                                                     if ci else "  (fixed)"))
    for s in r.sets:
        for p, (lo, hi) in r.ci95[s].items():
            if p not in r.shared:
                lines.append(f"  {p}[{s}] = {r.x[s][p]:.5g}  [{lo:.4g}, {hi:.4g}]{_mark(r.x[s][p], lo, hi)}")
    return "\n".join(lines + _footnote(lines))


def cmd_fit_joint(args, fixed, bounds) -> int:
    """`pbrdf-cl fit a.csv b.csv ...` or `fit table.csv --set-column wavelength`: a joint fit."""
    from ..fitting.sets import joint
    if args.compare:
        return error("--compare fits one data set; give one CSV without --shared or --set-column")
    try:
        if args.set_column:
            if len(args.data) != 1:
                raise ValueError(f"--set-column {args.set_column}: give one CSV (the table of every set), got "
                                 f"{len(args.data)}")
            sets = args.data[0]
        else:
            sets = joint.set_names_of_paths(args.data)
        engine = engine_for(args)
        r = joint.fit_joint(sets, args.shared, args.model, bounds=bounds, fixed=fixed, shadowing=args.shadowing,
                            set_column=args.set_column, engine=engine, progress=not args.quiet,
                            memory_budget=args.memory_budget)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    if not args.quiet:
        print("data: " + ", ".join(f"{s}: {m.source} ({_data_text(m)})" for s, m in r.measurements.items()))
    print(_joint_brief(r) if args.quiet else r.summary())
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(data={s: m.source for s, m in r.measurements.items()}, joint=_joint_json(r)), fh,
                      indent=2)
        print(f"wrote {args.json}")
    if args.plot:
        from ..plots.joint import plot_joint
        plot_joint(r, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _data_text(meas):
    """What a data set holds, for the first line of ``pbrdf-cl fit``: its points, and for
    polarimetric data the quantities measured and the incident states."""
    if not meas.polarimetric:
        return f"{len(meas)} points"
    from ..compute.measured import state_text
    states = [None] if meas.incident is None else np.unique(meas.incident, axis=0)
    return (f"{len(meas)} rows, {len(meas.channels())} measured numbers: {', '.join(meas.columns())} under "
            f"{len(states)} incident state{'s' if len(states) > 1 else ''}: {'; '.join(map(state_text, states))}")


def cmd_fit(args) -> int:
    from ..fitting.sample import inversion as _fit
    from ..io.measurements import read_csv
    if len(args.data) == 1 and args.shared is not None and not args.set_column:
        return error("--shared is for joint fits: give several CSVs (one set each) or one CSV with --set-column "
                     "COLUMN; to fit one data set, leave out --shared")
    is_joint = len(args.data) > 1 or bool(args.set_column)
    fixed, bounds = fit_assignments(args, sets=is_joint)
    args.memory_budget = parse_bytes("--memory-budget", args.memory_budget)
    check_suffix("--json", args.json, (".json",), "JSON is written here", allow_none=True)
    check_figure("--plot", args.plot)
    check_output("--json", args.json)
    check_output("--plot", args.plot)
    if is_joint:
        return cmd_fit_joint(args, fixed, bounds)
    try:
        meas = read_csv(args.data[0])
        engine = engine_for(args)
        kw = dict(shadowing=args.shadowing, bounds=bounds, fixed=fixed, engine=engine, progress=not args.quiet,
                  memory_budget=args.memory_budget)
        if args.compare:
            both = _fit.compare_models(meas, **kw)
            other = "specular" if args.model == "six-param" else "six-param"
            fits, best = {args.model: both[args.model], other: both[other]}, both["preferred"]
        else:
            if args.model == "specular":
                from ..fitting.setup import MODEL_PARAMS
                fitted = MODEL_PARAMS["specular"]
                kw["fixed"] = {k: v for k, v in fixed.items() if k in fitted}
                kw["bounds"] = {k: v for k, v in bounds.items() if k in fitted}
            fits, best = {args.model: _fit.fit(meas, args.model, **kw)}, None
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    if not args.quiet:
        print(f"data: {meas.source} ({_data_text(meas)})")
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
        from ..plots.fit import plot_fit
        plot_fit(meas, fits, args.plot)
        print(f"wrote {args.plot}")
    return 0


def cmd_fit_image(args) -> int:
    import time

    from ..fitting.images import batch
    from ..fitting.images import store as image_store
    fixed, bounds = fit_assignments(args)
    check_store("--out", args.out)
    check_figure("--png", args.png)
    check_output("--out", str(Path(args.out).parent), folder=True)
    check_output("--png", args.png)
    cluster = bool(args.workers or args.scheduler)
    t0 = time.perf_counter()
    try:
        engine = engine_for(args) if not cluster else None
        ds = batch.fit_batch(
            args.stack, store=args.out, model=args.model, bounds=bounds or None, fixed=fixed or None,
            shadowing=args.shadowing, memory_budget=args.memory_budget, progress=not args.no_progress, engine=engine,
            backend=args.backend, device=args.device, workers=args.workers, scheduler=args.scheduler,
            allow_large=args.allow_large, quantities=args.quantities, **_label_options(args))
        counts = image_store.status_counts(ds)
        if args.png:
            from ..plots.images import plot_batch_maps
            plot_batch_maps(ds, args.png)
    except KeyboardInterrupt:
        return interrupted(lambda: image_store.read_progress(args.out), "blocks", args.out)
    except (OSError, ValueError, RuntimeError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    seconds = time.perf_counter() - t0
    px, fit_s = ds.attrs["pixels_computed"], ds.attrs["seconds"]
    total = int(np.prod(ds["status"].shape, dtype=np.int64))
    rate = f", {px / fit_s:.4g} pixels/s" if px and fit_s > 0 else ""
    print(f"fit-image: {px} of {total} pixels fitted in {fit_s:.3g} s{rate} ({total - px} already in the store; "
          f"{seconds:.3g} s in all)")
    if "incident" in ds.attrs:  # polarimetric channels
        print(f"fitted: {', '.join(ds.attrs['quantities'].split())} (source: {ds.attrs['incident']})")
    print("status: " + ", ".join(f"{n} {c}" for n, c in counts.items()))
    if "goodness" in ds.attrs:
        print(ds.attrs["goodness"])
    if "goodness_warning" in ds.attrs:
        print(ds.attrs["goodness_warning"])
    for note in str(ds.attrs.get("data_notes", "")).splitlines():
        print(f"note: {note}")
    if "outside_ci95_note" in ds.attrs:
        print(f"note: {ds.attrs['outside_ci95_note']}")
    if "label" in ds.dims:
        _print_labels(ds)
    print(f"store: {ds.attrs['store']}" + (f"; maps: {args.png}" if args.png else ""))
    return 0


def _print_labels(ds):
    """fit-image --labels: each label's shared values with their 95% intervals (marked where the
    value lies outside), whether its values describe its pixels' data, the notes and the WARNING
    naming the labels that do not."""
    lines = []
    for j, lab in enumerate(ds["label"].values):
        values = []
        for n in ds.attrs["shared"].split():
            x, (lo, hi) = float(ds[f"label_{n}"][j]), ds[f"label_{n}_ci95"].values[j]
            values.append(f"{n} = {x:.4g} [{lo:.4g}, {hi:.4g}]{_mark(x, lo, hi)}")
        fits = int(ds["label_fits_data"][j]) if "label_fits_data" in ds else -1
        lines.append(f"label {lab}: " + ", ".join(values) + f" ({int(ds['label_pixels'][j])} pixels"
                     + ("; does not fit its pixels' data: see the WARNING" if fits == 0 else "") + ")")
    lines += _footnote(lines, indent="")
    print("\n".join(lines))
    for key in ("label_goodness", "label_cov_note"):
        for line in str(ds.attrs.get(key, "")).splitlines():
            print(line if key == "label_goodness" else f"note: {line}")
    print(f"note: {ds.attrs['label_interval_note']}")
    if "label_goodness_warning" in ds.attrs:
        print(ds.attrs["label_goodness_warning"])


def _label_options(args):
    """fit_batch's labels= and shared= from --labels (a .npy file or a variable of the stack) and --shared."""
    if args.labels is None:
        if args.shared is not None:
            raise ValueError("--shared needs --labels (the label image that says which pixels share them)")
        return {}
    labels = args.labels
    if labels.endswith(".npy"):
        if not Path(labels).is_file():
            raise ValueError(f"--labels: no such file {labels!r}")
        labels = files.read_npy(labels, "--labels")
    elif Path(labels).is_file():
        raise ValueError(f"--labels {labels}: a file, but not a .npy one; save the label image with numpy.save "
                         "(a .npy file), or give the name of a variable of the stack")
    return {"labels": labels, "shared": args.shared}


def fit_parser(sub):
    """The `pbrdf-cl fit` sub-command."""
    from ..fitting.sample.stages import MEMORY_BUDGET
    f = sub.add_parser("fit", help="invert n, k, sigma, kd/ks, c from measured DOP (CSV; several: a joint fit)",
                       description="Fit the six-parameter model (or, with --model specular, the ref. [7] "
                       "specular model; --compare: both) to a CSV of measurements (columns theta_i, theta_r, "
                       "dop[, phi, dop_std, f00|s0, f00_std]). Several CSVs (or one with --set-column): a joint "
                       "fit, the --shared parameters one value for every set, the others one per set.")
    f.add_argument("data", nargs="+", help="measurement CSV; several: one set each (named by its file name)")
    f.add_argument("--shared", metavar="NAMES", help="joint fit: the parameters shared by every set, separated by "
                   "commas or spaces (default sigma,c, those the model fits; '' shares nothing)")
    f.add_argument("--set-column", metavar="COLUMN", help="joint fit of one CSV whose column COLUMN (e.g. "
                   "wavelength) names each row's set")
    model_option(f)
    f.add_argument("--compare", action="store_true",
                   help="fit both models and compare them by AIC/BIC (--model's is listed first)")
    fit_settings(f, joint=True)
    f.add_argument("--memory-budget", default=MEMORY_BUDGET, metavar="SIZE",
                   help="memory of the grid stage's tables of the measurements (more run block by block, with the "
                   f"same result), e.g. 256MiB (default {MEMORY_BUDGET.replace(' ', '')})")
    device_options(f, " for the grid stage")
    f.add_argument("--json", metavar="OUT", help="write both fits as JSON")
    f.add_argument("--plot", metavar="PNG", help="plot data, both models and residuals")
    f.add_argument("--quiet", action="store_true",
                   help="no progress bar; only each fitted value with its 95%% interval")
    f.set_defaults(func=cmd_fit)


def fit_image_parser(sub):
    """The `pbrdf-cl fit-image` sub-command."""
    from ..fitting.images.job import BLOCK_BUDGET as DEFAULT_BUDGET
    f = sub.add_parser("fit-image", help="fit every pixel of a DOP or polarimetric image stack into a Zarr store "
                       "(resumable; dask)",
                       description="Fit the model to every pixel of a polarization image stack (.npz, .nc or "
                       ".zarr with dop (y, x, m), theta_i, theta_r[, phi, dop_std, f00|s0, f00_std, mask]; angles "
                       "shared (m) or per pixel; or a polarization camera's s1, s2 (normalised Stokes) with the "
                       "source's state in_s1, in_s2, in_s3 per measurement, s3, aop, Mueller elements m01..m33, "
                       "each with an optional <name>_std) block by block into a Zarr store. Run the same command "
                       "again after an interruption: only the missing blocks are fitted.")
    f.add_argument("stack", help="image stack: .npz, .nc or .zarr")
    f.add_argument("--out", required=True, metavar="STORE", help="Zarr store to create or resume (e.g. params.zarr)")
    model_option(f)
    fit_settings(f)
    f.add_argument("--memory-budget", default=DEFAULT_BUDGET, metavar="SIZE",
                   help="memory of one block of pixels in flight (host and device), e.g. 256MiB")
    cluster_options(f, "fit")
    f.add_argument("--png", metavar="PNG", help="also draw the parameter maps, their 95%% interval widths and the "
                   "fit status")
    f.add_argument("--no-progress", action="store_true", help="no progress bar")
    f.add_argument("--allow-large", action="store_true",
                   help="start even when the store (uncompressed) would not fit on the free disk")
    f.add_argument("--labels", metavar="NPY|NAME", help="integer label image over the pixels (0: not fitted), a .npy "
                   "file or a variable of the stack: the pixels of a label share --shared (docs/joint_images.md)")
    f.add_argument("--shared", metavar="NAMES", help="parameters the pixels of a label share, separated by commas or "
                   "spaces (default n,k, less a fixed one; '' shares nothing: every pixel on its own)")
    f.add_argument("--quantities", metavar="NAMES", help="the measured quantities to fit, separated by commas or "
                   "spaces (e.g. s1,s2; default: the stack's polarimetric ones where it gives the source's state "
                   "in_s1..in_s3 or has no dop, else dop)")
    f.set_defaults(func=cmd_fit_image)
