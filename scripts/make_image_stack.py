#!/usr/bin/env python3
"""Write a synthetic image stack to NetCDF or .npz, the truth maps in the file: a DOP stack
(pbrdf_cl.io.imagestack.synthetic_stack: two materials, a roughness gradient, a fixed camera and a
point light over M positions) or, with ``--source 45`` or ``--source four``, a linear polarization
camera's s1, s2 under a polarized source at the paper's 30 geometries
(pbrdf_cl.io.imagestack.polarimetric_stack: at 45 degrees, or linear at 0, 45, 90 degrees and
circular).  ``--check`` also fits a few pixels of a DOP stack one by one and prints the standard
errors.  Example: ``python scripts/make_image_stack.py --size 256 --out stack.nc``."""
import argparse
import sys
import time
from pathlib import Path

from pbrdf_cl.io import imagestack


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256, help="pixels along each side (default 256)")
    ap.add_argument("--lights", type=int, default=30, help="light positions M (default 30)")
    ap.add_argument("--noise", type=float, default=0.005, help="std of the Gaussian DOP noise (default 0.005)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise (default 0)")
    ap.add_argument("--out", default="stack.nc", help="output file, .nc or .npz (default stack.nc)")
    ap.add_argument("--source", choices=("unpolarised", "45", "four"), default="unpolarised",
                    help="the source: unpolarised (a DOP stack, default), polarized at 45 degrees or in four states "
                    "(an s1, s2 stack; --lights is then not used)")
    ap.add_argument("--check", action="store_true",
                    help="fit a few pixels with pbrdf_cl.fit and print truth, fit, stderr and 95%% interval")
    args = ap.parse_args(argv)
    if Path(args.out).suffix not in (".nc", ".npz"):  # refused before the rendering, not after it
        print(f"make_image_stack: --out {args.out}: write the stack as .nc (NetCDF) or .npz", file=sys.stderr)
        return 2
    if args.check and args.source != "unpolarised":
        print("make_image_stack: --check fits a DOP stack's pixels; leave it out with --source", file=sys.stderr)
        return 2
    try:
        t0 = time.perf_counter()
        if args.source == "unpolarised":
            ds = imagestack.synthetic_stack(args.size, n_lights=args.lights, noise=args.noise, seed=args.seed)
        else:
            states = imagestack.SOURCE_45 if args.source == "45" else imagestack.SOURCE_FOUR
            ds = imagestack.polarimetric_stack(args.size, states, noise=args.noise, seed=args.seed)
        seconds = time.perf_counter() - t0
        path = imagestack.save_stack(ds, args.out)
    except ValueError as e:
        print(f"make_image_stack: {e}", file=sys.stderr)
        return 2
    if args.source != "unpolarised":
        print(f"{path}: s1, s2 {dict(ds.s1.sizes)} under {len(ds.attrs['states'].split(';'))} source state(s), noise "
              f"{args.noise}, seed {args.seed}; rendered in {seconds:.1f} s")
        return 0
    print(f"{path}: dop {dict(ds.dop.sizes)}, noise {args.noise}, seed {args.seed}, "
          f"{ds.attrs['clipped']} values clipped to [0, 1]; rendered in {seconds:.1f} s")
    if args.check:
        for row in imagestack.check_pixels(ds, backend="numpy"):
            print(f"pixel (y={row['y']}, x={row['x']}) material {row['material']}, reduced chi2 "
                  f"{row['reduced_chi2']:.2f}, {row['seconds']:.1f} s")
            for name in imagestack.FIT_PARAMETERS:
                r = row[name]
                print(f"  {name:5s} true {r['true']:7.4f}  fit {r['fit']:7.4f}  stderr {r['stderr']:9.3g}  "
                      f"95% [{r['ci95'][0]:.4g}, {r['ci95'][1]:.4g}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
