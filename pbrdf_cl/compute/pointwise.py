"""Public API: DOP, F00, AoP, the Stokes vector and the Mueller matrix of the six-parameter pBRDF model.

Angles are in degrees: ``theta_i``, ``theta_r`` in [0, 90); ``phi`` is the relative
azimuth phi_i - phi_r, 180 being the in-plane (specular) geometry.  ``sigma`` is the
per-axis slope standard deviation.  All array arguments broadcast together.
"""
from __future__ import annotations

import numpy as np

from .. import sizes
from ..device import engine as _engine
from ..device.engine import BACKENDS, DTYPES, POINT_INPUTS, check_backend, compact_values, resolve_engine  # noqa: F401,E501 (pointwise.BACKENDS stays)
from ..errors import UnitsWarning  # noqa: F401 (pointwise.UnitsWarning stays)
from ..model import inputs, quantities, reference

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


#: Elements per block of the one-read checks: the minimum and maximum of each block are taken
#: while it is in cache.
CHECK_BLOCK = 1 << 16


def _blocks(a):
    """The values of the non-empty array ``a`` in blocks of at most :data:`CHECK_BLOCK` elements in
    memory order (a transposed or strided array too; a broadcast view's repeated axes are read
    once), no temporary beyond a block."""
    a = compact_values(a, a.ndim)
    if a.size <= CHECK_BLOCK:
        return [a]
    return np.nditer(a, flags=["external_loop", "buffered"], buffersize=CHECK_BLOCK, order="K")


def _min_max(a):
    """``(min, max)`` of the non-empty array ``a`` (NaN when it holds one: NaN propagates) in one
    read (:func:`_blocks`), the minimum and maximum of each block taken while it is in cache."""
    lo = hi = None
    for block in _blocks(a):
        b_lo, b_hi = np.min(block), np.max(block)
        lo = b_lo if lo is None else np.minimum(lo, b_lo)
        hi = b_hi if hi is None else np.maximum(hi, b_hi)
    return lo, hi


def _all_finite(a):
    """Whether every value is finite: one read (:func:`_min_max`) and no temporary."""
    return a.size == 0 or bool(np.all(np.isfinite(_min_max(a))))


#: The valid range of each input, as (test, words) (:data:`pbrdf_cl.model.inputs.RULES`).
RULES = inputs.RULES


def check_values(name, value):
    """``value`` as a float64 array, or a ``ValueError`` naming ``name`` and the first bad value."""
    a = _as_array(name, value).astype(np.float64, copy=False)
    _check_domain(name, a)
    return a


def _check_domain(name, a):
    """Every value of ``a`` (either float dtype) finite and in ``RULES[name]``, else a ``ValueError``
    naming the first bad one; one read (:func:`_min_max`) when all is well.  Returns ``(min, max)``
    (None for an empty array)."""
    ok, rule = RULES[name]
    if a.size:
        lo, hi = _min_max(a)  # NaN propagates
        if np.isfinite(lo) and np.isfinite(hi) and ok(lo) and ok(hi):
            return float(lo), float(hi)
        inputs.refuse_outside(name, a)


#: Zenith angles that all lie below this many degrees (and are not all 0) look like radians.
RADIANS_HINT = 1.6


def _reaches(a, x):
    """Whether some value of the non-empty array ``a`` is >= ``x``, read block by block
    (:func:`_blocks`) up to the first block that holds one."""
    return any(np.max(block) >= x for block in _blocks(a))


def radians_suspect(theta_i, theta_r, bounds=None):
    """The largest zenith angle when every one lies in [0, 1.6) and not all are 0 (such angles are
    almost always radians: pbrdf-cl takes degrees), else None.  ``bounds``: name -> (min, max)
    already read (by :func:`_check_domain`); the other arrays are read up to their first block
    holding an angle >= 1.6 (usually the first: degrees), and only where there is none in full
    (:func:`_min_max`)."""
    ranges = []
    for name, a in (("theta_i", theta_i), ("theta_r", theta_r)):
        known = (bounds or {}).get(name)
        if known is None and np.size(a):
            if _reaches(np.asarray(a), RADIANS_HINT):
                return None
            known = tuple(float(v) for v in _min_max(np.asarray(a)))
        ranges.append(known if known is not None else (0.0, 0.0))
    lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
    return hi if 0.0 < hi < RADIANS_HINT and lo >= 0.0 else None


def check_degrees(theta_i, theta_r, where="", bounds=None):
    """Warn (:class:`UnitsWarning`) when the zenith angles look like radians (:func:`radians_suspect`)."""
    hi = radians_suspect(theta_i, theta_r, bounds)
    if hi is not None:
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
    """Check and broadcast the inputs of the per-point functions.

    Parameters
    ----------
    theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend, model
        As for :func:`dop`.
    values : bool, default True
        False checks only the options, types and shapes (the vector kernels check the values
        themselves, writing NaN for a point outside the domain, and the caller checks again, to
        name the offender, only when the result holds a NaN).

    Returns
    -------
    (dict, tuple, str)
        The arrays by name (float32 and float64 arrays as they are, anything else as float64),
        the broadcast shape and the dtype's name.

    Raises
    ------
    ValueError
        Naming the offending argument, value and index.

    Examples
    --------
    >>> arrays, shape, dtype = validate(40, [20, 45], 180, 1.6, 2.1, 0.5, 1, 0, 0)
    >>> shape, dtype
    ((2,), 'float64')
    """
    dtype_name = check_options(shadowing, dtype)
    check_backend(backend)
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if sigma is None:
        raise ValueError("sigma is required (the per-axis slope standard deviation, > 0)")
    given = dict(theta_i=theta_i, theta_r=theta_r, phi=phi, n=n, k=k, sigma=sigma, ks=ks, kd=kd, c=c)
    arrays = {name: _as_array(name, given[name]) for name in POINT_INPUTS}
    bounds = {name: _check_domain(name, arrays[name]) for name in POINT_INPUTS} if values else None
    check_degrees(arrays["theta_i"], arrays["theta_r"], bounds=bounds)  # the bounds read above, if any
    if model == "specular":
        inputs.refuse_where("kd", arrays["kd"], lambda a: a == 0, "0 in the specular (ref. [7]) model")
    try:
        shape = np.broadcast_shapes(*(arrays[name].shape for name in POINT_INPUTS))
    except ValueError:
        shapes = ", ".join(f"{name}{arrays[name].shape}" for name in POINT_INPUTS if arrays[name].ndim)
        raise ValueError(f"array arguments do not broadcast together: {shapes}") from None
    return arrays, shape, dtype_name


@_engine.falls_back
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
    # the arrays as given: the reference broadcasts by itself, the device engine sends a short axis
    # once with its index rule (engine.input_plan) and gathers only other broadcast patterns
    out = eng.evaluate(quantity, arrays, shape, dtype=dtype_name, shadowing=shadowing)
    if not q.undefined_nan and not _all_finite(out):
        if fused:  # the kernel marks points outside the domain with NaN: name the first
            validate(*args, **kw)
        raise FloatingPointError(
            f"{quantity} is not finite in {dtype_name} (sigma too small for the specular peak's height, or "
            f"an input at the domain's edge that rounds outside it in {dtype_name}?); use dtype='float64' or "
            "a larger sigma")
    return out


#: The Parameters section shared by the per-point functions (numpydoc).
_POINT_PARAMETERS = """
    theta_i, theta_r : float or array_like
        Zenith angles of incidence and reflection in degrees, in [0, 90). All array arguments
        broadcast together; a short axis (``theta_r[:, None]``, ``sigma[None, :]``) is sent to the
        device once, its values read through an index rule, never expanded.
    phi : float or array_like, default 180
        Relative azimuth phi_i - phi_r in degrees; 180 is the plane of incidence on the specular side.
    n, k : float or array_like
        Complex refractive index n + ik of the surface (n > 0, k >= 0).
    sigma : float or array_like
        Slope standard deviation per axis (> 0; SCATMECH's total rms slope is sqrt(2) sigma).
    ks, kd : float or array_like, default 1 and 0
        Weights of the specular (> 0) and diffuse (>= 0) terms.
    c : float or array_like, default 0
        Minnaert exponent of the diffuse term, in [-1, 0] (0: Lambertian).
    shadowing : {"paper", "smith", "none"}, default "paper"
        The shadowing function: the paper's eq. 7-9, Smith's, or none.
    dtype : {"float64", "float32"}, default "float64"
        Precision of the computation and of the result.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        "auto": the OpenCL device, or the float64 numpy reference when no device is usable (a
        ``DeviceWarning`` says so); "opencl": the device or an error; "numpy": the reference.
    model : {"six-param", "specular"}, default "six-param"
        "specular" is the paper's ref. [7] (Thilak et al. 2007): kd must be 0.
    engine : pbrdf_cl.Engine, optional
        The engine (device) to use instead of the default one.

    Raises
    ------
    ValueError
        Naming the argument, the first bad value and its index.
    pbrdf_cl.TooLargeError
        When the result cannot fit in memory (found before any work)."""


def _documented(func):
    """Put the shared Parameters section where the docstring says ``{parameters}``."""
    func.__doc__ = func.__doc__.replace("    {parameters}", _POINT_PARAMETERS.strip("\n"))
    return func


@_documented
def dop(theta_i, theta_r, phi=180.0, *, n, k, sigma=None, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
        dtype="float64", backend="auto", model="six-param", engine=None):
    """Degree of polarization for unpolarized incidence (eq. 17-18).

    With ``model="specular"`` the DOP depends only on n, k and the geometry, so ``sigma`` may be
    omitted.

    Parameters
    ----------
    {parameters}

    Returns
    -------
    numpy.ndarray
        The DOP in [0, 1], of the broadcast shape, in ``dtype``.

    Examples
    --------
    >>> import pbrdf_cl
    >>> d = pbrdf_cl.dop(40, [20, 45, 65], n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
    >>> d.shape
    (3,)
    """
    if sigma is None and model == "specular":
        sigma = 1.0  # cancels: DOP of the specular term does not depend on sigma, ks or G
    return _evaluate("dop", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


@_documented
def brdf(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
         dtype="float64", backend="auto", model="six-param", engine=None):
    """The BRDF for unpolarized light, F00 = F^s_00 + F^d_00.

    Parameters
    ----------
    {parameters}

    Returns
    -------
    numpy.ndarray
        F00 in 1/sr, of the broadcast shape, in ``dtype``.

    Examples
    --------
    >>> import pbrdf_cl
    >>> float(pbrdf_cl.brdf(40, 45, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)) > 0
    True
    """
    return _evaluate("brdf", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


@_documented
def mueller(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
            dtype="float64", backend="auto", model="six-param", engine=None):
    """The 4x4 Mueller-matrix BRDF in the psps frames (NIST SCATMECH's convention).

    Parameters
    ----------
    {parameters}

    Returns
    -------
    numpy.ndarray
        Shape ``broadcast shape + (4, 4)``, in 1/sr; element [0, 0] is F00.

    Examples
    --------
    >>> import pbrdf_cl
    >>> pbrdf_cl.mueller(40, [20, 45], phi=150, n=1.6, k=2.139, sigma=0.5).shape
    (2, 4, 4)
    """
    return _evaluate("mueller", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


@_documented
def aop(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
        dtype="float64", backend="auto", model="six-param", engine=None):
    """Angle of linear polarization of the reflected light for unpolarized incidence.

    AoP = atan2(L2, L1) / 2 of the first column L of the Mueller matrix, in the psps frame of the
    outgoing beam (SCATMECH's): 0 means polarised along s, which is the case in plane, where
    Rs > Rp.  The diffuse term is unpolarised and the Fresnel factor only scales the linear part,
    so wherever it is defined the AoP depends on the geometry alone.

    Parameters
    ----------
    {parameters}

    Returns
    -------
    numpy.ndarray
        Degrees in (-90, 90], of the broadcast shape; NaN where the DOP is 0 and the AoP is
        undefined (e.g. the specular facet at normal incidence, b = 0).

    Examples
    --------
    >>> import pbrdf_cl
    >>> float(pbrdf_cl.aop(40, 45, phi=180, n=1.6, k=2.139, sigma=0.5))
    0.0
    """
    return _evaluate("aop", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)


@_documented
def stokes(theta_i, theta_r, phi=180.0, *, n, k, sigma, ks=1.0, kd=0.0, c=0.0, shadowing="paper",
           dtype="float64", backend="auto", model="six-param", engine=None, incident=None):
    """The Stokes vector reflected for incident light of unit radiance, unpolarized or polarized.

    In the psps frame of the outgoing beam (SPEC; ``docs/polarimetry.md``): unpolarized, the
    Mueller matrix's first column, what a polarization camera measures under an unpolarized lamp
    (S0 is F00, S3 is 0 in this model, DOP = sqrt(S1^2 + S2^2) / S0, AoP = atan2(S2, S1) / 2);
    with ``incident``, F S_in, S_in = (1, s1, s2, s3) given in the incoming beam's frame.

    Parameters
    ----------
    incident : array-like, optional
        The incident light's normalised Stokes vector (s1, s2, s3), shape ``(3,)`` or broadcasting
        against the points with a trailing axis of 3: (1, 0, 0) is linear polarization along the
        incoming beam's s axis (perpendicular to its plane of incidence), (0, 1, 0) at +45 degrees
        from s towards p, (0, 0, 1) circular.  s1^2 + s2^2 + s3^2 <= 1.  None: unpolarized.
    {parameters}

    Returns
    -------
    numpy.ndarray
        Shape ``broadcast shape + (4,)``: (S0, S1, S2, S3) in 1/sr.

    Examples
    --------
    >>> import pbrdf_cl
    >>> pbrdf_cl.stokes(40, [20, 45], phi=150, n=1.6, k=2.139, sigma=0.5).shape
    (2, 4)
    >>> s = pbrdf_cl.stokes(40, 45, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3, incident=(0, 1, 0))
    >>> [round(float(v), 5) for v in s[1:] / s[0]]   # SPEC's check values, source at 45 degrees
    [0.16759, -0.60201, -0.2387]
    """
    if incident is None:
        return _evaluate("stokes", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                         model, engine)
    s_in = check_incident(incident)
    M = _evaluate("mueller", theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend, model,
                  engine)
    return np.einsum("...ij,...j->...i", M, s_in).astype(M.dtype, copy=False)


def check_incident(incident):
    """The incident Stokes vectors (1, s1, s2, s3) from ``incident`` (s1, s2, s3): a trailing axis
    of 3, every vector at most fully polarised; one-line ``ValueError``s otherwise."""
    try:
        a = np.asarray(incident, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"incident must be (s1, s2, s3) numbers, got {incident!r}") from None
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"incident must be the normalised Stokes vector (s1, s2, s3): a trailing axis of 3, got "
                         f"shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError("incident must be finite numbers")
    norm2 = (a * a).sum(axis=-1)
    if (norm2 > 1.0 + 1e-9).any():
        i = np.unravel_index(int(np.argmax(norm2)), norm2.shape) if norm2.ndim else ()
        raise ValueError(f"incident {tuple(float(v) for v in a[i])} is not a Stokes vector: s1^2 + s2^2 + s3^2 = "
                         f"{float(norm2[i]):.4g} > 1 (normalised by S0)")
    return np.concatenate([np.ones(a.shape[:-1] + (1,)), a], axis=-1)


@_documented
def evaluate(quantity, theta_i, theta_r, phi=180.0, *, n, k, sigma=None, ks=1.0, kd=0.0, c=0.0,
             shadowing="paper", dtype="float64", backend="auto", model="six-param", engine=None):
    """Any quantity of the registry (:mod:`pbrdf_cl.quantities`) by name.

    The same as calling :func:`dop`, :func:`brdf`, :func:`aop`, :func:`stokes` or :func:`mueller`.

    Parameters
    ----------
    quantity : str
        "dop", "brdf" (or its alias "f00"), "aop", "stokes" or "mueller".
    {parameters}

    Returns
    -------
    numpy.ndarray
        As the function of that quantity returns.

    Examples
    --------
    >>> import pbrdf_cl
    >>> f00 = pbrdf_cl.evaluate("f00", 40, 45, n=1.6, k=2.139, sigma=0.5)
    >>> float(f00) == float(pbrdf_cl.brdf(40, 45, n=1.6, k=2.139, sigma=0.5))
    True
    """
    name = quantities.canonical(quantity, "points")
    if sigma is None and name == "dop" and model == "specular":
        sigma = 1.0  # as dop() does
    return _evaluate(name, theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing, dtype, backend,
                     model, engine)
