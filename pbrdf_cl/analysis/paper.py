"""Reproduce the figures and Table 1 of Zhu et al. (2020) and add dense roughness maps.

:func:`reproduce` writes into one folder:

- ``fig2_aluminum.png``, ``fig2_black_paint.png``: the paper's Fig. 2.  Its measured points (from
  Thilak et al.) are not published, so the data are generated from the six-parameter model at
  the true n, k of Table 1 with the roughness, diffuse weight, Minnaert exponent and noise of
  :data:`FIG2_SAMPLES` (stated on the figure and in ``summary.md``), in the specular geometry
  theta_r = theta_i, phi = 180.  Both models are fitted with :func:`pbrdf_cl.compare_models`.
- ``table1.md``, ``table1.csv``: true / ref. [7] / six-parameter estimates (ours, with 95%
  intervals) next to the paper's own numbers.
- ``fig4_steel.png``: DOP vs theta_r at theta_i = 30, 40, 50 deg with the paper's steel fit.
- ``fig5_sigma.png``: DOP vs theta_r at theta_i = 40 deg for sigma = 0.35, 0.5, 0.65.
- ``map_sigma_theta_r.png``: DOP over (theta_r, sigma) at theta_i = 40 deg with contours, and
  dDOP/dsigma from finite differences of device grids (maps.stencil).
- ``map_theta_i_theta_r.png``: DOP over (theta_i, theta_r) for sigma = 0.35, 0.5, 0.65.
- ``sobol_dop_theta_i_theta_r.png`` / ``.nc``: Sobol' indices (S1, ST) of the DOP over
  (theta_i, theta_r) for a box of materials around the paper's samples (:data:`SOBOL_RANGES`):
  which parameter controls the DOP where.
- ``design_steel.png`` / ``.nc``: where to measure the steel of Fig. 4: the 30 in-plane geometries of a
  5 degree grid that make the predicted 95% intervals of n and k narrowest (:func:`pbrdf_cl.design`,
  DOP noise :data:`DESIGN_NOISE`), against the paper's 30 (theta_i 30/40/50 x theta_r 20..65).
- one ``.npz`` per other figure with the arrays drawn, and ``summary.md`` listing every file.

The figures are drawn by :mod:`pbrdf_cl.plots.paper` (the map over (theta_r, sigma) by
:func:`pbrdf_cl.plots.maps.plot_map`, the Sobol' map by :mod:`pbrdf_cl.plots.sensitivity`) from
the arrays computed here.
"""
from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np

from ..compute import dense, pointwise
from ..device.engine import resolve_engine
from ..io.measurements import from_arrays
from ..plots import paper as figures
from ..plots.maps import plot_map
from . import maps
from .designs import PAPER_MATERIAL

#: The paper's fit to 45# steel at 435 nm, theta_i = 40 deg (SPEC).
STEEL = PAPER_MATERIAL
STEEL_THETA_I = (30.0, 40.0, 50.0)
STEEL_THETA_R = np.arange(20.0, 65.0 + 1e-9, 5.0)
SIGMAS = (0.35, 0.5, 0.65)
#: Table 1 of the paper: true and estimated (n, k).
TABLE1 = {"aluminum": {"true": (1.24, 6.6), "ref7": (1.37, 3.97), "six": (1.255, 6.582)},
          "black paint": {"true": (1.405, 0.2289), "ref7": (1.46, 1.32), "six": (1.413, 0.232)}}
#: The synthetic Fig. 2 samples: the true n, k of Table 1; the other parameters are our choice
#: (the paper does not give them), stated wherever the data are shown.
FIG2_SAMPLES = {"aluminum": dict(n=1.24, k=6.6, sigma=0.25, ks=1.0, kd=0.2, c=-0.3),
                "black paint": dict(n=1.405, k=0.2289, sigma=0.3, ks=1.0, kd=0.05, c=-0.5)}
#: The box of materials of the Sobol' map: it spans the paper's samples.  n: Table 1's aluminum
#: (1.24) and black paint (1.405) and the steel fit (1.6); k: black paint's 0.2289 to aluminum's
#: 6.6 (steel 2.139), log-uniform as it spans decades; sigma: the Fig. 2 samples' 0.25, 0.3 and
#: Fig. 5's 0.35..0.65 around the steel fit's 0.5; kd with ks = 1 fixed (the DOP sees kd/ks only):
#: Fig. 2's 0.05, 0.2 and the steel fit's kd/ks = 0.15/0.9 = 0.17; c: -0.3 (steel, aluminum) and
#: -0.5 (black paint) up to 0 (Lambert).  (The Fig. 2 samples' sigma, kd and c are our choice: the
#: paper gives only their n, k.)
SOBOL_RANGES = dict(n=(1.2, 1.7), k=(0.2, 7.0, "log"), sigma=(0.2, 0.7), kd=(0.0, 0.25), c=(-0.6, 0.0))
#: Base samples of the Sobol' map: N (D + 2) = 3584 model runs per geometry, a second or so on a CPU
#: device at 32 x 32 geometries; intervals of about +-0.05 on the dominant indices.
SOBOL_N = 512
SOBOL_FILE = "sobol_dop_theta_i_theta_r"
#: The measurement design of the steel: the DOP noise of one measurement (the paper does not state
#: its camera's; 0.005 is a typical DOP resolution of a liquid-crystal polarimeter) and the count.
DESIGN_NOISE = 0.005
DESIGN_MEASUREMENTS = 30
DESIGN_FILE = "design_steel"
FIG2_ANGLES = np.arange(10.0, 80.0 + 1e-9, 2.5)
FIG2_NOISE = 0.001
SEED = 2020


_params_text = figures.params_text


def fig2_data(sample, seed=SEED):
    """The synthetic measurements of one Fig. 2 sample: (Measurements, noise-free DOP)."""
    p = FIG2_SAMPLES[sample]
    ti = FIG2_ANGLES
    clean = pointwise.dop(ti, ti, 180.0, backend="numpy", **p)
    rng = np.random.default_rng([seed, sorted(FIG2_SAMPLES).index(sample)])
    noisy = np.clip(clean + rng.normal(0.0, FIG2_NOISE, ti.size), 0.0, 1.0)
    meas = from_arrays(ti, ti, noisy, 180.0, dop_std=np.full(ti.size, FIG2_NOISE), source=f"synthetic {sample}")
    return meas, clean


def fig2(sample, out, engine=None, seed=SEED):
    """Fit both models to one synthetic Fig. 2 sample, plot and save (``fig2_<sample>.png`` and
    ``.npz``).

    Parameters
    ----------
    sample : {"aluminum", "black paint"}
        A key of :data:`FIG2_SAMPLES`.
    out : pathlib.Path
        The folder written into.
    engine : pbrdf_cl.Engine, optional
        Where the fits' grid stage runs.
    seed : int, default 2020
        Seed of the synthetic noise.

    Returns
    -------
    ComparisonResult
        Both fits (:func:`pbrdf_cl.compare_models`).
    """
    from ..fitting.sample.inversion import compare_models
    meas, clean = fig2_data(sample, seed)
    both = compare_models(meas, engine=engine)
    six, spec = both["six-param"], both["specular"]
    angle = np.linspace(0.0, 85.0, 171)
    curve_six = pointwise.dop(angle, angle, 180.0, backend="numpy", shadowing=six.shadowing, **six.x)
    curve_spec = pointwise.dop(angle, angle, 180.0, backend="numpy", model="specular", **spec.x)
    curve_true = pointwise.dop(angle, angle, 180.0, backend="numpy", **FIG2_SAMPLES[sample])
    slug = sample.replace(" ", "_")
    figures.plot_fig2(out / f"fig2_{slug}.png", sample, FIG2_SAMPLES[sample], FIG2_NOISE, meas, angle, curve_true,
                      (six, curve_six), (spec, curve_spec))
    np.savez_compressed(out / f"fig2_{slug}.npz", theta_i=meas.theta_i, theta_r=meas.theta_r, dop=meas.dop,
                        dop_clean=clean, angle=angle, six_param=curve_six, specular=curve_spec, true=curve_true,
                        six_param_x=np.array([six.x[k] for k in dense.PARAMETERS]),
                        specular_x=np.array([spec.x["n"], spec.x["k"]]))
    return both


def _interval(r, name):
    """"x [lo, hi]", marked :data:`~pbrdf_cl.fitting.common.OUTSIDE_MARK` where x lies outside."""
    from ..fitting.common import OUTSIDE_MARK, outside_interval
    lo, hi = r.ci95[name]
    return f"{r.x[name]:.4g} [{lo:.3g}, {hi:.3g}]" + (f" {OUTSIDE_MARK}" if outside_interval(r.x[name], lo, hi) else "")


def table1(fits, out):
    """``table1.md`` and ``table1.csv``: true values, the paper's estimates and ours.  A best value
    outside its own 95% interval (a parameter the data do not determine, at a bound) is marked
    ``(*)`` in the Markdown, with the footnote that says why
    (:data:`~pbrdf_cl.fitting.common.OUTSIDE_FOOTNOTE`), and flagged in the CSV's
    ``ours_six_<n|k>_outside_ci95``; returns the CSV's rows."""
    from ..fitting.common import OUTSIDE_FOOTNOTE, OUTSIDE_MARK, outside_interval
    rows = []
    for sample, both in fits.items():
        true, paper = TABLE1[sample]["true"], TABLE1[sample]
        six, spec = both["six-param"], both["specular"]
        rows.append(dict(sample=sample, true_n=true[0], true_k=true[1],
                         paper_ref7_n=paper["ref7"][0], paper_ref7_k=paper["ref7"][1],
                         paper_six_n=paper["six"][0], paper_six_k=paper["six"][1],
                         ours_ref7_n=spec.x["n"], ours_ref7_k=spec.x["k"],
                         ours_six_n=six.x["n"], ours_six_k=six.x["k"],
                         ours_six_n_lo=six.ci95["n"][0], ours_six_n_hi=six.ci95["n"][1],
                         ours_six_k_lo=six.ci95["k"][0], ours_six_k_hi=six.ci95["k"][1],
                         ours_six_n_outside_ci95=bool(outside_interval(six.x["n"], *six.ci95["n"])),
                         ours_six_k_outside_ci95=bool(outside_interval(six.x["k"], *six.ci95["k"])),
                         ours_ref7_sse=spec.sse, ours_six_sse=six.sse, ours_ref7_bic=spec.bic, ours_six_bic=six.bic))
    with open(out / "table1.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    lines = ["# Table 1: n, k inverted from DOP data", "",
             "Paper columns: Zhu et al. 2020, Table 1 (their data: Thilak et al.). Our columns: fits of both "
             "models to synthetic data generated from the six-parameter model at the true n, k "
             "(other parameters and noise in `summary.md`); six-parameter values with their 95% intervals.", "",
             "| sample | true n | true k | paper ref.[7] n | paper ref.[7] k | paper six-param n | "
             "paper six-param k | our ref.[7] n | our ref.[7] k | our six-param n [95%] | "
             "our six-param k [95%] | BIC ref.[7] / six |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (sample, both), r in zip(fits.items(), rows):
        six, spec = both["six-param"], both["specular"]
        lines.append(f"| {sample} | {r['true_n']:g} | {r['true_k']:g} | {r['paper_ref7_n']:g} | "
                     f"{r['paper_ref7_k']:g} | {r['paper_six_n']:g} | {r['paper_six_k']:g} | "
                     f"{spec.x['n']:.4g} | {spec.x['k']:.4g} | {_interval(six, 'n')} | {_interval(six, 'k')} | "
                     f"{spec.bic:.1f} / {six.bic:.1f} |")
    if any(OUTSIDE_MARK in line for line in lines[-len(rows):]):
        lines += ["", OUTSIDE_FOOTNOTE + "."]
    (out / "table1.md").write_text("\n".join(lines) + "\n")
    return rows


def fig4(out):
    """DOP vs theta_r at the three incidence angles with the paper's steel fit: model values only
    (curves, and markers at the measured geometries); no measured data are drawn.

    Parameters
    ----------
    out : pathlib.Path
        The folder written into (``fig4_steel.png`` and ``.npz``).

    Returns
    -------
    matplotlib.figure.Figure
        The figure (written).
    """
    tr = np.linspace(20.0, 65.0, 181)
    curves = {ti: pointwise.dop(ti, tr, 180.0, backend="numpy", **STEEL) for ti in STEEL_THETA_I}
    measured = {ti: pointwise.dop(ti, STEEL_THETA_R, 180.0, backend="numpy", **STEEL) for ti in STEEL_THETA_I}
    fig = figures.plot_fig4(out / "fig4_steel.png", STEEL, tr, curves, STEEL_THETA_R, measured).figure
    np.savez_compressed(out / "fig4_steel.npz", theta_r=tr, theta_i=np.array(STEEL_THETA_I),
                        dop=np.stack([curves[t] for t in STEEL_THETA_I]))
    return fig


def fig5(out):
    """DOP vs theta_r at theta_i = 40 for three roughness values (model curves).

    Parameters
    ----------
    out : pathlib.Path
        The folder written into (``fig5_sigma.png`` and ``.npz``).

    Returns
    -------
    matplotlib.figure.Figure
        The figure (written).
    """
    tr = np.linspace(20.0, 65.0, 181)
    rows = [pointwise.dop(40.0, tr, 180.0, backend="numpy", **{**STEEL, "sigma": s}) for s in SIGMAS]
    fig = figures.plot_fig5(out / "fig5_sigma.png", STEEL, tr, SIGMAS, rows).figure
    np.savez_compressed(out / "fig5_sigma.npz", theta_r=tr, sigma=np.array(SIGMAS), dop=np.stack(rows))
    return fig


def map_sigma_theta_r(out, resolution=256, engine=None):
    """DOP over (theta_r, sigma) at theta_i = 40 deg, with dDOP/dsigma on the device grid."""
    fixed = {"theta_i": 40.0, **{k: v for k, v in STEEL.items() if k != "sigma"}}
    ds = maps.make_map(("theta_r", np.linspace(0.0, 85.0, resolution)),
                       ("sigma", np.linspace(0.05, 1.0, resolution)), fixed, derivative="sigma", engine=engine)
    plot_map(ds, out / "map_sigma_theta_r.png",
             title=f"DOP and dDOP/dsigma over (theta_r, sigma), in plane, {_params_text(fixed)}")
    maps.save_npz(ds, out / "map_sigma_theta_r.npz")
    return ds


def map_theta_i_theta_r(out, resolution=256, engine=None):
    """DOP over (theta_i, theta_r) for the three roughness values of Fig. 5 (one device grid)."""
    angles = np.linspace(0.0, 85.0, resolution)
    fixed = {k: v for k, v in STEEL.items() if k != "sigma"}
    da = dense.grid({"theta_i": angles, "theta_r": angles, "sigma": np.array(SIGMAS)}, fixed,
                    dtype="float64", engine=engine)
    figures.plot_dop_maps(out / "map_theta_i_theta_r.png", da, angles, SIGMAS, fixed)
    np.savez_compressed(out / "map_theta_i_theta_r.npz", theta_i=angles, theta_r=angles, sigma=np.array(SIGMAS),
                        dop=da.transpose("sigma", "theta_r", "theta_i").values)
    return da


def sobol_side(resolution):
    """Geometries per axis of the Sobol' map: resolution / 8, from 8 to 32 (32 at the default 256)."""
    return int(min(32, max(8, resolution // 8)))


def sobol_map(out, resolution=256, engine=None, seed=SEED):
    """Sobol' indices of the DOP over (theta_i, theta_r) for :data:`SOBOL_RANGES` (ks = 1): the
    figure and the result (netCDF).  Returns the Dataset."""
    from ..plots.sensitivity import plot_sensitivity
    from .sensitivity import sobol, write_result
    side = sobol_side(resolution)
    ds = sobol(SOBOL_RANGES, {"theta_i": np.linspace(0.0, 80.0, side), "theta_r": np.linspace(0.0, 85.0, side)},
               {"ks": 1.0}, N=SOBOL_N, seed=seed, engine=engine)
    plot_sensitivity(ds, out / f"{SOBOL_FILE}.png",
                     title=f"Which parameters control the DOP where: Sobol' indices over (theta_i, theta_r), in "
                           f"plane, for a box of materials around the paper's samples (N={SOBOL_N}, "
                           f"{ds.attrs['runs_per_geometry']} runs per geometry, ks=1)")
    write_result(ds, out / f"{SOBOL_FILE}.nc")
    return ds


def design_map(out, engine=None):
    """The measurement design for the steel (:data:`STEEL`): the figure and the result (netCDF).
    Returns the :class:`pbrdf_cl.analysis.designs.DesignResult`."""
    from ..plots.design import plot_design
    from .designs import design
    from .sensitivity import write_result
    r = design(STEEL, {"theta_i": "10:80:5", "theta_r": "0:85:5"}, noise=DESIGN_NOISE,
               n_measurements=DESIGN_MEASUREMENTS, target=("n", "k"), engine=engine)
    plot_design(r, out / f"{DESIGN_FILE}.png")
    write_result(r.to_dataset(), out / f"{DESIGN_FILE}.nc")
    return r


DESCRIPTIONS = {
    "fig2_aluminum.png": "Fig. 2, aluminum: synthetic DOP data vs incidence angle with the six-parameter and "
                         "ref. [7] fits and the true curve.",
    "fig2_black_paint.png": "Fig. 2, black paint: the same for the dielectric sample.",
    "table1.md": "Table 1: true n, k, the paper's estimates and ours (six-parameter with 95% intervals), as a "
                 "Markdown table.",
    "table1.csv": "Table 1 as CSV, with our intervals and both models' BIC.",
    "fig4_steel.png": "Fig. 4: DOP vs theta_r of 45# steel at theta_i = 30, 40, 50 deg with the paper's fit.",
    "fig5_sigma.png": "Fig. 5: DOP vs theta_r at theta_i = 40 deg for sigma = 0.35, 0.5, 0.65.",
    "map_sigma_theta_r.png": "Dense map of DOP over (theta_r, sigma) at theta_i = 40 deg with contours, and "
                             "dDOP/dsigma by finite differences of device grids (step 1e-4 sigma at every node).",
    "map_theta_i_theta_r.png": "Dense maps of DOP over (theta_i, theta_r) for sigma = 0.35, 0.5, 0.65 on one "
                               "colour scale.",
    f"{SOBOL_FILE}.png": "Sobol' first-order (S1) and total (ST) indices of the DOP over (theta_i, theta_r) "
                         "for a box of materials around the paper's samples: which parameter controls the DOP "
                         "where.",
    f"{SOBOL_FILE}.nc": "The Sobol' map's indices, bootstrap intervals, samples and settings (netCDF).",
    f"{DESIGN_FILE}.png": "Where to measure the steel: the information map over (theta_i, theta_r) with the 30 "
                          "chosen geometries and the paper's, and the predicted 95% interval widths of both "
                          "sets (with and without an F00 column).",
    f"{DESIGN_FILE}.nc": "The design: chosen and reference geometries, predicted widths, comparisons, the "
                         "information map (netCDF).",
}


def data_file(png):
    """The data file written with a figure of :data:`DESCRIPTIONS`: the ``.nc`` of the Sobol' map and
    the design, else the ``.npz`` of the arrays drawn."""
    stem = png[:-4]
    return f"{stem}.nc" if f"{stem}.nc" in DESCRIPTIONS else f"{stem}.npz"


def check_resolution(resolution):
    """Refuse a map resolution that is too small, or whose maps cannot fit in memory, before any work
    (the fits run first and take seconds)."""
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8 points per map axis, got {resolution}")
    # the larger of the two maps: theta_i x theta_r for each of Fig. 5's roughness values
    maps.check_map_size(resolution, resolution * max(2, len(SIGMAS)), True, what=f"--resolution {resolution}: a map")


def reproduce(out="paper-figures", *, resolution=256, engine=None, backend="auto", seed=SEED, log=print):
    """Write every figure, table and data file of the paper (``pbrdf-cl reproduce``) into ``out``.

    Parameters
    ----------
    out : str or path, default "paper-figures"
        The folder (created if absent).
    resolution : int, default 256
        Points per axis of the dense maps (the Sobol' map has resolution / 8, from 8 to 32).
    engine : pbrdf_cl.Engine, optional
        Where the fits' grid stage and the maps run.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        "auto": the OpenCL device, or the numpy reference without one.
    seed : int, default 2020
        Seed of the synthetic Fig. 2 data and of the Sobol' samples.
    log : callable, default print
        Called with each progress line.

    Returns
    -------
    dict
        File name -> one-sentence description (what ``summary.md`` lists)."""
    check_resolution(resolution)
    engine = resolve_engine(engine, backend)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    log(f"computing on {engine.description}")
    fits = {}
    for sample in FIG2_SAMPLES:
        fits[sample] = fig2(sample, out, engine=engine, seed=seed)
        log(f"fig2 {sample}: fitted both models ({time.perf_counter() - t0:.1f} s)")
    for r in table1(fits, out):
        marked = [p for p in ("n", "k") if r[f"ours_six_{p}_outside_ci95"]]
        if marked:
            log(f"table1 {r['sample']}: the six-parameter {' and '.join(marked)} lie outside their 95% intervals, "
                "marked (*) with a footnote in table1.md")
    fig4(out)
    fig5(out)
    map_sigma_theta_r(out, resolution, engine)
    map_theta_i_theta_r(out, resolution, engine)
    log(f"figures and maps done ({time.perf_counter() - t0:.1f} s)")
    ds = sobol_map(out, resolution, engine, seed)
    log(f"Sobol' map: {ds.attrs['model_runs']} model runs in {ds.attrs['seconds']:.1f} s "
        f"({time.perf_counter() - t0:.1f} s)")
    des = design_map(out, engine)
    w, wr = des.ci95_width, des.ci95_width_reference
    log(f"design: predicted n, k widths {w['n']:.3g}, {w['k']:.3g} at the chosen geometries against "
        f"{wr['n']:.3g}, {wr['k']:.3g} at the paper's ({time.perf_counter() - t0:.1f} s)")
    files = dict(DESCRIPTIONS)
    for png in [f for f in DESCRIPTIONS if f.endswith(".png") and data_file(f).endswith(".npz")]:
        files[data_file(png)] = f"the arrays drawn in {png}."
    files["summary.md"] = "this list."
    lines = ["# Reproduction of Zhu et al. (2020) and roughness maps", "",
             f"Written by `pbrdf-cl reproduce` (pbrdf_cl.analysis.paper.reproduce, seed {seed}, maps at {resolution} "
             f"points per axis, float64, shadowing `paper`; computed on {engine.description}).", "",
             "Fig. 2 data are synthetic (the paper's measured points are not published): the six-parameter "
             f"model in the specular geometry theta_r = theta_i = {FIG2_ANGLES[0]:g}..{FIG2_ANGLES[-1]:g} deg "
             f"(step {FIG2_ANGLES[1] - FIG2_ANGLES[0]:g}), phi = 180, Gaussian DOP noise sd {FIG2_NOISE:g}, "
             "clipped to [0, 1], with"]
    for sample, p in FIG2_SAMPLES.items():
        lines.append(f"- {sample}: {_params_text(p)}")
    side = sobol_side(resolution)
    box = ", ".join(f"{k} in [{r[0]:g}, {r[1]:g}]" + (" (log-uniform)" if len(r) > 2 else "")
                    for k, r in SOBOL_RANGES.items())
    lines += ["", f"Steel (Fig. 4, 5 and maps): the paper's fit {_params_text(STEEL)}.", "",
              f"Sobol' map: {box}, ks=1; N={SOBOL_N} (seed {seed}), {side} x {side} geometries, float32, "
              "SALib's sampler and estimators (pbrdf_cl.sobol).", "",
              f"Design: the steel, DOP noise {DESIGN_NOISE:g}, {DESIGN_MEASUREMENTS} geometries out of theta_i "
              "10..80 x theta_r 0..85 (step 5, in plane) for n and k (pbrdf_cl.design, criterion A); predicted 95% "
              f"widths n {w['n']:.3g}, k {w['k']:.3g} against the paper's geometry's {wr['n']:.3g}, {wr['k']:.3g}.",
              "", "| file | content |",
              "|---|---|"]
    lines += [f"| `{name}` | {text} |" for name, text in files.items()]
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    return files
