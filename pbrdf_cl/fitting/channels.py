"""The model's value of measured polarimetric channels for the local descents of every room
(:class:`ChannelModel`): a sample's fit (:mod:`pbrdf_cl.fitting.sample.polarimetric`) and an image's
pixels (:mod:`pbrdf_cl.fitting.images.pixels`) alike, from ``reference.py``'s channel functions."""
from __future__ import annotations

import numpy as np

from ..model import reference
from ..model.inputs import MEMBERS


class ChannelModel:
    """The model's value of every channel of ``ch`` (:class:`~pbrdf_cl.model.measurables.Channels`)
    at their geometry, for the local stages: ``rows(p)`` maps parameters (name -> scalars or (B, 1)
    arrays) to (B, C) values.  P (over n, k), 1/K (over sigma, ks) and fd (over kd, c) are computed
    once per distinct geometry (a Mueller polarimeter measures 15 channels at each, a camera under
    five source states 10) and spread to its channels, then each channel's terms and value by
    :func:`~pbrdf_cl.model.reference.channel_terms` and
    :func:`~pbrdf_cl.model.reference.channel_combine`."""

    def __init__(self, ch, shadowing):
        self.ch = ch
        self.at = None  # channels of per-pixel geometry (2-d arrays): every channel its own
        first = slice(None)
        if np.ndim(ch.theta_i) == 1:
            geo = np.column_stack([ch.theta_i, ch.theta_r, ch.phi])
            first, self.at = np.unique(geo, axis=0, return_index=True, return_inverse=True)[1:]
            self.at = self.at.reshape(-1)
        self.g = reference.geometry(ch.theta_i[first], ch.theta_r[first], ch.phi[first])
        self.fr = reference.frame_rotations(self.g, ch.phi[first])
        self.variant = reference.SHADOWING[shadowing]

    def per_distinct(self, compute, p, names):
        """:func:`per_distinct` where every parameter row sees the same channels (not per-pixel
        geometry, whose rows are each a pixel's)."""
        return compute(p) if self.at is None else per_distinct(compute, p, names)

    def spread(self, a):
        """Values per distinct geometry (last axis) to the channels."""
        return a if self.at is None else a[..., self.at]

    def terms(self, p):
        def compute(q):
            f = reference.fresnel(q["n"], q["k"], self.g.cb, self.g.sb)
            P = reference.mueller_at(f, self.fr, 1.0, 0.0)  # per distinct geometry; each channel takes its own
            ch = self.ch
            return reference.channel_terms(P, ch.u, ch.v, ch.comp, ch.kind, at=self.at)
        return self.per_distinct(compute, p, MEMBERS["index"])

    def inv_scale(self, p):
        def compute(q):
            g = self.g
            log_k = reference.log_specular_scale(g, q["sigma"], q["ks"],
                                                 reference.shadowing_factor(g, q["sigma"], self.variant))
            with np.errstate(over="ignore"):
                return self.spread(np.exp(-log_k))
        return self.per_distinct(compute, p, MEMBERS["specular"])

    def rows(self, p):
        tn, td = self.terms(p)
        fd = self.per_distinct(lambda q: self.spread(reference.diffuse(self.g, q["kd"], q["c"])), p, MEMBERS["diffuse"])
        ch = self.ch
        return reference.channel_combine(tn, td, self.inv_scale(p), fd, *np.moveaxis(ch.abc, -1, 0), ch.aop)


#: Batches of at least this many parameter rows look for the rows that share factors (:func:`per_distinct`).
DISTINCT_ROWS = 16


def per_distinct(compute, p, names):
    """``compute(p)`` for parameter rows ``p`` (name -> (B, 1) arrays or scalars) that depends only
    on the parameters ``names``, computed once per distinct pair of their values and spread back:
    the finite-difference Jacobians of the local stages step one parameter at a time, so most of
    their rows share the factors of the others.  A tuple result is spread item by item."""
    cols = [np.asarray(p[n], dtype=np.float64) for n in names]
    rows = max((c.shape[0] for c in cols if c.ndim), default=0)
    if rows < DISTINCT_ROWS:  # a few rows (the derivative-free stages' lockstep): not worth the search
        return compute(p)
    key = np.concatenate([np.broadcast_to(c.reshape(-1, 1) if c.ndim else c, (rows, 1)) for c in cols], axis=1)
    uniq, inverse = np.unique(key, axis=0, return_inverse=True)
    if len(uniq) == rows:
        return compute(p)
    out = compute({**p, **{n: uniq[:, j:j + 1] for j, n in enumerate(names)}})
    inverse = inverse.reshape(-1)
    return tuple(o[inverse] for o in out) if isinstance(out, tuple) else out[inverse]
