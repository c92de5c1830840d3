#!/usr/bin/env python3
"""Benchmark of the inversion (issue targets): for random problems in two geometries, how often
each method finds the optimum, its median wall time, and (for pbrdf_cl.fit) how often the 95%
intervals cover the truth.

Problems: parameters drawn uniformly inside the default bounds (n [1, 5], k [0, 10],
sigma [0.05, 1], kd/ks [0, 5], c [-1, 0]), ks = 1, Gaussian DOP noise of std 0.002 (given as
dop_std).  "Optimum found": SSE within 1e-6 relative of the best SSE any method found on that
problem.  Baselines (scipy): least_squares from the centre of the bounds, differential_evolution,
and least_squares from 64 random starts; they are slow, so they run on the first
--baseline-problems problems.  On every problem an oracle competitor also runs: scipy
least_squares started from the true parameters (impossible in practice, cheap here, and hard
to beat: it starts in the right valley), so "optimum found" is judged on all --problems
problems, not only where the baselines ran.
"""
import argparse
import json
import time

import numpy as np

import pbrdf_cl
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.fitting.sample import stages
from pbrdf_cl.io.measurements import from_arrays

GEOMETRIES = {
    "paper (theta_i 30/40/50 x theta_r 20..65, 30 points)":
        (np.repeat([30.0, 40.0, 50.0], 10), np.tile(np.arange(20.0, 66.0, 5.0), 3)),
    "one incidence angle (theta_i 40, theta_r 20..65, 10 points)":
        (np.full(10, 40.0), np.arange(20.0, 66.0, 5.0)),
}
NAMES = ("n", "k", "sigma", "kd", "c")
LO = np.array([fit_setup.DEFAULT_BOUNDS[n][0] for n in NAMES])
HI = np.array([fit_setup.DEFAULT_BOUNDS[n][1] for n in NAMES])
NOISE = 0.002
ORACLE = "oracle: least_squares from the truth"


def problem(rng, ti, tr):
    truth = dict(zip(NAMES, LO + rng.random(5) * (HI - LO)))
    d = pbrdf_cl.dop(ti, tr, 180.0, backend="numpy", **truth)
    d = np.clip(d + rng.normal(0, NOISE, d.size), 0, 1)
    return truth, from_arrays(ti, tr, d, 180.0, np.full(d.size, NOISE))


def residual(meas):
    mdl = stages.Model(meas, "paper")

    def resid(x):
        return (mdl.dop(dict(zip(NAMES, x), ks=1.0)) - meas.dop) / meas.dop_std
    return resid


def oracle(meas, truth):
    """least_squares from the truth (as tight as the fit's own polish), SSE and seconds."""
    from scipy.optimize import least_squares
    t = time.perf_counter()
    x0 = np.clip([truth[n] for n in NAMES], LO, HI)
    r = least_squares(residual(meas), x0, bounds=(LO, HI), x_scale=HI - LO, ftol=1e-15, xtol=1e-15, gtol=1e-15,
                      max_nfev=500)
    return 2 * r.cost, time.perf_counter() - t


def baselines(meas, rng, starts=64, de_maxiter=1000):
    from scipy.optimize import differential_evolution, least_squares
    resid = residual(meas)

    def sse(x):
        r = resid(x)
        return float(r @ r)
    out = {}
    t = time.perf_counter()
    r = least_squares(resid, (LO + HI) / 2, bounds=(LO, HI))
    out["scipy least_squares from the centre"] = (2 * r.cost, time.perf_counter() - t)
    t = time.perf_counter()
    r = differential_evolution(sse, list(zip(LO, HI)), seed=int(rng.integers(1 << 30)), polish=True,
                               maxiter=de_maxiter)
    out["scipy differential_evolution"] = (r.fun, time.perf_counter() - t)
    t = time.perf_counter()
    best = np.inf
    for x0 in LO + rng.random((starts, 5)) * (HI - LO):
        best = min(best, 2 * least_squares(resid, x0, bounds=(LO, HI)).cost)
    out[f"scipy {starts}-start least_squares"] = (best, time.perf_counter() - t)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--problems", type=int, default=200)
    p.add_argument("--baseline-problems", type=int, default=200)
    p.add_argument("--json", default="bench_fit.json")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--progress", action="store_true", help="a line per problem")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 4-start least squares and 3 differential_evolution generations as baselines")
    args = p.parse_args(argv)
    from pbrdf_cl.outputs import check_json
    check_json("--json", args.json, "bench_fit")  # before the work, not after it
    engine = pbrdf_cl.get_default_engine()
    report = {}
    for gname, (ti, tr) in GEOMETRIES.items():
        rng = np.random.default_rng(args.seed)
        pbrdf_cl.fit(problem(rng, ti, tr)[1], engine=engine)  # build the kernels outside the timing
        rows = []
        for i in range(args.problems):
            truth, meas = problem(rng, ti, tr)
            t = time.perf_counter()
            r = pbrdf_cl.fit(meas, engine=engine)
            sec = time.perf_counter() - t
            row = dict(truth=truth, x={n: r.x[n] for n in NAMES}, sse=r.chi2, seconds=sec,
                       covered={n: bool(r.ci95[n][0] <= truth[n] <= r.ci95[n][1]) for n in NAMES},
                       width={n: (r.ci95[n][1] - r.ci95[n][0]) / (HI[j] - LO[j]) for j, n in enumerate(NAMES)},
                       methods={"pbrdf_cl.fit": (r.chi2, sec)})
            row["methods"][ORACLE] = oracle(meas, truth)
            if i < args.baseline_problems:
                row["methods"].update(baselines(meas, rng, *((4, 3) if args.quick else ())))
            rows.append(row)
            if args.progress:
                print(f"  problem {i + 1}/{args.problems}: fit {sec:.2f} s", flush=True)
        # "optimum found": within 1e-6 relative of the best SSE any method found on that problem
        nb = min(args.baseline_problems, args.problems)
        summary = {}
        for m in rows[0]["methods"]:
            mine = [r for r in rows if m in r["methods"]]
            found = [r["methods"][m][0] <= min(v[0] for v in r["methods"].values()) * (1 + 1e-6) for r in mine]
            summary[m] = dict(problems=len(mine), optimum_found=float(np.mean(found)),
                              median_seconds=float(np.median([r["methods"][m][1] for r in mine])),
                              missed=[i for i, (r, f) in enumerate(zip(mine, found)) if not f])
        fit = summary["pbrdf_cl.fit"]  # it ran on every problem: its misses index rows
        fit["optimum_found_where_baselines_ran"] = (1 - sum(i < nb for i in fit["missed"]) / nb) if nb else float("nan")
        coverage = {n: float(np.mean([r["covered"][n] for r in rows])) for n in NAMES}
        width = {n: float(np.mean([r["width"][n] for r in rows])) for n in NAMES}
        rel_err = {n: float(np.median([abs(r["x"][n] - r["truth"][n]) / max(abs(r["truth"][n]), 1e-12) for r in rows]))
                   for n in ("n", "k")}
        report[gname] = dict(summary=summary, coverage_95=coverage, mean_width_over_bounds=width,
                             median_rel_err=rel_err, problems=len(rows))
        print(f"\n{gname}")
        print(f"  {'method':44s} {'problems':>8s} {'optimum found':>14s} {'median s':>9s}")
        for m, s in summary.items():
            print(f"  {m:44s} {s['problems']:8d} {s['optimum_found']:13.1%} {s['median_seconds']:9.3f}")
        print(f"  pbrdf_cl.fit on the {nb} problems where the baselines ran: "
              f"{summary['pbrdf_cl.fit']['optimum_found_where_baselines_ran']:.1%} optimum found")
        print(f"  pbrdf_cl.fit over {len(rows)} problems: median {summary['pbrdf_cl.fit']['median_seconds']:.3f} s; "
              "95% interval coverage " + ", ".join(f"{n} {c:.0%}" for n, c in coverage.items()))
        print("  mean 95% interval width / bound range: " + ", ".join(f"{n} {w:.2f}" for n, w in width.items()))
        print("  median relative error at the optimum: " + ", ".join(f"{n} {v:.0%}" for n, v in rel_err.items()))
    with open(args.json, "w") as fh:
        json.dump(report, fh, indent=2)
    print(f"\nwrote {args.json}")


if __name__ == "__main__":
    main()
