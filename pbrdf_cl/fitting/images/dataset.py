"""The result of an image fit: its status table (:data:`PIXEL_STATUS`), the per-pixel outputs of
a block (:func:`empty_outputs`), the ``xarray.Dataset`` they make (:func:`make_dataset`) and the
image's goodness of fit (:func:`goodness_summary`)."""
from __future__ import annotations

import numpy as np

from ...model import inputs
from ..common import (
    GOODNESS_P,
    GOODNESS_R2,
    MISTAKE_CAUSES,
    OUTSIDE_FOOTNOTE,
    OUTSIDE_MARK,
    OUTSIDE_WHY,
    outside_interval,
)
from .statistics import DETERMINED_FRACTION

#: The status of each pixel of an image fit (``status``): code -> (name, meaning).  (Not
#: :data:`pbrdf_cl.fitting.sample.result.FIT_STATUS`, the status of one fit, whose codes mean otherwise.)
PIXEL_STATUS = {
    1: ("converged", "the descent converged inside the bounds"),
    2: ("on_bound", "converged with a parameter on a bound"),
    3: ("ambiguous", "another start ended within one unit of chi2 of the best, more than 2 standard errors "
                     "away in some parameter: the data cannot decide between them"),
    4: ("underdetermined", "a parameter's 95% interval spans more than half its bounds: the pixel's data do not "
                           "determine it (see `determined`)"),
    0: ("not_converged", "the descent was still improving when its iterations ran out"),
    -1: ("masked", "not fitted: masked"),
    -2: ("too_few", "not fitted: fewer valid measurements (distinct geometries) than needed for the free "
                    "parameters"),
    -3: ("failed", "the model's residuals are not finite at any start"),
}


#: The fill value of a store's ``status`` array: (code, name, meaning) of a pixel whose block is
#: not written (not computed yet, or its chunk lost); never a status of :data:`PIXEL_STATUS`.
NOT_COMPUTED = (-128, "not_computed", "not computed: its block is not in the store")


def _status_attrs():
    return {"status_codes": "; ".join(f"{c}: {n} ({m})" for c, (n, m) in PIXEL_STATUS.items()),
            "flag_values": list(PIXEL_STATUS), "flag_meanings": " ".join(n for n, _ in PIXEL_STATUS.values())}


def empty_outputs(p, n_out):
    """The per-pixel outputs of :meth:`pbrdf_cl.fitting.images.job.BatchJob.fit_rows` for ``p`` pixels
    not fitted, ``n_out`` parameters each (keys, shapes and dtypes; status 0)."""
    return {"x": np.full((p, n_out), np.nan), "stderr": np.full((p, n_out), np.nan),
            "ci95": np.full((p, n_out, 2), np.nan), "determined": np.zeros((p, n_out), bool),
            "chi2": np.full(p, np.nan), "sse": np.full(p, np.nan), "r2": np.full(p, np.nan),
            "p_value": np.full(p, np.nan), "fits_data": np.full(p, -1, np.int8), "nfev": np.zeros(p, np.int64),
            "status": np.zeros(p, np.int8), "n_valid": np.zeros(p, np.int64)}


#: fit-image warns that the model does not describe the data when more than this share of the
#: fitted pixels fails the goodness-of-fit test (``fits_data`` 0): the chi2 test with dop_std;
#: the R^2 test without, which also fails pixels whose DOP hardly varies beyond its noise (a
#: third of random pixels in the paper's geometry at DOP noise 0.002, most of them nearly
#: unpolarised light), so there only when most pixels fail it.
GOODNESS_SHARE = {"chi2": 0.1, "r2": 0.5}
#: At most this many pixels' statistics are read for the medians of :func:`goodness_summary`
#: (every s-th pixel of a larger result).
GOODNESS_SAMPLE = 2 ** 22


def goodness_summary(ds):
    """Whether the model describes an image fit's data, over all its fitted pixels, as
    :func:`pbrdf_cl.fit` says it of one fit: the attributes :func:`pbrdf_cl.fit_batch` adds to
    its result (read block by block from a store).

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.fit_batch` (its ``fits_data``, ``chi2``, ``r2`` and ``n_valid``).

    Returns
    -------
    dict
        ``goodness_test`` ("chi2": the p-value of each pixel's chi2 below GOODNESS_P fails, with
        dop_std; "r2": R^2 below GOODNESS_R2 fails, without), ``goodness_tested`` (fitted
        pixels), ``goodness_failed``, ``goodness_share_failed``, ``goodness_fits_data`` (1
        unless more than GOODNESS_SHARE of the tested pixels fail: 10% of the chi2 test, 50% of
        the R^2 test), ``goodness`` (a line saying so, with the median and the worst pixel, by
        its indices) and, where ``goodness_fits_data`` is 0, ``goodness_warning`` (a WARNING
        line with the usual causes and the notes the data show).

    Examples
    --------
    >>> res = fit_batch(stack)  # doctest: +SKIP
    >>> res.attrs["goodness"].split("; ")[:2]  # doctest: +SKIP
    ['goodness of fit: 0 of 576 fitted pixels (0.0%) fail the chi2 test (p < 0.001 with dop_std)',
     'median chi2 22.8 for 25 degrees of freedom']
    """
    chi2_test = bool(ds.attrs.get("sigma_known", 0))
    free = len(str(ds.attrs.get("free", "")).split())
    intensity = "ks" in str(ds.attrs.get("free", "")).split()
    fits = ds["fits_data"]
    shape = fits.shape
    n_total = int(np.prod(shape, dtype=np.int64))
    step = max(1, -(-n_total // GOODNESS_SAMPLE))
    rows = fits.chunks[0] if fits.chunks else (shape[0],) if shape else (1,)
    tested = failed = 0
    sample, dofs = [], []
    worst = (None, None)  # (flat index, value): the largest reduced chi2 or the lowest R^2
    r = 0
    flat0 = 0
    for size in rows:
        part = {k: np.asarray(ds[k][r:r + size].values).ravel() for k in ("fits_data", "chi2", "r2", "n_valid")}
        r += size
        ok = part["fits_data"] >= 0
        tested += int(ok.sum())
        failed += int((part["fits_data"] == 0).sum())
        dof = np.maximum(part["n_valid"] * (2 if intensity else 1) - free, 1)
        value = part["chi2"] / dof if chi2_test else part["r2"]
        value = np.where(ok & np.isfinite(value), value, np.nan)
        if np.isfinite(value).any():
            i = int(np.nanargmax(value) if chi2_test else np.nanargmin(value))
            if worst[1] is None or (value[i] > worst[1] if chi2_test else value[i] < worst[1]):
                worst = (flat0 + i, float(value[i]))
        keep = np.arange(value.size)[(flat0 + np.arange(value.size)) % step == 0]
        keep = keep[np.isfinite(value[keep])]
        sample.append((part["chi2"] if chi2_test else value)[keep])
        dofs.append(dof[keep])
        flat0 += value.size
    out = {"goodness_test": "chi2" if chi2_test else "r2", "goodness_tested": tested, "goodness_failed": failed,
           "goodness_share_failed": failed / tested if tested else 0.0}
    share = out["goodness_share_failed"]
    out["goodness_fits_data"] = int(share <= GOODNESS_SHARE[out["goodness_test"]])
    test = (f"the chi2 test (p < {GOODNESS_P:g} with dop_std)" if chi2_test else
            f"the R^2 test (the fit explains less than {GOODNESS_R2:.0%} of the DOP's variance; no dop_std)")
    text = f"goodness of fit: {failed} of {tested} fitted pixels ({share:.1%}) fail {test}"
    sample = np.concatenate(sample) if sample else np.zeros(0)
    if sample.size:
        if chi2_test:
            text += (f"; median chi2 {np.median(sample):.3g} for {np.median(np.concatenate(dofs)):g} degrees of "
                     "freedom")
        else:
            text += f"; median R^2 {np.median(sample):.3g}"
    if worst[0] is not None:
        idx = np.unravel_index(worst[0], shape)
        where = ", ".join(f"{d}={i}" for d, i in zip(fits.dims, idx))
        text += (f"; worst at {where}: " + (f"reduced chi2 {worst[1]:.3g}" if chi2_test else f"R^2 {worst[1]:.3g}"))
    out["goodness"] = text
    if not out["goodness_fits_data"]:
        notes = "; ".join(str(ds.attrs.get("data_notes", "")).splitlines())
        out["goodness_warning"] = (f"WARNING: the model does not describe the data of {share:.0%} of the fitted "
                                   "pixels (fits_data = 0 there); their values and intervals are not to be trusted; "
                                   f"usual causes: {MISTAKE_CAUSES}" + (f"; the data show: {notes}" if notes else ""))
    return out


def interval_summary(ds):
    """Where the best value of a pixel lies outside its own 95% interval (a parameter the pixel's
    data do not determine, its best fit on a bound), over all the fitted pixels of an image fit:
    the attrs :func:`pbrdf_cl.fit_batch` adds to its result (counted block by block from a store).

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.fit_batch` (its ``<name>_outside_ci95`` variables).

    Returns
    -------
    dict
        ``outside_ci95`` (the count of such pixels per parameter, "k 12, n 3"; empty where none)
        and, where any, ``outside_ci95_note`` (a line with the counts, the variables and
        ``pbrdf_cl.fitting.common.OUTSIDE_FOOTNOTE``).

    Examples
    --------
    >>> res = fit_batch(stack)  # doctest: +SKIP
    >>> res.attrs["outside_ci95"]  # doctest: +SKIP
    'k 12'
    """
    names = [str(v)[:-len("_outside_ci95")] for v in ds.data_vars
             if str(v).endswith("_outside_ci95") and not str(v).startswith("label_")]
    counts = {n: int(ds[f"{n}_outside_ci95"].sum()) for n in names}
    counts = {n: c for n, c in counts.items() if c}
    out = {"outside_ci95": ", ".join(f"{n} {c}" for n, c in counts.items())}
    if counts:
        out["outside_ci95_note"] = (
            "the best value lies outside its own 95% interval at " + ", ".join(
                f"{c} pixel{'s' if c > 1 else ''} for {n}" for n, c in counts.items()) + " ("
            + ", ".join(f"{n}_outside_ci95" for n in counts) + f") {OUTSIDE_MARK}: {OUTSIDE_WHY}")
    return out


def make_dataset(job, out, seconds):
    """The result ``xarray.Dataset`` of ``job`` (a :class:`~pbrdf_cl.fitting.images.job.BatchJob`) from
    the per-pixel outputs ``out`` of its blocks, concatenated; ``seconds`` (or None) in its attrs."""
    import xarray as xr
    src, setup = job.source, job.setup
    shape, dims = src.shape, src.dims
    names = job.names
    ds = xr.Dataset(coords=dict(src.coords))  # the stack's coordinates over pixel dimensions (x_mm, y_mm, ...)
    units = inputs.UNITS
    long = dict(inputs.LONG_NAMES)
    if not setup.use_f00:
        long["kd"] += " relative to ks (kd/ks)"
    for j, n in enumerate(names):
        ds[n] = (dims, out["x"][:, j].reshape(shape), {"units": units[n], "long_name": long[n]})
        ds[f"{n}_stderr"] = (dims, out["stderr"][:, j].reshape(shape),
                             {"units": units[n], "long_name": f"standard error of {n}"})
        ds[f"{n}_ci95"] = (dims + ("bound",), out["ci95"][:, j].reshape(shape + (2,)),
                           {"units": units[n],
                            "long_name": f"95% interval of {n} (+- 1.96 standard errors cut at the bounds)"})
        ds[f"{n}_outside_ci95"] = (dims, outside_interval(out["x"][:, j], out["ci95"][:, j, 0],
                                                          out["ci95"][:, j, 1]).reshape(shape),
                                   {"long_name": OUTSIDE_FOOTNOTE})
    ds["sse"] = (dims, out["sse"].reshape(shape), {"long_name": "sum of squared DOP residuals", "units": "1"})
    ds["chi2"] = (dims, out["chi2"].reshape(shape),
                  {"long_name": "weighted sum of squared residuals" + (" (chi2)" if setup.sigma_known else
                                                                     " (dop_std = 1: no uncertainties given)")})
    ds["determined"] = (dims + ("param",), out["determined"].reshape(shape + (len(names),)),
                        {"long_name": "the 95% interval is narrower than "
                                      f"{DETERMINED_FRACTION:g} of the parameter's bounds"})
    ds["r2"] = (dims, out["r2"].reshape(shape), {"units": "1", "long_name": "share of the DOP's variance the fit "
                                                                            "explains (R^2)"})
    ds["p_value"] = (dims, out["p_value"].reshape(shape),
                     {"units": "1", "long_name": "p-value of chi2 for its degrees of freedom (n_valid minus the "
                                                 "free parameters; NaN without dop_std)"})
    ds["fits_data"] = (dims, out["fits_data"].reshape(shape),
                       {"long_name": "whether the model describes the pixel's data: "
                                     + (f"p_value >= {GOODNESS_P:g}" if setup.sigma_known else f"r2 >= {GOODNESS_R2:g}")
                                     + " (as pbrdf_cl.fit tests a fit)",
                        "flag_values": [1, 0, -1], "flag_meanings": "fits does_not_fit not_fitted"})
    ds["n_valid"] = (dims, out["n_valid"].reshape(shape), {"long_name": "valid DOP measurements"})
    ds["nfev"] = (dims, out["nfev"].reshape(shape), {"long_name": "model evaluations per measurement"})
    ds["status"] = (dims, out["status"].reshape(shape), {"long_name": "fit status", **_status_attrs()})
    ds = ds.assign_coords(bound=["low", "high"], param=names)
    lo, hi = setup.lo, setup.hi
    ds.attrs.update(model=setup.model, shadowing=setup.shadowing, free=" ".join(names),
                    bounds="; ".join(f"{n} [{lo[i]:g}, {hi[i]:g}]" for i, n in enumerate(setup.free))
                    + (f"; ks [{setup.ks_bounds[0]:g}, {setup.ks_bounds[1]:g}]" if setup.use_f00 else ""),
                    grid=" x ".join(f"{n} {a.size}" for n, a in setup.axes.items()), n_starts=setup.n_starts,
                    angles_units="degrees", sigma_known=int(setup.sigma_known),
                    geometry="shared" if src.shared else "per pixel",
                    **{f"fixed_{k}": v for k, v in setup.fixed.items()})
    if setup.model == "six-param" and not setup.use_f00:
        ds.attrs["note"] = ("DOP depends on ks and kd only through kd/ks: ks is fixed at "
                            f"{setup.base['ks']:g} and kd is the ratio kd/ks")
    ds.attrs["phi_given"] = int(src.phi_given)
    if job.notes:
        ds.attrs["data_notes"] = "\n".join(job.notes)  # one note a line
    if seconds is not None:
        ds.attrs["seconds"] = float(seconds)
    return ds
