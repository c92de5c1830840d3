"""The stages of :func:`pbrdf_cl.fit`, each a module-level function of explicit inputs (residual
rows, bounds, candidates) returning a :class:`StageResult`: the device grid (:func:`grid_stage`),
its basins (:func:`basin_stage`), DIRECT-L, BOBYQA, the batched Levenberg-Marquardt screen, trust-
region least squares, the final BOBYQA and the intensity stage; the model they evaluate
(:class:`Model`, :class:`Residuals`) and the candidates they pass on (:class:`Candidate`).
"""
from __future__ import annotations

import copy
import threading
import time
from dataclasses import dataclass, replace

import numpy as np

from ...compute import dense, pointwise
from ...model import reference
from ...model.inputs import MEMBERS
from ..common import fd_jacobian, lm_batch, run_starts
from . import basins

#: Extra seeds from valleys of the grid's profiles that none of the grid's best local minima lies in.
PROFILE_SEEDS = 2
#: Evaluations per free parameter of each basin's DIRECT-L and BOBYQA runs.
DIRECT_EVALS = 20
BOBYQA_EVALS = 20
#: Iterations of the batched Levenberg-Marquardt descent of all candidates.
SCREEN_ITERATIONS = 100
#: Residual evaluations per free parameter the least-squares polish may use.
LS_MAX_NFEV = 100
#: Evaluations per free parameter of the last BOBYQA run, when least squares ran out of them.
FINAL_BOBYQA = 80
#: Evaluations (in all, not per parameter) of the intensity stage's BOBYQA run.
INTENSITY_MAXEVAL = 6000
#: The default memory budget of the grid stage (``memory_budget`` of :func:`pbrdf_cl.fit`,
#: ``--memory-budget`` of ``pbrdf-cl fit``): its tables of the measurements, in blocks, and its sums.
MEMORY_BUDGET = "512 MiB"


class Model:
    """DOP (and F00) of the reference model at fixed geometry, for the local stages.

    The factors depend on (n, k), (sigma, ks) and (kd, c) separately; each is recomputed only
    when its parameters change (finite-difference Jacobians and DIRECT move one at a time)."""

    def __init__(self, meas, shadowing):
        self.g = reference.geometry(meas.theta_i, meas.theta_r, meas.phi)
        self.variant = reference.SHADOWING[shadowing]
        self._cache = {}

    def with_geometry(self, g):
        """This model (its shadowing variant) at the geometry ``g`` (the fields of
        :func:`~pbrdf_cl.model.reference.geometry`, of any shapes that broadcast), with its own cache."""
        other = copy.copy(self)
        other.g, other._cache = g, {}
        return other

    def _factor(self, name, key, compute):
        hit = self._cache.get(name)
        if hit is None or hit[0] != key:
            hit = (key, compute())
            self._cache[name] = hit
        return hit[1]

    def _fresnel(self, p):
        return reference.fresnel(p["n"], p["k"], self.g.cb, self.g.sb)

    def _log_scale(self, p):
        g = self.g
        return reference.log_specular_scale(g, p["sigma"], p["ks"],
                                            reference.shadowing_factor(g, p["sigma"], self.variant))

    def _diffuse(self, p):
        return reference.diffuse(self.g, p["kd"], p["c"])

    def parts(self, p):
        return (self._factor("fresnel", (p["n"], p["k"]), lambda: self._fresnel(p)),
                self._factor("scale", (p["sigma"], p["ks"]), lambda: self._log_scale(p)),
                self._factor("diffuse", (p["kd"], p["c"]), lambda: self._diffuse(p)))

    def dop(self, p):
        return reference.dop(*self.parts(p))

    def dop_rows(self, p, runs=()):
        """DOP for many parameter vectors at once: ``p`` maps names to (B, 1) arrays (or
        scalars); returns (B, M).  The same factors, without the cache.  ``runs``: the parameters
        whose rows come in long runs of one value (held per problem of a batch); a factor whose
        parameters are all among them (or scalars) is computed once per run (:func:`per_run`), and
        of a batch of at least :data:`DISTINCT_VALUES` values (B M), once per distinct row."""
        return reference.dop(*self.factors(p, runs))

    def factors(self, p, runs=()):
        """The Fresnel terms, the log specular scale and the diffuse term of parameter rows ``p``,
        as :meth:`dop_rows` computes them.  At a geometry of more than one axis: several sets side
        by side against at least :data:`RUN_ROWS` rows of (B, sets, 1), each factor once per run
        of rows with the same values of its parameters (:func:`same_runs`: the rows of
        finite-difference Jacobians; a joint fit 7% faster, the same numbers bit for bit), else
        (fewer rows, or one geometry per row: :meth:`with_geometry`) every row as it comes."""
        if self.g.cb.ndim > 1:
            B = max((np.shape(v)[0] for v in p.values() if np.ndim(v) > self.g.cb.ndim), default=0)
            if B >= RUN_ROWS:  # several sets side by side, against rows of (B, sets, 1)
                return tuple(same_runs(getattr(self, part), p, MEMBERS[family]) for part, family in FACTORS)
            return self._fresnel(p), self._log_scale(p), self._diffuse(p)
        rows = max((np.shape(v)[0] for v in p.values() if np.ndim(v)), default=1)
        many = rows * self.g.cb.size >= DISTINCT_VALUES

        def factor(compute, names):
            if many or (all(n in runs or np.ndim(p[n]) == 0 for n in names) and any(n in runs for n in names)):
                return per_run(compute, p, names)
            return compute(p)
        return tuple(factor(getattr(self, part), MEMBERS[family]) for part, family in FACTORS)

    def f00(self, p):
        return reference.brdf(*self.parts(p))

    def f00_rows(self, p):
        """F00 for many parameter vectors at once, like :meth:`dop_rows`."""
        return reference.brdf(*self.factors(p))


#: The model's factors, :class:`Model`'s methods, in :func:`~pbrdf_cl.model.reference.dop`'s order,
#: each with the family of the parameters it depends on (:data:`~pbrdf_cl.model.inputs.MEMBERS`).
FACTORS = (("_fresnel", "index"), ("_log_scale", "specular"), ("_diffuse", "diffuse"))
#: Batches of parameter rows times measurements from which :meth:`Model.dop_rows` computes each
#: factor once per distinct row (the finite-difference steps move one parameter at a time).
DISTINCT_VALUES = 1 << 16
#: Residuals (parameter rows times measurements) :meth:`Residuals.rows` computes at once: of a big
#: data set a few rows at a time, so that the model's temporaries (a dozen arrays) take ~16 MiB each.
ROWS_VALUES = 1 << 21


def in_row_blocks(rows_of, n, width):
    """Residual rows 0..n of ``width`` values each, ``rows_of(a, b)`` giving rows a..b: at once,
    or, for a big data set, :data:`ROWS_VALUES` values at a time into one array (the model's
    temporaries, a dozen arrays, then take ~16 MiB each)."""
    per = max(1, ROWS_VALUES // max(1, width))
    if n <= per:
        return rows_of(0, n)
    out = None
    for a in range(0, n, per):
        r = rows_of(a, min(n, a + per))
        if out is None:
            out = np.empty((n, r.shape[1]))
        out[a:a + len(r)] = r
    return out


def per_run(compute, p, names):
    """``compute(p)`` for parameter rows ``p`` (name -> (B, 1) array or scalar) that depends only
    on the parameters ``names``, computed once per distinct row of their values (the same bits:
    runs of consecutive rows, or rows apart) and spread back: ``compute(p)``'s result bit for bit.
    A result with fields (the Fresnel terms) is spread field by field."""
    cols = [np.asarray(p[n], dtype=np.float64) for n in names]
    rows = max((c.shape[0] for c in cols if c.ndim), default=0)
    if rows < 2:
        return compute(p)
    key = np.concatenate([np.broadcast_to(c.reshape(-1, 1) if c.ndim else c, (rows, 1)) for c in cols], axis=1)
    bits = np.ascontiguousarray(key).view(np.int64)
    _, first, inverse = np.unique(bits, axis=0, return_index=True, return_inverse=True)
    if first.size == rows:
        return compute(p)
    inverse = inverse.reshape(-1)
    return spread_rows(compute({**p, **{n: key[first, j:j + 1] for j, n in enumerate(names)}}), inverse)


#: Rows of several sets side by side from which :meth:`Model.factors` computes each factor once per
#: run of rows with the same values of its parameters (:func:`same_runs`).
RUN_ROWS = 24


def same_runs(compute, p, names):
    """``compute(p)`` for parameter rows ``p`` (name -> arrays whose first axis is the row, or
    scalars) that depends only on the parameters ``names``, computed once per run of consecutive
    rows with the same values of them and spread back: ``compute(p)``'s result bit for bit (every
    value is computed from the same numbers by the same element-wise operations).  The rows of
    finite-difference Jacobians (a point, then the point moved along each parameter in turn) hold
    most factors' parameters, so those are computed for a few of them.  A result with fields (the
    Fresnel terms) is spread field by field."""
    rows = max((np.shape(p[n])[0] for n in names if np.ndim(p[n])), default=1)
    varying = [n for n in names if np.ndim(p[n]) and np.shape(p[n])[0] == rows]  # the others broadcast
    if rows < 2 or not varying:
        return compute(p)
    start = run_starts(*(np.asarray(p[n]) for n in varying))
    first = np.flatnonzero(start)
    if first.size == rows:
        return compute(p)
    inverse = np.cumsum(start) - 1
    return spread_rows(compute({**p, **{n: p[n][first] for n in varying}}), inverse)


def spread_rows(out, inverse):
    """The rows ``inverse`` of a factor computed for distinct rows (an array, or the Fresnel terms'
    fields each)."""
    if isinstance(out, np.ndarray):
        return out[inverse]
    spread = copy.copy(out)
    for field, value in vars(out).items():
        setattr(spread, field, value[inverse])
    return spread


class _Lockstep:
    """Run several optimisers (nlopt, scipy) in threads, in lockstep: every round, each running
    optimiser asks for residual vectors at one or more points and waits; when all have asked,
    the round's points are evaluated by one batched numpy call (for a few dozen measurements
    the reference model's cost is per call, not per point, so six optimisers cost little more
    than one).  Each optimiser sees exactly the numbers it would see alone: results are
    deterministic and independent of the batching."""

    def __init__(self, resid_rows):
        self.resid_rows = resid_rows  # (B, d) -> (B, M)
        self.lock = threading.Lock()
        self.ready = threading.Event()  # set when every running optimiser has asked
        self.pending, self.results, self.events = {}, {}, {}
        self.active = 0
        self.rows = 0

    def _ask(self, tid, X):
        with self.lock:
            self.pending[tid] = X
            if len(self.pending) == self.active:
                self.ready.set()
        ev = self.events[tid]
        ev.wait()
        ev.clear()
        return self.results.pop(tid)

    def _done(self):
        with self.lock:
            self.active -= 1
            if self.active == 0 or len(self.pending) == self.active:
                self.ready.set()

    def run(self, jobs):
        """``jobs``: callables taking ``rows(X) -> residuals`` and returning a result; returns the
        results in order.  An exception in a job is raised here after the others finish."""
        if len(jobs) == 1:  # nothing to batch with
            def rows(X):
                X = np.atleast_2d(X)
                self.rows += len(X)
                return self.resid_rows(X)
            return [jobs[0](rows)]
        results, errors = [None] * len(jobs), []

        def worker(i, job):
            try:
                results[i] = job(lambda X: self._ask(i, np.atleast_2d(X)))
            except BaseException as exc:  # re-raised in the calling thread
                errors.append(exc)
            finally:
                self._done()
        self.active = len(jobs)
        self.events = {i: threading.Event() for i in range(len(jobs))}
        threads = [threading.Thread(target=worker, args=(i, job), daemon=True) for i, job in enumerate(jobs)]
        for t in threads:
            t.start()
        while True:
            self.ready.wait()
            with self.lock:
                self.ready.clear()
                if self.active == 0:
                    break
                if len(self.pending) < self.active:
                    continue
                ids = sorted(self.pending)
                blocks = [self.pending.pop(i) for i in ids]
            out = self.resid_rows(np.concatenate(blocks))
            self.rows += len(out)
            start = 0
            for i, b in zip(ids, blocks):
                self.results[i] = out[start:start + len(b)]
                start += len(b)
                self.events[i].set()
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        return results


@dataclass(frozen=True, eq=False)
class Candidate:
    """A point of the local stages: its objective ``sse`` (sum of squared weighted residuals),
    its free parameters ``x`` (in the order of the stage's bounds) and the ``seed`` (grid point)
    it descends from.  ``converged`` is what the last local method that ran on it said: True,
    False (it ran out of evaluations) or None (no method with a convergence test).  Frozen;
    equality is identity (``x`` and ``seed`` are arrays)."""
    sse: float
    x: np.ndarray
    seed: np.ndarray
    converged: bool | None = None

    def better(self, sse, x):
        """This candidate moved to ``x`` when ``sse`` is lower than its own, else itself."""
        return Candidate(float(sse), x, self.seed) if sse < self.sse else self


@dataclass(frozen=True)
class StageResult:
    """What one stage of :func:`fit` returns: its output ``value``, the residual rows it
    evaluated (``nfev``) and its wall time (``seconds``)."""
    value: object
    nfev: int
    seconds: float


@dataclass(frozen=True)
class GridStage:
    """Output of :func:`grid_stage`: the objective ``sse`` on the grid (axes in the order of the
    free parameters), the grid ``axes`` (name -> nodes) and each parameter's ``profiles``."""
    sse: np.ndarray
    axes: dict
    profiles: dict


@dataclass(frozen=True)
class Basins:
    """Output of :func:`basin_stage`: grid ``indices`` of the seeds, the ``seeds`` (parameter
    vectors) and ``steps`` (the larger grid step around each seed, per parameter)."""
    indices: list
    seeds: list
    steps: list


def ranked(cands):
    """Candidates best first (a stable sort: ties keep their order)."""
    return sorted(cands, key=lambda c: c.sse)


class Residuals:
    """Weighted residuals of the reference model at one data set's geometry as a function of the
    free parameters: ``rows(X)`` maps a (B, d) array of parameter vectors (over ``free``) to the
    (B, M) residuals, (DOP - dop) / dop_std, then (F00 - f00) / f00_std when ``f00`` is given
    (then the ``kd`` of a vector is the ratio kd/ks).  Non-finite residuals become 1e150.

    ``model`` is a :class:`Model` (the geometry), ``base`` the values of the other parameters."""

    def __init__(self, model, free, base, dop, dop_std, f00=None, f00_std=None):
        self.model, self.free, self.base = model, tuple(free), dict(base)
        self.dop, self.dop_std, self.f00, self.f00_std = dop, dop_std, f00, f00_std

    def _with(self, values):
        p = dict(self.base)
        p.update(values)
        if self.f00 is not None:
            p["kd"] = p["kd"] * p["ks"]  # fitted as the ratio kd/ks, reported as both
        return p

    def params(self, x):
        """Every model parameter at the free parameters ``x`` (a dict of scalars)."""
        return self._with(zip(self.free, x))

    @property
    def observed(self):
        """The measured values fitted: the DOP (the channels' values, for
        :class:`~pbrdf_cl.fitting.sample.polarimetric.ChannelResiduals`)."""
        return self.dop

    def raw(self, p):
        """The unweighted DOP residuals (model - measured) at every model parameter ``p`` (scalars)."""
        return self.model.dop(p) - self.dop

    def weighted(self, p, runs=()):
        """The weighted DOP residuals at every model parameter ``p`` (name -> scalars or (B, 1)
        arrays); ``runs`` as :meth:`Model.dop_rows`'s."""
        return finite_rows((self.model.dop_rows(p, runs=runs) - self.dop) / self.dop_std)

    def rows(self, X):
        return in_row_blocks(lambda a, b: self.rows_of(X[a:b]), len(X), self.dop.size)

    def rows_of(self, X):
        """:meth:`rows` at once."""
        p = self._with((n, X[:, j:j + 1]) for j, n in enumerate(self.free))
        r = (self.model.dop_rows(p) - self.dop) / self.dop_std
        if self.f00 is not None:
            r = np.concatenate([r, (self.model.f00_rows(p) - self.f00) / self.f00_std], axis=1)
        return finite_rows(r)


def _sse_of_rows(rows):
    """The objective sum(r^2) of the first residual row at x, as a Python float (for nlopt)."""
    def sse(x):
        r = rows(x)[0]
        return float(min(r @ r, 1e300))
    return sse


#: A BOBYQA run that used its whole budget still counts as converged (:func:`_settled`) when its
#: best objective fell by at most this fraction of itself (plus ``SETTLED_ABS``, far below one
#: unit of chi^2 or a squared DOP resolution) over the second half of its evaluations after its
#: initial model (2d + 1 points): its tolerances (ftol_rel 1e-15, xtol_rel 1e-12) are far below
#: what matters, and at an exact fit (objective near 0) a relative tolerance is never met.
SETTLED_REL = 1e-9
SETTLED_ABS = 1e-12


def _recording(func, seen):
    """``func``, appending each value it returns to the list ``seen``."""
    def recorded(x):
        v = func(x)
        seen.append(v)
        return v
    return recorded


def _settled(seen, skip=0):
    """Whether the best of the objective values ``seen`` (in evaluation order) stopped falling:
    by at most SETTLED_REL of itself plus SETTLED_ABS over the second half of those after the
    first ``skip`` (False where fewer than two are left)."""
    best = np.minimum.accumulate(np.asarray(seen, float))
    if best.size - skip < 2:
        return False
    return bool(best[skip + (best.size - skip) // 2] - best[-1] <= SETTLED_REL * best[-1] + SETTLED_ABS)


def run_stage(resid_rows, jobs):
    """Run the jobs (callables ``job(rows) -> output``) in lockstep (:class:`_Lockstep`, their
    evaluations batched); a :class:`StageResult` of the outputs in order."""
    t0 = time.perf_counter()
    runner = _Lockstep(resid_rows)
    out = runner.run(jobs)
    return StageResult(out, runner.rows, time.perf_counter() - t0)


def grid_stage(meas, free, axes, base, shadowing="paper", *, engine=None, backend="auto", progress=False,
               channels=None, memory_budget=MEMORY_BUDGET):
    """(a) The objective on the grid ``axes`` (name -> nodes, one per free parameter) with the
    other parameters at ``base``, on the OpenCL device (float32), and its profiles: of the DOP of
    ``meas``, or of polarimetric ``channels`` (:class:`~pbrdf_cl.model.measurables.Channels`); the
    measurements' tables in blocks within ``memory_budget`` (:func:`pbrdf_cl.objective`'s).  The
    DOP's as :func:`grid_stages`' of one set (the SSE alone: no labelled array, no best nodes)."""
    import warnings
    if channels is None:
        return grid_stages([meas], free, axes, base, shadowing, engine=engine, backend=backend, progress=progress,
                           memory_budget=memory_budget)[0]
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # fit's argument check gives the radians warning, once
        warnings.simplefilter("ignore", pointwise.UnitsWarning)
        obj = dense.objective(channels, grid={**base, **axes}, k_best=1, dtype="float32", shadowing=shadowing,
                              engine=engine, backend=backend, progress=progress, memory_budget=memory_budget)
    sse = obj.sse.transpose(*free).values
    profiles = basins.grid_profiles(sse, free)
    return StageResult(GridStage(sse, axes, profiles), int(sse.size), time.perf_counter() - t0)


def grid_stages(meases, free, axes, base, shadowing="paper", *, engine=None, backend="auto", progress=False,
                memory_budget=MEMORY_BUDGET):
    """:func:`grid_stage` of several DOP data sets ``meases`` measured at one geometry (the same
    theta_i, theta_r, phi in order) on one grid, in one pass (:func:`~pbrdf_cl.compute.dense.objective_sets`:
    each grid point's DOP combined once for every set); one :class:`StageResult` per set, each
    set's grid that of :func:`grid_stage` bit for bit, the pass's time shared equally."""
    import warnings
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", pointwise.UnitsWarning)
        names, sses = dense.objective_sets(list(meases), {**base, **axes}, dtype="float32", shadowing=shadowing,
                                           engine=engine, backend=backend, progress=progress,
                                           memory_budget=memory_budget)
    order = [names.index(n) for n in free]
    grids = []
    for sse in sses:
        sse = sse.transpose(order)
        grids.append(GridStage(sse, axes, basins.grid_profiles(sse, free)))
    share = (time.perf_counter() - t0) / len(grids)
    return [StageResult(g, int(g.sse.size), share) for g in grids]


def basin_stage(grid, free, n_basins, rise, profile_seeds=PROFILE_SEEDS):
    """(b) Seeds: the grid's best ``n_basins`` local minima, one per neighbourhood, then up to
    ``profile_seeds`` valleys of its profiles that none of them lies in (behind a ridge at least
    ``rise`` high); ``grid`` is a :class:`GridStage`."""
    t0 = time.perf_counter()
    indices = basins.grid_basins(grid.sse, n_basins)
    indices += basins.profile_seeds(grid.sse, grid.profiles, free, indices, profile_seeds, rise)
    seeds = [basins.grid_point(grid.axes, free, idx) for idx in indices]
    steps = [np.array([basins.local_spacing(grid.axes[n], i) for n, i in zip(free, idx)]) for idx in indices]
    return StageResult(Basins(indices, seeds, steps), 0, time.perf_counter() - t0)


def direct_stage(resid_rows, lo, hi, seeds, steps, evals=DIRECT_EVALS):
    """(c) DIRECT-L inside a box of +-1.5 ``steps`` around each seed (``evals`` evaluations per
    free parameter each, the seed counted as seen); one :class:`Candidate` per seed."""
    import nlopt

    def job(seed, step):
        blo, bhi = np.maximum(lo, seed - 1.5 * step), np.minimum(hi, seed + 1.5 * step)

        def run(rows):
            x, f, _ = _nlopt_min(nlopt.GN_DIRECT_L, _sse_of_rows(rows), blo, bhi, (blo + bhi) / 2,
                                 maxeval=evals * lo.size, start=seed)
            return Candidate(f, x, seed)
        return run
    return run_stage(resid_rows, [job(seed, step) for seed, step in zip(seeds, steps)])


def bobyqa_stage(resid_rows, lo, hi, cands, steps, evals=BOBYQA_EVALS):
    """(d) BOBYQA from each candidate over the whole bounds, ``steps`` as initial steps and
    ``evals`` evaluations per free parameter; the candidates in the same order."""
    import nlopt

    def job(cand, step):
        def run(rows):
            x, f, _ = _nlopt_min(nlopt.LN_BOBYQA, _sse_of_rows(rows), lo, hi, cand.x, maxeval=evals * lo.size,
                                 step=step)
            return Candidate(f, x, cand.seed)
        return run
    return run_stage(resid_rows, [job(c, step) for c, step in zip(cands, steps)])


def screen_stage(resid_rows, lo, hi, cands, iterations=SCREEN_ITERATIONS):
    """Batched Levenberg-Marquardt descent (:func:`lm_batch`) of every candidate (BOBYQA's
    ranking in a long flat valley says little about its floor); each candidate moves where the
    descent improved it, in the same order."""
    t0 = time.perf_counter()
    X, sse, rows = lm_batch(resid_rows, np.array([c.x for c in cands]), lo, hi, iterations)
    out = [c.better(sse[i], X[i]) for i, c in enumerate(cands)]
    return StageResult(out, rows, time.perf_counter() - t0)


def least_squares_stage(resid_rows, lo, hi, cands, max_nfev=LS_MAX_NFEV):
    """scipy's trust-region least squares to the end from each candidate (2-point Jacobians of
    :func:`fd_jacobian`, at most ``max_nfev`` evaluations per free parameter), which converges
    along the long, flat valleys where BOBYQA stalls; ``converged`` is False where it ran out of
    evaluations."""
    from scipy.optimize import least_squares

    def job(cand):
        def run(rows):
            ls = least_squares(lambda x: rows(x)[0], cand.x, jac=lambda x: fd_jacobian(rows, x[None], lo, hi)[1][0].T,
                               bounds=(lo, hi), x_scale=hi - lo, ftol=1e-15, xtol=1e-15, gtol=1e-15,
                               max_nfev=max_nfev * lo.size)
            moved = cand.better(2 * ls.cost, np.clip(ls.x, lo, hi))
            return replace(moved, converged=ls.status != 0)
        return run
    return run_stage(resid_rows, [job(c) for c in cands])


def final_bobyqa_stage(resid_rows, lo, hi, cand, evals=FINAL_BOBYQA):
    """BOBYQA from ``cand`` with steps of 1% of the bounds (``evals`` evaluations per free
    parameter): a flat valley running into a bound is where trust-region least squares crawls
    (it keeps strictly inside the bounds); BOBYQA, which steps onto them, finishes the job."""
    import nlopt
    maxeval = evals * lo.size

    def run(rows):
        seen = []
        x, f, n = _nlopt_min(nlopt.LN_BOBYQA, _recording(_sse_of_rows(rows), seen), lo, hi, cand.x, maxeval=maxeval,
                             step=0.01 * (hi - lo), start=cand.x)
        # (n and seen count the start too)
        return replace(cand.better(f, x), converged=n <= maxeval or _settled(seen, 2 * lo.size + 2))
    out = run_stage(resid_rows, [run])
    return StageResult(out.value[0], out.nfev, out.seconds)


#: How many of the best candidates of the screen get the least-squares polish.
LS_POLISH = 2


def local_stages(rows, lo, hi, grid, free, n_basins, rise, derivative_free=True, screened=None):
    """:func:`fit`'s stages between the grid and the intensities, on the residual rows ``rows``:
    the grid's basins (``n_basins``, valleys behind a ridge of ``rise``), DIRECT-L and BOBYQA from
    each (unless not ``derivative_free``), the Levenberg-Marquardt screen of them and of the bound
    slices' best nodes (:func:`seed_stages`), least squares from the best, the final BOBYQA where
    it ran out (:func:`polish_stages`).  ``screened``: the stages up to the screen done already
    (their results by name, the screen's among them: :func:`pbrdf_cl.fit_joint` screens all its
    sets' candidates at once).  Returns (candidates best first, whether the final BOBYQA ran, the
    stages' results by name)."""
    if screened is None:
        st, starts = seed_stages(rows, lo, hi, grid, free, n_basins, rise, derivative_free)
        st["screen"] = screen_stage(rows, lo, hi, starts, SCREEN_ITERATIONS)
    else:
        st = dict(screened)
    cands, final_ran, polish = polish_stages(rows, lo, hi, st["screen"].value)
    return cands, final_ran, {**st, **polish}


def seed_stages(rows, lo, hi, grid, free, n_basins, rise, derivative_free=True):
    """:func:`local_stages`'s first stages: the grid's basins, DIRECT-L and BOBYQA from each
    (unless not ``derivative_free``); returns (their results by name, the candidates the screen
    descends: those, and the best grid point of each bound slice)."""
    st = {"basins": basin_stage(grid, free, n_basins, rise, PROFILE_SEEDS)}
    found = st["basins"].value
    # the basins' optimisers of each stage run in lockstep, their evaluations batched
    if derivative_free:
        st["direct"] = direct_stage(rows, lo, hi, found.seeds, found.steps, DIRECT_EVALS)
        st["bobyqa"] = bobyqa_stage(rows, lo, hi, st["direct"].value, found.steps, BOBYQA_EVALS)
        starts = ranked(st["bobyqa"].value)
    else:
        starts = [Candidate(np.inf, x, x) for x in found.seeds]
    # every candidate, and the best grid point of each bound slice (this model's optimum often
    # sits on a bound: k = 0, n = 1, sigma = 1, kd = 0), descends its valley
    edges = [basins.grid_point(grid.axes, free, idx) for idx in basins.bound_seeds(grid.sse, found.indices)]
    return st, starts + [Candidate(np.inf, x, x) for x in edges]


def polish_stages(rows, lo, hi, screened):
    """:func:`local_stages` after the screen (``screened``: its candidates): least squares from
    the best, the final BOBYQA where it ran out; (candidates best first, whether the final
    BOBYQA ran, the stages' results by name)."""
    cands = ranked(screened)
    top = min(LS_POLISH, len(cands))  # the best candidates, least squares to the end
    st = {"least_squares": least_squares_stage(rows, lo, hi, cands[:top], LS_MAX_NFEV)}
    cands = ranked(st["least_squares"].value + cands[top:])
    final_ran = cands[0].converged is False
    st["final_bobyqa"] = (final_bobyqa_stage(rows, lo, hi, cands[0], FINAL_BOBYQA) if final_ran
                          else StageResult(cands[0], 0, 0.0))
    cands[0] = st["final_bobyqa"].value
    return cands, final_ran, st


def intensity_start(model, p, f00, f00_std, ks_bounds):
    """The ks that best scales the model's F00 at ``p`` (with ks = 1) to the intensities
    ``f00`` (weighted least squares), clipped to ``ks_bounds``."""
    m1 = model.f00(p)
    w = 1 / f00_std ** 2
    return float(np.clip((w * f00 * m1).sum() / max((w * m1 * m1).sum(), 1e-300), *ks_bounds))


def intensity_stage(residuals, lo, hi, x0, step, maxeval=INTENSITY_MAXEVAL):
    """BOBYQA over every free parameter of ``residuals`` (a :class:`Residuals` with intensities:
    ks free, kd as kd/ks) from ``x0`` with initial ``step``, at most ``maxeval`` evaluations in
    all: ks and kd separately (DOP alone cannot)."""
    import nlopt

    def run(rows):
        seen = []
        x, f, n = _nlopt_min(nlopt.LN_BOBYQA, _recording(_sse_of_rows(rows), seen), lo, hi, x0, maxeval=maxeval,
                             step=step)
        return Candidate(f, x, x0, converged=n < maxeval or _settled(seen, 2 * lo.size + 1))
    out = run_stage(residuals.rows, [run])
    return StageResult(out.value[0], out.nfev, out.seconds)


def finite_rows(r):
    """Residuals with non-finite entries replaced by a huge value (never NaN to the optimisers)."""
    return np.where(np.isfinite(r), r, 1e150)


def _nlopt_min(algorithm, func, lo, hi, x0, maxeval, step=None, start=None):
    """Minimise in coordinates scaled to [0, 1] per parameter; returns (x, f, evaluations).

    The best point seen is kept in a closure (nlopt can lose it on RoundoffLimited); ``start``
    (e.g. the grid seed) counts as seen."""
    import nlopt
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = hi - lo
    best = {"f": np.inf, "x": None, "n": 0}

    def f(u, grad):
        x = lo + u * span
        v = func(x)
        best["n"] += 1
        if v < best["f"]:
            best["f"], best["x"] = v, x.copy()
        return float(v)
    if start is not None:
        s = np.clip(np.asarray(start, float), lo, hi)
        f((s - lo) / span, None)
    opt = nlopt.opt(algorithm, lo.size)
    opt.set_lower_bounds(np.zeros(lo.size))
    opt.set_upper_bounds(np.ones(lo.size))
    opt.set_min_objective(f)
    opt.set_maxeval(int(maxeval))
    if algorithm == nlopt.LN_BOBYQA:
        opt.set_ftol_rel(1e-15)
        opt.set_xtol_rel(1e-12)
        if step is not None:
            opt.set_initial_step(np.clip(np.asarray(step, float) / span, 1e-9, 0.5))
    u0 = np.clip((np.asarray(x0, float) - lo) / span, 0, 1)
    try:
        opt.optimize(u0)
    except (nlopt.RoundoffLimited, RuntimeError, ValueError):
        pass
    return np.clip(best["x"], lo, hi), float(best["f"]), best["n"]
