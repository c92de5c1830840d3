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
from ..sample.stages import SCREEN_ITERATIONS, Candidate, StageResult, least_squares_stage, screen_stage

#: Local minima of each set's own grid slice that seed its own fit.
EXCHANGE_SEEDS = 4
#: The lowest nodes of a set's own grid slice searched first for its local minima (the whole
#: slice where they hold too few).
EXCHANGE_POOL = 256
#: Levenberg-Marquardt iterations of each own fit (three or so parameters, a few dozen points).
EXCHANGE_ITERATIONS = 30
#: Levenberg-Marquardt iterations of each own fit in the profile stage (it ranks the starting
#: points; the least squares and the exchange that follow finish the descent).  12, was 25: the
#: same reach on 140 bench problems (scripts/bench_joint.py and 120 with cached multi-starts:
#: 119/120 against 118/120), a joint fit about 18% faster.
PROFILE_ITERATIONS = 12
#: Exchange rounds at most (each: every set's own fit, then the joint least squares).
EXCHANGE_ROUNDS = 3
#: A set moves to another valley only where its chi^2 falls by more than this fraction (plus
#: ``EXCHANGE_ABS`` in units of chi^2): ties stay.
EXCHANGE_REL, EXCHANGE_ABS = 1e-9, 1e-9
#: The valley swap (:func:`valley_swap`) tries, per set, at most this many other own valleys...
VALLEY_SWAPS = 2
#: ... whose own chi^2 at the shared values reached is within this many units of chi^2 of the
#: set's best there ...
VALLEY_MARGIN = 4.0
#: ... and which lie this fraction of the bounds (in some own parameter) away from the set's
#: values and from each other.
VALLEY_APART = 0.2


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
    # the own axes, in free order (setup.own's order), copied once: a strided view was copied again by
    # each flattening and read slowly by each gather of the searches below
    sub = np.ascontiguousarray(grid.sse[tuple(index)])
    idxs = basins.grid_basins(sub, EXCHANGE_SEEDS, pool=EXCHANGE_POOL)
    idxs += basins.bound_seeds(sub, idxs)
    return [basins.grid_point(grid.axes, own, idx) for idx in idxs]


def exchange_round(setup, resid, grids, x):
    """One round: every set's own fit at the shared values of ``x`` (:func:`own_fits`, from its
    current own values too); returns (the exchanged joint vector, the sets that moved, every
    descent's end as :func:`own_descents` gives it, residual rows evaluated)."""
    x = np.array(x, dtype=np.float64)
    mine = {s: [x[own_columns(setup, s)]] for s in setup.names}
    X, sse, found, rows = _own_fits(setup, resid, grids, x[None, :len(setup.shared)], mine, EXCHANGE_ITERATIONS)
    moved = []
    for name, part, ix in zip(setup.names, resid.parts, resid.index):
        cols = own_columns(setup, name)
        if not cols.size:
            continue
        now = part.rows(x[ix][None])[0]
        if sse[name][0] < float(now @ now) * (1.0 - EXCHANGE_REL) - EXCHANGE_ABS:
            x[cols] = X[0, cols]
            moved.append(name)
    return x, moved, found, rows


def exchange_stage(setup, resid, grids, best, lo, hi, ls_nfev, unit=1.0):
    """Basin exchange rounds from the candidate ``best`` (at most :data:`EXCHANGE_ROUNDS`, until
    no set moves): each round's exchanged point descends by least squares on the stacked
    residuals (``ls_nfev`` evaluations per parameter) and is kept where it is better; then the
    valley swap (:func:`valley_swap`, ``unit`` the objective's unit of chi^2).  Returns a
    :class:`~pbrdf_cl.fitting.sample.stages.StageResult` whose value is (the best candidate, the
    sets moved in each round that was kept: a round whose descent did not improve is not listed)."""
    t0 = time.perf_counter()
    rows, history = 0, []
    for _ in range(EXCHANGE_ROUNDS):
        x, moved, found, n = exchange_round(setup, resid, grids, best.x)
        at, rows = best.x, rows + n
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
    if not np.array_equal(at, best.x):  # the last round moved: the descents at the point reached
        found, n = exchange_round(setup, resid, grids, best.x)[2:]
        rows += n
    best, moved, n = valley_swap(setup, resid, best, found, lo, hi, ls_nfev, unit)
    if moved:
        history.append(moved)
    return StageResult((best, tuple(history)), rows + n, time.perf_counter() - t0)


def valley_swap(setup, resid, best, found, lo, hi, ls_nfev, unit):
    """The joint descent from each set's other own valleys at the shared values of ``best``.

    The exchange moves a set only where its own chi^2 falls at the shared values held; a valley
    a little higher there can still lead, once the shared values move with it, to a lower joint
    optimum (a flat valley of n and k at each end of which the shared values differ).  For each
    set, its :data:`VALLEY_SWAPS` best other descents' ends (``found``, as
    :func:`own_descents` gives them) within :data:`VALLEY_MARGIN` units (``unit``) of its best
    there and :data:`VALLEY_APART` of the bounds away from its values and from each other take
    its place in ``best``; all descend together (the Levenberg-Marquardt screen), least squares
    finishes the best, kept where it is lower.  Returns (the best candidate, the sets whose
    valley was kept, rows evaluated)."""
    swaps, whose = [], []
    for name, (Xo, sse) in found.items():
        cols = own_columns(setup, name)
        span = hi[cols] - lo[cols]
        taken = [best.x[cols]]
        for i in np.argsort(sse, kind="stable"):
            if sse[i] > sse.min() + VALLEY_MARGIN * unit or len(taken) > VALLEY_SWAPS:
                break
            if all(np.max(np.abs(Xo[i] - t) / span) > VALLEY_APART for t in taken):
                taken.append(Xo[i])
                x = best.x.copy()
                x[cols] = Xo[i]
                swaps.append(Candidate(np.inf, x, best.seed))
                whose.append(name)
    if not swaps:
        return best, (), 0
    screen = screen_stage(resid.rows, lo, hi, swaps, SCREEN_ITERATIONS)
    k = int(np.argmin([c.sse for c in screen.value]))
    if not screen.value[k].sse < best.sse * (1.0 - EXCHANGE_REL) - EXCHANGE_ABS:
        return best, (), screen.nfev
    ls = least_squares_stage(resid.rows, lo, hi, [screen.value[k]], ls_nfev)
    cand = ls.value[0]
    return (cand, (whose[k],), screen.nfev + ls.nfev) if cand.sse < best.sse else (best, (), screen.nfev + ls.nfev)


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
    """Every set's own fit at each of the shared values ``points`` ((K, s) over ``setup.shared``),
    the best of :func:`own_descents` at each point.  Returns (X: (K, joint labels), the points
    with each set's best own values; set -> (K,) its best chi2 at each point; residual rows
    evaluated)."""
    X, sse_of, _, rows = _own_fits(setup, resid, grids, points, extra_own, iterations)
    return X, sse_of, rows


def _own_fits(setup, resid, grids, points, extra_own, iterations):
    """:func:`own_fits`, and what it chose from: (X, set -> chi2 per point, set -> (own vectors,
    chi2) per start, rows evaluated)."""
    shared = list(setup.shared)
    points = np.asarray(points, dtype=np.float64).reshape(len(points), len(shared))  # (1, 0): nothing shared
    X = np.zeros((len(points), len(setup.labels)))
    X[:, :len(shared)] = points
    found, lane_point, rows = own_descents(setup, resid, grids, points, extra_own, iterations)
    sse_of = {}
    for name, part, ix in zip(setup.names, resid.parts, resid.index):
        if name not in found:  # no own parameters
            r = part.rows(X[:, ix])
            sse_of[name] = np.einsum("pm,pm->p", r, r)
            continue
        Xo, sse = found[name]
        cols, lanes_of = own_columns(setup, name), lane_point[name]
        sse_of[name] = np.empty(len(points))
        for k in range(len(points)):
            lanes = np.flatnonzero(lanes_of == k)
            best = lanes[int(np.argmin(sse[lanes]))]
            X[k, cols] = Xo[best]
            sse_of[name][k] = sse[best]
    return X, sse_of, found, rows


def own_descents(setup, resid, grids, points, extra_own, iterations):
    """The batched descents of every set's own parameters at each of the shared values
    ``points`` ((K, s)): ``iterations`` of :func:`~pbrdf_cl.fitting.common.lm_batch` from the
    minima and bound slices of the set's grid slice at each point and from ``extra_own`` (set ->
    own vectors tried at every point), all points of a set in one call, and every set's in one
    call where their residuals stack (:class:`~pbrdf_cl.fitting.sets.stack.SetStack`: the same
    results, one model call per step where there were one per set).  Returns (set -> (own
    vectors, chi2) per start, set -> (starts,) each start's point, rows evaluated); sets without
    own parameters are left out."""
    shared = list(setup.shared)
    starts, lane_point = {}, {}
    for name in setup.names:
        if not own_columns(setup, name).size:
            continue
        starts[name], lane_point[name] = [], []
        for k, pt in enumerate(points):
            mine = own_grid_seeds(setup, grids[name], name, dict(zip(shared, pt))) + list(extra_own.get(name, []))
            starts[name] += mine
            lane_point[name] += [k] * len(mine)
    if not starts:
        return {}, {}, 0
    fits = _stacked_descents if _stackable(setup, resid, starts) else _descents
    found, rows = fits(setup, resid, points, starts, lane_point, iterations)
    return found, {s: np.array(v) for s, v in lane_point.items()}, rows


def _descents(setup, resid, points, starts, lane_point, iterations):
    """:func:`own_fits`'s descents set by set: (set -> (own vectors, chi2) per start, rows evaluated)."""
    shared, out, rows = list(setup.shared), {}, 0
    for name, part in zip(setup.names, resid.parts):
        if name not in starts:
            continue
        cols = own_columns(setup, name)
        one = len(points) == 1  # one point: its shared values held as scalars, not per problem
        own_rows = OwnResiduals(part, setup.own(name), shared, points[0] if one else None).rows
        Xo, sse, n = lm_batch(own_rows, np.array(starts[name]), setup.lo[cols], setup.hi[cols], iterations,
                              extra=None if one else points[np.array(lane_point[name])])
        out[name], rows = (Xo, sse), rows + n
    return out, rows


def _stackable(setup, resid, starts):
    """Whether :func:`own_fits`'s descents of every set can run as one: the sets' residuals stack
    and every set has own parameters with the same bounds."""
    if resid.stack is None or len(starts) != len(setup.names):
        return False
    bounds = {(tuple(setup.lo[own_columns(setup, s)]), tuple(setup.hi[own_columns(setup, s)])) for s in setup.names}
    return len(bounds) == 1


def _stacked_descents(setup, resid, points, starts, lane_point, iterations):
    """:func:`own_fits`'s descents of every set in one :func:`~pbrdf_cl.fitting.common.lm_batch`
    (each problem's shared values and set as its extra columns), returning what :func:`_descents` does."""
    stack, shared = resid.stack, list(setup.shared)
    own = setup.own(setup.names[0])
    # where each of the stack's free parameters is in a row (own values, then shared values), then the set
    where = [own.index(p) if p in own else len(own) + shared.index(p) for p in stack.free] + [-1]

    def rows(Y):
        return stack.tagged_rows(Y[:, where])
    names = list(starts)
    X0 = np.concatenate([np.array(starts[s]) for s in names])
    extra = np.concatenate([np.column_stack([points[np.array(lane_point[s])], np.full(len(starts[s]), i)])
                            for i, s in enumerate(names)])
    cols = own_columns(setup, names[0])
    Xo, sse, n = lm_batch(rows, X0, setup.lo[cols], setup.hi[cols], iterations, extra=extra)
    out, a = {}, 0
    for s in names:
        b = a + len(starts[s])
        out[s], a = (Xo[a:b], sse[a:b]), b
    return out, n


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
