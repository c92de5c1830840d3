#!/usr/bin/env python3
"""Benchmark of pbrdf_cl.fit on polarimetric data (issue #36): per instrument, on random materials.

Instruments (what is measured at each geometry, noise 0.005 on each normalised quantity, given as
<name>_std; the data made with the float64 numpy reference and Gaussian noise):

- ``dop``: the DOP under unpolarised light (the paper's experiment);
- ``camera45``: s1, s2 with a linear polarization camera, the source polarized at 45 degrees;
- ``camera4``: s1, s2 under four linear source states (0, 45, 90, 135 degrees) and circular;
- ``mueller``: the 15 Mueller elements normalised by M00.

Geometries: the paper's 30 in-plane ones (theta_i 30/40/50 x theta_r 20..65 step 5, phi 180), or
the same out of plane (phi 150; ``--phi``).  Materials: n U(1.2, 3), k U(0.05, 5), sigma U(0.15, 0.8),
ks 1, kd U(0, 0.5), c U(-0.95, -0.05).

Printed per instrument:
- the share of fits at the best chi^2 of a brute-force multi-start (scipy least_squares on the same
  weighted residuals from --starts random starts and from the truth), within 1e-6 relative plus
  1e-6 absolute;
- the coverage of the 95% intervals of n, k, sigma, kd, c (pooled, and of n and k);
- the median 95% widths of n and k, and their median ratio to the DOP fit's on the same material and
  geometries (the ``dop`` instrument's fit);
- the median wall time of a fit against the DOP fit's (warm: the programs built before).
"""
import argparse
import json
import time

import numpy as np
from scipy.optimize import least_squares

import pbrdf_cl
from pbrdf_cl.fitting.channels import ChannelModel
from pbrdf_cl.fitting.sample.polarimetric import ChannelResiduals, channel_stds
from pbrdf_cl.io.measurements import as_measurements

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
NOISE = 0.005
FREE = ("n", "k", "sigma", "kd", "c")
LO = np.array([1.0, 0.0, 0.05, 0.0, -1.0])
HI = np.array([5.0, 10.0, 1.0, 5.0, 0.0])
#: The source states (normalised incident Stokes vectors) of each camera instrument.
STATES = {"camera45": [(0, 1, 0)], "camera4": [(1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0), (0, 0, 1)]}
INSTRUMENTS = ("dop", "camera45", "camera4", "mueller")


def material(rng):
    return dict(n=rng.uniform(1.2, 3.0), k=rng.uniform(0.05, 5.0), sigma=rng.uniform(0.15, 0.8), ks=1.0,
                kd=rng.uniform(0.0, 0.5), c=rng.uniform(-0.95, -0.05))


def data(instrument, truth, phi, rng):
    """The measurements of ``instrument`` at the paper's geometries (azimuth ``phi``), with noise."""
    geo = dict(theta_i=TI, theta_r=TR, phi=phi)
    if instrument == "dop":
        d = pbrdf_cl.dop(TI, TR, phi, **truth, backend="numpy") + rng.normal(0, NOISE, TI.size)
        return dict(geo, dop=d, dop_std=np.full(TI.size, NOISE))
    if instrument == "mueller":
        M = pbrdf_cl.mueller(TI, TR, phi, **truth, backend="numpy")
        cols = {f"m{i}{j}": M[:, i, j] / M[:, 0, 0] + rng.normal(0, NOISE, TI.size)
                for i in range(4) for j in range(4) if i or j}
        return dict(geo, **cols, **{f"{k}_std": np.full(TI.size, NOISE) for k in cols})
    rows = []
    for state in STATES[instrument]:
        S = pbrdf_cl.stokes(TI, TR, phi, **truth, incident=state, backend="numpy")
        rows.append(dict(theta_i=TI, theta_r=TR, phi=np.full(TI.size, phi),
                         s1=S[:, 1] / S[:, 0] + rng.normal(0, NOISE, TI.size),
                         s2=S[:, 2] / S[:, 0] + rng.normal(0, NOISE, TI.size),
                         in_s1=np.full(TI.size, state[0]), in_s2=np.full(TI.size, state[1]),
                         in_s3=np.full(TI.size, state[2])))
    out = {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}
    return dict(out, s1_std=np.full(out["s1"].size, NOISE), s2_std=np.full(out["s1"].size, NOISE))


def brute_force(d, truth, rng, starts):
    """The best chi^2 of scipy least_squares on the fit's weighted residuals, from the truth and
    ``starts`` random starts."""
    meas = as_measurements(d)
    ch = meas.channels()
    std, _ = channel_stds(ch, "bench")
    resid = ChannelResiduals(ChannelModel(ch, "paper"), FREE, {"ks": 1.0}, std)
    x_truth = np.array([truth[p] for p in FREE])
    best = np.inf
    for x0 in [np.clip(x_truth, LO, HI)] + [LO + rng.random(LO.size) * (HI - LO) for _ in range(starts)]:
        r = least_squares(lambda x: resid.rows(x[None])[0], x0, bounds=(LO, HI), x_scale=HI - LO, ftol=1e-12,
                          xtol=1e-12, gtol=1e-12, max_nfev=2000)
        best = min(best, 2 * r.cost)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--materials", type=int, default=40)
    ap.add_argument("--starts", type=int, default=24, help="random starts of the brute-force multi-start")
    ap.add_argument("--instruments", default=",".join(INSTRUMENTS[1:]),
                    help="comma-separated, of " + ", ".join(INSTRUMENTS[1:]) + " (the DOP fit always runs)")
    ap.add_argument("--phi", type=float, default=180.0, help="the azimuth of every geometry (180: in plane)")
    ap.add_argument("--seed", type=int, default=36)
    ap.add_argument("--json", metavar="OUT", help="write the per-material records as JSON")
    args = ap.parse_args()
    instruments = [s.strip() for s in args.instruments.split(",") if s.strip()]
    unknown = [s for s in instruments if s not in INSTRUMENTS[1:]]
    if unknown:
        ap.error(f"unknown instrument {unknown[0]!r}; choose from {', '.join(INSTRUMENTS[1:])}")
    rng = np.random.default_rng(args.seed)
    warm = rng.bit_generator.state
    for inst in ("dop", *instruments):  # build the programs before timing
        pbrdf_cl.fit(data(inst, material(rng), args.phi, rng))
    rng.bit_generator.state = warm
    records = []
    for i in range(args.materials):
        truth = material(rng)
        rec = dict(truth=truth)
        for inst in ("dop", *instruments):
            d = data(inst, truth, args.phi, rng)
            t = time.perf_counter()
            r = pbrdf_cl.fit(d)
            seconds = time.perf_counter() - t
            rec[inst] = dict(seconds=seconds, chi2=r.chi2, x={p: r.x[p] for p in FREE},
                             ci95={p: list(r.ci95[p]) for p in FREE},
                             covered={p: bool(r.ci95[p][0] <= truth[p] <= r.ci95[p][1]) for p in FREE})
            if inst != "dop":
                best = brute_force(d, truth, rng, args.starts)
                rec[inst]["best_chi2"] = best
                rec[inst]["at_best"] = bool(r.chi2 <= best * (1 + 1e-6) + 1e-6)
        records.append(rec)
        print(f"material {i + 1}/{args.materials}: " + ", ".join(
            f"{inst} {rec[inst]['seconds']:.2f} s" + (f" {'ok' if rec[inst]['at_best'] else 'MISS'}"
                                                      if inst != "dop" else "")
            for inst in ("dop", *instruments)), flush=True)
    print(f"\n{args.materials} materials, phi = {args.phi:g}, noise {NOISE} (std given), {args.starts} random starts "
          "+ the truth in the multi-start\n")
    print(f"{'instrument':10s} {'at best':>9s} {'coverage':>9s} {'cov n,k':>8s} {'width n':>9s} {'width k':>9s} "
          f"{'n vs DOP':>9s} {'k vs DOP':>9s} {'time':>7s} {'vs DOP':>7s}")
    t_dop = np.median([r["dop"]["seconds"] for r in records])
    for inst in ("dop", *instruments):
        rs = [r[inst] for r in records]
        cov = np.mean([c for r in rs for c in r["covered"].values()])
        cov_nk = np.mean([r["covered"][p] for r in rs for p in ("n", "k")])
        width = {p: [r["ci95"][p][1] - r["ci95"][p][0] for r in rs] for p in ("n", "k")}
        ratio = {p: np.median([(r[inst]["ci95"][p][1] - r[inst]["ci95"][p][0]) /
                               (r["dop"]["ci95"][p][1] - r["dop"]["ci95"][p][0]) for r in records])
                 for p in ("n", "k")}
        at_best = f"{sum(r['at_best'] for r in rs)}/{len(rs)}" if inst != "dop" else "-"
        t = np.median([r["seconds"] for r in rs])
        print(f"{inst:10s} {at_best:>9s} {cov:9.1%} {cov_nk:8.1%} {np.median(width['n']):9.4g} "
              f"{np.median(width['k']):9.4g} {ratio['n']:9.3g} {ratio['k']:9.3g} {t:6.2f}s {t / t_dop:6.2f}x")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(args=vars(args), records=records), fh, indent=1)
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
