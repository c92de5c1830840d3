"""Per-pixel statistics of an image fit (:func:`statistics`): covariance from J^T J, 95% intervals
(the best values +- 1.96 standard errors, Student's t without known noise, cut at the bounds:
:func:`~pbrdf_cl.fitting.common.bounded_interval`; a pixel's k, poorly determined by its few
measurements, without the labels' hull with k^2's interval, which would take a metal's pixels'
intervals to k = 0 that a fit held there rejects), ``determined``,
ambiguity, the status codes of :data:`pbrdf_cl.fitting.images.dataset.PIXEL_STATUS` and each pixel's
goodness-of-fit test (as :func:`pbrdf_cl.fit` tests a fit)."""
from __future__ import annotations

import numpy as np

from .. import report
from ..common import NULL_RCOND, X_RESOLUTION, bounded_interval, null_parameters, valid_covariance
from .pixels import PixelResiduals, descent_bounds, internal

#: A parameter counts as determined by a pixel's data where its 95% interval is narrower than
#: this fraction of its bound range.
DETERMINED_FRACTION = 0.5


def _covariances(jtj, s2, span):
    """Covariance (p, D, D) from J^T J in internal coordinates (pseudo-inverse in coordinates
    scaled to the bounds: a direction the data do not see gets an infinite variance), made valid
    (:func:`pbrdf_cl.fitting.common.valid_covariance`: NaN in the rows and columns of a parameter
    without a finite variance), and the variances (p, D) (inf along a direction the data do not see)."""
    A = jtj * span[None, :, None] * span[None, None, :]
    eigval, eigvec = np.linalg.eigh(A)
    top = np.maximum(eigval.max(axis=1, keepdims=True), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(eigval > NULL_RCOND * top, 1.0 / eigval, np.inf)
    # infinite variance along a null direction: var_i = sum_k v_ik^2 / l_k (inf where v_ik != 0)
    with np.errstate(invalid="ignore"):
        cov = np.einsum("pik,pk,pjk->pij", eigvec, np.where(np.isinf(inv), 0.0, inv), eigvec)
        null = null_parameters(eigval, eigvec)
    cov = cov * span[None, :, None] * span[None, None, :] * s2[:, None, None]
    var = np.where(null, np.inf, np.einsum("pii->pi", cov))
    # valid (symmetric positive semi-definite), NaN in the rows and columns of the parameters of
    # infinite (null directions) or no variance
    np.einsum("pii->pi", cov)[...] = var
    return valid_covariance(cov).cov, var


def statistics(setup, blk, names, xb, chi2, jtj, settled, X_all, sse_all, nfev):
    """The per-pixel outputs of a block (the keys of :func:`pbrdf_cl.fitting.images.dataset.empty_outputs`)
    from each pixel's best point ``xb`` (p, D) over ``names``, its objective ``chi2``, ``jtj`` (J^T J
    in the descent's coordinates), whether its descent ``settled``, every start's end (``X_all``,
    ``sse_all``: the ambiguity test) and the evaluations ``nfev``."""
    p, D = xb.shape
    lo, hi = descent_bounds(setup, names)
    span = hi - lo
    n_valid = blk.count + (blk.valid.sum(axis=1) if setup.use_f00 else 0)
    dof = np.maximum(n_valid - D, 1)
    if setup.sigma_known:
        s2 = np.ones(p)
    else:
        s2 = np.maximum(chi2 / dof, blk.noise_floor ** 2)
    cov, var = _covariances(jtj, s2, span)
    se_int = np.sqrt(np.clip(var, 0, None))
    xi = internal(xb, names)
    resolution = X_RESOLUTION * span
    floored = setup.sigma_known or (chi2 / dof < blk.noise_floor ** 2)
    se_i = np.maximum(se_int, resolution)
    lo95 = np.empty((p, D))
    hi95 = np.empty((p, D))
    known = floored if np.ndim(floored) else np.full(p, bool(floored))
    for kind in (True, False):
        sel = known == kind
        if not sel.any():
            continue
        l_, h_ = bounded_interval(xi[sel], se_i[sel], lo, hi, None if kind else dof[sel][:, None])
        lo95[sel], hi95[sel] = l_, h_
    determined = (hi95 - lo95) < DETERMINED_FRACTION * span
    ci = np.stack([lo95, hi95], axis=-1)
    se = se_int.copy()
    # DOP-only SSE (unweighted) at the optimum, from the descent's parameters (kd as kd/ks with
    # intensities: it is made absolute just below)
    dop_sse = _dop_sse(setup, blk, names, xb)
    xb = xb.copy()
    if "ks" in names:  # back to ks from log ks, and kd from kd/ks (reported as in pbrdf_cl.fit)
        j = names.index("ks")
        ci[:, j] = np.exp(ci[:, j])
        se[:, j] = se_int[:, j] * xb[:, j]
        if "kd" in names:
            d, ks = names.index("kd"), xb[:, j]
            ratio = xb[:, d].copy()
            # kd = ratio ks, d kd = ks d ratio + ratio ks d(log ks)
            with np.errstate(invalid="ignore"):
                var = ks ** 2 * (cov[:, d, d] + ratio ** 2 * cov[:, j, j] + 2 * ratio * cov[:, d, j])
            var = np.where(np.isinf(se_int[:, d]) | np.isinf(se_int[:, j]) | np.isnan(var), np.inf, var)
            xb[:, d] = ratio * ks
            se[:, d] = np.sqrt(np.clip(var, 0, None))
            kd_hi = setup.hi[setup.free.index("kd")] * ks
            l_, h_ = bounded_interval(xb[:, d], np.maximum(se[:, d], resolution[d] * ks), 0.0 * ks, kd_hi,
                                      None if setup.sigma_known else dof)
            ci[:, d, 0], ci[:, d, 1] = l_, h_
    # ambiguity: another start within one unit of chi2, more than 2 standard errors away
    unit = np.where(setup.sigma_known, 1.0, s2)
    D0 = len(setup.free)
    best = chi2 if not setup.use_f00 else np.min(sse_all, axis=0)
    close = (sse_all - np.min(sse_all, axis=0)[None]) <= unit[None]
    far = np.any(np.abs(X_all - X_all[np.argmin(sse_all, axis=0), np.arange(p)][None])
                 > 2 * np.maximum(se[None, :, :D0], 1e-12), axis=-1)
    ambiguous = np.any(close & far, axis=0)
    on_bound = np.any((xi <= lo + resolution) | (xi >= hi - resolution), axis=1)
    status = np.ones(p, np.int8)
    status[on_bound] = 2
    status[ambiguous] = 3
    status[~determined.all(axis=1)] = 4
    status[~settled] = 0
    status[~np.isfinite(best)] = -3
    failed = status == -3
    r2, p_value, fits = _goodness(setup, blk, dop_sse, chi2, n_valid - D)
    out = {"x": xb, "stderr": se, "ci95": ci, "determined": determined & ~failed[:, None], "chi2": chi2,
           "sse": dop_sse, "r2": r2, "p_value": p_value, "fits_data": np.where(failed, -1, fits).astype(np.int8),
           "nfev": nfev, "status": status}
    for k in ("x", "stderr", "ci95", "chi2", "sse", "r2", "p_value"):
        out[k] = np.where(failed.reshape((-1,) + (1,) * (out[k].ndim - 1)), np.nan, out[k]).astype(float)
    return out


def _goodness(setup, blk, dop_sse, chi2, dof):
    """Per pixel, as :func:`pbrdf_cl.fit` tests a fit (:func:`pbrdf_cl.fitting.report.goodness`):
    (R^2 of the DOP, the p-value of chi2 with ``dof`` degrees of freedom (NaN without dop_std), 1
    where the model describes the pixel's data else 0; a pixel whose DOP does not vary passes)."""
    n = np.maximum(blk.count, 1)
    mean = (blk.obs * blk.valid).sum(axis=1) / n
    sst = np.where(blk.valid, blk.obs - mean[:, None], 0.0)
    sst = np.einsum("pm,pm->p", sst, sst)
    fits, p_value, r2 = report.goodness(chi2, dof, dop_sse, sst, setup.sigma_known)
    return r2, p_value, fits.astype(np.int8)


def _dop_sse(setup, blk, names, xb):
    """Sum of squared (unweighted) DOP residuals over each pixel's valid measurements, float64
    reference model."""
    res = PixelResiduals(setup, blk, names, np.arange(blk.p), setup.use_f00, weights=blk.valid.astype(float))
    r = np.where(blk.valid, res.rows(internal(xb, names))[:, :blk.valid.shape[1]], 0.0)
    return np.einsum("pm,pm->p", r, r)
