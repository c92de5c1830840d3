"""Check pbrdf_cl.design against pbrdf_cl.fit: predicted vs fitted 95% interval widths.

For the paper's material (its fit at theta_i = 40, SPEC.md) and DOP noise 0.005: design 30
measurements for the target n, k from a 5-degree candidate grid; simulate ``--sets`` noisy data
sets at the chosen geometries and at the paper's (theta_i 30/40/50 x theta_r 20..65 step 5, 30
points), fit each with :func:`pbrdf_cl.fit` (dop_std given) and compare each parameter's
predicted width with the fit's ``ci95_jacobian`` width.

    python scripts/check_design.py [--sets 100] [--noise 0.005] [--n 30] [--seed 1] [--json out.json]

Prints the median ratio predicted / fitted width per parameter (the target is 0.75-1.33) and the
median fitted n and k widths at the chosen geometries and at the paper's.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

import pbrdf_cl
from pbrdf_cl.analysis.designs import PAPER_MATERIAL


def simulate_and_fit(geo, material, noise, sets, rng, engine):
    """Fitted ci95_jacobian widths (sets, free) and the fits' free names at geometry ``geo``."""
    truth = pbrdf_cl.dop(geo["theta_i"], geo["theta_r"], geo["phi"], **material, dtype="float64", backend="numpy")
    widths, names, xs = [], None, []
    for _ in range(sets):
        dop = truth + noise * rng.standard_normal(truth.shape)
        data = dict(theta_i=geo["theta_i"], theta_r=geo["theta_r"], phi=geo["phi"], dop=dop,
                    dop_std=np.full(dop.shape, noise))
        r = pbrdf_cl.fit(data, engine=engine)
        names = r.free
        widths.append([r.ci95_jacobian[n][1] - r.ci95_jacobian[n][0] for n in names])
        xs.append([r.x[n] / (r.x["ks"] if n == "kd" else 1.0) for n in names])
    return np.array(widths), list(names), np.array(xs)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", type=int, default=100, help="simulated data sets per geometry")
    ap.add_argument("--noise", type=float, default=0.005, help="DOP noise standard deviation")
    ap.add_argument("--n", type=int, default=30, help="measurements to design")
    ap.add_argument("--seed", type=int, default=1, help="seed of the simulated noise")
    ap.add_argument("--json", metavar="OUT", help="also write the numbers as JSON")
    args = ap.parse_args(argv)
    from pbrdf_cl.outputs import check_json
    check_json("--json", args.json, "check_design")  # before the work, not after it
    t0 = time.perf_counter()
    engine = pbrdf_cl.get_default_engine()
    d = pbrdf_cl.design(PAPER_MATERIAL, candidates={"theta_i": "10:80:5", "theta_r": "0:85:5", "phi": 180},
                        noise=args.noise, n_measurements=args.n, target=("n", "k"), engine=engine)
    t_design = time.perf_counter() - t0
    print(d.summary())
    print()
    rng = np.random.default_rng(args.seed)
    chosen = dict(theta_i=d.theta_i, theta_r=d.theta_r, phi=d.phi)
    out = dict(material=PAPER_MATERIAL, noise=args.noise, n_measurements=args.n, sets=args.sets,
               design_seconds=t_design, predicted_chosen=d.ci95_width, predicted_paper=d.ci95_width_reference)
    for key, geo, pred in (("chosen", chosen, d.ci95_width), ("paper", d.reference, d.ci95_width_reference)):
        t1 = time.perf_counter()
        W, names, X = simulate_and_fit(geo, PAPER_MATERIAL, args.noise, args.sets, rng, engine)
        ratio = np.array([pred[n] for n in names])[None, :] / W
        med = dict(zip(names, map(float, np.median(ratio, axis=0))))
        fitted = dict(zip(names, map(float, np.median(W, axis=0))))
        out[key] = dict(median_ratio=med, median_fitted_width=fitted, points=int(len(geo["theta_i"])),
                        seconds=time.perf_counter() - t1,
                        ratio_quartiles={n: list(map(float, np.percentile(ratio[:, j], [25, 75])))
                                         for j, n in enumerate(names)})
        print(f"{key} geometry ({len(geo['theta_i'])} points, {args.sets} data sets, "
              f"{out[key]['seconds']:.1f} s of fits):")
        print("  parameter   predicted  median fitted  median ratio (predicted/fitted)")
        for n in names:
            print(f"  {n:<9s} {pred[n]:>10.4g} {fitted[n]:>14.4g} {med[n]:>10.3f}")
    ok = all(0.75 <= v <= 1.33 for v in out["chosen"]["median_ratio"].values())
    out["chosen_ratios_within"] = ok
    print()
    print(f"median ratio at the chosen geometries within 0.75-1.33 for every parameter: {ok}")
    for n in ("n", "k"):
        print(f"median fitted {n} width: chosen {out['chosen']['median_fitted_width'][n]:.4g} vs paper "
              f"{out['paper']['median_fitted_width'][n]:.4g} "
              f"({out['paper']['median_fitted_width'][n] / out['chosen']['median_fitted_width'][n]:.1f}x narrower)")
    out["seconds"] = time.perf_counter() - t0
    print(f"time: design {t_design:.2f} s, total {out['seconds']:.1f} s")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)
        print(f"wrote {args.json}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
