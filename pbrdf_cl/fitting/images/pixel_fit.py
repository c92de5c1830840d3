"""One block of an image fit through its stages (:func:`fit_block`): the pixels that can be fitted
go through (a) the grid (each region's minimum, ``batch_grid``), (b) the descents of the best
region minima (``batch_descents``: on a device float32 descents by successive halving, the best
polished in float64 and moved towards and off nearby bounds; on the numpy backend one float64
descent of every start), the corner stage (:func:`pbrdf_cl.fitting.images.corners.corner_polish`), with
intensities one more run adding ks, and (c) their statistics
(:func:`pbrdf_cl.fitting.images.statistics.statistics`); the others get their status."""
from __future__ import annotations

import numpy as np

from ...compute import pointwise
from ...device import engine as _engine
from ...device import ops
from ..setup import PARAMETERS
from .corners import corner_polish
from .dataset import empty_outputs
from .pixel_stages import device_lm
from .pixels import Block, Descent, grid_points
from .statistics import statistics

#: The float32 descents: (how many of the best starts, iterations), in turn, each continuing the
#: best of the previous; then the float64 polish of the best POLISH_STARTS.
SCREEN_SCHEDULE = ((32, 12), (8, 30))
#: The schedule, and how many of its best are polished, of pixels whose measurements share one
#: angle of incidence: their DOP trades n, k, kd and c along long valleys that end on bounds, and
#: basins a few units of chi^2 apart rank differently after a short float32 descent, so more
#: starts descend longer and more are polished.  Measured with ``scripts/bench_batch.py --only
#: match`` (theta_i 45, theta_r 5..80, 500 pixels of three seeds, Debian PoCL 3.1 and PoCL 3.0):
#: the share of pixels reaching pbrdf_cl.fit's objective went from 98.4% (SCREEN_SCHEDULE, one
#: polished) to 99.5-99.8%, for about twice the time per pixel.
ONE_INCIDENCE_SCHEDULE = ((32, 20), (16, 30))
ONE_INCIDENCE_POLISH_STARTS = 4
#: The numpy backend's one descent of every start runs the schedule's iterations (not fit's own
#: SCREEN_ITERATIONS of :mod:`pbrdf_cl.fitting.sample.stages`, 100: a different stage), then the polish's.
NUMPY_SCREEN_ITERATIONS = sum(iterations for _, iterations in SCREEN_SCHEDULE)
POLISH_STARTS = 1
POLISH_ITERATIONS = 20
#: Descents not settled after the polish continue alone, up to this many runs of this many iterations.
EXTRA_ROUNDS = 3
EXTRA_ITERATIONS = 60
#: Coordinates of the best polished point within this fraction of the bound range from a bound are
#: moved closer to it for one more polished descent (:func:`_towards_bounds`).
SNAP = 0.05
#: Iterations of the float64 run with intensities (ks free).
INTENSITY_ITERATIONS = 40
#: A pixel's own start (:func:`fit_block`'s ``starts``) replaces the grid's best where it ends
#: lower by more than this fraction of its chi2: less is the float64 polish's convergence.
OWN_START_GAIN = 1e-6


@_engine.falls_back
def fit_block(eng, setup, raw, order, rstart, names, starts=None):
    """The flat per-pixel results of one block of pixels (``raw``: :meth:`pbrdf_cl.io.source.Source.rows`)
    for :class:`~pbrdf_cl.fitting.images.pixels.BatchSetup` ``setup``, the grid's region order ``order``,
    ``rstart`` (:func:`pbrdf_cl.fitting.images.pixels.regions`) and the fitted parameters ``names``: the
    pixels that can be fitted go through the stages, the others get their status.  ``starts``
    (p, free parameters; optional): a start of each pixel's own, polished and kept where it ends
    lower than the grid's starts (:func:`_own_starts`; a row with a NaN: none)."""
    D = len(setup.free)
    blk = Block(raw, setup, eng.call("batch_lanes"))
    p, n_out = blk.p, len(names)
    status = np.full(p, 1, np.int8)
    status[(blk.count < D + 1) | (blk.distinct < D)] = -2
    status[~blk.mask] = -1
    out = empty_outputs(p, n_out)
    out["status"], out["n_valid"] = status, blk.count.astype(np.int64)
    # the pixels of one angle of incidence descend on their own schedule (ONE_INCIDENCE_SCHEDULE)
    own = np.zeros(p, bool) if starts is None else np.all(np.isfinite(starts), axis=1)
    for one, mine in ((False, False), (True, False), (False, True), (True, True)):
        todo = np.flatnonzero((status > 0) & (blk.one_incidence == one) & (own == mine))
        if not todo.size:
            continue
        schedule = (ONE_INCIDENCE_SCHEDULE, ONE_INCIDENCE_POLISH_STARTS) if one else (SCREEN_SCHEDULE, POLISH_STARTS)
        done = _fit_pixels(eng, setup, blk if todo.size == p else blk.subset(todo), order, rstart, names, schedule,
                           starts[todo] if mine else None)
        for k, v in done.items():
            out[k][todo] = v
    return out


def _fit_pixels(eng, setup, blk, order, rstart, names, schedule, starts=None):
    """The stages for every pixel of ``blk`` (each has enough valid measurements); ``schedule``:
    (the float32 descents' schedule, how many of their best are polished) on a device;
    ``starts`` (p, D): each pixel's own start (:func:`_own_starts`)."""
    p = blk.p
    # (a) grid: each region's minimum; the best n_starts per pixel seed the descents
    best, arg = eng.call("batch_grid", setup, blk, order, rstart)
    X0 = grid_points(setup, order, _distinct_starts(best, arg, order, setup.n_starts))  # (S, p, D)
    nfev = np.zeros(p, np.int64)
    nfev += int(len(order))
    # (b) the descents of every start; the screened starts' ends (X_all, sse_all) for the ambiguity test
    fit, X_all, sse_all = eng.call("batch_descents", setup, blk, X0, nfev, schedule)
    sse = np.where(np.isfinite(fit.sse) & (fit.sse < 1e299), fit.sse, np.inf)
    sse_all = np.where(np.isfinite(sse_all) & (sse_all < 1e299), sse_all, np.inf)
    if starts is not None:
        fit, sse, X_all, sse_all = _own_starts(eng, setup, blk, starts, fit, sse, X_all, sse_all, nfev)
    b = np.argmin(sse, axis=0)
    ar = np.arange(p)
    xb, sb, jb, setb = fit.x[b, ar], sse[b, ar], fit.jtj[b, ar], fit.settled[b, ar]
    corner_polish(eng, setup, blk, xb, sb, jb, nfev)
    names_out = list(setup.free)
    if setup.use_f00:
        # ks from the weighted least-squares scale of F00 at ks = 1, then every parameter with ks
        ks0 = _ks_start(eng, setup, blk, xb)
        X2 = np.concatenate([xb, ks0[:, None]], axis=1)[None]
        end = _polish(eng, setup, blk, X2, "float64" if eng.fp64 else "float32", nfev, names=names, intensity=True,
                      iterations=INTENSITY_ITERATIONS)
        xb, sb, jb, setb = end.x[0], end.sse[0], end.jtj[0], end.settled[0]
        names_out = names
    # (c) covariance, intervals, status
    return statistics(setup, blk, names_out, xb, sb, jb, setb, X_all, sse_all, nfev)


def _own_starts(eng, setup, blk, starts, fit, sse, X_all, sse_all, nfev):
    """Each pixel's own start (p, D) polished in float64 (:func:`_polish`) and added to the
    descents' ends where it ends lower than all of them by more than OWN_START_GAIN of their
    chi2 (not the polish's rounding; elsewhere as not finite, so that a
    pixel's result and ambiguity test are those of the grid's starts): (fit, sse, X_all,
    sse_all) with one more row."""
    own = _polish(eng, setup, blk, np.asarray(starts, float)[None], "float64" if eng.fp64 else "float32", nfev)
    s = np.where(np.isfinite(own.sse) & (own.sse < 1e299), own.sse, np.inf)
    wins = s[0] < sse.min(axis=0) * (1 - OWN_START_GAIN)
    s = np.where(wins[None], s, np.inf)
    own = own._replace(sse=np.where(wins[None], own.sse, np.inf))
    return fit.concat(own), np.concatenate([sse, s]), np.concatenate([X_all, own.x]), np.concatenate([sse_all, s])


@ops.implements("batch_descents", "opencl")
def _descents_opencl(eng, setup, blk, X0, nfev, schedule=(SCREEN_SCHEDULE, POLISH_STARTS)):
    """(b) on the device, from the starts X0 (S, p, D): float32 descents of every start, the best
    continued (successive halving, ``schedule[0]``, SCREEN_SCHEDULE by default: a short descent
    says which basin a start falls into), then the best ``schedule[1]`` (POLISH_STARTS) polished
    in float64 (:func:`_polish`) and moved towards and off nearby bounds
    (:func:`_off_the_bounds`).  Returns (the polished
    :class:`~pbrdf_cl.fitting.images.pixels.Descent`, X_all, sse_all: every screened start's end, the
    polished ones' too); the evaluations are added to ``nfev``."""
    D = len(setup.free)
    X, sse = X0, np.zeros((X0.shape[0], blk.p))
    screen, polish_starts = schedule
    for count, iterations in screen:
        keep = min(count, X.shape[0])
        top = np.argsort(np.where(np.isfinite(sse), sse, np.inf), axis=0, kind="stable")[:keep]
        X = np.take_along_axis(X, top[..., None], axis=0)
        X, sse, _, _ = device_lm(eng, setup, blk, X, setup.free, "float32", iterations, False)
        nfev += keep * (D + 1) * (iterations + 1)
    T = min(polish_starts, X.shape[0])
    top = np.argsort(np.where(np.isfinite(sse), sse, np.inf), axis=0, kind="stable")[:T]
    X1 = np.take_along_axis(X, top[..., None], axis=0)
    dtype = "float64" if eng.fp64 else "float32"
    polished = _off_the_bounds(eng, setup, blk, _polish(eng, setup, blk, X1, dtype, nfev), dtype, nfev)
    # the best is one of the polished; the screened starts that were not polished keep their
    # float32 result, which only the ambiguity test reads
    return polished, np.concatenate([X, polished.x]), np.concatenate([sse, polished.sse])


@ops.implements("batch_descents", "numpy")
def _descents_numpy(eng, setup, blk, X0, nfev, schedule=None):
    """:func:`_descents_opencl` on the numpy backend: one float64 descent of every start
    (NUMPY_SCREEN_ITERATIONS + POLISH_ITERATIONS iterations), every start's end its own (every
    start is polished: no ``schedule``)."""
    S, D = X0.shape[0], len(setup.free)
    fit = eng.call("batch_lm", setup, blk, X0, setup.free, "float64", NUMPY_SCREEN_ITERATIONS + POLISH_ITERATIONS,
                   False)
    nfev += S * (D + 1) * (NUMPY_SCREEN_ITERATIONS + POLISH_ITERATIONS + 2)
    return fit, fit.x, fit.sse


def _off_the_bounds(eng, setup, blk, polished, dtype, nfev):
    """Towards the bounds: from the best polished point, the coordinates near a bound moved 10,
    100 and 1000 times closer to it (alone and together), the best of those polished too (a
    descent into this model's corners (n = 1, k = 0, kd = 0 where the DOP is discontinuous,
    sigma = 1) crawls geometrically, each step's move onto the bound rejected): ``polished`` with
    one more start, the best point of each pixel or its polished candidate."""
    p, D = blk.p, len(setup.free)
    bt = np.argmin(np.where(np.isfinite(polished.sse), polished.sse, np.inf), axis=0)
    xb = polished.x[bt, np.arange(p)]
    cand = _towards_bounds(xb, setup.lo, setup.hi)
    moved = np.flatnonzero(np.any(cand != xb[None], axis=(0, 2))) if cand is not None else np.empty(0, int)
    if not moved.size:
        return polished
    sub = blk.subset(moved)
    ssec = device_lm(eng, setup, sub, cand[:, moved], setup.free, "float32", 0, False).sse
    nfev[moved] += cand.shape[0] * (D + 1)
    start = cand[np.argmin(ssec, axis=0), moved][None]
    towards = _polish(eng, setup, sub, start, dtype, nfev, moved)
    row = Descent(*(a[bt, np.arange(p)][None].copy() for a in polished))
    for r, v in zip(row, towards):
        r[0, moved] = v[0]
    return polished.concat(row)


def _towards_bounds(x, lo, hi):
    """Candidates (K, p, D) from the points ``x`` (p, D): the coordinates on a bound moved off it
    by 0.1% and 1% of the range, and those within SNAP of the range from a bound moved 10, 100
    and 1000 times closer to it, each alone and all together (None where no coordinate of any
    point is near a bound).  The same K candidates for every point (a candidate that moves
    nothing of a point is that point), so that a pixel's candidates, and the one it keeps, do
    not depend on the other pixels of its block."""
    span = hi - lo
    near_lo, near_hi = x - lo < SNAP * span, hi - x < SNAP * span
    near = near_lo | near_hi
    if not near.any():
        return None
    out = []
    # a coordinate on a bound can hide others: at kd = 0 the DOP depends on neither sigma nor c,
    # so a descent that reached kd = 0 cannot move them; off the bound by 0.1% and 1% it can
    on_lo, on_hi = x - lo <= 1e-9 * span, hi - x <= 1e-9 * span
    for f in (1e-3, 1e-2):
        out.append(np.where(on_lo, lo + f * span, np.where(on_hi, hi - f * span, x)))
    for f in (1e-1, 1e-2, 1e-3):
        closer = np.where(near_lo, lo + (x - lo) * f, np.where(near_hi, hi - (hi - x) * f, x))
        out.append(closer)
        for j in range(x.shape[1]):
            one = x.copy()
            one[:, j] = closer[:, j]
            out.append(one)
    return np.stack(out)


def _polish(eng, setup, blk, X, dtype, nfev, pixels=None, names=None, intensity=False, iterations=None):
    """The float64 descent from the starts X (T, p, D) of ``blk`` over ``names`` (default the free
    parameters; ``intensity``: with the F00 residuals): ``iterations`` (default POLISH_ITERATIONS),
    then the descents not settled continue alone (compacted) for up to EXTRA_ROUNDS runs of
    EXTRA_ITERATIONS; adds the evaluations to ``nfev`` (of the pixels ``pixels`` of the caller's
    block, default all).  Returns a :class:`~pbrdf_cl.fitting.images.pixels.Descent`."""
    D = X.shape[-1]
    names = setup.free if names is None else names
    iterations = POLISH_ITERATIONS if iterations is None else iterations
    pixels = np.arange(X.shape[1]) if pixels is None else pixels
    out = eng.call("batch_lm", setup, blk, X, names, dtype, iterations, intensity)
    nfev[pixels] += X.shape[0] * (D + 1) * (iterations + 1)
    for _ in range(EXTRA_ROUNDS):
        t_idx, p_idx = np.nonzero(~out.settled)
        if t_idx.size == 0:
            break
        more = eng.call("batch_lm", setup, blk.subset(p_idx), out.x[t_idx, p_idx][None], names, dtype, EXTRA_ITERATIONS,
                        intensity)
        for a, b in zip(out, more):
            a[t_idx, p_idx] = b[0]
        np.add.at(nfev, pixels[p_idx], (D + 1) * (EXTRA_ITERATIONS + 1))
    return out


def _distinct_starts(best, arg, order, n):
    """Per pixel, the grid indices (into ``order``) of the ``n`` best region minima that are distinct
    grid points, (n, p); a pixel with fewer distinct ones repeats its best."""
    rank = np.argsort(best, axis=0, kind="stable")
    g = np.take_along_axis(order[arg], rank, axis=0)  # grid points, best region first
    a = np.take_along_axis(arg, rank, axis=0)
    dup = np.zeros(g.shape, bool)
    for r in range(1, g.shape[0]):
        dup[r] = np.any(g[:r] == g[r][None], axis=0)
    key = np.where(dup, g.shape[0], np.arange(g.shape[0])[:, None])  # distinct ones first, in rank order
    pick = np.argsort(key, axis=0, kind="stable")[:n]
    chosen = np.take_along_axis(a, pick, axis=0)
    ok = ~np.take_along_axis(dup, pick, axis=0)
    return np.where(ok, chosen, chosen[:1])


def _ks_start(eng, setup, blk, xb):
    """Per pixel, the ks that best scales the model's F00 (ks = 1) to the intensities."""
    p = dict(setup.base)
    for j, n in enumerate(setup.free):
        p[n] = xb[:, j:j + 1]
    p["ks"] = 1.0
    ang = [a[None, :] if blk.shared else a for a in blk.angles]
    m1 = pointwise.brdf(*ang, shadowing=setup.shadowing, engine=eng,
                        **{n: p[n] for n in PARAMETERS})
    w = blk.fw
    num = (w * blk.fobs * m1).sum(axis=1)
    den = np.maximum((w * m1 * m1).sum(axis=1), 1e-300)
    return np.clip(num / den, *setup.ks_bounds)
