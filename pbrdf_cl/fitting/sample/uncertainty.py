"""Uncertainties of a fit (:func:`uncertainty_stage`): the central-difference Jacobian at the
optimum, the covariance, and the three kinds of 95% interval of :class:`pbrdf_cl.FitResult`
(the posterior mixture ``ci95``, ``ci95_jacobian``, ``ci95_profile``)."""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from ..common import (
    CHI2_95,
    X_RESOLUTION,
    bounded_interval,
    fd_jacobian,
    lm_batch,
    null_parameters,
    on_bound,
    seen_through_square,
    valid_covariance,
)
from .basins import local_spacing
from .stages import Residuals, StageResult

#: The grid's profile enters a 95% interval where its own 95% interval spans at least this many
#: grid cells (where it is narrower, the grid does not resolve the parameter).
GRID_RESOLVED_CELLS = 3


@dataclass(frozen=True)
class Uncertainties:
    """Output of :func:`uncertainty_stage` (see :class:`FitResult` for the intervals)."""
    residuals: np.ndarray
    jacobian: np.ndarray
    chi2: float
    dof: int
    stderr: np.ndarray
    cov: np.ndarray
    corr: np.ndarray
    condition_number: float
    eig: tuple
    unit: float
    ci95: dict
    ci95_jacobian: dict
    ci95_profile: dict
    noise_floor: float | None = None  # the noise standard deviation assumed where the fit is exact
    cov_note: str | None = None  # what valid_covariance did to cov and corr (None: valid as computed)


def uncertainty_stage(residuals, x, lo, hi, grid, dop_sse, n_points, sigma_known, noise_floor=None):
    """(e) Statistics and uncertainties at the optimum ``x`` of ``residuals`` (names
    ``residuals.free``): the central-difference Jacobian, covariance, and the three kinds of
    95% interval of :class:`FitResult`; ``grid`` is the :class:`GridStage`, ``dop_sse`` the
    DOP-only objective at the optimum (the grid's scale), ``n_points`` the measurements.

    Without known uncertainties the noise variance is estimated as chi2 / dof; where that is
    below ``noise_floor ** 2`` (see :data:`DOP_NOISE_FLOOR`) the noise is taken as known, of
    standard deviation ``noise_floor`` (``Uncertainties.noise_floor`` says so)."""
    from scipy.stats import norm
    from scipy.stats import t as student_t
    t0 = time.perf_counter()
    names = residuals.free
    R, J = fd_jacobian(residuals.rows, x[None], lo, hi, "central")
    r, J = R[0], J[0].T
    dof = r.size - len(names)
    chi2 = float(r @ r)
    s2 = 1.0 if sigma_known else chi2 / dof
    unit = 1.0 if sigma_known else dop_sse / dof  # one unit of chi^2 on the DOP-only SSE scale
    floored = not sigma_known and noise_floor is not None and not s2 >= noise_floor ** 2
    if floored:  # an (almost) exact fit: the noise is taken as known, at the floor
        s2 = unit = float(noise_floor) ** 2
    known = sigma_known or floored
    cov, cond, eig = _covariance(J, s2, hi - lo)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    # with known uncertainties the Gaussian quantile, else Student's t on the residual dof
    dist = norm if known else student_t(dof)
    q = float(dist.ppf(0.975))
    # never narrower than the optimizer's resolution (noise-free data would give a zero width)
    resolution = X_RESOLUTION * (hi - lo)
    half = np.maximum(q * se, resolution)
    ci_jac = {n: (max(lo[i], x[i] - half[i]), min(hi[i], x[i] + half[i])) for i, n in enumerate(names)}
    # likelihood-ratio intervals from the profile of the grid objective (banana-shaped valleys
    # are not ellipses)
    ci_prof = _profile_intervals(grid.profiles, grid.axes, dop_sse + 3.84 * unit)
    ci = _posterior_intervals(names, J, x, se, lo, hi, grid, StandardCdf(None if known else dof), resolution / q,
                              n_points, known, s2 if floored else 1.0)
    ci = _to_bounds_allowed(ci, residuals, names, x, np.maximum(se, resolution / q), lo, hi, None if known else dof,
                            chi2 + CHI2_95 * s2)
    # symmetric positive semi-definite, correlations in [-1, 1], NaN where they cannot be computed
    valid = valid_covariance(cov)
    out = Uncertainties(r, J, chi2, dof, se, valid.cov, valid.corr, float(cond), eig, unit, ci, ci_jac, ci_prof,
                        noise_floor if floored else None, valid.note(names))
    return StageResult(out, 2 * len(names) + 1, time.perf_counter() - t0)


def squared_parameters(residuals):
    """Which of ``residuals.free`` the data see through their square at their lower bound 0
    (:func:`~pbrdf_cl.fitting.common.seen_through_square`): polarimetric where any set's residuals
    are not the DOP's (or intensities')."""
    parts = getattr(residuals, "parts", [residuals])
    return seen_through_square(residuals.free, not all(isinstance(p, Residuals) for p in parts))


#: Levenberg-Marquardt iterations of the fits held at a bound (:func:`_bounds_allowed`) at most, in
#: rounds of BOUND_ROUND; a round that lowers chi^2 by less than BOUND_STALL of its distance to
#: the threshold ends a test.
BOUND_ITERATIONS = 20
BOUND_ROUND = 5
BOUND_STALL = 0.2


def domain_edges(names, lo, hi):
    """Which of the bounds ``lo``, ``hi`` of the parameters ``names`` (``n``, ``k[set]``, ...) are
    closed edges of the parameter's domain (:data:`pbrdf_cl.model.inputs.REGISTRY`): values a
    material can take exactly, where a truth may lie (k = 0 and kd = 0, c = -1 and c = 0), unlike a
    search range's ends (n = 1 or 5, sigma = 0.05, k = 10)."""
    from ...model.inputs import REGISTRY, Domain
    dom = [REGISTRY[n.split("[")[0]].domain if n.split("[")[0] in REGISTRY else Domain(None) for n in names]
    at_lo = np.array([d.lo is not None and d.lo_included and v == d.lo for d, v in zip(dom, lo)], dtype=bool)
    at_hi = np.array([d.hi is not None and d.hi_included and v == d.hi for d, v in zip(dom, hi)], dtype=bool)
    return at_lo, at_hi


def _to_bounds_allowed(ci, residuals, names, x, se, lo, hi, dof, threshold):
    """The posterior's intervals ``ci``, each taken to a bound on its domain's edge
    (:func:`domain_edges`: k = 0, kd = 0, c = -1 or 0) that the data allow: where the local
    approximation's interval reaches it (the best values +- 1.96 standard errors, Student's t with
    ``dof``, cut at the bounds, k's holding k^2's, :func:`~pbrdf_cl.fitting.common.bounded_interval`:
    a finite standard error only), the fit held at the bound, the other parameters descended
    from the best values, ends within the likelihood-ratio test's ``threshold`` of chi^2 (its
    best chi^2 + 3.84 units; :func:`_bounds_allowed`).  The central 95% of a posterior over the
    bounds never holds a bound: a dielectric of k = 0 fitted with k = 0.21 +- 0.36 had [0.019,
    0.97], and on 40 such fits (the paper's geometry, noise 0.003 and 0.01) k = 0 was covered 16
    times.  The test, not the local approximation alone, decides: far from the best values it is
    not to be trusted (the bundled steel's k = 2.59 +- 0.83, whose k^2 +- 1.96 standard errors
    reach 0, is 1.28 or more by the posterior, and the test agrees)."""
    reach_lo, reach_hi = bounded_interval(x, se, lo, hi, dof, squared_parameters(residuals))
    edge_lo, edge_hi = domain_edges(names, lo, hi)
    finite = np.isfinite(se)
    a = np.array([ci[n][0] for n in names], dtype=float)
    b = np.array([ci[n][1] for n in names], dtype=float)
    tests = [(i, lo[i]) for i in np.flatnonzero(finite & edge_lo & (reach_lo <= lo) & (lo < a))]
    tests += [(i, hi[i]) for i in np.flatnonzero(finite & edge_hi & (reach_hi >= hi) & (b < hi))]
    out = dict(ci)
    for (i, bound), ok in zip(tests, _bounds_allowed(residuals, x, lo, hi, tests, threshold)):
        if ok:
            low, high = out[names[i]]
            out[names[i]] = (float(bound), high) if bound == lo[i] else (low, float(bound))
    return out


def _bounds_allowed(residuals, x, lo, hi, tests, threshold):
    """For each (parameter i, bound) of ``tests``, whether the fit with that parameter held at the
    bound, the others descended from ``x``, comes within ``threshold`` of chi^2: batched descents
    (:func:`~pbrdf_cl.fitting.common.lm_batch`, every test in one: a test's held parameter is its
    extra columns' and the rows do not depend on its own column, so that it stays put) in rounds of
    :data:`BOUND_ROUND` iterations, at most :data:`BOUND_ITERATIONS` in all; a test ends where it
    comes within the threshold (allowed) or where a round lowered its chi^2 by less than
    :data:`BOUND_STALL` of its distance to the threshold (not allowed)."""
    if not tests:
        return []
    which = np.array([i for i, _ in tests])
    at = np.array([v for _, v in tests], dtype=float)
    X = np.repeat(x[None], len(tests), axis=0)
    X[np.arange(len(tests)), which] = at

    def rows(Y):
        Z = Y[:, :-2].copy()
        Z[np.arange(len(Z)), Y[:, -2].astype(np.intp)] = Y[:, -1]
        return residuals.rows(Z)
    r = rows(np.column_stack([X, which, at]))
    sse = np.einsum("pm,pm->p", r, r)
    allowed = sse <= threshold
    live = np.flatnonzero(~allowed)
    for _ in range(0, BOUND_ITERATIONS, BOUND_ROUND):
        if not live.size:
            break
        X[live], new, _ = lm_batch(rows, X[live], lo, hi, BOUND_ROUND, extra=np.column_stack([which[live], at[live]]))
        stalled = sse[live] - new < BOUND_STALL * (sse[live] - threshold)
        sse[live] = np.minimum(sse[live], new)
        allowed[live] = sse[live] <= threshold
        live = live[~allowed[live] & ~stalled]
    return list(allowed)


def _posterior_intervals(names, J, x, se, lo, hi, grid, dist, min_se, n_points, sigma_known, chi2_unit=1.0):
    """95% intervals: the posterior under a uniform prior over the bounds, the equal mixture of
    the local (Laplace) approximation and the grid's profile (where the grid resolves it; its
    SSE divided by ``chi2_unit`` is chi^2 when ``sigma_known``)."""
    ci = {}
    col = np.linalg.norm(J, axis=0)
    for i, n in enumerate(names):
        # a direction the DOP does not depend on at all has no finite standard error
        se_i = np.inf if col[i] <= 1e-12 * max(col.max(), 1e-300) else max(se[i], min_se[i])
        cdfs = [_truncated_cdf(dist, x[i], se_i, lo[i], hi[i])]
        if n in grid.axes:
            # the grid's profile counts where the grid resolves it: its own 95% interval spans
            # several cells (a valley, a banana, a flat stretch); else it only says "near the
            # best node", which the local approximation says better
            prof, vals = grid.profiles[n], grid.axes[n]
            g = _grid_cdf(prof / chi2_unit, vals, n_points, sigma_known)
            g_a, g_b = _central_interval([g], x[i], se_i, lo[i], hi[i], vals)
            resolved = g_b - g_a >= GRID_RESOLVED_CELLS * local_spacing(vals, int(np.argmin(prof)))
            if np.isinf(se_i):
                # the local approximation says nothing (an infinite standard error: the uniform
                # prior): the profile alone, one-sided from a bound the best value is on (k = 0,
                # where the profile is flattest: a central interval would leave out the values
                # the data fit best); where the grid does not resolve it, out to the nodes
                # around (not the uniform prior's [0.25, 9.75], which left out k = 0 itself)
                a, b = _profile_alone(g, x[i], lo[i], hi[i], vals)
                if not resolved:
                    a = float(vals[max(np.searchsorted(vals, a, side="right") - 1, 0)])
                    b = float(vals[min(np.searchsorted(vals, b, side="left"), vals.size - 1)])
                ci[n] = (a, b)
                continue
            if resolved:
                cdfs.append(g)
        ci[n] = _central_interval(cdfs, x[i], se_i, lo[i], hi[i], grid.axes.get(n, ()))
    return ci


#: The pseudo-inverse's cutoff of J^T J (a fraction of its largest singular value).
PINV_RCOND = 1e-15


def _profile_alone(g, x, lo, hi, nodes):
    """The 95% interval of the grid profile's distribution ``g`` alone: from the bound ``x`` lies on
    (:func:`~pbrdf_cl.fitting.common.on_bound`) to its 95% quantile (or from its 5% quantile), else its central
    95%."""
    low, high = on_bound(x, lo, hi)
    if low:
        return lo, _central_interval([g], x, np.inf, lo, hi, nodes, level=0.90)[1]
    if high:
        return _central_interval([g], x, np.inf, lo, hi, nodes, level=0.90)[0], hi
    return _central_interval([g], x, np.inf, lo, hi, nodes)


def _covariance(J, s2, scale):
    """Covariance s2 (J^T J)^+ and, in parameters scaled by their bound ranges, the condition
    number and eigen-decomposition of J^T J.  The parameter that a direction the data do not see
    there mostly is (an eigenvalue at most NULL_RCOND of the largest, scaled: k at k = 0, where
    the model's derivative in k vanishes) gets an infinite variance, not the small one the
    pseudo-inverse leaves it where it cuts that direction off
    (:func:`~pbrdf_cl.fitting.common.null_parameters`; k = 0 had come out +- 5e-6); the others
    keep theirs (the direction moves them by a few millionths of their ranges)."""
    JtJ = J.T @ J
    cov = s2 * np.linalg.pinv(JtJ, rcond=PINV_RCOND)
    Js = J * scale[None, :]
    w, v = np.linalg.eigh(Js.T @ Js)
    np.fill_diagonal(cov, np.where(null_parameters(w, v, share=0.5), np.inf, np.diag(cov)))
    cond = w[-1] / w[0] if w[0] > 0 else np.inf
    return cov, cond, (w, v)


def _profile_intervals(profiles, axes, threshold):
    """For each free parameter, the range of grid values whose profile (min SSE over the other
    parameters) is below ``threshold``, widened to the neighbouring nodes; None where no node is."""
    out = {}
    for n, prof in profiles.items():
        ok = np.nonzero(prof <= threshold)[0]
        if ok.size == 0:
            out[n] = None
            continue
        vals = axes[n]
        out[n] = (float(vals[max(ok[0] - 1, 0)]), float(vals[min(ok[-1] + 1, vals.size - 1)]))
    return out


class StandardCdf:
    """The standard normal distribution (``dof`` None) or Student's t with ``dof`` degrees of freedom,
    its ``cdf`` alone: scipy.special's ``ndtr`` and ``stdtr``, the functions scipy.stats' ``norm.cdf``
    and ``t(dof).cdf`` evaluate, the same numbers bit for bit without their argument handling of
    each call (about 80 microseconds; some 70 calls a joint fit, 20 a fit)."""

    def __init__(self, dof=None):
        from scipy.special import ndtr, stdtr
        self.cdf = ndtr if dof is None else functools.partial(stdtr, dof)


def _truncated_cdf(dist, x, se, lo, hi):
    """CDF of ``x + se * dist`` truncated to [lo, hi] (the Laplace approximation of the posterior
    under a uniform prior over the bounds), as a function of the parameter value; an infinite
    ``se`` (a direction the data do not constrain at all) gives the uniform prior itself."""
    if not np.isfinite(se):
        return lambda t: np.clip((t - lo) / (hi - lo), 0.0, 1.0)
    a, b = dist.cdf((lo - x) / se), dist.cdf((hi - x) / se)
    if not b - a > 1e-300:  # x many standard errors outside the bounds: cannot happen for a fit's x
        return lambda t: (np.asarray(t) >= x).astype(float)
    return lambda t: np.clip((dist.cdf((np.asarray(t) - x) / se) - a) / (b - a), 0.0, 1.0)


def _grid_cdf(prof, vals, n_obs, sigma_known):
    """CDF of one parameter's grid profile likelihood (``prof`` at the nodes ``vals``) normalised
    over its bounds (a uniform prior), the likelihood linear between nodes.  With known
    uncertainties the likelihood is exp(-chi2 / 2); else the noise is integrated out (Jeffreys
    prior): SSE^(-N/2).  Where the data are weak this follows the valley wherever it goes
    (banana-shaped and multimodal profiles); where they are sharp the grid's nodes miss the
    valley floor and it is only as fine as the grid."""
    prof = np.where(np.isfinite(prof), prof, np.inf)
    ref = prof.min()
    if sigma_known:
        w = np.exp(-0.5 * (prof - ref))
    else:
        w = np.exp(-0.5 * n_obs * np.log(np.maximum(prof, 1e-300) / max(ref, 1e-300)))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(vals))])
    if not cdf[-1] > 0:  # one node: all the mass there
        k = float(vals[int(np.argmin(prof))])
        return lambda t: (np.asarray(t) >= k).astype(float)
    cdf /= cdf[-1]
    return lambda t: np.interp(t, vals, cdf)


def _central_interval(cdfs, x, se, lo, hi, nodes=(), level=0.95):
    """Central ``level`` interval of the equal-weight mixture of the distributions ``cdfs``
    (callables), found on a mesh over [lo, hi] refined around x (+-8 se) and at ``nodes``."""
    mesh = [np.linspace(lo, hi, 2001), np.asarray(nodes, float)]
    if np.isfinite(se) and se > 0:
        mesh.append(x + se * np.linspace(-8, 8, 321))
    mesh = np.unique(np.clip(np.concatenate(mesh + [[x]]), lo, hi))
    cdf = np.mean([c(mesh) for c in cdfs], axis=0)
    cdf = np.maximum.accumulate(cdf)
    tail = (1 - level) / 2

    def inverse(p):  # linear inside the mesh cell that brackets p
        j = int(np.clip(np.searchsorted(cdf, p, side="left"), 1, mesh.size - 1))
        c0, c1 = cdf[j - 1], cdf[j]
        return float(mesh[j] if c1 <= c0 else mesh[j - 1] + (p - c0) / (c1 - c0) * (mesh[j] - mesh[j - 1]))
    return inverse(tail), inverse(1 - tail)
