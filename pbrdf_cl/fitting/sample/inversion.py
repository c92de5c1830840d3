"""Robust global inversion of measured DOP: device grid -> distinct basins -> nlopt DIRECT-L
-> BOBYQA -> batched Levenberg-Marquardt -> trust-region least squares, with uncertainties,
identifiability diagnostics and model comparison.

DOP depends on ks and kd only through kd/ks (SPEC), so DOP-only fits fix ks = 1 and report
kd as kd/ks.  When intensities (``f00`` or ``s0``) are given, a last stage fits ks and kd
separately with the intensity residuals added.

:func:`fit` only orchestrates: its setup is a :class:`~pbrdf_cl.fitting.setup.FitSetup`, its
stages are the functions of ``pbrdf_cl.fitting.sample.stages`` (the schedule's constants there too:
``DIRECT_EVALS``, ``SCREEN_ITERATIONS``, ...) and :mod:`pbrdf_cl.fitting.sample.uncertainty`, its result a
:class:`~pbrdf_cl.fitting.sample.result.FitResult`.
"""
from __future__ import annotations

import numpy as np

from ...compute import pointwise
from ...io.measurements import as_measurements
from ..common import dop_noise_floor, one_blas_thread
from ..setup import F00_REL_STD, MODEL_PARAMS, FitSetup, check_model
from .polarimetric import fit_channels
from .result import ComparisonResult, fit_result, fit_status, model_notes
from .stages import (
    INTENSITY_MAXEVAL,
    MEMORY_BUDGET,
    Model,
    Residuals,
    grid_stage,
    intensity_stage,
    intensity_start,
    local_stages,
)
from .uncertainty import uncertainty_stage

#: Grid points per free parameter for the device stage.
DEFAULT_GRID = dict(n=24, k=32, sigma=16, kd=16, c=8)
SPECULAR_GRID = dict(n=160, k=200)


def check_fit_args(data, model, bounds, fixed, shadowing):
    """The checked inputs of :func:`fit`: (measurements, :class:`~pbrdf_cl.fitting.setup.FitSetup`)."""
    check_model(model, shadowing)
    meas = as_measurements(data)
    pointwise.check_degrees(meas.theta_i, meas.theta_r, f"{meas.source}: ")
    setup = FitSetup.check(model, bounds, fixed, shadowing)
    free = setup.free
    if meas.polarimetric:  # several numbers a row: fit_channels counts them
        return meas, setup
    if len(meas) <= len(free):
        raise ValueError(f"{meas.source}: {len(meas)} measurements for {len(free)} free parameters "
                         f"({', '.join(free)}); at least {len(free) + 1} are needed")
    geometries = distinct_geometries(meas)
    if geometries < len(free):
        raise ValueError(f"{meas.source}: {geometries} distinct geometr{'y' if geometries == 1 else 'ies'} "
                         f"(theta_i, theta_r, phi) for {len(free)} free parameters ({', '.join(free)}): the data "
                         f"cannot determine them; measure more geometries or fix parameters (e.g. fixed="
                         f"{{'{free[-1]}': ...}}, --fix {free[-1]}=...)")
    return meas, setup


def distinct_geometries(meas):
    """How many distinct (theta_i, theta_r, phi) the measurements have (repeats add no geometry)."""
    return len(np.unique(np.column_stack([meas.theta_i, meas.theta_r, meas.phi]), axis=0))


def fit(data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, grid_shape=None, n_basins=6,
        engine=None, backend="auto", progress=False, memory_budget=MEMORY_BUDGET):
    """Fit the model to measured DOP (and F00 where given), or to any polarimetric data: the
    pipeline of stages of ``pbrdf_cl.fitting.sample.stages``.

    Parameters
    ----------
    data : str or path, dict, DataFrame, xarray.Dataset or Measurements
        The measurements: theta_i, theta_r (degrees), dop, and optionally phi (default 180),
        dop_std (weights 1/dop_std^2), f00 (or s0) and f00_std; a CSV path with those columns.
    model : {"six-param", "specular"}, default "six-param"
        "six-param": n, k, sigma, kd/ks, c (ks = 1 unless an intensity column separates it);
        "specular": the paper's ref. [7], n and k only.
    bounds : dict, optional
        Name -> (low, high); defaults n [1, 5], k [0, 10], sigma [0.05, 1], kd [0, 5], c [-1, 0], ks [1e-3, 1e3].
    fixed : dict, optional
        Name -> value of parameters held fixed (e.g. ``{"sigma": 0.45}``).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function of the model fitted.
    grid_shape : dict, optional
        Name -> nodes of the device grid stage (defaults ``DEFAULT_GRID``, ``SPECULAR_GRID``).
    n_basins : int, default 6
        How many distinct basins of the grid the local stages start from.
    engine : pbrdf_cl.Engine, optional
        Where the grid stage runs.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        As for :func:`pbrdf_cl.dop`.
    progress : bool, default False
        A progress bar for the grid stage.
    memory_budget : int or str, default "512 MiB"
        Bytes the grid stage's tables of the measurements may take (with its sums), or a size such
        as "256 MiB" (:func:`pbrdf_cl.ranges.parse_bytes`): more measurements than fit run block by
        block, with the same result (``docs/performance.md``).

    Returns
    -------
    FitResult
        ``x``, ``stderr``, ``ci95`` (and two other kinds of interval), ``corr``/``cov`` (labelled),
        ``sse``, ``chi2``, ``p_value``, ``r2``, ``fits_data``, ``aic``, ``bic``, ``notes``,
        ``success``/``status``/``message``, per-stage ``nfev`` and ``seconds``; ``summary()``.

    Raises
    ------
    ValueError
        For bad arguments, and for data that cannot determine the free parameters (fewer distinct
        geometries than free parameters), naming the counts; a :class:`pbrdf_cl.RangeError` for a
        ``memory_budget`` that is not a size or too small for one measurement's tables (naming the
        least).

    Examples
    --------
    >>> import pbrdf_cl
    >>> res = pbrdf_cl.fit("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> res.x["n"], res.ci95["n"], res.fits_data  # doctest: +SKIP
    """
    meas, setup = check_fit_args(data, model, bounds, fixed, shadowing)
    axes = setup.grid_axes(grid_shape_of(model, grid_shape))
    if meas.polarimetric:
        return fit_channels(meas, setup, axes, n_basins, engine=engine, backend=backend, progress=progress,
                            memory_budget=memory_budget)
    grid = grid_stage(meas, setup.free, axes, setup.base, shadowing, engine=engine, backend=backend,
                      progress=progress, memory_budget=memory_budget)
    return fit_on_grid(meas, setup, grid, n_basins)


def grid_shape_of(model, grid_shape=None):
    """The nodes per free parameter of ``model``'s grid stage: :data:`DEFAULT_GRID` (or
    :data:`SPECULAR_GRID`) updated with ``grid_shape``."""
    return {**(SPECULAR_GRID if model == "specular" else DEFAULT_GRID), **(grid_shape or {})}


def local_inputs(meas, setup, grid_result):
    """What :func:`fit_on_grid`'s local stages take from ``meas``, ``setup`` and the grid stage's
    result: (the model, the DOP residuals, the grid, the ridge between valleys ``rise``: one
    unit of chi^2, estimated from the grid without given uncertainties)."""
    std = meas.dop_std if meas.dop_std is not None else np.ones(len(meas))
    mdl = Model(meas, setup.shadowing)
    dop_resid = Residuals(mdl, setup.free, setup.base, meas.dop, std)
    grid = grid_result.value
    rise = 1.0 if meas.dop_std is not None else float(grid.sse.min()) / (len(meas) - len(setup.free))
    return mdl, dop_resid, grid, rise


@one_blas_thread
def fit_on_grid(meas, setup, grid_result, n_basins=6, derivative_free=True, rows=None, screened=None):
    """:func:`fit`'s stages after its grid stage: ``meas`` and ``setup`` as :func:`check_fit_args`
    returns them, ``grid_result`` the :class:`~pbrdf_cl.fitting.sample.stages.StageResult` of
    :func:`~pbrdf_cl.fitting.sample.stages.grid_stage` on ``setup.grid_axes(...)`` (what
    :func:`pbrdf_cl.fit_joint` computes once for its joint and its separate fits).  Returns the
    :class:`FitResult`.  ``derivative_free`` False skips the DIRECT-L and BOBYQA stages: the
    grid's basins go straight to the Levenberg-Marquardt screen (the lighter schedule of
    :func:`pbrdf_cl.fit_joint`'s separate fits, about half the local stages' time).  ``rows``:
    what the local stages evaluate, the DOP residuals' rows of the free parameters (by default
    computed here; :func:`pbrdf_cl.fit_joint` passes them batched with its other sets');
    ``screened``: the local stages up to the screen, done already (as
    :func:`~pbrdf_cl.fitting.sample.stages.local_stages` takes them)."""
    model, shadowing = setup.model, setup.shadowing
    free, base, lo, hi = setup.free, setup.base, setup.lo, setup.hi
    mdl, dop_resid, grid, rise = local_inputs(meas, setup, grid_result)
    std = dop_resid.dop_std
    cands, final_ran, st = local_stages(dop_resid.rows if rows is None else rows, lo, hi, grid, free, n_basins, rise,
                                        derivative_free, screened)
    st = {"grid": grid_result, **st}
    best = cands[0]
    axes = grid.axes

    use_f00 = setup.fits_intensity(meas.f00 is not None)
    resid, x_final, lo_f, hi_f = dop_resid, best.x, lo, hi
    if use_f00:
        f00_std = meas.f00_std if meas.f00_std is not None else F00_REL_STD * np.maximum(meas.f00, 1e-300)
        ks_bounds = setup.ks_bounds
        ks0 = intensity_start(mdl, dop_resid.params(best.x), meas.f00, f00_std, ks_bounds)
        resid = Residuals(mdl, free + ["ks"], base, meas.dop, std, meas.f00, f00_std)
        lo_f, hi_f = np.append(lo, ks_bounds[0]), np.append(hi, ks_bounds[1])
        spacing = np.array([np.median(np.diff(axes[n])) for n in free])
        st["intensity"] = intensity_stage(resid, lo_f, hi_f, np.append(best.x, ks0), np.append(spacing, ks0 * 0.1),
                                          INTENSITY_MAXEVAL)
        x_final = st["intensity"].value.x
    floor = dop_noise_floor(meas.dop) if meas.dop_std is None else None
    unc = uncertainty_stage(resid, x_final, lo_f, hi_f, grid, best.sse, len(meas), meas.dop_std is not None,
                            floor).value
    status = fit_status(best, final_ran, st["intensity"].value if use_f00 else None)
    return fit_result(meas, model, shadowing, resid, x_final, lo_f, hi_f, unc, cands, grid, st, status,
                      model_notes(model, setup.fixed, use_f00, meas))


def compare_models(data, shadowing="paper", bounds=None, fixed=None, engine=None, backend="auto", progress=False,
                   memory_budget=MEMORY_BUDGET):
    """Fit the six-parameter model and the ref. [7] specular model to the same data and compare them.

    Parameters
    ----------
    data, shadowing, bounds, fixed, engine, backend, progress, memory_budget
        As for :func:`fit`; the specular fit takes the bounds and fixed values of n and k only.

    Returns
    -------
    ComparisonResult
        "six-param" and "specular" FitResults (also in ``fits``), "preferred" (the lower BIC),
        "table" (Markdown: n, k, free parameters, SSE, AIC, BIC) and ``summary()``.

    Examples
    --------
    >>> both = pbrdf_cl.compare_models("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> both.preferred  # doctest: +SKIP
    'six-param'
    """
    meas = as_measurements(data)
    six = fit(meas, "six-param", bounds=bounds, fixed=fixed, shadowing=shadowing, engine=engine, backend=backend,
              progress=progress, memory_budget=memory_budget)
    spec_fixed = {k: v for k, v in (fixed or {}).items() if k in MODEL_PARAMS["specular"]}
    spec_bounds = {k: v for k, v in (bounds or {}).items() if k in MODEL_PARAMS["specular"]}
    spec = fit(meas, "specular", bounds=spec_bounds, fixed=spec_fixed, shadowing=shadowing, engine=engine,
               backend=backend, progress=progress, memory_budget=memory_budget)
    rows = ["| model | n | k | free params | SSE | AIC | BIC |", "|---|---|---|---|---|---|---|"]
    for name, r in (("six-param", six), ("specular (ref. [7])", spec)):
        rows.append(f"| {name} | {r.x['n']:.4g} | {r.x['k']:.4g} | {len(r.free)} | {r.sse:.4g} | {r.aic:.2f} | "
                    f"{r.bic:.2f} |")
    preferred = "six-param" if six.bic <= spec.bic else "specular"
    return ComparisonResult({"six-param": six, "specular": spec, "preferred": preferred, "table": "\n".join(rows),
                             "fits": {"six-param": six, "specular": spec}})
