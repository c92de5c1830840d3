"""Instruments for the measurement design: what is measured at each geometry.

An instrument is the same list of channels at every geometry: measurable quantities of
``pbrdf_cl.model.measurables`` (the DOP, the normalised Stokes components s1..s3 = S_j / S0,
the normalised Mueller elements m_ij = M_ij / M00) under one or more incident states (the source's
normalised Stokes vector (s1, s2, s3) in the incoming beam's frame; SPEC, "Polarized incidence and
polarimetric measurements"), and one noise: the standard deviation of each normalised quantity.
:data:`REGISTRY` holds the instruments :func:`pbrdf_cl.design` compares by name:

- ``dop``: the DOP under an unpolarised source (1 channel per geometry);
- ``camera45`` (alias ``camera``): a linear polarization camera's s1, s2 with the source
  linearly polarised at 45 degrees, S_in = (1, 0, 1, 0) (2 channels);
- ``camera4``: s1, s2 under four linear source states (0, 45, 90, 135 degrees) and circular
  (0, 0, 1) (10 channels);
- ``mueller``: a Mueller polarimeter's 15 elements normalised by M00 (15 channels).

Users give their own as text, ``QUANTITIES[@STATES]`` (``s1+s2@0+90``, ``dop@45``, or a registry
name with other states, ``camera@0+45+circular``), or as a dict (``quantities``, ``states``,
``noise``, ``name``).  A state is a linear polariser's angle in degrees from the incoming beam's s
axis towards its p axis (S_in = (1, cos 2a, sin 2a, 0)), ``circular`` (0, 0, 1), ``-circular``,
``unpolarized``, or (in a dict) the vector (s1, s2, s3) itself.

Only normalised quantities are instruments' channels (their noise is one number in the
quantities' own units, and like the DOP they depend on ks and kd only through kd/ks); absolute
intensities are the design's ``intensity`` rows (F00).  The channels' values come from the
model's Mueller matrix by arithmetic (``pbrdf_cl.model.measurables.Channels.values_of``), never
from physics written here.
"""
from __future__ import annotations

import difflib
import numbers
from dataclasses import dataclass, replace

import numpy as np

from ..compute.pointwise import check_incident
from ..model import measurables

UNPOLARISED = (0.0, 0.0, 0.0)
#: Named source states: their normalised Stokes vectors (s1, s2, s3).
STATES = {"unpolarized": UNPOLARISED, "unpolarised": UNPOLARISED, "circular": (0.0, 0.0, 1.0),
          "-circular": (0.0, 0.0, -1.0)}
#: The quantities an instrument may measure: the normalised ones.
QUANTITIES = ("dop", "s1", "s2", "s3") + measurables.MUELLER[1:]
#: Absolute quantities and the AoP, refused with the reason.
REFUSED = {**{q: "an absolute intensity: give intensity=True (F00 rows) instead" for q in ("s0", "m00", "f00")},
           "aop": "its noise is in degrees and wraps at 180: give s1 and s2, whose angle it is"}


def linear(angle):
    """The normalised Stokes vector of light linearly polarised at ``angle`` degrees from the s
    axis towards the p axis: (cos 2a, sin 2a, 0), exact zeros where a is a multiple of 45."""
    a = np.deg2rad(2.0 * float(angle))
    return (round(float(np.cos(a)), 15) + 0.0, round(float(np.sin(a)), 15) + 0.0, 0.0)


@dataclass(frozen=True)
class Instrument:
    """What an instrument measures at each geometry (:data:`REGISTRY`; made and checked by
    :func:`instruments` from a name, text or a dict).

    Parameters
    ----------
    name : str
        Its name in a design's tables.
    description : str
        What it measures, in words.
    quantities : tuple of str
        Normalised measurable quantities: ``"dop"``, ``"s1"``, ``"s2"``, ``"s3"`` (S_j / S0),
        ``"m01"`` ... ``"m33"`` (M_ij / M00), in the order of a measurement row.
    states : tuple of tuple
        The source states, each the incident light's normalised Stokes vector (s1, s2, s3) in the
        incoming beam's frame; every quantity is measured under each.
    noise : float or None
        The standard deviation of each number measured; None: the design's ``noise``.
    """
    name: str
    description: str
    quantities: tuple
    states: tuple = (UNPOLARISED,)
    noise: float | None = None

    @property
    def per_geometry(self):
        """Channels per geometry."""
        return len(self.quantities) * len(self.states)

    @property
    def unpolarised_dop(self):
        """Whether this is the DOP under an unpolarised source: the design's own DOP rows."""
        return tuple(self.quantities) == ("dop",) and tuple(self.states) == (UNPOLARISED,)

    def channels(self, theta_i, theta_r, phi):
        """The instrument's channels at some geometries.

        Parameters
        ----------
        theta_i, theta_r, phi : array-like
            The geometries, 1-d (or scalars), degrees.

        Returns
        -------
        pbrdf_cl.model.measurables.Channels
            ``pbrdf_cl.model.measurables.channels`` of a measurement row per geometry and source
            state (geometry-major), :attr:`per_geometry` channels per geometry.
        """
        S = len(self.states)
        geo = [np.repeat(np.atleast_1d(np.asarray(a, dtype=np.float64)), S) for a in (theta_i, theta_r, phi)]
        rows = geo[0].size
        incident = np.tile(np.asarray(self.states, dtype=np.float64), (rows // S, 1))
        return measurables.channels(*geo, {q: np.zeros(rows) for q in self.quantities}, incident=incident)

    def values(self, F):
        """The channels' values from the model's Mueller matrices.

        Parameters
        ----------
        F : array-like
            Mueller matrices (..., 4, 4) with K and fd folded in, as :func:`pbrdf_cl.mueller`
            returns them.

        Returns
        -------
        numpy.ndarray
            (..., c), c = :attr:`per_geometry`, in the order of :meth:`channels` at one geometry:
            arithmetic on ``F`` (s_j = (F u)_j / (F u)_0 for a source state u, ...).
        """
        return self.channels(0.0, 0.0, 180.0).values_of(np.asarray(F)[..., None, :, :])

    def info(self):
        """The instrument as plain data (a design's ``instruments``)."""
        return dict(name=self.name, description=self.description, quantities=list(self.quantities),
                    states=[list(s) for s in self.states], noise=self.noise, per_geometry=self.per_geometry)


def _registry():
    cam4 = tuple(linear(a) for a in (0, 45, 90, 135)) + (STATES["circular"],)
    return {i.name: i for i in (
        Instrument("dop", "DOP, unpolarised source", ("dop",)),
        Instrument("camera45", "s1, s2 (linear polarization camera), source linear at 45 deg", ("s1", "s2"),
                   (linear(45),)),
        Instrument("camera4", "s1, s2 under sources linear at 0, 45, 90, 135 deg and circular", ("s1", "s2"), cam4),
        Instrument("mueller", "the 15 Mueller elements m_ij = M_ij / M00 (Mueller polarimeter)",
                   measurables.MUELLER[1:]),
    )}


#: The instruments :func:`pbrdf_cl.design` knows by name: ``dop``, ``camera45``, ``camera4``, ``mueller``.
REGISTRY = _registry()
ALIASES = {"camera": "camera45"}
FORMS = ("the instruments are " + ", ".join(REGISTRY) + " (camera: camera45), or QUANTITIES[@STATES] such as "
         "s1+s2@0+45+circular, or a dict of quantities, states, noise")


def _nearest(word, choices):
    close = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_noise(where, noise):
    """An instrument's noise: a positive number below 1 (normalised quantities lie in [-1, 1])."""
    if isinstance(noise, (bool, np.bool_)) or not isinstance(noise, numbers.Real) or not np.isfinite(noise) \
            or noise <= 0:
        raise ValueError(f"{where}: noise must be a positive number, got {noise!r}")
    if noise >= 1.0:
        raise ValueError(f"{where}: noise must be below 1, the normalised quantities lie in [-1, 1], got {noise:g} "
                         "(a percentage? 0.5% is 0.005)")
    return float(noise)


def _state(where, s):
    """One source state: a name, an angle (degrees) or a vector (s1, s2, s3), as a tuple."""
    if isinstance(s, str):
        word = s.strip().lower()
        if word in STATES:
            return STATES[word]
        try:
            return linear(float(word))
        except ValueError:
            raise ValueError(f"{where}: unknown source state {s!r}{_nearest(word, STATES)}; a state is a linear "
                             "polariser's angle in degrees, circular, -circular, unpolarized or (s1, s2, s3)") \
                from None
    if isinstance(s, numbers.Real) and not isinstance(s, (bool, np.bool_)):
        if not np.isfinite(s):
            raise ValueError(f"{where}: a source state's angle must be finite, got {s!r}")
        return linear(s)
    try:
        u = check_incident(s)
    except ValueError as exc:
        raise ValueError(f"{where}: source state: {exc}") from None
    if u.shape != (4,):
        raise ValueError(f"{where}: a source state is one (s1, s2, s3) vector, got shape {np.shape(s)}")
    return tuple(float(x) for x in u[1:])


def _quantities(where, qs):
    if isinstance(qs, str):
        qs = [q for q in qs.replace("+", ",").split(",") if q.strip()]
    qs = [str(q).strip().lower() for q in qs]
    if not qs:
        raise ValueError(f"{where}: give at least one quantity, e.g. s1+s2")
    for q in qs:
        if q in REFUSED:
            raise ValueError(f"{where}: {q!r} cannot be an instrument's channel: {REFUSED[q]}")
        if q not in QUANTITIES:
            raise ValueError(f"{where}: unknown quantity {q!r}{_nearest(q, QUANTITIES)}; the quantities are dop, "
                             "s1, s2, s3, m01 .. m33")
    if len(set(qs)) != len(qs):
        raise ValueError(f"{where}: a quantity is named twice in {'+'.join(qs)}")
    return tuple(q for q in QUANTITIES if q in qs)  # the registry's order, as in a measurement row


def _make(where, name, quantities, states, noise, description=None):
    """A checked :class:`Instrument`."""
    qs = _quantities(where, quantities)
    if states is None:
        states = [UNPOLARISED]
    elif isinstance(states, str):
        states = [s for s in states.replace("+", ",").split(",") if s.strip()]
    states = [_state(where, s) for s in states]
    if not states:
        raise ValueError(f"{where}: give at least one source state")
    if len(set(states)) != len(states):
        raise ValueError(f"{where}: a source state is given twice")
    mueller = [q for q in qs if q.startswith("m")]
    if mueller and states != [UNPOLARISED]:
        raise ValueError(f"{where}: Mueller elements ({mueller[0]}) do not depend on the source state: give them "
                         "without states")
    if noise is not None:
        noise = check_noise(where, noise)
    if description is None:
        description = "+".join(qs) + ("" if states == [UNPOLARISED] else
                                      f", {len(states)} source state{'s' if len(states) > 1 else ''}")
    return Instrument(name, description, qs, tuple(states), noise)


def instrument(spec, where="instrument"):
    """One instrument from ``spec``: a registry name, ``QUANTITIES[@STATES]`` text, a dict
    (``quantities``, optional ``states``, ``noise``, ``name``, ``description``) or an
    :class:`Instrument`; one-line ``ValueError``s naming what is wrong."""
    if isinstance(spec, Instrument):
        return _make(where, spec.name, spec.quantities, spec.states, spec.noise, spec.description)
    if isinstance(spec, dict):
        unknown = sorted(set(spec) - {"name", "quantities", "states", "noise", "description"})
        if unknown:
            raise ValueError(f"{where}: unknown key {unknown[0]!r}{_nearest(unknown[0], ('quantities', 'states'))} "
                             "; the keys are quantities, states, noise, name, description")
        if "quantities" not in spec:
            raise ValueError(f"{where}: a dict needs quantities, e.g. dict(quantities=('s1', 's2'), states=(45,))")
        name = spec.get("name") or "+".join(_quantities(where, spec["quantities"]))
        return _make(f"{where} {name!r}", str(name), spec["quantities"], spec.get("states"), spec.get("noise"),
                     spec.get("description"))
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"{where}: give a name, QUANTITIES[@STATES] text or a dict, got {spec!r:.60}; {FORMS}")
    text = spec.strip()
    head, _, states = text.partition("@")
    key = ALIASES.get(head.strip().lower(), head.strip().lower())
    if key in REGISTRY:
        base = REGISTRY[key]
        if not states:
            return base
        return _make(f"{where} {text!r}", text, base.quantities, states, None)
    if "+" not in head and key not in QUANTITIES and key not in REFUSED:
        raise ValueError(f"{where}: unknown {head.strip()!r}{_nearest(key, [*REGISTRY, *ALIASES, *QUANTITIES])}; "
                         f"{FORMS}")
    return _make(f"{where} {text!r}", text, head, states or None, None)


def instruments(spec, noise):
    """The instruments of ``design(instrument=...)``, checked.

    Parameters
    ----------
    spec : str, dict, Instrument or sequence
        One instrument or several: a name of :data:`REGISTRY` (``"dop"``, ``"camera45"`` or
        ``"camera"``, ``"camera4"``, ``"mueller"``), ``QUANTITIES[@STATES]`` text joined by
        ``+`` (``"s1+s2@0+90"``, ``"camera@0+45+circular"``), a dict (``quantities``, optional
        ``states``, ``noise``, ``name``, ``description``; states may be (s1, s2, s3) vectors), a
        comma-separated text of several, or a sequence of these.
    noise : float
        The noise of the instruments without their own.

    Returns
    -------
    list of Instrument
        Each with its noise; one-line ``ValueError`` for an unknown name (the nearest offered), a
        source state that is not a Stokes vector, a noise that is not positive, a name given twice.

    Examples
    --------
    >>> from pbrdf_cl.analysis.instruments import instruments
    >>> [(i.name, i.per_geometry) for i in instruments("dop,camera4,s1+s2@0+90", 0.005)]
    [('dop', 1), ('camera4', 10), ('s1+s2@0+90', 4)]
    """
    if isinstance(spec, str):
        spec = [s for s in spec.split(",") if s.strip()]
    elif not isinstance(spec, (list, tuple)):
        spec = [spec]  # a dict, an Instrument, or something instrument() refuses in one line
    out = [instrument(s) for s in spec]
    if not out:
        raise ValueError(f"instrument: give at least one; {FORMS}")
    names = [i.name for i in out]
    for n in names:
        if names.count(n) > 1:
            raise ValueError(f"instrument: {n!r} is named twice")
    return [i if i.noise is not None else replace(i, noise=float(noise)) for i in out]


# ------------------------------------------------------------------------- a design's instrument table

def _cell(c, n):
    if n not in c["widths"]:
        return "-"
    if n in c["undetermined"]:
        return "undet."
    return f"{c['widths'][n]:.3g} ({c['se'][n]:.3g})"


def instrument_table(result):
    """The lines of a design's instrument comparison (:meth:`pbrdf_cl.DesignResult.summary`): per
    set of geometries (the reference, then the chosen), one row per instrument, the predicted 95%
    widths of the free parameters with the standard errors in parentheses side by side, then what
    each instrument measures; no lines without instruments."""
    comp = result.get("instrument_comparisons")
    if not comp:
        return []
    names = list(result.free)
    kd = "kd" if "ks" in result.get("fixed", {}) else "kd/ks"
    labels = {"reference": "paper 30/40/50 x 20..65" if result.reference_is_paper else "reference",
              "chosen": f"chosen ({result.criterion}) for {result.instruments[0]['name']}"}
    lines = ["", "instruments at the same geometries: predicted 95% interval widths (standard errors)"
             + (", each with F00 rows" if result.intensity else "")]
    head = f"  {'instrument':<14s}{'chan.':>6s}{'noise':>8s}" + "".join(f"{kd if n == 'kd' else n:>18s}" for n in names)
    undetermined = False
    for key in ("reference", "chosen"):
        first = next(iter(comp[key].values()))
        lines += [f" {labels[key]}, {first['n_points']} points:", head]
        for info in result.instruments:
            c = comp[key][info["name"]]
            undetermined = undetermined or bool(c["undetermined"])
            lines.append(f"  {info['name'][:13]:<14s}{info['per_geometry']:>6d}{info['noise']:>8.3g}"
                         + "".join(f"{_cell(c, n):>18s}" for n in names))
    lines.append("  chan.: channels per geometry; noise: standard deviation of each normalised quantity"
                 + ("; undet.: the interval spans the whole bounds" if undetermined else ""))
    lines += [f"  {i['name']}: {i['description']}" for i in result.instruments]
    return lines


def instrument_variables(result):
    """A design's instrument comparison as Dataset variables and coordinates (``to_dataset``):
    ``instrument_width``, ``instrument_se``, ``instrument_undetermined`` over (instrument_set,
    instrument, parameter_all), and each instrument's description, noise and channels per geometry."""
    import xarray as xr
    comp = result.instrument_comparisons
    sets, names, allp = list(comp), [i["name"] for i in result.instruments], result.compared

    def grid(get):
        return np.array([[[get(comp[s][i], n) for n in allp] for i in names] for s in sets])
    dims = ("instrument_set", "instrument", "parameter_all")
    data = {
        "instrument_width": xr.Variable(dims, grid(lambda c, n: c["widths"].get(n, np.nan)),
                                        {"long_name": "predicted 95% interval width per instrument (NaN: not free)"}),
        "instrument_se": xr.Variable(dims, grid(lambda c, n: c["se"].get(n, np.nan)),
                                     {"long_name": "predicted standard error per instrument (before clipping to the "
                                                   "bounds; inf: along the data's null space)"}),
        "instrument_undetermined": xr.Variable(dims, grid(lambda c, n: n in c["undetermined"]).astype(np.int8),
                                               {"long_name": "1 where the instrument does not determine the "
                                                             "parameter (its interval spans the whole bounds)"}),
        "instrument_description": xr.Variable(("instrument",), [i["description"] for i in result.instruments]),
        "instrument_noise": xr.Variable(("instrument",), [i["noise"] for i in result.instruments],
                                        {"long_name": "standard deviation of each normalised quantity"}),
        "instrument_channels": xr.Variable(("instrument",), [i["per_geometry"] for i in result.instruments],
                                           {"long_name": "channels per geometry"}),
    }
    return data, {"instrument": names, "instrument_set": sets}
