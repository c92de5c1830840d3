"""The label stage's work on a subsample of each label's pixels, held in memory: the global search
for the shared parameters (:func:`rank_seeds`: every candidate seed refined briefly and ranked by
its chi2), the optional parametric bootstrap of the estimator inverted as a test
(:func:`binding_correction`) and, without ``dop_std``, the goodness-of-fit test of each label (:func:`f_test`).

Both take the label stage (``pbrdf_cl.fitting.images.label_stage._Stage``) as ``st`` and use only its
public methods (``local_fit``, ``local_blocks``, ``local_at``, ``local_steps`` and their batches
``local_at_many``, ``local_steps_many``, ``scale``); the
subsample is a fixed, evenly spaced choice of each label's fitted pixels (:func:`subsample`), so
the results do not depend on the blocks.
"""
from __future__ import annotations

import numpy as np

from ..common import on_bound
from .pixel_fit import fit_block
from .pixels import Block, PixelResiduals, internal, take

#: Pixels of each label in the subsample (all of a smaller label).
SUBSAMPLE = 32
#: Gauss-Newton steps of each candidate seed on the subsample before they are ranked.
RANK_ROUNDS = 3
#: Further Gauss-Newton steps at most of the best end on the subsample (and of an end of another
#: basin that may be refined on all the pixels), so that the refinement on all the pixels starts
#: near its optimum.
POLISH_ROUNDS = 12
#: Candidates whose subsample refinements end closer than this fraction of the bounds (in every
#: shared parameter) are one basin.
SAME_BASIN = 0.02
#: An end of a candidate's refinement with a shared parameter on a bound is refined again from
#: these fractions of the bounds inside it: at k = 0 the chi2's derivative in k vanishes (the model
#: depends on k through k^2 there), so a descent cannot leave k = 0 even where k > 0 is far lower.
INWARD = (0.02, 0.05, 0.1)
#: The runner-up basin is refined on all the label's pixels too where its subsample chi2, scaled
#: to the label's pixels, exceeds the best's by less than this (times the label's chi2 scale).
RUNNER_UP_CHI2 = 50.0
#: Replicates at each design point and Gauss-Newton steps of each replicate's refit of the
#: parametric bootstrap of the label's estimator (:func:`binding_correction`; the default of
#: ``LabelJob.bias_replicates``).  0: off, the intervals then leave out the incidental parameters'
#: bias: on the two-material bench the binding slope of steel's k is 0.2-0.45, so its intervals
#: are too wide for the issue's width criterion, and it costs several times the label fit
#: (docs/joint_images.md; 8 replicates covered 47 of 48 on seeds no test uses).
BOOT_REPLICATES = 0
BOOT_ROUNDS = 8
#: The design of the binding function's linear model: the fitted values and one step either way
#: in each shared parameter (up to three), steps of DESIGN_STEP standard errors.
DESIGN = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
DESIGN_STEP = 3.0


def subsample(st, size=SUBSAMPLE):
    """Per label, at most ``size`` of its fitted pixels evenly spaced over them in pixel order
    (flat indices, ascending)."""
    picks = []
    for L in range(st.ids.size):
        pix = np.flatnonzero(st.fitted & (st.lab == L))
        if pix.size > size:
            pix = pix[np.unique(np.linspace(0, pix.size - 1, size).round().astype(np.int64))]
        picks.append(pix)
    return picks


def median_node(st, nodes_of_pixels):
    """Per label, the coordinate-wise median of its pixels' own best nodes of the shared grid (the
    per-pixel optima's centre: a candidate seed the label's summed profile can miss), (L, S)."""
    out = np.full((st.ids.size, len(st.shared)), np.nan)
    for L in range(st.ids.size):
        mine = nodes_of_pixels[st.fitted & (st.lab == L)]
        mine = mine[mine >= 0]
        if mine.size:
            out[L] = np.median(st.nodes[mine], axis=0)
    return out


def rank_seeds(st, subs, cand, ok, pixels):
    """Every candidate seed ``cand`` (C, L, S) of each label refined on the label's subsample
    ``subs`` (``st.local_at``, ``st.local_steps``: RANK_ROUNDS steps) and ranked by the
    subsample's chi2; the best end then refined on, up to POLISH_ROUNDS more steps (the seed of
    the refinement on all the pixels, which then starts near its optimum).  The runner-up and
    its gap are those of the ends as ranked (:func:`runner_up`).  The candidates of every label
    are refined together, each step of all of them one batch (``st.local_steps_many``); each
    end is the one it has alone.

    Returns (best, runner_up, gap): the best end (L, S); the best end of another basin (NaN where
    none); the runner-up's chi2 above the best's, scaled by ``pixels`` over the subsample's pixels
    and divided by the label's chi2 scale (inf where none)."""
    L_n, S = cand.shape[1], cand.shape[2]
    best = np.full((L_n, S), np.nan)
    runner = np.full((L_n, S), np.nan)
    gap = np.full(L_n, np.inf)
    labels = np.flatnonzero(ok)
    blocks = {L: st.local_blocks(subs[L]) for L in labels}
    seeds = [(L, cand[c, L]) for L in labels for c in range(cand.shape[0])
             if np.all(np.isfinite(cand[c, L])) and not any(np.array_equal(cand[c, L], cand[d, L]) for d in range(c))]
    ends = {L: [] for L in labels}
    for (L, _), end in zip(seeds, short_fits(st, [(blocks[L], t) for L, t in seeds])):
        ends[L].append(end)
    inward = [(L, t) for L in labels for t in inward_starts(st, [e[0] for e in ends[L] if e is not None])]
    for (L, _), end in zip(inward, short_fits(st, [(blocks[L], t) for L, t in inward])):
        ends[L].append(end)
    ranked = {L: sorted((e for e in ends[L] if e is not None), key=lambda e: e[1][3]) for L in labels}
    found = [L for L in labels if ranked[L]]
    for L in labels:
        if not ranked[L]:
            best[L] = cand[0, L]
    polished = st.local_steps_many([(blocks[L], *ranked[L][0][:3], POLISH_ROUNDS, ranked[L][0][3]) for L in found])
    for L, end in zip(found, polished):
        best[L] = end[0]
        runner[L], gap[L] = runner_up(st, ranked[L], pixels[L])
    return best, runner, gap


def runner_up(st, ends, pixels):
    """Of one label's subsample ``ends`` (chi2 order), the first end of another basin than the
    best's (``ends[0]``; as its RANK_ROUNDS steps left it, before it is refined on): (its theta, its
    chi2 above the best's scaled to the label's ``pixels`` and chi2 scale), or (NaN, inf) where
    none."""
    span = st.span[st.si]
    for theta, sums, _, _ in ends[1:]:
        if np.any(np.abs(theta - ends[0][0]) > SAME_BASIN * span):
            return theta, (sums[3] - ends[0][1][3]) * pixels / sums[0] / st.scale(ends[0][1][None])[0]
    return np.nan, np.inf


def short_fits(st, items):
    """Candidate seeds (a list of (``st.local_blocks`` of a subsample, theta)) each refined on its
    subsample (RANK_ROUNDS steps), all as one batch: per item (theta, sums, beta, damping) as
    ``st.local_steps`` returns them, or None where no pixel counts."""
    starts = st.local_at_many([(blocks, theta, None) for blocks, theta in items])
    ends = st.local_steps_many([(blocks, theta, sums, beta, RANK_ROUNDS, 1e-3)
                                for (blocks, theta), (beta, sums) in zip(items, starts)])
    return [end if np.isfinite(end[1][3]) and end[1][0] > 0 else None for end in ends]


def inward_starts(st, ends):
    """Starts moved inside the bounds from the candidates' subsample ``ends`` (a list of (S,)) that
    have a shared parameter on a bound: that parameter :data:`INWARD` fractions of its bounds
    inside, the others as they are (each distinct end once)."""
    starts, seen = [], []
    for t in ends:
        if not np.any(on_bound(t, st.lo[st.si], st.hi[st.si])) or any(np.array_equal(t, u) for u in seen):
            continue
        seen.append(t)
        starts += [moved_inside(st, t, f) for f in INWARD]
    return starts


def moved_inside(st, theta, f):
    """``theta`` (..., S) with every shared parameter on a bound (:func:`~pbrdf_cl.fitting.common.on_bound`)
    moved the fraction ``f`` of its range inside, the others as they are."""
    lo, hi, span = st.lo[st.si], st.hi[st.si], st.span[st.si]
    low, high = on_bound(theta, lo, hi)
    return np.where(low, lo + f * span, np.where(high, hi - f * span, theta))


def simulate(st, raw, theta, beta, s2, rng):
    """``raw`` with its DOP (and intensities) replaced by the model at (``theta``, each pixel's
    ``beta``) plus Gaussian noise of the data's weights times ``s2`` (the label's chi2 scale)."""
    setup, names = st.job.setup, st.job.names
    blk = Block(raw, setup, 1)
    X = np.empty((blk.p, len(names)))
    X[:, st.si], X[:, st.bi] = theta, beta
    r = PixelResiduals(setup, blk, names, np.arange(blk.p), setup.use_f00).rows(internal(X, names))
    out = dict(raw)
    M = blk.valid.shape[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        sd = np.sqrt(s2 / blk.w)
        model = blk.obs + r[:, :M] * sd / np.sqrt(s2)
        out["dop"] = np.where(blk.valid, model + sd * rng.standard_normal(model.shape), np.nan)
        if setup.use_f00:
            fsd = np.sqrt(s2 / blk.fw)
            fmodel = blk.fobs + r[:, M:] * fsd / np.sqrt(s2)
            out["f00"] = np.where(blk.valid, fmodel + fsd * rng.standard_normal(fmodel.shape), np.nan)
    return out


def binding_correction(st, subs, picks, theta, cov, s2, ok, replicates=BOOT_REPLICATES):
    """The parametric bootstrap of each label's estimator inverted as a test (indirect inference):
    its expected value g(t) at true shared values t, the binding function, estimated on the label's
    subsample at the DESIGN points t around ``theta`` and fitted by a linear model, then solved for
    the shared values whose expected estimate is the one found.

    At each point t the pixels' own parameters are fitted with the shared held at t (the nuisance
    parameters' estimates under the hypothesis "the truth is t", as a bootstrap test takes them)
    and drawn towards their mean so that their spread is the true values' (:func:`ensemble_factor`,
    measured at the first point; fitted values are more dispersed than the truth's, and the bias
    depends on them); ``replicates`` data sets are simulated there (:func:`simulate`, noise of the
    label's chi2 scale ``s2``, the same draws at every point) and the label refitted from t
    (``st.local_fit``, BOOT_ROUNDS steps); g(t) is their mean.  The linear model
    g(t) = a + G (t - theta) (least squares over the points) gives the corrected values
    theta_c = theta + G^-1 (theta - a) and their covariance G^-1 (V + W) G^-T: V the label's
    covariance ``cov`` (L, S, S, in the parameters' units), W the variance of the bootstrap's mean
    (the replicates' variance over ``replicates``, at least V scaled to the subsample's pixels over
    ``replicates``).  The bias of the incidental per-pixel parameters does not shrink with the
    pixel count, so the subsample's binding function is the label's.  The noise is drawn from a
    generator seeded per label value: the same in every run.

    Returns (theta_c, cov_c, slope) per label (unchanged, with an infinite variance where G cannot
    be inverted; ``slope`` (L, S) the diagonal of G, NaN where not computed)."""
    L_n, S = theta.shape
    out, cov_c = theta.copy(), cov.copy()
    slope = np.full((L_n, S), np.nan)
    span = st.span[st.si]
    lo, hi = st.lo[st.si], st.hi[st.si]
    for L in np.flatnonzero(ok):
        idx = picks[L]
        keep = np.all(np.isfinite(st.beta[idx]), axis=1)
        se = np.sqrt(np.clip(np.diag(cov[L]), 0, None))
        if keep.sum() < 2 or replicates < 1 or not np.all(np.isfinite(se)):
            continue
        raw = take(subs[L], keep)
        beta = st.beta[idx[keep]]
        step = np.maximum(DESIGN_STEP * se, 1e-3 * span)
        points = np.clip(theta[L] + DESIGN[:1 + 2 * S, :S] * step, lo, hi)
        means, spread, factor = [], [], None
        for t in points:
            _, _, b0 = st.local_fit(raw, t.copy(), 0, beta=beta)
            if factor is None:
                factor = ensemble_factor(st, raw, t, b0, s2[L], np.random.default_rng([20261, int(st.ids[L])]))
            b0 = shrink(st, b0, factor)
            rng = np.random.default_rng([20260, int(st.ids[L])])
            ends = [st.local_fit(simulate(st, raw, t, b0, s2[L], rng), t.copy(), BOOT_ROUNDS, beta=b0)[0]
                    for _ in range(replicates)]
            means.append(np.mean(ends, axis=0))
            spread.append(np.var(ends, axis=0, ddof=1) if replicates > 1 else np.zeros(S))
        X = np.column_stack([np.ones(len(points)), points - theta[L]])
        coef = np.linalg.lstsq(X, np.array(means), rcond=None)[0]
        a, G = coef[0], coef[1:].T
        floor = np.diag(cov[L]) * np.sum(st.fitted & (st.lab == L)) / keep.sum()
        W = np.diag(np.maximum(spread[0], floor) / replicates)
        with np.errstate(all="ignore"):
            Gi = np.linalg.pinv(G, rcond=1e-3)
        slope[L] = np.diag(G)
        if np.linalg.matrix_rank(G, tol=1e-3 * np.abs(G).max()) < S or np.any(np.diag(G) <= 0):
            cov_c[L] = np.diag(np.full(S, np.inf))
            continue
        out[L] = np.clip(theta[L] + Gi @ (theta[L] - a), lo, hi)
        cov_c[L] = Gi @ (cov[L] + W) @ Gi.T
    return out, cov_c, slope


def ensemble_factor(st, raw, theta, beta, s2, rng):
    """The factor by which the pixels' own parameters ``beta`` (p, own), fitted with the shared held
    at ``theta``, are drawn towards their mean so that their spread is the one of the true values
    (Louis 1984, the constrained Bayes estimates of an ensemble): per own parameter
    sqrt(max(1 - v_noise / v_fit, 0)), v_fit the fitted values' variance over the pixels, v_noise
    their estimation noise's, measured by one data set simulated at (``theta``, ``beta``) with the
    noise ``s2`` and the own parameters refitted there."""
    _, _, again = st.local_fit(simulate(st, raw, theta, beta, s2, rng), theta.copy(), 0, beta=beta)
    good = np.all(np.isfinite(again), axis=1)
    v_fit = beta[good].var(axis=0)
    v_noise = (again[good] - beta[good]).var(axis=0)
    with np.errstate(all="ignore"):
        return np.where(v_fit > 0, np.sqrt(np.clip(1.0 - v_noise / v_fit, 0.0, None)), 0.0)


def shrink(st, beta, factor):
    """``beta`` (p, own) drawn towards its mean over the pixels by ``factor`` (:func:`ensemble_factor`),
    inside the own parameters' bounds."""
    m = beta.mean(axis=0)
    return np.clip(m + factor * (beta - m), st.lo[st.bi], st.hi[st.bi])


def f_test(st, subs, picks, theta, ok, pixels):
    """Without ``dop_std`` (no chi2 to test): per label, the p-value of the F test of its shared
    values against each pixel's own, on its subsample (NaN where it cannot be made).

    The label's model (``theta`` held, each pixel's own parameters ``st.beta``) is nested in the
    pixels' own fits (every parameter free: :func:`pbrdf_cl.fitting.images.pixel_fit.fit_block`, each
    pixel's chi2 taken no higher than at the label's values): F = ((chi2_label - chi2_own) / (S P))
    / s2 with S shared parameters over P pixels (S (P - 1) where the subsample is the label), s2
    the own fits' chi2 per degree of freedom, at least the pixels' mean noise floor squared (an
    exact fit of noise-free data is not a misfit).  Where the pixels are of two materials, their
    own fits explain the data and the label's do not."""
    from scipy.stats import f as f_dist
    job, setup = st.job, st.job.setup
    S, D = len(st.shared), len(job.names)
    p_value = np.full(st.ids.size, np.nan)
    for L in np.flatnonzero(ok):
        beta = st.beta[picks[L]]
        keep = np.all(np.isfinite(beta), axis=1)
        if keep.sum() < 2:
            continue
        raw = take(subs[L], keep)
        vals = st.values(setup, Block(raw, setup, 1), np.broadcast_to(theta[L], (int(keep.sum()), S)), beta[keep])
        own = fit_block(st.eng, setup, raw, job.order, job.rstart, job.names)["chi2"]
        good = np.isfinite(vals[:, 3]) & np.isfinite(own)
        P = int(good.sum())
        chi2_label = vals[good, 3].sum()
        chi2_own = np.minimum(own[good], vals[good, 3]).sum()
        df1 = S * P - (S if P >= pixels[L] else 0)
        df2 = vals[good, 1].sum() - P * D
        if P < 2 or df1 < 1 or df2 < 1:
            continue
        s2 = max(chi2_own / df2, vals[good, 2].mean())
        p_value[L] = float(f_dist.sf((chi2_label - chi2_own) / df1 / s2, df1, df2))
    return p_value
