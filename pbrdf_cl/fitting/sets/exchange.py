"""The basin exchange of :func:`pbrdf_cl.fit_joint`: given the shared parameters, each set's own
parameters are a separate small fit, and a set's DOP often has several valleys of nearly equal
depth (n and k are weakly determined).  The joint descent keeps each set in the valley its seed
started in; the exchange lets every set move to its best valley at the current shared values,
then descends jointly again, until no set moves.

Each set's own fit starts from the current values and from the local minima and bound slices
of its grid at the shared grid node nearest the current shared values (its own axes only, a
few thousand nodes), and runs the batched Levenberg-Marquardt descent of
:func:`~pbrdf_cl.fitting.common.lm_batch`.  A set whose best own valley lowers its chi^2 takes
it (the joint chi^2 falls by as much, the sets' own parameters being independent), and the
trust-region least squares on the stacked residuals follows from the exchanged point.
"""
from __future__ import annotations

import time

import numpy as np

from ..common import lm_batch
from ..sample import basins
from ..sample.stages import Candidate, StageResult, least_squares_stage

#: Local minima of each set's own grid slice that seed its own fit.
EXCHANGE_SEEDS = 6
#: The lowest nodes of a set's own grid slice searched first for its local minima (the whole
#: slice where they hold too few).
EXCHANGE_POOL = 256
#: Levenberg-Marquardt iterations of each own fit (three or so parameters, a few dozen points).
EXCHANGE_ITERATIONS = 30
#: Levenberg-Marquardt iterations of each own fit in the profile stage (it ranks the starting
#: points; the least squares and the exchange that follow finish the descent).
PROFILE_ITERATIONS = 25
#: Exchange rounds at most (each: every set's own fit, then the joint least squares).
EXCHANGE_ROUNDS = 3
#: A set moves to another valley only where its chi^2 falls by more than this fraction (plus
#: ``EXCHANGE_ABS`` in units of chi^2): ties stay.
EXCHANGE_REL, EXCHANGE_ABS = 1e-9, 1e-9


def own_grid_seeds(setup, grid, name, shared_values):
    """Set ``name``'s own parameter vectors (its ``own`` order) at the local minima and the bound
    slices of its grid ``grid`` (a :class:`~pbrdf_cl.fitting.sample.stages.GridStage` over its ``free``
    axes) at the shared grid node nearest ``shared_values`` (name -> value)."""
    free = setup.setups[name].free
    own = setup.own(name)
    index = [slice(None)] * len(free)
    for p, v in shared_values.items():
        if p in free:
            index[free.index(p)] = int(np.argmin(np.abs(grid.axes[p] - v)))
    sub = grid.sse[tuple(index)]  # the own axes, in free order: setup.own's order
    idxs = basins.grid_basins(sub, EXCHANGE_SEEDS, pool=EXCHANGE_POOL)
    idxs += basins.bound_seeds(sub, idxs)
    return [basins.grid_point(grid.axes, own, idx) for idx in idxs]


def exchange_round(setup, resid, grids, x):
    """One round: every set's own fit at the shared values of ``x`` (:func:`own_fits`, from its
    current own values too); returns (the exchanged joint vector, the sets that moved, residual
    rows evaluated)."""
    x = np.array(x, dtype=np.float64)
    mine = {s: [x[own_columns(setup, s)]] for s in setup.names}
    X, sse, rows = own_fits(setup, resid, grids, x[None, :len(setup.shared)], mine, EXCHANGE_ITERATIONS)
    moved = []
    for name, part, ix in zip(setup.names, resid.parts, resid.index):
        cols = own_columns(setup, name)
        if not cols.size:
            continue
        now = part.rows(x[ix][None])[0]
        if sse[name][0] < float(now @ now) * (1.0 - EXCHANGE_REL) - EXCHANGE_ABS:
            x[cols] = X[0, cols]
            moved.append(name)
    return x, moved, rows


def exchange_stage(setup, resid, grids, best, lo, hi, ls_nfev):
    """Basin exchange rounds from the candidate ``best`` (at most :data:`EXCHANGE_ROUNDS`, until
    no set moves): each round's exchanged point descends by least squares on the stacked
    residuals (``ls_nfev`` evaluations per parameter) and is kept where it is better.  Returns
    a :class:`~pbrdf_cl.fitting.sample.stages.StageResult` whose value is (the best candidate, the sets
    moved in each round that was kept: a round whose descent did not improve is not listed)."""
    t0 = time.perf_counter()
    rows, history = 0, []
    for _ in range(EXCHANGE_ROUNDS):
        x, moved, n = exchange_round(setup, resid, grids, best.x)
        rows += n
        if not moved:
            break
        r = resid.rows(x[None])[0]
        start = Candidate(float(r @ r), x, best.seed)
        ls = least_squares_stage(resid.rows, lo, hi, [start], ls_nfev)
        rows += ls.nfev
        cand = ls.value[0]
        if not cand.sse < best.sse:
            break
        best = cand
        history.append(tuple(moved))
    return StageResult((best, tuple(history)), rows, time.perf_counter() - t0)


class OwnResiduals:
    """One set's residuals over its own parameters ``own``, the shared ones ``shared`` held: at
    ``at`` (one point's shared values, scalars: every problem at the same point), or, without it,
    per problem as the last columns of the rows ``rows`` gets (for
    :func:`~pbrdf_cl.fitting.common.lm_batch` with ``extra=``)."""

    def __init__(self, part, own, shared, at=None):
        self.part = part
        self.base = dict(part.base) if at is None else {**part.base, **dict(zip(shared, at))}
        self.names = tuple(own) + (tuple(shared) if at is None else ())
        self.runs = tuple(shared) if at is None else ()

    def rows(self, X):
        p = dict(self.base)
        p.update({n: X[:, j:j + 1] for j, n in enumerate(self.names)})
        # shared values held per problem change only from one problem to the next: the factors
        # of shared (and held) parameters alone once per problem
        return self.part.weighted(p, runs=self.runs)


def own_columns(setup, name):
    """The joint vector's columns of set ``name``'s own (not shared) parameters, in its ``own`` order."""
    labels = setup.labels
    return np.array([labels.index(f"{p}[{name}]") for p in setup.own(name)], dtype=int)


def own_fits(setup, resid, grids, points, extra_own, iterations):
    """Every set's own fit at each of the shared values ``points`` ((K, s) over ``setup.shared``):
    the batched descent (``iterations`` of :func:`~pbrdf_cl.fitting.common.lm_batch`) from the
    minima and bound slices of the set's grid slice at each point and from ``extra_own`` (set ->
    own vectors tried at every point), all points of a set in one call.  Returns (X: (K, joint
    labels), the points with each set's best own values; set -> (K,) its best chi2 at each point;
    residual rows evaluated)."""
    shared = list(setup.shared)
    points = np.asarray(points, dtype=np.float64).reshape(len(points), len(shared))  # (1, 0): nothing shared
    X = np.zeros((len(points), len(setup.labels)))
    X[:, :len(shared)] = points
    sse_of, rows = {}, 0
    for name, part, ix in zip(setup.names, resid.parts, resid.index):
        cols = own_columns(setup, name)
        if not cols.size:
            r = part.rows(X[:, ix])
            sse_of[name] = np.einsum("pm,pm->p", r, r)
            continue
        starts, lane_point = [], []
        for k, pt in enumerate(points):
            mine = own_grid_seeds(setup, grids[name], name, dict(zip(shared, pt))) + list(extra_own.get(name, []))
            starts += mine
            lane_point += [k] * len(mine)
        lane_point = np.array(lane_point)
        one = len(points) == 1  # one point: its shared values held as scalars, not per problem
        own_rows = OwnResiduals(part, setup.own(name), shared, points[0] if one else None).rows
        Xo, sse, n = lm_batch(own_rows, np.array(starts), setup.lo[cols], setup.hi[cols], iterations,
                              extra=None if one else points[lane_point])
        rows += n
        sse_of[name] = np.empty(len(points))
        for k in range(len(points)):
            lanes = np.flatnonzero(lane_point == k)
            best = lanes[int(np.argmin(sse[lanes]))]
            X[k, cols] = Xo[best]
            sse_of[name][k] = sse[best]
    return X, sse_of, rows


def profile_stage(setup, resid, grids, points, extra_own=None):
    """The joint profile at the shared values ``points`` (a list of arrays over ``setup.shared``):
    at each, every set's own fit (:func:`own_fits`, from ``extra_own`` too: set -> own vectors
    tried everywhere).  Returns a StageResult whose value is a list, best first, of
    :class:`~pbrdf_cl.fitting.sample.stages.Candidate` joint vectors (the points with each set's best own
    values; ``sse`` the profile there)."""
    t0 = time.perf_counter()
    X, sse_of, rows = own_fits(setup, resid, grids, points, extra_own or {}, PROFILE_ITERATIONS)
    total = sum(sse_of.values())
    order = np.argsort(total, kind="stable")
    cands = [Candidate(float(total[k]), X[k], X[k]) for k in order]
    return StageResult(cands, rows, time.perf_counter() - t0)
