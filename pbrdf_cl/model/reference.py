"""Float64 numpy reference of the six-parameter pBRDF model.

This module mirrors ``kernels/pbrdf.h`` function by function: ``geometry`` is
``pb_geometry``, ``fresnel`` is ``pb_fresnel`` and so on, with the same steps in
the same order.  Change one, change the other.  Angles are in degrees, as in
the header; :func:`evaluate` is the entry point used by the public API's
``backend="numpy"``.  All functions broadcast over numpy arrays.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from scipy.special import erfc

SHADOW_NONE, SHADOW_PAPER, SHADOW_SMITH = 0, 1, 2
SHADOWING = {"none": SHADOW_NONE, "paper": SHADOW_PAPER, "smith": SHADOW_SMITH}

#: Beyond this argument the shadowing function S is below 1e-36 and is taken as 0.
SHADOW_ARG_MAX = 9.0


DEG = np.pi / 180.0


def sincosd(x):
    """(sin, cos) of x degrees with exact argument reduction to [-45, 45] (``pb_sincosd``)."""
    x = np.asarray(x, dtype=np.float64)
    q = np.rint(x * (1.0 / 90))
    y = (x - 90.0 * q) * DEG  # exact (a tie either way reduces exactly)
    sy, cy = np.sin(y), np.cos(y)
    iq = q.astype(np.int64) & 3
    c = np.choose(iq, [cy, -sy, -cy, sy])
    return np.choose(iq, [sy, cy, -sy, -cy]), c


def geometry(ti, tr, phi):
    """Eq. 2-3 in stable form; angles in degrees (``pb_geometry``)."""
    ti, tr, phi = (np.asarray(v, dtype=np.float64) for v in (ti, tr, phi))
    g = SimpleNamespace()
    g.sti, g.cti = sincosd(ti)
    g.str, g.ctr = sincosd(tr)
    sh, ch = sincosd(0.5 * phi)
    cp, _ = sincosd(0.5 * ((90.0 - ti) + (90.0 - tr)))  # cos((ti+tr)/2)
    sm, _ = sincosd(0.5 * (ti - tr))  # in (-45, 45): pb_geometry skips the reduction, the identity there
    q = g.sti * g.str
    g.cb = np.sqrt(cp * cp + q * ch * ch)
    g.sb = np.sqrt(sm * sm + q * sh * sh)
    ds = g.sti - g.str
    cs = g.cti + g.ctr
    g.tan2a = (ds * ds + 4.0 * q * ch * ch) / (cs * cs)
    return g


def fresnel(n, k, cb, sb):
    """Eq. 11-13 on the facet (``pb_fresnel``): Rs, Rp, Rs - Rp and x = rs rp*."""
    # every output combines n, k and cb, so it has their broadcast shape (no broadcast_arrays:
    # at a few dozen points it cost more than the arithmetic)
    n, k, cb, sb = (np.asarray(v, dtype=np.float64) for v in (n, k, cb, sb))
    f = SimpleNamespace()
    nk = n * k
    E = (n - k) * (n + k) - 1.0  # D - cos^2 b: exact for n = 1, k = 0
    D = E + cb * cb
    sC = np.hypot(2.0 * nk, D)
    # the root that does not cancel, sqrt((sC + |D|)/2): A for D >= 0, B for D < 0; the other
    # from A B = n k
    root = np.sqrt(0.5 * (sC + np.where(D >= 0.0, D, -D)))
    with np.errstate(divide="ignore", invalid="ignore"):
        other = np.where(root > 0.0, nk / root, 0.0)
    A = np.where(D >= 0.0, root, other)
    B = np.where(D >= 0.0, other, root)
    B2 = B * B
    ap = A + cb
    am = np.where(E >= 0.0, (E + B2) / ap, A - cb)  # A - cb = (A^2 - cb^2)/(A + cb)
    f.Rs = (am * am + B2) / (ap * ap + B2)
    t = sb * sb / cb
    tm, tp = A - t, A + t
    Rs_den = f.Rs / (tp * tp + B2)
    f.Rp = Rs_den * (tm * tm + B2)
    f.diff = Rs_den * 4.0 * A * t
    f.re_x = -Rs_den * ((A - t) * (A + t) + B2)
    f.im_x = Rs_den * 2.0 * B * t
    return f


def shadow_S(ct, st, sigma, variant):
    """Eq. 7-9: the shadowing function S(theta) of one beam (``pb_shadow_S``)."""
    ct, st, sigma = (np.asarray(v, dtype=np.float64) for v in (ct, st, sigma))
    if variant == SHADOW_NONE:
        return np.zeros(np.broadcast_shapes(ct.shape, st.shape, sigma.shape))
    w = np.sqrt(2.0) * sigma if variant == SHADOW_SMITH else sigma
    with np.errstate(divide="ignore"):
        a = ct / (w * st)
    a = np.where(a < SHADOW_ARG_MAX, a, SHADOW_ARG_MAX)
    den = a if variant == SHADOW_SMITH else a * a
    S = np.exp(-a * a) / (2.0 * np.sqrt(np.pi) * den) - 0.5 * erfc(a)
    return np.where(a < SHADOW_ARG_MAX, S, 0.0)


def shadowing_factor(g, sigma, variant):
    """G = 1 / (1 + S(ti) + S(tr)) (``pb_shadowing_factor``)."""
    return shadowing_of(shadow_S(g.cti, g.sti, sigma, variant), shadow_S(g.ctr, g.str, sigma, variant))


def shadowing_of(s_i, s_r):
    """G = 1 / (1 + S(ti) + S(tr)) from the two beams' :func:`shadow_S` (``pb_shadowing_of``)."""
    return 1.0 / (1.0 + s_i + s_r)


def log_specular_scale(g, sigma, ks, G):
    """log K, K = ks exp(-tan^2 a/(2 sigma^2)) G / (8 pi sigma^2 cos^4 a cos ti cos tr) (eq. 6)."""
    inv_s = 1.0 / sigma
    with np.errstate(invalid="ignore"):
        u2 = np.where(g.tan2a > 0.0, g.tan2a * inv_s * inv_s, 0.0)  # tan^2 a / sigma^2
    inv_cos2a = 1.0 + g.tan2a
    return (np.log(ks * G * inv_cos2a * inv_cos2a / (8.0 * np.pi * g.cti * g.ctr))
            - 2.0 * np.log(sigma) - 0.5 * u2)


def diffuse2_over_K(g, sigma, ks, G, kd, c):
    """2 fd / K (eq. 6 and 15) in one exponential, = 2 :func:`diffuse` exp(-:func:`log_specular_scale`):
    16 kd sigma^2 cos ti cos tr / (ks G (1 + tan^2 a)^2) exp(c log(cos ti cos tr) + tan^2 a / (2 sigma^2)),
    0 where kd = 0, inf where the exponential overflows (``pb_diffuse2_over_K``, the per-point DOP
    kernels' form)."""
    inv_s = 1.0 / sigma
    with np.errstate(invalid="ignore"):
        u2 = np.where(g.tan2a > 0.0, g.tan2a * inv_s * inv_s, 0.0)  # tan^2 a / sigma^2
    inv_cos2a = 1.0 + g.tan2a
    p = g.cti * g.ctr
    with np.errstate(over="ignore"):
        e = np.exp(c * np.log(p) + 0.5 * u2)
    r = 16.0 * kd * p * sigma * sigma / (ks * G * inv_cos2a * inv_cos2a)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.where(kd == 0.0, 0.0, np.where(e < np.inf, r * e, e))


def minnaert(g, c):
    """Eq. 15's Minnaert factor (cos ti cos tr)^c (``pb_minnaert``)."""
    return np.exp(c * np.log(g.cti * g.ctr))


def diffuse_of(kd, minnaert_):
    """Eq. 15: kd/pi (cos ti cos tr)^c from its factor :func:`minnaert` (``pb_diffuse_of``)."""
    kd = np.asarray(kd, dtype=np.float64)
    return np.where(kd == 0.0, 0.0, kd * (1.0 / np.pi) * minnaert_)


def diffuse(g, kd, c):
    """Eq. 15: Minnaert diffuse term kd/pi (cos ti cos tr)^c (``pb_diffuse``)."""
    return diffuse_of(kd, minnaert(g, c))


def dop_combine(sum_, diff, fd2, inv_K):
    """DOP = (Rs - Rp) / (Rs + Rp + fd2 / K) from precomputed factors (``pb_dop_combine``)."""
    with np.errstate(invalid="ignore"):
        r = np.where(fd2 > 0.0, fd2 * inv_K, 0.0)
    den = sum_ + r
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0.0, diff / den, 0.0)


def brdf_combine(sum_, K, fd):
    """F00 = K (Rs + Rp) / 2 + fd from precomputed factors (``pb_brdf_combine``)."""
    return 0.5 * K * sum_ + fd


def dop_at(f, inv_K, fd):
    """Eq. 17-18 at inv_K = 1/K: K (Rs - Rp) / (K (Rs + Rp) + 2 fd) (``pb_dop_at``)."""
    return dop_combine(f.Rs + f.Rp, f.diff, 2.0 * fd, inv_K)


def dop_of(f, fd2_K):
    """Eq. 17-18 from fd2_K = 2 fd / K (:func:`diffuse2_over_K`): (Rs - Rp) / (Rs + Rp + 2 fd / K)
    (``pb_dop_of``)."""
    return dop_combine(f.Rs + f.Rp, f.diff, fd2_K, 1.0)


def dop(f, logK, fd):
    """Eq. 17-18: K (Rs - Rp) / (K (Rs + Rp) + 2 fd) (``pb_dop``)."""
    with np.errstate(over="ignore"):
        return dop_at(f, np.exp(-logK), fd)


def brdf(f, logK, fd):
    """F00 = K (Rs + Rp) / 2 + fd (``pb_brdf``)."""
    with np.errstate(over="ignore"):
        return brdf_combine(f.Rs + f.Rp, np.exp(logK), fd)


def frame_rotations(g, phi):
    """cos/sin of the in/out frame rotations of the out-of-plane Mueller matrix; phi in degrees
    (``pb_frame_rotations``).

    w_i = (sti cph, sti sph, cti) towards the source, w_r = (str, 0, ctr) towards the viewer;
    macro bases s = unit(k x z), p = k x s; facet s_f = unit(k_in x h) = unit(w_r x w_i).
    """
    fr = SimpleNamespace()
    sph, cph = sincosd(phi)
    vx = -g.ctr * g.sti * sph
    vy = g.ctr * g.sti * cph - g.str * g.cti
    vz = g.str * g.sti * sph
    vx, vy, vz = np.broadcast_arrays(vx, vy, vz)
    nv = np.sqrt(vx * vx + vy * vy + vz * vz)
    # retro-reflection (nv = 0): any facet frame gives the same matrix; take s_in
    with np.errstate(divide="ignore", invalid="ignore"):
        vx = np.where(nv > 0.0, vx / nv, -sph)
        vy = np.where(nv > 0.0, vy / nv, cph)
        vz = np.where(nv > 0.0, vz / nv, 0.0)
    # s_in = (-sph, cph, 0), p_in = (cti cph, cti sph, -sti)
    fr.ci = -vx * sph + vy * cph
    fr.si = vx * g.cti * cph + vy * g.cti * sph - vz * g.sti
    # s_out = (0, -1, 0), p_out = (ctr, 0, -str); so = s_out . (k_out x s_f) = -s_f . p_out
    fr.co = -vy
    fr.so = -(vx * g.ctr - vz * g.str)
    return fr


def rotation2(c, s):
    """(c^2 - s^2, 2 c s): cos and sin of twice the rotation angle of cos c, sin s (``pb_rotation2``)."""
    return c * c - s * s, 2.0 * c * s


def mueller_at(f, fr, K, fd):
    """F = K R_out M^s R_in + fd e00 at the scale K itself, shape (..., 4, 4) (``pb_mueller_at``);
    with K = 1 and fd = 0 it is P = R_out M^s R_in, the specular part per unit K.

    R(c, s) = [[1,0,0,0],[0,c2,s2,0],[0,-s2,c2,0],[0,0,0,1]], c2 = c^2 - s^2, s2 = 2 c s.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        m00 = 0.5 * K * (f.Rs + f.Rp)
        m01 = 0.5 * K * f.diff
        rx, ix = K * f.re_x, K * f.im_x
        c, s = rotation2(fr.ci, fr.si)
        C, S = rotation2(fr.co, fr.so)
        m00, m01, rx, ix, c, s, C, S, fd = np.broadcast_arrays(m00, m01, rx, ix, c, s, C, S, fd)
        zero = np.zeros(m00.shape)
        # A = M^s R_in
        a1 = [m01, m00 * c, m00 * s, zero]
        a2 = [zero, -rx * s, rx * c, ix]
        m = np.empty(m00.shape + (16,))
        m[..., 0], m[..., 1], m[..., 2], m[..., 3] = m00 + fd, m01 * c, m01 * s, zero
        for j in range(4):
            m[..., 4 + j] = C * a1[j] + S * a2[j]
            m[..., 8 + j] = -S * a1[j] + C * a2[j]
        m[..., 12], m[..., 13], m[..., 14], m[..., 15] = zero, ix * s, -ix * c, rx
    return m.reshape(m00.shape + (4, 4))


def mueller(f, fr, logK, fd):
    """F = K R_out M^s R_in + fd e00 from log K (``pb_mueller``, :func:`mueller_at`)."""
    with np.errstate(over="ignore"):
        return mueller_at(f, fr, np.exp(logK), fd)


#: Polarimetric channel kinds (``PB_CHANNEL_*``): a ratio (or an absolute value), the DOP and the AoP
#: of the reflected light for an incident Stokes vector u (see :func:`channel_terms`).
CHANNEL_RATIO, CHANNEL_DOP, CHANNEL_AOP = 0, 1, 2


def channel_terms(m, u, v, comp, kind, at=None):
    """The terms (tn, td) of a polarimetric channel from P = R_out M^s R_in per unit K (``m``,
    (..., 4, 4): :func:`mueller_at` with K = 1, fd = 0) and the channel's incident vectors ``u``,
    ``v`` ((..., 4)), output component ``comp`` and ``kind`` (scalars, or arrays over the
    channels) (``pb_channel_terms``): ratio: (P u)_comp and (P v)_0; DOP: |(P u)_123| and (P u)_0;
    AoP: the AoP of P u (degrees) and 1.  ``at`` (int array over the channels): ``m`` holds P per
    distinct geometry ((..., G, 4, 4)) and channel i takes ``m[..., at[i], :, :]`` (the same
    numbers, without spreading P to every channel first)."""
    m = np.asarray(m, dtype=np.float64)
    u, v = np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
    comp, kind = np.asarray(comp), np.asarray(kind)
    whole = np.any(kind != CHANNEL_RATIO)  # the DOP and the AoP take the whole of P u
    if at is not None:  # the rows needed, gathered per channel: (..., C, 4)
        row, r0 = m[..., at, comp, :], m[..., at, 0, :]
        if whole:
            m = m[..., at, :, :]
    else:
        shape = np.broadcast_shapes(m.shape[:-2], u.shape[:-1], v.shape[:-1], comp.shape, kind.shape)
        rows = np.broadcast_to(np.broadcast_to(comp, shape)[..., None, None], shape + (1, 4))
        row = np.take_along_axis(np.broadcast_to(m, shape + (4, 4)), rows, axis=-2)[..., 0, :]
        r0 = m[..., 0, :]
    tn = row[..., 0] * u[..., 0] + row[..., 1] * u[..., 1] + row[..., 2] * u[..., 2] + row[..., 3] * u[..., 3]
    td = r0[..., 0] * v[..., 0] + r0[..., 1] * v[..., 1] + r0[..., 2] * v[..., 2] + r0[..., 3] * v[..., 3]
    if whole:
        t = [m[..., i, 0] * u[..., 0] + m[..., i, 1] * u[..., 1] + m[..., i, 2] * u[..., 2] + m[..., i, 3] * u[..., 3]
             for i in range(4)]
        with np.errstate(invalid="ignore"):
            dop_n = np.sqrt(t[1] * t[1] + t[2] * t[2] + t[3] * t[3])
        tn = np.where(kind == CHANNEL_DOP, dop_n, tn)
        td = np.where(kind == CHANNEL_DOP, t[0], td)
        if np.any(kind == CHANNEL_AOP):
            tn = np.where(kind == CHANNEL_AOP, aop_of(t[1], t[2]), tn)
            td = np.where(kind == CHANNEL_AOP, 1.0, td)
    return tn, td


def channel_combine(tn, td, inv_K, fd, a, b, c, aop):
    """A channel's value (``pb_channel_combine``): the AoP (``aop`` true) is ``tn`` itself; an
    absolute channel (c != 0) K tn + a fd; a normalised one (tn + a q) / (td + b q) with q = fd / K
    (0 where fd is 0), 0 where that denominator is 0; a zero coefficient adds nothing.  ``inv_K``
    is 1/K."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        q = np.where(fd > 0.0, fd * inv_K, 0.0)
        num = tn + np.where(a != 0, a * q, 0.0)
        den = td + np.where(b != 0, b * q, 0.0)
        ratio = np.where(den > 0.0, num / den, 0.0)
        value = np.where(c != 0, tn / inv_K + a * fd, ratio)
    return np.where(aop, tn, value)


def channel(f, fr, logK, fd, u, v, comp, kind, a, b, c):
    """One channel at points of the model (``pb_channel``): P, its terms, its value."""
    tn, td = channel_terms(mueller_at(f, fr, 1.0, 0.0), u, v, comp, kind)
    with np.errstate(over="ignore"):
        return channel_combine(tn, td, np.exp(-logK), fd, a, b, c, np.asarray(kind) == CHANNEL_AOP)


def channel_residual(value, obs, aop):
    """A channel's residual, wrapped into [-90, 90] for an AoP (modulo 180 degrees), an undefined
    AoP (NaN) 90 degrees off (``pb_channel_residual``)."""
    r = np.asarray(value, dtype=np.float64) - obs
    with np.errstate(invalid="ignore"):
        w = r - 180.0 * np.rint(r / 180.0)
    return np.where(aop, np.where(np.isnan(w), 90.0, w), r)


def stokes_combine(sum_, diff, K, fd, C, S):
    """The Stokes vector reflected for unpolarised incidence, the first column of F, from the grid
    tables' factors (``pb_stokes_combine``, all four components at once): shape (..., 4)."""
    with np.errstate(invalid="ignore"):
        m01 = 0.5 * K * diff
        s0 = 0.5 * K * sum_ + fd
        s1, s2 = C * m01, -S * m01
        s0, s1, s2 = np.broadcast_arrays(s0, s1, s2)
        return np.stack([s0, s1, s2, np.zeros(s0.shape)], axis=-1)


def aop_of(L1, L2):
    """Angle of linear polarisation in degrees in (-90, 90] of S1 = L1, S2 = L2; NaN where both are 0
    (``pb_aop_of``)."""
    a = 0.5 * np.arctan2(L2, L1) / DEG
    b = np.where(a <= -90.0, a + 180.0, a + 0.0)  # -90 is +90; -0 is 0
    return np.where((L1 != 0.0) | (L2 != 0.0), b, np.nan)


def aop_combine(diff, K, fd, C, S):
    """AoP from the grid tables' factors (``pb_aop_combine``): L = m01 (C, -S), m01 = K diff / 2,
    taken along (C, -S) where the light is polarised (diff > 0, and K > 0 unless fd = 0)."""
    with np.errstate(invalid="ignore"):
        on = np.where((diff > 0.0) & ((K > 0.0) | (fd == 0.0)), 1.0, 0.0)
    return aop_of(on * C, -on * S)


# ---- The output quantities: for each registry name (pbrdf_cl/model/quantities.py) ``point_<name>(g, f,
# phi, logK, fd)`` (the values of points, a trailing axis for a width above 1) and, where the grid
# supports it, ``grid_<name>(sum, diff, fdx, scale, C, S)`` (from the tables; every component).
# They mirror ``pb_point_<name>`` and ``pb_grid_<name>`` of pbrdf.h.

def point_dop(g, f, phi, logK, fd):
    return dop(f, logK, fd)


def grid_dop(sum_, diff, fd2, inv_K, C, S):
    return dop_combine(sum_, diff, fd2, inv_K)


def point_brdf(g, f, phi, logK, fd):
    return brdf(f, logK, fd)


def grid_brdf(sum_, diff, fd, K, C, S):
    return brdf_combine(sum_, K, fd)


def point_mueller(g, f, phi, logK, fd):
    return mueller(f, frame_rotations(g, phi), logK, fd)


def out_rotation2(g, phi):
    """(cos 2 psi, sin 2 psi) of the outgoing frame rotation (``pb_out_rotation2``)."""
    fr = frame_rotations(g, phi)
    return rotation2(fr.co, fr.so)


def point_stokes(g, f, phi, logK, fd):
    C, S = out_rotation2(g, phi)
    with np.errstate(over="ignore"):
        return stokes_combine(f.Rs + f.Rp, f.diff, np.exp(logK), fd, C, S)


def grid_stokes(sum_, diff, fd, K, C, S):
    return stokes_combine(sum_, diff, K, fd, C, S)


def point_aop(g, f, phi, logK, fd):
    C, S = out_rotation2(g, phi)
    with np.errstate(over="ignore"):
        return aop_combine(f.diff, np.exp(logK), fd, C, S)


def grid_aop(sum_, diff, fd, K, C, S):
    return aop_combine(diff, K, fd, C, S)


def evaluate(quantity, theta_i, theta_r, phi, n, k, sigma, ks, kd, c, shadowing="paper"):
    """Evaluate ``quantity`` (a name of :data:`pbrdf_cl.quantities.REGISTRY` with a points path:
    "dop", "brdf", "mueller", "aop", "stokes") in float64; angles in degrees.

    Mirrors the body shared by the kernels of ``kernels/pbrdf_points.cl``.  No input validation:
    the public API (:mod:`pbrdf_cl.compute.pointwise`) validates before calling this.
    """
    point = globals().get(f"point_{quantity}")
    if point is None:
        raise ValueError(f"quantity: no point function point_{quantity} in reference.py")
    variant = SHADOWING[shadowing]
    g = geometry(theta_i, theta_r, phi)
    f = fresnel(n, k, g.cb, g.sb)
    G = shadowing_factor(g, sigma, variant)
    logK = log_specular_scale(g, sigma, ks, G)
    fd = diffuse(g, kd, c)
    return point(g, f, np.asarray(phi, dtype=np.float64), logK, fd)
