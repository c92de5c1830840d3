"""The label stage of an image fit with shared material parameters (:func:`run_label_stage`): the
values of the shared parameters (n, k by default) of every label of a label image, found from all
the pixels of the label before the per-pixel pass fits each pixel with them held.

The label's objective is the sum over its pixels of each pixel's chi2, every pixel with its own
values of the other parameters (beta): F(theta) = sum_p min_beta chi2_p(theta, beta).  It is found
in passes over the blocks of the stack (a label's pixels may lie in every block):

1. the profile: the grid stage (``batch_grid``) with one region per node of the shared
   parameters' grid axes gives every pixel's least chi2 at each node (over the grid of its own
   parameters); summed over a label's pixels, the label's profile on the grid, whose local
   minima are candidate seeds of theta;
2. the search (:mod:`pbrdf_cl.fitting.images.label_search`, on an evenly spaced subsample of at most
   SUBSAMPLE of the label's pixels held in memory): the SEEDS lowest local minima of the label's
   profile and the median of its pixels' own best nodes, each refined by a few Gauss-Newton
   steps (as in 3.) on the subsample and ranked by the subsample's chi2; the best, refined on to
   the subsample's optimum (at most ``label_search.POLISH_ROUNDS`` more steps), seeds the
   label, and every pixel's own parameters are descended with theta held there (from the
   GRID_STARTS best nodes of the grid of its own parameters, as in 3.; the per-pixel pass fits
   them with the usual stages once the label's values are final).  The best end of another
   basin is refined on all the pixels too where its subsample chi2, scaled to the label, lies
   within RUNNER_UP_CHI2 of the best's (both as ranked); the basin of lower label chi2 is kept;
3. the refinement, variable projection: each pass moves theta by a damped Gauss-Newton step on
   F from the sums over the label's pixels of the Schur complement of each pixel's normal
   equations (the information on theta left once the pixel's own parameters are eliminated) and
   of the reduced gradient, then re-descends every pixel's own parameters at the new theta
   (``batch_lm`` from the previous ones) and keeps the step where F fell (per label; Marquardt
   damping otherwise), until F stops falling.  A label left with a shared parameter on a bound
   that the data hardly see there (k = 0: the model depends on k through k^2, so no Gauss-Newton
   step leaves it, :func:`unseen_on_bound`) is refined again on all the pixels from 2% of that
   parameter's range inside, and the basin of lower chi2 kept, as for the runner-up (2.; the
   bound's end, where the two lie within 3.84, counted in the interval as its values alone);
4. the intervals: the covariance of theta is the inverse of the summed Schur complements (an
   infinite variance for the parameter that a direction they do not see mostly is), scaled
   by the label's reduced chi2 where ``dop_std`` is not given; the values +- 1.96 standard errors
   (Student's t without ``dop_std``) cut at the bounds, k's holding that of k^2 too (the DOP
   depends on k through k^2: near k = 0 the likelihood is Gaussian in k^2;
   :func:`~pbrdf_cl.fitting.common.bounded_interval`), then cross-checked against the label's profile on
   the grid: a node whose profile (an upper bound of the true one) lies within chi2 3.84 (times
   the reduced chi2) of the minimum but outside the interval widens it to cover that node and
   marks the label ambiguous, as does another basin (2.) whose label chi2 lies within 3.84 of the
   kept one's (the interval then covers that basin's interval too);
5. the goodness of fit of each label (:func:`label_goodness`): with ``dop_std`` (and ``f00_std``
   with intensities) its chi2 against its degrees of freedom, else an F test of its shared values
   against each pixel's own on its subsample (:func:`pbrdf_cl.fitting.images.label_search.f_test`); a
   p-value below ``GOODNESS_P``
   says the label's pixels do not share one material (each pixel's own parameters absorb the
   misfit, so the pixels' own tests pass);
6. optionally (``LabelJob.bias_replicates`` > 0; default 0) the parametric bootstrap of the
   label's estimator inverted as a test on the subsample
   (:func:`pbrdf_cl.fitting.images.label_search.binding_correction`: the estimator's expected
   value as a linear function of the true shared values, the pixels' own parameters refitted at
   each and drawn towards their mean to the truth's spread; solved for the values whose
   expected estimate is the one found, the covariance transformed alike).  Off by default: its
   intervals of steel's k on the two-material bench are too wide (a binding slope of 0.2-0.45)
   and it costs several times the label fit (docs/joint_images.md).  By default instead
   (``LabelJob.integrated``; off: the profile's values, whose intervals leave out the
   incidental parameters' bias) the values that minimise the label's integrated likelihood
   over its pixels' own parameters
   (:func:`pbrdf_cl.fitting.images.label_adjust.integrated_correction`), with the profile's
   covariance (plus the correction's sampling noise where it is estimated on a subsample of a
   large label): it covers the truth far more often and costs several label fits.

The derivatives and the objective of the refinement are the float64 reference model's
(:class:`~pbrdf_cl.fitting.images.pixels.PixelResiduals`, forward differences on the host): the same on
every backend.  Sums over a label's pixels are taken row by row of the stack in row order, so the
result does not depend on the blocks (the memory budget), nor on where they run: each pass's work
on a block (:class:`Passes`) runs here or, with a cluster, on a ``dask.distributed`` worker
(``pbrdf_cl.fitting.images.label_workers``), and its sums per row are added here in row order.
Memory beyond a block: the pixels' own parameters at the current and the trial theta (two floats
per parameter and pixel) and the labels' sums; the current ones are kept in the result
(``LabelResult.beta``): the per-pixel pass starts each pixel from them too.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .. import report
from ..common import (
    CHI2_95,
    GOODNESS_P,
    NULL_RCOND,
    X_RESOLUTION,
    bounded_interval,
    fd_jacobian,
    null_parameters,
    on_bound,
    seen_through_square,
    valid_covariance,
)
from ..setup import PARAMETERS
from . import label_search as search
from .label_adjust import integrated_correction
from .pixels import (
    Block,
    PixelResiduals,
    concatenate,
    descent_bounds,
    grid_points,
    grid_values,
    internal,
    regions,
    stack_blocks,
    take,
)
from .statistics import DETERMINED_FRACTION

#: Passes of the refinement at most (each one pass over the stack).
MAX_ROUNDS = 20
#: Iterations of each pixel's float32 descents of its own parameters after a step of theta, and
#: of the float64 polish of the best.
LM_ITERATIONS = 10
POLISH_ITERATIONS = 10
#: Candidate seeds per label: the best local minima of its profile on the grid, each tried (with the
#: median of its pixels' best nodes) on a subsample of its pixels (:mod:`label_search`).
SEEDS = 6
#: Starts of each pixel's descent at a trial theta from the grid of its own parameters (with its
#: previous values).
GRID_STARTS = 3
#: The refinement of a label stops where a step would lower its chi2 by less than this (times the
#: label's reduced chi2 without dop_std): a tenth of a standard error moves chi2 by 0.01.
CHI2_TOL = 1e-2
#: A damped step of the subsample's refinement (:meth:`_Stage.local_steps`) that differs by less
#: than this fraction of its length (scaled to the bounds) from the step just rejected, along
#: which the chi2 rose by more than the fall it predicted, is rejected too without its pixels
#: being descended (the damping grows on): Marquardt's scaling hardly shortens a step along a
#: weakly determined direction.  On the bench's 16x16 and 32x32 stacks (24) none of the 161
#: steps so skipped would have lowered the chi2 (of those within 0.1 of the step, 6 would have).
SAME_STEP = 0.05
#: Pixels at most of one batch of the subsample's descents (:meth:`_Stage.local_at_many`: every
#: label's candidates, each its subsample's pixels): the memory of its arrays stays that of a few
#: thousand pixels whatever the number of labels.
BATCH_PIXELS = 4096
#: The status of each label: code -> (name, meaning).
LABEL_STATUS = {
    1: ("converged", "the refinement converged inside the bounds"),
    2: ("on_bound", "converged with a shared parameter on a bound"),
    3: ("ambiguous", "a node of the label's profile on the grid, or another basin's refinement, lies within chi2 3.84 "
                     "of the minimum outside the local interval: the interval is widened to cover it"),
    4: ("underdetermined", "a shared parameter's 95% interval spans more than half its bounds"),
    0: ("not_converged", f"the refinement still improved after {MAX_ROUNDS} passes"),
    -2: ("too_few", "not fitted: too few pixels of the label with enough valid measurements"),
}


@dataclass
class LabelResult:
    """The label stage's result, arrays over the labels (``ids``): ``theta`` (L, S) the shared
    parameters' values (``shared`` order), ``stderr``, ``ci95`` (L, S, 2), ``determined``
    (L, S), ``pixels`` (fitted pixels), ``chi2`` (the label's F), ``sse`` (its unweighted DOP
    residuals), ``dof``, ``status`` (:data:`LABEL_STATUS`), ``rounds`` (refinement passes) and
    ``profile`` (L, nodes: the label's chi2 profile on the grid) with ``nodes`` (nodes, S),
    ``bias`` (L, S): the bootstrap's (or the integrated likelihood's) estimate of the bias, already
    taken off ``theta``, the
    goodness of fit (:func:`label_goodness`): ``p_value``, ``fits_data`` (1: fits, 0: does
    not, -1: not fitted or not tested) and ``goodness_test`` ("chi2" or "F"), and ``corr``
    (L, S, S) the correlations of the shared parameters (valid or NaN,
    :func:`pbrdf_cl.fitting.common.valid_covariance`) with ``cov_notes`` (a sentence per label
    where the covariance needed one, else None); ``beta`` (pixels, own parameters) each pixel's
    own parameters at its label's values as the refinement left them (the descent's coordinates:
    kd as kd/ks with intensities; NaN where not fitted), the start of its per-pixel fit."""
    ids: np.ndarray
    shared: tuple
    theta: np.ndarray
    stderr: np.ndarray
    ci95: np.ndarray
    determined: np.ndarray
    pixels: np.ndarray
    chi2: np.ndarray
    sse: np.ndarray
    dof: np.ndarray
    status: np.ndarray
    rounds: int
    profile: np.ndarray
    nodes: np.ndarray
    bias: np.ndarray
    p_value: np.ndarray
    fits_data: np.ndarray
    goodness_test: str
    corr: np.ndarray
    cov_notes: list
    beta: np.ndarray = None


def node_regions(setup, shared):
    """The grid's points (as :func:`pbrdf_cl.fitting.images.pixels.regions` orders them) grouped by the
    node of the ``shared`` parameters: (order, rstart, nodes), node r holding
    order[rstart[r]:rstart[r + 1]] and ``nodes[r]`` its shared values."""
    v = grid_values(setup)
    sizes = [v[n].size for n in PARAMETERS]
    idx = np.indices(sizes).reshape(6, -1)
    shape = [sizes[PARAMETERS.index(n)] for n in shared]
    node = np.ravel_multi_index([idx[PARAMETERS.index(n)] for n in shared], shape)
    counts = np.bincount(node, minlength=int(np.prod(shape)))
    rstart = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    order = np.argsort(node, kind="stable").astype(np.int32)
    unr = np.unravel_index(np.arange(counts.size), shape)
    nodes = np.stack([v[n][u] for n, u in zip(shared, unr)], axis=1)
    return order, rstart, nodes


def held_setup(setup, shared, theta):
    """``setup`` with the ``shared`` parameters held at ``theta`` (the per-pixel fits of a label)."""
    fixed = {**setup.fixed, **{n: float(t) for n, t in zip(shared, theta)}}
    return replace(setup, fixed=fixed, axes={n: a for n, a in setup.axes.items() if n not in shared})


def row_parts(rows, lab, values, n_labels):
    """The sums of the per-pixel ``values`` (p, size) of pixels in ``rows`` (ascending) of labels
    ``lab`` per (row, label), rows in order: (labels, sums) for :meth:`RowSums.add_parts`."""
    uk, inv = np.unique(rows * n_labels + lab, return_inverse=True)
    part = np.zeros((uk.size, values.shape[1]))
    np.add.at(part, inv.ravel(), values)
    return uk % n_labels, part


class RowSums:
    """Sums over each label's pixels taken row by row of the stack, rows in order: the same
    whatever the blocks (a row is never split between blocks) and wherever they are computed
    (a block's sums per row, :func:`row_parts`, are added here in row order)."""

    def __init__(self, n_labels, size):
        self.total = np.zeros((n_labels, size))

    def add_parts(self, labels, part):
        """Add a block's sums per (row, label) (:func:`row_parts`), in their order."""
        np.add.at(self.total, labels, part)  # in key order: a label's rows in order


class Passes:
    """The label stage's work on one block of rows (``<pass>_block``: pure functions of the
    block's rows and the pass's inputs, run here or on a ``dask.distributed`` worker,
    :mod:`pbrdf_cl.fitting.images.label_workers`) and what every pass shares: the job's
    constants and an engine.  Each returns the block's sums per row (:func:`row_parts`), added in
    row order where the stage runs (:class:`RowSums`), and what the pass keeps per pixel."""

    def __init__(self, job, eng):
        self.job, self.eng = job, eng
        setup = job.setup
        self.shared = tuple(job.shared)
        self.own = [n for n in job.names if n not in self.shared]
        self.si = [job.names.index(n) for n in self.shared]
        self.bi = [job.names.index(n) for n in self.own]
        self.lo, self.hi = descent_bounds(setup, job.names)
        self.span = self.hi - self.lo
        self.ids = job.label_ids
        self.lab = job.label_index  # flat, -1: not fitted
        self.row = int(np.prod(job.source.shape[1:], dtype=np.int64))
        self.node_order, self.node_rstart, self.nodes = node_regions(setup, self.shared)
        self.order_own, self.rstart_own = regions(grid_values(held_setup(setup, self.shared, np.zeros(2))),
                                                  held_setup(setup, self.shared, np.zeros(2)).free)
        self.dtype = "float64" if getattr(eng, "fp64", True) else "float32"
        self.lanes = eng.call("batch_lanes")

    def profile_block(self, r0, r1):
        """Pass 1 on rows r0..r1 (their values checked): the pixels that can be fitted (label > 0,
        not masked, enough valid measurements; indices in the block), each one's best node of the
        shared parameters' grid and the block's sums of their least chi2 at every node:
        (indices, nodes, [sums per row])."""
        setup = self.job.setup
        blk = Block(self.job.read_rows(r0, r1), setup, self.lanes)
        lab = self.lab[r0 * self.row:r0 * self.row + blk.p]
        need = len(self.own)
        ok = (lab >= 0) & blk.mask & (blk.count >= need + 1) & (blk.distinct >= need)
        idx = np.flatnonzero(ok)
        if not idx.size:
            return idx, np.zeros(0, np.int64), []
        best, _ = self.eng.call("batch_grid", setup, blk.subset(idx), self.node_order, self.node_rstart)
        best = np.asarray(best, float).T
        good = np.all(np.isfinite(best), axis=1)
        idx, best = idx[good], best[good]
        parts = [row_parts(idx // self.row, lab[idx], best, self.ids.size)] if idx.size else []
        return idx, np.argmin(best, axis=1), parts

    def values(self, setup, sub, theta_px, beta):
        """Per pixel of ``sub`` at (theta, beta): [1, residual rows, noise floor^2, chi2, DOP sse,
        Schur complement (S x S), reduced gradient (S)] in coordinates scaled to the bounds."""
        job = self.job
        D = len(job.names)
        X = np.empty((sub.p, D))
        X[:, self.si], X[:, self.bi] = theta_px, beta
        Xi = internal(X, job.names)
        few = all(n in self.shared or n not in job.names for n in ("n", "k"))  # n, k the label's
        res = PixelResiduals(setup, sub, job.names, np.arange(sub.p), setup.use_f00, few_nk=few)
        r, J = fd_jacobian(res.rows, Xi, self.lo, self.hi, varied=res.varied)
        chi2 = np.einsum("pm,pm->p", r, r)
        M = sub.valid.shape[1]
        with np.errstate(divide="ignore", invalid="ignore"):
            sse = np.where(sub.w > 0, r[:, :M] ** 2 / sub.w, 0.0).sum(axis=1)
        J = J * self.span[None, :, None]
        H = np.einsum("pim,pjm->pij", J, J)
        g = np.einsum("pim,pm->pi", J, r)
        b, s = self.bi, self.si
        xi = Xi[:, b]
        held = (((xi <= self.lo[b] + 1e-9 * self.span[b]) & (g[:, b] > 0))
                | ((xi >= self.hi[b] - 1e-9 * self.span[b]) & (g[:, b] < 0)))
        keep = (~held).astype(float)
        Hbb = H[:, b][:, :, b] * keep[:, :, None] * keep[:, None, :]
        Hsb = H[:, s][:, :, b] * keep[:, None, :]
        P = np.linalg.pinv(Hbb, rcond=1e-12, hermitian=True)
        schur = H[:, s][:, :, s] - Hsb @ P @ np.swapaxes(Hsb, 1, 2)
        grad = g[:, s] - (Hsb @ P @ (g[:, b] * keep)[:, :, None])[:, :, 0]
        rows = sub.count * (2 if setup.use_f00 else 1)
        return np.concatenate([np.ones((sub.p, 1)), rows[:, None], sub.noise_floor[:, None] ** 2, chi2[:, None],
                               sse[:, None], schur.reshape(sub.p, -1), grad], axis=1)

    def evaluate_block(self, r0, r1, fitted, active, thetas, previous=None):
        """:meth:`_Stage.evaluate` on rows r0..r1 (``fitted``: their pixels' marks; ``previous``:
        their own parameters, None: from the grid alone): (their own parameters at each candidate
        (C, p, own), NaN where not fitted; per candidate the block's :meth:`values` summed per row)."""
        setup = self.job.setup
        C = thetas.shape[0]
        raw = self.job.source.rows(r0, r1)
        off = r0 * self.row
        lab = self.lab[off:off + raw["dop"].shape[0]]
        fit = fitted & active[np.maximum(lab, 0)]
        trial = np.full((C, lab.size, len(self.own)), np.nan)
        parts = [[] for _ in range(C)]
        labels = np.unique(lab[fit])
        if not labels.size:
            return trial, parts
        idxs = [np.flatnonzero(fit & (lab == L)) for L in labels]
        raws = [take(raw, idx) for idx in idxs]
        # every label's pixels at every candidate as one batch
        done = self.values_sets([(thetas[:, L], Block(r, setup, self.lanes),
                                  None if previous is None else np.broadcast_to(previous[idx], (C,) + idx.shape +
                                                                                previous.shape[1:]))
                                 for L, idx, r in zip(labels, idxs, raws)], [Block(r, setup, 1) for r in raws])
        for L, idx, (beta, vals) in zip(labels, idxs, done):
            for c in range(C):
                trial[c, idx] = beta[c]
                parts[c].append(row_parts((off + idx) // self.row, np.full(idx.size, L), vals[c], self.ids.size))
        return trial, parts

    def values_sets(self, sets, subs):
        """:meth:`descend_sets` of ``sets``, then :meth:`values` of every pixel at each of its set's
        values, all as one call (``subs``: each set's pixels' block for the sums, lanes 1): per set
        (own parameters (C, p, own), values (C, p, sums))."""
        betas = self.descend_sets(sets)
        thetas = np.concatenate([np.repeat(t, b.shape[1], axis=0) for (t, _, _), b in zip(sets, betas)])
        own = np.concatenate([b.reshape(-1, b.shape[2]) for b in betas])
        v = self.values(self.job.setup, stack_blocks(subs, [len(t) for t, _, _ in sets]),
                        thetas.reshape(-1, len(self.shared)), own)
        ends = np.cumsum([b.shape[0] * b.shape[1] for b in betas])
        return [(b, v[e - b.shape[0] * b.shape[1]:e].reshape(b.shape[:2] + (-1,))) for b, e in zip(betas, ends)]

    def descend(self, thetas, blk, previous=None):
        """Each pixel's own parameters at trial values ``thetas`` (C, S) of the shared ones, (C, p,
        own): the best end of float32 descents (``batch_lm``, LM_ITERATIONS) from its ``previous``
        values (C, p, own; None: none) and from the GRID_STARTS best region minima of the grid of
        its own parameters at that value (a pixel's own parameters can jump to another basin as
        theta moves), polished (POLISH_ITERATIONS in float64 where the device has it).
        :meth:`descend_sets` of one set."""
        return self.descend_sets([(thetas, blk, previous)])[0]

    def descend_sets(self, sets):
        """:meth:`descend` of several sets of pixels (a list of (thetas (C, S), block, previous)), all
        as one batch: every set's pixels stacked once per value (:func:`stack_blocks`), each held at
        its own (``batch_lm``'s ``fixed_rows``), a set's grids in one pass (``batch_grid_fixed``);
        every pixel's result is the one it has alone.  ``previous`` given for every set or for
        none.  Returns a list of (C, p, own)."""
        setup = self.job.setup
        X, fixed, prev, held = [], [], [], None
        for thetas, blk, previous in sets:
            helds = [held_setup(setup, self.shared, t) for t in thetas]
            held = helds[0]
            best, arg = self.eng.call("batch_grid_fixed", helds, blk, self.order_own, self.rstart_own)  # (C, R, p)
            top = np.argsort(np.asarray(best, float), axis=1, kind="stable")[:, :GRID_STARTS]
            X += [grid_points(h, self.order_own, np.take_along_axis(a, t, axis=0)) for h, a, t in zip(helds, arg, top)]
            fixed.append(np.repeat(thetas, blk.p, axis=0))
            if previous is not None:
                prev.append(np.asarray(previous).reshape(-1, len(self.own)))
        X = np.concatenate(X, axis=1)  # (T, pixels, free)
        fixed = np.concatenate(fixed)
        cols = [self.own.index(n) for n in held.free]
        starts = np.ones(X.shape[:2] + (len(self.own),))  # ks (with intensities) from 1
        starts[:, :, cols] = X
        prev = np.concatenate(prev) if prev else None
        if prev is not None:
            starts = np.concatenate([prev[None], starts])
        blk = stack_blocks([b for _, b, _ in sets], [len(t) for t, _, _ in sets])
        kw = {}
        if np.any(fixed != fixed[:1]):  # several values held: each pixel its own
            kw["fixed_rows"] = {n: fixed[:, j] for j, n in enumerate(self.shared)}
        d = self.eng.call("batch_lm", held, blk, starts, self.own, "float32", LM_ITERATIONS, held.use_f00, **kw)
        pick = np.argmin(np.where(np.isfinite(d.sse), d.sse, np.inf), axis=0)
        x = d.x[pick, np.arange(blk.p)]
        if prev is not None:  # the float32 descent cannot better a float64 optimum: keep it
            x = np.where((pick == 0)[:, None], prev, x)
        x = self.eng.call("batch_lm", held, blk, x[None], self.own, self.dtype, POLISH_ITERATIONS, held.use_f00,
                          **kw).x[0]
        sizes = [len(t) * b.p for t, b, _ in sets]
        return [x[e - n:e].reshape(len(t), b.p, -1) for e, n, (t, b, _) in zip(np.cumsum(sizes), sizes, sets)]

    def gather_block(self, r0, r1, picks):
        """The raw rows of the pixels ``picks`` of rows r0..r1 (per label, indices in the block):
        one raw dict per label (None where none)."""
        raw = self.job.source.rows(r0, r1)
        return [take(raw, mine) if mine.size else None for mine in picks]


class _Stage(Passes):
    """The passes of one label stage (see the module's docstring): each block's work
    (:class:`Passes`) here, or on the workers of ``workers``
    (:class:`pbrdf_cl.fitting.images.label_workers.WorkerBlocks`: ``map(pass, items)`` yields the
    blocks' results in block order), its results kept and summed here."""

    def __init__(self, job, eng, progress, workers=None):
        super().__init__(job, eng)
        self.progress, self.workers = progress, workers
        self.fitted = np.zeros(self.lab.size, bool)
        self.pixel_node = np.full(self.lab.size, -1, np.int64)  # each pixel's best node of the profile
        self.beta = np.full((self.lab.size, len(self.own)), np.nan)

    def _bar(self, desc, total):
        if not self.progress:
            return None
        from tqdm.auto import tqdm
        return tqdm(total=total, desc=f"labels: {desc}", unit="px", unit_scale=True, smoothing=0.1)

    def _blocks(self, desc, kind, args_of):
        """(pixel offset, result) of every block in order: ``<kind>_block`` of :class:`Passes` on
        its rows and ``args_of(offset, pixels)``, here or on the workers, with a progress bar in
        pixels."""
        blocks = self.job.blocks()
        items = ((r0, r1, *args_of(r0 * self.row, (r1 - r0) * self.row)) for r0, r1 in blocks)
        if self.workers is None:
            results = (getattr(self, f"{kind}_block")(*item) for item in items)
        else:
            results = self.workers.map(kind, items)
        bar = self._bar(desc, self.job.source.n_pixels)
        try:
            for (r0, r1), res in zip(blocks, results):
                yield r0 * self.row, res
                if bar is not None:
                    bar.update((r1 - r0) * self.row)
        finally:
            results.close()
            if bar is not None:
                bar.close()

    def profile(self):
        """Pass 1: each label's chi2 profile over the shared parameters' grid nodes; marks the
        pixels that can be fitted (label > 0, not masked, enough valid measurements)."""
        sums = RowSums(self.ids.size, self.node_rstart.size - 1)
        for off, (idx, node, parts) in self._blocks("grid", "profile", lambda off, p: ()):
            self.fitted[off + idx] = True
            self.pixel_node[off + idx] = node
            for part in parts:
                sums.add_parts(*part)
        return sums.total

    def evaluate(self, thetas, active, start=False):
        """One pass at candidate values ``thetas`` (C, L, S) of the ``active`` labels: each pixel's
        own parameters descended (:meth:`descend`; ``start``: from its grid alone, else also from
        its current ones) into ``trial_beta`` (C, pixels, own); returns the labels' sums of
        :meth:`values` at each candidate, (C, L, sums)."""
        C, S = thetas.shape[0], len(self.shared)
        sums = [RowSums(self.ids.size, 5 + S * S + S) for _ in range(C)]
        self.trial_beta = np.full((C,) + self.beta.shape, np.nan)

        def args(off, p):  # copies: a worker's block may still be on its way when the driver moves on
            return self.fitted[off:off + p].copy(), active, thetas, None if start else self.beta[off:off + p].copy()
        for off, (trial, parts) in self._blocks("start" if start else "refine", "evaluate", args):
            self.trial_beta[:, off:off + trial.shape[1]] = trial
            for c in range(C):
                for part in parts[c]:
                    sums[c].add_parts(*part)
        return np.stack([t.total for t in sums])

    def start(self, theta, active):
        """The pass at the seeds ``theta`` (L, S): every pixel's own parameters descended from the
        grid of its own parameters alone (:meth:`evaluate` with ``start``) into ``beta`` (a pixel
        whose descent fails leaves the label stage); the labels' sums there.  (The refinement's
        passes descend them again at every step, each from its previous values and the grid; the
        per-pixel pass fits them with the usual stages at the label's final values.)"""
        sums = self.evaluate(theta[None], active, start=True)[0]
        mine = self.fitted & active[np.maximum(self.lab, 0)]
        kept = np.all(np.isfinite(self.trial_beta[0]), axis=1)
        self.fitted &= ~(mine & ~kept)
        self.beta[mine & kept] = self.trial_beta[0, mine & kept]
        return sums

    def gather(self, picks):
        """One pass over the stack: the raw rows of the pixels ``picks`` (a list per label of flat
        pixel indices, ascending), in memory, as one raw dict per label (None where empty)."""
        parts = [[] for _ in picks]

        def args(off, p):
            return ([idx[(idx >= off) & (idx < off + p)] - off for idx in picks],)
        for _, got in self._blocks("subsample", "gather", args):
            for L, part in enumerate(got):
                if part is not None:
                    parts[L].append(part)
        return [concatenate(ps) if ps else None for ps in parts]

    def local_fit(self, raw, theta, rounds, beta=None):
        """The shared parameters of one label refined on the in-memory pixels ``raw`` from ``theta``:
        each pixel's own parameters descended there (:meth:`local_at`, from ``beta`` where given),
        then up to ``rounds`` damped Gauss-Newton steps (:meth:`local_steps`) kept where the chi2
        of these pixels falls.  Returns (theta, sums of :meth:`values` over the pixels, beta); a
        pixel whose descent fails counts nowhere."""
        raw = self.local_blocks(raw)
        beta, sums = self.local_at(raw, theta, beta)
        theta, sums, beta, _ = self.local_steps(raw, theta, sums, beta, rounds)
        return theta, sums, beta

    def local_blocks(self, raw):
        """The in-memory pixels ``raw`` prepared once for :meth:`local_at` (which takes either):
        (raw, their block for the descents, their block for :meth:`values`)."""
        if isinstance(raw, tuple):
            return raw
        setup = self.job.setup  # a block does not depend on the values held (held_setup)
        return raw, Block(raw, setup, self.lanes), Block(raw, setup, 1)

    def local_at(self, raw, theta, previous=None):
        """The own parameters of the in-memory pixels ``raw`` (or :meth:`local_blocks` of them)
        descended (:meth:`descend`, from ``previous`` where given) with the shared held at
        ``theta``: (beta, the sums of :meth:`values` over the pixels whose values are finite)."""
        return self.local_at_many([(self.local_blocks(raw), theta, previous)])[0]

    def local_at_many(self, items):
        """:meth:`local_at` of several (:meth:`local_blocks`, theta, previous) at once, as one batch
        (:meth:`descend_sets`, :meth:`values` of the stacked pixels; those with ``previous`` and
        those without apart, in batches of at most BATCH_PIXELS pixels, or of one item that alone
        holds more): each result is the one it has alone.  Returns a list of (beta, sums)."""
        out = [None] * len(items)
        batches = []  # those with previous and those without apart, each in batches of BATCH_PIXELS
        for first in (True, False):
            mine, pixels = [], 0
            for i, item in enumerate(items):
                if (item[2] is None) != first:
                    continue
                if mine and pixels + item[0][1].p > BATCH_PIXELS:
                    batches.append((first, mine))
                    mine, pixels = [], 0
                mine.append(i)
                pixels += item[0][1].p
            if mine:
                batches.append((first, mine))
        for first, mine in batches:
            groups = {}  # the items of each subsample, in order of first appearance
            for i in mine:
                groups.setdefault(id(items[i][0][1]), []).append(i)
            groups = list(groups.values())
            sets = [(np.stack([np.asarray(items[i][1], float) for i in g]), items[g[0]][0][1],
                     None if first else np.stack([items[i][2] for i in g])) for g in groups]
            done = self.values_sets(sets, [items[g[0]][0][2] for g in groups])
            for g, (b, v) in zip(groups, done):
                for c, i in enumerate(g):
                    out[i] = (b[c], v[c][np.all(np.isfinite(v[c]), axis=1)].sum(axis=0))
        return out

    def local_steps(self, raw, theta, sums, beta, rounds, lam=1e-3):
        """Up to ``rounds`` damped Gauss-Newton steps (:meth:`step`, Marquardt damping ``lam``) of
        one label's shared parameters on the in-memory pixels ``raw`` (or :meth:`local_blocks` of
        them) from ``theta`` (``sums``, ``beta``: :meth:`local_at` there), each kept where the
        chi2 of these pixels falls; they stop where a step would lower it by less than CHI2_TOL
        (times its chi2 scale).  Returns (theta, sums, beta, lam): a later call resumes where this
        one stopped."""
        return self.local_steps_many([(self.local_blocks(raw), theta, sums, beta, rounds, lam)])[0]

    def local_steps_many(self, items):
        """:meth:`local_steps` of several (:meth:`local_blocks`, theta, sums, beta, rounds, lam) in
        step: each round's trial points of all of them evaluated as one batch
        (:meth:`local_at_many`); each result is the one it has alone.  Returns a list of (theta,
        sums, beta, lam)."""
        span = self.span[self.si]
        state = [dict(blocks=blocks, theta=theta, sums=sums, beta=beta, left=rounds, lam=np.array([lam], float),
                      rejected=None) for blocks, theta, sums, beta, rounds, lam in items]
        live = [q for q in state if q["left"] > 0]
        while live:
            trials = []
            for q in live:
                q["left"] -= 1
                trial, predicted = self.step(q["theta"][None], q["sums"][None], q["lam"])
                if predicted[0] <= CHI2_TOL * self.scale(q["sums"][None])[0]:
                    q["left"] = 0
                    continue
                du = (trial[0] - q["theta"]) / span
                rejected = q["rejected"]
                if rejected is not None and np.linalg.norm(du - rejected) < SAME_STEP * np.linalg.norm(rejected):
                    q["lam"] = q["lam"] * 10.0  # the step just rejected, hardly shorter: rejected again, unevaluated
                    continue
                trials.append((q, trial[0], du, predicted[0]))
            ends = self.local_at_many([(q["blocks"], t, q["beta"]) for q, t, _, _ in trials])
            for (q, t, du, predicted), (b, v) in zip(trials, ends):
                if v[3] < q["sums"][3]:
                    q.update(theta=t, sums=v, beta=b, lam=q["lam"] / 3.0, rejected=None)
                else:  # a step along which the chi2 rose by more than the fall it predicted is remembered
                    q.update(lam=q["lam"] * 10.0, rejected=du if v[3] - q["sums"][3] > predicted else None)
            live = [q for q in live if q["left"] > 0]
        return [(q["theta"], q["sums"], q["beta"], float(q["lam"][0])) for q in state]

    def unpack(self, sums):
        """(pixels, rows, floor^2 sum, chi2, sse, Schur (L, S, S), gradient (L, S)) from sums."""
        S = len(self.shared)
        return (sums[:, 0], sums[:, 1], sums[:, 2], sums[:, 3], sums[:, 4], sums[:, 5:5 + S * S].reshape(-1, S, S),
                sums[:, 5 + S * S:])

    def step(self, theta, sums, lam):
        """The damped Gauss-Newton trial of every label from its sums at ``theta``: (trial theta,
        the decrease of F the step predicts)."""
        _, _, _, _, _, A, g = self.unpack(sums)
        S = A.shape[1]
        s = self.si
        scale = np.einsum("lii->li", A)
        ridge = 1e-12 * np.maximum(scale.max(axis=1), 1e-300)
        Ad = A + (lam[:, None] * scale + ridge[:, None])[:, :, None] * np.eye(S)[None]
        with np.errstate(all="ignore"):
            du = -np.linalg.solve(Ad, g[:, :, None])[:, :, 0]
        du = np.where(np.isfinite(du), du, 0.0)
        trial = np.clip(theta + du * self.span[s], self.lo[s], self.hi[s])
        du = (trial - theta) / self.span[s]
        predicted = -np.einsum("li,li->l", g, du) - 0.5 * np.einsum("li,lij,lj->l", du, A, du)
        return trial, predicted

    def refine(self, theta, sums, active):
        """Passes of the refinement (:meth:`step`, :meth:`evaluate`) until no active label's F
        falls; returns (theta, sums, not converged, passes)."""
        lam = np.full(self.ids.size, 1e-3)
        self.beta[~self.fitted] = np.nan
        rounds = 0
        for _ in range(MAX_ROUNDS):
            chi2 = sums[:, 3]
            tol = CHI2_TOL * self.scale(sums)
            trial, predicted = self.step(theta, sums, lam)
            active &= predicted > tol
            if not active.any():
                break
            rounds += 1
            new = self.evaluate(trial[None], active)[0]
            better = active & (new[:, 3] < chi2)
            mine = self.fitted & np.isin(self.lab, np.flatnonzero(better))
            self.beta[mine] = self.trial_beta[0, mine]
            theta, sums = np.where(better[:, None], trial, theta), np.where(better[:, None], new, sums)
            lam = np.where(better, lam / 3.0, np.where(active, lam * 10.0, lam))
            active &= better | (lam < 1e8)
            active &= ~(better & (chi2 - new[:, 3] <= tol))
        return theta, sums, active, rounds

    def dof(self, sums):
        """Each label's degrees of freedom: its residuals less its pixels' own parameters and the shared."""
        return np.maximum(sums[:, 1] - sums[:, 0] * len(self.own) - len(self.shared), 1)

    def scale(self, sums):
        """Each label's chi2 of one standard error squared: 1 with dop_std, else its reduced chi2
        (at least its pixels' mean noise floor squared)."""
        if self.job.setup.sigma_known:
            return np.ones(sums.shape[0])
        return np.maximum(sums[:, 3] / self.dof(sums), sums[:, 2] / np.maximum(sums[:, 0], 1))

    def covariance(self, sums, given=None):
        """Each label's covariance of the shared parameters, in coordinates scaled to the bounds:
        the inverse of its summed Schur complements times its chi2 scale (the pseudo-inverse, with
        an infinite variance for the parameter that a direction they do not see mostly is: k at
        k = 0, where the model's derivative in k vanishes,
        :func:`~pbrdf_cl.fitting.common.null_parameters`, as :func:`pbrdf_cl.fit` has it),
        or ``given`` (L, S, S, scaled coordinates: the bootstrap's,
        :func:`pbrdf_cl.fitting.images.label_search.binding_correction`) where given, made valid
        (:func:`pbrdf_cl.fitting.common.valid_covariance`; NaN where a variance cannot be computed)."""
        if given is not None:
            return valid_covariance(given)
        A = self.unpack(sums)[5]
        with np.errstate(all="ignore"):
            cov = np.linalg.pinv(A, rcond=NULL_RCOND, hermitian=True) * self.scale(sums)[:, None, None]
            seen = np.all(np.isfinite(A), axis=(1, 2))
            null = np.zeros(A.shape[:2], bool)
            if seen.any():
                null[seen] = null_parameters(*np.linalg.eigh(A[seen]), share=0.5)
            np.einsum("lii->li", cov)[...] = np.where(null, np.inf, np.einsum("lii->li", cov))
            return valid_covariance(cov)

    def natural(self, cov, inverse=False):
        """A covariance (L, S, S) scaled to the bounds in the shared parameters' units (or back)."""
        span = self.span[self.si]
        f = np.outer(span, span)
        return cov / f if inverse else cov * f

    def gauss(self, theta, sums, given=None):
        """Standard errors and the 95% intervals (the estimate +- 1.96 standard errors, Student's t
        without dop_std, cut at the bounds, k's holding that of k^2 too where the data see k
        through k^2, every fit but one of polarimetric channels:
        :func:`~pbrdf_cl.fitting.common.bounded_interval`) of every label at ``theta``
        from its sums (or the covariance ``given``, see :meth:`covariance`); returns (se, ci, dof,
        chi2 scale).  A variance that cannot be computed gives an infinite standard error (the
        interval spans the bounds)."""
        setup = self.job.setup
        s, span = self.si, self.span[self.si]
        dof, s2 = self.dof(sums), self.scale(sums)
        with np.errstate(invalid="ignore"):
            se = np.sqrt(np.clip(np.einsum("lii->li", self.covariance(sums, given).cov), 0, None)) * span
        se = np.where(np.isfinite(se), se, np.inf)
        ci = np.stack(bounded_interval(theta, np.maximum(se, X_RESOLUTION * span), self.lo[s], self.hi[s],
                                       None if setup.sigma_known else dof[:, None],
                                       seen_through_square(self.shared, setup.channels)), axis=-1)
        return se, ci, dof, s2

    def intervals(self, theta, sums, profile, active, given=None, other=None):
        """Standard errors, 95% intervals, ``determined`` and the status of every label (see the
        module's docstring): :meth:`gauss` with the covariance ``given``, widened to the profile's
        nodes the data allow and to ``other`` (L, S, 2: another basin's interval, NaN where none)
        where given, either marking the label ambiguous."""
        chi2 = self.unpack(sums)[3]
        s, span = self.si, self.span[self.si]
        lo, hi = self.lo[s], self.hi[s]
        se, ci, dof, s2 = self.gauss(theta, sums, given)
        # the profile on the grid is an upper bound of the true one: a node within the threshold
        # of the minimum is a value the data allow
        near = profile <= (chi2 + CHI2_95 * s2)[:, None]
        ambiguous = np.zeros(theta.shape[0], bool)
        for L in range(theta.shape[0]):
            v = self.nodes[near[L]]
            if other is not None and np.all(np.isfinite(other[L])):
                v = np.concatenate([v, other[L].T])
            if not v.size:
                continue
            out = (v < ci[L, :, 0]) | (v > ci[L, :, 1])
            ambiguous[L] = out.any()
            ci[L, :, 0] = np.minimum(ci[L, :, 0], v.min(axis=0))
            ci[L, :, 1] = np.maximum(ci[L, :, 1], v.max(axis=0))
        determined = (ci[..., 1] - ci[..., 0]) < DETERMINED_FRACTION * span
        status = np.ones(theta.shape[0], np.int8)
        status[np.any((theta <= lo + X_RESOLUTION * span) | (theta >= hi - X_RESOLUTION * span), axis=1)] = 2
        status[ambiguous] = 3
        status[~determined.all(axis=1)] = 4
        status[active] = 0
        return se, ci, determined, status, dof

    def full_fit(self, theta, ok):
        """Every pixel of the labels ``ok`` fitted at ``theta`` (:meth:`start`), then
        :meth:`refine`: (theta, sums, ok, not converged, passes)."""
        sums = self.start(theta, ok)
        ok = ok & (sums[:, 0] >= self.job.min_label_pixels)
        theta, sums, active, rounds = self.refine(theta, sums, ok.copy())
        return theta, sums, ok, active, rounds


def run_label_stage(job, eng, progress=False, workers=None):
    """The shared parameters of every label of ``job`` (a ``pbrdf_cl.fitting.images.labels.LabelJob``).

    Parameters
    ----------
    job : pbrdf_cl.fitting.images.labels.LabelJob
        The checked job: the stack, its setup, the label image and the shared parameters.
    eng : pbrdf_cl.Engine or NumpyEngine
        Where the grid and the pixels' descents run.
    progress : bool, default False
        A progress bar per pass over the stack.
    workers : optional
        Where the passes' blocks run: here with ``eng`` (None), or on a ``dask.distributed``
        cluster's workers (a ``pbrdf_cl.fitting.images.label_workers.WorkerBlocks``); the same
        result bit for bit (on the same device).  The subsample's search and the intervals run here.

    Returns
    -------
    LabelResult
        Values, standard errors, intervals and status of the shared parameters, per label.

    Examples
    --------
    >>> job = LabelJob(stack, labels=L)  # doctest: +SKIP
    >>> run_label_stage(job, engine).theta  # doctest: +SKIP
    array([[1.601, 2.142], [1.398, 0.503]])
    """
    st = _Stage(job, eng, progress, workers)
    L = st.ids.size
    profile = st.profile()
    pixels = np.bincount(st.lab[st.fitted], minlength=L)
    ok = pixels >= job.min_label_pixels
    shape = [job.setup.axes[n].size for n in st.shared]
    cand = st.nodes[seed_nodes(np.where(ok[:, None], profile, 0.0), shape, SEEDS)]  # (C, L, S)
    cand = np.concatenate([cand, search.median_node(st, st.pixel_node)[None]])
    picks = search.subsample(st)
    subs = st.gather(picks)
    best, runner, gap = search.rank_seeds(st, subs, cand, ok, pixels)
    theta, sums, ok, active, rounds = st.full_fit(best, ok)
    other = np.full(theta.shape + (2,), np.nan)
    second = ok & (gap < search.RUNNER_UP_CHI2)
    if second.any():
        theta, sums, active, other, more = refit_runner_up(st, theta, sums, active, runner, second)
        rounds += more
    stuck = ok & unseen_on_bound(st, theta, sums)
    if stuck.any():  # k = 0, where no descent can leave it: fitted again from inside, the better kept
        start = search.moved_inside(st, theta, search.INWARD[0])
        theta, sums, active, inside, more = refit_runner_up(st, theta, sums, active, start, stuck, point_first=True)
        other = np.where(np.isfinite(inside), inside, other)
        rounds += more
    p_value, fits, test = label_goodness(st, sums, subs, picks, theta, ok, pixels)
    s = st.si
    given = None
    if job.bias_replicates:
        cov = st.natural(st.covariance(sums).cov)
        corrected, cov, _ = search.binding_correction(st, subs, picks, theta, cov, st.scale(sums), ok,
                                                      job.bias_replicates)
        bias, given = theta - corrected, st.natural(cov, inverse=True)
    elif job.integrated:
        corrected, cov = integrated_correction(st, theta, sums, ok)
        bias = theta - corrected
        if not np.array_equal(cov, st.covariance(sums).cov, equal_nan=True):  # a label's subsample's noise
            given = cov
    else:
        bias = np.zeros_like(theta)
    theta = np.where(ok[:, None], np.clip(theta - bias, st.lo[s], st.hi[s]), 0.0)
    se, ci, determined, status, dof = st.intervals(theta, sums, profile, active, given, other)
    status[~ok] = -2
    nan = np.where(ok[:, None], 1.0, np.nan)
    _, _, _, chi2, sse, _, _ = st.unpack(sums)
    valid = st.covariance(sums, given)
    notes = [valid.note(st.shared, L, f"the covariance of label {st.ids[L]}'s {', '.join(st.shared)}") if ok[L]
             else None for L in range(st.ids.size)]
    return LabelResult(st.ids, st.shared, theta * nan, se * nan, ci * nan[..., None], determined & ok[:, None],
                       sums[:, 0].astype(np.int64), np.where(ok, chi2, np.nan), np.where(ok, sse, np.nan),
                       np.where(ok, dof, 0).astype(np.int64), status, rounds, profile, st.nodes, bias * nan,
                       np.where(ok, p_value, np.nan), np.where(ok, fits, -1).astype(np.int8),
                       test, valid.corr * nan[:, :, None], notes,
                       np.where((st.fitted & np.isin(st.lab, np.flatnonzero(ok)))[:, None], st.beta, np.nan))


def label_goodness(st, sums, subs, picks, theta, ok, pixels):
    """Whether each label's shared values describe its pixels' data: (p-value, fits (1, 0, or -1
    where not tested), the test: "chi2" or "F").  With given uncertainties (``dop_std``, and
    ``f00_std`` with intensities) the label's chi2 against its degrees of freedom (its residuals
    less its pixels' own parameters and the shared ones); else (its chi2 has no scale, or an
    assumed one) the F test of :func:`pbrdf_cl.fitting.images.label_search.f_test` on its subsample.  A
    p-value below :data:`~pbrdf_cl.fitting.common.GOODNESS_P` fails, as a fit's."""
    setup = st.job.setup
    if setup.sigma_known and (not setup.use_f00 or "f00_std" in st.job.source.vars):
        chi2 = st.unpack(sums)[3]
        p_value, test = np.where(ok, report.chi2_p_value(chi2, st.dof(sums)), np.nan), "chi2"
    else:
        p_value, test = search.f_test(st, subs, picks, theta, ok, pixels), "F"
    fits = np.where(np.isfinite(p_value), p_value >= GOODNESS_P, -1).astype(np.int8)
    return p_value, fits, test


def refit_runner_up(st, theta, sums, active, runner, second, point_first=False):
    """The labels ``second`` fitted again on all their pixels from their runner-up basin
    ``runner``; per label the basin of lower chi2 kept (its pixels' own parameters too).  Returns
    (theta, sums, not converged, other, passes): ``other`` (L, S, 2) the interval of the basin not
    kept where its chi2 lies within CHI2_95 (times the chi2 scale) of the kept one's, else NaN;
    with ``point_first``, the first basin's interval is its values alone (a label left on a bound
    the data hardly see, :func:`unseen_on_bound`: its Gaussian interval there is the central 95%
    of an almost uniform spread over the bounds, which leaves out the bound itself)."""
    beta, fitted = st.beta.copy(), st.fitted.copy()
    t2, s2, ok2, a2, rounds = st.full_fit(np.where(second[:, None], runner, theta), second.copy())
    ok2 &= second
    better = ok2 & (s2[:, 3] < sums[:, 3])
    keep_first = np.isin(st.lab, np.flatnonzero(second & ~better))
    st.beta[keep_first], st.fitted[keep_first] = beta[keep_first], fitted[keep_first]
    _, ci1, _, sc1 = st.gauss(theta, sums)
    if point_first:
        ci1 = np.stack([theta, theta], axis=-1)
    _, ci2, _, sc2 = st.gauss(t2, s2)
    close = ok2 & (np.abs(s2[:, 3] - sums[:, 3]) < CHI2_95 * np.maximum(sc1, sc2))
    other = np.where((close & better)[:, None, None], ci1, np.where((close & ~better)[:, None, None], ci2, np.nan))
    theta = np.where(better[:, None], t2, theta)
    sums = np.where(better[:, None], s2, sums)
    active = np.where(better, a2, active)
    return theta, sums, active, other, rounds


#: A shared parameter on a bound whose standard error there exceeds this fraction of its range
#: (or has none) is one the data hardly see there (:func:`unseen_on_bound`).
UNSEEN_SE = 0.25


def unseen_on_bound(st, theta, sums):
    """The labels (L,) with a shared parameter on one of its bounds (:func:`~pbrdf_cl.fitting.common.on_bound`)
    that the data hardly see there: no variance, or a standard error of more than UNSEEN_SE of
    its range (:meth:`_Stage.covariance`).  k at k = 0 is one: the model's derivative in k
    vanishes there (it depends on k through k^2), so that the refinement's Gauss-Newton steps
    cannot leave it even where k > 0 fits the data better (the search's subsample refinements
    start again from inside such a bound, :data:`label_search.INWARD`; the refinement on all the
    pixels can still end there)."""
    low, high = on_bound(theta, st.lo[st.si], st.hi[st.si])
    cov = st.covariance(sums)
    with np.errstate(invalid="ignore"):
        weak = cov.undefined | ~(np.einsum("lii->li", cov.cov) <= UNSEEN_SE ** 2)  # scaled coordinates
    return np.any((low | high) & weak, axis=1)


def seed_nodes(profile, shape, count):
    """Per label, the ``count`` lowest local minima of its ``profile`` (L, nodes) over the node
    grid of ``shape`` (a node no higher than its neighbours along every axis), lowest first,
    the lowest repeated where there are fewer: (count, L) node indices."""
    P = profile.reshape((-1,) + tuple(shape))
    local = np.ones(P.shape, bool)
    for ax in range(1, P.ndim):
        n = P.shape[ax]
        for shift in (1, -1):
            nb = np.roll(P, shift, axis=ax)
            edge = [slice(None)] * P.ndim
            edge[ax] = 0 if shift == 1 else n - 1
            nb[tuple(edge)] = np.inf
            local &= P <= nb
    flat = profile.reshape(profile.shape[0], -1)
    key = np.where(local.reshape(flat.shape), flat, np.inf)
    order = np.argsort(key, axis=1, kind="stable")[:, :count]
    first = order[:, :1]
    order = np.where(np.isfinite(np.take_along_axis(key, order, axis=1)), order, first)
    return order.T
