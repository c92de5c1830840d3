#!/usr/bin/env python
"""Benchmark of the Sobol' sensitivity maps (issue #15): ``pbrdf_cl.sobol`` end to end against the
same computation with SALib and the numpy reference model, in the same run.

The case of the issue: 5 parameters (n, k log-uniform, sigma, kd, c), N = 4096 base samples,
N (D + 2) = 28,672 model runs per geometry, a 64 x 64 (theta_i, theta_r) grid: 1.2e8 model runs.

Rows printed:
  * ``pbrdf_cl.sobol`` end to end (sampling, the device's model runs, the estimators with their
    bootstrap intervals, the Dataset), and the device's model runs alone (``dense.outer`` over
    the same samples and geometries: the "kernel" figure beside the user's);
  * SALib + numpy reference: ``reference.evaluate`` on the same samples and ``SALib.analyze.sobol``
    per geometry (with the same seed), on ``--reference-geometries`` of the geometries (all of
    them by default: minutes) and, when fewer, extrapolated to all (said so);
  * the largest difference between our indices and SALib's on those geometries (our float32 model
    runs against SALib on float64 reference outputs), and with ``--float64`` our float64 run's.

    python scripts/bench_sobol.py [--N 4096] [--grid 64] [--reference-geometries 4096] [--json out.json]
"""
import argparse
import json
import time
import warnings

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--N", type=int, default=4096, help="base samples (default 4096)")
    ap.add_argument("--grid", type=int, default=64, help="theta_i x theta_r values per axis (default 64)")
    ap.add_argument("--reference-geometries", type=int, default=None,
                    help="geometries the SALib + numpy reference runs on (default: all; fewer: extrapolated)")
    ap.add_argument("--float64", action="store_true", help="also time a float64 run and compare it with SALib")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    from pbrdf_cl.outputs import check_json
    check_json("--json", args.json, "bench_sobol")  # before the work, not after it

    import pbrdf_cl
    from pbrdf_cl.analysis import sensitivity
    from pbrdf_cl.compute import dense
    from pbrdf_cl.model import reference
    # SALib divides by the outputs' standard deviation, which is 0 where the DOP is (theta_i = theta_r = 0)
    warnings.filterwarnings("ignore", "invalid value encountered in divide", RuntimeWarning)
    from SALib.analyze import sobol as salib_sobol

    ranges = {"n": (1.2, 2.5), "k": (0.01, 3.0, "log"), "sigma": (0.1, 0.6), "kd": (0.0, 0.5), "c": (-1.0, 0.0)}
    geometry = {"theta_i": f"0:80@{args.grid}", "theta_r": f"0:85@{args.grid}"}
    eng = pbrdf_cl.get_default_engine()
    print(f"device: {eng.description}")
    # build the kernels and warm up outside the timings (the first call at a new build pays it)
    pbrdf_cl.sobol(ranges, {"theta_i": 40, "theta_r": [10.0, 20.0]}, N=64, seed=args.seed, engine=eng)
    out = {"N": args.N, "grid": args.grid, "parameters": len(ranges), "device": eng.description}

    t0 = time.perf_counter()
    ds = pbrdf_cl.sobol(ranges, geometry, N=args.N, seed=args.seed, engine=eng)
    e2e = time.perf_counter() - t0
    runs, G = ds.attrs["runs_per_geometry"], ds.attrs["geometries"]
    total = runs * G
    out.update(model_runs=total, runs_per_geometry=runs, geometries=G, seconds_end_to_end=e2e)
    print(f"pbrdf_cl.sobol, float32, end to end: {e2e:.2f} s for {total:.3g} model runs "
          f"({G} geometries x {runs} runs; {total / e2e / 1e6:.1f} M runs/s, estimators and bootstrap included)")

    # the device's model runs alone, the same samples and geometries
    rngs = sensitivity.check_ranges(ranges)
    fixed = sensitivity.check_fixed(None, {r.name for r in rngs})
    axes, scalars = sensitivity.check_geometry(geometry)
    geo, shape = sensitivity.geometry_list(axes, scalars)
    names = list(ds.parameter.values)
    params = {n: ds.samples.sel(parameter=n).values if n in names else np.full(runs, fixed[n])
              for n in dense.PARAMETERS}
    block = max(1, (256 << 20) // (runs * 4))
    buf = np.empty((min(block, G), runs), np.float32)
    t0 = time.perf_counter()
    for g0 in range(0, G, block):
        g1 = min(G, g0 + block)
        dense.outer(eng, "dop", geo, params, "float32", out=buf[:g1 - g0], rows=(g0, g1))
    kern = time.perf_counter() - t0
    out["seconds_model_runs"] = kern
    print(f"  the device's model runs alone (dense.outer): {kern:.2f} s ({total / kern / 1e6:.1f} M runs/s); "
          f"estimators, sampling and the rest: {e2e - kern:.2f} s")

    # SALib + numpy reference on the same samples (float64), per geometry
    K = G if args.reference_geometries is None else max(1, min(G, args.reference_geometries))
    pick = np.unique(np.linspace(0, G - 1, K).round().astype(int))
    problem = {"num_vars": len(names), "names": names, "bounds": [list(ds.attrs[f"range_{n}"]) for n in names]}
    worst = {"S1": 0.0, "ST": 0.0}
    t_model = t_salib = 0.0
    S1 = ds.S1.values.reshape(len(names), G)
    ST = ds.ST.values.reshape(len(names), G)
    for i in pick:
        t0 = time.perf_counter()
        y = reference.evaluate("dop", geo["theta_i"][i], geo["theta_r"][i], geo["phi"][i],
                               *(params[n] for n in dense.PARAMETERS))
        t1 = time.perf_counter()
        S = salib_sobol.analyze(problem, y, calc_second_order=False, seed=args.seed)
        t2 = time.perf_counter()
        t_model += t1 - t0
        t_salib += t2 - t1
        worst["S1"] = max(worst["S1"], float(np.max(np.abs(S1[:, i] - S["S1"]))))
        worst["ST"] = max(worst["ST"], float(np.max(np.abs(ST[:, i] - S["ST"]))))
    ref = (t_model + t_salib) * G / pick.size
    how = "measured" if pick.size == G else f"extrapolated from {pick.size} of the {G} geometries"
    out.update(reference_seconds=ref, reference_geometries=int(pick.size),
               reference_model_seconds=t_model * G / pick.size,
               reference_salib_seconds=t_salib * G / pick.size, max_abs_difference_float32=worst)
    print(f"SALib + numpy reference (float64): {ref:.1f} s ({how}): model {t_model * G / pick.size:.1f} s, "
          f"SALib.analyze.sobol {t_salib * G / pick.size:.1f} s; pbrdf_cl.sobol is {ref / e2e:.0f}x faster")
    print(f"  largest |our float32 index - SALib's|: S1 {worst['S1']:.2e}, ST {worst['ST']:.2e} "
          f"(on {pick.size} geometries)")

    if args.float64:
        t0 = time.perf_counter()
        d64 = pbrdf_cl.sobol(ranges, geometry, N=args.N, seed=args.seed, dtype="float64", engine=eng)
        t64 = time.perf_counter() - t0
        w64 = 0.0
        for i in pick[:64]:
            y = reference.evaluate("dop", geo["theta_i"][i], geo["theta_r"][i], geo["phi"][i],
                                   *(params[n] for n in dense.PARAMETERS))
            S = salib_sobol.analyze(problem, y, calc_second_order=False, seed=args.seed)
            for key in ("S1", "ST", "S1_conf", "ST_conf"):
                w64 = max(w64, float(np.max(np.abs(d64[key].values.reshape(len(names), G)[:, i] - S[key]))))
        out.update(seconds_float64=t64, max_abs_difference_float64=w64)
        print(f"pbrdf_cl.sobol, float64, end to end: {t64:.2f} s; largest difference from SALib "
              f"(S1, ST and intervals, {min(64, pick.size)} geometries): {w64:.1e}")
    target = 10.0
    print(f"target: <= {target:g} s end to end for this case on 2 cores: "
          f"{'met' if e2e <= target else 'NOT met'} ({e2e:.2f} s)")
    out["target_seconds"] = target
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)


if __name__ == "__main__":
    main()
