"""The correction of a label's shared values for the incidental parameters' bias by its integrated
likelihood (:func:`integrated_correction`; on by default, ``LabelJob.integrated``; see
docs/joint_images.md for what it achieves and costs).

The label stage's estimate minimises the profile F(theta) = sum_p min_beta chi2_p(theta, beta): every
pixel's own parameters (sigma, kd, c) are fitted at each theta.  With ~30 measurements per pixel
and bounded own parameters its bias does not shrink with the pixel count while its standard error
does (the Neyman-Scott problem).  The integrated likelihood treats the own parameters as random
effects instead: each pixel's own parameters in logit coordinates u = logit((x - lo) / (hi - lo))
(smooth and unbounded, so nothing sticks to a bound) drawn from a Gaussian population
N(mu, diag(D)) estimated from the pixels (empirical Bayes), and the label's objective is minus
twice the log of the marginal likelihood in its Laplace approximation,

    G(theta) = sum_p [Q_p(theta) + log det H_p(theta)] + P log det D,
    Q_p = min_u chi2_p(theta, u) / s2 + (u - mu)^T D^-1 (u - mu),

H_p = J_u^T J_u / s2 + D^-1 the Gauss-Newton Hessian of Q_p / 2 at the pixel's mode, s2 the label's
chi2 scale.  The population's mean and variance are fitted at the profile's values (Laplace EM,
the mean by Newton steps with the modes following it, :meth:`Integrated.mean_step`); at every
other theta the mean is fitted again and the variance held.  From the profile's values, up to
NEWTON_ROUNDS Newton steps on G, each from G's quadratic fitted over a 3 x 3 stencil of one
profile standard error (:func:`stencil`, :func:`newton`); where that quadratic is not convex (G's
minimum lies farther along the profile's valley of correlated n and k than the stencil reaches),
steps downhill along the profile's metric first (:func:`downhill`), up to DOWNHILL_ROUNDS rounds
in all.  The intervals stay the profile's
(its covariance, centred on the corrected values).  Everything is evaluated with the reference
model's residual rows (:class:`~pbrdf_cl.fitting.images.pixels.PixelResiduals`) on the host, on at
most PIXELS of the label's pixels, evenly spaced and gathered in one more pass over the stack: on
a larger label the correction is that subsample's, its sampling noise taken out by the profile's
gradient there and its remaining noise added to the interval (:func:`integrated_correction`).
What bias G leaves does not shrink with the label's pixels while the profile's standard error
does: a label of more than PRECISION_PIXELS pixels reports the covariance of that many of them.
The labels are corrected together, in groups of at most GROUP_PIXELS pixels (:class:`Integrated`
holds a group's pixels): each call of the reference model evaluates the rows of every label of
the group still stepping, and each label's numbers are those it would have alone.  With several
labels the groups are spread over the machine's cores, in forked processes on Linux
(:func:`pbrdf_cl.fitting.processes.spread`; ``PBRDF_CL_HOST_PROCESSES=1``: all here): the same numbers.
"""
from __future__ import annotations

from itertools import product

import numpy as np

from .. import processes
from ..common import fd_steps
from .label_search import subsample
from .pixels import Block, PixelResiduals, concatenate, take

#: Whether the label stage corrects its values by default (``LabelJob.integrated``).
INTEGRATED = True
#: Laplace EM iterations of the population's mean and variance at the label's values.
EM_ROUNDS = 6
#: Gauss-Newton (Levenberg-Marquardt) iterations of each pixel's mode, at most.
MODE_ITERATIONS = 8
#: ... a pixel's ending where its step changes its Q by less than this, or would by its quadratic
#: model (then without evaluating it: one evaluation of the model fewer per pixel and call).
MODE_TOL = 1e-5
#: The own parameters' fractions of their bounds the logit coordinates start from (at most this
#: close to a bound) and the modes' logit coordinates' bound.
EDGE = 1e-4
U_MAX = 12.0
#: The step of the stencil of G, in standard errors of the label's profile values.
STEP = 1.0
#: Newton steps on G at most, each at most MAX_STEP standard errors per parameter; the population
#: refitted (POPULATION_ROUNDS of EM) at each new point.
NEWTON_ROUNDS = 2
MAX_STEP = 3.0
#: Rounds in all of a label whose G is not convex at its values (:func:`downhill`), and the
#: fractions of its step along the profile's metric where G is evaluated.
DOWNHILL_ROUNDS = 6
LINE_STEPS = (1.0 / 3.0, 2.0 / 3.0, 1.0)
POPULATION_ROUNDS = 2
#: Pixels of each label G is evaluated on (all of a smaller label; evenly spaced).
PIXELS = 128
#: Labels are corrected together in groups of at most this many pixels (one label at least): the
#: model's temporaries then take a few tens of MB whatever the number of labels.
GROUP_PIXELS = 1024
#: The most pixels whose precision a corrected label's interval claims: a larger label's
#: covariance is that of this many of its pixels (its own times pixels / PRECISION_PIXELS).  What
#: bias G leaves is about the same whatever the label's size while its standard error shrinks
#: (docs/joint_images.md), so a larger label's own interval would not hold it.  96, was 128: on
#: 64 labels of 128 pixels at DOP noise 0.01 (seeds no test uses) their own intervals covered
#: 53-54 times, these 57.
PRECISION_PIXELS = 96


def spans(start, ls):
    """Each label of ``ls`` (labels j holding rows start[j]..start[j + 1]): the slice of its rows
    among the rows of the labels ``ls`` laid end to end, in order."""
    sizes = np.diff(start)[ls]
    ends = np.cumsum(sizes)
    return [slice(e - n, e) for e, n in zip(ends, sizes)]


class Integrated:
    """The terms of the integrated chi2 G (see the module's docstring) of several labels at once:
    label j's pixels those of ``raws[j]`` (a raw dict), its own parameters from ``betas[j]``
    (pixels, own; the profile's values at the label's), its chi2 scale ``s2[j]``.  Its methods
    work on the labels ``ls`` (indices into those given, ascending) and take K values of each
    one's shared parameters at once (``thetas`` (K, len(ls), S)); the modes ``u`` (K, rows, own)
    over the rows of those labels' pixels (:meth:`rows`), the populations' means ``mu`` (K,
    len(ls), own) and variances ``D`` (len(ls), own; held over the K values): one call of the
    reference model per iteration for all of them.  Every label's numbers are those it would
    have alone (every operation is row by row, or a label's own sum)."""

    def __init__(self, setup, names, shared, raws, betas, s2, lo, hi):
        self.names = list(names)
        self.si = [self.names.index(n) for n in shared]
        self.bi = [self.names.index(n) for n in self.names if n not in shared]
        self.lo, self.hi = lo, hi
        sizes = np.array([b.shape[0] for b in betas])
        self.start = np.concatenate([[0], np.cumsum(sizes)])
        blk = Block(concatenate(raws), setup, 1)
        self.p = blk.p
        self.s2 = np.repeat(np.asarray(s2, float), sizes)  # each pixel's label's
        #: the reference model's residual rows of the pixels
        self.res = PixelResiduals(setup, blk, self.names, np.arange(self.p), setup.use_f00, few_nk=True)
        b = self.bi
        self.beta = np.concatenate(betas)
        f = np.clip((self.beta - lo[b]) / (hi[b] - lo[b]), EDGE, 1 - EDGE)
        self.u = np.log(f / (1 - f))
        self.mu = np.stack([self.u[self.pixels(j)].mean(axis=0) for j in range(sizes.size)])
        self.D = np.stack([np.maximum(self.u[self.pixels(j)].var(axis=0), 1e-2) for j in range(sizes.size)])
        self.theta = np.full((sizes.size, len(self.si)), np.nan)  # where the stored modes were fitted

    def pixels(self, j):
        """The rows of label j's pixels."""
        return slice(self.start[j], self.start[j + 1])

    def rows(self, ls):
        """The rows of the pixels of the labels ``ls`` in order, and each one's position in ``ls``."""
        sizes = np.diff(self.start)[ls]
        return np.concatenate([np.arange(self.start[j], self.start[j + 1]) for j in ls]), np.repeat(
            np.arange(len(ls)), sizes)

    def own(self, u):
        """The own parameters at logit coordinates ``u`` and their derivatives dx/du."""
        b = self.bi
        s = 1.0 / (1.0 + np.exp(-u))
        w = self.hi[b] - self.lo[b]
        return self.lo[b] + w * s, w * s * (1.0 - s)

    def _jacobian(self, th, u, pix, shared=False):
        """The residual rows r (B, rows; over the labels' chi2 scales) of the pixels ``pix`` at
        shared values ``th`` (B, S) and modes ``u`` (B, own), their forward differences along the
        own parameters in logit coordinates, Ju (B, own, rows), and with ``shared`` along the
        shared ones too, Jt (B, S, rows; natural units; else None): scipy's steps, inwards at an
        upper bound."""
        B, o = u.shape
        x, dx = self.own(u)
        X = np.empty((B, len(self.names)))
        X[:, self.si] = th
        X[:, self.bi] = x
        h, cols = fd_steps(x, self.hi[self.bi]), self.bi
        if shared:
            h, cols = np.concatenate([h, fd_steps(th, self.hi[self.si])], axis=1), self.bi + self.si
        R = self.res.varied(X, cols, h, pix) / np.sqrt(self.s2[pix])[:, None, None]
        r = R[:, 0]
        Ju = (R[:, 1:1 + o] - r[:, None]) * (dx / h[:, :o])[:, :, None]
        return r, Ju, (R[:, 1 + o:] - r[:, None]) / h[:, o:, None] if shared else None

    def _at(self, th, u, mu, D, pix):
        """(Q, H, g) of rows of (shared values ``th`` (B, S), modes ``u`` (B, own), mean ``mu``
        and variance ``D`` (B, own)) of the pixels ``pix``: forward differences along the own
        parameters only (:meth:`_jacobian`)."""
        o = u.shape[1]
        r, Ju, _ = self._jacobian(th, u, pix)
        pr = (u - mu) / np.sqrt(D)
        Q = np.einsum("pm,pm->p", r, r) + np.einsum("pi,pi->p", pr, pr)
        H = np.einsum("pim,pjm->pij", Ju, Ju) + (1.0 / D)[:, :, None] * np.eye(o)
        g = np.einsum("pim,pm->pi", Ju, r) + pr / np.sqrt(D)
        return Q, H, g

    def modes(self, thetas, u, mu, D, ls, at=None):
        """Each pixel's mode of its own parameters at every theta (Levenberg-Marquardt from
        ``u``, a pixel's iterations ending where its step changes its Q by less than MODE_TOL, or
        where the step's quadratic model says it would, before the step is evaluated): (u, Q (K,
        rows), H (K, rows, own, own), g (K, rows, own)) at the last point.  ``at``: (Q, H, g) at
        ``u`` where known (:meth:`reprior`), else evaluated there first."""
        K, R, o = u.shape
        rows, which = self.rows(ls)
        th, mu = thetas[:, which].reshape(K * R, -1), mu[:, which].reshape(K * R, o)
        D = np.tile(D[which], (K, 1))
        pix = np.tile(rows, K)
        u = u.reshape(K * R, o).copy()
        if at is None:
            Q, H, g = self._at(th, u, mu, D, pix)
        else:
            Q, H, g = (a.reshape((K * R,) + a.shape[2:]).copy() for a in at)
        lam = np.full(K * R, 1e-3)
        eye = np.eye(o)
        on = np.arange(K * R)
        for _ in range(MODE_ITERATIONS):
            Hd = H[on] + (lam[on, None] * np.einsum("pii->pi", H[on]))[..., None] * eye
            step = np.linalg.solve(Hd, g[on][..., None])[..., 0]
            # the fall of Q that the step's quadratic model predicts (Q = r^T r + prior, g and H
            # half its gradient and Gauss-Newton Hessian): a pixel whose step would change Q by
            # less than MODE_TOL is at its mode and not evaluated again
            near = 2.0 * np.einsum("pi,pi->p", g[on], step) - np.einsum("pi,pij,pj->p", step, H[on], step) < MODE_TOL
            on, step = on[~near], step[~near]
            if on.size == 0:
                break
            un = np.clip(u[on] - step, -U_MAX, U_MAX)
            Qn, Hn, gn = self._at(th[on], un, mu[on], D[on], pix[on])
            better = Qn < Q[on]
            done = np.abs(Q[on] - Qn) < MODE_TOL
            b = on[better]
            u[b], Q[b], H[b], g[b] = un[better], Qn[better], Hn[better], gn[better]
            lam[on] = np.where(better, lam[on] / 5.0, lam[on] * 10.0)
            on = on[~done]
            if on.size == 0:
                break
        return u.reshape(K, R, o), Q.reshape(K, R), H.reshape(K, R, o, o), g.reshape(K, R, o)

    def reprior(self, at, u, mu, D, mu2, D2, ls):
        """(Q, H, g) of :meth:`modes` at ``u`` under the populations (``mu``, ``D``) moved to
        (``mu2``, ``D2``): only the prior's terms change, the model is not evaluated again."""
        Q, H, g = at
        which = self.rows(ls)[1]
        s, s2 = np.sqrt(D[which]), np.sqrt(D2[which])
        a, b = (u - mu[:, which]) / s, (u - mu2[:, which]) / s2
        Q = Q - np.einsum("kpi,kpi->kp", a, a) + np.einsum("kpi,kpi->kp", b, b)
        H = H + (1.0 / D2[which] - 1.0 / D[which])[..., None] * np.eye(u.shape[-1])
        return Q, H, g - a / s + b / s2

    def _spans(self, ls):
        """Each label of ``ls``: the slice of its rows among theirs (:meth:`rows`)."""
        return spans(self.start, ls)

    def mean_step(self, u, mu, D, Hi, ls):
        """The Newton step of each population's mean with its pixels' modes following it (the
        Schur complement of their joint problem; ``Hi`` the inverses of the modes' H): the means
        there (the modes follow in the next :meth:`modes`, whose first step is the one this step
        predicts for them)."""
        mu = mu.copy()
        for j, sl in enumerate(self._spans(ls)):
            Di, Hj, uj = 1.0 / D[j], np.ascontiguousarray(Hi[:, sl]), np.ascontiguousarray(u[:, sl])
            M = uj.shape[1] * np.diag(Di)[None] - np.einsum("i,kpij,j->kij", Di, Hj, Di)
            mu[:, j] = mu[:, j] + np.linalg.solve(M, (Di * (uj - mu[:, j, None, :]).sum(axis=1))[..., None])[..., 0]
        return mu

    def population(self, thetas, u, mu, D, rounds, variance, ls):
        """The populations' means (and their ``variance`` with a Laplace EM update, one theta
        only, else held) fitted at ``thetas`` by ``rounds`` of (modes, :meth:`mean_step`):
        (u, mu, D, Q, H), Q, H the modes' at the end."""
        at = None  # the modes' (Q, H, g) where known: moved with the population (reprior), not evaluated
        for _ in range(rounds):
            u, *at = self.modes(thetas, u, mu, D, ls, at)
            if variance:
                D2 = np.stack([np.maximum(u[0, sl].var(axis=0) + np.einsum("pii->pi", np.linalg.inv(at[1][0, sl])).mean(
                    axis=0), 1e-4) for sl in self._spans(ls)])
                at, D = self.reprior(at, u, mu, D, mu, D2, ls), D2
                u, *at = self.modes(thetas, u, mu, D, ls, at)
            mu2 = self.mean_step(u, mu, D, np.linalg.inv(at[1]), ls)
            at, mu = self.reprior(at, u, mu, D, mu2, D, ls), mu2
        u, Q, H, _ = self.modes(thetas, u, mu, D, ls, at)
        return u, mu, D, Q, H

    def fit_population(self, theta, ls, rounds=EM_ROUNDS):
        """The populations' means and variances of the labels ``ls`` at ``theta`` (len(ls), S)
        (from the stored), stored."""
        rows, _ = self.rows(ls)
        u, mu, D, _, _ = self.population(theta[None], self.u[rows][None], self.mu[ls][None], self.D[ls], rounds, True,
                                         ls)
        self.u[rows], self.mu[ls], self.D[ls], self.theta[ls] = u[0], mu[0], D, theta

    def terms(self, thetas, ls, rounds=0):
        """Each pixel's term Q_p + log det H_p + log det D of G at every theta of ``thetas``
        (K, len(ls), S): (K, rows), the populations' means refitted by ``rounds`` of
        :meth:`population` from the stored ones (which are kept), moved to each theta to first
        order (:meth:`predicted`) where the stored ones have their values."""
        K = thetas.shape[0]
        rows, which = self.rows(ls)
        u, mu = np.repeat(self.u[rows][None], K, axis=0), np.repeat(self.mu[ls][None], K, axis=0)
        if np.all(np.isfinite(self.theta[ls])):
            u, mu = self.predicted(thetas, u, mu, ls)
        _, _, D, Q, H = self.population(thetas, u, mu, self.D[ls], rounds, False, ls)
        return Q + np.linalg.slogdet(H)[1] + np.log(D).sum(axis=1)[which]

    def predicted(self, thetas, u, mu, ls):
        """The starts of the modes ``u`` and the populations' means ``mu`` (stored ones, one copy per
        theta) at ``thetas`` (K, len(ls), S): where they move to from the stored values, to first
        order: the modes with the means held (:meth:`response`), then the means' Newton step with
        the modes following it (:meth:`mean_step`).  The population's rounds of :meth:`terms` go on
        from there (fewer of the model's evaluations: the modes' first iterations start near their
        ends)."""
        K, which = thetas.shape[0], self.rows(ls)[1]
        dU, H = self.response(ls)
        u = np.clip(u + np.einsum("pis,kps->kpi", dU, (thetas - self.theta[ls][None])[:, which]), -U_MAX, U_MAX)
        Hi = np.linalg.inv(H)  # the same for every theta
        mu2 = self.mean_step(u, mu, self.D[ls], np.broadcast_to(Hi, (K,) + Hi.shape), ls)
        follow = np.einsum("pij,kpj->kpi", Hi, ((mu2 - mu) / self.D[ls][None])[:, which])
        return np.clip(u + follow, -U_MAX, U_MAX), mu2

    def response(self, ls):
        """The stored modes' first-order move with the shared values of their labels ``ls``, du/dtheta
        (rows, own, S; natural units) at the stored values, modes and populations: -H^-1 J_u^T
        J_theta (forward differences; the populations held), and the modes' H there."""
        rows, which = self.rows(ls)
        _, Ju, Jt = self._jacobian(self.theta[ls][which], self.u[rows], rows, shared=True)
        H = np.einsum("pim,pjm->pij", Ju, Ju) + (1.0 / self.D[ls][which])[:, :, None] * np.eye(Ju.shape[1])
        return -np.linalg.solve(H, np.einsum("pim,psm->pis", Ju, Jt)), H

    def profile_gradient(self, theta, j):
        """The gradient of label j's subsample's profile F = sum_p min_beta chi2_p / s2 at its
        values ``theta`` (S,) (natural units), where every pixel's own parameters are the
        profile's (its minimum at theta: the envelope theorem, bounds included): every pixel's
        2 J_p^T r_p (pixels, S), J_p the central differences of its residuals along the shared
        parameters."""
        S, sl = len(self.si), self.pixels(j)
        p = sl.stop - sl.start
        X = np.empty((p, len(self.names)))
        X[:, self.si], X[:, self.bi] = theta, self.beta[sl]
        lo, hi = self.lo[self.si], self.hi[self.si]
        h = np.cbrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(theta))
        up, down = np.minimum(theta + h, hi), np.maximum(theta - h, lo)
        pts = np.repeat(X[:, None, :], 2 * S + 1, axis=1)
        for i, c in enumerate(self.si):
            pts[:, 1 + i, c], pts[:, 1 + S + i, c] = up[i], down[i]
        res = self.res
        mine = PixelResiduals(res.setup, res.blk, self.names, np.arange(sl.start, sl.stop), res.intensity, res.w,
                              res.few_nk)
        R = mine.rows(pts.reshape(-1, X.shape[1])).reshape(p, 2 * S + 1, -1) / np.sqrt(self.s2[sl.start])
        J = (R[:, 1:1 + S] - R[:, 1 + S:]) / (up - down)[None, :, None]
        return 2.0 * np.einsum("psm,pm->ps", J, R[:, 0])


def integrated_correction(st, theta, sums, ok, pixels=None):
    """The values of every label ``ok`` that minimise its integrated chi2 G (see the module's
    docstring), from the label stage's values ``theta`` (L, S) and sums, on at most ``pixels``
    (default PIXELS) of each label's pixels (evenly spaced; one pass over the stack gathers them).

    On a subsample (a label of P > p pixels) G's minimum carries the subsample's sampling noise:
    the subsample's profile F_sub has its minimum about sqrt(P / p) of the label's standard errors
    off the label's values t0, where the label's F has its own.  There G_sub is tilted by F_sub's
    gradient at t0, G_sub(t) - grad F_sub(t0) . (t - t0) (:meth:`Integrated.profile_gradient`):
    the label's F is stationary at t0, so the tilt takes out
    the part of G_sub's gradient that the subsample's noise puts in both (their pixels' gradients
    nearly agree) and leaves the bias in.  (The difference of the two minima, argmin G_sub -
    argmin F_sub, does not: G is the more curved along a correlated pair of shared parameters, so
    the noise moves its minimum less than F's.)  What noise remains, that of the subsample's sum
    of the pixels' gradient differences (:func:`spread`), is added to the label's covariance.  The
    stencil's step and the steps' limit are then the subsample's standard errors, sqrt(P / p)
    times the label's.  A label of at most ``pixels`` pixels is its own subsample, stationary in
    F at t0: no tilt, and the profile's covariance.

    Returns (theta_c (L, S), cov), unchanged where the label has too few pixels, no finite
    standard error, or G neither a positive curvature nor a lower point along the profile's
    valley (:func:`_corrected`): cov (L, S, S) the profile's covariance (the label
    stage's intervals; plus the correction's noise on a subsample; times pixels / PRECISION_PIXELS
    on a label of more pixels, corrected or not) in coordinates scaled to the bounds, as
    ``st.covariance`` gives it.  (G's own curvature, 2 H^-1, and the sandwich of the pixels'
    gradients both covered less than the profile's: docs/joint_images.md.)"""
    setup, names = st.job.setup, st.job.names
    s2 = st.scale(sums)
    cov = st.covariance(sums).cov.copy()
    picks = subsample(st, PIXELS if pixels is None else pixels)
    subs = st.gather(picks)
    out = theta.copy()
    labels, raws, betas, totals, ses, metrics = [], [], [], [], [], []
    for L in np.flatnonzero(ok):
        beta = st.beta[picks[L]]
        keep = np.all(np.isfinite(beta), axis=1)
        total = np.count_nonzero(st.fitted & (st.lab == L))
        se = np.sqrt(np.clip(np.diag(cov[L]), 0, None) * (total / picks[L].size))  # scaled coordinates
        if keep.sum() < 3 or not np.all(np.isfinite(se) & (se > 0)):
            continue
        labels.append(L)
        raws.append(take(subs[L], keep))
        betas.append(beta[keep])
        totals.append(total)
        ses.append(se)
        metrics.append(cov[L] * (total / picks[L].size))
    sizes = [b.shape[0] for b in betas]

    def correct(share):  # the labels of a share (positions in ``labels``), in groups of at most GROUP_PIXELS
        done, start = [], 0
        while start < len(share):  # (one label at least)
            end = start + 1
            while end < len(share) and sum(sizes[i] for i in share[start:end + 1]) <= GROUP_PIXELS:
                end += 1
            grp = share[start:end]
            Ls = [labels[i] for i in grp]
            itg = Integrated(setup, names, st.shared, [raws[i] for i in grp], [betas[i] for i in grp], s2[Ls],
                             st.lo, st.hi)
            done += _corrected(st, itg, theta[Ls], np.array([ses[i] for i in grp]), np.array([metrics[i] for i in grp]),
                               [totals[i] for i in grp], [picks[L].size < totals[i] for L, i in zip(Ls, grp)])
            start = end
        return done

    # each label's numbers are those it has alone: its share and group do not change them
    for L, total, (t, noise) in zip(labels, totals, processes.spread(correct, range(len(labels)), sizes)):
        if t is not None:
            out[L] = t
            if noise is not None:
                cov[L] = cov[L] + noise
        # the floor holds uncorrected values too: the profile's bias is G's and more
        cov[L] = cov[L] * max(1.0, total / PRECISION_PIXELS)
    return out, cov


def _corrected(st, itg, theta, se, metric, totals, thin):
    """The corrected values of the labels of ``itg`` from their values ``theta`` (n, S) and
    standard errors ``se`` (n, S, scaled coordinates; ``metric``: the subsample's profile covariance
    (n, S, S), scaled; ``totals``: their pixels, ``thin``: whether ``itg`` holds a subsample of them):
    per label, in order, (its values or None where G has no positive curvature and no lower point
    along the profile's valley, the correction's noise to add to its covariance or None).

    Each round fits G's quadratic over the stencil (:func:`stencil`) and takes its Newton step
    (:func:`newton`) where that is positive definite.  Where it is not (G is not convex there:
    its minimum lies farther along the profile's valley of correlated n and k than a stencil
    reaches), the label steps downhill instead (:func:`downhill`), along the profile's metric, for
    up to DOWNHILL_ROUNDS rounds in all."""
    s, span = st.si, st.span[st.si]
    n = theta.shape[0]
    itg.fit_population(theta, np.arange(n))
    t = theta / span
    lo, hi = st.lo[s] / span, st.hi[s] / span
    cf = [itg.profile_gradient(theta[j], j) * span if thin[j] else np.zeros((1, len(s))) for j in range(n)]
    tilt, noise, H = [c.sum(axis=0) for c in cf], [0.0] * n, [None] * n  # tilt: the subsample's noise in F's gradient
    moved = np.zeros(n, bool)  # stepped downhill where G is not convex
    todo = np.arange(n)
    for r in range(DOWNHILL_ROUNDS):
        going, down = [], []
        fits = stencil(itg, t[todo], se[todo], lo, hi, span, todo)
        for j, (g, H[j], c, G0) in zip(todo, fits):
            if thin[j] and r == 0:
                noise[j] = spread(c - cf[j], H[j], totals[j])
            if positive_definite(H[j]):
                d = newton(g - tilt[j], H[j], se[j])
                t[j] = np.clip(t[j] + d, lo, hi)
                if not (np.all(np.abs(d) < 0.2 * se[j]) or r == (DOWNHILL_ROUNDS if moved[j] else NEWTON_ROUNDS) - 1):
                    going.append(j)
            else:
                down.append((j, g - tilt[j], G0))
        if down:
            js = [j for j, _, _ in down]
            steps = downhill(itg, t[js], se[js], metric[js], np.array([g for _, g, _ in down]),
                             np.array([G0 for _, _, G0 in down]), np.array([tilt[j] for j in js]), lo, hi, span, js)
            for j, d in zip(js, steps):
                if np.any(d != 0):
                    t[j] = np.clip(t[j] + d, lo, hi)
                    moved[j] = True
                    if r < DOWNHILL_ROUNDS - 1:
                        going.append(j)
        if not going:
            break
        todo = np.array(sorted(going))
        itg.fit_population(t[todo] * span, todo, POPULATION_ROUNDS)
    return [(t[j] * span if moved[j] or positive_inverse(H[j]) is not None else None, noise[j] if thin[j] else None)
            for j in range(n)]


def downhill(itg, t, se, metric, g, G0, tilt, lo, hi, span, ls):
    """The steps of the labels ``ls`` whose G is not convex at ``t`` (len(ls), S; scaled): along
    the profile's metric (-``metric`` g, the subsample's profile covariance times the gradient
    ``g`` of G less its ``tilt``: along the valley of correlated shared parameters, where the
    diagonal's step would cross it), at most MAX_STEP standard errors ``se`` per parameter, the
    best of LINE_STEPS fractions of it where G less the tilt is lower there than at ``t`` (G there:
    ``G0``), else no step (zeros)."""
    p = -np.einsum("lij,lj->li", metric, g)
    scale = np.max(np.abs(p) / se, axis=1)
    p = p * np.where(scale > 0, MAX_STEP / np.where(scale > 0, scale, 1.0), 0.0)[:, None]
    a = np.asarray(LINE_STEPS)
    pts = np.clip(t[None] + a[:, None, None] * p[None], lo, hi)  # (K, labels, S)
    vals = itg.terms(pts * span, np.asarray(ls), POPULATION_ROUNDS)
    out = np.zeros_like(t)
    for m, sl in enumerate(spans(itg.start, ls)):
        G = vals[:, sl].sum(axis=1) - (pts[:, m] - t[m]) @ tilt[m]
        best = int(np.argmin(G))
        if G[best] < G0[m]:
            out[m] = pts[best, m] - t[m]
    return out


def stencil(itg, t, se, lo, hi, span, ls):
    """G's quadratic model of each label of ``ls`` at its ``t`` (len(ls), S; scaled) fitted per
    pixel over the 3^S points t + (-1, 0, 1) STEP standard errors ``se`` in every shared parameter
    (inside the bounds ``lo``, ``hi``): per label (gradient, Hessian) of its sum and every
    pixel's gradient (pixels, S) at t."""
    S = t.shape[1]
    offs = np.array(list(product((-1.0, 0.0, 1.0), repeat=S)))
    pts = np.clip(t[None] + offs[:, None] * STEP * se[None], lo, hi)  # (3^S, labels, S)
    vals = itg.terms(pts * span, ls, POPULATION_ROUNDS)  # (3^S, rows)
    i, j = np.triu_indices(S)
    fits = []
    for m, sl in enumerate(spans(itg.start, ls)):
        d = pts[:, m] - t[m]
        X = np.column_stack([np.ones(len(d)), d, d[:, i] * d[:, j] * np.where(i == j, 0.5, 1.0)])
        coef = np.linalg.lstsq(X, np.ascontiguousarray(vals[:, sl]), rcond=None)[0]  # (1 + S + S (S + 1) / 2, p)
        c = coef[1:1 + S].T
        H = np.zeros((S, S))
        H[i, j] = H[j, i] = coef[1 + S:].sum(axis=1)
        fits.append((c.sum(axis=0), H, c, float(vals[len(offs) // 2, sl].sum())))
    return fits


def spread(a, H, total):
    """The covariance of the Newton step -H^-1 sum_p a_p of a subsample's pixels' gradients ``a``
    (pixels, S) as an estimate of the label's (``total`` pixels; drawn without replacement), H the
    subsample's Hessian; zero where H is not positive definite."""
    p = a.shape[0]
    Hi = positive_inverse(H)
    if p < 2 or Hi is None:
        return 0.0
    return Hi @ (np.cov(a.T).reshape(H.shape) * p * (1.0 - p / total)) @ Hi


def positive_definite(H):
    """Whether the symmetric H is finite and positive definite."""
    with np.errstate(all="ignore"):
        return bool(np.all(np.isfinite(H)) and np.all(np.linalg.eigvalsh(H) > 0))


def positive_inverse(H):
    """H^-1 where the symmetric H is positive definite and its inverse finite, else None."""
    if not positive_definite(H):
        return None
    with np.errstate(all="ignore"):
        Hi = np.linalg.inv(H)
    return Hi if np.all(np.isfinite(Hi)) else None


def newton(g, H, se):
    """The Newton step of G (in scaled coordinates), at most MAX_STEP standard errors ``se`` per
    parameter; along the gradient scaled by the diagonal where H is not positive definite (or
    not finite)."""
    with np.errstate(all="ignore"):
        if positive_definite(H):
            d = -np.linalg.solve(H, g)
        else:
            d = -g / np.maximum(np.abs(np.diag(H)), 1e-300)
    d = np.where(np.isfinite(d), d, 0.0)
    return np.clip(d, -MAX_STEP * se, MAX_STEP * se)
