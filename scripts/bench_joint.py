#!/usr/bin/env python3
"""Benchmark of pbrdf_cl.fit_joint (issue #28): three sets sharing sigma and c, on random problems.

Problems: one sample at three "wavelengths": sigma and c drawn once, n, k and kd/ks drawn per set,
all uniform inside the default bounds (n [1, 5], k [0, 10], sigma [0.05, 1], kd/ks [0, 5],
c [-1, 0]), ks = 1; the paper's geometry per set (theta_i 30/40/50 x theta_r 20..65, 30 points);
Gaussian DOP noise of std 0.003, given as dop_std.  The data are made with the numpy reference.

Printed:
- the fraction of problems where fit_joint reaches the best joint SSE found by a brute-force
  multi-start (scipy least_squares on the stacked residuals from --starts random starts, and from
  the truth), within 1e-6 relative (plus 1e-6 absolute, in units of chi^2);
- the coverage of the 95% intervals, pooled over every fitted parameter of every set;
- the median ratio of the joint to the separate 95% widths of n and k;
- the median wall time of a three-set joint fit against one single fit (pbrdf_cl.fit of one set).
"""
import argparse
import time

import numpy as np

import pbrdf_cl
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.fitting.sets import joint
from pbrdf_cl.io.measurements import from_arrays

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
NOISE = 0.003
SETS = ("a", "b", "c")
B = fit_setup.DEFAULT_BOUNDS


def uniform(rng, name):
    return B[name][0] + rng.random() * (B[name][1] - B[name][0])


def problem(rng):
    geo = {p: uniform(rng, p) for p in ("sigma", "c")}
    truths, sets = {}, {}
    for s in SETS:
        truths[s] = {**{p: uniform(rng, p) for p in ("n", "k", "kd")}, **geo}
        d = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", ks=1.0, **truths[s])
        d = np.clip(d + rng.normal(0, NOISE, d.size), 0, 1)
        sets[s] = from_arrays(TI, TR, d, 180.0, np.full(d.size, NOISE))
    return truths, sets


def brute_force(sets, truths, rng, starts):
    """The best joint objective (chi^2) of scipy least_squares from ``starts`` random starts and
    from the truth, on the stacked residuals."""
    from scipy.optimize import least_squares
    setup = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    lo, hi = setup.lo, setup.hi
    labels = setup.labels
    truth = np.array([truths[SETS[0]][p] if "[" not in p else truths[p[p.index("[") + 1:-1]][p[:p.index("[")]]
                      for p in labels])
    x0s = [np.clip(truth, lo, hi)] + [lo + rng.random(lo.size) * (hi - lo) for _ in range(starts)]
    best = np.inf
    for x0 in x0s:
        r = least_squares(lambda x: resid.rows(x[None])[0], x0, bounds=(lo, hi), x_scale=hi - lo, ftol=1e-12,
                          xtol=1e-12, gtol=1e-12, max_nfev=2000)
        best = min(best, 2 * r.cost)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=30)
    ap.add_argument("--starts", type=int, default=24, help="random starts of the brute-force multi-start")
    ap.add_argument("--seed", type=int, default=2028)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=np.full(TI.size, 0.1)))  # warm the device's programs
    reached, covered, ratios, t_joint, t_single = [], [], [], [], []
    for i in range(args.problems):
        truths, sets = problem(rng)
        t = time.perf_counter()
        res = pbrdf_cl.fit_joint(sets)
        t_joint.append(time.perf_counter() - t)
        t = time.perf_counter()
        pbrdf_cl.fit(sets[SETS[0]])
        t_single.append(time.perf_counter() - t)
        best = brute_force(sets, truths, rng, args.starts)
        ok = res.chi2 <= best * (1 + 1e-6) + 1e-6
        reached.append(ok)
        for s in SETS:
            for p, (lo, hi) in res.ci95[s].items():
                if p in res.shared and s != SETS[0]:
                    continue  # a shared parameter counts once
                covered.append(lo <= truths[s][p] <= hi)
            ratios += [res.width_ratio[s][p] for p in ("n", "k") if p in res.width_ratio[s]]
        print(f"problem {i:3d}: joint chi2 {res.chi2:12.8g}, multi-start best {best:12.8g} "
              f"{'ok' if ok else 'MISSED'}; {t_joint[-1]:.2f} s joint, {t_single[-1]:.2f} s single; covered so far "
              f"{sum(covered)}/{len(covered)}", flush=True)
    print()
    print(f"problems: {args.problems} (three sets sharing sigma and c, noise {NOISE} with dop_std, "
          f"{args.starts} random starts + the truth for the multi-start)")
    print(f"fit_joint reaches the best multi-start SSE: {np.mean(reached):.1%} ({sum(reached)}/{len(reached)})")
    print(f"95% interval coverage, pooled over parameters: {np.mean(covered):.1%} ({sum(covered)}/{len(covered)})")
    print(f"median joint/separate 95% width ratio, n and k: {np.median(ratios):.3f} "
          f"(n: {np.median(ratios[0::2]):.3f}, k: {np.median(ratios[1::2]):.3f})")
    print(f"time: three-set joint fit median {np.median(t_joint):.2f} s, one single fit median "
          f"{np.median(t_single):.2f} s, ratio of medians {np.median(t_joint) / np.median(t_single):.2f} "
          f"(median of per-problem ratios {np.median(np.array(t_joint) / np.array(t_single)):.2f})")


if __name__ == "__main__":
    main()
