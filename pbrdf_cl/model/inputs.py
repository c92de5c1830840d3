"""The registry of the model's inputs: one record per input (the geometry and the six material
parameters), read by every path, beside :mod:`pbrdf_cl.model.quantities` (the outputs).

A record says what an input is (``kind``, ``family``: the factor of the model it enters), how to
show it (``long_name``, ``units``, ``symbol``, ``label``), its value where it is not given
(``default``), the search bounds of a fit (``bounds``) and the range the explorer's sliders span
(``view``), and the rule its values obey (``domain``, with the words of a refusal, ``rule``).
Everything else is derived here: :data:`NAMES` (the kernels' argument order), :data:`GEOMETRY`,
:data:`PARAMETERS`, :data:`FITTED`, :data:`DEFAULTS`, :data:`UNITS`, :data:`LONG_NAMES`,
:data:`LABELS`, :data:`DEFAULT_BOUNDS`, :data:`RULES`.  Adding an input (a dispersion parameter,
the incident light's polarization) is one record here, then its physics in ``kernels/pbrdf.h``
and ``model/reference.py``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Domain:
    """A valid range of values, as a mask: ``domain(a)``; its bounds make the minimum and the
    maximum of an array enough to check all of it (every value must also be finite)."""

    def __init__(self, lo=None, hi=None, lo_included=True, hi_included=False):
        self.lo, self.hi, self.lo_included, self.hi_included = lo, hi, lo_included, hi_included

    def __call__(self, a):
        ok = np.ones(np.shape(a), bool)
        if self.lo is not None:
            ok &= (a >= self.lo) if self.lo_included else (a > self.lo)
        if self.hi is not None:
            ok &= (a <= self.hi) if self.hi_included else (a < self.hi)
        return ok


class Input(NamedTuple):
    """One input of the model.

    name : canonical name (keyword of every API, column of a CSV, axis of a grid)
    kind : "geometry" (angles, degrees) or "material" (a parameter of the model)
    family : the factor of the model it enters: "geometry", "index" (the Fresnel factors: n, k),
        "specular" (the facet distribution and its weight: sigma, ks) or "diffuse" (kd, c); the
        grid's factor tables are per family
    long_name, units, symbol : for DataArray attrs and figures; ``label`` is the axis label
    default : its value where a caller does not give it (None: required)
    bounds : the search bounds of a fit by default (None: never fitted)
    view : the range the explorer's sliders and maps span by default
    domain, rule : the valid values (a :class:`Domain`) and the words that say them in a refusal
    fitted : whether the six-parameter fit varies it (ks is held: DOP sees kd/ks only, and only
        intensities free it)
    limits : the widest bounds a fit searches (None: the domain's): beyond them the grid stage's
        nodes and the descents' steps leave the range where the model's arithmetic and the search
        resolve it (``n`` up to 1e300 overflowed into a wrong fit labelled as a misfit)
    """

    name: str
    kind: str
    family: str
    long_name: str
    units: str
    symbol: str
    label: str
    default: float | None
    bounds: tuple | None
    view: tuple | None
    domain: Domain
    rule: str
    fitted: bool = False
    limits: tuple | None = None


_ZENITH = Domain(0.0, 90.0)

REGISTRY = {i.name: i for i in (
    Input("theta_i", "geometry", "geometry", "incidence zenith angle", "deg", "theta_i",
          "incidence zenith angle theta_i (deg)", None, None, (0.0, 89.0), _ZENITH, "in [0, 90) degrees"),
    Input("theta_r", "geometry", "geometry", "reflection zenith angle", "deg", "theta_r",
          "reflection zenith angle theta_r (deg)", None, None, (0.0, 89.0), _ZENITH, "in [0, 90) degrees"),
    Input("phi", "geometry", "geometry", "relative azimuth (180 = in plane)", "deg", "phi",
          "relative azimuth phi (deg, 180 = in plane)", 180.0, None, (0.0, 360.0), Domain(), "finite"),
    Input("n", "material", "index", "refractive index", "1", "n", "refractive index n", None, (1.0, 5.0),
          (1.0, 5.0), Domain(0.0, lo_included=False), "> 0", fitted=True, limits=(0.01, 100.0)),
    Input("k", "material", "index", "extinction coefficient", "1", "k", "extinction coefficient k", None,
          (0.0, 10.0), (0.0, 10.0), Domain(0.0), ">= 0", fitted=True, limits=(0.0, 100.0)),
    Input("sigma", "material", "specular", "per-axis rms slope", "1", "sigma", "per-axis rms slope sigma", None,
          (0.05, 1.0), (0.05, 1.0), Domain(0.0, lo_included=False), "> 0", fitted=True, limits=(1e-3, 10.0)),
    Input("ks", "material", "specular", "specular weight", "1", "ks", "specular weight ks", 1.0, (1e-3, 1e3),
          (0.05, 5.0), Domain(0.0, lo_included=False), "> 0", limits=(1e-6, 1e6)),
    Input("kd", "material", "diffuse", "diffuse weight", "1", "kd", "diffuse weight kd", 0.0, (0.0, 5.0),
          (0.0, 5.0), Domain(0.0), ">= 0", fitted=True, limits=(0.0, 1e3)),
    Input("c", "material", "diffuse", "Minnaert exponent", "1", "c", "Minnaert exponent c", 0.0, (-1.0, 0.0),
          (-1.0, 0.0), Domain(-1.0, 0.0, hi_included=True), "in [-1, 0]", fitted=True, limits=(-1.0, 0.0)),
)}

#: Every input, in the kernels' argument order (geometry, then the parameters).
NAMES = tuple(REGISTRY)
GEOMETRY = tuple(n for n, i in REGISTRY.items() if i.kind == "geometry")
#: The model's six parameters, in the order of the kernels' parameter vectors.
PARAMETERS = tuple(n for n, i in REGISTRY.items() if i.kind == "material")
#: The parameters the six-parameter fit varies (ks held; see :class:`Input`).
FITTED = tuple(n for n, i in REGISTRY.items() if i.fitted)
#: The parameters of the Fresnel factors alone: what the specular reference model (ref. [7]) fits.
INDEX = tuple(n for n, i in REGISTRY.items() if i.family == "index")
FAMILIES = ("geometry", "index", "specular", "diffuse")
#: The inputs of each family, in their order: ``MEMBERS["specular"] == ("sigma", "ks")``.
MEMBERS = {f: tuple(n for n, i in REGISTRY.items() if i.family == f) for f in FAMILIES}
DEFAULTS = {n: i.default for n, i in REGISTRY.items() if i.default is not None}
UNITS = {n: i.units for n, i in REGISTRY.items()}
LONG_NAMES = {n: i.long_name for n, i in REGISTRY.items()}
LABELS = {n: i.label for n, i in REGISTRY.items()}
#: The fit's default search bounds: the fitted parameters first, then ks (freed by intensities).
DEFAULT_BOUNDS = {n: REGISTRY[n].bounds for n in FITTED + tuple(n for n in PARAMETERS if n not in FITTED)
                  if REGISTRY[n].bounds is not None}
#: The widest bounds a fit searches, per parameter (:attr:`Input.limits`).
BOUND_LIMITS = {n: i.limits for n, i in REGISTRY.items() if i.limits is not None}
VIEWS = {n: i.view for n, i in REGISTRY.items() if i.kind == "material"}
#: The valid range of each input, as (test, words); every input must also be finite.  The vector
#: kernels of ``kernels/pbrdf_points.cl`` check the same (``PB_IN_DOMAIN``).
RULES = {n: (i.domain, i.rule) for n, i in REGISTRY.items()}


def family_index(name):
    """The index of ``name``'s family in :data:`FAMILIES` (0 geometry, 1 index, 2 specular, 3 diffuse)."""
    return FAMILIES.index(REGISTRY[name].family)


def refuse_where(name, a, ok, rule):
    """A one-line ``ValueError`` where some value of the array ``a`` fails ``ok``: "``name`` must be
    ``rule``, got the first such value (at its index)"."""
    bad = ~ok(a)
    if bad.any():
        where = f" at index {np.argwhere(bad)[0].tolist()}" if a.ndim else ""
        raise ValueError(f"{name} must be {rule}, got {float(a[bad].flat[0])!r}{where}")


def refuse_outside(name, a):
    """A one-line ``ValueError`` naming ``name`` and the first value of the array ``a`` that is not
    finite or breaks its rule (:data:`RULES`), with its index; nothing where every value is good."""
    refuse_where(name, a, np.isfinite, "finite")
    refuse_where(name, a, *RULES[name])
