"""The commands that explore the model: ``pbrdf-cl sweep`` (into a Zarr store), ``map``, ``sobol``,
``design`` and ``reproduce`` (the paper's figures)."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from .. import ranges
from ..device import engine as _engine
from ..model.reference import SHADOWING
from ..outputs import check_figure, check_output, check_store, check_suffix
from .common import (
    SHADOWING_HELP,
    check_result_outputs,
    cluster_options,
    device_options,
    engine_for,
    error,
    fit_settings,
    interrupted,
    items,
    quantity_choices,
)


def cmd_sweep(args) -> int:
    from ..analysis.sweeps import load_spec, read_done, sweep
    check_store("--out", args.out)
    check_output("--out", str(Path(args.out).parent), folder=True)
    try:
        spec = load_spec(args.spec)
        engine = engine_for(args) if not (args.workers or args.scheduler) else None
        res = sweep(spec, args.out, engine=engine, device=args.device, backend=args.backend, workers=args.workers,
                    scheduler=args.scheduler, progress=not args.quiet, allow_large=args.allow_large)
    except KeyboardInterrupt:
        return interrupted(lambda: (int(read_done(spec, args.out).sum()), spec.n_chunks), "chunks", args.out)
    except (OSError, ValueError, RuntimeError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    print(res.summary())
    return 0


def cmd_verify(args) -> int:
    """`pbrdf-cl verify STORE ...`: check sweep or fit-image stores against their digests and
    manifests; exit 0 when every one is intact, 1 with one line per kind of damage."""
    from ..store.verify import verify_store
    rc = 0
    for store in args.store:
        try:
            rep = verify_store(store)
        except (OSError, ValueError) as exc:
            rc = error(exc)
            continue
        for note in rep["notes"]:
            print(f"note: {rep['store']}: {note}")
        if rep["ok"]:
            print(f"{rep['store']}: intact ({rep['done']} of {rep['units']} units verified against their digests)")
            continue
        for problem in rep["problems"]:
            print(f"pbrdf-cl: error: {rep['store']}: {problem}", file=sys.stderr)
        print(f"pbrdf-cl: run the command that wrote {rep['store']} again to recompute what is damaged",
              file=sys.stderr)
        rc = 1
    return rc


def cmd_sobol(args) -> int:
    """`pbrdf-cl sobol SPEC.toml`: a Sobol' (or Morris) sensitivity map, its file, figure and summary."""
    from ..analysis import sensitivity
    check_result_outputs(args)
    try:
        settings = sensitivity.load_sobol_spec(args.spec)
        if args.png:  # refused before the work, not after it
            from ..plots.sensitivity import check_axes
            check_axes(sensitivity.check_geometry(settings["geometry"])[0], "--png")
        with warnings.catch_warnings():  # the summary below prints the result's notes
            warnings.simplefilter("ignore", sensitivity.SensitivityWarning)
            ds = sensitivity.sobol(**settings, progress=not args.no_progress, engine=engine_for(args))
        if args.out:
            sensitivity.write_result(ds, args.out)
        if args.png:
            from ..plots.sensitivity import plot_sensitivity
            plot_sensitivity(ds, args.png)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    print(sensitivity.summary(ds))
    wrote = [p for p in (args.out, args.png) if p]
    if wrote:
        print(f"wrote {' and '.join(wrote)}")
    return 0


def cmd_reproduce(args) -> int:
    from ..analysis import paper
    try:
        paper.check_resolution(args.resolution)
    except ValueError as exc:
        return error(exc)
    check_output("--out", args.out, folder=True)
    try:
        engine = engine_for(args)
        files = paper.reproduce(args.out, resolution=args.resolution, engine=engine,
                                log=(lambda *a: None) if args.quiet else print)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    print(f"wrote {len(files)} files to {args.out}/ (list: {args.out}/summary.md):")
    for name in files:
        print(f"  {args.out}/{name}")
    return 0


def cmd_map(args) -> int:
    from ..analysis import maps
    from ..plots.maps import plot_map
    try:
        x = maps.parse_axis("--x", args.x)
        y = maps.parse_axis("--y", args.y)
        fixed = maps.parse_fixed("--fix", args.fix)
        if args.params:  # a parameter-set file (`pbrdf-cl explore` exports them): --fix and the axes win
            from ..io.params import read_params
            fixed = {**{k: v for k, v in read_params(args.params).items() if k not in (x[0], y[0])}, **fixed}
        check_figure("--out", args.out)
        check_suffix("--npz", args.npz, (".npz",), "numpy's archive of the arrays is written here")
        check_output("--out", args.out)
        check_output("--npz", args.npz)
        engine = engine_for(args)
        ds = maps.make_map(x, y, fixed, quantity=args.quantity, derivative=args.derivative, dtype=args.dtype,
                           shadowing=args.shadowing, engine=engine, memory_budget=args.memory_budget)
        plot_map(ds, args.out)
        if args.npz:
            maps.save_npz(ds, args.npz)
    except (OSError, ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    for note in ds.attrs.get("notes", []):
        print(f"pbrdf-cl: note: {note}", file=sys.stderr)
    v = ds[ds.attrs["quantity"]].values
    print(f"{ds.attrs['quantity']} over {x[0]} ({x[1].size} points) x {y[0]} ({y[1].size} points): "
          f"min {np.nanmin(v):.6g}, max {np.nanmax(v):.6g}")
    print(f"wrote {args.out}" + (f" and {args.npz}" if args.npz else ""))
    return 0


def cmd_design(args) -> int:
    from ..analysis.designs import GEOMETRY, design
    from ..analysis.sensitivity import write_result
    from ..compute.dense import PARAMETERS
    from ..fitting.setup import DEFAULT_BOUNDS
    from ..plots.design import plot_design
    params = ranges.parse_assignments(items(args.params), PARAMETERS, "value", "--params", check=True)
    box = ranges.parse_assignments(items(args.box), PARAMETERS, "bounds", "--box")
    both = sorted(set(params) & set(box))
    if both:
        return error(f"--box {both[0]}: also given in --params; give it once")
    params.update(box)
    cand = ranges.parse_assignments(args.candidates, GEOMETRY, "values", "--candidates") if args.candidates else None
    ref = ranges.parse_assignments(args.reference, GEOMETRY, "values", "--reference") if args.reference else None
    fixed = ranges.parse_assignments(args.fix, tuple(DEFAULT_BOUNDS), "value", "--fix", check=True)
    bounds = ranges.parse_assignments(args.bounds, tuple(DEFAULT_BOUNDS), "bounds", "--bounds")
    target = tuple(t.strip() for t in args.target.split(",") if t.strip())
    instrument = [s for a in args.instrument for s in a.split(",") if s.strip()] if args.instrument else None
    check_result_outputs(args)
    try:
        res = design(params, cand, noise=args.noise, n_measurements=args.n, target=target, intensity=args.intensity,
                     fixed=fixed, criterion=args.criterion, reference=ref, intensity_noise=args.intensity_noise,
                     bounds=bounds, materials=args.materials, repeats=args.repeats, seed=args.seed,
                     shadowing=args.shadowing, instrument=instrument, engine=engine_for(args),
                     memory_budget=args.memory_budget)
    except (ValueError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    print(res.summary())
    try:
        if args.out:
            write_result(res.to_dataset(), args.out)
        if args.png:
            plot_design(res, args.png)
    except (OSError, ValueError) as exc:  # e.g. a .zarr path that is something else
        return error(exc)
    wrote = [p for p in (args.out, args.png) if p]
    if wrote:
        print(f"wrote {' and '.join(wrote)}")
    return 0


def sweep_parser(sub):
    """The `pbrdf-cl sweep` sub-command."""
    s = sub.add_parser("sweep", help="a sweep of any size into a Zarr store (resumable; dask cluster)",
                       description="Evaluate the sweep described by a TOML spec (axes, fixed values, quantity, "
                       "dtype, chunks, optional reductions; see examples/sweep_sigma_theta.toml) chunk by chunk "
                       "into a Zarr store. Run the same command again after an interruption: only the missing "
                       "chunks are computed.")
    s.add_argument("spec", help="TOML spec")
    s.add_argument("--out", required=True, metavar="STORE", help="Zarr store to create or resume (e.g. result.zarr)")
    cluster_options(s, "run")
    s.add_argument("--quiet", action="store_true", help="no progress bar; one summary line at the end")
    s.add_argument("--allow-large", action="store_true",
                   help="start even when the store (uncompressed) would not fit on the free disk")
    s.set_defaults(func=cmd_sweep)


def verify_parser(sub):
    """The `pbrdf-cl verify` sub-command."""
    v = sub.add_parser("verify", help="check a sweep or fit-image store: every chunk against its digest",
                       description="Check a store of `pbrdf-cl sweep` or `pbrdf-cl fit-image` without its spec: "
                       "its metadata and coordinates against the manifest in its root attributes, every done "
                       "chunk's values against the digest written with it, the consolidated metadata and the "
                       "completion mark; removes the .partial files of interrupted writes. Exit status 0 when "
                       "intact, 1 with one line per kind of damage (counts and the first chunks); running the "
                       "command that wrote the store again recomputes what is damaged.")
    v.add_argument("store", metavar="STORE", nargs="+", help="Zarr stores (paths or fsspec URLs)")
    v.set_defaults(func=cmd_verify)


def reproduce_parser(sub):
    """The `pbrdf-cl reproduce` sub-command."""
    r = sub.add_parser("reproduce", help="reproduce the paper's figures and Table 1, plus roughness maps",
                       description="Writes Fig. 2 (aluminum, black paint: synthetic data, both models fitted), "
                       "Table 1, Fig. 4, Fig. 5, two dense DOP maps, a Sobol' map of the DOP and a measurement design "
                       "for the steel (.png, .nc), the arrays of each figure (.npz) and summary.md into one folder.")
    r.add_argument("--out", default="paper-figures", help="output folder (default: paper-figures)")
    r.add_argument("--resolution", type=int, default=256, help="points per map axis (default 256)")
    device_options(r)
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    r.set_defaults(func=cmd_reproduce)


def map_parser(sub):
    """The `pbrdf-cl map` sub-command."""
    m = sub.add_parser("map", help="a dense map of DOP, F00 or AoP over any two axes (PNG + optional .npz)",
                       description=f"Axes: NAME=VALUES, VALUES being {ranges.GRAMMAR}; see the docs, "
                       "docs/guide/cli.md, Ranges and name=value. Angles in degrees. Inputs not on an axis are "
                       "fixed with --fix "
                       "(phi, ks, kd, c default to 180, 1, 0, 0). Example: pbrdf-cl map --x theta_r=0:85@256 "
                       "--y sigma=0.05:1@256 --fix theta_i=40 n=1.6 k=2.139 ks=0.9 kd=0.15 c=-0.3 --derivative sigma "
                       "--out map.png")
    m.add_argument("--x", required=True, metavar="NAME=VALUES", help="horizontal axis, e.g. theta_r=0:85@256")
    m.add_argument("--y", required=True, metavar="NAME=VALUES", help="vertical axis, e.g. sigma=0.05:1:0.05")
    m.add_argument("--fix", nargs="*", metavar="NAME=VALUE", help="the other inputs, e.g. theta_i=40 n=1.6")
    m.add_argument("--params", metavar="FILE", help="n, k, sigma, ks, kd, c from a JSON or TOML file (as `pbrdf-cl "
                   "explore` exports a set); --fix and the axes win")
    m.add_argument("--quantity", choices=quantity_choices("map"), default="dop", type=str.lower,
                   help="what to map: dop, brdf (alias f00; 1/sr, log colours when it spans decades), aop (deg)")
    m.add_argument("--derivative", metavar="NAME",
                   help="add a panel with d(quantity)/d(NAME): finite differences of step 1e-4 at every node, "
                   "one-sided at a bound of the domain, on float64 device grids")
    m.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision")
    m.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=SHADOWING_HELP)
    device_options(m)
    m.add_argument("--memory-budget", default="1 GiB", metavar="SIZE", help="the memory the map may take (about 144 "
                   "bytes a point, 400 with --derivative); a larger map is refused before any work (default: 1 GiB)")
    m.add_argument("--out", default="map.png", help="PNG to write (default map.png)")
    m.add_argument("--npz", metavar="NPZ", help="also save the arrays (coordinates, values, derivative)")
    m.set_defaults(func=cmd_map)


def sobol_parser(sub):
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
    device_options(s)
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_sobol)


def design_parser(sub):
    """The `pbrdf-cl design` sub-command."""
    from ..fitting.setup import F00_REL_STD
    d = sub.add_parser("design", help="choose measurement geometries from the Fisher information (predicted "
                       "95%% interval widths)",
                       description="For a hypothesised material (--params) or a box of materials (--box), "
                       "choose the --n geometries out of the candidates that make the target parameters' "
                       "predicted 95% intervals narrowest, and compare with the paper's geometry (theta_i "
                       "30/40/50 x theta_r 20..65 step 5); with --instrument, for the first instrument, and "
                       "every instrument compared at the same geometries. Example: pbrdf-cl design --params "
                       "n=1.6,k=2.139,sigma=0.5,kd=0.15,c=-0.3 --noise 0.005 --n 30 --instrument "
                       "dop,camera45,camera4,mueller --out design.nc --png design.png")
    d.add_argument("--params", nargs="+", metavar="NAME=VALUE", required=True,
                   help="the material: n, k, sigma (and kd, c, ks; defaults 0, 0, 1), e.g. n=1.6,k=2.139,sigma=0.5")
    d.add_argument("--box", nargs="+", metavar="NAME=LO:HI", help="parameters ranging over a box (instead of "
                   "a value in --params), e.g. n=1.2:2.5; the criterion is averaged over --materials draws")
    d.add_argument("--candidates", nargs="+", action="extend", metavar="NAME=VALUES",
                   help="candidate grid axes (degrees), e.g. theta_i=10:80:5 theta_r=0:85:5 (default; phi 180)")
    d.add_argument("--reference", nargs="+", action="extend", metavar="NAME=VALUES",
                   help="the grid to compare with (default the paper's: theta_i=30,40,50 theta_r=20:65:5)")
    d.add_argument("--noise", type=float, default=0.005, help="standard deviation of each DOP measurement (with "
                   "--instrument: of each normalised quantity measured)")
    d.add_argument("--instrument", nargs="+", action="extend", metavar="NAME",
                   help="what is measured at each geometry, one or several (comma-separated) to compare: dop (the "
                   "DOP, unpolarised source), camera45 or camera (s1, s2; source linear at 45 deg), camera4 (s1, s2; "
                   "sources linear at 0/45/90/135 deg and circular), mueller (the 15 m_ij = M_ij / M00), or "
                   "QUANTITIES[@STATES] joined by + (s1+s2@0+90+circular, dop@45, camera@0+45); the geometries are "
                   "chosen for the first")
    d.add_argument("--n", type=int, default=30, help="how many measurements to choose")
    d.add_argument("--target", default="n,k", help="the parameters to determine best, comma-separated")
    d.add_argument("--intensity", action="store_true", help="each geometry also measures F00 (ks free, kd as kd/ks)")
    d.add_argument("--intensity-noise", type=float, default=F00_REL_STD, help="relative standard deviation of F00")
    d.add_argument("--criterion", choices=("A", "D"), default="A",
                   help="A: sum of the targets' variances / bound range^2; D: log det of their covariance")
    d.add_argument("--materials", type=int, default=16, help="materials drawn from --box")
    d.add_argument("--seed", type=int, default=0, help="seed of the materials drawn from --box")
    d.add_argument("--repeats", action="store_true", help="allow a geometry to be chosen more than once")
    d.add_argument("--memory-budget", default="1 GiB", metavar="SIZE", help="the memory the design may take (about "
                   "2 KiB per candidate and material); more candidates are refused before any work (default: 1 GiB)")
    fit_settings(d)
    device_options(d)
    d.add_argument("--out", metavar="FILE", help="write the design: .nc (netCDF) or .zarr (a Zarr store)")
    d.add_argument("--png", metavar="PNG", help="draw the information map and the predicted widths")
    d.set_defaults(func=cmd_design)
