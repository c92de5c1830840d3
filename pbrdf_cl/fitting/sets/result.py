"""What :func:`pbrdf_cl.fit_joint` returns: :class:`JointResult`, with the separate fits beside
the joint one, and the notes a joint fit carries (which parameters the joint data still cannot
determine, bounds, correlations, goodness of fit)."""
from __future__ import annotations

import numpy as np

from ...io.measurements import duplicates_note
from ...results import Result
from .. import report
from ..common import DOP_NOISE_FLOOR, OUTSIDE_FOOTNOTE, OUTSIDE_MARK, on_bound, outside_interval, outside_note
from ..sample.result import FIT_STATUS, reported_stderr
from ..setup import PARAMETERS

#: A parameter is "not determined" by the joint data where its 95% interval spans more than this
#: fraction of its bounds.
UNDETERMINED_FRACTION = 0.5


class JointResult(Result):
    """Result of :func:`pbrdf_cl.fit_joint`; keys are also attributes (like :class:`FitResult`).

    sets, shared (the shared parameter names), model, shadowing, measurements
        what was fitted: the set names in order, the parameters that take one value for all, and
        set -> the :class:`~pbrdf_cl.io.measurements.Measurements` fitted.
    x, stderr, ci95
        dicts set -> parameter -> value (every model parameter, fitted or held, as
        ``FitResult.x``: ``pbrdf_cl.dop(..., **res.x["a"])`` evaluates set a's fit), standard
        error, 95% interval (lo, hi) (the fitted ones).  Shared parameters repeat in every set.
        ``ci95`` is :class:`FitResult`'s posterior mixture (the joint Jacobian's local
        approximation and the joint grid's profile likelihood), see :class:`FitResult`.
    outside_ci95
        set -> the parameters whose best value lies outside its own 95% interval (marked ``(*)``
        in ``summary()``, a note says why; see :class:`FitResult`).
    shared_x
        shared parameter -> its one value.
    free
        the joint parameter vector's labels: the shared parameters, then ``"n[a]"``, ...
    sse, set_sse, chi2, dof, aic, bic, p_value, r2, fits_data
        the sum of squares of the DOP, or of polarimetric sets' normalised channels (all sets, and
        per set), chi2 (weighted), the information criteria
        of the joint model (same formulas as :class:`FitResult`'s, on the stacked residuals) and
        the goodness-of-fit test.
    separate, separate_aic, separate_bic, width_ratio
        each set fitted alone (set -> :class:`FitResult`, on the same grid), the information
        criteria of all those separate fits together (where they are lower than the joint's
        ``aic``/``bic``, the data prefer separate values of the shared parameters; where higher,
        as usual when sharing is right, the joint model), and set -> parameter -> joint 95% width /
        separate 95% width (below 1: sharing narrowed it).
    exchanged
        the sets whose own parameters the basin exchange moved (refitted alone at the shared
        values, from their grid's valleys, to a lower chi2), one tuple per round kept (empty: the
        joint descent had reached each set's best itself); a note says so.
    corr, cov, condition_number, notes, success, status, message, nfev, seconds
        as :class:`FitResult`'s, over the joint labels (``corr`` and ``cov`` made valid, or NaN
        with a note, as :class:`FitResult`'s); ``seconds["total"]`` the wall time.
    """

    def summary(self):
        sets = self["sets"]
        lines = [f"joint fit: {self['model']} (shadowing {self['shadowing']}), {len(sets)} sets, "
                 f"{self['n_points']} points, {len(self['free'])} free parameters; shared: "
                 f"{', '.join(self['shared']) or 'none'}"]
        if not self.get("fits_data", True):
            lines.append("  WARNING: the model does not describe these data (see the first note)")
        if self["shared"]:
            lines.append("  shared (one value for every set):")
            first = sets[0]
            for p in self["shared"]:
                if p in self["ci95"][first]:
                    ratios = ", ".join(f"{s} x{self['width_ratio'][s][p]:.2g}" for s in sets
                                       if p in self["width_ratio"][s])
                    lines.append(self._line(first, p) + (f"   width / separate: {ratios}" if ratios else ""))
                else:
                    lines.append(f"    {p:6s} = {self['shared_x'][p]:10.5g}  (fixed)")
        for s in sets:
            lines.append(f"  set {s} ({self['separate'][s]['n_points']} points, SSE {self['set_sse'][s]:.4g}):")
            for p, v in self["x"][s].items():
                if p in self["shared"]:
                    continue
                if p in self["ci95"][s]:
                    sep = self["separate"][s]["ci95"].get(p)
                    extra = (f"   separate [{sep[0]:.4g}, {sep[1]:.4g}], width x{self['width_ratio'][s][p]:.2g}"
                             if sep is not None else "")
                    lines.append(self._line(s, p) + extra)
                else:
                    lines.append(f"    {p:6s} = {v:10.5g}  (fixed)")
        fit_line = f"  SSE {self['sse']:.4g} (DOP, all sets)"
        if self.get("sigma_known"):
            fit_line += f", chi2 {self['chi2']:.4g} for {self['dof']} dof (p = {self['p_value']:.3g})"
        lines.append(fit_line + f", AIC {self['aic']:.2f}, BIC {self['bic']:.2f}; set by set: AIC "
                     f"{self['separate_aic']:.2f}, BIC {self['separate_bic']:.2f}")
        lines.append(f"  time {self['seconds']['total']:.3g} s (" + ", ".join(
            f"{k} {v:.3g} s" for k, v in self["seconds"].items() if k != "total") + ")")
        if not self.get("success", True):
            lines.append(f"  status {self['status']}: {self['message']}")
        lines += [f"  note: {note}" for note in self["notes"]]
        return "\n".join(lines)

    def _line(self, s, p):
        lo, hi = self["ci95"][s][p]
        mark = f" {OUTSIDE_MARK}" if outside_interval(self["x"][s][p], lo, hi) else ""
        return (f"    {p:6s} = {self['x'][s][p]:10.5g}  +- {self['stderr'][s][p]:.3g}   95% interval "
                f"[{lo:.4g}, {hi:.4g}]{mark}")

    def to_dataset(self):
        """The result as an ``xarray.Dataset`` over ``set`` and ``param`` (and ``bound``: lo, hi).

        Returns
        -------
        xarray.Dataset
            ``x``, ``stderr``, ``ci95`` (set, param, bound), ``separate_x``, ``separate_ci95``,
            ``width_ratio``, ``outside_ci95`` (set, param: the best value lies outside its own 95%
            interval; its ``long_name`` says why); coordinate ``shared`` (param: whether it is shared); attrs: model,
            shadowing, shared, sse, chi2, aic, bic, separate_aic, separate_bic, notes, exchanged (the
            sets moved in each exchange round kept: "a,c; c").

        Examples
        --------
        >>> ds = res.to_dataset()  # doctest: +SKIP
        >>> ds["ci95"].sel(param="n", bound="hi")  # doctest: +SKIP
        """
        import xarray as xr
        sets = list(self["sets"])
        params = list(self["x"][sets[0]])

        def table(get, extra=()):
            out = np.full((len(sets), len(params)) + tuple(extra), np.nan)
            for i, s in enumerate(sets):
                for j, p in enumerate(params):
                    v = get(s, p)
                    if v is not None:
                        out[i, j] = v
            return out
        sep = self["separate"]
        dims, dims3 = ("set", "param"), ("set", "param", "bound")
        ds = xr.Dataset(
            {"x": (dims, table(lambda s, p: self["x"][s][p])),
             "stderr": (dims, table(lambda s, p: self["stderr"][s].get(p))),
             "ci95": (dims3, table(lambda s, p: self["ci95"][s].get(p), (2,))),
             "separate_x": (dims, table(lambda s, p: sep[s]["x"].get(p))),
             "separate_ci95": (dims3, table(lambda s, p: sep[s]["ci95"].get(p), (2,))),
             "width_ratio": (dims, table(lambda s, p: self["width_ratio"][s].get(p)))},
            coords={"set": sets, "param": params, "bound": ["lo", "hi"],
                    "shared": ("param", [p in self["shared"] for p in params])})
        ds["width_ratio"].attrs["long_name"] = "joint 95% width / separate 95% width"
        ci = ds["ci95"].values
        ds["outside_ci95"] = (dims, outside_interval(ds["x"].values, ci[..., 0], ci[..., 1]),
                              {"long_name": OUTSIDE_FOOTNOTE})
        ds.attrs.update(model=self["model"], shadowing=self["shadowing"], shared=",".join(self["shared"]),
                        sse=self["sse"], chi2=self["chi2"], aic=self["aic"], bic=self["bic"],
                        separate_aic=self["separate_aic"], separate_bic=self["separate_bic"],
                        notes="\n".join(self["notes"]),
                        exchanged="; ".join(",".join(moved) for moved in self["exchanged"]))
        return ds

    def __repr__(self):
        shared = ", ".join(f"{p}={v:.4g}" for p, v in self["shared_x"].items())
        return (f"JointResult(model={self['model']!r}, sets={list(self['sets'])}, success={self['success']}, "
                f"shared: {shared or 'none'}, sse={self['sse']:.4g}, notes={len(self['notes'])}; .summary() for "
                "the report)")


def _goodness(setup, resid, raw, unc):
    """(fits, p-value or None, R^2, notes) of the joint fit, as :func:`pbrdf_cl.fit` tests one
    (:func:`pbrdf_cl.fitting.report.goodness`; R^2 against each set's own mean of what it measures:
    the DOP, or its channels)."""
    sse = sum(float(r @ r) for r in raw.values())
    sst = sum(float(((part.observed - part.observed.mean()) ** 2).sum()) for part in resid.parts)
    fits, p, r2 = report.goodness(unc.chi2, unc.dof, sse, sst, setup.sigma_known)
    p, r2 = (float(v) if np.isfinite(v) else None for v in (p, r2))
    if fits:
        return True, p, r2, []
    if p is None:
        label = "data" if any(m.polarimetric for m in setup.meas.values()) else "DOP"
        return False, p, r2, [report.not_described(np.nan, r2, unc.chi2, unc.dof, label=label)]
    return False, p, r2, [report.not_described(p, r2, unc.chi2, unc.dof, "these data with the shared parameters",
                                               advice="compare separate_aic (the sets fitted alone), and the ")]


def _joint_notes(setup, labels, x, lo, hi, unc):
    """What the joint data still cannot determine, bounds, the noise floor."""
    notes = []
    for i, name in enumerate(labels):
        a, b = unc.ci95[name]
        span = hi[i] - lo[i]
        if b - a > UNDETERMINED_FRACTION * span:
            notes.append(f"{name} is not determined by the joint data: its 95% interval [{a:.4g}, {b:.4g}] spans "
                         f"{(b - a) / span:.0%} of its bounds")
        low, high = on_bound(x[i], lo[i], hi[i])
        side = "lower" if low else ("upper" if high else None)
        if side:
            notes.append(f"{name} = {x[i]:.4g} is on its {side} bound: the data push it there")
    outside = [f"{n}'s best value {x[i]:.4g} lies outside its 95% interval [{unc.ci95[n][0]:.4g}, {unc.ci95[n][1]:.4g}]"
               for i, n in enumerate(labels) if outside_interval(x[i], *unc.ci95[n])]
    if outside:
        notes.append(outside_note(outside))
    notes += report.uncertainty_notes(labels, unc, x, hi - lo)
    if unc.noise_floor is not None:
        notes.append(f"the joint fit is (nearly) exact: the uncertainties assume DOP noise of std "
                     f"{unc.noise_floor:.2g} (at least {DOP_NOISE_FLOOR:g}); give a dop_std column to set it")
    return notes


def _model_notes(setup):
    notes = list(setup.notes)
    if setup.setups[setup.names[0]].model == "six-param":
        what = ("normalised Stokes parameters, Mueller elements, the DOP and the AoP depend"
                if any(m.polarimetric for m in setup.meas.values()) else "DOP depends")
        notes.append(f"{what} on ks and kd only through kd/ks: ks is held (at 1 unless fixed) and each set's kd "
                     "is the ratio kd/ks")
    no_phi = [s for s in setup.names if not setup.meas[s].phi_given]
    if no_phi:
        notes.append(f"phi was not given for set{'s' if len(no_phi) > 1 else ''} {', '.join(no_phi)}: every "
                     "measurement there is taken in plane (phi = 180)")
    for s in setup.names:
        dup = duplicates_note(setup.meas[s])
        if dup:
            notes.append(f"set {s}: {dup}")
    return notes


def _per_set(setup, labels, values):
    """set -> parameter -> values[label] for each set's free parameters."""
    return {s: {p: values[labels.index(p if p in setup.shared else f"{p}[{s}]")] for p in setup.setups[s].free}
            for s in setup.names}


def _width(ci):
    return ci[1] - ci[0]


def joint_result(setup, resid, best, cands, unc, jgrid, separate, stages, status, seconds):
    """The :class:`JointResult` of :func:`pbrdf_cl.fit_joint` from its stages' outputs."""
    import xarray as xr
    labels, lo, hi = list(resid.free), setup.lo, setup.hi
    model = setup.setups[setup.names[0]].model
    xs = resid.split(best.x)
    params = {s: part.params(xs[s]) for s, part in zip(setup.names, resid.parts)}
    reported = PARAMETERS if model == "six-param" else ("n", "k")
    x = {s: {p: float(params[s][p]) for p in reported} for s in setup.names}
    raw = {s: part.raw(params[s]) for s, part in zip(setup.names, resid.parts)}  # the DOP's, or the channels'
    stderr = _per_set(setup, labels, [float(v) for v in reported_stderr(unc)])
    ci95 = _per_set(setup, labels, [tuple(map(float, unc.ci95[n])) for n in labels])
    ratio = {s: {p: _width(ci95[s][p]) / _width(separate[s].ci95[p]) for p in ci95[s]
                 if p in separate[s].ci95 and _width(separate[s].ci95[p]) > 0} for s in setup.names}
    m_obs, n_free = unc.residuals.size, len(labels)
    aic, bic = report.information(unc.chi2, m_obs, n_free, setup.sigma_known)
    sep_aic, sep_bic = report.information(sum(r.chi2 for r in separate.values()), m_obs,
                                    sum(len(r.free) for r in separate.values()), setup.sigma_known)
    fits, p_value, r2, first = _goodness(setup, resid, raw, unc)
    notes = first + _model_notes(setup) + _joint_notes(setup, labels, best.x, lo, hi, unc)
    exchanged = tuple(stages["exchange"].value[1]) if "exchange" in stages else ()
    moved = sorted({s for rnd in exchanged for s in rnd}, key=list(setup.names).index)
    if moved:
        notes.append(f"the basin exchange lowered the chi2 of set{'s' if len(moved) > 1 else ''} "
                     f"{', '.join(moved)}: refitted alone at the shared values (from its grid's valleys) it found "
                     "own parameters the joint descent had not reached; the data have more than one valley")
    amb = report.ambiguous(cands, unc.unit, unc.stderr)
    if amb:
        alt = ", ".join(f"{n}={v:.4g}" for n, v in zip(labels, amb[0].x))
        notes.append(f"ambiguous: another joint optimum fits equally well ({alt}: objective {amb[0].sse:.4g} against "
                     f"{best.sse:.4g}, within one unit of chi2); the data cannot decide between them")
    shared_x = {p: float(best.x[labels.index(p)]) for p in setup.shared}
    shared_x.update({p: float(v) for p, v in setup.shared_fixed.items()})
    corr, cov = (xr.DataArray(np.asarray(m), dims=("param", "param_2"), coords={"param": labels, "param_2": labels},
                              name=name) for m, name in ((unc.corr, "correlation"), (unc.cov, "covariance")))
    timing = {k: float(v.seconds) for k, v in stages.items()}
    timing["total"] = float(seconds)
    return JointResult(
        model=model, shadowing=setup.setups[setup.names[0]].shadowing, sets=list(setup.names),
        measurements=dict(setup.meas),
        shared=[p for p in PARAMETERS if p in setup.shared or p in setup.shared_fixed], shared_x=shared_x,
        free=labels, x=x, stderr=stderr, ci95=ci95, sse=float(sum(r @ r for r in raw.values())),
        set_sse={s: float(r @ r) for s, r in raw.items()}, chi2=float(unc.chi2), dof=int(unc.dof),
        n_points=int(sum(part.observed.size for part in resid.parts)), aic=aic, bic=bic, p_value=p_value, r2=r2,
        fits_data=fits, sigma_known=setup.sigma_known, separate=separate, separate_aic=sep_aic,
        separate_bic=sep_bic, width_ratio=ratio, corr=corr, cov=cov,
        outside_ci95={s: [p for p, (a, b) in ci95[s].items() if outside_interval(x[s][p], a, b)] for s in setup.names},
        condition_number=float(unc.condition_number),
        profiles={n: dict(values=jgrid.axes[n], sse=jgrid.profiles[n]) for n in labels},
        notes=notes, exchanged=exchanged, nfev={k: int(v.nfev) for k, v in stages.items()}, seconds=timing,
        success=status > 0, status=status, message=FIT_STATUS[status])
