"""Benchmark of image fits with shared material parameters (issue #28 part 3): a synthetic image of
two materials (n, k shared by the pixels of each; sigma, kd, c per pixel; DOP noise given as
dop_std) fitted with ``fit_batch(labels=L, shared=("n", "k"))`` and with the plain ``fit_batch``.
Prints, per label and parameter, whether the label's 95% interval covers the truth and how much
narrower it is than the median per-pixel interval of the plain fit, and the time of both fits,
wall and CPU of the process and of the children it forked (issue #37's target: labels at most 1.5x
the plain fit at 32x32; the plain fit's kernels run on every core, the label stage's host work on
one, the integrated correction's labels spread over forked processes: ``pbrdf_cl.fitting.processes``).

    python scripts/bench_joint_image.py [--size 16] [--noise 0.003 0.006 0.01] [--seeds 1 2 3 4] [--device skylake]
        [--bias-replicates 4] [--stack halves]

``--stack`` picks the image (issue #37 asks for coverage on stacks unlike the bench's too):
``halves``, the bench's (above: 30 measurements, incidence 30/40/50 degrees); ``thirds``, three
other materials (n, k = 2.2, 3.1 in the left third; 1.5, 0.15 and 1.9, 1.2 in the top and bottom
halves of the rest) with wider own-parameter ranges (sigma 0.2-0.7, kd 0.05-0.4, c -0.6 to -0.05),
21 measurements at incidence 20/45/70 x reflection 10-70 degrees; ``one-angle``, a quarter of the
image (n, k = 1.3, 0.3) inside another material (1.8, 2.6), 12 measurements at one incidence,
45 degrees, reflection 5-75 degrees.

The bias replicates are those of the label stage's parametric bootstrap inverted as a test
(``LabelJob.bias_replicates``, ``label_search.binding_correction``; 0, the default: none).  With
them the label fit runs twice, without and with the bootstrap, and the bootstrap's cost is printed
as the time of the label fit with it over the time without.  Coverage is printed per noise level.
"""
import argparse
import resource
import time

import numpy as np

import pbrdf_cl

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
TRUTH = {1: (1.6, 2.139), 2: (1.4, 0.5)}
OWN = (("sigma", 0.3, 0.6), ("kd", 0.1, 0.3), ("c", -0.5, -0.1))
#: --stack: (incidence, reflection angles (degrees), (n, k) per label, own-parameter ranges)
STACKS = {
    "halves": (TI, TR, TRUTH, OWN),
    "thirds": (np.repeat([20.0, 45.0, 70.0], 7), np.tile(np.arange(10.0, 71.0, 10.0), 3),
               {1: (2.2, 3.1), 2: (1.5, 0.15), 3: (1.9, 1.2)},
               (("sigma", 0.2, 0.7), ("kd", 0.05, 0.4), ("c", -0.6, -0.05))),
    "one-angle": (np.full(12, 45.0), np.linspace(5.0, 75.0, 12), {1: (1.8, 2.6), 2: (1.3, 0.3)},
                  (("sigma", 0.25, 0.55), ("kd", 0.1, 0.35), ("c", -0.5, -0.1))),
}


def label_map(kind, size):
    """The labels of a ``size`` x ``size`` image of ``--stack`` ``kind``."""
    lab = np.ones((size, size), np.int64)
    if kind == "halves":
        lab[:, size // 2:] = 2
    elif kind == "thirds":
        lab[:, size // 3:] = 2
        lab[size // 2:, size // 3:] = 3
    else:
        lab[:size // 2, :size // 2] = 2
    return lab


def stack(size, std, seed, kind="halves"):
    """(data, labels, truth) of a synthetic ``size`` x ``size`` stack of ``--stack`` ``kind`` with
    DOP noise ``std`` (given as dop_std) drawn from ``seed``; truth: (n, k) per label."""
    ti, tr, truth, ranges = STACKS[kind]
    rng = np.random.default_rng(seed)
    lab = label_map(kind, size)
    n, k = (np.choose(lab - 1, [truth[L][i] for L in sorted(truth)])[..., None] for i in (0, 1))
    own = {a: rng.uniform(lo, hi, (size, size, 1)) for a, lo, hi in ranges}
    dop = pbrdf_cl.dop(ti, tr, n=n, k=k, **own, backend="numpy") + rng.normal(0, std, (size, size, ti.size))
    dop = np.abs(dop)  # a measured DOP is a magnitude: noise that would take it below 0 folds back
    return dict(dop=dop, theta_i=ti, theta_r=tr, dop_std=np.full(dop.shape, std)), lab, truth


def cpu():
    """CPU seconds of this process and of its children that have ended (the forked processes of
    ``pbrdf_cl.fitting.processes``)."""
    return sum(u.ru_utime + u.ru_stime for u in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                         resource.RUSAGE_CHILDREN)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=16)
    ap.add_argument("--noise", type=float, nargs="+", default=[0.003, 0.006, 0.01])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--bias-replicates", type=int, default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--stack", choices=sorted(STACKS), default="halves")
    args = ap.parse_args()
    kw = dict(device=args.device) if args.device else {}
    from pbrdf_cl.fitting.images import label_search
    if args.bias_replicates is not None:
        label_search.BOOT_REPLICATES = args.bias_replicates
    data, lab, _ = stack(8, 0.003, 0, args.stack)
    pbrdf_cl.fit_batch(data, labels=lab, **kw)  # kernels built before timing
    covered = total = 0
    ratios, times, costs = [], [], []
    per_noise = {}
    for std in args.noise:
        for seed in args.seeds:
            data, lab, truth = stack(args.size, std, seed, args.stack)
            t0, c0 = time.perf_counter(), cpu()
            plain = pbrdf_cl.fit_batch(data, **kw)
            t1, c1 = time.perf_counter(), cpu()
            res = pbrdf_cl.fit_batch(data, labels=lab, **kw)
            t2, c2 = time.perf_counter(), cpu()
            times.append((t1 - t0, t2 - t1, c1 - c0, c2 - c1))
            if args.bias_replicates:
                label_search.BOOT_REPLICATES = 0
                t3 = time.perf_counter()
                pbrdf_cl.fit_batch(data, labels=lab, **kw)
                costs.append((t2 - t1) / (time.perf_counter() - t3))
                label_search.BOOT_REPLICATES = args.bias_replicates
            print(f"noise {std:g} seed {seed}: plain {t1 - t0:.2f} s, labels {t2 - t1:.2f} s "
                  f"({(t2 - t1) / (t1 - t0):.2f}x; CPU {(c2 - c1) / (c1 - c0):.2f}x), "
                  f"{res.attrs['label_rounds']} refinement passes")
            for j, L in enumerate(sorted(truth)):
                for i, name in enumerate(("n", "k")):
                    lo, hi = res[f"label_{name}_ci95"].values[j]
                    se = float(res[f"label_{name}_stderr"][j])
                    off = (float(res[f"label_{name}"][j]) - truth[L][i]) / se
                    per_pixel = float(np.nanmedian(plain[f"{name}_ci95"].diff("bound").values[lab == L]))
                    ok = lo <= truth[L][i] <= hi
                    covered += ok
                    total += 1
                    per_noise.setdefault(std, []).append(ok)
                    ratios.append(per_pixel / (hi - lo))
                    print(f"  label {L} {name}: {float(res[f'label_{name}'][j]):.4f} [{lo:.4f}, {hi:.4f}] truth "
                          f"{truth[L][i]} {'covered' if ok else 'MISSED'} ({off:+.1f} se); per-pixel median width "
                          f"{per_pixel:.3g}, {per_pixel / (hi - lo):.1f}x narrower; status {int(res.label_status[j])}")
    t = np.array(times)
    for std, oks in per_noise.items():
        print(f"noise {std:g}: {sum(oks)} of {len(oks)} label intervals cover the truth")
    if costs:
        print(f"the bootstrap ({args.bias_replicates} replicates a design point): label fit with it / without: median "
              f"{np.median(costs):.2f}x (min {np.min(costs):.2f}x, max {np.max(costs):.2f}x)")
    print(f"coverage: {covered} of {total} label intervals cover the truth; width ratio median "
          f"{np.median(ratios):.1f}x (min {np.min(ratios):.1f}x); time labels / plain: median "
          f"{np.median(t[:, 1] / t[:, 0]):.2f}x wall, {np.median(t[:, 3] / t[:, 2]):.2f}x CPU "
          f"(target <= 1.5x at 32x32), {args.size}x{args.size} pixels")


if __name__ == "__main__":
    main()
