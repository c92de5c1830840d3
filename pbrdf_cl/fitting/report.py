"""What every kind of fit reports the same way (a sample, several sets, the pixels of an image and its
labels): the goodness-of-fit test (:func:`goodness`, :func:`not_described`), the information
criteria (:func:`information`), the check for other basins that fit as well (:func:`ambiguous`)
and the notes on what the data do not determine (:func:`identifiability_notes`).  The constants
they test against (``GOODNESS_P``, ``GOODNESS_R2``, ``MISTAKE_CAUSES``) are
:mod:`pbrdf_cl.fitting.common`'s."""
from __future__ import annotations

from typing import Protocol

import numpy as np

from .common import GOODNESS_P, GOODNESS_R2, MISTAKE_CAUSES

#: How many of the strongest correlations the notes name.
MAX_CORR_NOTES = 3


class FitReport(Protocol):
    """What a sample's fit (:class:`~pbrdf_cl.fitting.sample.result.FitResult`) and a joint fit of
    several sets (:class:`~pbrdf_cl.fitting.sets.result.JointResult`) both report, under one name
    and with one meaning (their keys, also attributes).  A joint fit's ``x``, ``stderr``, ``ci95``
    and ``outside_ci95`` are per set (set -> the sample's dict); everything else has the sample's
    shape.  An image fit's ``xarray.Dataset`` holds the per-pixel fields of :data:`PIXEL_FIELDS`
    under the same names."""

    success: bool            #: ``status > 0``
    status: int              #: 1 converged, 2 converged after a budget ran out on a flat valley, 0 a
                             #: budget ran out while the objective still fell, -1 no finite residuals
    message: str             #: what ``status`` means here
    model: str               #: "six-param" or "specular"
    shadowing: str           #: the shadowing variant
    free: list               #: the names of the fitted coordinates (order of ``corr`` and ``cov``)
    x: dict                  #: every model parameter as the model takes it (fitted and held)
    stderr: dict             #: standard errors (NaN where the variance cannot be computed)
    ci95: dict               #: 95% intervals (lo, hi) of the fitted parameters (the posterior mixture)
    outside_ci95: object     #: the parameters whose best value lies outside their ci95
    sse: float               #: sum of squared residuals
    chi2: float              #: weighted sum of squared residuals
    dof: int                 #: measurements minus free parameters
    p_value: float           #: of chi2 on dof (NaN without given uncertainties)
    r2: float                #: share of the data's variance the fit explains
    fits_data: bool          #: the goodness-of-fit test (:func:`goodness`)
    aic: float               #: Akaike's information criterion (:func:`information`)
    bic: float               #: the Bayesian information criterion
    sigma_known: bool        #: whether the data gave their uncertainties
    n_points: int            #: measurements fitted
    corr: np.ndarray         #: correlation matrix over ``free`` (valid, or NaN rows and a note)
    cov: np.ndarray          #: covariance matrix over ``free``
    condition_number: float  #: of the scaled J^T J
    profiles: dict           #: the grid's profile of each free parameter
    notes: list              #: sentences on what the data do and do not determine
    nfev: dict               #: model evaluations per stage
    seconds: dict            #: wall time per stage and in total


#: The fields of :class:`FitReport`, in its order.
RESULT_FIELDS = tuple(FitReport.__annotations__)
#: The fields of :class:`FitReport` an image fit's Dataset holds per pixel (variables of the same
#: names; the parameters' values, ``stderr``, ``ci95`` and ``outside_ci95`` as ``n``,
#: ``n_stderr``, ``n_ci95``, ``n_outside_ci95``, ...).
PIXEL_FIELDS = ("status", "sse", "chi2", "p_value", "r2", "fits_data", "nfev")


def chi2_p_value(chi2, dof):
    """The p-value of ``chi2`` on ``dof`` degrees of freedom (arrays or scalars; NaN where dof <= 0)."""
    from scipy.stats import chi2 as chi2_dist
    dof = np.asarray(dof)
    return np.where(dof > 0, chi2_dist.sf(chi2, np.maximum(dof, 1)), np.nan)


def goodness(chi2, dof, sse, sst, sigma_known):
    """Whether the model describes the data, as every fit tests it: (fits, p-value, R^2), arrays or
    scalars alike.  With given uncertainties (``sigma_known``) chi2 on ``dof`` degrees of freedom
    must reach a p-value of GOODNESS_P; without them the fit must explain GOODNESS_R2 of the data's
    variance (R^2 = 1 - sse / sst; data that do not vary pass).  NaN where a statistic does not
    apply."""
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(np.asarray(sst) > 0, 1.0 - np.asarray(sse) / sst, np.nan)
    if sigma_known:
        p = chi2_p_value(chi2, dof)
        fits = ~(p < GOODNESS_P)
    else:
        p = np.full(np.shape(r2), np.nan)
        fits = ~(r2 < GOODNESS_R2)
    return fits, p, r2


def not_described(p, r2, chi2, dof, what="these data", label="DOP", detail="", advice=""):
    """The note of a failed goodness test: chi2 and its p-value, or the share of ``label``'s variance
    explained (``detail``: more on it), then ``advice`` and the usual causes."""
    if np.isfinite(p):
        head = f"the model does not describe {what}: chi2 = {chi2:.4g} for {dof} degrees of freedom (p = {p:.2g})"
    else:
        head = f"the model does not describe {what}: it explains {max(r2, 0):.0%} of the {label}'s variance{detail}"
    return f"{head}; {advice}usual causes: {MISTAKE_CAUSES}"


def information(chi2, m_obs, n_free, sigma_known):
    """(AIC, BIC): -2 log L up to a constant is chi2 with known uncertainties, else m log(SSE / m)."""
    neg2ll = chi2 if sigma_known else m_obs * np.log(max(chi2, 1e-300) / m_obs)
    return float(neg2ll + 2 * n_free), float(neg2ll + n_free * np.log(m_obs))


def ambiguous(cands, unit, se):
    """The other candidates (best first in ``cands``) within one ``unit`` of chi^2 of the best and
    more than 2 standard errors ``se`` away from it in some parameter: other basins that fit the
    data as well."""
    best = cands[0]
    se = np.maximum(se[:best.x.size], 1e-12)
    return [c for c in cands[1:] if c.sse - best.sse <= unit and np.any(np.abs(c.x - best.x) > 2 * se)]


def uncertainty_notes(names, unc, x, scale):
    """The notes of a fit's uncertainty stage ``unc`` (a
    :class:`~pbrdf_cl.fitting.sample.uncertainty.Uncertainties` over ``names``, at the optimum ``x``,
    ``scale`` the bound ranges): :func:`identifiability_notes`, then what was done to make the
    covariance valid (``cov_note``), as a sample's and a joint fit both report them."""
    notes = identifiability_notes(names, unc.jacobian, unc.condition_number, unc.eig, x, unc.stderr, unc.corr, scale)
    return notes + ([unc.cov_note] if unc.cov_note else [])


def identifiability_notes(names, J, cond, eig, x, se, corr, scale):
    """The notes on what the data do not determine: a near-degenerate direction (condition number
    ``cond`` of the scaled J^T J, eigen-decomposition ``eig``), parameters the data do not change
    with or poorly determined (``se``), strong correlations (``corr``); ``J`` the Jacobian over
    ``names``, ``x`` the optimum, ``scale`` the bound ranges."""
    notes = []
    w, v = eig
    if not np.isfinite(cond) or cond > 1e4:
        weak = v[:, 0]
        order = np.argsort(-np.abs(weak))
        terms = " ".join(f"{'+' if weak[i] >= 0 else '-'} {abs(weak[i]):.2f} d{names[i]}" for i in order[:3]
                         if abs(weak[i]) > 0.1)
        notes.append(f"near-degenerate direction (condition number {cond:.2g} in parameters scaled to their "
                     f"bounds): the data barely constrain the combination {terms.lstrip('+ ')}")
    col = np.linalg.norm(J, axis=0) * scale
    for i, n in enumerate(names):
        if col[i] < 1e-8 * max(col.max(), 1e-300):
            notes.append(f"{n} is not determined by these data (the DOP does not change with it here"
                         + ("; with kd = 0 the DOP does not depend on sigma or c" if n in ("sigma", "c") else "")
                         + ")")
        elif abs(x[i]) > 0 and se[i] > 0.5 * abs(x[i]):
            notes.append(f"{n} is poorly determined: standard error {se[i]:.3g} on {x[i]:.4g}")
    pairs = sorted(((abs(corr[i, j]), i, j) for i in range(len(names)) for j in range(i + 1, len(names))
                    if np.isfinite(corr[i, j]) and abs(corr[i, j]) > 0.95), key=lambda t: -t[0])
    if pairs:
        shown = ", ".join(f"{names[i]}-{names[j]} (r = {corr[i, j]:+.3f})" for _, i, j in pairs[:MAX_CORR_NOTES])
        more = f", and {len(pairs) - MAX_CORR_NOTES} more (see .corr)" if len(pairs) > MAX_CORR_NOTES else ""
        notes.append(f"strongly correlated: {shown}{more}")
    return notes
