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

import numpy as np

import pbrdf_cl
from pbrdf_cl.io import imagestack


def default_check_pixels(size):
    """A handful of (y, x) pixels spanning both materials and the roughness gradient.

    Parameters
    ----------
    size : int
        Pixels along each side of the stack.

    Returns
    -------
    list of (int, int)
        On the middle row: metal at the left and right edges (lowest and highest sigma), the
        dielectric disc at its left, centre and right; metal near the top-left and bottom-right
        corners.

    Examples
    --------
    >>> default_check_pixels(32)[:2]
    [(16, 1), (16, 30)]
    """
    size = int(size)
    mid, last = size // 2, size - 1
    frac = lambda f: min(last, max(0, int(round(f * last))))   # noqa: E731
    return [(mid, frac(0.03)), (mid, frac(0.97)), (frac(0.06), frac(0.06)), (frac(0.94), frac(0.94)),
            (mid, frac(0.28)), (mid, mid), (mid, frac(0.72))]   # the disc spans x = 0.2..0.8 of the side


def check_pixels(ds, pixels=None, **fit_kw):
    """Fit single pixels of a stack with :func:`pbrdf_cl.fit` and compare with the truth maps.

    A check that the stack's geometry determines the parameters at its noise, not a batch fit
    (``--check``).

    Parameters
    ----------
    ds : xarray.Dataset
        A stack with per-pixel ``theta_i``, ``theta_r``, ``phi``, ``dop``, ``dop_std`` and the
        ``true_*`` maps (:func:`pbrdf_cl.io.imagestack.synthetic_stack`).
    pixels : sequence of (int, int), optional
        (y, x) indices; default :func:`default_check_pixels`.
    **fit_kw
        Passed to :func:`pbrdf_cl.fit` (``backend="numpy"``, ``bounds=...``).

    Returns
    -------
    list of dict
        One per pixel: ``y``, ``x``, ``material``, and for each of ``imagestack.FIT_PARAMETERS`` its
        ``true``, ``fit``, ``stderr`` and ``ci95`` in a dict under the parameter's name, plus
        ``reduced_chi2`` and ``seconds``.

    Examples
    --------
    >>> rows = check_pixels(synthetic_stack(32), [(16, 16)], backend="numpy")  # doctest: +SKIP
    >>> rows[0]["sigma"]["stderr"]  # doctest: +SKIP
    """
    import time
    import warnings

    pixels = default_check_pixels(ds.sizes["x"]) if pixels is None else pixels
    rows = []
    for y, x in pixels:
        p = ds.isel(y=y, x=x)
        data = {v: np.asarray(p[v].values) for v in ("theta_i", "theta_r", "phi", "dop", "dop_std") if v in p}
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # ignored columns, no-device notes: not the point here
            res = pbrdf_cl.fit(data, **fit_kw)
        row = {"y": int(y), "x": int(x), "material": int(p["material"]) if "material" in p else None,
               "reduced_chi2": float(res.reduced_chi2), "seconds": time.perf_counter() - t0}
        for name in imagestack.FIT_PARAMETERS:
            row[name] = {"true": float(p[f"true_{name}"]), "fit": float(res.x[name]),
                         "stderr": float(res.stderr[name]), "ci95": tuple(float(v) for v in res.ci95[name])}
        rows.append(row)
    return rows


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
        for row in check_pixels(ds, backend="numpy"):
            print(f"pixel (y={row['y']}, x={row['x']}) material {row['material']}, reduced chi2 "
                  f"{row['reduced_chi2']:.2f}, {row['seconds']:.1f} s")
            for name in imagestack.FIT_PARAMETERS:
                r = row[name]
                print(f"  {name:5s} true {r['true']:7.4f}  fit {r['fit']:7.4f}  stderr {r['stderr']:9.3g}  "
                      f"95% [{r['ci95'][0]:.4g}, {r['ci95'][1]:.4g}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
