"""What :func:`pbrdf_cl.fit` returns: :class:`FitResult` (with ``FIT_STATUS``, its status
table), :class:`ComparisonResult`, and the notes a fit carries (the model's conventions, the
data's mistakes, bounds, identifiability, goodness of fit, ambiguous basins)."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ...compute import pointwise
from ...io.measurements import duplicates_note
from ...results import Result
from .. import report
from ..common import DOP_NOISE_FLOOR, OUTSIDE_MARK, dop_resolution, on_bound, outside_interval, outside_note
from ..setup import F00_REL_STD, MODEL_PARAMS, PARAMETERS

#: FitResult.status -> message (scipy's convention: success is status > 0).
FIT_STATUS = {
    1: "converged: the local stages met their tolerances",
    2: "converged: least squares ran out of evaluations along a flat valley and BOBYQA finished (it stopped "
       "improving)",
    0: "stopped: an evaluation budget ran out while the objective was still falling; the result is the best "
       "point found",
    -1: "failed: the model's residuals are not finite at any candidate",
}


class FitResult(Result):
    """Result of :func:`fit`; keys are also attributes, which may be assigned (like scipy's
    ``OptimizeResult``).

    success, status, message
        like scipy's: ``status`` is one of ``FIT_STATUS`` (1: the local stages converged; 2:
        least squares ran out of evaluations along a flat valley and the final BOBYQA finished;
        0: an evaluation budget ran out while the objective was still falling (see ``SETTLED_REL``
        in ``pbrdf_cl.fitting.sample.stages``), the result is the best point found; -1: the residuals
        are not finite at any candidate), ``success`` is ``status > 0`` and ``message`` says which.

    Without given uncertainties (no dop_std) the noise is estimated from the residuals, never
    below ``dop_noise_floor`` (an exact fit would make every interval a point); a note says
    when the floor was used.  Fewer distinct geometries than free parameters are refused.

    x (dict: every model parameter, fitted and fixed, as the model takes them: ``x["kd"]`` is
    the absolute kd, so that ``pbrdf_cl.dop(..., **res.x)`` evaluates the fit), kd_ratio (kd/ks),
    free (names fitted), sse, chi2, reduced_chi2, rmse, residuals, stderr (NaN where the variance
    cannot be computed, as in ``cov``), corr and cov (matrices
    over ``free``), condition_number, aic, bic, dof, nfev and seconds per stage, basins (candidates
    with their SSE), ambiguous, notes (list of sentences), and three kinds of 95% interval (dicts
    name -> (lo, hi)).

    ``cov`` is symmetric positive semi-definite and ``corr`` lies in [-1, 1]: where the matrix as
    computed is not (rounding in the inverse of a near-singular J^T J) it is projected, the
    variances kept, and where a parameter's variance cannot be computed (the data do not change
    with it) its row and column are NaN; a note says which
    (``pbrdf_cl.fitting.common.valid_covariance``).

    Which kd: without intensities the DOP sees kd/ks only, ks is fixed (at 1 unless ``fixed``
    says otherwise) and kd is fitted as itself (equal to kd/ks at ks = 1).  With an intensity
    column (``f00``/``s0``) ks is fitted too and the fitted coordinate is the ratio: ``stderr``,
    the intervals, ``corr`` and ``profiles`` under "kd" are those of kd/ks (``kd_ratio``), while
    ``x["kd"]`` is kd/ks x ks.  ``summary()`` prints both rows, kd/ks and kd, saying which is which.

    ci95
        the central 95% of the parameter's posterior under a uniform prior over the bounds,
        approximated as the equal mixture of two approximations: the local (Laplace) one,
        x +- stderr * (Gaussian, or Student's t without given uncertainties) truncated to the
        bounds, and the device grid's profile likelihood normalised over the bounds (where the
        grid resolves it: its own interval spans at least ``GRID_RESOLVED_CELLS`` cells, of
        ``pbrdf_cl.fitting.sample.uncertainty``).  Where the data determine a parameter this is
        about x +- 1.96 stderr; where they do not, it is the middle 95% of its bounds (not all of
        them), so it covers the truth about 95% of the time in both cases (``scripts/bench_fit.py``
        measures it).  It need not contain x: the best fit of a parameter the data do not
        determine is arbitrary and often sits on a bound: ``outside_ci95`` lists the parameters
        whose best value lies outside, ``summary()`` marks their lines with ``(*)`` and a note
        says why.
    ci95_jacobian
        x +- 1.96 stderr (Student's t without given uncertainties, unless the noise floor was
        used), clipped to the bounds.
    ci95_profile
        likelihood ratio: the grid nodes whose profile is within 3.84 units of chi^2 of the
        optimum, widened to the next node (None where no node is).

    profiles maps each free parameter to the grid's profile: ``values`` (nodes) and ``sse``
    (minimum of the objective over the other parameters at each node).
    """

    def summary(self):
        lines = [f"model: {self['model']}  (shadowing {self['shadowing']}, {self['n_points']} points, "
                 f"{len(self['free'])} free parameters)"]
        if not self.get("fits_data", True):
            lines.append("  WARNING: the model does not describe these data (see the first note); the "
                         "values and intervals below are not to be trusted")
        ratio = "ks" in self["free"] and "kd" in self["free"]  # intensities: kd/ks and ks were fitted
        for name in self["x"]:
            if name == "kd" and ratio:
                lo, hi = self["ci95"][name]
                lines.append(f"  {'kd/ks':6s} = {self['kd_ratio']:10.5g}  +- {self['stderr'][name]:.3g}   "
                             f"95% interval [{lo:.4g}, {hi:.4g}]{self._mark(name)}  (fitted: stderr, ci95, corr of "
                             "'kd')")
                lines.append(f"  {'kd':6s} = {self['x'][name]:10.5g}  (absolute, kd/ks x ks: x['kd'])")
            elif name in self["free"]:
                lo, hi = self["ci95"][name]
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  +- {self['stderr'][name]:.3g}   "
                             f"95% interval [{lo:.4g}, {hi:.4g}]" + self._mark(name) + self._kd_tag(name))
            else:
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  (fixed)" + self._kd_tag(name))
        fit_line = f"  SSE {self['sse']:.4g} ({self.get('observed', 'DOP')}), RMSE {self['rmse']:.4g}"
        if self.get("sigma_known"):  # chi2 means something only with given uncertainties
            fit_line += (f", chi2 {self['chi2']:.4g} for {self['dof']} dof (reduced {self['reduced_chi2']:.3g}, "
                         f"p = {self['p_value']:.3g})")
        lines.append(fit_line + f", AIC {self['aic']:.2f}, BIC {self['bic']:.2f}")
        lines.append("  stages: " + ", ".join(f"{k} {self['nfev'][k]} evals / {self['seconds'][k]:.3f} s"
                                               for k in self["nfev"]))
        if not self.get("success", True):
            lines.append(f"  status {self['status']}: {self['message']}")
        for note in self["notes"]:
            lines.append(f"  note: {note}")
        return "\n".join(lines)

    def fitted_value(self, name):
        """The fitted coordinate of free parameter ``name``, the one its ``stderr`` and ``ci95`` are
        of: ``kd_ratio`` for "kd" where intensities were fitted (kd/ks), else ``x[name]``."""
        if name == "kd" and "ks" in self["free"] and "kd" in self["free"]:
            return self["kd_ratio"]
        return self["x"][name]

    def _mark(self, name):
        """" (*)" where the best value of ``name`` lies outside its own 95% interval (the notes say why)."""
        lo, hi = self["ci95"][name]
        return f" {OUTSIDE_MARK}" if outside_interval(self.fitted_value(name), lo, hi) else ""

    def _kd_tag(self, name):
        """What a DOP-only fit's kd is: the ratio kd/ks where ks is 1, else absolute at the fixed ks."""
        if name != "kd" or "ks" not in self["x"] or "ks" in self["free"]:
            return ""
        ks = self["x"]["ks"]
        return "  (= kd/ks: ks fixed at 1)" if ks == 1.0 else f"  (absolute, with ks fixed at {ks:g})"

    def __repr__(self):
        values = ", ".join(f"{n}={v:.4g}" for n, v in self["x"].items())
        return (f"FitResult(model={self['model']!r}, success={self['success']}, {values}, "
                f"sse={self['sse']:.4g}, notes={len(self['notes'])}; .summary() for the report)")


class ComparisonResult(Result):
    """Result of :func:`pbrdf_cl.compare_models`: ``fits`` (model name -> :class:`FitResult`, also the keys
    "six-param" and "specular"), ``preferred`` (the lower BIC), ``table`` (Markdown) and
    :meth:`summary`."""

    def summary(self):
        lines = ["model comparison (lower AIC/BIC is better):"]
        for name, r in self["fits"].items():
            lines.append(f"  {name:10s} SSE {r.sse:10.4g}  AIC {r.aic:9.2f}  BIC {r.bic:9.2f}  ({len(r.free)} free)")
        lines.append(f"  preferred by BIC: {self['preferred']}")
        return "\n".join(lines)

    def __repr__(self):
        return (f"ComparisonResult(preferred={self['preferred']!r}, "
                + ", ".join(f"{k}: BIC {r.bic:.2f}" for k, r in self["fits"].items()) + ")")


def fit_status(best, final_ran, intensity):
    """FitResult.status from the best candidate, whether the final BOBYQA ran, and the intensity
    stage's candidate (or None)."""
    last = intensity if intensity is not None else best
    if not last.sse < 1e300:
        return -1
    if last.converged is False:
        return 0
    return 2 if final_ran else 1


class Observed(NamedTuple):
    """What a fit's summary statistics are of (the DOP of a DOP fit, the normalised channels of a
    polarimetric one): the measured ``values``, the ``residuals`` of the fit at them (unweighted;
    an AoP's wrapped), whether their uncertainties were given (``sigma_known``) and the ``label``
    of the report's SSE ("DOP", "s1, s2", ...)."""
    values: np.ndarray
    residuals: np.ndarray
    sigma_known: bool
    label: str = "DOP"


def fit_result(meas, model, shadowing, resid, x, lo, hi, unc, cands, grid, stages, status, notes, observed=None):
    """The :class:`FitResult` of :func:`fit` from its stages' outputs; ``observed`` (an
    :class:`Observed`) is what its SSE, RMSE and goodness of fit are of (default: the DOP)."""
    names, free = list(resid.free), list(grid.axes)
    p = resid.params(x)
    if observed is None:
        observed = Observed(meas.dop, resid.model.dop(p) - meas.dop, meas.dop_std is not None)
    sigma_known, dop_resid = observed.sigma_known, observed.residuals
    aic, bic = report.information(unc.chi2, unc.residuals.size, len(names), sigma_known)
    fits_data, p_value, r2, first = _goodness(observed, unc)
    notes = first + _convention_notes(meas) + notes + _bound_notes(names, x, lo, hi, unc.ci95)
    notes += report.uncertainty_notes(names, unc, x, hi - lo)
    if unc.noise_floor is not None:
        notes.append(f"the fit is (nearly) exact: the noise estimated from the residuals (std "
                     f"{np.sqrt(unc.chi2 / unc.dof):.2g}) is below the noise floor, so the uncertainties assume "
                     f"DOP noise of std {unc.noise_floor:.2g} (the larger of the data's DOP resolution "
                     f"{dop_resolution(observed.values):g} / sqrt(12) and {DOP_NOISE_FLOOR:g}); give a dop_std column "
                     "to set it")
    ambiguous = [dict(zip(free, map(float, c.x)), sse=float(c.sse))
                 for c in report.ambiguous(cands, unc.unit, unc.stderr)]
    if ambiguous:
        alt = ", ".join(f"{n}={ambiguous[0][n]:.4g}" for n in free)
        notes.append(f"ambiguous: another basin fits equally well ({alt}: its objective, the weighted sum of "
                     f"squares the local stages minimise, is {ambiguous[0]['sse']:.4g} against the best's "
                     f"{cands[0].sse:.4g}, within one unit of chi2, {unc.unit:.3g}); the data cannot decide "
                     "between them")
    x_out = {n: float(p[n]) for n in PARAMETERS}
    kd_ratio = x_out["kd"] / x_out["ks"]
    if model == "specular":
        x_out = {n: x_out[n] for n in MODEL_PARAMS["specular"]}
    return FitResult(
        model=model, shadowing=shadowing, x=x_out, kd_ratio=float(kd_ratio) if model == "six-param" else None,
        free=names, sse=float(dop_resid @ dop_resid), chi2=unc.chi2,
        reduced_chi2=unc.chi2 / unc.dof, rmse=float(np.sqrt(np.mean(dop_resid ** 2))), residuals=dop_resid,
        dof=unc.dof, n_points=observed.values.size, observed=observed.label,
        stderr=dict(zip(names, map(float, reported_stderr(unc)))), ci95=unc.ci95,
        ci95_jacobian=unc.ci95_jacobian, ci95_profile=unc.ci95_profile,
        profiles={n: dict(values=grid.axes[n], sse=grid.profiles[n]) for n in free},
        corr=_labelled(unc.corr, names, "correlation"), cov=_labelled(unc.cov, names, "covariance"),
        outside_ci95=[n for i, n in enumerate(names) if outside_interval(x[i], *unc.ci95[n])],
        fits_data=fits_data, p_value=p_value, r2=r2,
        condition_number=unc.condition_number, aic=float(aic), bic=float(bic),
        nfev={k: s.nfev for k, s in stages.items()}, seconds={k: s.seconds for k, s in stages.items()},
        basins=[dict(zip(free, map(float, c.x)), sse=float(c.sse), seed=dict(zip(free, map(float, c.seed))))
                for c in cands],
        ambiguous=ambiguous, notes=notes, sigma_known=sigma_known,
        success=status > 0, status=status, message=FIT_STATUS[status])


def model_notes(model, fx, use_f00, meas):
    notes = []
    if model == "six-param" and not use_f00:
        if "ks" in fx:
            notes.append(f"ks is fixed at {fx['ks']:g} by the caller; DOP depends on ks and kd only through "
                         "kd/ks, so kd is determined only relative to that choice")
        else:
            notes.append("DOP depends on ks and kd only through kd/ks: ks is fixed at 1 and kd is the ratio "
                         "kd/ks (add an f00 or s0 intensity column to separate them)")
    if model == "specular" and meas.f00 is not None:
        notes.append("the specular model is fitted to the DOP only; the intensity column was not used")
    if use_f00 and meas.f00_std is None:
        notes.append(f"intensities weighted with an assumed {F00_REL_STD:.0%} relative uncertainty "
                     "(give an f00_std column to set it)")
    dup = duplicates_note(meas)
    if dup:
        notes.append(dup)
    return notes


def _goodness(observed, unc):
    """(fits, p-value or None, R^2 or None, notes) of a fit (:func:`pbrdf_cl.fitting.report.goodness`)
    of ``observed`` (an :class:`Observed`)."""
    values, resid = observed.values, observed.residuals
    sse, sst = float(resid @ resid), float(np.sum((values - values.mean()) ** 2))
    fits, p, r2 = report.goodness(unc.chi2, unc.dof, sse, sst, observed.sigma_known)
    p, r2 = (float(v) if np.isfinite(v) else None for v in (p, r2))
    if fits:
        return True, p, r2, []
    detail = (f" (RMSE {np.sqrt(np.mean(resid ** 2)):.3g} against the data's spread "
              f"{np.sqrt(sst / values.size):.3g})")
    return False, p, r2, [report.not_described(np.nan if p is None else p, r2, unc.chi2, unc.dof,
                                               label=observed.label, detail=detail)]


def _convention_notes(meas):
    """The unit and convention mistakes the data show by themselves."""
    notes = []
    hi = pointwise.radians_suspect(meas.theta_i, meas.theta_r)
    if hi is not None:
        notes.append(f"every theta_i and theta_r lies below {pointwise.RADIANS_HINT} degrees (the largest is "
                     f"{hi:.4g}): radians? pbrdf-cl takes degrees")
    if not meas.phi_given:
        from ...io.measurements import PHI_DEFAULT_NOTE
        notes.append(PHI_DEFAULT_NOTE)
    if np.all(meas.phi == 0.0):
        notes.append("phi = 0 for every point: that is the plane of incidence on the source's side (back-"
                     "scattering); in-plane specular data have phi = 180 here (SCATMECH's phi = 0 is our 180)")
    return notes


def _bound_notes(names, x, lo, hi, ci95):
    """A note for each parameter on a bound, then one for the best values outside their own 95%
    intervals (:func:`pbrdf_cl.fitting.common.outside_note`)."""
    notes, outside = [], []
    for i, n in enumerate(names):
        low, high = on_bound(x[i], lo[i], hi[i])
        side = "lower" if low else ("upper" if high else None)
        a, b = ci95[n]
        if side:
            notes.append(f"{n} = {x[i]:.4g} is on its {side} bound: the data push it there (the optimum may lie "
                         "beyond; widen the bounds if that is physical)")
        if outside_interval(x[i], a, b):
            outside.append(f"{n}'s best value {x[i]:.4g} lies outside its 95% interval [{a:.4g}, {b:.4g}]")
    return notes + ([outside_note(outside)] if outside else [])


def reported_stderr(unc):
    """The standard errors a result reports: NaN where the variance cannot be computed (the NaN
    diagonal of the valid covariance, :func:`pbrdf_cl.fitting.common.valid_covariance`), else
    those of the uncertainty stage."""
    return np.where(np.isnan(np.diag(unc.cov)), np.nan, unc.stderr)


def _labelled(matrix, names, what):
    """``matrix`` over the free parameters as an ``xarray.DataArray`` with their names on both axes."""
    import xarray as xr
    return xr.DataArray(np.asarray(matrix), dims=("param", "param_2"), coords={"param": list(names),
                        "param_2": list(names)}, name=what)
