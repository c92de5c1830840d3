"""The label stage's work on a subsample of each label's pixels, held in memory: the global search
for the shared parameters (:func:`rank_seeds`: every candidate seed refined briefly and ranked by
its chi2), the parametric bootstrap of the estimator's bias (:func:`bootstrap_bias`) and, without
``dop_std``, the goodness-of-fit test of each label (:func:`f_test`).

Both take the label stage (``pbrdf_cl.fitting.images.label_stage._Stage``) as ``st`` and use only its
public methods (``local_fit``, ``scale``); the subsample is a fixed, evenly spaced choice of each
label's fitted pixels (:func:`subsample`), so the results do not depend on the blocks.
"""
from __future__ import annotations

import numpy as np

from ...io.source import ANGLES
from .pixel_fit import fit_block
from .pixels import Block, PixelResiduals, internal

#: Pixels of each label in the subsample (all of a smaller label).
SUBSAMPLE = 32
#: Gauss-Newton steps of each candidate seed on the subsample before they are ranked.
RANK_ROUNDS = 3
#: Candidates whose subsample refinements end closer than this fraction of the bounds (in every
#: shared parameter) are one basin.
SAME_BASIN = 0.02
#: The runner-up basin is refined on all the label's pixels too where its subsample chi2, scaled
#: to the label's pixels, exceeds the best's by less than this (times the label's chi2 scale).
RUNNER_UP_CHI2 = 50.0
#: Replicates and Gauss-Newton steps of the parametric bootstrap of the bias (the default of
#: ``LabelJob.bias_replicates``).  0: off, because at the fitted point (the pixels' own
#: parameters as fitted from noisy data) the bootstrap's bias did not estimate the estimator's
#: bias at the truth on the two-material bench (DOP noise 0.01: -0.03 against +0.12 in the
#: dielectric's k, whose bias a simulation at the true values reproduces).
BOOT_REPLICATES = 0
BOOT_ROUNDS = 8


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
    ``subs`` (``st.local_fit``, RANK_ROUNDS steps) and ranked by the subsample's chi2.

    Returns (best, runner_up, gap): the best end (L, S); the best end of another basin (NaN where
    none); the runner-up's chi2 above the best's, scaled by ``pixels`` over the subsample's pixels
    and divided by the label's chi2 scale (inf where none)."""
    L_n, S = cand.shape[1], cand.shape[2]
    best = np.full((L_n, S), np.nan)
    runner = np.full((L_n, S), np.nan)
    gap = np.full(L_n, np.inf)
    span = st.span[st.si]
    for L in np.flatnonzero(ok):
        ends = []
        for c in range(cand.shape[0]):
            t = cand[c, L]
            if not np.all(np.isfinite(t)) or any(np.array_equal(t, cand[d, L]) for d in range(c)):
                continue
            theta, sums, _ = st.local_fit(subs[L], t, RANK_ROUNDS)
            if np.isfinite(sums[3]) and sums[0] > 0:
                ends.append((sums[3], theta, sums))
        if not ends:
            best[L] = cand[0, L]
            continue
        ends.sort(key=lambda e: e[0])
        best[L] = ends[0][1]
        for chi2, theta, sums in ends[1:]:
            if np.any(np.abs(theta - best[L]) > SAME_BASIN * span):
                runner[L] = theta
                gap[L] = (chi2 - ends[0][0]) * pixels[L] / sums[0] / st.scale(ends[0][2][None])[0]
                break
    return best, runner, gap


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


def bootstrap_bias(st, subs, picks, theta, se, s2, ok, replicates=BOOT_REPLICATES):
    """The parametric bootstrap of each label's estimator on its subsample: data simulated at the
    label's fit (``theta``, the pixels' own parameters ``st.beta``) with its noise (``s2``), the
    label refitted from ``theta`` (``st.local_fit``, BOOT_ROUNDS steps), ``replicates`` times.

    Returns (bias, var): the replicates' mean shift of the shared parameters (L, S) (the bias of
    the incidental per-pixel parameters does not shrink with the pixel count, so the subsample's
    is the label's) and the variance of that mean as an estimate: the replicates' variance, at
    least the label's variance ``se`` ** 2 scaled to the subsample's pixels, over ``replicates``.  The
    noise is drawn from a generator seeded per label value: the same in every run."""
    L_n, S = theta.shape
    bias = np.zeros((L_n, S))
    var = np.zeros((L_n, S))
    for L in np.flatnonzero(ok):
        idx = picks[L]
        keep = np.all(np.isfinite(st.beta[idx]), axis=1)
        if keep.sum() < 2 or replicates < 1:
            continue
        raw = {k: (v if (v.ndim == 1 and k in ANGLES) else v[keep]) for k, v in subs[L].items()}
        beta = st.beta[idx[keep]]
        rng = np.random.default_rng([20260, int(st.ids[L])])
        shifts = []
        for _ in range(replicates):
            sim = simulate(st, raw, theta[L], beta, s2[L], rng)
            t, _, _ = st.local_fit(sim, theta[L].copy(), BOOT_ROUNDS, beta=beta)
            shifts.append(t - theta[L])
        shifts = np.array(shifts)
        bias[L] = shifts.mean(axis=0)
        spread = shifts.var(axis=0, ddof=1) if replicates > 1 else np.zeros(S)
        floor = se[L] ** 2 * np.sum(st.fitted & (st.lab == L)) / keep.sum()
        var[L] = np.maximum(spread, floor) / replicates
    return bias, var


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
        raw = {k: (v if (v.ndim == 1 and k in ANGLES) else v[keep]) for k, v in subs[L].items()}
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
