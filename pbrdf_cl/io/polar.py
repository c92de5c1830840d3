"""The checks of polarimetric measurements (:mod:`pbrdf_cl.model.measurables`): what
:func:`pbrdf_cl.io.measurements.from_arrays` runs where the data hold more than DOP, each refusal one
line naming the row (its CSV line) and the column.

- a normalised Stokes vector longer than 1, or an absolute one longer than its S0, beyond its
  noise (3 standard deviations where given, else :data:`NORMALISED_SLACK`);
- a normalised Mueller element outside [-1, 1] (or an absolute one above M00) beyond its noise;
- a DOP outside [0, 1]; a negative S0, M00 or F00; a standard deviation that is not positive, or
  given where its value is not;
- an incident state that is not a Stokes vector (in_s1^2 + in_s2^2 + in_s3^2 > 1), or not given at a
  row where the incident columns are;
- Stokes parameters without an incident state where rows of one geometry disagree beyond their
  noise (the file mixes source states without saying which);
- AoP values that all lie within +-pi/2 draw a :class:`~pbrdf_cl.errors.UnitsWarning` (radians?).
"""
from __future__ import annotations

import warnings

import numpy as np

from ..errors import UnitsWarning
from ..model import measurables

#: Normalised Stokes and Mueller values may exceed 1 in magnitude by this much (3 of their standard
#: deviations where given) before a row is refused: noise, not a mistake.
NORMALISED_SLACK = 0.02
#: Rows of one geometry whose Stokes parameters differ by more than this (plus 5 standard
#: deviations) without an incident state are taken as measured under different source states.
STATE_SPLIT = 0.1


def _first(bad):
    return int(np.argmax(bad))


def _std_of(cols, name):
    s = cols.get(f"{name}_std")
    return None if s is None else s


def _slack(cols, names, scale=1.0):
    """The allowance of rows for noise: 3 standard deviations (the largest of ``names``, over
    ``scale``) where given, else NORMALISED_SLACK."""
    stds = [cols[f"{n}_std"] for n in names if f"{n}_std" in cols]
    if not stds:
        return NORMALISED_SLACK
    worst = np.nanmax(np.column_stack(stds), axis=1)
    return np.where(np.isfinite(worst), 3.0 * worst / scale, NORMALISED_SLACK)


def _check_stds(cols, locate):
    for name in cols:
        base = name[:-4]
        if not name.endswith("_std") or base == "f00":  # f00_std: from_arrays checks it
            continue
        if base not in cols:
            raise ValueError(f"{locate(0).split(',')[0]}: {name} is given without {base}")
        std, value = cols[name], cols[base]
        bad = np.isfinite(value) & ~(std > 0)
        if bad.any():
            i = _first(bad)
            raise ValueError(f"{locate(i)}: {name} = {float(std[i])!r} is not > 0 (the std of the measured "
                             f"{base} = {float(value[i]):g})")


def _check_incident(cols, locate):
    """(M, 3) incident vectors, or None where no incident column is given."""
    given = [n for n in measurables.INCIDENT if n in cols]
    if not given:
        return None
    M = len(cols["theta_i"])
    inc = np.column_stack([cols.get(n, np.zeros(M)) for n in measurables.INCIDENT])
    missing = ~np.isfinite(inc)
    if missing.any():
        i, j = np.unravel_index(_first(missing.ravel()), inc.shape)
        raise ValueError(f"{locate(int(i))}: {measurables.INCIDENT[j]} is empty; give the incident state of every "
                         "row (in_s1, in_s2, in_s3 = 0, 0, 0 for unpolarised light)")
    norm = np.sqrt((inc * inc).sum(axis=1))
    bad = norm > 1.0 + 1e-9
    if bad.any():
        i = _first(bad)
        raise ValueError(f"{locate(i)}: the incident state ({', '.join(f'{v:g}' for v in inc[i])}) is not a Stokes "
                         f"vector: in_s1^2 + in_s2^2 + in_s3^2 = {norm[i] ** 2:.4g} > 1 (normalised by S0)")
    return inc


def _intensity(cols, name, what, locate):
    """The rows' intensity column ``name`` (s0, m00), refused in one line where negative (``what``
    it is), or 1 where the data are normalised (no such column)."""
    if name not in cols:
        return 1.0
    v = cols[name]
    bad = v < 0
    if bad.any():
        i = _first(bad)
        raise ValueError(f"{locate(i)}: {name} = {float(v[i])!r} is not >= 0 ({what})")
    return v


def _check_stokes(cols, locate):
    comps = [n for n in ("s1", "s2", "s3") if n in cols]
    if not comps:
        return
    s0 = _intensity(cols, "s0", "an intensity", locate)
    length = np.sqrt(np.nansum(np.column_stack([cols[n] ** 2 for n in comps]), axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = length / s0
    bad = np.isfinite(rel) & (rel > 1.0 + _slack(cols, comps + (["s0"] if "s0" in cols else []), s0))
    if bad.any():
        i = _first(bad)
        what = "s0" if "s0" in cols else "1 (normalised)"
        raise ValueError(f"{locate(i)}: the Stokes vector is longer than {what} beyond its noise: sqrt("
                         + " + ".join(f"{n}^2" for n in comps) + f") = {length[i]:.4g}"
                         + (f" > s0 = {float(cols['s0'][i]):.4g}" if "s0" in cols else " > 1")
                         + " (more than fully polarised light: wrong signs, units or normalisation?)")


def _check_mueller(cols, locate):
    names = [n for n in measurables.MUELLER if n in cols and n != "m00"]
    m00 = _intensity(cols, "m00", "the BRDF", locate)
    for n in names:
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(cols[n]) / m00
        bad = np.isfinite(rel) & (rel > 1.0 + _slack(cols, [n] + (["m00"] if "m00" in cols else []), m00))
        if bad.any():
            i = _first(bad)
            if "m00" in cols:
                raise ValueError(f"{locate(i)}: |{n}| = {abs(float(cols[n][i])):.4g} exceeds m00 = "
                                 f"{float(cols['m00'][i]):.4g} beyond its noise (no Mueller element exceeds M00)")
            raise ValueError(f"{locate(i)}: {n} = {float(cols[n][i]):.4g} is outside [-1, 1] beyond its noise "
                             "(normalised by M00, as without an m00 column: give m00 for absolute elements)")


def _check_states(cols, locate):
    """Refuse Stokes parameters without an incident state where rows of one geometry disagree."""
    comps = [n for n in ("s1", "s2", "s3") if n in cols]
    if not comps or any(n in cols for n in measurables.INCIDENT):
        return
    geo = np.column_stack([cols["theta_i"], cols["theta_r"], cols["phi"]])
    _, group = np.unique(geo, axis=0, return_inverse=True)
    group = group.reshape(-1)
    for n in comps:
        v, std = cols[n], _std_of(cols, n)
        tol = STATE_SPLIT + (0.0 if std is None else 5.0 * np.where(np.isfinite(std), std, 0.0))
        for g in np.unique(group):
            rows = np.flatnonzero((group == g) & np.isfinite(v))
            if rows.size < 2:
                continue
            lo, hi = rows[np.argmin(v[rows])], rows[np.argmax(v[rows])]
            if v[hi] - v[lo] > max(np.broadcast_to(tol, v.shape)[lo], np.broadcast_to(tol, v.shape)[hi]):
                a, b = sorted((int(lo), int(hi)))
                raise ValueError(f"{locate(a)} and {locate(b).split(', ')[-1]}: {n} = {v[a]:.4g} and {v[b]:.4g} at "
                                 "one geometry: measured under different incident states? give the incident state "
                                 "of every row (in_s1, in_s2, in_s3; 0, 0, 0 for unpolarised light)")


def _warn_aop_radians(cols, where):
    a = cols.get("aop")
    if a is None:
        return
    a = np.abs(a[np.isfinite(a)])
    if a.size >= 3 and a.max() <= np.pi / 2 + 1e-9 and a.max() > 0.3:
        warnings.warn(f"{where}aop: every value lies within +-{np.pi / 2:.4g} (the largest is {a.max():.4g}): are "
                      "they in radians? pbrdf-cl takes degrees (np.degrees(...) converts)", UnitsWarning, stacklevel=5)


def check_normalised(cols, locate):
    """Refuse, in one line naming ``locate(i)`` and the column, a Stokes vector longer than 1 (or its
    S0) and a Mueller element beyond 1 (or M00) in magnitude, beyond their noise: ``cols`` maps the
    names of (M,) arrays (NaN: not measured) to them, their ``<name>_std`` too (image stacks run it
    over their flattened pixels)."""
    _check_stokes(cols, locate)
    _check_mueller(cols, locate)


def check_polar(cols, locate):
    """Check the polarimetric columns of ``cols`` (name -> (M,) arrays, NaN where not measured)
    in one-line errors; returns the :class:`~pbrdf_cl.io.measurements.Measurements` fields
    ``quantities``, ``stds`` and ``incident``."""
    _check_stds(cols, locate)
    incident = _check_incident(cols, locate)
    check_normalised(cols, locate)
    _check_states(cols, locate)
    where = locate(0).split(",")[0] + ": "
    _warn_aop_radians(cols, where)
    quantities = {n: cols[n] for n in measurables.REGISTRY if n in cols and n not in ("dop", "f00")}
    stds = {n: cols[f"{n}_std"] for n in quantities if f"{n}_std" in cols}
    measured = np.zeros(len(cols["theta_i"]), bool)
    for n in measurables.REGISTRY:
        if n in cols:
            measured |= np.isfinite(cols[n])
    if not measured.all():
        i = _first(~measured)
        raise ValueError(f"{locate(i)}: nothing measured at this row (every quantity is empty)")
    return dict(quantities=quantities, stds=stds, incident=incident)
