"""The model's value of what a polarimeter measures (:mod:`pbrdf_cl.model.measurables`: the DOP, the
AoP, a Stokes parameter, a Mueller element or F00, normalised or absolute) under an incident state:
the Mueller matrix through the public per-point function (:func:`pbrdf_cl.evaluate`), then the
quantity's channel (:func:`pbrdf_cl.model.measurables.quantity_channels`, the channels the fit
takes): what the fit's figure and the explorer draw beside measured data.  Under unpolarized light
the DOP and the AoP are :func:`pbrdf_cl.evaluate`'s ``dop`` and ``aop`` themselves.
"""
from __future__ import annotations

import numpy as np

from ..model import measurables, reference
from .pointwise import check_incident, evaluate

#: The families of measurable quantities whose value depends on the incident state (a Mueller
#: element and F00 do not).
STATE_DEPENDENT = ("dop", "aop", "stokes")


def unpolarized(incident):
    """Whether ``incident`` (None, or s1, s2, s3) is unpolarized light: None or every component 0."""
    return incident is None or not np.any(np.asarray(incident, dtype=np.float64))


def measured(name, theta_i, theta_r, phi=180.0, *, incident=None, normalised=True, params, shadowing="paper",
             dtype="float64", model="six-param", engine=None, backend="auto"):
    """The model's value of the measurable quantity ``name`` at broadcast points.

    Parameters
    ----------
    name : str
        A measurable quantity (``pbrdf_cl.model.measurables.REGISTRY``, the columns of measurements):
        ``dop``, ``aop``, ``s0`` ... ``s3``, ``m00`` ... ``m33`` or ``f00``.
    theta_i, theta_r, phi : array-like
        The geometry in degrees (broadcasting).
    incident : array-like, optional
        The incident light's normalised Stokes vector (s1, s2, s3), or an array of them with a
        trailing axis of 3 broadcasting against the points; None: unpolarized.
    normalised : bool
        A Stokes parameter s1..s3 as S_j / S0, a Mueller element as M_ij / M00 (as a column of
        measurements without ``s0`` or ``m00`` is read); else absolute (1/sr).  ``s0``, ``m00`` and
        ``f00`` are absolute, ``dop`` and ``aop`` ratios, either way.
    params : dict
        The model's parameters n, k, sigma, ks, kd, c (scalars or broadcasting arrays).
    shadowing, dtype, model, engine, backend : optional
        As :func:`pbrdf_cl.evaluate` takes them.

    Returns
    -------
    numpy.ndarray
        The values, of the broadcast shape; degrees for the AoP.

    Examples
    --------
    A polarization camera's s1 = S1/S0 of the steel under a source polarized at +45 degrees (SPEC's
    check value), which :func:`pbrdf_cl.stokes` gives as well:

    >>> from pbrdf_cl.compute.measured import measured
    >>> steel = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
    >>> round(float(measured("s1", 40, 45, incident=(0, 1, 0), params=steel)), 5)
    0.16759
    """
    q = measurables.REGISTRY[name]
    kw = dict(shadowing=shadowing, dtype=dtype, model=model, engine=engine, backend=backend, **params)
    if unpolarized(incident) and q.family in ("dop", "aop"):
        return evaluate(q.family, theta_i, theta_r, phi, **kw)
    F = evaluate("mueller", theta_i, theta_r, phi, **kw)
    s_in = check_incident((0.0, 0.0, 0.0) if incident is None else incident)
    shape = np.broadcast_shapes(F.shape[:-2], s_in.shape[:-1])
    u = np.broadcast_to(s_in, shape + (4,)).reshape(-1, 4)
    ch = measurables.quantity_channels(name, u, normalised)
    values = ch.values_of(np.broadcast_to(F, shape + (4, 4)).reshape(-1, 4, 4).astype(np.float64))
    return values.reshape(shape).astype(F.dtype, copy=False)


#: Incident states by name: (s1, s2, s3) of the incident light, in the incoming beam's s, p basis
#: (SPEC: s1 = 1 is linear along s, s2 = 1 linear at +45 degrees from s towards p).
NAMED_STATES = {"unpolarized": (0.0, 0.0, 0.0), "linear s": (1.0, 0.0, 0.0), "linear p": (-1.0, 0.0, 0.0),
                "linear +45": (0.0, 1.0, 0.0), "linear -45": (0.0, -1.0, 0.0),
                "circular s3 = +1": (0.0, 0.0, 1.0), "circular s3 = -1": (0.0, 0.0, -1.0)}


def state_text(incident):
    """An incident state in words: its name where it has one (:data:`NAMED_STATES`) and its numbers,
    ``linear +45 (0, 1, 0)``, ``(0.5, 0.5, 0)``; None is ``unpolarized``."""
    s = (0.0, 0.0, 0.0) if incident is None else tuple(float(v) for v in incident)
    name = next((n for n, v in NAMED_STATES.items() if v == s), None)
    numbers = "(" + ", ".join(f"{v:.4g}" for v in s) + ")"
    return "unpolarized" if name == "unpolarized" else f"{name} {numbers}" if name else numbers


def label(name, normalised=True):
    """(label, units) of the measurable quantity ``name`` as measured: ``("s1 = S1/S0", "1")`` for a
    normalised Stokes parameter, ``("S1", "1/sr")`` for an absolute one, ``("m01 = M01/M00", "1")``, ..."""
    q = measurables.REGISTRY[name]
    fixed = {"dop": ("DOP", "1"), "aop": ("AoP", "deg"), "f00": ("BRDF F00", "1/sr")}
    if q.family in fixed:
        return fixed[q.family]
    big = name.upper()
    if not normalised or not q.comp and not q.col:  # s0, m00: absolute always
        return big, "1/sr"
    return f"{name} = {big}/{big[0]}0{'0' if q.family == 'mueller' else ''}", "1"


def residual(name, value, obs):
    """value - obs of the quantity ``name``: an AoP's wrapped into [-90, 90] degrees (modulo 180), as
    the fit's residuals (:func:`pbrdf_cl.model.reference.channel_residual`)."""
    return reference.channel_residual(value, obs, measurables.REGISTRY[name].family == "aop")


def groups(meas):
    """What measurements hold, quantity by quantity and incident state by state: (name, normalised,
    incident state (s1, s2, s3) or None, rows (a mask)) for each measured quantity ``name`` (in the
    registry's order) and each incident state with data, as ``meas`` (a
    :class:`~pbrdf_cl.io.measurements.Measurements`) reads its columns (a Stokes parameter or Mueller
    element is normalised without ``s0`` or ``m00``); a Mueller element or F00 once, over every
    state (state None: it does not depend on it)."""
    cols = meas.columns()
    stokes_norm, mueller_norm = measurables.normalised(cols)
    M = len(meas)
    inc = np.zeros((M, 3)) if meas.incident is None else np.asarray(meas.incident, dtype=np.float64)
    states = list(dict.fromkeys(tuple(float(v) for v in row) for row in inc))
    out = []
    for name, values in cols.items():
        q = measurables.REGISTRY[name]
        norm = {"stokes": stokes_norm, "mueller": mueller_norm}.get(q.family, q.family != "f00")
        if q.family in STATE_DEPENDENT:
            parts = [(s, (inc == s).all(axis=1)) for s in states]
        else:
            parts = [(None, np.ones(M, bool))]
        for state, rows in parts:
            rows = rows & np.isfinite(values)
            if rows.any():
                out.append((name, norm, state, rows))
    return out
