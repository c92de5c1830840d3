#!/usr/bin/env python3
"""Write the bundled example data (examples/*.csv, *.npz): DOP, and s1, s2 of a polarization camera
under a polarized source, generated from the six-parameter model with stated parameters and
Gaussian noise; each file says so (a CSV in its header, a stack in its attributes)."""
from pathlib import Path

import numpy as np

import pbrdf_cl
from pbrdf_cl.io.measurements import from_arrays, write_csv

OUT = Path(__file__).resolve().parent.parent / "examples"
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)  # the paper's 45# steel fit, 435 nm


def main():
    OUT.mkdir(exist_ok=True)
    rng = np.random.default_rng(20200509)
    ti = np.repeat([30.0, 40.0, 50.0], 10)
    tr = np.tile(np.arange(20.0, 66.0, 5.0), 3)
    noise = 0.002
    dop = pbrdf_cl.dop(ti, tr, 180.0, backend="numpy", **STEEL)
    f00 = pbrdf_cl.brdf(ti, tr, 180.0, backend="numpy", **STEEL)
    meas = from_arrays(ti, tr, np.clip(dop + rng.normal(0, noise, ti.size), 0, 1), 180.0, np.full(ti.size, noise))
    params = ", ".join(f"{k} = {v}" for k, v in STEEL.items())
    write_csv(OUT / "steel_435nm.csv", meas,
              "Synthetic DOP of 45# steel at 435 nm in the paper's geometry (Zhu et al. 2020, Fig. 4):\n"
              "theta_i = 30/40/50 deg, theta_r = 20..65 deg step 5, phi = 180 (in plane).\n"
              f"Generated from the six-parameter model with shadowing 'paper' and {params}\n"
              f"(kd/ks = {STEEL['kd'] / STEEL['ks']:.6g}), plus Gaussian noise of std {noise} (seed 20200509).\n"
              "Written by scripts/make_examples.py.")
    meas = from_arrays(ti, tr, np.clip(dop + rng.normal(0, noise, ti.size), 0, 1), 180.0, np.full(ti.size, noise),
                       f00=f00 * (1 + rng.normal(0, 0.02, ti.size)), f00_std=0.02 * f00)
    write_csv(OUT / "steel_435nm_with_f00.csv", meas,
              "As steel_435nm.csv (same parameters, new DOP noise of std 0.002), plus the BRDF f00 (1/sr)\n"
              "with 2% Gaussian relative noise (f00_std): intensities separate ks and kd, which DOP alone\n"
              "cannot.\n"
              "Written by scripts/make_examples.py.")
    # a small camera stack (per-pixel geometry, two materials, a roughness gradient) for fit-image
    from pbrdf_cl.io import imagestack
    imagestack.save_stack(imagestack.synthetic_stack(size=16, seed=0), OUT / "camera_stack_16.npz")
    # linear-polarization-camera stacks (s1, s2, shared geometry) under a polarized source, noise 0.005: at
    # 45 degrees at the paper's 30 geometries, and under four states (linear at 0, 45, 90 degrees, circular)
    # at every third of them (10: theta_i 30, 40, 50, theta_r 20..65)
    imagestack.save_stack(imagestack.polarimetric_stack(16, imagestack.SOURCE_45, seed=0), OUT / "camera_45deg_16.npz")
    imagestack.save_stack(imagestack.polarimetric_stack(16, imagestack.SOURCE_FOUR, seed=1,
                                                        theta_i=imagestack.PAPER_THETA_I[::3],
                                                        theta_r=imagestack.PAPER_THETA_R[::3]),
                          OUT / "camera_four_states_16.npz")
    camera_csv(ti, tr)


def camera_csv(ti, tr, noise=0.005, seed=20240536):
    """examples/steel_camera_45.csv: what a polarization camera measures (s1, s2 normalised by S0)
    of the same steel, lit by a source polarized at +45 degrees (in_s1, in_s2, in_s3 = 0, 1, 0)."""
    rng = np.random.default_rng(seed)
    s = pbrdf_cl.stokes(ti, tr, 180.0, incident=(0, 1, 0), backend="numpy", **STEEL)
    s1 = s[:, 1] / s[:, 0] + rng.normal(0, noise, ti.size)
    s2 = s[:, 2] / s[:, 0] + rng.normal(0, noise, ti.size)
    params = ", ".join(f"{k} = {v}" for k, v in STEEL.items())
    header = ("Synthetic polarization-camera data of 45# steel at 435 nm in the paper's geometry: theta_i =\n"
              "30/40/50 deg, theta_r = 20..65 deg step 5, phi = 180 (in plane), the source linearly polarized at\n"
              "+45 deg from s towards p (in_s1, in_s2, in_s3 = 0, 1, 0). s1 = S1/S0 and s2 = S2/S0 of the reflected\n"
              f"light (psps frame) from the six-parameter model with shadowing 'paper' and {params},\n"
              f"plus Gaussian noise of std {noise} (s1_std, s2_std; seed {seed}).\n"
              "Written by scripts/make_examples.py.")
    with open(OUT / "steel_camera_45.csv", "w", encoding="utf-8") as fh:
        fh.writelines(f"# {line}\n" for line in header.splitlines())
        fh.write("theta_i,theta_r,phi,s1,s1_std,s2,s2_std,in_s1,in_s2,in_s3\n")
        for row in zip(ti, tr, s1, s2):
            a, b, v1, v2 = (float(v) for v in row)
            fh.write(f"{a:g},{b:g},180,{v1:.10g},{noise},{v2:.10g},{noise},0,1,0\n")


if __name__ == "__main__":
    main()
