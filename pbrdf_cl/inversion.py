"""Robust global inversion of measured DOP: device grid -> distinct basins -> nlopt DIRECT-L
-> BOBYQA -> batched Levenberg-Marquardt -> trust-region least squares, with uncertainties,
identifiability diagnostics and model comparison.

DOP depends on ks and kd only through kd/ks (SPEC), so DOP-only fits fix ks = 1 and report
kd as kd/ks.  When intensities (``f00`` or ``s0``) are given, a last stage fits ks and kd
separately with the intensity residuals added.
"""
from __future__ import annotations

import threading
import time

import numpy as np

from . import dense, reference
from .data import as_measurements

MODEL_PARAMS = {"six-param": ("n", "k", "sigma", "kd", "c"), "specular": ("n", "k")}
DEFAULT_BOUNDS = {"n": (1.0, 5.0), "k": (0.0, 10.0), "sigma": (0.05, 1.0), "kd": (0.0, 5.0), "c": (-1.0, 0.0),
                  "ks": (1e-3, 1e3)}
#: Grid points per free parameter for the device stage.
DEFAULT_GRID = {"n": 24, "k": 32, "sigma": 16, "kd": 16, "c": 8}
SPECULAR_GRID = {"n": 160, "k": 200}
#: The value a fixed-by-the-model parameter takes (specular: no diffuse term; sigma cancels).
MODEL_FIXED = {"six-param": {"ks": 1.0}, "specular": {"ks": 1.0, "kd": 0.0, "c": 0.0, "sigma": 0.5}}
#: Extra seeds from valleys of the grid's profiles that none of the grid's best local minima lies in.
PROFILE_SEEDS = 2
#: Evaluations per free parameter of each basin's DIRECT-L and BOBYQA runs.
DIRECT_EVALS = 20
BOBYQA_EVALS = 20
#: Iterations of the batched Levenberg-Marquardt descent of all candidates.
SCREEN_ITERATIONS = 100
#: How many of the best BOBYQA candidates get the final least-squares polish.
LS_POLISH = 2
#: Residual evaluations per free parameter the least-squares polish may use.
LS_MAX_NFEV = 100
#: Evaluations per free parameter of the last BOBYQA run, when least squares ran out of them.
FINAL_BOBYQA = 80
#: The grid's profile enters a 95% interval where its own 95% interval spans at least this many
#: grid cells (where it is narrower, the grid does not resolve the parameter).
GRID_RESOLVED_CELLS = 3
#: Resolution of the located optimum, as a fraction of each parameter's bound range: the
#: smallest half-width a 95% interval is given.
X_RESOLUTION = 1e-8
#: Default relative uncertainty of intensities when no f00_std column is given.
F00_REL_STD = 0.05


class FitResult(dense.Result):
    """Result of :func:`fit`; keys are also attributes (like scipy's ``OptimizeResult``).

    x (dict: every model parameter, fitted and fixed), free (names fitted), sse, chi2,
    reduced_chi2, rmse, residuals, stderr, corr (matrix over ``free``), condition_number, aic,
    bic, dof, nfev and seconds per stage, basins (candidates with their SSE), ambiguous, notes
    (list of sentences), and three kinds of 95% interval (dicts name -> (lo, hi)):

    ci95
        the central 95% of the parameter's posterior under a uniform prior over the bounds,
        approximated as the equal mixture of two approximations: the local (Laplace) one,
        x +- stderr * (Gaussian, or Student's t without given uncertainties) truncated to the
        bounds, and the device grid's profile likelihood normalised over the bounds (where the
        grid resolves it: its own interval spans at least ``GRID_RESOLVED_CELLS`` cells).  Where the
        data determine a parameter this is about x +- 1.96 stderr; where they do not, it is the
        middle 95% of its bounds (not all of them), so it covers the truth about 95% of the time
        in both cases (``scripts/bench_fit.py`` measures it).  It need not contain x: the best
        fit of a parameter the data do not determine is arbitrary and often sits on a bound.
    ci95_jacobian
        x +- 1.96 stderr (Student's t without given uncertainties), clipped to the bounds.
    ci95_profile
        likelihood ratio: the grid nodes whose profile is within 3.84 units of chi^2 of the
        optimum, widened to the next node (None where no node is).

    profiles maps each free parameter to the grid's profile: ``values`` (nodes) and ``sse``
    (minimum of the objective over the other parameters at each node).
    """

    def summary(self):
        lines = [f"model: {self['model']}  (shadowing {self['shadowing']}, {self['n_points']} points, "
                 f"{len(self['free'])} free parameters)"]
        for name in self["x"]:
            if name in self["free"]:
                lo, hi = self["ci95"][name]
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  +- {self['stderr'][name]:.3g}   "
                             f"95% interval [{lo:.4g}, {hi:.4g}]")
            else:
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  (fixed)")
        lines.append(f"  SSE {self['sse']:.4g}, RMSE {self['rmse']:.4g}, reduced chi2 {self['reduced_chi2']:.4g}, "
                     f"AIC {self['aic']:.2f}, BIC {self['bic']:.2f}")
        lines.append("  stages: " + ", ".join(f"{k} {self['nfev'][k]} evals / {self['seconds'][k]:.3f} s"
                                               for k in self["nfev"]))
        for note in self["notes"]:
            lines.append(f"  note: {note}")
        return "\n".join(lines)

    def __repr__(self):
        return self.summary()


class _Model:
    """DOP (and F00) of the reference model at fixed geometry, for the local stages.

    The factors depend on (n, k), (sigma, ks) and (kd, c) separately; each is recomputed only
    when its parameters change (finite-difference Jacobians and DIRECT move one at a time)."""

    def __init__(self, meas, shadowing):
        self.g = reference.geometry(meas.theta_i, meas.theta_r, meas.phi)
        self.variant = reference.SHADOWING[shadowing]
        self._cache = {}

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

    def dop_rows(self, p):
        """DOP for many parameter vectors at once: ``p`` maps names to (B, 1) arrays (or
        scalars); returns (B, M).  The same factors, without the cache."""
        return reference.dop(self._fresnel(p), self._log_scale(p), self._diffuse(p))

    def f00(self, p):
        return reference.brdf(*self.parts(p))


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


def _fd_steps(x, hi):
    """scipy's '2-point' steps for ``x`` (any shape): relative step sqrt(eps), inwards at an
    upper bound, as actually taken (exactly representable)."""
    h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(x))
    h = np.where(x + h > hi, -h, h)
    return (x + h) - x


def _fd_jacobian(rows, x, lo, hi):
    """scipy's '2-point' Jacobian (see :func:`_fd_steps`), with the base point and all steps in
    one batched call."""
    h = _fd_steps(x, hi)
    X = np.vstack([x, x + np.diag(h)])
    R = rows(X)
    return ((R[1:] - R[0]) / h[:, None]).T


def _lm_batch(resid_rows, X0, lo, hi, iterations):
    """Bounded Levenberg-Marquardt from P starts at once, every problem's trial point and its
    forward-difference Jacobian (scipy's step, inwards at the upper bound) in one batched call
    per iteration.  Levenberg damping in coordinates scaled to the bounds (a coordinate whose
    column vanishes, as k does at k = 0, gets no runaway step); a coordinate on a bound whose
    descent direction points outwards is held there, the others' steps are projected onto the
    bounds.  Returns (X, sse, row evaluations)."""
    X = np.clip(np.array(X0, float), lo, hi)
    P, d = X.shape
    span = hi - lo
    eye = np.eye(d)
    tol = 1e-12 * span

    def evaluate(X):
        h = _fd_steps(X, hi)
        pts = np.concatenate([X[:, None, :], X[:, None, :] + h[:, :, None] * eye[None]], axis=1)
        R = resid_rows(pts.reshape(-1, d)).reshape(P, d + 1, -1)
        r = R[:, 0]
        J = (R[:, 1:] - r[:, None]) / h[:, :, None] * span[None, :, None]  # (P, d, M), scaled
        return r, J, np.einsum("pm,pm->p", r, r)

    r, J, sse = evaluate(X)
    lam = 1e-3 * np.einsum("pim,pim->p", J, J) / d
    for _ in range(iterations):
        g = np.einsum("pim,pm->pi", J, r)
        held = ((X <= lo + tol) & (g > 0)) | ((X >= hi - tol) & (g < 0))
        Jf = np.where(held[:, :, None], 0.0, J)
        g = np.where(held, 0.0, g)
        A = np.einsum("pim,pjm->pij", Jf, Jf) + (lam[:, None] + held)[:, :, None] * eye[None]
        with np.errstate(all="ignore"):
            try:
                du = -np.linalg.solve(A, g[:, :, None])[:, :, 0]
            except np.linalg.LinAlgError:  # an overflowing Jacobian: no step, more damping
                du = np.zeros_like(X)
        du = np.where(np.isfinite(du), du, 0.0)
        Xt = np.clip(X + du * span, lo, hi)
        rt, Jt, sset = evaluate(Xt)
        ok = sset < sse
        X[ok], r[ok], J[ok], sse[ok] = Xt[ok], rt[ok], Jt[ok], sset[ok]
        lam = np.clip(np.where(ok, lam * 0.3, lam * 6.0), 1e-300, 1e300)
    return X, sse, P * (d + 1) * (iterations + 1)


def _check_bounds(model, bounds, fixed):
    names = MODEL_PARAMS[model]
    b = {n: DEFAULT_BOUNDS[n] for n in names}
    for name, v in (bounds or {}).items():
        if name not in DEFAULT_BOUNDS:
            raise ValueError(f"bounds: unknown parameter {name!r}; parameters are {', '.join(DEFAULT_BOUNDS)}")
        try:
            lo, hi = (float(x) for x in v)
        except (TypeError, ValueError):
            raise ValueError(f"bounds: {name} must be a (low, high) pair, got {v!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
            raise ValueError(f"bounds: {name} = ({lo}, {hi}) must be finite with low < high")
        b[name] = (lo, hi)
    phys = {"n": lambda v: v > 0, "k": lambda v: v >= 0, "sigma": lambda v: v > 0, "kd": lambda v: v >= 0,
            "ks": lambda v: v > 0, "c": lambda v: np.isfinite(v)}
    for name, (lo, hi) in b.items():
        if not phys[name](lo):
            raise ValueError(f"bounds: {name} low = {lo} is outside the model's domain")
    fx = {}
    for name, v in (fixed or {}).items():
        if name not in DEFAULT_BOUNDS:
            raise ValueError(f"fixed: unknown parameter {name!r}; parameters are {', '.join(DEFAULT_BOUNDS)}")
        v = float(v)
        if not (np.isfinite(v) and phys[name](v)):
            raise ValueError(f"fixed: {name} = {v} is outside the model's domain")
        if name not in names and not (model == "six-param" and name == "ks"):
            raise ValueError(f"fixed: {name} is not a parameter of the {model} model")
        fx[name] = v
    return b, fx


def fit(data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, grid_shape=None, n_basins=6,
        engine=None, backend="auto", progress=False):
    """Fit the model to measured DOP (see the module docstring for the pipeline).

    Parameters
    ----------
    data : CSV path, dict of arrays (theta_i, theta_r, dop[, phi, dop_std, f00|s0, f00_std]) or Measurements
    model : "six-param" (n, k, sigma, kd/ks, c; ks = 1) or "specular" (the paper's ref. [7]: n, k)
    bounds : dict name -> (low, high); defaults n [1, 5], k [0, 10], sigma [0.05, 1], kd [0, 5], c [-1, 0]
    fixed : dict name -> value, parameters held fixed (e.g. ``{"sigma": 0.45}``)
    grid_shape : dict name -> points of the device grid stage
    engine, backend : where the grid stage runs ("auto": the OpenCL device, or numpy without one)
    """
    if model not in MODEL_PARAMS:
        raise ValueError(f"model must be one of {sorted(MODEL_PARAMS)}, got {model!r}")
    if shadowing not in reference.SHADOWING:
        raise ValueError(f"shadowing must be one of {sorted(reference.SHADOWING)}, got {shadowing!r}")
    meas = as_measurements(data)
    bnds, fx = _check_bounds(model, bounds, fixed)
    free = [n for n in MODEL_PARAMS[model] if n not in fx]
    if not free:
        raise ValueError("every parameter is fixed: nothing to fit")
    if len(meas) <= len(free):
        raise ValueError(f"{meas.source}: {len(meas)} measurements for {len(free)} free parameters "
                         f"({', '.join(free)}); at least {len(free) + 1} are needed")
    base = dict(MODEL_FIXED[model])
    base.update({n: v for n, v in fx.items()})
    lo = np.array([bnds[n][0] for n in free])
    hi = np.array([bnds[n][1] for n in free])
    span = hi - lo
    std = meas.dop_std if meas.dop_std is not None else np.ones(len(meas))
    mdl = _Model(meas, shadowing)
    nfev, seconds = {}, {}

    def params(x):
        p = dict(base)
        p.update(zip(free, x))
        return p

    def resid_dop(x):
        return _finite((mdl.dop(params(x)) - meas.dop) / std)

    def resid_rows(X):
        p = dict(base)
        p.update((n, X[:, j:j + 1]) for j, n in enumerate(free))
        return _finite((mdl.dop_rows(p) - meas.dop) / std)

    def sse_via(rows):
        def sse(x):
            r = rows(x)[0]
            return float(min(r @ r, 1e300))
        return sse

    # (a) the objective on a dense grid over the bounds, on the OpenCL device
    t0 = time.perf_counter()
    shape = dict(SPECULAR_GRID if model == "specular" else DEFAULT_GRID)
    shape.update(grid_shape or {})
    axes = {n: _grid_axis(n, bnds[n], int(shape[n])) for n in free}
    grid_params = {**{n: v for n, v in base.items()}, **axes}
    res = dense.objective(meas.as_dict(), grid=grid_params, k_best=1, dtype="float32", shadowing=shadowing,
                          engine=engine, backend=backend, progress=progress)
    sse_grid = res.sse.transpose(*free).values
    nfev["grid"] = int(sse_grid.size)
    profiles = _grid_profiles(sse_grid, free)
    seconds["grid"] = time.perf_counter() - t0

    # (b) distinct basins: local minima of the grid objective, best first, one per neighbourhood
    t0 = time.perf_counter()
    basins = _grid_basins(sse_grid, n_basins)
    # ... and valleys of the grid's profiles that none of them lies in (a ridge of at least one
    # unit of chi^2 between; without given uncertainties the unit is estimated from the grid)
    rise = 1.0 if meas.dop_std is not None else float(sse_grid.min()) / (len(meas) - len(free))
    basins += _profile_seeds(sse_grid, profiles, free, basins, PROFILE_SEEDS, rise)
    seeds = [np.array([axes[n][i] for n, i in zip(free, idx)]) for idx in basins]
    spacings = [np.array([_local_spacing(axes[n], i) for n, i in zip(free, idx)]) for idx in basins]
    spacing = np.array([np.median(np.diff(axes[n])) for n in free])
    seconds["basins"] = time.perf_counter() - t0
    nfev["basins"] = 0

    # (c) DIRECT-L inside a box of +-1.5 grid spacings around each basin, (d) BOBYQA polish with
    # the grid spacing as initial step, a batched Levenberg-Marquardt descent of every candidate,
    # then least squares to the end for the best (scipy's trust-region reflective), which
    # converges along the long, flat valleys where BOBYQA stalls.  The basins' optimisers of
    # each stage run in lockstep, their evaluations batched.
    import nlopt
    from scipy.optimize import least_squares

    def stage(name, jobs):
        t0 = time.perf_counter()
        runner = _Lockstep(resid_rows)
        out = runner.run(jobs)
        nfev[name], seconds[name] = runner.rows, time.perf_counter() - t0
        return out

    def direct(seed, step):
        blo, bhi = np.maximum(lo, seed - 1.5 * step), np.minimum(hi, seed + 1.5 * step)
        return lambda rows: _nlopt_min(nlopt.GN_DIRECT_L, sse_via(rows), blo, bhi, (blo + bhi) / 2,
                                       maxeval=DIRECT_EVALS * len(free), start=seed)[:2]

    def bobyqa(x0, step):
        return lambda rows: _nlopt_min(nlopt.LN_BOBYQA, sse_via(rows), lo, hi, x0, maxeval=BOBYQA_EVALS * len(free),
                                       step=step)[:2]

    def polish(x0):
        def job(rows):
            return least_squares(lambda x: rows(x)[0], x0, jac=lambda x: _fd_jacobian(rows, x, lo, hi),
                                 bounds=(lo, hi), x_scale=span, ftol=1e-15, xtol=1e-15, gtol=1e-15,
                                 max_nfev=LS_MAX_NFEV * len(free))
        return job

    found = stage("direct", [direct(seed, step) for seed, step in zip(seeds, spacings)])
    found = stage("bobyqa", [bobyqa(x_d, step) for (x_d, _), step in zip(found, spacings)])
    cands = sorted(((f_b, x_b, seed) for (x_b, f_b), seed in zip(found, seeds)), key=lambda c: c[0])
    # every candidate, and the best grid point of each bound slice (this model's optimum often
    # sits on a bound: k = 0, n = 1, sigma = 1, kd = 0), descends its valley by batched
    # Levenberg-Marquardt: BOBYQA's ranking in a long flat valley says little about its floor
    t0 = time.perf_counter()
    for idx in _bound_seeds(sse_grid, basins):
        x_e = np.array([axes[n][i] for n, i in zip(free, idx)])
        cands.append((np.inf, x_e, x_e))
    X_s, f_s, nfev["screen"] = _lm_batch(resid_rows, np.array([c[1] for c in cands]), lo, hi, SCREEN_ITERATIONS)
    cands = sorted(((float(f_s[i]), X_s[i], c[2]) if f_s[i] < c[0] else c for i, c in enumerate(cands)),
                   key=lambda c: c[0])
    seconds["screen"] = time.perf_counter() - t0
    top = min(LS_POLISH, len(cands))  # the best candidates, least squares to the end
    unfinished = set()
    for i, ls in enumerate(stage("least_squares", [polish(cands[i][1]) for i in range(top)])):
        if 2 * ls.cost < cands[i][0]:
            cands[i] = (float(2 * ls.cost), np.clip(ls.x, lo, hi), cands[i][2])
        if ls.status == 0:  # out of evaluations: still creeping along a flat valley
            unfinished.add(id(cands[i]))
    cands.sort(key=lambda c: c[0])
    # a flat valley running into a bound is where trust-region least squares crawls (it keeps
    # strictly inside the bounds); BOBYQA, which steps onto them, finishes the job
    nfev["final_bobyqa"], seconds["final_bobyqa"] = 0, 0.0
    if id(cands[0]) in unfinished:
        f_0, x_0, seed_0 = cands[0]
        (x_f, f_f), = stage("final_bobyqa", [lambda rows: _nlopt_min(
            nlopt.LN_BOBYQA, sse_via(rows), lo, hi, x_0, maxeval=FINAL_BOBYQA * len(free), step=0.01 * span,
            start=x_0)[:2]])
        if f_f < f_0:
            cands[0] = (f_f, x_f, seed_0)
    best_sse, best_x, _ = cands[0]

    # intensities: fit ks and kd separately (DOP alone cannot)
    use_f00 = meas.f00 is not None and model == "six-param" and "ks" not in fx and "kd" not in fx
    f00_std = None
    free_all = list(free)
    if use_f00:
        t0 = time.perf_counter()
        f00_std = meas.f00_std if meas.f00_std is not None else F00_REL_STD * np.maximum(meas.f00, 1e-300)
        p = params(best_x)
        m1 = mdl.f00(p)  # ks = 1, kd = kd/ks
        w = 1 / f00_std ** 2
        ks_lo, ks_hi = bnds.get("ks", DEFAULT_BOUNDS["ks"])
        ks0 = float(np.clip((w * meas.f00 * m1).sum() / max((w * m1 * m1).sum(), 1e-300), ks_lo, ks_hi))
        free_all = free + ["ks"]
        lo_all = np.append(lo, ks_lo)
        hi_all = np.append(hi, ks_hi)

        def params_all(x):
            p = dict(base)
            p.update(zip(free_all, x))
            p["kd"] = p["kd"] * p["ks"]  # fitted as the ratio kd/ks, reported as both
            return p

        def resid_all(x):
            p = params_all(x)
            return _finite(np.concatenate([(mdl.dop(p) - meas.dop) / std, (mdl.f00(p) - meas.f00) / f00_std]))
        x_i, f_i, ne = _nlopt_min(nlopt.LN_BOBYQA, _sum_of_squares(resid_all), lo_all, hi_all, np.append(best_x, ks0), maxeval=6000,
                                  step=np.append(spacing, ks0 * 0.1))
        nfev["intensity"] = ne
        seconds["intensity"] = time.perf_counter() - t0

    # (e) the best wins; statistics and uncertainties
    if use_f00:
        x_final, lo_f, hi_f, p_final, resid = x_i, lo_all, hi_all, params_all(x_i), resid_all
    else:
        x_final, lo_f, hi_f, p_final, resid = best_x, lo, hi, params(best_x), resid_dop
    r = resid(x_final)
    m_obs, n_free = r.size, len(free_all)
    dof = m_obs - n_free
    chi2 = float(r @ r)
    sigma_known = meas.dop_std is not None
    s2 = 1.0 if sigma_known else chi2 / dof
    unit = 1.0 if sigma_known else best_sse / dof  # one unit of chi^2 on the DOP-only SSE scale
    J = _jacobian(resid, x_final, lo_f, hi_f)
    cov, cond, eig = _covariance(J, s2, hi_f - lo_f)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    from scipy.stats import norm, t as student_t
    # with known uncertainties the Gaussian quantile, else Student's t on the residual dof
    dist = norm if sigma_known else student_t(dof)
    q = float(dist.ppf(0.975))
    # never narrower than the optimizer's resolution (noise-free data would give a zero width)
    res = X_RESOLUTION * (hi_f - lo_f)
    half = np.maximum(q * se, res)
    ci_jac = {n: (max(lo_f[i], x_final[i] - half[i]), min(hi_f[i], x_final[i] + half[i]))
              for i, n in enumerate(free_all)}
    # likelihood-ratio intervals from the profile of the grid objective (banana-shaped valleys
    # are not ellipses)
    ci_prof = _profile_intervals(profiles, axes, best_sse + 3.84 * unit)
    # 95% intervals: posterior under a uniform prior over the bounds, the equal mixture of the
    # local (Laplace) approximation and the grid's profile
    ci = {}
    col = np.linalg.norm(J, axis=0)
    for i, n in enumerate(free_all):
        # a direction the DOP does not depend on at all has no finite standard error
        se_i = np.inf if col[i] <= 1e-12 * max(col.max(), 1e-300) else max(se[i], res[i] / q)
        cdfs = [_truncated_cdf(dist, x_final[i], se_i, lo_f[i], hi_f[i])]
        if n in axes:
            # the grid's profile counts where the grid resolves it: its own 95% interval spans
            # several cells (a valley, a banana, a flat stretch); else it only says "near the
            # best node", which the local approximation says better
            g = _grid_cdf(profiles[n], axes[n], len(meas), sigma_known)
            g_a, g_b = _central_interval([g], x_final[i], se_i, lo_f[i], hi_f[i], axes[n])
            if g_b - g_a >= GRID_RESOLVED_CELLS * _local_spacing(axes[n], int(np.argmin(profiles[n]))):
                cdfs.append(g)
        ci[n] = _central_interval(cdfs, x_final[i], se_i, lo_f[i], hi_f[i], axes.get(n, ()))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    dop_resid = mdl.dop(p_final) - meas.dop
    # -2 log-likelihood up to a constant: chi^2 with known sigmas, else m log(SSE / m)
    neg2ll = chi2 if sigma_known else m_obs * np.log(max(chi2, 1e-300) / m_obs)
    aic, bic = neg2ll + 2 * n_free, neg2ll + n_free * np.log(m_obs)

    notes = []
    if model == "six-param" and not use_f00:
        if "ks" in fx:
            notes.append(f"ks is fixed at {fx['ks']:g} by the caller; DOP depends on ks and kd only through "
                         "kd/ks, so kd is determined only relative to that choice")
        else:
            notes.append("DOP depends on ks and kd only through kd/ks: ks is fixed at 1 and kd is the ratio "
                         "kd/ks (add an f00 or s0 intensity column to separate them)")
    if model == "specular" and meas.f00 is not None:
        notes.append("the specular model is fitted to the DOP only; the intensity column was not used")
    if use_f00 and meas.f00_std is None:
        notes.append(f"intensities weighted with an assumed {F00_REL_STD:.0%} relative uncertainty "
                     "(give an f00_std column to set it)")
    notes += _identifiability_notes(free_all, J, cond, eig, x_final, se, corr, hi_f - lo_f)
    ambiguous = []
    for f_c, x_c, seed in cands[1:]:
        if f_c - best_sse <= unit and np.any(np.abs(x_c - best_x) > 2 * np.maximum(se[:len(free)], 1e-12)):
            ambiguous.append(dict(zip(free, map(float, x_c)), sse=float(f_c)))
    if ambiguous:
        alt = ", ".join(f"{n}={ambiguous[0][n]:.4g}" for n in free)
        notes.append(f"ambiguous: another basin fits equally well ({alt}, SSE {ambiguous[0]['sse']:.4g} vs "
                     f"{best_sse:.4g}); the data cannot decide between them")
    x_out = {n: float(p_final[n]) for n in ("n", "k", "sigma", "ks", "kd", "c")}
    if model == "specular":
        x_out = {n: x_out[n] for n in ("n", "k")}
    return FitResult(
        model=model, shadowing=shadowing, x=x_out, free=free_all, sse=float(dop_resid @ dop_resid), chi2=chi2,
        reduced_chi2=chi2 / dof, rmse=float(np.sqrt(np.mean(dop_resid ** 2))), residuals=dop_resid, dof=dof,
        n_points=len(meas), stderr=dict(zip(free_all, map(float, se))), ci95=ci, ci95_jacobian=ci_jac,
        ci95_profile=ci_prof, profiles={n: dict(values=axes[n], sse=profiles[n]) for n in free}, corr=corr,
        condition_number=float(cond), aic=float(aic), bic=float(bic), nfev=nfev, seconds=seconds,
        basins=[dict(zip(free, map(float, x)), sse=float(f), seed=dict(zip(free, map(float, s)))) for f, x, s in cands],
        ambiguous=ambiguous, notes=notes, sigma_known=sigma_known)


def _finite(r):
    """Residuals with non-finite entries replaced by a huge value (never NaN to the optimisers)."""
    return np.where(np.isfinite(r), r, 1e150)


def _sum_of_squares(resid):
    """The objective sum(resid(x)^2) as a Python float, for nlopt."""
    def sse(x):
        r = resid(x)
        return float(min(r @ r, 1e300))
    return sse


def _grid_axis(name, bounds, count):
    """Grid values of one parameter.  n, k and kd are spaced quadratically from their lower
    bound: near n = 1, k = 0 (an almost index-matched surface) and near kd = 0 (a small diffuse
    share) the DOP changes fastest and its minima are narrowest.  sigma is spaced
    geometrically: the specular lobe's shape depends on tan(a) / sigma, so equal ratios of sigma
    matter equally (on a linear grid, smooth surfaces with sigma < 0.1 fell between nodes)."""
    if name == "sigma" and bounds[0] > 0:
        return np.geomspace(bounds[0], bounds[1], count)
    u = np.linspace(0.0, 1.0, count)
    if name in ("n", "k", "kd"):
        u = u * u
    return bounds[0] + (bounds[1] - bounds[0]) * u


def _local_spacing(values, i):
    """The larger of the two grid steps around index i."""
    left = values[i] - values[i - 1] if i > 0 else 0.0
    right = values[i + 1] - values[i] if i + 1 < values.size else 0.0
    return max(left, right)


def _grid_basins(sse, n_basins, pool=4096):
    """Grid indices of the best ``n_basins`` local minima, at least 3 cells apart in some axis.

    Only the ``pool`` lowest cells are examined first (a partition, not a sort, of the grid);
    the greedy choice depends only on lower minima, so when the pool yields ``n_basins`` the
    answer is the same as from the whole grid, which is searched otherwise."""
    flat = sse.ravel()
    if flat.size > 4 * pool:
        cells = np.flatnonzero(flat <= np.partition(flat, pool)[pool])
    else:
        cells = np.arange(flat.size)
    chosen = _grid_minima(sse, cells, n_basins)
    if len(chosen) < n_basins and cells.size < flat.size:
        chosen = _grid_minima(sse, np.arange(flat.size), n_basins)
    return [tuple(int(v) for v in c) for c in chosen]


def _profile_seeds(sse, profiles, free, basins, count, rise):
    """Grid indices of up to ``count`` more seeds: for each parameter, the valleys of its grid
    profile that none of ``basins`` lies in (separated from them by a ridge at least ``rise``
    higher than the valley floor), each seeded at the best grid point of its slice; the best
    valleys first."""
    if count <= 0:
        return []
    found = []
    for j, n in enumerate(free):
        prof = profiles[n]
        taken = sorted({b[j] for b in basins})
        for i in range(prof.size):
            if not ((i == 0 or prof[i] <= prof[i - 1]) and (i == prof.size - 1 or prof[i] < prof[i + 1])):
                continue
            # the lowest ridge between this valley floor and any basin's slice
            ridge = min(prof[min(i, t):max(i, t) + 1].max() for t in taken)
            if ridge - prof[i] >= rise:
                found.append((prof[i], j, i))
    found.sort()
    out = []
    for _, j, i in found:
        idx = _slice_argmin(sse, j, i)
        if _apart(idx, list(basins) + out):
            out.append(idx)
        if len(out) == count:
            break
    return out


def _bound_seeds(sse, basins):
    """Grid indices of the best point of each parameter's two bound slices (the optimum of
    this model often sits on a bound: k = 0, n = 1, sigma = 1, kd = 0), where no basin is
    within 3 cells."""
    out = []
    for j in range(sse.ndim):
        for i in (0, sse.shape[j] - 1):
            idx = _slice_argmin(sse, j, i)
            if _apart(idx, list(basins) + out):
                out.append(idx)
    return out


def _slice_argmin(sse, j, i):
    """Grid index of the best point of the slice ``sse[..., i, ...]`` (index i along axis j)."""
    sl = np.take(sse, i, axis=j)
    rest = [int(v) for v in np.unravel_index(int(np.argmin(sl)), sl.shape)]
    return tuple(rest[:j] + [int(i)] + rest[j:])


def _apart(idx, others, cells=3):
    """True when grid index ``idx`` is at least ``cells`` cells from each of ``others`` in some axis."""
    return all(max(abs(int(a) - int(b)) for a, b in zip(idx, o)) >= cells for o in others)


def _grid_minima(sse, cells, n_basins):
    idx = np.array(np.unravel_index(cells, sse.shape)).T
    vals = sse.ravel()[cells]
    is_min = np.ones(cells.size, bool)
    for ax in range(sse.ndim):
        for shift in (-1, 1):
            nb = idx.copy()
            nb[:, ax] += shift
            inside = (nb[:, ax] >= 0) & (nb[:, ax] < sse.shape[ax])
            nbv = np.full(cells.size, np.inf)
            nbv[inside] = sse[tuple(nb[inside].T)]
            is_min &= vals <= nbv
    cand = idx[is_min]
    order = np.argsort(vals[is_min], kind="stable")
    chosen = []
    for c in cand[order]:
        if _apart(c, chosen):
            chosen.append(c)
        if len(chosen) == n_basins:
            break
    return chosen


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


def _jacobian(resid, x, lo, hi):
    """Central-difference Jacobian of the residual vector (one-sided at a bound)."""
    h = 1e-6 * (hi - lo)
    cols = []
    for j in range(x.size):
        up, dn = min(x[j] + h[j], hi[j]), max(x[j] - h[j], lo[j])
        xu, xd = x.copy(), x.copy()
        xu[j], xd[j] = up, dn
        cols.append((resid(xu) - resid(xd)) / (up - dn))
    return np.array(cols).T


def _covariance(J, s2, scale):
    """Covariance s2 (J^T J)^+ and, in parameters scaled by their bound ranges, the condition
    number and eigen-decomposition of J^T J."""
    JtJ = J.T @ J
    cov = s2 * np.linalg.pinv(JtJ, rcond=1e-15)
    Js = J * scale[None, :]
    w, v = np.linalg.eigh(Js.T @ Js)
    cond = w[-1] / w[0] if w[0] > 0 else np.inf
    return cov, cond, (w, v)


def _grid_profiles(sse, free):
    """Profile of the grid objective along each free parameter: the minimum over the others
    (float64, one value per grid node).  Two passes over the grid: the minimum over the
    trailing axes gives the leading axes' profiles and vice versa."""
    k = (sse.ndim + 1) // 2
    lead = sse.reshape(int(np.prod(sse.shape[:k])), -1)
    head = lead.min(axis=1).reshape(sse.shape[:k])  # over the trailing axes
    tail = lead.min(axis=0).reshape(sse.shape[k:])  # over the leading axes
    out = {}
    for i, n in enumerate(free):
        part, j = (head, i) if i < k else (tail, i - k)
        others = tuple(a for a in range(part.ndim) if a != j)
        out[n] = (part.min(axis=others) if others else part).astype(np.float64)
    return out


def _profile_intervals(profiles, axes, threshold):
    """For each free parameter, the range of grid values whose profile (min SSE over the other
    parameters) is below ``threshold``, widened to the neighbouring nodes; None where no node is."""
    out = {}
    for n, prof in profiles.items():
        ok = np.nonzero(prof <= threshold)[0]
        if ok.size == 0:
            out[n] = None
            continue
        vals = axes[n]
        out[n] = (float(vals[max(ok[0] - 1, 0)]), float(vals[min(ok[-1] + 1, vals.size - 1)]))
    return out


def _truncated_cdf(dist, x, se, lo, hi):
    """CDF of ``x + se * dist`` truncated to [lo, hi] (the Laplace approximation of the posterior
    under a uniform prior over the bounds), as a function of the parameter value; an infinite
    ``se`` (a direction the data do not constrain at all) gives the uniform prior itself."""
    if not np.isfinite(se):
        return lambda t: np.clip((t - lo) / (hi - lo), 0.0, 1.0)
    a, b = dist.cdf((lo - x) / se), dist.cdf((hi - x) / se)
    if not b - a > 1e-300:  # x many standard errors outside the bounds: cannot happen for a fit's x
        return lambda t: (np.asarray(t) >= x).astype(float)
    return lambda t: np.clip((dist.cdf((np.asarray(t) - x) / se) - a) / (b - a), 0.0, 1.0)


def _grid_cdf(prof, vals, n_obs, sigma_known):
    """CDF of one parameter's grid profile likelihood (``prof`` at the nodes ``vals``) normalised
    over its bounds (a uniform prior), the likelihood linear between nodes.  With known
    uncertainties the likelihood is exp(-chi2 / 2); else the noise is integrated out (Jeffreys
    prior): SSE^(-N/2).  Where the data are weak this follows the valley wherever it goes
    (banana-shaped and multimodal profiles); where they are sharp the grid's nodes miss the
    valley floor and it is only as fine as the grid."""
    prof = np.where(np.isfinite(prof), prof, np.inf)
    ref = prof.min()
    if sigma_known:
        w = np.exp(-0.5 * (prof - ref))
    else:
        w = np.exp(-0.5 * n_obs * np.log(np.maximum(prof, 1e-300) / max(ref, 1e-300)))
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(vals))])
    if not cdf[-1] > 0:  # one node: all the mass there
        k = float(vals[int(np.argmin(prof))])
        return lambda t: (np.asarray(t) >= k).astype(float)
    cdf /= cdf[-1]
    return lambda t: np.interp(t, vals, cdf)


def _central_interval(cdfs, x, se, lo, hi, nodes=(), level=0.95):
    """Central ``level`` interval of the equal-weight mixture of the distributions ``cdfs``
    (callables), found on a mesh over [lo, hi] refined around x (+-8 se) and at ``nodes``."""
    mesh = [np.linspace(lo, hi, 2001), np.asarray(nodes, float)]
    if np.isfinite(se) and se > 0:
        mesh.append(x + se * np.linspace(-8, 8, 321))
    mesh = np.unique(np.clip(np.concatenate(mesh + [[x]]), lo, hi))
    cdf = np.mean([c(mesh) for c in cdfs], axis=0)
    cdf = np.maximum.accumulate(cdf)
    tail = (1 - level) / 2

    def inverse(p):  # linear inside the mesh cell that brackets p
        j = int(np.clip(np.searchsorted(cdf, p, side="left"), 1, mesh.size - 1))
        c0, c1 = cdf[j - 1], cdf[j]
        return float(mesh[j] if c1 <= c0 else mesh[j - 1] + (p - c0) / (c1 - c0) * (mesh[j] - mesh[j - 1]))
    return inverse(tail), inverse(1 - tail)


def _identifiability_notes(names, J, cond, eig, x, se, corr, scale):
    notes = []
    w, v = eig
    if not np.isfinite(cond) or cond > 1e4:
        weak = v[:, 0]
        order = np.argsort(-np.abs(weak))
        terms = " ".join(f"{'+' if weak[i] >= 0 else '-'} {abs(weak[i]):.2f} d{names[i]}" for i in order[:3]
                         if abs(weak[i]) > 0.1)
        notes.append(f"near-degenerate direction (condition number {cond:.2g} in parameters scaled to their "
                     f"bounds): the data barely constrain the combination {terms.lstrip('+ ')}")
    col = np.linalg.norm(J, axis=0) * scale
    for i, n in enumerate(names):
        if col[i] < 1e-8 * max(col.max(), 1e-300):
            notes.append(f"{n} is not determined by these data (the DOP does not change with it here"
                         + ("; with kd = 0 the DOP does not depend on sigma or c" if n in ("sigma", "c") else "")
                         + ")")
        elif abs(x[i]) > 0 and se[i] > 0.5 * abs(x[i]):
            notes.append(f"{n} is poorly determined: standard error {se[i]:.3g} on {x[i]:.4g}")
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if np.isfinite(corr[i, j]) and abs(corr[i, j]) > 0.95:
                notes.append(f"{names[i]} and {names[j]} are strongly correlated (r = {corr[i, j]:+.3f})")
    return notes


def compare_models(data, shadowing="paper", bounds=None, fixed=None, engine=None, backend="auto", progress=False):
    """Fit the six-parameter model and the ref. [7] specular model to the same data (the
    specular fit takes the bounds and fixed values of n and k only).

    Returns a dict: "six-param" and "specular" FitResults, "preferred" (lower BIC) and "table"
    (a text table of both with SSE, AIC and BIC)."""
    meas = as_measurements(data)
    six = fit(meas, "six-param", bounds=bounds, fixed=fixed, shadowing=shadowing, engine=engine, backend=backend,
              progress=progress)
    spec_fixed = {k: v for k, v in (fixed or {}).items() if k in ("n", "k")}
    spec_bounds = {k: v for k, v in (bounds or {}).items() if k in ("n", "k")}
    spec = fit(meas, "specular", bounds=spec_bounds, fixed=spec_fixed, shadowing=shadowing, engine=engine,
               backend=backend, progress=progress)
    rows = ["| model | n | k | free params | SSE | AIC | BIC |", "|---|---|---|---|---|---|---|"]
    for name, r in (("six-param", six), ("specular (ref. [7])", spec)):
        rows.append(f"| {name} | {r.x['n']:.4g} | {r.x['k']:.4g} | {len(r.free)} | {r.sse:.4g} | {r.aic:.2f} | "
                    f"{r.bic:.2f} |")
    preferred = "six-param" if six.bic <= spec.bic else "specular"
    return {"six-param": six, "specular": spec, "preferred": preferred, "table": "\n".join(rows)}
