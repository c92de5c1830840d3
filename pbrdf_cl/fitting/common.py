"""The internal interface the modules of :mod:`pbrdf_cl.fitting` share (scipy's ``_lsq/common.py``
in spirit), and :func:`pbrdf_cl.design` with them:

- finite differences and the batched descent: :func:`fd_jacobian` (forward, scipy's steps, or
  central), :func:`lm_batch` (bounded Levenberg-Marquardt from many starts at once; the numpy
  backend's per-pixel descent and :func:`pbrdf_cl.fit`'s screen stage);
- the noise floor of fits without given uncertainties: :data:`DOP_NOISE_FLOOR`,
  :func:`dop_resolution`, :func:`dop_noise_floor`; the resolution of a located optimum
  (:data:`X_RESOLUTION`);
- the goodness-of-fit test of a fit, of each pixel and of each label of an image fit:
  :data:`GOODNESS_P`, :data:`GOODNESS_R2` and the usual causes of a failure named in their notes
  (:data:`MISTAKE_CAUSES`, :data:`LABEL_MISTAKE_CAUSES`);
- the covariances every fit reports, made valid in one place (:func:`valid_covariance`: symmetric
  positive semi-definite, correlations in [-1, 1], NaN where they cannot be computed, a note);
- a best value outside its own 95% interval, decided in one place (:func:`outside_interval`) and
  marked and explained in one wording (:data:`OUTSIDE_MARK`, :func:`outside_note`,
  :data:`OUTSIDE_FOOTNOTE`).
"""
import functools
from dataclasses import dataclass

import numpy as np

#: Resolution of the located optimum, as a fraction of each parameter's bound range: the
#: smallest half-width a 95% interval is given.
X_RESOLUTION = 1e-8
#: A value within this fraction of its bound range of a bound is on that bound (the fit's notes,
#: the one-sided intervals at a bound, the label stage's refit from inside).
BOUND_TOL = 1e-6
#: Without given uncertainties (no dop_std) the DOP noise is estimated from the residuals, and an
#: exact fit (noise-free synthetic data; as many distinct geometries as free parameters) would make
#: it zero and every interval a point.  The estimate is never taken below a floor: the standard
#: deviation of the rounding error of the data's DOP resolution (step / sqrt(12), the step read
#: from the decimals of the values, e.g. 0.01 for "0.25, 0.31, ..."), and at least this value, a
#: conservative precision of DOP measurement (polarimeters resolve DOP to about 1e-3 to 1e-2).
DOP_NOISE_FLOOR = 1e-3
#: The most decimals :func:`dop_resolution` looks for (more: no resolution is read from the values).
DOP_MAX_DECIMALS = 8
#: With given uncertainties, a chi2 whose p-value is below this says the model does not fit.
GOODNESS_P = 1e-3
#: Without them, a fit that explains less than this fraction of the DOP's variance does not fit.
GOODNESS_R2 = 0.9
#: What usually makes a fit fail the goodness-of-fit test (named in its note and warning).
MISTAKE_CAUSES = ("angles in radians (pbrdf-cl takes degrees), the phi convention (180 is in plane, the specular "
                  "side; SCATMECH's 0), another shadowing variant (shadowing=), DOP in percent or dop_std too small")
#: What usually makes a label of an image fit fail its goodness-of-fit test: its pixels do not
#: share one material, then the causes of any fit.
LABEL_MISTAKE_CAUSES = ("two materials under one label (split it: its pixels do not share one n, k), " + MISTAKE_CAUSES)


def one_blas_thread(func):
    """``func`` with BLAS (numpy's OpenBLAS) on one thread while it runs: the local stages' BLAS
    calls (a residual vector's dot product, least squares' J^T J) are small and many, and BLAS's
    threads, woken by each of those over 10,000 measurements, spin between them: on two cores a
    fifth of a 20,000-row fit's CPU time, taken from the model's values (the same sums: below that
    size BLAS runs on one thread anyway, and on one thread its sums do not depend on the cores)."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        from threadpoolctl import threadpool_limits
        with threadpool_limits(1, user_api="blas"):
            return func(*args, **kwargs)
    return wrapper


def fd_steps(x, hi):
    """scipy's '2-point' steps for ``x`` (any shape): relative step sqrt(eps), inwards at an
    upper bound, as actually taken (exactly representable)."""
    h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(x))
    h = np.where(x + h > hi, -h, h)
    return (x + h) - x


#: Step of the central differences of :func:`fd_jacobian`, as a fraction of each bound range.
CENTRAL_STEP = 1e-6


def fd_jacobian(rows, X, lo, hi, scheme="2-point", varied=None):
    """Finite-difference Jacobians of a batched residual function at P points at once, the points
    and all their steps in one call of ``rows`` ((B, d) parameter vectors -> (B, M) residuals).

    ``scheme`` "2-point": scipy's forward differences (:func:`fd_steps`: relative step sqrt(eps),
    inwards at an upper bound); "central": steps of ``CENTRAL_STEP`` of each bound range either
    side, cut (one-sided) at a bound.  ``varied`` (optional, "2-point" only): a function giving
    what ``rows`` gives of the points and their steps, (X, columns, steps (P, d)) -> (P, d + 1,
    M) (:meth:`pbrdf_cl.fitting.images.pixels.PixelResiduals.varied`, which computes each part of
    the model again only for the steps that move it).  Returns (R, J): the residuals at ``X``
    (P, M) and the Jacobians (P, d, M), ``J[p, j]`` the derivative along parameter j."""
    X = np.asarray(X, float)
    P, d = X.shape
    base = X[:, None, :]
    if scheme == "2-point":
        h = fd_steps(X, hi)
        if varied is not None:
            R = varied(X, list(range(d)), h)
        else:
            pts = np.concatenate([base, base + h[:, :, None] * np.eye(d)[None]], axis=1)
            R = rows(pts.reshape(-1, d)).reshape(P, d + 1, -1)
        J = R[:, 1:] - R[:, :1]
        J /= h[:, :, None]  # in place: of a big data set each (P, d, M) array is tens of MB
        return R[:, 0], J
    if scheme != "central":
        raise ValueError(f"scheme must be '2-point' or 'central', got {scheme!r}")
    h = CENTRAL_STEP * (hi - lo)
    up, dn = np.minimum(X + h, hi), np.maximum(X - h, lo)
    eye = np.eye(d, dtype=bool)[None]
    pts = np.concatenate([base, np.where(eye, up[:, None, :], base), np.where(eye, dn[:, None, :], base)], axis=1)
    R = rows(pts.reshape(-1, d)).reshape(P, 2 * d + 1, -1)
    return R[:, 0], (R[:, 1:d + 1] - R[:, d + 1:]) / (up - dn)[:, :, None]


def lm_batch(resid_rows, X0, lo, hi, iterations, rows_apart=True, extra=None, per_problem=False):
    """Bounded Levenberg-Marquardt from P starts at once, every problem's trial point and its
    forward-difference Jacobian (:func:`fd_jacobian`, "2-point") in one batched call per
    iteration.  Levenberg damping in coordinates scaled to the bounds (a coordinate whose
    column vanishes, as k does at k = 0, gets no runaway step); a coordinate on a bound whose
    descent direction points outwards is held there, the others' steps are projected onto the
    bounds.  Returns (X, sse, row evaluations).

    A problem is frozen, and no longer evaluated, once its step cannot move it any more: its
    trial point rounds to itself in every coordinate, and the step only shrinks while it stays
    (the same Jacobian, more damping: the step's norm falls as the damping grows), so its
    remaining iterations would be rejected evaluations of the same point.  The result is the
    one of all ``iterations`` bit for bit; the loop ends when every problem is frozen.
    ``rows_apart`` False: ``resid_rows`` needs every problem's row in its place (the image
    fits' rows are their pixels), so the frozen are evaluated too, until all are.  ``extra``
    (P, k): values of k more parameters per problem, not varied, appended to its rows as the
    last columns of what ``resid_rows`` gets (its width is d + k).  ``per_problem``: the rows
    evaluated are returned per problem (an array), not in all."""
    X = np.clip(np.array(X0, float), lo, hi)
    P, d = X.shape
    span = hi - lo
    eye = np.eye(d)
    tol = 1e-12 * span

    def evaluate(X, lanes=None):
        rows = resid_rows
        if extra is not None:
            more = np.repeat(extra if lanes is None else extra[lanes], d + 1, axis=0)
            rows = lambda Y: resid_rows(np.concatenate([Y, more], axis=1))  # noqa: E731
        r, J = fd_jacobian(rows, X, lo, hi)
        J *= span[None, :, None]  # in coordinates scaled to the bounds
        return r, J, np.einsum("pm,pm->p", r, r)

    r, J, sse = evaluate(X)
    evaluated = np.ones(P, dtype=np.int64)
    lam = 1e-3 * np.einsum("pim,pim->p", J, J) / d
    live = np.ones(P, bool)
    for _ in range(iterations):
        g = np.einsum("pim,pm->pi", J, r)
        held = ((X <= lo + tol) & (g > 0)) | ((X >= hi - tol) & (g < 0))
        Jf = np.where(held[:, :, None], 0.0, J) if held.any() else J
        g = np.where(held, 0.0, g)
        A = np.einsum("pim,pjm->pij", Jf, Jf) + (lam[:, None] + held)[:, :, None] * eye[None]
        with np.errstate(all="ignore"):
            try:
                du = -np.linalg.solve(A, g[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:  # a singular problem (an overflowing or vanishing Jacobian):
                du = np.zeros_like(X)     # no step for it, more damping; the others step as alone
                for i in range(P):
                    try:
                        du[i] = -np.linalg.solve(A[i], g[i])
                    except np.linalg.LinAlgError:
                        pass
        du = np.where(np.isfinite(du), du, 0.0)
        Xt = np.clip(X + du * span, lo, hi)
        live &= ~_frozen(X, Xt, du, span, held)
        if not live.any():
            break
        ok = np.zeros(P, bool)
        idx = np.flatnonzero(live) if rows_apart else np.arange(P)
        rt, Jt, sset = evaluate(Xt[idx], idx)
        evaluated[idx] += 1
        better = sset < sse[idx]
        won = idx[better]
        ok[won] = True
        X[won], r[won], J[won], sse[won] = Xt[won], rt[better], Jt[better], sset[better]
        lam = np.clip(np.where(ok, lam * 0.3, lam * 6.0), 1e-300, 1e300)
    return X, sse, evaluated * (d + 1) if per_problem else int(evaluated.sum()) * (d + 1)


def _frozen(X, Xt, du, span, held):
    """The problems of :func:`lm_batch` whose steps can no longer move them: the trial point is
    the point, and every coordinate not held stays put for any step no longer than this one
    (each coordinate's step is at most the step's norm times its span, under half its spacing)."""
    same = np.all(Xt == X, axis=1)
    room = np.where(held, np.inf, 0.5 * np.spacing(np.abs(X)))
    reach = np.sqrt(np.einsum("pi,pi->p", du, du))[:, None] * span[None, :]
    return same & np.all(reach < room, axis=1)


def run_starts(*columns):
    """Where the runs of equal consecutive rows begin: a bool array over the rows, True at the first
    row and at each row that differs from the row before it in any of ``columns`` (arrays whose
    first axis is the row, all of the same length)."""
    rows = len(columns[0])
    start = np.zeros(rows, bool)
    start[:1] = True
    for c in columns:
        differ = c[1:] != c[:-1]
        start[1:] |= differ.any(axis=tuple(range(1, differ.ndim))) if differ.ndim > 1 else differ
    return start


def dop_resolution(dop, max_decimals=DOP_MAX_DECIMALS, axis=None):
    """The DOP resolution of the values: 10 ** -d for the fewest decimals d (at most
    ``max_decimals``) that write every value exactly, or 0.0 where none does; with ``axis``, of
    each slice along it (an array)."""
    dop = np.asarray(dop, float)
    res = 0.0
    for d in range(max_decimals, -1, -1):  # the fewest decimals that write every value win
        step = 10.0 ** -d
        res = np.where(np.all(np.abs(np.round(dop / step) * step - dop) <= 1e-9 * step, axis=axis), step, res)
    return res if axis is not None else float(res)


def dop_noise_floor(dop):
    """The smallest DOP noise standard deviation assumed without given uncertainties
    (:data:`DOP_NOISE_FLOOR`): the rounding error of the data's resolution, at least the default."""
    return max(DOP_NOISE_FLOOR, dop_resolution(dop) / np.sqrt(12.0))


#: A correlation matrix with an eigenvalue below minus this is not positive semi-definite beyond
#: rounding (its eigenvalues lie in [0, d]; a pseudo-inverse's rounding leaves about 1e-12), and
#: one whose C - C^T exceeds ASYMMETRY_TOLERANCE (in correlation) is not symmetric beyond it.
PSD_TOLERANCE = 1e-10
ASYMMETRY_TOLERANCE = 1e-8


@dataclass(frozen=True)
class Covariance:
    """A covariance made valid by :func:`valid_covariance`, over the last two axes of its arrays.

    cov, corr
        (..., d, d): symmetric, positive semi-definite, correlations in [-1, 1]; NaN in the rows
        and columns of the ``undefined`` parameters.
    undefined
        (..., d) bool: the parameters whose variance cannot be computed (zero, negative or not
        finite: the data do not determine them, or J^T J is singular along them).
    repaired
        (...) bool: the rest was not symmetric or not positive semi-definite beyond rounding and
        was projected (its negative eigenvalues set to 0 in correlation space, the variances kept).
    worst, asymmetry
        (...) the most negative eigenvalue of the correlation matrix before (0 where none), and
        the largest |C - C^T| in correlation (divided by the standard errors).
    """
    cov: np.ndarray
    corr: np.ndarray
    undefined: np.ndarray
    repaired: np.ndarray
    worst: np.ndarray
    asymmetry: np.ndarray

    def note(self, names, index=(), what="the covariance"):
        """One sentence on what was done to the matrix ``index`` (``()`` for one matrix) over the
        parameters ``names``, or None where it was valid as computed."""
        bad = [n for n, u in zip(names, self.undefined[index]) if u]
        parts = []
        if self.repaired[index]:
            problem = []
            if self.asymmetry[index] > ASYMMETRY_TOLERANCE:
                problem.append(f"not symmetric (by {self.asymmetry[index]:.2g} in correlation)")
            if self.worst[index] < -PSD_TOLERANCE:
                problem.append(f"not positive semi-definite (an eigenvalue of {self.worst[index]:.2g} in correlation)")
            parts.append(f"{what} as computed was {' and '.join(problem)}, numerical error in the pseudo-inverse of a "
                         "near-singular J^T J: it is projected onto a valid one in correlation space (symmetrised, "
                         "negative eigenvalues set to 0, the variances kept), so its correlations are approximate")
        if bad:
            one = len(bad) == 1
            parts.append(f"the variance of {', '.join(bad)} cannot be computed (zero or not finite: the data do not "
                         f"determine {'it' if one else 'them'}), so {'its' if one else 'their'} covariances and "
                         "correlations are NaN")
        return "; ".join(parts) or None


def on_bound(x, lo, hi):
    """(on the lower bound, on the upper): where ``x`` lies within BOUND_TOL of its range ``hi -
    lo`` of each bound, elementwise."""
    tol = BOUND_TOL * (hi - lo)
    return x <= lo + tol, x >= hi - tol


#: A direction of an information matrix (coordinates scaled to the bounds) whose eigenvalue is at
#: most this fraction of the largest is one the data do not see: an infinite variance along it.
NULL_RCOND = 1e-12


def null_parameters(eigval, eigvec, rcond=NULL_RCOND, share=1e-12):
    """The parameters (..., d) of information matrices (their eigenvalues (..., d) and eigenvectors
    (..., d, d), coordinates scaled to the bounds) with a component along a direction the data do
    not see (an eigenvalue at most ``rcond`` times the largest), its square more than ``share``:
    their variance is infinite, not the pseudo-inverse's zero along that direction.  (With a
    ``share`` of 1/2, only the parameter that direction mostly is: :func:`pbrdf_cl.fit`'s rule,
    where a parameter that the direction barely moves keeps the intervals of its own data.)"""
    top = np.maximum(eigval.max(axis=-1, keepdims=True), 1e-300)
    unseen = ~(eigval > rcond * top)
    return np.einsum("...ik,...k->...i", eigvec ** 2 > share, unseen.astype(float)) > 0


#: chi^2 of one parameter's 95% interval: the likelihood-ratio test's rise (the label stage's
#: profile cross-check, the fit's test of a bound).
CHI2_95 = 3.841458820694124


def seen_through_square(names, polarimetric):
    """Which of the parameters ``names`` (``k``, ``k[set]``, ...) the data see through their
    square at their lower bound 0 (``square`` of :func:`bounded_interval`): k, wherever the data
    are the DOP or intensities (Rs and Rp depend on k through k^2), not polarimetric channels
    (circular components see k itself)."""
    return np.array([not polarimetric and n.split("[")[0] == "k" for n in names], dtype=bool)


def bounded_interval(x, se, lo, hi, dof, square=False):
    """The 95% intervals x +- z se (z Student's t's quantile with ``dof`` where given, else the
    normal's) cut at the bounds [lo, hi], elementwise: the image fits' intervals (the pixels' and
    the labels'), and where :func:`pbrdf_cl.fit`'s reach a bound
    (:func:`~pbrdf_cl.fitting.sample.uncertainty.uncertainty_stage`).  They always hold x, and
    they hold a bound x lies on or near as often as a value inside: a truth on a bound (k = 0 of a
    dielectric, kd = 0 of a metal) is covered at the nominal rate, where the central 95% of the
    Gaussian truncated to the bounds (their rule until issue #37's round 8) leaves the bound out
    whenever x lies within a few hundredths of a standard error of it (a metal's kd = 0 was
    covered by 2% of its pixels, now by 99-100%).

    ``square`` (broadcasting, e.g. per parameter): a parameter whose lower bound is 0 and which the
    data see through its square there (k, on which the DOP depends through k^2: near k = 0 the
    likelihood is Gaussian in k^2, not in k, whose derivative vanishes there).  Its interval also
    holds that of x^2, x^2 +- 2 z x se (the delta method) cut at the bounds and mapped back by the
    square root: the hull of the two, since away from 0 which is the better local model is not
    known (there the square's lies lower by about z^2 se^2 / (2 x): 0.2 standard errors at x = 10
    se).  The hull reaches 0 where x <= 2 z se: a truth k = 0 is covered at the nominal rate
    where k^2's estimate is Gaussian, against 84% for the Gaussian in k."""
    from scipy import special
    x, se, lo, hi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x, se, lo, hi)))
    z = special.ndtri(0.975) if dof is None else special.stdtrit(dof, 0.975)
    with np.errstate(invalid="ignore"):
        lo95 = np.where(np.isfinite(se), np.clip(x - z * se, lo, hi), lo)
        hi95 = np.where(np.isfinite(se), np.clip(x + z * se, lo, hi), hi)
        sq = np.broadcast_to(np.asarray(square, bool), x.shape) & (lo == 0.0) & np.isfinite(se)
        if sq.any():
            lo95 = np.where(sq, np.minimum(lo95, np.sqrt(np.clip(x * x - 2.0 * z * x * se, 0.0, None))), lo95)
    return lo95, hi95


def valid_covariance(cov):
    """A covariance (..., d, d) made valid, or said not to be: the one place every fit's covariance
    passes through (:func:`pbrdf_cl.fit`, :func:`pbrdf_cl.fit_joint`, the pixels and the labels
    of :func:`pbrdf_cl.fit_batch`).

    The parameters whose variance is zero, negative or not finite cannot be given one: their rows
    and columns are NaN.  The rest is made exactly symmetric, (C + C^T) / 2 (the diagonal, the
    variances, unchanged; a symmetric C unchanged bit for bit); where it is symmetric and positive
    semi-definite to rounding (:data:`ASYMMETRY_TOLERANCE`, :data:`PSD_TOLERANCE` on its
    correlation matrix) that is all, and the correlations C_ij / (se_i se_j) are only clipped to
    [-1, 1] (which moves rounding alone): a valid covariance is not regularised.  Else it is
    projected in correlation space: its negative eigenvalues set to 0, rescaled to a unit
    diagonal, so that the variances (the standard errors a fit reports) are kept.  Returns a
    :class:`Covariance`; its :meth:`Covariance.note` says what was done."""
    C = np.array(cov, dtype=float)
    d = C.shape[-1]
    diag = np.einsum("...ii->...i", C)
    with np.errstate(invalid="ignore"):
        undefined = ~(np.isfinite(diag) & (diag > 0))
        # a covariance not finite against a parameter that has a variance (a row and column NaN
        # against one without: this function's own output, given again, is unchanged)
        undefined |= np.any(~np.isfinite(C) & ~undefined[..., None, :], axis=-1)
    both = undefined[..., :, None] | undefined[..., None, :]
    se = np.sqrt(np.where(undefined, 1.0, diag))
    scale = se[..., :, None] * se[..., None, :]
    C = np.where(both, 0.0, C)  # the rows and columns without a variance zeroed (NaN at the end)
    asymmetry = np.max(np.abs(C - np.swapaxes(C, -1, -2)) / scale, axis=(-2, -1), initial=0.0)
    C = 0.5 * (C + np.swapaxes(C, -1, -2))  # exactly symmetric (a symmetric C is unchanged)
    R = np.where(both & np.eye(d, dtype=bool), 1.0, C / scale)
    w, v = np.linalg.eigh(R)
    worst = np.minimum(w[..., 0], 0.0) if d else np.zeros(C.shape[:-2])
    repaired = (worst < -PSD_TOLERANCE) | (asymmetry > ASYMMETRY_TOLERANCE)
    if np.any(repaired):
        P = np.einsum("...ik,...k,...jk->...ij", v, np.maximum(w, 0.0), v)
        p = np.sqrt(np.maximum(np.einsum("...ii->...i", P), 1e-300))
        P = P / (p[..., :, None] * p[..., None, :])
        P = 0.5 * (P + np.swapaxes(P, -1, -2))
        R = np.where(repaired[..., None, None], P, R)
        C = np.where(repaired[..., None, None], P * scale, C)
    return Covariance(np.where(both, np.nan, C), np.where(both, np.nan, np.clip(R, -1.0, 1.0)), undefined, repaired,
                      worst, asymmetry)


#: The mark of a best value outside its own 95% interval, in every table and summary, and why
#: that is no mistake (:func:`outside_note`, :data:`OUTSIDE_FOOTNOTE`).
OUTSIDE_MARK = "(*)"
OUTSIDE_WHY = ("the 95% interval is the central 95% of the posterior over the bounds, and where the data barely "
               "determine a parameter its best fit is arbitrary and often at a bound: quote the interval, not the "
               "best value")
#: The footnote of a table whose rows carry :data:`OUTSIDE_MARK`.
OUTSIDE_FOOTNOTE = f"{OUTSIDE_MARK} the best value lies outside its own 95% interval: {OUTSIDE_WHY}"


def outside_interval(x, lo, hi):
    """Whether each best value ``x`` lies outside its 95% interval [``lo``, ``hi``] (elementwise,
    broadcasting; False where any of them is NaN): the one test behind :data:`OUTSIDE_MARK`."""
    x, lo, hi = (np.asarray(a, dtype=float) for a in (x, lo, hi))
    with np.errstate(invalid="ignore"):
        return (x < lo) | (x > hi)


def outside_note(items):
    """The note of best values outside their intervals: ``items`` (e.g. "k's best value 10 lies
    outside its 95% interval [0.254, 9.75]") joined, then the mark and why."""
    return f"{'; '.join(items)} {OUTSIDE_MARK}: {OUTSIDE_WHY}"
