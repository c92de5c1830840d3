"""Joint fits of several data sets (:func:`fit_joint`): some parameters take one value for every
set (``shared``: by default the roughness sigma and the Minnaert exponent c, which are geometry
and do not change with the wavelength), the others one value per set.

The pipeline is :func:`pbrdf_cl.fit`'s, on the stacked residuals of every set:

1. one device grid per set (:func:`~pbrdf_cl.fitting.sample.stages.grid_stage`, the same grid as
   ``fit``'s; sets measured at one geometry go through it in one pass, :func:`set_grids`).  The
   joint objective is a sum over sets, and given the shared parameters each set's own parameters
   are minimised independently, so the profile of the joint grid over the
   shared axes is exactly the sum of each set's grid minimised over its own axes
   (:func:`joint_profiles`): the joint grid (the product of every set's own axes) is never made,
   and nothing is lost by not making it;
2. starting points: the best local minima and bound slices of that joint profile and the
   separate fits' shared values (:func:`joint_points`);
3. at each, the joint profile: every set's own fit at those shared values, batched
   (:func:`~pbrdf_cl.fitting.sets.exchange.profile_stage`; a set's DOP has valleys of nearly
   equal depth, and its best grid node is often not in its best valley); trust-region least
   squares on the stacked residuals from the best, the basin exchange of each set's own
   parameters at the shared values reached (:func:`~pbrdf_cl.fitting.sets.exchange.exchange_stage`),
   a final BOBYQA where the least squares ran out of evaluations;
4. uncertainties as ``fit``'s (:func:`~pbrdf_cl.fitting.sample.uncertainty.uncertainty_stage`): the
   posterior mixture of the joint Jacobian's local approximation and the joint grid's profile of
   each parameter (shared and per set, :func:`joint_profiles`).

Each set's separate fit (:func:`~pbrdf_cl.fitting.sample.inversion.fit_on_grid`, on the same grid) is
done beside it, so that the result shows what sharing bought.  The result is a
:class:`~pbrdf_cl.fitting.sets.result.JointResult`.
"""
from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from ...io.measurements import split_sets
from ..common import dop_noise_floor, lm_batch, one_blas_thread
from ..sample import basins
from ..sample.inversion import check_fit_args, fit_on_grid, grid_shape_of, local_inputs
from ..sample.polarimetric import channel_residuals, fit_channels, normalised_channels
from ..sample.result import fit_status
from ..sample.stages import (
    FINAL_BOBYQA,
    LS_POLISH,
    MEMORY_BUDGET,
    SCREEN_ITERATIONS,
    GridStage,
    Model,
    Residuals,
    StageResult,
    final_bobyqa_stage,
    grid_stage,
    grid_stages,
    least_squares_stage,
    ranked,
    run_stage,
    screen_stage,
    seed_stages,
)
from ..sample.uncertainty import uncertainty_stage
from ..setup import check_model, check_shared
from .exchange import exchange_stage, profile_stage
from .result import joint_result
from .stack import SetStack

#: The parameters shared by default: the surface's geometry (roughness and the diffuse lobe's
#: shape), the same at every wavelength; n, k and kd/ks change with it.
DEFAULT_SHARED = ("sigma", "c")
#: Local minima of the joint grid profile (over the shared axes) that seed the local stages.
JOINT_SEEDS = 8
#: The best points of the profile stage that descend jointly.
PROFILE_SCREEN = 4
#: Residual evaluations per free parameter of the joint least-squares polish (fit's LS_MAX_NFEV is
#: 100: with 11 parameters a flat valley along a bound made it crawl for seconds; where this runs
#: out, the final BOBYQA finishes, as in fit).
JOINT_LS_NFEV = 40


@dataclass(frozen=True)
class JointSetup:
    """The checked setup of :func:`fit_joint`: ``names`` (the sets, in order), per set its
    ``meas`` and :class:`~pbrdf_cl.fitting.setup.FitSetup` (``setups``); ``shared`` (the
    shared parameters the fit varies, model order) and ``shared_fixed`` (shared and held, name
    -> value); ``notes`` about the inputs; whether the sets give the standard deviations of what
    they measure (``sigma_known``: every set or none).  The joint parameter vector is
    :attr:`labels`: the shared parameters, then each set's own free parameters (``"n[a]"``)."""
    names: tuple
    meas: dict
    setups: dict
    shared: tuple
    shared_fixed: dict
    notes: tuple
    sigma_known: bool

    def own(self, name):
        """The free parameters of set ``name`` that are not shared."""
        return [p for p in self.setups[name].free if p not in self.shared]

    @property
    def labels(self):
        return list(self.shared) + [f"{p}[{s}]" for s in self.names for p in self.own(s)]

    def index(self, name):
        """The joint vector's columns of set ``name``'s free parameters (in its ``free`` order)."""
        labels = self.labels
        return np.array([labels.index(p if p in self.shared else f"{p}[{name}]") for p in self.setups[name].free])

    @property
    def lo(self):
        return self._bounds(0)

    @property
    def hi(self):
        return self._bounds(1)

    def _bounds(self, end):
        out = np.empty(len(self.labels))
        for s in self.names:
            out[self.index(s)] = (self.setups[s].lo, self.setups[s].hi)[end]
        return out


class JointResiduals:
    """The stacked weighted residuals of every set (each a
    :class:`~pbrdf_cl.fitting.sample.stages.Residuals`) as a function of the joint vector: ``rows(X)``
    maps (B, d) joint vectors to (B, sum of M); ``free`` are the joint labels."""

    def __init__(self, setup):
        self.setup = setup
        self.free = tuple(setup.labels)
        self.parts = [set_residuals(setup.meas[s], setup.setups[s]) for s in setup.names]
        self.index = [setup.index(s) for s in setup.names]
        self.stack = SetStack.of(self.parts)  # every set in one model call, where they can be
        self.columns = np.stack(self.index, axis=1) if self.stack is not None else None  # (free, sets)

    def rows(self, X):
        X = np.atleast_2d(X)
        if self.stack is not None and self.stack.fits(len(X)):
            return self.stack.joint_rows(X, self.columns)
        return np.concatenate([r.rows(X[:, ix]) for r, ix in zip(self.parts, self.index)], axis=1)

    def split(self, x):
        """Set name -> that set's free parameters (an array in its ``free`` order) from the joint ``x``."""
        return {s: np.asarray(x)[ix] for s, ix in zip(self.setup.names, self.index)}


def set_residuals(meas, setup):
    """The residuals of one set, as :func:`pbrdf_cl.fit`'s: of the DOP (weights 1/dop_std^2 where
    given), or of the normalised channels of polarimetric data (Stokes parameters, Mueller
    elements, ...: :func:`~pbrdf_cl.fitting.sample.polarimetric.channel_residuals`)."""
    if meas.polarimetric:
        return channel_residuals(meas, setup)
    std = meas.dop_std if meas.dop_std is not None else np.ones(len(meas))
    return Residuals(Model(meas, setup.shadowing), setup.free, setup.base, meas.dop, std)


def stds_given(meas, setup):
    """Whether the set ``meas`` gives the standard deviations of what it measures."""
    return normalised_channels(meas, setup.free)[3] if meas.polarimetric else meas.dop_std is not None


def set_grid(meas, setup, part, axes, shadowing, engine, backend, progress, memory_budget=MEMORY_BUDGET):
    """:func:`~pbrdf_cl.fitting.sample.stages.grid_stage` of one set: its DOP, or the normalised
    channels its residuals ``part`` fit."""
    ch = part.model.ch if meas.polarimetric else None
    return grid_stage(meas, setup.free, axes, setup.base, shadowing, engine=engine, backend=backend,
                      progress=progress, channels=ch, memory_budget=memory_budget)


def set_grids(setup, resid, shape, shadowing, engine, backend, progress, memory_budget=MEMORY_BUDGET):
    """Every set's grid stage (:func:`set_grid`): set name -> its StageResult.  The DOP sets measured
    at one geometry (the same angles, in order) whose grids have the same axes and held values
    (several wavelengths of one goniometer run) go through the grid in one pass
    (:func:`~pbrdf_cl.fitting.sample.stages.grid_stages`: each grid point's DOP is combined once for
    all of them), each set's grid the same, bit for bit."""
    out, groups = {}, {}
    for s, part in zip(setup.names, resid.parts):
        meas, su = setup.meas[s], setup.setups[s]
        axes = su.grid_axes(shape)
        key = (s,) if meas.polarimetric else (  # a polarimetric set: a pass of its own
            tuple(np.asarray(a, np.float64).tobytes() for a in (meas.theta_i, meas.theta_r, meas.phi)),
            tuple(su.free), tuple((n, np.asarray(v, np.float64).tobytes()) for n, v in axes.items()),
            tuple(sorted((n, float(v)) for n, v in su.base.items())))
        groups.setdefault(key, []).append((s, part, axes))
    for members in groups.values():
        if len(members) == 1:
            s, part, axes = members[0]
            out[s] = set_grid(setup.meas[s], setup.setups[s], part, axes, shadowing, engine, backend, progress,
                              memory_budget)
            continue
        su, axes = setup.setups[members[0][0]], members[0][2]
        done = grid_stages([setup.meas[s] for s, _, _ in members], su.free, axes, su.base, shadowing, engine=engine,
                           backend=backend, progress=progress, memory_budget=memory_budget)
        out.update((s, g) for (s, _, _), g in zip(members, done))
    return {s: out[s] for s in setup.names}


def separate_fit(meas, setup, grid_result, n_basins):
    """One set fitted alone on its grid (the lighter schedule: no DIRECT-L and BOBYQA stages), on
    what the joint fit uses of it (no intensities)."""
    if meas.polarimetric:
        return fit_channels(meas, setup, None, n_basins, grid_result=grid_result, derivative_free=False,
                            absolute=False)
    return fit_on_grid(meas, setup, grid_result, n_basins, derivative_free=False)


def separate_fits(setup, resid, grid_results, n_basins):
    """Every set fitted alone (:func:`separate_fit`): set -> its FitResult.  Where the sets'
    residuals stack (:class:`~pbrdf_cl.fitting.sets.stack.SetStack`) the fits run side by side in
    lockstep (:func:`~pbrdf_cl.fitting.sample.stages.run_stage`), each step's evaluations of
    every set in one model call, and where the sets also have the same size and bounds their
    screens run as one (:func:`screen_sets`); each fit sees the numbers it would alone, bit for bit."""
    names = setup.names
    if resid.stack is None:
        return {s: separate_fit(setup.meas[s], setup.setups[s], grid_results[s], n_basins) for s in names}
    stack = resid.stack
    screened = screen_sets(setup, stack, grid_results, n_basins)

    def job(i, s):
        def run(rows):
            def own(X):
                X = np.atleast_2d(X)
                return rows(np.column_stack([X, np.full(len(X), float(i))]))[:, :stack.sizes[i]]
            return fit_on_grid(setup.meas[s], setup.setups[s], grid_results[s], n_basins, derivative_free=False,
                               rows=own, screened=screened and screened[s])
        return run
    return dict(zip(names, run_stage(stack.tagged_rows, [job(i, s) for i, s in enumerate(names)]).value))


def screen_sets(setup, stack, grid_results, n_basins):
    """The separate fits' stages up to their screen (:func:`~pbrdf_cl.fitting.sample.stages.seed_stages`,
    the lighter schedule), every set's screen in one batched descent (its set a last, held
    column): set -> the stages' results by name, as
    :func:`~pbrdf_cl.fitting.sample.stages.local_stages` takes them (``screened``; the screen's
    time is that of all sets' together); None where the sets differ in size or bounds."""
    names, sus = setup.names, [setup.setups[s] for s in setup.names]
    if stack.ragged or any(not (np.array_equal(su.lo, sus[0].lo) and np.array_equal(su.hi, sus[0].hi)) for su in sus):
        return None
    t0 = time.perf_counter()
    seeds = {}
    for s, su in zip(names, sus):
        _, dop_resid, grid, rise = local_inputs(setup.meas[s], su, grid_results[s])
        seeds[s] = seed_stages(dop_resid.rows, su.lo, su.hi, grid, su.free, n_basins, rise, derivative_free=False)
    starts = [c for s in names for c in seeds[s][1]]
    which = np.repeat(np.arange(len(names)), [len(seeds[s][1]) for s in names])
    X, sse, rows = lm_batch(stack.tagged_rows, np.array([c.x for c in starts]), sus[0].lo, sus[0].hi,
                            SCREEN_ITERATIONS, extra=which[:, None].astype(np.float64), per_problem=True)
    seconds = time.perf_counter() - t0
    out = {}
    for i, s in enumerate(names):
        lanes = np.flatnonzero(which == i)
        cands = [starts[j].better(sse[j], X[j]) for j in lanes]
        out[s] = {**seeds[s][0], "screen": StageResult(cands, int(rows[lanes].sum()), seconds)}
    return out


def _as_sets(sets, set_column):
    """Set name -> data from what :func:`fit_joint` takes."""
    if set_column is not None:
        return split_sets(sets, set_column)
    if isinstance(sets, Mapping):
        return {str(k): v for k, v in sets.items()}
    if isinstance(sets, (list, tuple)) and all(isinstance(v, (str, bytes)) or hasattr(v, "__fspath__")
                                               for v in sets):
        return set_names_of_paths(sets)
    raise ValueError("sets must be a dict set name -> data, a list of CSV paths, or one table with set_column= "
                     f"naming its set column, got {type(sets).__name__}")


def set_names_of_paths(paths):
    """Set name -> path: each file's name without its suffix, or the whole path where two share one."""
    paths = [os.fsdecode(p) for p in paths]
    stems = [os.path.splitext(os.path.basename(p))[0] for p in paths]
    names = stems if len(set(stems)) == len(stems) else paths
    if len(set(names)) != len(names):
        raise ValueError(f"sets: the same file is given twice ({', '.join(paths)})")
    return dict(zip(names, paths))


def _per_set(arg, names, what, is_value):
    """``fixed`` or ``bounds`` per set: entries name -> value apply to every set; entries set ->
    dict to that set (they win)."""
    common, own = {}, {s: {} for s in names}
    for key, v in (arg or {}).items():
        if key in own and isinstance(v, Mapping):
            own[key] = dict(v)
        elif is_value(v):
            common[key] = v
        else:
            raise ValueError(f"{what}: {key!r} is neither a parameter with a value nor a set "
                             f"({', '.join(names)}) with a dict")
    return {s: {**common, **own[s]} for s in names}


def _shared_split(shared, setups):
    """(the shared parameters varied, the shared parameters held: name -> value); refuses a
    shared parameter held in some sets only, at different values, or with different bounds."""
    free, held = [], {}
    for p in shared:
        fixed = {s: su.fixed.get(p) for s, su in setups.items()}
        values = set(fixed.values())
        if values == {None}:
            bounds = {s: su.bounds[p] for s, su in setups.items()}
            if len(set(bounds.values())) > 1:
                raise ValueError(f"bounds: {p} is shared, so its bounds must be the same in every set, got "
                                 + ", ".join(f"{s}: {b}" for s, b in bounds.items()))
            free.append(p)
        elif len(values) == 1:
            held[p] = values.pop()
        else:
            raise ValueError(f"fixed: {p} is shared, so it must be held in every set at one value or in none, got "
                             + ", ".join(f"{s}: {'free' if v is None else v}" for s, v in fixed.items()))
    return tuple(free), held


def check_joint_args(sets, shared, model, bounds, fixed, shadowing, set_column=None):
    """The checked inputs of :func:`fit_joint`: a :class:`JointSetup` (one-line ``ValueError``s
    naming the set, the parameter and the value)."""
    check_model(model, shadowing)
    shared_given = shared
    check_shared(shared, model, DEFAULT_SHARED)  # the names, before the data are read
    data = _as_sets(sets, set_column)
    names = tuple(data)
    if len(names) < 2:
        raise ValueError(f"sets: {len(names)} set{'' if len(names) == 1 else 's'} ({', '.join(names)}); a joint fit "
                         "needs at least two (fit one set with pbrdf_cl.fit)")
    fx = _per_set(fixed, names, "fixed", lambda v: np.ndim(v) == 0 and not isinstance(v, Mapping))
    bd = _per_set(bounds, names, "bounds", lambda v: not isinstance(v, Mapping) and np.ndim(v) == 1)
    unlike = {p for f in fx.values() for p in f if len({repr(fx[s].get(p)) for s in names}) > 1}
    shared = check_shared(shared, model, DEFAULT_SHARED, unlike)
    meas, setups, notes, given = {}, {}, [], []
    for s in names:
        try:
            meas[s], setups[s] = check_fit_args(data[s], model, bd[s], fx[s], shadowing)
            if stds_given(meas[s], setups[s]):  # polarimetric data: also refuses too few numbers
                given.append(s)
        except ValueError as exc:
            raise ValueError(f"set {s!r}: {exc}") from None
    if given and len(given) < len(names):
        what, them = (("standard deviations (<name>_std)", "them") if any(m.polarimetric for m in meas.values())
                      else ("dop_std", "it"))
        raise ValueError(f"{what}: given for set{'s' if len(given) > 1 else ''} {', '.join(given)} but not for "
                         f"{', '.join(s for s in names if s not in given)}; give {them} for every set or for none")
    with_f00 = [s for s in names if meas[s].f00 is not None and not meas[s].polarimetric]
    if with_f00:
        notes.append(f"the intensities (f00) of set{'s' if len(with_f00) > 1 else ''} {', '.join(with_f00)} were "
                     "not used: fit_joint fits the DOP only, and so do the separate fits beside it")
        meas = {s: replace(m, f00=None, f00_std=None) if s in with_f00 else m for s, m in meas.items()}
    absolute = [s for s in names if meas[s].polarimetric and meas[s].channels().absolute.any()]
    if absolute:
        notes.append(f"the absolute channels (S0, M00, F00) of set{'s' if len(absolute) > 1 else ''} "
                     f"{', '.join(absolute)} entered only as ratios: fit_joint fits normalised quantities (ks held, "
                     "kd as kd/ks), and so do the separate fits beside it")
    free_shared, held = _shared_split(shared, setups)
    if not free_shared:
        why = (f" (by default the sets share {', '.join(DEFAULT_SHARED)} where the {model} model fits them and "
               "no set holds them apart)" if shared_given is None and not shared else "")
        notes.append(f"nothing is shared{why}" + (f" but held ({', '.join(held)})" if held else "")
                     + ": the joint fit is each set fitted on its own (the separate fits), reported together")
    return JointSetup(names, meas, setups, free_shared, held, tuple(notes), bool(given))


def joint_profiles(setup, grids):
    """The joint grid's objective profiles, from each set's grid (``grids``: set name ->
    :class:`~pbrdf_cl.fitting.sample.stages.GridStage`, axes in its ``free`` order).

    Returns (total, per_set, profiles): ``total`` the joint objective on the shared axes (each
    set's grid minimised over its own axes, summed: exact, the joint objective being a sum over
    sets whose own parameters are independent), ``per_set`` set -> its part of it, and
    ``profiles`` joint label -> the profile (minimum over every other joint parameter) at its
    nodes."""
    shared = list(setup.shared)
    per_set, own_profiles = {}, {}
    for s in setup.names:
        free, sse = setup.setups[s].free, grids[s].sse
        lead = [free.index(p) for p in shared]
        own_axes = [free.index(p) for p in setup.own(s)]
        own_profiles[s] = [np.transpose(m, lead + [j] + [a for a in own_axes if a != j]).reshape(
            [sse.shape[a] for a in lead + [j]]) for j, m in zip(own_axes, each_own_axis(sse, own_axes))]
        first = own_profiles[s][0] if own_profiles[s] else sse.transpose(lead)[..., None]
        per_set[s] = first.min(axis=len(shared)).astype(np.float64)
    total = sum(per_set.values())
    profiles = {}
    for j, p in enumerate(shared):
        others = tuple(a for a in range(len(shared)) if a != j)
        profiles[p] = total.min(axis=others) if others else total
    lead = tuple(range(len(shared)))
    for s in setup.names:
        rest = total - per_set[s]
        for p, g in zip(setup.own(s), own_profiles[s]):
            g = g.astype(np.float64) + np.asarray(rest)[..., None]
            profiles[f"{p}[{s}]"] = g.min(axis=lead) if lead else g
    return total, per_set, profiles


def each_own_axis(a, axes):
    """For each axis j of ``axes``, the minimum of ``a`` over the others of ``axes`` (dimensions
    kept, of length 1).  Halving ``axes``, each level reduces one half away for the other: two
    passes over ``a`` for any number of axes, where one minimum per axis took one pass each (a
    grid of 1.6 million nodes per set); each axis reduced in place (:func:`axis_min`), not
    through a transposed copy."""
    if len(axes) <= 1:
        return [a] if axes else []
    h = len(axes) // 2
    head, tail = a, a
    for ax in axes[h:]:
        head = axis_min(head, ax)
    for ax in axes[:h]:
        tail = axis_min(tail, ax)
    return each_own_axis(head, axes[:h]) + each_own_axis(tail, axes[h:])


def axis_min(a, axis):
    """The minimum of ``a`` over ``axis``, its length kept as 1: by halving (the elementwise minimum
    of the two halves, then of those, ...), which reads contiguous runs where numpy's reduction
    over an inner axis strides through memory (4x faster on a grid's middle axis); the same
    numbers (a minimum is exact; NaN propagates alike)."""
    n = a.shape[axis]

    def part(lo, hi):
        return (slice(None),) * axis + (slice(lo, hi),)
    if n == 0 or all(d == 1 for d in a.shape[:axis]):  # a leading axis: numpy's contiguous reduction
        return a.min(axis=axis, keepdims=True)
    while n > 1:
        h = n // 2
        m = np.minimum(a[part(0, h)], a[part(h, 2 * h)])
        if n % 2:
            m[part(0, 1)] = np.minimum(m[part(0, 1)], a[part(2 * h, n)])
        a, n = m, h
    return a


def joint_points(setup, grids, total, separate, count=JOINT_SEEDS):
    """Where the local stages start: (shared points, own starts).  The shared points (arrays over
    ``setup.shared``) are the best ``count`` local minima of the joint profile ``total`` (over
    the shared grid axes), its bound slices' best nodes, and each separate fit's shared values;
    the own starts (set -> own vectors, tried at every point) are each set's separate optimum
    (``separate``: set -> its :class:`~pbrdf_cl.fitting.sample.result.FitResult`, or None)."""
    shared = list(setup.shared)
    axes0 = grids[setup.names[0]].axes
    if shared:
        idxs = basins.grid_basins(total, count)
        idxs += basins.bound_seeds(total, idxs)
    else:
        idxs = [()]
    points = [np.array([axes0[p][i] for p, i in zip(shared, idx)]) for idx in idxs]
    own = {s: [] for s in setup.names}
    if separate:
        if shared:
            points += [np.array([separate[s].x[p] for p in shared]) for s in setup.names]
        own = {s: [np.array([separate[s].x[p] for p in setup.own(s)])] for s in setup.names}
    return points, own


def _local_stages(setup, resid, grids, points, own):
    """The local stages on the stacked residuals: the joint profile at each shared point (every
    set's own fit there, :func:`~pbrdf_cl.fitting.sets.exchange.profile_stage`), least squares
    (the best :data:`PROFILE_SCREEN` points), their batched Levenberg-Marquardt descent on the
    stacked residuals, least squares to the end from the best, the basin exchange of each set's own parameters
    (:func:`~pbrdf_cl.fitting.sets.exchange.exchange_stage`), BOBYQA where the last least
    squares ran out; (candidates best first, whether the final BOBYQA ran, stage results)."""
    lo, hi = setup.lo, setup.hi
    st = {"profile": profile_stage(setup, resid, grids, points, own)}
    cands = st["profile"].value[:PROFILE_SCREEN]
    st["screen"] = screen_stage(resid.rows, lo, hi, cands, SCREEN_ITERATIONS)
    cands = ranked(st["screen"].value)
    top = min(LS_POLISH, len(cands))
    st["least_squares"] = least_squares_stage(resid.rows, lo, hi, cands[:top], JOINT_LS_NFEV)
    cands = ranked(st["least_squares"].value + cands[top:])
    # the objective's unit of chi^2: 1 with the data's standard deviations, else estimated from the fit
    dof = max(1, sum(part.observed.size for part in resid.parts) - lo.size)
    unit = 1.0 if setup.sigma_known else cands[0].sse / dof
    st["exchange"] = exchange_stage(setup, resid, grids, cands[0], lo, hi, JOINT_LS_NFEV, unit)
    cands[0] = st["exchange"].value[0]
    final_ran = cands[0].converged is False
    st["final_bobyqa"] = (final_bobyqa_stage(resid.rows, lo, hi, cands[0], FINAL_BOBYQA) if final_ran
                          else StageResult(cands[0], 0, 0.0))
    cands[0] = st["final_bobyqa"].value
    return cands, final_ran, st


@one_blas_thread
def fit_joint(sets, shared=None, model="six-param", bounds=None, fixed=None, shadowing="paper", *,
              set_column=None, grid_shape=None, n_basins=6, engine=None, backend="auto", progress=False,
              memory_budget=MEMORY_BUDGET):
    """Fit the model to several data sets at once, some parameters shared by every set.

    Parameters
    ----------
    sets : dict, list of CSV paths, or one table
        Set name -> anything :func:`pbrdf_cl.fit` takes (Measurements, CSV path, dict, DataFrame):
        DOP, or polarimetric data (normalised Stokes parameters under polarized light, Mueller
        elements, AoP; the sets may mix them; absolute S0, M00 and F00 enter as ratios only);
        a list of CSV paths (each set named by its file name); or, with ``set_column``, one table
        (CSV path, dict, DataFrame, Dataset) whose column ``set_column`` names each row's set.
    shared : sequence of str or str, optional
        The parameters that take one value for every set (e.g. ``("n", "k")`` for several samples
        of one material), a sequence or one string (``"n,k"``, ``"n, k"``, ``"n k"``); the others
        take one value per set.  By default ("sigma", "c") where the model fits them and no set
        fixes them; ``()`` or ``""`` shares nothing (the joint fit is then the separate fits).
    model, shadowing
        As for :func:`pbrdf_cl.fit`.
    bounds, fixed : dict, optional
        As for :func:`pbrdf_cl.fit` (name -> (low, high), name -> value), for every set; an entry
        set name -> dict applies to that set only (``fixed={"a": {"kd": 0.1}}``).  A shared
        parameter has one bounds for all, and is held in every set at one value or in none.
    set_column : str, optional
        The column naming the sets when ``sets`` is one table (e.g. ``"wavelength"``).
    grid_shape, n_basins, engine, backend, progress, memory_budget
        As for :func:`pbrdf_cl.fit` (each set's grid stage, and its separate fit's basins).

    Returns
    -------
    JointResult
        ``x``, ``stderr``, ``ci95`` (set -> parameter -> value / (lo, hi); shared values repeat
        in every set and are also in ``shared_x``), ``sse``, ``chi2``, ``aic``, ``bic``, ``notes``,
        ``separate`` (set -> the :class:`FitResult` of that set alone), ``width_ratio`` (set ->
        parameter -> joint 95% width / separate 95% width), ``summary()``, ``to_dataset()``.

    Raises
    ------
    ValueError
        One line naming the set, the parameter or the value: fewer than two sets, an unknown shared
        parameter, a shared parameter held or bounded differently per set, dop_std given for some
        sets only, and each set's own refusals as :func:`pbrdf_cl.fit`'s.

    Examples
    --------
    >>> import pbrdf_cl
    >>> res = pbrdf_cl.fit_joint({"435": "a.csv", "532": "b.csv", "633": "c.csv"})  # doctest: +SKIP
    >>> res.shared_x["sigma"], res.ci95["435"]["n"], res.width_ratio["435"]["n"]  # doctest: +SKIP
    """
    t0 = time.perf_counter()
    setup = check_joint_args(sets, shared, model, bounds, fixed, shadowing, set_column)
    shape = grid_shape_of(model, grid_shape)
    resid = JointResiduals(setup)
    grid_results = set_grids(setup, resid, shape, shadowing, engine, backend, progress, memory_budget)
    grids = {s: g.value for s, g in grid_results.items()}
    t_sep = time.perf_counter()
    separate = separate_fits(setup, resid, grid_results, n_basins)
    st = {"grid": StageResult(None, sum(g.nfev for g in grid_results.values()),
                              sum(g.seconds for g in grid_results.values())),
          "separate": StageResult(None, sum(sum(r.nfev.values()) for r in separate.values()) -
                                  sum(g.nfev for g in grid_results.values()), time.perf_counter() - t_sep)}
    t1 = time.perf_counter()
    total, _, profiles = joint_profiles(setup, grids)
    points, own = joint_points(setup, grids, total, separate)
    st["seeds"] = StageResult(None, 0, time.perf_counter() - t1)
    lo, hi = setup.lo, setup.hi
    cands, final_ran, local = _local_stages(setup, resid, grids, points, own)
    st.update(local)
    best = cands[0]
    n_points = sum(part.observed.size for part in resid.parts)
    floor = None if setup.sigma_known else dop_noise_floor(np.concatenate([part.observed for part in resid.parts]))
    axes = {p: grids[setup.names[0]].axes[p] for p in setup.shared}
    axes.update({f"{p}[{s}]": grids[s].axes[p] for s in setup.names for p in setup.own(s)})
    jgrid = GridStage(total, axes, profiles)
    unc = uncertainty_stage(resid, best.x, lo, hi, jgrid, best.sse, n_points, setup.sigma_known, floor)
    st["uncertainty"] = unc
    status = fit_status(best, final_ran, None)
    return joint_result(setup, resid, best, cands, unc.value, jgrid, separate, st, status,
                        time.perf_counter() - t0)
