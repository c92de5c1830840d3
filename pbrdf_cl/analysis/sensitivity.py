"""Global sensitivity maps: Sobol' indices and Morris screening of the model over geometry axes.

Variance-based sensitivity (Sobol' indices) answers "which parameter controls the signal, and
where": at every geometry of a grid, the share of the variance of the DOP (or F00) over a box of
materials that each parameter explains alone (first order, ``S1``) and with all its
interactions (total, ``ST``).  The model runs are what SALib leaves to its user; here they are
one dense evaluation on the device, the sample sets times the geometries
(:func:`pbrdf_cl.compute.dense.outer`), and the estimators are those of ``SALib.analyze.sobol`` and
``SALib.analyze.morris``, vectorised over the geometries: the bootstrap's resamples become one
matrix product (the resample counts times the per-sample terms of every geometry).

* Samples come from SALib's samplers (``SALib.sample.sobol``: Saltelli's scheme over a scrambled
  Sobol' sequence; ``SALib.sample.morris``) with the given ``seed``; the same seed draws the
  bootstrap resamples exactly as SALib's analysers do, so with float64 the indices and their
  confidence intervals equal SALib's run on the same outputs (``tests/test_sensitivity.py``).
* A log-uniform range is sampled uniformly in log(value) (the indices are then those of the
  log-uniform distribution).
* Memory: the geometries run in blocks within ``memory_budget`` (the outputs of a block and the
  estimators' terms); a progress bar over the geometries when it takes more than a second.
"""
from __future__ import annotations

import numbers
import time

import numpy as np

from ..compute import pointwise
from ..compute.dense import DEFAULTS, LONG_NAMES, PARAMETERS, outer, progress_bar
from ..device.engine import DTYPES, resolve_engine
from ..errors import SensitivityWarning
from ..io.results import compatible
from ..model import inputs, quantities

GEOMETRY = inputs.GEOMETRY
#: Bootstrap resamples and confidence level of the intervals (SALib's defaults).
NUM_RESAMPLES = 100
CONF_LEVEL = 0.95
DEFAULT_BUDGET = "512 MiB"
METHODS = ("sobol", "morris")
#: Quantities with a sensitivity map: one value per point, not an angle (a wrapped angle has no
#: meaningful variance decomposition).
SCALAR = tuple(n for n, q in quantities.REGISTRY.items() if q.width == 1 and q.period is None)


class Range:
    """One parameter's range: ``low``, ``high`` and ``scale`` ("linear" or "log")."""

    def __init__(self, name, low, high, scale="linear"):
        self.name, self.low, self.high, self.scale = name, float(low), float(high), scale

    @property
    def bounds(self):
        """The sampler's bounds: the values, or their logarithms for a log-uniform range."""
        return [np.log(self.low), np.log(self.high)] if self.scale == "log" else [self.low, self.high]

    def values(self, u):
        """Sampler values (in :attr:`bounds`) to parameter values."""
        return np.exp(u) if self.scale == "log" else u

    def __repr__(self):
        return f"{self.name} in [{self.low:g}, {self.high:g}]" + (" (log-uniform)" if self.scale == "log" else "")


def _hint(name, names):
    """``"; did you mean 'sigma'?"`` for a near miss of one of ``names``, else ``""``."""
    from ..ranges import did_you_mean
    near = did_you_mean(str(name), [n.lower() for n in names])
    near = next((n for n in names if n.lower() == near), None) if near else None
    return f" (did you mean {near!r}?)" if near else ""


def _number(where, v):
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise ValueError(f"{where}: {v!r} is not a number")
    v = float(v)
    if not np.isfinite(v):
        raise ValueError(f"{where}: {v!r} is not finite")
    return v


def check_ranges(ranges, where="ranges"):
    """``{name: (low, high)}`` (or ``(low, high, "log")``, or ``{"low", "high", "scale"}``) ->
    a tuple of :class:`Range` in the model's parameter order, each checked against the model's
    domain (``pointwise.RULES``); a ``ValueError`` naming the parameter and the value otherwise."""
    if not isinstance(ranges, dict) or not ranges:
        raise ValueError(f"{where}: give a dict of parameter -> (low, high), e.g. "
                         "{'n': (1.2, 2.5), 'k': (0.01, 3, 'log')}")
    out = {}
    for name, spec in ranges.items():
        if name not in PARAMETERS:
            raise ValueError(f"{where}: unknown parameter {name!r}{_hint(name, PARAMETERS)}; "
                             f"valid names are {', '.join(PARAMETERS)}")
        field = f"{where}[{name!r}]"
        if isinstance(spec, dict):
            extra = set(spec) - {"low", "high", "scale"}
            if extra or not {"low", "high"} <= set(spec):
                raise ValueError(f"{field}: a table takes low, high and optionally scale, got {sorted(spec)}")
            low, high, scale = spec["low"], spec["high"], spec.get("scale", "linear")
        elif isinstance(spec, (list, tuple)) and len(spec) in (2, 3):
            low, high = spec[0], spec[1]
            scale = spec[2] if len(spec) == 3 else "linear"
        else:
            raise ValueError(f"{field}: {spec!r} is not (low, high) or (low, high, 'log')")
        low, high = _number(f"{field} low", low), _number(f"{field} high", high)
        if scale not in ("linear", "log"):
            raise ValueError(f"{field}: scale must be 'linear' or 'log', got {scale!r}")
        if not low < high:
            raise ValueError(f"{field}: low must be below high, got ({low:g}, {high:g})")
        pointwise.check_values(name, np.array([low, high]))
        if scale == "log" and low <= 0:
            raise ValueError(f"{field}: a log-uniform range needs low > 0, got {low:g}")
        out[name] = Range(name, low, high, scale)
    return tuple(out[n] for n in PARAMETERS if n in out)


def check_fixed(fixed, ranged, where="fixed"):
    """The values of the parameters without a range: ``fixed``, else the defaults (ks 1, kd 0,
    c 0); n, k and sigma have none.  A ``ValueError`` for a parameter given twice or missing."""
    fixed = dict(fixed or {})
    for name in fixed:
        if name not in PARAMETERS:
            raise ValueError(f"{where}: unknown parameter {name!r}{_hint(name, PARAMETERS)}; "
                             f"valid names are {', '.join(PARAMETERS)}")
        if name in ranged:
            raise ValueError(f"{where}: {name!r} has a range and a fixed value; give one")
    missing = [n for n in PARAMETERS if n not in ranged and n not in fixed and n not in DEFAULTS]
    if missing:
        raise ValueError(f"{' and '.join(missing)} need{'s' if len(missing) == 1 else ''} a range or a fixed "
                         f"value (no default)")
    out = {}
    for name in PARAMETERS:
        if name in ranged:
            continue
        if name in fixed:
            a = np.asarray(fixed[name], dtype=object)
            if a.ndim:
                raise ValueError(f"{where}[{name!r}] must be a single value, got shape {a.shape}")
            v = _number(f"{where}[{name!r}]", fixed[name])
            pointwise.check_values(name, v)
            out[name] = v
        else:
            out[name] = float(DEFAULTS[name])
    return out


def check_geometry(geometry, where="geometry", defaults=(("phi", 180.0),)):
    """``{theta_i, theta_r, phi: values}`` (a number, a 1-d sequence or a range string such as
    ``"0:85@64"``) -> ``(axes, scalars)``: the axes with more than one value (name -> float64
    array, in the order theta_i, theta_r, phi) and the single values.  theta_i and theta_r are
    required; phi defaults to 180 (in plane)."""
    from .. import ranges as rg
    if not isinstance(geometry, dict):
        raise ValueError(f"{where}: give a dict of theta_i, theta_r (and phi) -> angles in degrees")
    values = dict(defaults)
    for name, v in geometry.items():
        if name not in GEOMETRY:
            raise ValueError(f"{where}: unknown axis {name!r}{_hint(name, GEOMETRY)}; valid names are "
                             f"{', '.join(GEOMETRY)}")
        values[name] = v
    axes, scalars = {}, {}
    for name in GEOMETRY:
        if name not in values:
            raise ValueError(f"{where}: {name} is required (degrees)")
        v = values[name]
        if isinstance(v, str):
            try:
                a = rg.parse_values(v, label=f"{where}[{name!r}] = {v!r}")
            except rg.RangeError as exc:
                raise ValueError(str(exc)) from None
        else:
            a = np.asarray(v, dtype=object)
            if a.ndim > 1:
                raise ValueError(f"{where}[{name!r}] must be a number or a 1-d sequence, got shape {a.shape}")
            if a.size == 0:
                raise ValueError(f"{where}[{name!r}] is empty")
            a = np.array([_number(f"{where}[{name!r}][{i}]" if a.ndim else f"{where}[{name!r}]", x)
                          for i, x in enumerate(a.reshape(-1))])
        pointwise.check_values(name, a)
        if a.size == 1 and (isinstance(v, numbers.Real) or np.ndim(v) == 0):
            scalars[name] = float(a[0])
        else:
            axes[name] = a
    zenith = [axes[n] if n in axes else scalars[n] for n in ("theta_i", "theta_r")]
    pointwise.check_degrees(*zenith, where=f"{where}: ")  # once, both angles together
    return axes, scalars


def geometry_list(axes, scalars):
    """The geometries of the product of ``axes`` (the single values broadcast), flattened in C
    order: name -> array of G values, and the grid's shape."""
    shape = tuple(a.size for a in axes.values())
    mesh = np.meshgrid(*axes.values(), indexing="ij") if axes else []
    flat = dict(zip(axes, (m.reshape(-1) for m in mesh)))
    G = int(np.prod(shape, dtype=np.int64))
    return {n: flat[n] if n in flat else np.full(G, scalars[n]) for n in GEOMETRY}, shape


def _problem(rngs):
    return {"num_vars": len(rngs), "names": [r.name for r in rngs], "bounds": [r.bounds for r in rngs]}


def parameter_sets(X, rngs, fixed):
    """Sampler rows ``X`` (runs, D) in the sampler's space -> the six parameter arrays."""
    S = X.shape[0]
    out = {n: np.full(S, v) for n, v in fixed.items()}
    for j, r in enumerate(rngs):
        out[r.name] = r.values(X[:, j])
    return {n: out[n] for n in PARAMETERS}


def _counts(idx, n):
    """Bootstrap resample index arrays ``idx`` (R, n) -> how often each sample is drawn (R, n)."""
    R = idx.shape[0]
    flat = (idx + n * np.arange(R)[:, None]).reshape(-1)
    return np.bincount(flat, minlength=R * n).reshape(R, n).astype(np.float64)


def _std1(a, axis=0):
    return a.std(axis=axis, ddof=1)


class _SobolTerms:
    """The Sobol' estimators of ``SALib.analyze.sobol`` for a block of geometries: every index is
    a ratio of means of per-sample terms over the N base samples, so the estimate is one sum over
    the samples and the bootstrap's R resamples are one product (R, N) @ (N, G x terms)."""

    def __init__(self, D, N, second_order, W, Z):
        self.D, self.N, self.second_order, self.W, self.Z = D, N, second_order, W, Z
        self.step = 2 * D + 2 if second_order else D + 2
        self.pairs = [(j, k) for j in range(D) for k in range(j + 1, D)] if second_order else []
        self.C = 4 + 2 * D + len(self.pairs)

    def block_bytes(self, runs, itemsize=8):
        """Bytes per geometry beyond its outputs: the terms (N x C float64, and their float32 copy for
        float32 outputs), the centred AB columns and the resampled sums."""
        return (8 * (self.N * (self.C + self.D + 2) + 3 * self.W.shape[0] * self.C)
                + (4 * self.N * self.C if itemsize == 4 else 0))

    def __call__(self, Y):
        """``Y`` (G, runs) -> dict of S1, ST, S1_conf, ST_conf (D, G) (and S2, S2_conf (D, D, G)).

        SALib first normalises the outputs of a geometry by their mean and standard deviation;
        the standard deviation cancels from every index, so only the mean is subtracted here
        (and SALib's tests for a constant output are scaled by it)."""
        D, N = self.D, self.N
        G = Y.shape[0]
        mean = Y.mean(axis=1, dtype=np.float64)
        Y3 = Y.reshape(G, N, self.step)
        T = np.empty((G, self.C, N))  # the per-sample terms, sample index last (contiguous)
        A, B = T[:, 0], T[:, 1]
        np.subtract(Y3[:, :, 0], mean[:, None], out=A)
        np.subtract(Y3[:, :, self.step - 1], mean[:, None], out=B)
        np.multiply(A, A, out=T[:, 2])
        np.multiply(B, B, out=T[:, 3])
        AB = np.empty((D, G, N))
        squares = T[:, 2].sum(axis=1) + T[:, 3].sum(axis=1)  # of every run about the mean: the scale
        for j in range(D):
            np.subtract(Y3[:, :, j + 1], mean[:, None], out=AB[j])
            squares += np.einsum("gn,gn->g", AB[j], AB[j])
            np.subtract(AB[j], A, out=T[:, 4 + D + j])
            np.multiply(B, T[:, 4 + D + j], out=T[:, 4 + j])
            np.square(T[:, 4 + D + j], out=T[:, 4 + D + j])
        if self.second_order:
            BA = [Y3[:, :, j + 1 + D] - mean[:, None] for j in range(D)]
            squares += sum(np.einsum("gn,gn->g", x, x) for x in BA)
            for p, (j, k) in enumerate(self.pairs):
                T[:, 4 + 2 * D + p] = BA[j] * AB[k] - A * B
            del BA
        del AB
        scale = np.sqrt(squares / Y.shape[1])  # Y's standard deviation per geometry
        ptp = np.maximum(A.max(axis=1), B.max(axis=1)) - np.minimum(A.min(axis=1), B.min(axis=1))
        eps = np.finfo(float).eps
        with np.errstate(invalid="ignore"):
            varies = ptp > eps * scale  # SALib: ptp of the normalised output > eps (False for a constant one)
        full = T.sum(axis=2)[None]  # (1, G, C)
        # the resamples' sums; in float32 for float32 outputs (an interval needs a few digits)
        Tb = T.reshape(G * self.C, N)
        if Y.dtype == np.float32:
            Tb = Tb.astype(np.float32)
        boot = np.moveaxis((Tb @ self.W.T.astype(Tb.dtype)).reshape(G, self.C, -1), 2, 0)
        boot = boot.astype(np.float64)  # (R, G, C)
        del Tb
        del T
        est = [self._indices(x, varies, scale) for x in (full, boot)]
        out = {"S1": est[0][0][:, 0], "ST": est[0][1][:, 0],
               "S1_conf": self.Z * _std1(est[1][0], axis=1), "ST_conf": self.Z * _std1(est[1][1], axis=1),
               "constant": ~varies}
        if self.second_order:
            s2, s2c = (np.full((D, D, G), np.nan) for _ in range(2))
            for p, (j, k) in enumerate(self.pairs):
                s2[j, k], s2c[j, k] = est[0][2][p][0], self.Z * _std1(est[1][2][p])
            out["S2"], out["S2_conf"] = s2, s2c
        return out

    def _indices(self, s, varies, scale):
        """Sums ``s`` (R, G, C) over the samples (or a resample) -> first, total (D, R, G) and the
        second-order estimates (pairs, R, G), zero where the output does not vary (as SALib)."""
        D, N = self.D, self.N
        mean = (s[..., 0] + s[..., 1]) / (2 * N)
        var = (s[..., 2] + s[..., 3]) / (2 * N) - mean ** 2  # np.var over A and B together
        with np.errstate(invalid="ignore"):
            ok = varies[None] & (var > np.finfo(float).eps * scale ** 2)
        safe = np.where(ok, var, 1.0)

        def ratio(num):
            return np.where(ok, num / safe, 0.0)
        first = np.stack([ratio(s[..., 4 + j] / N) for j in range(D)])
        total = np.stack([ratio(0.5 * s[..., 4 + D + j] / N) for j in range(D)])
        second = [ratio(s[..., 4 + 2 * D + p] / N) - first[j] - first[k] for p, (j, k) in enumerate(self.pairs)]
        return first, total, second


class _MorrisTerms:
    """The Morris statistics of ``SALib.analyze.morris`` (unscaled elementary effects) for a block
    of geometries: mu, mu_star, ee_std (SALib's sigma) and mu_star's bootstrap interval."""

    def __init__(self, X, D, num_levels, rng, R, Z):
        T = X.shape[0] // (D + 1)
        Xt = X.reshape(T, D + 1, D)
        dX = np.diff(Xt, axis=1)  # (T, D steps, D variables): one variable moves per step
        self.var = np.argmax(np.abs(dX), axis=2)  # (T, steps)
        self.sign = np.sign(np.take_along_axis(dX, self.var[..., None], axis=2)[..., 0])
        self.T, self.D = T, D
        self.delta = num_levels / (2.0 * (num_levels - 1))
        # SALib draws one (R, T) index array per parameter, in parameter order, from one generator
        self.W = [_counts(rng.integers(T, size=(R, T)), T) for _ in range(D)]
        self.Z = Z

    def block_bytes(self, runs, itemsize=8):
        """Bytes per geometry beyond its outputs: the float64 outputs, steps and elementary effects."""
        return 8 * (2 * runs + 3 * self.T * self.D + len(self.W) * self.W[0].shape[0])

    def __call__(self, Y):
        Y = np.asarray(Y, np.float64)
        G = Y.shape[0]
        Yt = Y.reshape(G, self.T, self.D + 1)
        step = np.diff(Yt, axis=2) * (self.sign / self.delta)[None]  # (G, T, steps)
        ee = np.empty((self.D, G, self.T))
        for s in range(self.D):  # the effect of step s of each trajectory, on the variable it moved
            ee[self.var[:, s], :, np.arange(self.T)] = step[:, :, s].T
        mu = ee.mean(axis=2)
        mu_star = np.abs(ee).mean(axis=2)
        ee_std = ee.std(axis=2, ddof=1)
        conf = np.stack([self.Z * _std1(self.W[j] @ np.abs(ee[j]).T / self.T) for j in range(self.D)])
        return {"mu": mu, "mu_star": mu_star, "ee_std": ee_std, "mu_star_conf": conf, "constant": _constant(Y)}


def _constant(Y):
    """Per geometry (rows of ``Y``, (G, runs)): does the output not vary over the box (its range
    within rounding of its scale, SALib's test of the normalised output)?"""
    Y = np.asarray(Y, np.float64)
    mean = Y.mean(axis=1, keepdims=True)
    scale = np.sqrt(np.mean((Y - mean) ** 2, axis=1)) + np.abs(mean[:, 0])
    with np.errstate(invalid="ignore"):
        return ~(np.ptp(Y, axis=1) > np.finfo(float).eps * np.maximum(scale, np.finfo(float).tiny))


#: The long name of the ``constant`` variable.
CONSTANT = ("1 where the output does not vary over the box at this geometry: every index is 0 there "
            "and means nothing")

VARIABLES = {
    "sobol": {"S1": "first-order Sobol' index", "ST": "total Sobol' index",
              "S1_conf": "half-width of the 95% bootstrap interval of S1",
              "ST_conf": "half-width of the 95% bootstrap interval of ST",
              "S2": "second-order Sobol' index", "S2_conf": "half-width of the 95% bootstrap interval of S2"},
    "morris": {"mu": "mean elementary effect", "mu_star": "mean absolute elementary effect (mu*)",
               "ee_std": "standard deviation of the elementary effects (SALib's sigma)",
               "mu_star_conf": "half-width of the 95% bootstrap interval of mu*"},
}


def sobol(ranges, geometry, fixed=None, quantity="dop", N=4096, seed=None, dtype="float32", shadowing="paper",
          second_order=False, *, method="sobol", num_levels=None, memory_budget=DEFAULT_BUDGET, progress=False,
          engine=None, backend="auto"):
    """Global sensitivity of ``quantity`` to the model's parameters at every geometry of a grid.

    Parameters
    ----------
    ranges : dict
        Parameter -> (low, high) for the parameters that vary (uniform), or (low, high, "log")
        for a log-uniform range; any of n, k, sigma, ks, kd, c.  The DOP depends on kd and ks only
        through kd/ks: vary kd with ks fixed (the default ks = 1).
    geometry : dict
        Any of theta_i, theta_r, phi (degrees) -> a value, a 1-d sequence or a range string
        ("0:85@64", "20:65:5"); theta_i and theta_r are required, phi defaults to 180 (in plane).
        Every axis with more than one value is a dimension of the result.
    fixed : dict, optional
        Values of the parameters without a range (ks, kd, c default to 1, 0, 0).
    quantity : {"dop", "brdf"}, default "dop"
    N : int, default 4096
        Base samples: N (D + 2) model runs per geometry (N (2D + 2) with ``second_order``) for
        Sobol; N trajectories of D + 1 runs for Morris.  A power of 2 for Sobol' sequences.
    seed : int, optional
        Seeds SALib's sampler and the bootstrap resamples exactly as SALib does.
    dtype : {"float32", "float64"}, default "float32"
        Precision of the model runs (the estimators are float64).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function (as for :func:`pbrdf_cl.dop`).
    second_order : bool, default False
        Also S2 and S2_conf (over ``parameter`` and ``parameter_2``; NaN on and below the diagonal).
    num_levels : int, optional
        Morris only: the levels of its grid (default 4).
    method : {"sobol", "morris"}, default "sobol"
        "morris": elementary effects on a ``num_levels`` grid (SALib's Morris sampler and
        analyser): mu, mu_star, ee_std (the elementary effects' standard deviation, SALib's
        ``sigma``, renamed so as not to be read as the roughness) and mu_star_conf.
    memory_budget : int or str, default "512 MiB"
        Host memory of one block of geometries (the outputs and the estimators' terms).
    progress : bool
        A progress bar over the geometries (when the work takes more than a second).
    engine, backend : where the model runs (see :func:`pbrdf_cl.device.engine.resolve_engine`)

    Returns
    -------
    xarray.Dataset
        Sobol: ``S1``, ``ST``, ``S1_conf``, ``ST_conf`` over ``parameter`` and the geometry axes;
        Morris: ``mu``, ``mu_star``, ``ee_std``, ``mu_star_conf``.  ``constant`` (geometry axes)
        marks the geometries where the output does not vary over the box (every index is 0 there,
        as in SALib, and means nothing).  ``samples`` (run, parameter) holds the parameter sets run
        at every geometry; ``attrs`` the settings, the ranges, the fixed values, the model runs,
        the seconds and ``notes`` (what the indices cannot mean for these settings).

    Examples
    --------
    >>> import pbrdf_cl
    >>> ds = pbrdf_cl.sobol({"n": (1.2, 2.5), "k": (0.01, 3, "log"), "sigma": (0.1, 0.6)},
    ...                     {"theta_i": 40, "theta_r": "0:85@18"}, N=256, seed=1)
    >>> ds.S1.dims
    ('parameter', 'theta_r')
    """
    from ..ranges import parse_bytes
    t0 = time.perf_counter()
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(map(repr, METHODS))}, got {method!r}")
    q = quantities.get(quantity, "points")
    if q.name not in SCALAR:
        raise ValueError(f"quantity: {q.name!r} has no sensitivity map ("
                         + ("an angle modulo its period: its variance is not meaningful" if q.period else
                            "not one value per point") + f"); available: {', '.join(SCALAR)}")
    dtype = pointwise.check_options(shadowing, dtype)
    if isinstance(N, bool) or not isinstance(N, (int, np.integer)) or N < 2:
        raise ValueError(f"N must be an integer >= 2, got {N!r}")
    if method == "morris" and second_order:
        raise ValueError("second_order: Morris screening has no second-order indices (only Sobol' has S2: "
                         "method='sobol'); drop second_order")
    if method == "sobol" and num_levels is not None:
        raise ValueError(f"num_levels = {num_levels!r}: only Morris screening has levels (method='morris'); drop it")
    num_levels = 4 if num_levels is None else num_levels
    if not isinstance(num_levels, (int, np.integer)) or isinstance(num_levels, bool) or num_levels < 2:
        raise ValueError(f"num_levels must be an integer >= 2, got {num_levels!r}")
    memory_budget = parse_bytes("memory_budget", memory_budget)
    rngs = check_ranges(ranges)
    fixed = check_fixed(fixed, {r.name for r in rngs})
    notes = _notes(q.name, rngs)
    for note in notes:
        import warnings
        warnings.warn(note, SensitivityWarning, stacklevel=2)
    axes, scalars = check_geometry(geometry)
    geo, shape = geometry_list(axes, scalars)
    G = int(np.prod(shape, dtype=np.int64))
    X, terms = _sampler(method, rngs, int(N), second_order, int(num_levels), seed)
    params = parameter_sets(X, rngs, fixed)
    eng = resolve_engine(engine, backend)
    results, blocks = _run_blocks(eng, q.name, geo, params, dtype, shadowing, terms, memory_budget, progress)
    ds = _dataset(results, method, q, rngs, params, axes, scalars, shape)
    ds.attrs.update(method=method, quantity=q.name, quantity_units=q.units, N=int(N),
                    seed=-1 if seed is None else int(seed), dtype=dtype, shadowing=shadowing,
                    runs_per_geometry=int(X.shape[0]), geometries=G, model_runs=int(X.shape[0]) * G, blocks=blocks,
                    num_resamples=NUM_RESAMPLES, conf_level=CONF_LEVEL, engine=eng.description,
                    seconds=round(time.perf_counter() - t0, 3),
                    sampler=("SALib.sample.sobol (Saltelli's scheme, scrambled Sobol' sequence)" if method == "sobol"
                             else f"SALib.sample.morris ({num_levels} levels)"),
                    estimator=("SALib.analyze.sobol (Saltelli 2010 first order, Jansen total order), vectorised"
                               if method == "sobol" else
                               "SALib.analyze.morris (unscaled elementary effects), vectorised"))
    if method == "sobol":
        ds.attrs["second_order"] = int(bool(second_order))
    else:
        ds.attrs["num_levels"] = int(num_levels)
    for r in rngs:
        ds.attrs[f"range_{r.name}"] = [r.low, r.high]
        ds.attrs[f"scale_{r.name}"] = r.scale
    for n, v in fixed.items():
        ds.attrs[f"fixed_{n}"] = v
    ds.attrs["notes"] = " | ".join(notes)
    return ds


def _notes(quantity, rngs):
    """Sentences on what the indices of these settings cannot mean."""
    names = {r.name for r in rngs}
    if quantity == "dop" and {"ks", "kd"} <= names:
        return ["ks and kd both have a range, but the DOP depends on them only through kd/ks: the variance of kd/ks "
                "is split between them and neither index means what it seems; give ks a fixed value (fixed={'ks': 1})"
                " and a range to kd, which then stands for kd/ks"]
    return []


def _sampler(method, rngs, N, second_order, num_levels, seed):
    """SALib's samples for ``method`` (rows in the sampler's space) and the estimators of the
    outputs, their bootstrap resamples drawn as SALib's analysers draw them for ``seed``."""
    from scipy.stats import norm
    problem = _problem(rngs)
    Z = float(norm.ppf(0.5 + CONF_LEVEL / 2))
    if method == "sobol":
        from SALib.sample import sobol as sobol_sample
        X = sobol_sample.sample(problem, N, calc_second_order=second_order, seed=seed)
        # SALib.analyze.sobol: a truthy seed seeds the resamples, else numpy's global generator
        draw = np.random.default_rng(seed).integers if seed else np.random.randint
        return X, _SobolTerms(len(rngs), N, second_order, _counts(draw(N, size=(N, NUM_RESAMPLES)).T, N), Z)
    from SALib.sample import morris as morris_sample
    from SALib.util import handle_seed
    X = morris_sample.sample(problem, N, num_levels=num_levels, seed=seed)
    return X, _MorrisTerms(X, len(rngs), num_levels, handle_seed(seed), NUM_RESAMPLES, Z)


def _run_blocks(eng, quantity, geo, params, dtype, shadowing, terms, memory_budget, progress):
    """The model runs of every parameter set at every geometry, block of geometries by block within
    ``memory_budget``, each reduced by ``terms`` as it comes: (name -> array (..., G), blocks)."""
    G = geo["theta_i"].size
    runs = params["n"].size
    itemsize = np.dtype(DTYPES[dtype]).itemsize
    per_geometry = runs * itemsize + terms.block_bytes(runs, itemsize)
    block = int(max(1, min(G, memory_budget // per_geometry)))
    results = {}
    bar = progress_bar(G, progress, "sensitivity", unit="geometry")
    for g0 in range(0, G, block):
        g1 = min(G, g0 + block)
        Y = outer(eng, quantity, geo, params, dtype, shadowing, rows=(g0, g1))
        for key, v in terms(Y.reshape(g1 - g0, runs)).items():
            if key not in results:
                results[key] = np.empty(v.shape[:-1] + (G,))
            results[key][..., g0:g1] = v
        if bar is not None:
            bar.update(g1 - g0)
    if bar is not None:
        bar.close()
    return results, -(-G // block)


def _dataset(results, method, q, rngs, params, axes, scalars, shape):
    """The indices over (parameter, geometry axes) as a Dataset with labelled coordinates and the
    samples; the caller adds the settings to ``attrs``."""
    import xarray as xr
    names = [r.name for r in rngs]
    dims = ("parameter",) + tuple(axes)
    coords = {"parameter": names}
    for n, a in axes.items():
        coords[n] = xr.Variable((n,), a, {"units": "deg", "long_name": LONG_NAMES[n]})
    for n, v in scalars.items():
        coords[n] = xr.Variable((), v, {"units": "deg", "long_name": LONG_NAMES[n]})
    data = {}
    for key, v in results.items():
        if key == "constant":
            data[key] = xr.Variable(tuple(axes), v.reshape(shape).astype(np.int8), {"long_name": CONSTANT})
            continue
        lead = v.shape[:-1]
        kdims = ("parameter", "parameter_2") + tuple(axes) if len(lead) == 2 else dims
        data[key] = xr.Variable(kdims, v.reshape(lead + shape),
                                {"long_name": VARIABLES[method][key], "units": "1" if method == "sobol" else q.units})
    if "S2" in data:
        coords["parameter_2"] = names
    data["samples"] = xr.Variable(("run", "parameter"), np.stack([params[n] for n in names], axis=1),
                                  {"long_name": "parameter sets run at every geometry"})
    return xr.Dataset(data, coords=coords)


def morris(ranges, geometry, fixed=None, quantity="dop", N=256, seed=None, **kwargs):
    """Morris screening (:func:`sobol` with ``method="morris"``): ``N`` trajectories.

    Parameters
    ----------
    ranges, geometry, fixed, quantity, seed : as for :func:`sobol`
    N : int, default 256
        Trajectories of D + 1 runs each (SALib's Morris sampler).
    **kwargs
        The other keywords of :func:`sobol` (``num_levels``, ``dtype``, ``memory_budget``, ...).

    Returns
    -------
    xarray.Dataset
        ``mu``, ``mu_star``, ``ee_std``, ``mu_star_conf`` over ``parameter`` and the geometry axes,
        and ``constant``.

    Examples
    --------
    >>> import pbrdf_cl
    >>> ds = pbrdf_cl.morris({"n": (1.2, 2.5), "sigma": (0.1, 0.6)}, {"theta_i": 40, "theta_r": "0:85@18"},
    ...                      fixed={"k": 2.139}, N=16, seed=1)
    >>> sorted(ds.data_vars)
    ['constant', 'ee_std', 'mu', 'mu_star', 'mu_star_conf', 'samples']
    """
    return sobol(ranges, geometry, fixed, quantity, N, seed, method="morris", **kwargs)


# ---------------------------------------------------------------------------------------------
# the TOML spec of `pbrdf-cl sobol`, writing a result, its summary

#: The keys of a sensitivity spec (``examples/sobol.toml``); the tables last.
SPEC_KEYS = ("title", "quantity", "method", "N", "seed", "dtype", "shadowing", "second_order", "num_levels",
             "memory_budget", "ranges", "geometry", "fixed")


def _spec_error(field, exc):
    """``exc``'s message as a :class:`pbrdf_cl.analysis.sweeps.SpecError` that starts with ``field``; the
    ``ranges['k']`` of :func:`check_ranges` and friends spelt as in TOML, ``ranges.k``."""
    import re

    from .sweeps import SpecError
    text = re.sub(r"\b(ranges|geometry|fixed)\['(\w+)'\]", r"\1.\2", str(exc))
    return SpecError(text if text.startswith(field) else f"{field}: {text}")


def _integer(field, v, low):
    from .sweeps import SpecError
    if isinstance(v, bool) or not isinstance(v, int) or v < low:
        raise SpecError(f"{field}: must be an integer >= {low}, got {v!r}")
    return v


def _spec_settings(data):
    """A parsed spec (dict) -> the keyword arguments of :func:`sobol`, every field checked."""
    from .sweeps import SpecError
    if not isinstance(data, dict):
        raise SpecError(f"a sensitivity spec is a table (dict), got {type(data).__name__}")
    for key in data:
        if key not in SPEC_KEYS:
            raise SpecError(f"unknown key {key!r}{_hint(key, SPEC_KEYS)}; valid keys are {', '.join(SPEC_KEYS)}")
    out = _spec_options(data)
    out["ranges"] = _spec_ranges(data)
    out["fixed"] = _spec_fixed(data, out["ranges"])
    out["geometry"] = _spec_geometry(data)
    return out


def _spec_options(data):
    """The spec's top-level settings (method, quantity, N, seed, dtype, shadowing, second_order,
    num_levels, memory_budget), checked."""
    from ..device.engine import DTYPES
    from ..model.reference import SHADOWING
    from .sweeps import SpecError
    out = {}
    method = data.get("method", "sobol")
    if method not in METHODS:
        raise SpecError(f"method: must be one of {', '.join(map(repr, METHODS))}, "
                        f"got {method!r}{_hint(method, METHODS)}")
    out["method"] = method
    quantity = data.get("quantity", "dop")
    try:
        q = quantities.get(quantity, "points", "quantity")
    except ValueError as exc:
        raise _spec_error("quantity", exc) from None
    if q.name not in SCALAR:
        raise SpecError(f"quantity: {q.name!r} has no sensitivity map; available: {', '.join(SCALAR)}")
    out["quantity"] = q.name
    out["N"] = _integer("N", data.get("N", 4096 if method == "sobol" else 256), 2)
    if "seed" in data:
        if data["seed"] == 0 and not isinstance(data["seed"], bool):
            raise SpecError("seed: must be an integer >= 1 (SALib's analysers take 0 as no seed: the bootstrap "
                            "intervals would differ run to run); leave it out for an unseeded run")
        out["seed"] = _integer("seed", data["seed"], 1)
    out["dtype"] = data.get("dtype", "float32")
    if out["dtype"] not in DTYPES:
        raise SpecError(f"dtype: must be float32 or float64, got {out['dtype']!r}")
    out["shadowing"] = data.get("shadowing", "paper")
    if out["shadowing"] not in SHADOWING:
        raise SpecError(f"shadowing: must be one of {', '.join(sorted(SHADOWING))}, got {out['shadowing']!r}"
                        f"{_hint(out['shadowing'], sorted(SHADOWING))}")
    if "second_order" in data:
        if not isinstance(data["second_order"], bool):
            raise SpecError(f"second_order: must be true or false, got {data['second_order']!r}")
        if method != "sobol" and data["second_order"]:
            raise SpecError("second_order: only with method = \"sobol\" (Morris has no second-order indices)")
        if method == "sobol":
            out["second_order"] = data["second_order"]
    if "num_levels" in data:
        if method != "morris":
            raise SpecError("num_levels: only with method = \"morris\" (the levels of its grid)")
        out["num_levels"] = _integer("num_levels", data["num_levels"], 2)
    from ..ranges import RangeError, parse_bytes
    budget = data.get("memory_budget", DEFAULT_BUDGET)
    try:
        parse_bytes("memory_budget", budget)
    except RangeError as exc:
        raise SpecError(str(exc)) from None
    out["memory_budget"] = budget
    return out


def _spec_ranges(data):
    """The spec's ``[ranges]`` table, each range checked (``ranges.<name>: ...``)."""
    from .sweeps import SpecError
    rng_in = data.get("ranges")
    if not isinstance(rng_in, dict) or not rng_in:
        raise SpecError("ranges: a table of parameter = [low, high] (or [low, high, \"log\"]), e.g. "
                        "[ranges] n = [1.2, 2.5]")
    ranges = {}
    for name, spec in rng_in.items():
        field = f"ranges.{name}"
        if name not in PARAMETERS:
            raise SpecError(f"{field}: unknown parameter{_hint(name, PARAMETERS)}; valid names are "
                            f"{', '.join(PARAMETERS)}")
        if isinstance(spec, list):
            spec = tuple(spec)
        try:
            check_ranges({name: spec})
        except ValueError as exc:
            raise _spec_error(field, exc) from None
        ranges[name] = spec
    return ranges


def _spec_fixed(data, ranges):
    """The spec's ``[fixed]`` table, checked against the ranges (a parameter in one place only, none
    without a value)."""
    from .sweeps import SpecError
    fixed = data.get("fixed", {})
    if not isinstance(fixed, dict):
        raise SpecError(f"fixed: must be a table of name = value, got {fixed!r}")
    for name, v in fixed.items():
        if name not in PARAMETERS:
            raise SpecError(f"fixed.{name}: unknown parameter{_hint(name, PARAMETERS)}; valid names are "
                            f"{', '.join(PARAMETERS)}")
        if name in ranges:
            raise SpecError(f"fixed.{name}: {name} also has a range (ranges.{name}); give it in one place only")
        try:
            check_fixed({name: v}, set(PARAMETERS) - {name})
        except ValueError as exc:
            raise _spec_error(f"fixed.{name}", exc) from None
    missing = [n for n in PARAMETERS if n not in ranges and n not in fixed and n not in DEFAULTS]
    if missing:
        raise SpecError(f"ranges: {', '.join(missing)} need{'s' if len(missing) == 1 else ''} a range (or a value "
                        "under [fixed]): no default")
    return dict(fixed)


def _spec_geometry(data):
    """The spec's ``[geometry]`` table, each axis checked (``geometry.<name>: ...``)."""
    import warnings

    from .sweeps import SpecError
    geometry = data.get("geometry")
    if not isinstance(geometry, dict) or not geometry:
        raise SpecError("geometry: a table of theta_i, theta_r (and phi) = angles in degrees, e.g. "
                        "[geometry] theta_i = \"0:80@64\"")
    with warnings.catch_warnings():  # a radians warning is sobol's to give, once, when it runs
        warnings.simplefilter("ignore", pointwise.UnitsWarning)
        for name, v in geometry.items():
            if name not in GEOMETRY:
                raise SpecError(f"geometry.{name}: unknown axis{_hint(name, GEOMETRY)}; valid names are "
                                f"{', '.join(GEOMETRY)}")
            try:
                check_geometry({"theta_i": 0.0, "theta_r": 0.0, name: v})
            except ValueError as exc:
                raise _spec_error(f"geometry.{name}", exc) from None
        try:
            check_geometry(geometry)
        except ValueError as exc:
            raise _spec_error("geometry", exc) from None
    return dict(geometry)


def load_sobol_spec(spec):
    """The settings of a sensitivity map from its TOML spec (``pbrdf-cl sobol SPEC.toml``).

    Parameters
    ----------
    spec : str, path or dict
        A TOML file, TOML text (anything with a newline or ``=``), or the same keys as a dict:
        ``quantity``, ``method``, ``N``, ``seed``, ``dtype``, ``shadowing``, ``second_order``,
        ``num_levels`` (Morris), ``memory_budget``, an optional ``title``, and the tables
        ``[ranges]`` (name = [low, high] or [low, high, "log"]), ``[geometry]`` (theta_i,
        theta_r, phi = a value, a list or a range string such as ``"0:85@64"``, degrees) and
        ``[fixed]``.  See ``examples/sobol.toml`` and ``docs/sensitivity.md``.

    Returns
    -------
    dict
        The keyword arguments of :func:`sobol` (``sobol(**settings)`` runs the map), every field
        checked; ``title`` is not among them.

    Raises
    ------
    pbrdf_cl.analysis.sweeps.SpecError
        A ``ValueError`` of one line naming the field (``ranges.k: ...``), an unknown key with the
        nearest valid one, a TOML syntax error with its line.

    Examples
    --------
    >>> settings = load_sobol_spec('''
    ... N = 256
    ... seed = 1
    ... [ranges]
    ... n = [1.2, 2.5]
    ... k = [0.01, 3.0, "log"]
    ... sigma = [0.1, 0.6]
    ... [geometry]
    ... theta_i = 40
    ... theta_r = "0:85@18"
    ... ''')
    >>> settings["ranges"]["k"], settings["N"]
    ((0.01, 3.0, 'log'), 256)
    """
    import os
    from pathlib import Path

    from .sweeps import SpecError, tomllib
    source = None
    if isinstance(spec, dict):
        return _spec_settings(spec)
    if isinstance(spec, os.PathLike) or (isinstance(spec, str) and "\n" not in spec and "=" not in spec):
        source = str(spec)
        try:
            spec = Path(spec).read_text()
        except OSError as exc:
            raise SpecError(f"cannot read the spec {source!r}: {exc.strerror or exc}") from None
    if not isinstance(spec, str):
        raise SpecError(f"spec must be a TOML file path, TOML text or a dict, got {type(spec).__name__}")
    try:
        data = tomllib.loads(spec)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(f"{source or 'spec'}: not valid TOML: {exc}") from None
    return _spec_settings(data)


def _storable(v):
    """An attribute value every netCDF engine (scipy's netCDF3 included) and Zarr can store: bools and
    None as ints / "", integers beyond int32 as floats, sequences as float arrays."""
    if v is None:
        return ""
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    if isinstance(v, (numbers.Integral,)):
        return int(v) if -2 ** 31 <= int(v) < 2 ** 31 else float(v)
    if isinstance(v, numbers.Real):
        return float(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        return [float(x) for x in np.asarray(v, dtype=float).ravel()]
    return v if isinstance(v, str) else str(v)


def write_result(ds, path):
    """Write a result of :func:`pbrdf_cl.sobol` to ``path``.

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.sobol` or :func:`pbrdf_cl.morris` (or a design's
        ``to_dataset()``).
    path : str or path
        ``.nc`` (netCDF: netCDF4 or h5netcdf when installed, else scipy's netCDF3) or ``.zarr``
        (a Zarr store, replaced if it is one already); a ``ValueError`` for any other suffix, or
        for a ``.zarr`` path that exists and is not a Zarr store.

    Returns
    -------
    str
        The path."""
    from pathlib import Path
    path = Path(path)
    ds = ds.copy()
    ds.attrs = {k: _storable(v) for k, v in ds.attrs.items()}
    for name in list(ds.variables):
        ds[name].attrs = {k: _storable(v) for k, v in ds[name].attrs.items()}
    suffix = path.suffix.lower()
    if suffix == ".nc":
        ds.to_netcdf(path)
    elif suffix == ".zarr":
        if path.exists() and not any((path / m).exists() for m in (".zgroup", "zarr.json")):
            raise ValueError(f"{path} exists and is not a Zarr store; choose another path or delete it")
        import warnings
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*(fixed-length|FixedLengthUTF32|unstable).*")
            ds.to_zarr(path, mode="w", zarr_format=2, consolidated=True)
    else:
        raise ValueError(f"{path}: write a result as .nc (netCDF) or .zarr (a Zarr store), "
                         f"not {suffix or 'no suffix'!r}")
    return str(path)


def _indices(ds):
    """The two index variables a summary and a figure show: (S1, ST) or (mu_star, ee_std)."""
    return ("S1", "ST") if "S1" in ds else ("mu_star", "ee_std")


def summary(ds):
    """A few lines on a result of :func:`pbrdf_cl.sobol`: the work done, and per parameter its mean
    indices over the geometries and where it dominates (the share of geometries where its total
    index, or mu*, is the largest).

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.sobol` or :func:`pbrdf_cl.morris`.

    Returns
    -------
    str"""
    ds = compatible(ds)
    first, second = _indices(ds)
    geo = [d for d in ds[first].dims if d != "parameter"]
    size = " x ".join(f"{d}[{ds.sizes[d]}]" for d in geo) or "one geometry"
    a = ds.attrs
    names = ", ".join(map(str, ds.parameter.values))
    lines = [f"{a.get('method', 'sobol')}: {ds.sizes['parameter']} parameters ({names}) "
             f"of {a.get('quantity', '?')} over {size}: {a.get('runs_per_geometry')} runs per geometry, "
             f"{a.get('model_runs')} model runs in {float(a.get('seconds', 0)):.3g} s on {a.get('engine', '?')}"]
    key = "ST" if first == "S1" else "mu_star"
    v = ds[key].values.reshape(ds.sizes["parameter"], -1)
    finite = np.isfinite(v).all(axis=0) & (np.nanmax(np.abs(v), axis=0) > 0)
    if "constant" in ds:
        finite &= ~ds["constant"].values.reshape(-1).astype(bool)
    best = np.argmax(np.where(np.isfinite(v), v, -np.inf), axis=0)
    m1 = ds[first].values.reshape(v.shape[0], -1)
    m2 = ds[second].values.reshape(v.shape[0], -1)
    what = "largest ST" if key == "ST" else "largest mu*"
    lines.append(f"  {'parameter':10s} {'mean ' + first:>10s} {'mean ' + second:>10s}  dominates ({what})")
    for i, p in enumerate(ds.parameter.values):
        share = np.mean(best[finite] == i) if finite.any() else 0.0
        lines.append(f"  {str(p):10s} {np.nanmean(m1[i]):10.3g} {np.nanmean(m2[i]):10.3g}  {share:6.1%} of geometries")
    if (~finite).any():
        lines.append(f"  ({int((~finite).sum())} geometries where {a.get('quantity', 'the output')} does not vary: "
                     "indices 0, meaning nothing; marked in `constant` and hatched in the figure)")
    lines += [f"  note: {n}" for n in str(a.get("notes", "")).split(" | ") if n]
    return "\n".join(lines)
