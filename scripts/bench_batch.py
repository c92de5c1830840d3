#!/usr/bin/env python3
"""Benchmark of the per-pixel inversion of image stacks, pbrdf_cl.fit_batch (issue targets).

One run prints, on the default device (or --backend numpy):

1. Rate with shared geometry (the paper's 30 measurements per pixel; --pixels random pixels,
   parameters uniform in the default bounds, DOP noise 0.002 given as dop_std): end-to-end
   pixels/s of fit_batch (input arrays to result Dataset), its stages' shares, and the rate of
   pbrdf_cl.fit looped over --loop-pixels of the same pixels in the same run, and the ratio.
2. Rate with per-pixel geometry: the synthetic camera stack of pbrdf_cl.io.imagestack
   (--stack-size squared pixels, 30 light positions).
3. SSE agreement: on --match random pixels in each of two geometries (the paper's; one incidence
   angle, 45 degrees, theta_r 5..80 in 30 steps), the share of pixels where fit_batch's SSE
   reaches pbrdf_cl.fit's (within 1e-6 relative, or lower).  Slow: pbrdf_cl.fit takes ~0.5 s
   per pixel on 2 cores.
4. Coverage: on the synthetic stack (--coverage-size squared pixels), the share of pixels whose
   95% interval contains the truth, per parameter.
5. Memory: the peak of host allocations (tracemalloc) of fit_batch at a fixed memory_budget for
   two image sizes.
6. A polarization camera under a 45-degree source: s1, s2 (noise 0.002 given) of --camera-size
   squared random pixels (parameters uniform in the default bounds) at the paper's geometry, and
   the DOP of the same pixels and geometry: pixels/s of each, their stages' shares and the ratio.
7. Profile per driver: the rate of section 1 (--profile-pixels) on every usable OpenCL CPU device
   (or --profile-devices) with a profiling queue: device seconds per kernel and launches, and the
   host's share (wall time less the kernels': Python, numpy, transfers).

    python scripts/bench_batch.py                       # everything (about 15 min on 2 cores)
    python scripts/bench_batch.py --match 0 --coverage-size 64   # a quick look
    python scripts/bench_batch.py --only camera --camera-size 32 --repeats 3   # the camera's rate only
"""
import argparse
import time
import tracemalloc

import numpy as np

import pbrdf_cl
from pbrdf_cl.device.engine import Engine, NumpyEngine
from pbrdf_cl.fitting.images import corners, pixel_fit
from pbrdf_cl.fitting.images.dataset import PIXEL_STATUS
from pbrdf_cl.fitting.setup import DEFAULT_BOUNDS
from pbrdf_cl.io import imagestack

NAMES = ("n", "k", "sigma", "kd", "c")
LO = np.array([DEFAULT_BOUNDS[n][0] for n in NAMES])
HI = np.array([DEFAULT_BOUNDS[n][1] for n in NAMES])
NOISE = 0.002
GEOMETRIES = {
    "paper (theta_i 30/40/50 x theta_r 20..65)": (np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)),
    "one incidence (theta_i 45, theta_r 5..80)": (np.full(30, 45.0), np.linspace(5.0, 80.0, 30)),
}


def pixels(n, ti, tr, seed):
    rng = np.random.default_rng(seed)
    x = LO + rng.random((n, 5)) * (HI - LO)
    truth = {name: x[:, j:j + 1] for j, name in enumerate(NAMES)}
    d = pbrdf_cl.dop(ti, tr, backend="numpy", **truth)
    return np.clip(d + rng.normal(0, NOISE, d.shape), 0, 1)


class StageClock:
    """Wall time spent in the stages of an image fit (wrapped for the run): the grid and the descents
    run through the engine (the operations ``batch_grid`` and ``batch_lm``) or the device's descent
    called directly (``device_lm`` in pbrdf_cl.fitting.images.pixel_fit and .corners), and the statistics."""

    OPERATIONS = {"batch_grid": "grid", "batch_lm": "descent"}
    FUNCTIONS = {(pixel_fit, "device_lm"): "descent", (corners, "device_lm"): "descent",
                 (pixel_fit, "statistics"): "statistics"}

    def __init__(self):
        self.seconds = dict.fromkeys(("grid", "descent", "statistics"), 0.0)
        self.saved = []

    def _timed(self, func, stage):
        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return func(*a, **k)
            finally:
                self.seconds[stage] += time.perf_counter() - t0
        return timed

    def __enter__(self):
        for (module, name), stage in self.FUNCTIONS.items():
            func = getattr(module, name)
            self.saved.append((module, name, func))
            setattr(module, name, self._timed(func, stage))
        for cls in (Engine, NumpyEngine):
            self.saved.append((cls, "call", cls.call))

            def call(eng, operation, *a, _call=cls.call, **k):
                stage = self.OPERATIONS.get(operation)
                if stage is None:
                    return _call(eng, operation, *a, **k)
                return self._timed(_call, stage)(eng, operation, *a, **k)
            cls.call = call
        return self

    def __exit__(self, *exc):
        for owner, name, func in reversed(self.saved):
            setattr(owner, name, func)


class KernelClock:
    """Device time per kernel of a run on a profiling engine (``Engine(..., profiling=True)``):
    every launch's event is kept and its start-to-end time added to its kernel's name, with the
    launches counted, so that the device time of each program and the host time (the wall time
    less the kernels') can be printed per driver."""

    def __init__(self, eng):
        self.eng, self.events, self.saved = eng, [], None

    def __enter__(self):
        self.saved = launch = self.eng.launch

        def timed(kernel, *a, **k):
            ev = launch(kernel, *a, **k)
            self.events.append((kernel.function_name, ev))
            return ev
        self.eng.launch = timed
        return self

    def __exit__(self, *exc):
        self.eng.launch = self.saved
        self.eng.queue.finish()

    def seconds(self):
        """Kernel name -> (launches, device seconds), largest first."""
        out = {}
        for name, ev in self.events:
            n, t = out.get(name, (0, 0.0))
            out[name] = (n + 1, t + (ev.profile.end - ev.profile.start) * 1e-9)
        return dict(sorted(out.items(), key=lambda kv: -kv[1][1]))


def profile(args, eng):
    """Section 7: where an image fit's time goes on each OpenCL device (``--profile-devices``, default
    every usable PoCL CPU device): device time per kernel, and the host's share (wall time less
    the kernels': Python, numpy, transfers, waits)."""
    from pbrdf_cl.device import choice
    ti, tr = GEOMETRIES["paper (theta_i 30/40/50 x theta_r 20..65)"]
    dop = pixels(args.profile_pixels, ti, tr, seed=1)
    data = dict(dop=dop, theta_i=ti, theta_r=tr, dop_std=NOISE)
    devices = args.profile_devices or [d for d in choice.candidates() if d.type & 2 and choice.probe(d).usable]
    for dev in devices:
        peng = Engine(dev, profiling=True)
        pbrdf_cl.fit_batch(dict(dop=dop[:16], theta_i=ti, theta_r=tr, dop_std=NOISE), engine=peng)  # build kernels
        with KernelClock(peng) as clock:
            t0 = time.perf_counter()
            pbrdf_cl.fit_batch(data, engine=peng)
            wall = time.perf_counter() - t0
        kernels = clock.seconds()
        device_s = sum(t for _, t in kernels.values())
        print(f"profile, {peng.description} (vector widths {peng.vector_width}, LM lanes {peng.lm_lanes}): "
              f"{args.profile_pixels} px in {wall:.2f} s = {args.profile_pixels / wall:.0f} px/s; kernels "
              f"{device_s:.2f} s ({device_s / wall:.0%}), host {wall - device_s:.2f} s ({1 - device_s / wall:.0%})")
        for name, (n, t) in kernels.items():
            print(f"    {name:28s} {n:6d} launches {t:8.3f} s  {t / wall:6.1%}")


def rate(args, eng):
    ti, tr = GEOMETRIES["paper (theta_i 30/40/50 x theta_r 20..65)"]
    dop = pixels(args.pixels, ti, tr, seed=1)
    data = dict(dop=dop, theta_i=ti, theta_r=tr, dop_std=NOISE)
    pbrdf_cl.fit_batch(dict(dop=dop[:16], theta_i=ti, theta_r=tr, dop_std=NOISE), engine=eng)  # build kernels
    with StageClock() as clock:
        t0 = time.perf_counter()
        res = pbrdf_cl.fit_batch(data, engine=eng)
        t_batch = time.perf_counter() - t0
    rate_batch = args.pixels / t_batch
    t0 = time.perf_counter()
    for d in dop[:args.loop_pixels]:
        pbrdf_cl.fit(dict(theta_i=ti, theta_r=tr, dop=d, dop_std=np.full(d.size, NOISE)), engine=eng)
    rate_loop = args.loop_pixels / (time.perf_counter() - t0)
    shares = ", ".join(f"{k} {v / t_batch:.0%}" for k, v in clock.seconds.items())
    print(f"shared geometry, 30 measurements: fit_batch {args.pixels} px in {t_batch:.2f} s = {rate_batch:.0f} px/s "
          f"end to end (stages: {shares}); pbrdf_cl.fit looped over {args.loop_pixels} px: {rate_loop:.2f} px/s; "
          f"ratio {rate_batch / rate_loop:.0f}x")
    codes = dict(zip(*np.unique(res.status.values, return_counts=True)))
    print("  status counts:", ", ".join(f"{PIXEL_STATUS[int(c)][0]} {n}" for c, n in codes.items()))


def per_pixel_rate(args, eng):
    ds = imagestack.synthetic_stack(size=args.stack_size, seed=3)
    pbrdf_cl.fit_batch(ds.isel(y=slice(0, 4), x=slice(0, 4)), engine=eng)
    with StageClock() as clock:
        t0 = time.perf_counter()
        pbrdf_cl.fit_batch(ds, engine=eng)
        dt = time.perf_counter() - t0
    n = args.stack_size ** 2
    shares = ", ".join(f"{k} {v / dt:.0%}" for k, v in clock.seconds.items())
    print(f"per-pixel geometry (synthetic camera stack {args.stack_size} x {args.stack_size}, 30 lights): "
          f"{n} px in {dt:.2f} s = {n / dt:.0f} px/s end to end (stages: {shares})")


def match(args, eng):
    for name, (ti, tr) in GEOMETRIES.items():
        dop = pixels(args.match, ti, tr, seed=2)
        res = pbrdf_cl.fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr, dop_std=NOISE), engine=eng)
        single = np.array([pbrdf_cl.fit(dict(theta_i=ti, theta_r=tr, dop=d, dop_std=np.full(d.size, NOISE)),
                                        engine=eng).chi2 for d in dop])
        rel = (res.chi2.values - single) / single
        worse = rel > 1e-6
        print(f"SSE agreement, {name}: fit_batch reaches pbrdf_cl.fit's SSE (1e-6 relative or lower) on "
              f"{1 - worse.mean():.1%} of {args.match} pixels (lower on {np.mean(rel < -1e-6):.1%}); "
              f"where it does not, the median excess is {np.median(rel[worse]) if worse.any() else 0:.1e}")


def coverage(args, eng):
    ds = imagestack.synthetic_stack(size=args.coverage_size, seed=0)
    t0 = time.perf_counter()
    res = pbrdf_cl.fit_batch(ds, engine=eng)
    dt = time.perf_counter() - t0
    fitted = res.status.values >= 0
    parts = []
    for name in NAMES:
        lo, hi = res[f"{name}_ci95"].values[..., 0], res[f"{name}_ci95"].values[..., 1]
        t = ds[f"true_{name}"].values
        parts.append(f"{name} {np.mean(((lo <= t) & (t <= hi))[fitted]):.1%}")
    print(f"coverage of the truth by the 95% intervals, synthetic stack {args.coverage_size} x {args.coverage_size} "
          f"({fitted.sum()} px fitted in {dt:.1f} s): " + ", ".join(parts))


def memory(args, eng):
    out = []
    for size in (32, 96):
        ds = imagestack.synthetic_stack(size=size, seed=4)
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        pbrdf_cl.fit_batch(ds, engine=eng, memory_budget=args.budget)
        peak = tracemalloc.get_traced_memory()[1] - base
        tracemalloc.stop()
        out.append(f"{size} x {size} px: {peak / 2**20:.1f} MiB")
    print(f"peak host allocations of fit_batch at memory_budget={args.budget!r} (tracemalloc, inputs excluded): "
          + ", ".join(out))


def camera_rate(args, eng):
    ti, tr = GEOMETRIES["paper (theta_i 30/40/50 x theta_r 20..65)"]
    n = args.camera_size ** 2
    rng = np.random.default_rng(5)
    x = LO + rng.random((n, 5)) * (HI - LO)
    truth = {name: x[:, j:j + 1] for j, name in enumerate(NAMES)}
    S = pbrdf_cl.stokes(ti, tr, 180.0, backend="numpy", incident=(0.0, 1.0, 0.0), **truth)
    shape = (args.camera_size, args.camera_size, ti.size)
    cam = {f"s{j}": (S[..., j] / S[..., 0] + rng.normal(0, NOISE, S.shape[:-1])).reshape(shape) for j in (1, 2)}
    cam.update(s1_std=NOISE, s2_std=NOISE, theta_i=ti, theta_r=tr, in_s1=np.zeros(ti.size), in_s2=np.ones(ti.size),
               in_s3=np.zeros(ti.size))
    dop = np.clip(pbrdf_cl.dop(ti, tr, backend="numpy", **truth) + rng.normal(0, NOISE, (n, ti.size)), 0, 1)
    stacks = {"camera s1, s2 (45-degree source)": cam,
              "DOP (unpolarised)": dict(dop=dop.reshape(shape), dop_std=NOISE, theta_i=ti, theta_r=tr)}
    rates = {}
    for name, data in stacks.items():
        pbrdf_cl.fit_batch({k: (v[:1] if np.ndim(v) == 3 else v) for k, v in data.items()}, engine=eng)  # build
        best = None
        for _ in range(args.repeats):
            with StageClock() as clock:
                t0 = time.perf_counter()
                pbrdf_cl.fit_batch(data, engine=eng)
                dt = time.perf_counter() - t0
            if best is None or dt < best[0]:
                best = (dt, dict(clock.seconds))
        dt, seconds = best
        rates[name] = n / dt
        shares = ", ".join(f"{k} {v / dt:.0%}" for k, v in seconds.items())
        print(f"{name}, paper geometry, {args.camera_size} x {args.camera_size} random pixels: {n / dt:.0f} px/s "
              f"(best of {args.repeats}; stages: {shares})")
    (a, ra), (b, rb) = rates.items()
    print(f"  the camera's rate is {ra / rb:.2f} of the DOP's")


SECTIONS = ("rate", "per-pixel", "match", "coverage", "memory", "camera", "profile")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pixels", type=int, default=8192)
    ap.add_argument("--loop-pixels", type=int, default=20)
    ap.add_argument("--stack-size", type=int, default=64)
    ap.add_argument("--match", type=int, default=500)
    ap.add_argument("--coverage-size", type=int, default=256)
    ap.add_argument("--budget", default="32 MiB")
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--camera-size", type=int, default=32, help="pixels per side of section 6 (0 skips it)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of section 6, the best counted")
    ap.add_argument("--profile-pixels", type=int, default=4096, help="pixels of section 7, the per-kernel profile")
    ap.add_argument("--profile-devices", nargs="+", help="devices of section 7 (P:D or a name; default every "
                    "usable CPU device)")
    ap.add_argument("--only", nargs="+", choices=SECTIONS, help="run only these sections")
    args = ap.parse_args()
    eng = pbrdf_cl.device.engine.resolve_engine(None, args.backend)
    print("device:", getattr(eng, "description", "numpy"))
    run = set(args.only or SECTIONS)
    if "rate" in run:
        rate(args, eng)
    if "per-pixel" in run:
        per_pixel_rate(args, eng)
    if args.match and "match" in run:
        match(args, eng)
    if args.coverage_size and "coverage" in run:
        coverage(args, eng)
    if "memory" in run:
        memory(args, eng)
    if args.camera_size and "camera" in run:
        camera_rate(args, eng)
    if args.profile_pixels and "profile" in run:
        profile(args, eng)


if __name__ == "__main__":
    main()
