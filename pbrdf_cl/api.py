"""Public API: DOP, F00, AoP, the Stokes vector and the Mueller matrix of the six-parameter pBRDF model.

Angles are in degrees: ``theta_i``, ``theta_r`` in [0, 90); ``phi`` is the relative
azimuth phi_i - phi_r, 180 being the in-plane (specular) geometry.  ``sigma`` is the
per-axis slope standard deviation.  All array arguments broadcast together.
"""
from __future__ import annotations

import numpy as np

from . import quantities, reference, sizes
from .engine import BACKENDS, DTYPES, POINT_INPUTS, check_backend, resolve_engine  # noqa: F401 (api.BACKENDS stays)

MODELS = ("six-param", "specular")
#: The quantities with a per-point path (the registry, :mod:`pbrdf_cl.quantities`, says more).
QUANTITIES = quantities.names("points")


def _as_array(name, value):
    """``value`` as a float array: float32 and float64 arrays as they are (no copy), anything else
    converted to float64."""
    if isinstance(value, np.ndarray) and value.dtype in (np.float32, np.float64):
        return value
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number or an array of numbers, got {value!r}") from None


def _all_finite(a):
    """Whether every value is finite: two reads (min, max: NaN propagates) and no temporary."""
    return a.size == 0 or bool(np.isfinite(np.min(a)) and np.isfinite(np.max(a)))


class _Range:
    """A valid range of values, as a mask: ``rule(a)``; its bounds make the minimum and the
    maximum of an array enough to check all of it."""

    def __init__(self, lo=None, hi=None, lo_included=True, hi_included=False):
        self.lo, self.hi, self.lo_included, self.hi_included = lo, hi, lo_included, hi_included

    def __call__(self, a):
        ok = np.ones(np.shape(a), bool)
        if self.lo is not None:
            ok &= (a >= self.lo) if self.lo_included else (a > self.lo)
        if self.hi is not None:
            ok &= (a <= self.hi) if self.hi_included else (a < self.hi)
        return ok


def _where(a, bad):
    return f" at index {np.argwhere(bad)[0].tolist()}" if a.ndim else ""


def _check(name, a, ok, rule):
    bad = ~ok(a)
    if bad.any():
        raise ValueError(f"{name} must be {rule}, got {float(a[bad].flat[0])!r}{_where(a, bad)}")


#: The valid range of each input, as (test, words); every input must also be finite.  The vector
#: kernels of ``kernels/pbrdf_points.cl`` check the same (``PB_IN_DOMAIN``).
RULES = {
    "theta_i": (_Range(0.0, 90.0), "in [0, 90) degrees"),
    "theta_r": (_Range(0.0, 90.0), "in [0, 90) degrees"),
    "phi": (_Range(), "finite"),
    "n": (_Range(0.0, lo_included=False), "> 0"),
    "k": (_Range(0.0), ">= 0"),
    "sigma": (_Range(0.0, lo_included=False), "> 0"),
    "ks": (_Range(0.0, lo_included=False), "> 0"),
    "kd": (_Range(0.0), ">= 0"),
    "c": (_Range(), "finite"),
}


def check_values(name, value):
    """``value`` as a float64 array, or a ``ValueError`` naming ``name`` and the first bad value."""
    a = _as_array(name, value).astype(np.float64, copy=False)
    _check_domain(name, a)
    return a


def _check_domain(name, a):
    """Every value of ``a`` (either float dtype) finite and in ``RULES[name]``, else a ``ValueError``
    naming the first bad one; two reads (min, max) when all is well."""
    ok, rule = RULES[name]
    if a.size:
        lo, hi = np.min(a), np.max(a)  # NaN propagates
        if np.isfinite(lo) and np.isfinite(hi) and ok(lo) and ok(hi):
            return
        bad = ~np.isfinite(a)
        if bad.any():
            raise ValueError(f"{name} must be finite, got {float(a[bad].flat[0])!r}{_where(a, bad)}")
        _check(name, a, ok, rule)


class UnitsWarning(UserWarning):
    """Inputs that look like a unit or convention mistake (angles in radians, DOP in percent, ...)."""


#: Zenith angles that all lie below this many degrees (and are not all 0) look like radians.
RADIANS_HINT = 1.6


def check_degrees(theta_i, theta_r, where=""):
    """Warn (:class:`UnitsWarning`) when every zenith angle lies below 1.6 and not all are 0: such
    angles are almost always radians (pbrdf-cl takes degrees).  Two reads of each array."""
    hi = max(float(np.max(a)) if np.size(a) else 0.0 for a in (theta_i, theta_r))
    lo = min(float(np.min(a)) if np.size(a) else 0.0 for a in (theta_i, theta_r))
    if 0.0 < hi < RADIANS_HINT and lo >= 0.0:
        import warnings
        warnings.warn(f"{where}theta_i and theta_r all lie below {RADIANS_HINT} degrees (the largest is {hi:.4g}): "
                      "are they in radians? pbrdf-cl takes degrees (np.degrees(...) converts)", UnitsWarning,
                      stacklevel=5)


def check_options(shadowing, dtype):
    """Check the shadowing name and the dtype; returns the dtype's name."""
    if shadowing not in reference.SHADOWING:
        raise ValueError(f"shadowing must be one of {sorted(reference.SHADOWING)}, got {shadowing!r}")
    dtype_name = np.dtype(dtype).name if dtype in (np.float32, np.float64) else dtype
    if dtype_name not in DTYPES:
        raise ValueError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
    return dtype_name


def validate(theta_i, theta_r, phi, n, k, sigma, ks, kd, c, *, shadowing="paper", dtype="float64",
             backend="auto", model="six-param", values=True):
    """Check and broadcast the inputs; returns ``(arrays dict, shape, dtype name)``; the arrays keep
    a float32 or float64 dtype (no copy), anything else becomes float64.

    Raises ``ValueError`` naming the offending argument, value and index.  ``values=False`` checks
    only the options, types and shapes (the vector kernels check the values themselves, writing NaN
    for a point outside the domain, and the caller checks again, to name the offender, only when
    the result holds a NaN).
    """
    dtype_name = check_options(shadowing, dtype)
    check_backend(backend)
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if sigma is None:
        raise ValueError("sigma is required (the per-axis slope standard deviation, > 0)")
    given = dict(theta_i=theta_i, theta_r=theta_r, phi=phi, n=n, k=k, sigma=sigma, ks=ks, kd=kd, c=c)
    arrays = {name: _as_array(name, given[name]) for name in POINT_INPUTS}
    if values:
        for name in POINT_INPUTS:
            _check_domain(name, arrays[name])
    check_degrees(arrays["theta_i"], arrays["theta_r"])
    if model == "specular":
        _check("kd", arrays["kd"], lambda a: a == 0, "0 in the specular (ref. [7]) model")
    try:
        shape = np.broadcast_shapes(*(arrays[name].shape for name in POINT_INPUTS))
    except ValueError:
        shapes = ", ".join(f"{name}{arrays[name].shape}" for name in POINT_INPUTS if arrays[name].ndim)
        raise ValueError(f"array arguments do not broadcast together: {shapes}") from None
    return arrays, shape, dtype_name


def _evaluate(quantity, theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
              model, engine):
    q = quantities.get(quantity, "points")
    quantity = q.name
    eng = resolve_engine(engine, backend)
    fused = eng.checks_domain(quantity)  # the kernel checks the values as it reads them (NaN)
    kw = dict(shadowing=shadowing, dtype=dtype, backend=backend, model=model)
    args = (theta_i, theta_r, phi, n, k, sigma, ks, kd, c)
    arrays, shape, dtype_name = validate(*args, **kw, values=not fused)
    points = int(np.prod(shape, dtype=np.int64))
    sizes.check_memory(points * q.width * np.dtype(DTYPES[dtype_name]).itemsize, f"the {quantity} of {points} points",
                       "evaluate fewer points per call; for a Cartesian product of axes use pbrdf_cl.grid, or "
                       "pbrdf-cl sweep (chunked into a Zarr store)")
    if eng.is_numpy:  # the reference broadcasts by itself
        out = eng.evaluate(quantity, arrays, shape, dtype=dtype_name, shadowing=shadowing)
    else:
        inputs = {name: (a if a.size == 1 or a.shape == shape else np.broadcast_to(a, shape))
                  for name, a in arrays.items()}
        out = eng.evaluate(quantity, inputs, shape, dtype=dtype_name, shadowing=shadowing)
    if not q.undefined_nan and not _all_finite(out):
        if fused:  # the kernel marks points outside the domain with NaN: name the first
            validate(*args, **kw)
        raise FloatingPointError(
            f"{quantity} is not finite in {dtype_name} (sigma too small for the specular peak's height, or "
            f"an input at the domain's edge that rounds outside it in {dtype_name}?); use dtype='float64' or "
            "a larger sigma")
    return out


def dop(theta_i, theta_r, phi=180.0, *, n, k, sigma=None, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
        dtype="float64", backend="auto", model="six-param", engine=None):
    """Degree of polarization for unpolarized incidence (eq. 17-18).

    ``model="specular"`` is the paper's ref. [7] (Thilak et al. 2007): kd = 0, and the DOP
    depends only on n, k and the geometry, so ``sigma`` may be omitted.
    Returns an array of the broadcast shape, in ``dtype``.

    ``backend``: "auto" (the OpenCL device, or the numpy reference when no device is usable),
    "opencl" (the device or an error) or "numpy" (the float64 reference).
    """
    if sigma is None and model == "specular":
        sigma = 1.0  # cancels: DOP of the specular term does not depend on sigma, ks or G
    return _evaluate("dop", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


def brdf(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
         dtype="float64", backend="auto", model="six-param", engine=None):
    """The BRDF for unpolarized light, F00 = F^s_00 + F^d_00, in 1/sr."""
    return _evaluate("brdf", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


def mueller(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
            dtype="float64", backend="auto", model="six-param", engine=None):
    """The 4x4 Mueller-matrix BRDF in the psps frames (NIST SCATMECH's convention), shape (..., 4, 4)."""
    return _evaluate("mueller", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


def aop(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
        dtype="float64", backend="auto", model="six-param", engine=None):
    """Angle of linear polarization of the reflected light for unpolarized incidence, in degrees in
    (-90, 90]: AoP = atan2(L2, L1) / 2 of the first column L of the Mueller matrix, in the psps frame
    of the outgoing beam (SCATMECH's; 0 means polarised along s, which is the case in plane, where
    Rs > Rp).  NaN where the DOP is 0 and the AoP is undefined (e.g. at the specular facet's normal
    incidence, b = 0).  The diffuse term is unpolarised, so the AoP depends on kd, c only through
    whether the DOP is 0."""
    return _evaluate("aop", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


def stokes(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
           dtype="float64", backend="auto", model="six-param", engine=None):
    """The Stokes vector (S0, S1, S2, S3) reflected for unpolarized incidence of unit radiance (the
    Mueller matrix's first column, 1/sr; psps frame of the outgoing beam), shape (..., 4): what a
    polarization camera measures, up to its radiometric scale.  S0 is F00; S3 is 0 in this model;
    DOP = sqrt(S1^2 + S2^2) / S0 and AoP = atan2(S2, S1) / 2."""
    return _evaluate("stokes", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


def evaluate(quantity, theta_i, theta_r, phi=180.0, *, n, k, sigma=None, ks=1.0, kd=0.0, c=0.0,
             shadowing="paper", dtype="float64", backend="auto", model="six-param", engine=None):
    """Any quantity of the registry by name ("dop", "brdf" or its alias "f00", "aop", "stokes",
    "mueller"): the same as calling :func:`dop`, :func:`brdf`, ... with the other arguments."""
    name = quantities.canonical(quantity, "points")
    if sigma is None and name == "dop" and model == "specular":
        sigma = 1.0  # as dop() does
    return _evaluate(name, theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)
