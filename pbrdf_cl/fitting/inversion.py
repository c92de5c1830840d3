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
from dataclasses import dataclass, replace

import numpy as np

from ..compute import pointwise
from ..compute import dense
from ..model import reference
from ..compute.pointwise import RULES
from ..io.measurements import as_measurements
from ..results import Result

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
#: Evaluations (in all, not per parameter) of the intensity stage's BOBYQA run.
INTENSITY_MAXEVAL = 6000
#: The grid's profile enters a 95% interval where its own 95% interval spans at least this many
#: grid cells (where it is narrower, the grid does not resolve the parameter).
GRID_RESOLVED_CELLS = 3
#: Resolution of the located optimum, as a fraction of each parameter's bound range: the
#: smallest half-width a 95% interval is given.
X_RESOLUTION = 1e-8
#: Default relative uncertainty of intensities when no f00_std column is given.
F00_REL_STD = 0.05
#: Without given uncertainties (no dop_std) the DOP noise is estimated from the residuals, and an
#: exact fit (noise-free synthetic data; as many distinct geometries as free parameters) would make
#: it zero and every interval a point.  The estimate is never taken below a floor: the standard
#: deviation of the rounding error of the data's DOP resolution (step / sqrt(12), the step read
#: from the decimals of the values, e.g. 0.01 for "0.25, 0.31, ..."), and at least this value, a
#: conservative precision of DOP measurement (polarimeters resolve DOP to about 1e-3 to 1e-2).
DOP_NOISE_FLOOR = 1e-3
#: The most decimals :func:`dop_resolution` looks for (more: no resolution is read from the values).
DOP_MAX_DECIMALS = 8




class FitResult(Result):
    """Result of :func:`fit`; keys are also attributes, which may be assigned (like scipy's
    ``OptimizeResult``).

    success, status, message
        like scipy's: ``status`` is one of :data:`FIT_STATUS` (1: the local stages converged; 2:
        least squares ran out of evaluations along a flat valley and the final BOBYQA finished;
        0: an evaluation budget ran out while the objective was still falling (see
        :func:`_settled`), the result is the best point found; -1: the residuals are not finite at
        any candidate), ``success`` is ``status > 0`` and ``message`` says which.

    Without given uncertainties (no dop_std) the noise is estimated from the residuals, never
    below :func:`dop_noise_floor` (an exact fit would make every interval a point); a note says
    when the floor was used.  Fewer distinct geometries than free parameters are refused.

    x (dict: every model parameter, fitted and fixed, as the model takes them: ``x["kd"]`` is
    the absolute kd, so that ``pbrdf_cl.dop(..., **res.x)`` evaluates the fit), kd_ratio (kd/ks),
    free (names fitted), sse, chi2, reduced_chi2, rmse, residuals, stderr, corr (matrix over
    ``free``), condition_number, aic, bic, dof, nfev and seconds per stage, basins (candidates
    with their SSE), ambiguous, notes (list of sentences), and three kinds of 95% interval (dicts
    name -> (lo, hi)).

    Which kd: without intensities the DOP sees kd/ks only, ks is fixed (at 1 unless ``fixed``
    says otherwise) and kd is fitted as itself (equal to kd/ks at ks = 1).  With an intensity
    column (``f00``/``s0``) ks is fitted too and the fitted coordinate is the ratio: ``stderr``,
    the intervals, ``corr`` and ``profiles`` under "kd" are those of kd/ks (``kd_ratio``), while
    ``x["kd"]`` is kd/ks x ks.  ``summary()`` prints both rows, kd/ks and kd, saying which is which.

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
        x +- 1.96 stderr (Student's t without given uncertainties, unless the noise floor was
        used), clipped to the bounds.
    ci95_profile
        likelihood ratio: the grid nodes whose profile is within 3.84 units of chi^2 of the
        optimum, widened to the next node (None where no node is).

    profiles maps each free parameter to the grid's profile: ``values`` (nodes) and ``sse``
    (minimum of the objective over the other parameters at each node).
    """

    def summary(self):
        lines = [f"model: {self['model']}  (shadowing {self['shadowing']}, {self['n_points']} points, "
                 f"{len(self['free'])} free parameters)"]
        if not self.get("fits_data", True):
            lines.append("  WARNING: the model does not describe these data (see the first note); the "
                         "values and intervals below are not to be trusted")
        ratio = "ks" in self["free"] and "kd" in self["free"]  # intensities: kd/ks and ks were fitted
        for name in self["x"]:
            if name == "kd" and ratio:
                lo, hi = self["ci95"][name]
                lines.append(f"  {'kd/ks':6s} = {self['kd_ratio']:10.5g}  +- {self['stderr'][name]:.3g}   "
                             f"95% interval [{lo:.4g}, {hi:.4g}]  (fitted: stderr, ci95, corr of 'kd')")
                lines.append(f"  {'kd':6s} = {self['x'][name]:10.5g}  (absolute, kd/ks x ks: x['kd'])")
            elif name in self["free"]:
                lo, hi = self["ci95"][name]
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  +- {self['stderr'][name]:.3g}   "
                             f"95% interval [{lo:.4g}, {hi:.4g}]" + self._kd_tag(name))
            else:
                lines.append(f"  {name:6s} = {self['x'][name]:10.5g}  (fixed)" + self._kd_tag(name))
        fit_line = f"  SSE {self['sse']:.4g} (DOP), RMSE {self['rmse']:.4g}"
        if self.get("sigma_known"):  # chi2 means something only with given uncertainties
            fit_line += (f", chi2 {self['chi2']:.4g} for {self['dof']} dof (reduced {self['reduced_chi2']:.3g}, "
                         f"p = {self['p_value']:.3g})")
        lines.append(fit_line + f", AIC {self['aic']:.2f}, BIC {self['bic']:.2f}")
        lines.append("  stages: " + ", ".join(f"{k} {self['nfev'][k]} evals / {self['seconds'][k]:.3f} s"
                                               for k in self["nfev"]))
        if not self.get("success", True):
            lines.append(f"  status {self['status']}: {self['message']}")
        for note in self["notes"]:
            lines.append(f"  note: {note}")
        return "\n".join(lines)

    def _kd_tag(self, name):
        """What a DOP-only fit's kd is: the ratio kd/ks where ks is 1, else absolute at the fixed ks."""
        if name != "kd" or "ks" not in self["x"] or "ks" in self["free"]:
            return ""
        ks = self["x"]["ks"]
        return "  (= kd/ks: ks fixed at 1)" if ks == 1.0 else f"  (absolute, with ks fixed at {ks:g})"

    def __repr__(self):
        values = ", ".join(f"{n}={v:.4g}" for n, v in self["x"].items())
        return (f"FitResult(model={self['model']!r}, success={self['success']}, {values}, "
                f"sse={self['sse']:.4g}, notes={len(self['notes'])}; .summary() for the report)")


class ComparisonResult(Result):
    """Result of :func:`compare_models`: ``fits`` (model name -> :class:`FitResult`, also the keys
    "six-param" and "specular"), ``preferred`` (the lower BIC), ``table`` (Markdown) and
    :meth:`summary`."""

    def summary(self):
        lines = ["model comparison (lower AIC/BIC is better):"]
        for name, r in self["fits"].items():
            lines.append(f"  {name:10s} SSE {r.sse:10.4g}  AIC {r.aic:9.2f}  BIC {r.bic:9.2f}  ({len(r.free)} free)")
        lines.append(f"  preferred by BIC: {self['preferred']}")
        return "\n".join(lines)

    def __repr__(self):
        return (f"ComparisonResult(preferred={self['preferred']!r}, "
                + ", ".join(f"{k}: BIC {r.bic:.2f}" for k, r in self["fits"].items()) + ")")


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

    def f00_rows(self, p):
        """F00 for many parameter vectors at once, like :meth:`dop_rows`."""
        return reference.brdf(self._fresnel(p), self._log_scale(p), self._diffuse(p))


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


@dataclass(frozen=True)
class Uncertainties:
    """Output of :func:`uncertainty_stage` (see :class:`FitResult` for the intervals)."""
    residuals: np.ndarray
    jacobian: np.ndarray
    chi2: float
    dof: int
    stderr: np.ndarray
    cov: np.ndarray
    corr: np.ndarray
    condition_number: float
    eig: tuple
    unit: float
    ci95: dict
    ci95_jacobian: dict
    ci95_profile: dict
    noise_floor: float | None = None  # the noise standard deviation assumed where the fit is exact


def _ranked(cands):
    """Candidates best first (a stable sort: ties keep their order)."""
    return sorted(cands, key=lambda c: c.sse)


def _fd_steps(x, hi):
    """scipy's '2-point' steps for ``x`` (any shape): relative step sqrt(eps), inwards at an
    upper bound, as actually taken (exactly representable)."""
    h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(x))
    h = np.where(x + h > hi, -h, h)
    return (x + h) - x


#: Step of the central differences of :func:`fd_jacobian`, as a fraction of each bound range.
CENTRAL_STEP = 1e-6


def fd_jacobian(rows, X, lo, hi, scheme="2-point"):
    """Finite-difference Jacobians of a batched residual function at P points at once, the points
    and all their steps in one call of ``rows`` ((B, d) parameter vectors -> (B, M) residuals).

    ``scheme`` "2-point": scipy's forward differences (:func:`_fd_steps`: relative step sqrt(eps),
    inwards at an upper bound); "central": steps of ``CENTRAL_STEP`` of each bound range either
    side, cut (one-sided) at a bound.  Returns (R, J): the residuals at ``X`` (P, M) and the
    Jacobians (P, d, M), ``J[p, j]`` the derivative along parameter j."""
    X = np.asarray(X, float)
    P, d = X.shape
    base = X[:, None, :]
    if scheme == "2-point":
        h = _fd_steps(X, hi)
        pts = np.concatenate([base, base + h[:, :, None] * np.eye(d)[None]], axis=1)
        R = rows(pts.reshape(-1, d)).reshape(P, d + 1, -1)
        return R[:, 0], (R[:, 1:] - R[:, :1]) / h[:, :, None]
    if scheme != "central":
        raise ValueError(f"scheme must be '2-point' or 'central', got {scheme!r}")
    h = CENTRAL_STEP * (hi - lo)
    up, dn = np.minimum(X + h, hi), np.maximum(X - h, lo)
    eye = np.eye(d, dtype=bool)[None]
    pts = np.concatenate([base, np.where(eye, up[:, None, :], base), np.where(eye, dn[:, None, :], base)], axis=1)
    R = rows(pts.reshape(-1, d)).reshape(P, 2 * d + 1, -1)
    return R[:, 0], (R[:, 1:d + 1] - R[:, d + 1:]) / (up - dn)[:, :, None]


def _lm_batch(resid_rows, X0, lo, hi, iterations):
    """Bounded Levenberg-Marquardt from P starts at once, every problem's trial point and its
    forward-difference Jacobian (:func:`fd_jacobian`, "2-point") in one batched call per
    iteration.  Levenberg damping in coordinates scaled to the bounds (a coordinate whose
    column vanishes, as k does at k = 0, gets no runaway step); a coordinate on a bound whose
    descent direction points outwards is held there, the others' steps are projected onto the
    bounds.  Returns (X, sse, row evaluations)."""
    X = np.clip(np.array(X0, float), lo, hi)
    P, d = X.shape
    span = hi - lo
    eye = np.eye(d)
    tol = 1e-12 * span

    def evaluate(X):
        r, J = fd_jacobian(resid_rows, X, lo, hi)
        J = J * span[None, :, None]  # in coordinates scaled to the bounds
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
            except np.linalg.LinAlgError:  # a singular problem (an overflowing or vanishing Jacobian):
                du = np.zeros_like(X)     # no step for it, more damping; the others step as alone
                for i in range(P):
                    try:
                        du[i] = -np.linalg.solve(A[i], g[i])
                    except np.linalg.LinAlgError:
                        pass
        du = np.where(np.isfinite(du), du, 0.0)
        Xt = np.clip(X + du * span, lo, hi)
        rt, Jt, sset = evaluate(Xt)
        ok = sset < sse
        X[ok], r[ok], J[ok], sse[ok] = Xt[ok], rt[ok], Jt[ok], sset[ok]
        lam = np.clip(np.where(ok, lam * 0.3, lam * 6.0), 1e-300, 1e300)
    return X, sse, P * (d + 1) * (iterations + 1)


class Residuals:
    """Weighted residuals of the reference model at one data set's geometry as a function of the
    free parameters: ``rows(X)`` maps a (B, d) array of parameter vectors (over ``free``) to the
    (B, M) residuals, (DOP - dop) / dop_std, then (F00 - f00) / f00_std when ``f00`` is given
    (then the ``kd`` of a vector is the ratio kd/ks).  Non-finite residuals become 1e150.

    ``model`` is a :class:`_Model` (the geometry), ``base`` the values of the other parameters."""

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

    def rows(self, X):
        p = self._with((n, X[:, j:j + 1]) for j, n in enumerate(self.free))
        r = (self.model.dop_rows(p) - self.dop) / self.dop_std
        if self.f00 is not None:
            r = np.concatenate([r, (self.model.f00_rows(p) - self.f00) / self.f00_std], axis=1)
        return _finite(r)


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


def _check_bounds(model, bounds, fixed):
    """Bounds (name -> (lo, hi)) of the model's parameters and the fixed values, checked against
    the domain rules of :data:`pbrdf_cl.compute.pointwise.RULES`."""
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
    for name, (lo, hi) in b.items():
        ok, rule = RULES[name]
        for end, v in (("low", lo), ("high", hi)):
            if not ok(v):
                raise ValueError(f"bounds: {name} {end} = {v} is outside the model's domain ({name} must be {rule})")
    fx = {}
    for name, v in (fixed or {}).items():
        if name not in DEFAULT_BOUNDS:
            raise ValueError(f"fixed: unknown parameter {name!r}; parameters are {', '.join(DEFAULT_BOUNDS)}")
        v = float(v)
        ok, rule = RULES[name]
        if not (np.isfinite(v) and ok(v)):
            raise ValueError(f"fixed: {name} = {v} is outside the model's domain ({name} must be {rule})")
        if name not in names and not (model == "six-param" and name == "ks"):
            raise ValueError(f"fixed: {name} is not a parameter of the {model} model")
        fx[name] = v
    return b, fx


def _check_fit_args(data, model, bounds, fixed, shadowing):
    """The checked inputs of :func:`fit`: (measurements, bounds, fixed values, free names)."""
    if model not in MODEL_PARAMS:
        raise ValueError(f"model must be one of {sorted(MODEL_PARAMS)}, got {model!r}")
    if shadowing not in reference.SHADOWING:
        raise ValueError(f"shadowing must be one of {sorted(reference.SHADOWING)}, got {shadowing!r}")
    meas = as_measurements(data)
    pointwise.check_degrees(meas.theta_i, meas.theta_r, f"{meas.source}: ")
    bnds, fx = _check_bounds(model, bounds, fixed)
    free = [n for n in MODEL_PARAMS[model] if n not in fx]
    if not free:
        raise ValueError("every parameter is fixed: nothing to fit")
    if len(meas) <= len(free):
        raise ValueError(f"{meas.source}: {len(meas)} measurements for {len(free)} free parameters "
                         f"({', '.join(free)}); at least {len(free) + 1} are needed")
    geometries = distinct_geometries(meas)
    if geometries < len(free):
        raise ValueError(f"{meas.source}: {geometries} distinct geometr{'y' if geometries == 1 else 'ies'} "
                         f"(theta_i, theta_r, phi) for {len(free)} free parameters ({', '.join(free)}): the data "
                         f"cannot determine them; measure more geometries or fix parameters (e.g. fixed="
                         f"{{'{free[-1]}': ...}}, --fix {free[-1]}=...)")
    return meas, bnds, fx, free


def distinct_geometries(meas):
    """How many distinct (theta_i, theta_r, phi) the measurements have (repeats add no geometry)."""
    return len(np.unique(np.column_stack([meas.theta_i, meas.theta_r, meas.phi]), axis=0))


def dop_resolution(dop, max_decimals=DOP_MAX_DECIMALS, axis=None):
    """The DOP resolution of the values: 10 ** -d for the fewest decimals d (at most
    ``max_decimals``) that write every value exactly, or 0.0 where none does; with ``axis``, of
    each slice along it (an array)."""
    dop = np.asarray(dop, float)
    res = 0.0
    for d in range(max_decimals, -1, -1):  # the fewest decimals that write every value win
        step = 10.0 ** -d
        res = np.where(np.all(np.abs(np.round(dop / step) * step - dop) <= 1e-9 * step, axis=axis), step, res)
    return res if axis is not None else float(res)


def dop_noise_floor(dop):
    """The smallest DOP noise standard deviation assumed without given uncertainties
    (:data:`DOP_NOISE_FLOOR`): the rounding error of the data's resolution, at least the default."""
    return max(DOP_NOISE_FLOOR, dop_resolution(dop) / np.sqrt(12.0))


def grid_stage(meas, free, axes, base, shadowing="paper", *, engine=None, backend="auto", progress=False):
    """(a) The objective on the grid ``axes`` (name -> nodes, one per free parameter) with the
    other parameters at ``base``, on the OpenCL device (float32), and its profiles."""
    import warnings
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # fit's argument check gives the radians warning, once
        warnings.simplefilter("ignore", pointwise.UnitsWarning)
        obj = dense.objective(meas.as_dict(), grid={**base, **axes}, k_best=1, dtype="float32", shadowing=shadowing,
                              engine=engine, backend=backend, progress=progress)
    sse = obj.sse.transpose(*free).values
    profiles = _grid_profiles(sse, free)
    return StageResult(GridStage(sse, axes, profiles), int(sse.size), time.perf_counter() - t0)


def _grid_point(axes, free, idx):
    return np.array([axes[n][i] for n, i in zip(free, idx)])


def basin_stage(grid, free, n_basins, rise, profile_seeds=PROFILE_SEEDS):
    """(b) Seeds: the grid's best ``n_basins`` local minima, one per neighbourhood, then up to
    ``profile_seeds`` valleys of its profiles that none of them lies in (behind a ridge at least
    ``rise`` high); ``grid`` is a :class:`GridStage`."""
    t0 = time.perf_counter()
    indices = _grid_basins(grid.sse, n_basins)
    indices += _profile_seeds(grid.sse, grid.profiles, free, indices, profile_seeds, rise)
    seeds = [_grid_point(grid.axes, free, idx) for idx in indices]
    steps = [np.array([_local_spacing(grid.axes[n], i) for n, i in zip(free, idx)]) for idx in indices]
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
    """Batched Levenberg-Marquardt descent (:func:`_lm_batch`) of every candidate (BOBYQA's
    ranking in a long flat valley says little about its floor); each candidate moves where the
    descent improved it, in the same order."""
    t0 = time.perf_counter()
    X, sse, rows = _lm_batch(resid_rows, np.array([c.x for c in cands]), lo, hi, iterations)
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


def uncertainty_stage(residuals, x, lo, hi, grid, dop_sse, n_points, sigma_known, noise_floor=None):
    """(e) Statistics and uncertainties at the optimum ``x`` of ``residuals`` (names
    ``residuals.free``): the central-difference Jacobian, covariance, and the three kinds of
    95% interval of :class:`FitResult`; ``grid`` is the :class:`GridStage`, ``dop_sse`` the
    DOP-only objective at the optimum (the grid's scale), ``n_points`` the measurements.

    Without known uncertainties the noise variance is estimated as chi2 / dof; where that is
    below ``noise_floor ** 2`` (see :data:`DOP_NOISE_FLOOR`) the noise is taken as known, of
    standard deviation ``noise_floor`` (``Uncertainties.noise_floor`` says so)."""
    from scipy.stats import norm, t as student_t
    t0 = time.perf_counter()
    names = residuals.free
    R, J = fd_jacobian(residuals.rows, x[None], lo, hi, "central")
    r, J = R[0], J[0].T
    dof = r.size - len(names)
    chi2 = float(r @ r)
    s2 = 1.0 if sigma_known else chi2 / dof
    unit = 1.0 if sigma_known else dop_sse / dof  # one unit of chi^2 on the DOP-only SSE scale
    floored = not sigma_known and noise_floor is not None and not s2 >= noise_floor ** 2
    if floored:  # an (almost) exact fit: the noise is taken as known, at the floor
        s2 = unit = float(noise_floor) ** 2
    known = sigma_known or floored
    cov, cond, eig = _covariance(J, s2, hi - lo)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    # with known uncertainties the Gaussian quantile, else Student's t on the residual dof
    dist = norm if known else student_t(dof)
    q = float(dist.ppf(0.975))
    # never narrower than the optimizer's resolution (noise-free data would give a zero width)
    resolution = X_RESOLUTION * (hi - lo)
    half = np.maximum(q * se, resolution)
    ci_jac = {n: (max(lo[i], x[i] - half[i]), min(hi[i], x[i] + half[i])) for i, n in enumerate(names)}
    # likelihood-ratio intervals from the profile of the grid objective (banana-shaped valleys
    # are not ellipses)
    ci_prof = _profile_intervals(grid.profiles, grid.axes, dop_sse + 3.84 * unit)
    ci = _posterior_intervals(names, J, x, se, lo, hi, grid, dist, resolution / q, n_points, known,
                              s2 if floored else 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    out = Uncertainties(r, J, chi2, dof, se, cov, corr, float(cond), eig, unit, ci, ci_jac, ci_prof,
                        noise_floor if floored else None)
    return StageResult(out, 2 * len(names) + 1, time.perf_counter() - t0)


def _posterior_intervals(names, J, x, se, lo, hi, grid, dist, min_se, n_points, sigma_known, chi2_unit=1.0):
    """95% intervals: the posterior under a uniform prior over the bounds, the equal mixture of
    the local (Laplace) approximation and the grid's profile (where the grid resolves it; its
    SSE divided by ``chi2_unit`` is chi^2 when ``sigma_known``)."""
    ci = {}
    col = np.linalg.norm(J, axis=0)
    for i, n in enumerate(names):
        # a direction the DOP does not depend on at all has no finite standard error
        se_i = np.inf if col[i] <= 1e-12 * max(col.max(), 1e-300) else max(se[i], min_se[i])
        cdfs = [_truncated_cdf(dist, x[i], se_i, lo[i], hi[i])]
        if n in grid.axes:
            # the grid's profile counts where the grid resolves it: its own 95% interval spans
            # several cells (a valley, a banana, a flat stretch); else it only says "near the
            # best node", which the local approximation says better
            prof, vals = grid.profiles[n], grid.axes[n]
            g = _grid_cdf(prof / chi2_unit, vals, n_points, sigma_known)
            g_a, g_b = _central_interval([g], x[i], se_i, lo[i], hi[i], vals)
            if g_b - g_a >= GRID_RESOLVED_CELLS * _local_spacing(vals, int(np.argmin(prof))):
                cdfs.append(g)
        ci[n] = _central_interval(cdfs, x[i], se_i, lo[i], hi[i], grid.axes.get(n, ()))
    return ci


def _model_notes(model, fx, use_f00, meas):
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
    return notes


def _ambiguous_basins(cands, free, unit, se):
    """The other candidates within one unit of chi^2 of the best and more than 2 standard errors
    away from it in some parameter (dicts of their parameters and SSE)."""
    best = cands[0]
    out = []
    for c in cands[1:]:
        if c.sse - best.sse <= unit and np.any(np.abs(c.x - best.x) > 2 * np.maximum(se[:len(free)], 1e-12)):
            out.append(dict(zip(free, map(float, c.x)), sse=float(c.sse)))
    return out


#: FitResult.status -> message (scipy's convention: success is status > 0).
FIT_STATUS = {
    1: "converged: the local stages met their tolerances",
    2: "converged: least squares ran out of evaluations along a flat valley and BOBYQA finished (it stopped "
       "improving)",
    0: "stopped: an evaluation budget ran out while the objective was still falling; the result is the best "
       "point found",
    -1: "failed: the model's residuals are not finite at any candidate",
}


def _fit_status(best, final_ran, intensity):
    """FitResult.status from the best candidate, whether the final BOBYQA ran, and the intensity
    stage's candidate (or None)."""
    last = intensity if intensity is not None else best
    if not last.sse < 1e300:
        return -1
    if last.converged is False:
        return 0
    return 2 if final_ran else 1


def fit(data, model="six-param", bounds=None, fixed=None, shadowing="paper", *, grid_shape=None, n_basins=6,
        engine=None, backend="auto", progress=False):
    """Fit the model to measured DOP (and F00 where given): the pipeline of stages of this module.

    Parameters
    ----------
    data : str or path, dict, DataFrame, xarray.Dataset or Measurements
        The measurements: theta_i, theta_r (degrees), dop, and optionally phi (default 180),
        dop_std (weights 1/dop_std^2), f00 (or s0) and f00_std; a CSV path with those columns.
    model : {"six-param", "specular"}, default "six-param"
        "six-param": n, k, sigma, kd/ks, c (ks = 1 unless an intensity column separates it);
        "specular": the paper's ref. [7], n and k only.
    bounds : dict, optional
        Name -> (low, high); defaults n [1, 5], k [0, 10], sigma [0.05, 1], kd [0, 5], c [-1, 0], ks [1e-3, 1e3].
    fixed : dict, optional
        Name -> value of parameters held fixed (e.g. ``{"sigma": 0.45}``).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function of the model fitted.
    grid_shape : dict, optional
        Name -> nodes of the device grid stage (defaults :data:`DEFAULT_GRID`, :data:`SPECULAR_GRID`).
    n_basins : int, default 6
        How many distinct basins of the grid the local stages start from.
    engine : pbrdf_cl.Engine, optional
        Where the grid stage runs; ``backend`` ("auto", "opencl", "numpy") as for :func:`pbrdf_cl.dop`.
    progress : bool, default False
        A progress bar for the grid stage.

    Returns
    -------
    FitResult
        ``x``, ``stderr``, ``ci95`` (and two other kinds of interval), ``corr``/``cov`` (labelled),
        ``sse``, ``chi2``, ``p_value``, ``r2``, ``fits_data``, ``aic``, ``bic``, ``notes``,
        ``success``/``status``/``message``, per-stage ``nfev`` and ``seconds``; ``summary()``.

    Raises
    ------
    ValueError
        For bad arguments, and for data that cannot determine the free parameters (fewer distinct
        geometries than free parameters), naming the counts.

    Examples
    --------
    >>> import pbrdf_cl
    >>> res = pbrdf_cl.fit("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> res.x["n"], res.ci95["n"], res.fits_data  # doctest: +SKIP
    """
    meas, bnds, fx, free = _check_fit_args(data, model, bounds, fixed, shadowing)
    base = {**MODEL_FIXED[model], **fx}
    lo, hi = np.array([bnds[n][0] for n in free]), np.array([bnds[n][1] for n in free])
    std = meas.dop_std if meas.dop_std is not None else np.ones(len(meas))
    mdl = _Model(meas, shadowing)
    dop_resid = Residuals(mdl, free, base, meas.dop, std)
    rows = dop_resid.rows
    shape = {**(SPECULAR_GRID if model == "specular" else DEFAULT_GRID), **(grid_shape or {})}
    axes = {n: _grid_axis(n, bnds[n], int(shape[n])) for n in free}
    st = {"grid": grid_stage(meas, free, axes, base, shadowing, engine=engine, backend=backend, progress=progress)}
    grid = st["grid"].value
    # a ridge of at least one unit of chi^2 between valleys; without given uncertainties the
    # unit is estimated from the grid
    rise = 1.0 if meas.dop_std is not None else float(grid.sse.min()) / (len(meas) - len(free))
    st["basins"] = basin_stage(grid, free, n_basins, rise, PROFILE_SEEDS)
    basins = st["basins"].value
    # the basins' optimisers of each stage run in lockstep, their evaluations batched
    st["direct"] = direct_stage(rows, lo, hi, basins.seeds, basins.steps, DIRECT_EVALS)
    st["bobyqa"] = bobyqa_stage(rows, lo, hi, st["direct"].value, basins.steps, BOBYQA_EVALS)
    # every candidate, and the best grid point of each bound slice (this model's optimum often
    # sits on a bound: k = 0, n = 1, sigma = 1, kd = 0), descends its valley
    edges = [_grid_point(axes, free, idx) for idx in _bound_seeds(grid.sse, basins.indices)]
    st["screen"] = screen_stage(rows, lo, hi, _ranked(st["bobyqa"].value) + [Candidate(np.inf, x, x) for x in edges],
                                SCREEN_ITERATIONS)
    cands = _ranked(st["screen"].value)
    top = min(LS_POLISH, len(cands))  # the best candidates, least squares to the end
    st["least_squares"] = least_squares_stage(rows, lo, hi, cands[:top], LS_MAX_NFEV)
    cands = _ranked(st["least_squares"].value + cands[top:])
    final_ran = cands[0].converged is False
    st["final_bobyqa"] = (final_bobyqa_stage(rows, lo, hi, cands[0], FINAL_BOBYQA) if final_ran
                          else StageResult(cands[0], 0, 0.0))
    cands[0] = best = st["final_bobyqa"].value

    use_f00 = meas.f00 is not None and model == "six-param" and "ks" not in fx and "kd" not in fx
    resid, x_final, lo_f, hi_f = dop_resid, best.x, lo, hi
    if use_f00:
        f00_std = meas.f00_std if meas.f00_std is not None else F00_REL_STD * np.maximum(meas.f00, 1e-300)
        ks_bounds = bnds.get("ks", DEFAULT_BOUNDS["ks"])
        ks0 = intensity_start(mdl, dop_resid.params(best.x), meas.f00, f00_std, ks_bounds)
        resid = Residuals(mdl, free + ["ks"], base, meas.dop, std, meas.f00, f00_std)
        lo_f, hi_f = np.append(lo, ks_bounds[0]), np.append(hi, ks_bounds[1])
        spacing = np.array([np.median(np.diff(axes[n])) for n in free])
        st["intensity"] = intensity_stage(resid, lo_f, hi_f, np.append(best.x, ks0), np.append(spacing, ks0 * 0.1),
                                          INTENSITY_MAXEVAL)
        x_final = st["intensity"].value.x
    floor = dop_noise_floor(meas.dop) if meas.dop_std is None else None
    unc = uncertainty_stage(resid, x_final, lo_f, hi_f, grid, best.sse, len(meas), meas.dop_std is not None,
                            floor).value
    status = _fit_status(best, final_ran, st["intensity"].value if use_f00 else None)
    return _fit_result(meas, model, shadowing, resid, x_final, lo_f, hi_f, unc, cands, grid, st, status,
                       _model_notes(model, fx, use_f00, meas))


def _fit_result(meas, model, shadowing, resid, x, lo, hi, unc, cands, grid, stages, status, notes):
    """The :class:`FitResult` of :func:`fit` from its stages' outputs."""
    names, free = list(resid.free), list(grid.axes)
    sigma_known = meas.dop_std is not None
    p = resid.params(x)
    dop_resid = resid.model.dop(p) - meas.dop
    m_obs, n_free = unc.residuals.size, len(names)
    # -2 log-likelihood up to a constant: chi^2 with known sigmas, else m log(SSE / m)
    neg2ll = unc.chi2 if sigma_known else m_obs * np.log(max(unc.chi2, 1e-300) / m_obs)
    aic, bic = neg2ll + 2 * n_free, neg2ll + n_free * np.log(m_obs)
    fits_data, p_value, r2, first = _goodness(meas, dop_resid, unc, sigma_known)
    notes = first + _convention_notes(meas) + notes + _bound_notes(names, x, lo, hi, unc.ci95)
    notes += _identifiability_notes(names, unc.jacobian, unc.condition_number, unc.eig, x, unc.stderr, unc.corr,
                                    hi - lo)
    if unc.noise_floor is not None:
        notes.append(f"the fit is (nearly) exact: the noise estimated from the residuals (std "
                     f"{np.sqrt(unc.chi2 / unc.dof):.2g}) is below the noise floor, so the uncertainties assume "
                     f"DOP noise of std {unc.noise_floor:.2g} (the larger of the data's DOP resolution "
                     f"{dop_resolution(meas.dop):g} / sqrt(12) and {DOP_NOISE_FLOOR:g}); give a dop_std column "
                     "to set it")
    ambiguous = _ambiguous_basins(cands, free, unc.unit, unc.stderr)
    if ambiguous:
        alt = ", ".join(f"{n}={ambiguous[0][n]:.4g}" for n in free)
        notes.append(f"ambiguous: another basin fits equally well ({alt}: its objective, the weighted sum of "
                     f"squares the local stages minimise, is {ambiguous[0]['sse']:.4g} against the best's "
                     f"{cands[0].sse:.4g}, within one unit of chi2, {unc.unit:.3g}); the data cannot decide "
                     "between them")
    x_out = {n: float(p[n]) for n in ("n", "k", "sigma", "ks", "kd", "c")}
    kd_ratio = x_out["kd"] / x_out["ks"]
    if model == "specular":
        x_out = {n: x_out[n] for n in ("n", "k")}
    return FitResult(
        model=model, shadowing=shadowing, x=x_out, kd_ratio=float(kd_ratio) if model == "six-param" else None,
        free=names, sse=float(dop_resid @ dop_resid), chi2=unc.chi2,
        reduced_chi2=unc.chi2 / unc.dof, rmse=float(np.sqrt(np.mean(dop_resid ** 2))), residuals=dop_resid,
        dof=unc.dof, n_points=len(meas), stderr=dict(zip(names, map(float, unc.stderr))), ci95=unc.ci95,
        ci95_jacobian=unc.ci95_jacobian, ci95_profile=unc.ci95_profile,
        profiles={n: dict(values=grid.axes[n], sse=grid.profiles[n]) for n in free},
        corr=_labelled(unc.corr, names, "correlation"), cov=_labelled(unc.cov, names, "covariance"),
        fits_data=fits_data, p_value=p_value, r2=r2,
        condition_number=unc.condition_number, aic=float(aic), bic=float(bic),
        nfev={k: s.nfev for k, s in stages.items()}, seconds={k: s.seconds for k, s in stages.items()},
        basins=[dict(zip(free, map(float, c.x)), sse=float(c.sse), seed=dict(zip(free, map(float, c.seed))))
                for c in cands],
        ambiguous=ambiguous, notes=notes, sigma_known=sigma_known,
        success=status > 0, status=status, message=FIT_STATUS[status])


def _finite(r):
    """Residuals with non-finite entries replaced by a huge value (never NaN to the optimisers)."""
    return np.where(np.isfinite(r), r, 1e150)




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
    pairs = sorted(((abs(corr[i, j]), i, j) for i in range(len(names)) for j in range(i + 1, len(names))
                    if np.isfinite(corr[i, j]) and abs(corr[i, j]) > 0.95), key=lambda t: -t[0])
    if pairs:
        shown = ", ".join(f"{names[i]}-{names[j]} (r = {corr[i, j]:+.3f})" for _, i, j in pairs[:MAX_CORR_NOTES])
        more = f", and {len(pairs) - MAX_CORR_NOTES} more (see .corr)" if len(pairs) > MAX_CORR_NOTES else ""
        notes.append(f"strongly correlated: {shown}{more}")
    return notes


#: How many of the strongest correlations the notes name.
MAX_CORR_NOTES = 3
#: With given uncertainties, a chi2 whose p-value is below this says the model does not fit.
GOODNESS_P = 1e-3
#: Without them, a fit that explains less than this fraction of the DOP's variance does not fit.
GOODNESS_R2 = 0.9
_CAUSES = ("angles in radians (pbrdf-cl takes degrees), the phi convention (180 is in plane, the specular side; "
           "SCATMECH's 0), another shadowing variant (shadowing=), DOP in percent or dop_std too small")


def _goodness(meas, dop_resid, unc, sigma_known):
    """(fits, p-value or None, R^2 or None, notes): whether the model describes the data, by chi2
    against its degrees of freedom with given uncertainties, else by the residuals against the
    data's spread."""
    from scipy.stats import chi2 as chi2_dist
    sst = float(np.sum((meas.dop - meas.dop.mean()) ** 2))
    r2 = 1.0 - float(dop_resid @ dop_resid) / sst if sst > 0 else None
    p = float(chi2_dist.sf(unc.chi2, unc.dof)) if sigma_known and unc.dof > 0 else None
    if p is not None and p < GOODNESS_P:
        return False, p, r2, [f"the model does not describe these data: chi2 = {unc.chi2:.4g} for {unc.dof} degrees "
                              f"of freedom (p = {p:.2g}); usual causes: {_CAUSES}"]
    if p is None and r2 is not None and r2 < GOODNESS_R2:
        return False, p, r2, [f"the model does not describe these data: it explains {max(r2, 0):.0%} of the DOP's "
                              f"variance (RMSE {np.sqrt(np.mean(dop_resid ** 2)):.3g} against the data's spread "
                              f"{np.sqrt(sst / len(meas)):.3g}); usual causes: {_CAUSES}"]
    return True, p, r2, []


def _convention_notes(meas):
    """The unit and convention mistakes the data show by themselves."""
    notes = []
    hi = pointwise.radians_suspect(meas.theta_i, meas.theta_r)
    if hi is not None:
        notes.append(f"every theta_i and theta_r lies below {pointwise.RADIANS_HINT} degrees (the largest is {hi:.4g}): "
                     "radians? pbrdf-cl takes degrees")
    if not meas.phi_given:
        from ..io.measurements import PHI_DEFAULT_NOTE
        notes.append(PHI_DEFAULT_NOTE)
    if np.all(meas.phi == 0.0):
        notes.append("phi = 0 for every point: that is the plane of incidence on the source's side (back-"
                     "scattering); in-plane specular data have phi = 180 here (SCATMECH's phi = 0 is our 180)")
    return notes


def _bound_notes(names, x, lo, hi, ci95):
    """A note for each parameter on a bound, and for a best value outside its own 95% interval."""
    notes = []
    for i, n in enumerate(names):
        tol = 1e-6 * (hi[i] - lo[i])
        side = "lower" if x[i] <= lo[i] + tol else ("upper" if x[i] >= hi[i] - tol else None)
        a, b = ci95[n]
        if side:
            notes.append(f"{n} = {x[i]:.4g} is on its {side} bound: the data push it there (the optimum may lie "
                         "beyond; widen the bounds if that is physical)")
        if not a <= x[i] <= b:
            notes.append(f"{n}'s best value {x[i]:.4g} lies outside its 95% interval [{a:.4g}, {b:.4g}]: the "
                         "interval is the central 95% of the posterior over the bounds, and where the data barely "
                         "determine a parameter its best fit is arbitrary and often at an edge; quote the interval")
    return notes


def _labelled(matrix, names, what):
    """``matrix`` over the free parameters as an ``xarray.DataArray`` with their names on both axes."""
    import xarray as xr
    return xr.DataArray(np.asarray(matrix), dims=("param", "param_2"), coords={"param": list(names),
                        "param_2": list(names)}, name=what)


def compare_models(data, shadowing="paper", bounds=None, fixed=None, engine=None, backend="auto", progress=False):
    """Fit the six-parameter model and the ref. [7] specular model to the same data and compare them.

    Parameters
    ----------
    data, shadowing, bounds, fixed, engine, backend, progress
        As for :func:`fit`; the specular fit takes the bounds and fixed values of n and k only.

    Returns
    -------
    ComparisonResult
        "six-param" and "specular" FitResults (also in ``fits``), "preferred" (the lower BIC),
        "table" (Markdown: n, k, free parameters, SSE, AIC, BIC) and ``summary()``.

    Examples
    --------
    >>> both = pbrdf_cl.compare_models("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> both.preferred  # doctest: +SKIP
    'six-param'
    """
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
    return ComparisonResult({"six-param": six, "specular": spec, "preferred": preferred, "table": "\n".join(rows),
                             "fits": {"six-param": six, "specular": spec}})
