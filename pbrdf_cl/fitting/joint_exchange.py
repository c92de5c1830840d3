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

from . import basins
from .common import lm_batch
from .stages import Candidate, Residuals, StageResult, finite_rows, least_squares_stage

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
    slices of its grid ``grid`` (a :class:`~pbrdf_cl.fitting.stages.GridStage` over its ``free``
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


def own_residuals(part, own, shared_values):
    """Set residuals (a :class:`~pbrdf_cl.fitting.stages.Residuals` of the joint fit's ``parts``)
    over the set's own parameters ``own``, the shared ones held at ``shared_values``."""
    return Residuals(part.model, own, {**part.base, **shared_values}, part.dop, part.dop_std)


def exchange_round(setup, resid, grids, x, lo, hi):
    """One round: every set's own fit at the shared values of ``x``; returns (the exchanged
    joint vector, the sets that moved, residual rows evaluated)."""
    labels = setup.labels
    x = np.array(x, dtype=np.float64)
    shared_values = {p: float(x[labels.index(p)]) for p in setup.shared}
    moved, rows = [], 0
    for name, part in zip(setup.names, resid.parts):
        own = setup.own(name)
        if not own:
            continue
        cols = np.array([labels.index(f"{p}[{name}]") for p in own])
        res = own_residuals(part, own, shared_values)
        now = res.rows(x[cols][None])[0]
        now_sse = float(now @ now)
        starts = np.array([x[cols]] + own_grid_seeds(setup, grids[name], name, shared_values))
        X, sse, n = lm_batch(res.rows, starts, lo[cols], hi[cols], EXCHANGE_ITERATIONS)
        rows += n
        best = int(np.argmin(sse))
        if sse[best] < now_sse * (1.0 - EXCHANGE_REL) - EXCHANGE_ABS:
            x[cols] = X[best]
            moved.append(name)
    return x, moved, rows


def exchange_stage(setup, resid, grids, best, lo, hi, ls_nfev):
    """Basin exchange rounds from the candidate ``best`` (at most :data:`EXCHANGE_ROUNDS`, until
    no set moves): each round's exchanged point descends by least squares on the stacked
    residuals (``ls_nfev`` evaluations per parameter) and is kept where it is better.  Returns
    a :class:`~pbrdf_cl.fitting.stages.StageResult` whose value is (the best candidate, the sets
    moved in each round)."""
    t0 = time.perf_counter()
    rows, history = 0, []
    for _ in range(EXCHANGE_ROUNDS):
        x, moved, n = exchange_round(setup, resid, grids, best.x, lo, hi)
        rows += n
        history.append(tuple(moved))
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
    return StageResult((best, tuple(history)), rows, time.perf_counter() - t0)


class OwnResiduals:
    """One set's residuals over its own parameters ``own`` then the shared ones ``shared`` (the
    columns of the rows ``rows`` gets): for :func:`~pbrdf_cl.fitting.common.lm_batch` with the
    shared values held per problem (``extra=``), so that each problem has its own."""

    def __init__(self, part, own, shared):
        self.part, self.names = part, tuple(own) + tuple(shared)

    def rows(self, X):
        p = dict(self.part.base)
        p.update({n: X[:, j:j + 1] for j, n in enumerate(self.names)})
        # the shared values (sigma, c) change only from one problem to the next: their factors
        # once per problem
        return finite_rows((self.part.model.dop_rows(p, runs=True) - self.part.dop) / self.part.dop_std)


def profile_stage(setup, resid, grids, points, extra_own=None):
    """The joint profile at the shared values ``points`` (a list of arrays over ``setup.shared``):
    at each, every set's own fit (the batched descent from its grid slice's minima and bound
    slices there, and from ``extra_own``: set -> own vectors tried everywhere), all points of a
    set in one batched call.  Returns a StageResult whose value is a list, best first, of
    :class:`~pbrdf_cl.fitting.stages.Candidate` joint vectors (the points with each set's best own
    values; ``sse`` the profile there)."""
    t0 = time.perf_counter()
    labels = setup.labels
    shared = list(setup.shared)
    X = np.zeros((len(points), len(labels)))
    X[:, :len(shared)] = np.array(points).reshape(len(points), len(shared))
    total = np.zeros(len(points))
    rows = 0
    for name, part in zip(setup.names, resid.parts):
        own = setup.own(name)
        if not own:
            r = np.array([part.rows(x[resid.index[setup.names.index(name)]][None])[0] for x in X])
            total += np.einsum("pm,pm->p", r, r)
            continue
        cols = np.array([labels.index(f"{p}[{name}]") for p in own])
        starts, lane_point = [], []
        for k, pt in enumerate(points):
            values = dict(zip(shared, np.atleast_1d(pt)))
            mine = own_grid_seeds(setup, grids[name], name, values) + list((extra_own or {}).get(name, []))
            starts += mine
            lane_point += [k] * len(mine)
        lane_point = np.array(lane_point)
        own_rows = OwnResiduals(part, own, shared).rows
        Xo, sse, n = lm_batch(own_rows, np.array(starts), setup.lo[cols], setup.hi[cols], PROFILE_ITERATIONS,
                              extra=X[lane_point, :len(shared)])
        rows += n
        for k in range(len(points)):
            mine = np.flatnonzero(lane_point == k)
            best = mine[int(np.argmin(sse[mine]))]
            X[k, cols] = Xo[best]
            total[k] += sse[best]
    order = np.argsort(total, kind="stable")
    cands = [Candidate(float(total[k]), X[k], X[k]) for k in order]
    return StageResult(cands, rows, time.perf_counter() - t0)

