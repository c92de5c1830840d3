"""What a polarimeter measures, as data: the registry of measurable quantities and the channels
they make (SPEC, "Polarized incidence and polarimetric measurements").

A row of measurements holds, at one geometry and for one incident state (the incident light's
normalised Stokes vector ``in_s1, in_s2, in_s3``; 0, 0, 0: unpolarised), any subset of

- ``dop``: the degree of polarization of the reflected light;
- ``aop``: its angle of linear polarization, degrees, from the outgoing beam's s axis towards its p
  axis (modulo 180);
- ``s0, s1, s2, s3``: the reflected Stokes vector in the psps frame of the outgoing beam, absolute
  (1/sr for unit incident radiance) where ``s0`` is given, else ``s1, s2, s3`` normalised by S0;
- ``m00`` ... ``m33``: Mueller matrix elements, absolute (1/sr) where ``m00`` is given, else
  normalised by M00 (a Mueller polarimeter's usual output);
- ``f00``: the BRDF (M00) for unpolarised light.

Each number measured is a *channel*: the model's value is one of three forms of F = K P + fd e00
(``pb_channel_terms``, ``pb_channel_combine`` of ``kernels/pbrdf.h`` and their mirrors in
``reference.py``), set by its incident vector ``u``, its normalising vector ``v``, its output
component, its kind and three coefficients (a, b, c).  :func:`channels` makes them from columns;
:class:`Channels` holds them flat, the form the device objective and the fit's residuals take.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import numpy as np

from . import reference

#: The incident light's normalised Stokes vector, per row (default 0: unpolarised).
INCIDENT = ("in_s1", "in_s2", "in_s3")
STOKES = ("s0", "s1", "s2", "s3")
MUELLER = tuple(f"m{i}{j}" for i in range(4) for j in range(4))


class Measurable(NamedTuple):
    """One measurable quantity: ``name`` (a column), ``long_name``, ``units`` (absolute form),
    ``family`` ("dop", "aop", "stokes", "mueller", "f00"), the output component ``comp`` and, for a
    Mueller element, its column ``col`` (the incident basis vector e_col)."""
    name: str
    long_name: str
    units: str
    family: str
    comp: int = 0
    col: int = 0


REGISTRY = {q.name: q for q in (
    Measurable("dop", "degree of polarization of the reflected light", "1", "dop"),
    Measurable("aop", "angle of linear polarization of the reflected light (psps frame)", "deg", "aop"),
    *(Measurable(n, f"reflected Stokes S{i}", "1/sr", "stokes", i) for i, n in enumerate(STOKES)),
    *(Measurable(f"m{i}{j}", f"Mueller matrix element M{i}{j}", "1/sr", "mueller", i, j)
      for i in range(4) for j in range(4)),
    Measurable("f00", "BRDF F00 for unpolarised light", "1/sr", "f00"),
)}
#: The AoP's period: its residuals are wrapped into (-90, 90].
AOP_PERIOD = 180.0


def normalised(names):
    """Whether the Stokes and the Mueller columns of ``names`` are normalised: (stokes, mueller),
    True where s0 (m00) is absent."""
    return "s0" not in names, "m00" not in names


@dataclass(frozen=True)
class Channels:
    """Measured channels, flat (one entry per number measured): the geometry ``theta_i``,
    ``theta_r``, ``phi`` (degrees), the incident vector ``u`` and the normalising vector ``v``
    ((C, 4)), the output component ``comp`` and ``kind`` (int arrays), the coefficients ``abc``
    ((C, 3): a, b, c of ``pb_channel_combine``), whether each is an AoP (``aop``), the measured
    value ``obs``, its standard deviation ``std`` (NaN: not given), the ``name`` of its quantity
    and the ``row`` of the measurements it comes from."""
    theta_i: np.ndarray
    theta_r: np.ndarray
    phi: np.ndarray
    u: np.ndarray
    v: np.ndarray
    comp: np.ndarray
    kind: np.ndarray
    abc: np.ndarray
    aop: np.ndarray
    obs: np.ndarray
    std: np.ndarray
    name: np.ndarray
    row: np.ndarray

    def __len__(self):
        return self.obs.size

    def take(self, index):
        """The channels at ``index`` (a mask or indices)."""
        return replace(self, **{f.name: getattr(self, f.name)[index] for f in fields(self)})

    @property
    def absolute(self):
        """Which channels are absolute (their value scales with ks): c = 1."""
        return self.abc[:, 2] > 0

    def normalised(self):
        """These channels with the absolute ones made relative to their row's intensity, as the DOP:
        S1..S3 over the row's S0, M_ij over its M00 (their std propagated), and S0, M00, F00 and
        absolute channels of rows without them left out.  What depends on ks and kd only through
        kd/ks: the channels of the fit's grid stage."""
        keep = ~self.absolute
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out = {k: np.array(v, copy=True) for k, v in out.items()}
        for family, first in (("s", "s0"), ("m", "m00")):
            base = {r: i for i, (r, n) in enumerate(zip(self.row, self.name)) if n == first}
            for i in np.flatnonzero(self.absolute):
                name = self.name[i]
                if name == first or not name.startswith(family) or self.row[i] not in base:
                    continue
                j = base[self.row[i]]
                if not self.obs[j] > 0:
                    continue
                ratio = self.obs[i] / self.obs[j]
                out["obs"][i] = ratio
                out["std"][i] = np.hypot(self.std[i], ratio * self.std[j]) / self.obs[j]
                out["v"][i] = self.u[i] if family == "s" else np.eye(4)[0]
                out["abc"][i] = (0.0, 1.0, 0.0)
                keep[i] = True
        return replace(self, **out).take(keep)

    def values(self, f, fr, logK, fd):
        """The model's value of every channel from the Fresnel factors ``f``, frames ``fr``, log K
        and fd at the channels' geometry (arrays broadcasting over the channels, last axis)."""
        return reference.channel(f, fr, logK, fd, self.u, self.v, self.comp, self.kind, *self.abc.T)

    def values_of(self, F):
        """The model's value of every channel from Mueller matrices ``F`` (..., 4, 4) with K and fd
        folded in, F = K P + fd e00 (what :func:`pbrdf_cl.mueller` and ``dense.outer`` of "mueller"
        give), broadcasting over the channels (the axis before the matrix's two): arithmetic on
        the model's output, the same channel terms and combination as :meth:`values` with K = 1
        and fd = 0 (a normalised channel's ratio (F u)_comp / (F v)_0, the DOP |(F u)_123| /
        (F u)_0, an absolute channel (F u)_comp, the AoP of F u)."""
        tn, td = reference.channel_terms(F, self.u, self.v, self.comp, self.kind)
        return reference.channel_combine(tn, td, 1.0, 0.0, *self.abc.T, self.aop)

    def residuals(self, values):
        """(value - obs) per channel, an AoP's wrapped (``reference.channel_residual``)."""
        return reference.channel_residual(values, self.obs, self.aop)


def _spec(q, u, normalised_):
    """(u, v, comp, kind, (a, b, c)) of measurable ``q`` with incident vectors ``u`` ((R, 4))."""
    R = len(u)
    e = np.eye(4)
    if q.family == "dop":
        return u, u, 0, reference.CHANNEL_DOP, (0.0, 1.0, 0.0)
    if q.family == "aop":
        return u, u, 0, reference.CHANNEL_AOP, (0.0, 0.0, 0.0)
    if q.family in ("mueller", "f00"):
        u = np.broadcast_to(e[q.col], (R, 4))
    a = u[:, 0] * (q.comp == 0)  # the diffuse term adds to S0 (M00) alone
    if normalised_:
        v = u if q.family == "stokes" else np.broadcast_to(e[0], (R, 4))
        return u, v, q.comp, reference.CHANNEL_RATIO, (a, 1.0, 0.0)
    return u, np.zeros((R, 4)), q.comp, reference.CHANNEL_RATIO, (a, 0.0, 1.0)


def quantity_channels(name, u, normalised_=True):
    """The channels of one measurable quantity ``name`` for incident vectors ``u`` ((R, 4): (1, s1, s2,
    s3) each), normalised (S_j / S0, M_ij / M00) or absolute (``normalised_`` False; s0, m00 and f00 are
    absolute either way): their ``values_of`` a model's Mueller matrices gives the quantity (no
    geometry, no measurement)."""
    q = REGISTRY[name]
    u = np.asarray(u, dtype=np.float64)
    R = len(u)
    absolute_only = q.family == "f00" or (q.family in ("stokes", "mueller") and not q.comp and not q.col)
    cu, cv, comp, kind, abc = _spec(q, u, normalised_ and not absolute_only)
    zero = np.zeros(R)
    return Channels(zero, zero, zero, np.broadcast_to(cu, (R, 4)), np.broadcast_to(cv, (R, 4)), np.full(R, comp),
                    np.full(R, kind), np.column_stack([np.broadcast_to(np.asarray(x, dtype=np.float64), (R,))
                                                       for x in abc]),
                    np.full(R, q.family == "aop"), zero, np.full(R, np.nan), np.full(R, name, dtype=object),
                    np.arange(R))


def channels(theta_i, theta_r, phi, columns, stds=None, incident=None):
    """The channels of measurements: ``columns`` maps measurable names to (M,) arrays over the
    rows (NaN: not measured at that row), ``stds`` names to their standard deviations (missing:
    not given), ``incident`` an (M, 3) array of the incident normalised Stokes vectors (None:
    unpolarised).  Channels come row by row, in the order of :data:`REGISTRY` within a row."""
    M = np.size(theta_i)
    u = np.ones((M, 4))
    u[:, 1:] = 0.0 if incident is None else np.asarray(incident, dtype=np.float64)
    stokes_norm, mueller_norm = normalised(columns)
    parts = []
    for name, q in REGISTRY.items():
        if name not in columns:
            continue
        obs = np.asarray(columns[name], dtype=np.float64)
        norm = {"mueller": mueller_norm, "stokes": stokes_norm}.get(q.family, q.family != "f00")
        cu, cv, comp, kind, abc = _spec(q, u, norm)
        std = np.asarray((stds or {}).get(name, np.full(M, np.nan)), dtype=np.float64)
        abc = np.column_stack([np.broadcast_to(np.asarray(x, dtype=np.float64), (M,)) for x in abc])
        parts.append(dict(u=np.broadcast_to(cu, (M, 4)), v=np.broadcast_to(cv, (M, 4)), comp=np.full(M, comp),
                          kind=np.full(M, kind), abc=abc, aop=np.full(M, q.family == "aop"), obs=obs, std=std,
                          name=np.full(M, name, dtype=object), row=np.arange(M)))
    if not parts:
        raise ValueError("no measured quantity: give at least one of " + ", ".join(REGISTRY))
    flat = {k: np.stack([p[k] for p in parts], axis=1).reshape((M * len(parts),) + np.shape(parts[0][k])[1:])
            for k in parts[0]}
    keep = np.isfinite(flat["obs"])
    geo = {k: np.repeat(np.asarray(a, dtype=np.float64), len(parts)) for k, a in
           (("theta_i", theta_i), ("theta_r", theta_r), ("phi", phi))}
    return Channels(**geo, **flat).take(keep)
