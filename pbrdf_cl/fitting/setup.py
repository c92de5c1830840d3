"""The one setup of a fit: the model, its shadowing function and, per parameter, its bounds and
whether it is free or held at a value (lmfit's ``Parameters`` in spirit), checked once with
one-line errors.  :func:`pbrdf_cl.fit`, :func:`pbrdf_cl.fit_batch` and :func:`pbrdf_cl.design`
all start from :meth:`FitSetup.check`.

Which kd: without intensities the DOP depends on kd and ks only through kd/ks, so ks is held (at
1 unless fixed otherwise) and kd is fitted as itself (kd/ks at ks = 1); with intensities ks is
free too and the fitted coordinate is the ratio kd/ks (:meth:`FitSetup.fits_intensity`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..compute.pointwise import RULES
from ..model import inputs, reference
from ..ranges import did_you_mean

#: The model's six parameters, in the order of the kernels' parameter vectors (the registry's).
PARAMETERS = inputs.PARAMETERS
#: The parameters each model fits (ks is never among them: only intensities separate it from kd);
#: the specular model (ref. [7]) fits the Fresnel factors' n and k alone.
MODEL_PARAMS = {"six-param": inputs.FITTED, "specular": inputs.INDEX}
DEFAULT_BOUNDS = inputs.DEFAULT_BOUNDS
#: sigma's value in the specular model, where it cancels (any value gives the same DOP).
SPECULAR_SIGMA = 0.5
#: The value a fixed-by-the-model parameter takes: the registry's default (specular: no diffuse
#: term, and sigma, which cancels, at SPECULAR_SIGMA).
MODEL_FIXED = {model: {p: inputs.DEFAULTS.get(p, SPECULAR_SIGMA) for p in PARAMETERS if p not in fitted}
               for model, fitted in MODEL_PARAMS.items()}
#: Default relative uncertainty of intensities without an f00_std column (the fit's weights and
#: the design's intensity noise).
F00_REL_STD = 0.05
#: The parameters of the index corner, where a surface is almost index-matched and has a small
#: diffuse share (n = 1, k = 0, kd = 0 at their lower bounds): there the DOP changes fastest and
#: its minima are narrowest, so the grid is denser there and image fits descend there too.
INDEX_CORNER = inputs.INDEX + ("kd",)


class Parameter(NamedTuple):
    """One parameter of a :class:`FitSetup`: its ``bounds`` (low, high), whether it is ``free``
    (varied by the fit) and, where it is not, the ``value`` it is held at (None where free)."""
    name: str
    value: float | None
    bounds: tuple
    free: bool


def check_model(model, shadowing):
    """Refuse an unknown model or shadowing function in one line (before the data are read)."""
    if model not in MODEL_PARAMS:
        raise ValueError(f"model must be one of {sorted(MODEL_PARAMS)}, got {model!r}")
    if shadowing not in reference.SHADOWING:
        raise ValueError(f"shadowing must be one of {sorted(reference.SHADOWING)}, got {shadowing!r}")


def _checked_bounds(model, bounds):
    """Bounds (name -> (lo, hi)) of the model's parameters (defaults where not given) and of any
    other parameter given, checked against the domain rules of
    :data:`pbrdf_cl.compute.pointwise.RULES` and the widest bounds a fit searches
    (:data:`pbrdf_cl.model.inputs.BOUND_LIMITS`)."""
    b = {n: DEFAULT_BOUNDS[n] for n in MODEL_PARAMS[model]}
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
        lim = inputs.BOUND_LIMITS.get(name)
        if lim is not None and not (lim[0] <= lo and hi <= lim[1]):
            raise ValueError(f"bounds: {name} = ({lo:g}, {hi:g}) reaches beyond what a fit searches ({name} in "
                             f"[{lim[0]:g}, {lim[1]:g}]: the model's arithmetic and the search's resolution); give "
                             f"bounds within it")
    return b


def _checked_fixed(model, fixed):
    """The fixed values (name -> float), each inside the model's domain and a parameter of it."""
    fx = {}
    for name, v in (fixed or {}).items():
        if name not in DEFAULT_BOUNDS:
            raise ValueError(f"fixed: unknown parameter {name!r}; parameters are {', '.join(DEFAULT_BOUNDS)}")
        v = float(v)
        ok, rule = RULES[name]
        if not (np.isfinite(v) and ok(v)):
            raise ValueError(f"fixed: {name} = {v} is outside the model's domain ({name} must be {rule})")
        if name not in MODEL_PARAMS[model] and not (model == "six-param" and name == "ks"):
            raise ValueError(f"fixed: {name} is not a parameter of the {model} model")
        fx[name] = v
    return fx


@dataclass(frozen=True)
class FitSetup:
    """The checked setup of a fit (:meth:`check` makes one).

    ``model``, ``shadowing``; ``bounds``: name -> (low, high) of the model's parameters and of any
    other one given (``ks``); ``fixed``: name -> value, what the caller held.  Derived:
    :attr:`free` (the fitted parameters, ks never among them), :attr:`base` (the values of the
    others), :attr:`lo` / :attr:`hi` (the bounds of :attr:`free`), :attr:`ks_bounds`, and
    :attr:`params`, one :class:`Parameter` per model parameter."""
    model: str
    shadowing: str
    bounds: dict
    fixed: dict

    @classmethod
    def check(cls, model="six-param", bounds=None, fixed=None, shadowing="paper", *, need_free=True):
        """The setup of ``model`` with ``bounds`` and ``fixed`` (dicts name -> (low, high), name ->
        value), checked in one-line ``ValueError``s; ``need_free``: refuse a setup without a free
        parameter."""
        check_model(model, shadowing)
        setup = cls(model, shadowing, _checked_bounds(model, bounds), _checked_fixed(model, fixed))
        if need_free and not setup.free:
            raise ValueError("every parameter is fixed: nothing to fit")
        return setup

    @property
    def free(self):
        """The fitted parameters (in :data:`MODEL_PARAMS` order): the model's, less the fixed."""
        return [n for n in MODEL_PARAMS[self.model] if n not in self.fixed]

    @property
    def base(self):
        """The values of the parameters not fitted: the model's (:data:`MODEL_FIXED`), then the
        caller's fixed values."""
        return {**MODEL_FIXED[self.model], **self.fixed}

    @property
    def lo(self):
        """Lower bounds of :attr:`free` (an array in its order)."""
        return np.array([self.bounds[n][0] for n in self.free])

    @property
    def hi(self):
        """Upper bounds of :attr:`free`."""
        return np.array([self.bounds[n][1] for n in self.free])

    @property
    def ks_bounds(self):
        """The bounds of ks where intensities free it (given, else the default)."""
        return self.bounds.get("ks", DEFAULT_BOUNDS["ks"])

    def bounds_of(self, names):
        """(lo, hi) arrays of the parameters ``names`` (ks: :attr:`ks_bounds`)."""
        pairs = [self.ks_bounds if n == "ks" else self.bounds[n] for n in names]
        return np.array([b[0] for b in pairs]), np.array([b[1] for b in pairs])

    @property
    def params(self):
        """name -> :class:`Parameter`, every parameter of the model (:data:`PARAMETERS` order)."""
        free, base = set(self.free), self.base
        return {n: Parameter(n, None if n in free else float(base[n]),
                             self.ks_bounds if n == "ks" else tuple(self.bounds.get(n, DEFAULT_BOUNDS[n])), n in free)
                for n in PARAMETERS}

    def fits_intensity(self, has_f00):
        """Whether intensities (``has_f00``) enter the fit: ks is then free and kd is fitted as the
        ratio kd/ks; only the six-parameter model with neither ks nor kd fixed separates them."""
        return bool(has_f00) and self.model == "six-param" and "ks" not in self.fixed and "kd" not in self.fixed

    def grid_axes(self, shape):
        """The grid of a grid stage: free parameter -> nodes (:func:`grid_axis`), ``shape`` giving
        the nodes per parameter."""
        return {n: grid_axis(n, self.bounds[n], int(shape[n])) for n in self.free}


def grid_axis(name, bounds, count):
    """Grid values of one parameter.  n, k and kd are spaced quadratically from their lower
    bound: near n = 1, k = 0 (an almost index-matched surface) and near kd = 0 (a small diffuse
    share) the DOP changes fastest and its minima are narrowest.  sigma is spaced
    geometrically: the specular lobe's shape depends on tan(a) / sigma, so equal ratios of sigma
    matter equally (on a linear grid, smooth surfaces with sigma < 0.1 fell between nodes)."""
    if name == "sigma" and bounds[0] > 0:
        return np.geomspace(bounds[0], bounds[1], count)
    u = np.linspace(0.0, 1.0, count)
    if name in INDEX_CORNER:
        u = u * u
    return bounds[0] + (bounds[1] - bounds[0]) * u


def check_shared(shared, model, default, unlike=()):
    """The parameters a fit shares (:func:`pbrdf_cl.fit_joint`'s sets, a label's pixels of
    :func:`pbrdf_cl.fit_batch`), in model order: the one reading of ``shared`` for every fit.

    ``shared`` is a sequence of names or one string of them separated by commas and/or spaces
    (``"sigma,c"``, ``"sigma, c"``, ``"sigma c"``); an empty one (``()``, ``""``) shares nothing;
    None takes ``default``, less what the model does not fit and what is held ``unlike`` (names
    the user held in some parts of the fit only, or at different values: a default never shares
    them).  A shared parameter held at one value everywhere stays shared: one value for all,
    which the callers hold.  Refused in one line: a name that is not a parameter (the nearest one
    offered), one the model does not fit, a name given twice."""
    params = MODEL_PARAMS[model]
    if shared is None:
        return tuple(p for p in params if p in default and p not in unlike)
    if isinstance(shared, str):
        names = tuple(re.split(r"[\s,]+", shared.strip(" ,\t\n"))) if shared.strip(" ,\t\n") else ()
    else:
        try:
            names = tuple(shared)
        except TypeError:
            raise ValueError(f"shared: give parameter names (a sequence, or a string such as 'sigma,c'), got "
                             f"{shared!r}") from None
    for name in names:
        if not isinstance(name, str):
            raise ValueError(f"shared: {name!r} is not a parameter name; parameters are {', '.join(params)}")
        if name not in params:
            near = did_you_mean(name, list(PARAMETERS))
            if name in PARAMETERS:
                why = f"{name} is not fitted by the {model} model (its fitted parameters: {', '.join(params)})"
            else:
                why = f"{name!r} is not a parameter" + (f" (did you mean {near!r}?)" if near else "") + \
                      f"; the {model} model fits {', '.join(params)}"
            raise ValueError(f"shared: {why}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"shared: {', '.join(twice)} named twice ({', '.join(names)})")
    return tuple(p for p in params if p in names)
