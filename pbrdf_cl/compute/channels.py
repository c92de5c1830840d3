"""The least-squares objective of polarimetric channels (:class:`pbrdf_cl.model.measurables.Channels`:
Stokes parameters under polarized light, Mueller elements, DOP, AoP, intensities) over a grid of
parameter vectors, on the device: the engine operation ``objective_channel_blocks`` that
:func:`pbrdf_cl.compute.dense.objective` runs for channels.

As for the DOP, nothing transcendental is evaluated per grid point: per channel the terms (tn, td)
of P = R_out M^s R_in are tabulated over (n, k) (``pbrdf_tables.cl``'s ``channel_table``), the
inverse scale 1/K over (sigma, ks) and the diffuse term fd over (kd, c), and each grid point combines them
(``pbrdf_grid.cl``'s ``objective_channel_rows``, launched by
:mod:`pbrdf_cl.compute.dense`, which owns the grid programs; ``pb_channel_combine`` and
``pb_channel_residual`` of ``kernels/pbrdf.h``).  The numpy backend computes the same tables and
combination with ``reference.py`` in float64.
"""
from __future__ import annotations

import numpy as np

from ..device import ops
from ..device.engine import DTYPES
from ..model import reference
from .tables import factor_table, summed_over_rows


def channel_weights(ch):
    """The weights 1/std^2 of channels ``ch`` (1 where no std is given)."""
    std = np.asarray(ch.std, dtype=np.float64)
    return np.where(np.isfinite(std), 1.0 / np.where(np.isfinite(std), std, 1.0) ** 2, 1.0)


def pairs(first, second):
    """The parameter pairs i_first * n_second + i_second of two axes, as (1, n) rows."""
    return np.repeat(first, second.size)[None, :], np.tile(second, first.size)[None, :]


def numpy_channel_tables(ch, v, shadowing):
    """The tables of ``channel_table``, ``scale_table`` (1/K) and ``diffuse_table`` (fd) from
    ``reference.py`` over the channels ``ch`` and the axes ``v``: (tn, td) (C, n_n n_k), 1/K
    (C, n_sigma n_ks), fd (C, n_kd n_c)."""
    g = reference.geometry(ch.theta_i[:, None], ch.theta_r[:, None], ch.phi[:, None])
    nn, kk = pairs(v["n"], v["k"])
    f = reference.fresnel(nn, kk, g.cb, g.sb)
    fr = reference.frame_rotations(g, ch.phi[:, None])
    P = reference.mueller_at(f, fr, 1.0, 0.0)
    tn, td = reference.channel_terms(P, ch.u[:, None, :], ch.v[:, None, :], ch.comp[:, None], ch.kind[:, None])
    sigma, ks = pairs(v["sigma"], v["ks"])
    variant = reference.SHADOWING[shadowing]
    log_k = reference.log_specular_scale(g, sigma, ks, reference.shadowing_factor(g, sigma, variant))
    with np.errstate(over="ignore"):
        K = np.exp(-log_k)  # 1/K
    kd, c = pairs(v["kd"], v["c"])
    fd = np.broadcast_to(reference.diffuse(g, kd, c), (len(ch), kd.size))
    return tn, td, K, fd


#: float64 bytes per (channel, grid point) of a numpy block (the values and temporaries).
NUMPY_BYTES = 64


@ops.implements("objective_channel_blocks", "numpy")
def _numpy_blocks(eng, plan, ch, dtype, shadowing, room, out, rows):
    """(flat start, SSE) of the parameter grid ``plan`` over channels ``ch`` on the numpy backend,
    in blocks of (n, k) rows within ``room`` bytes; where the tables of all channels do not fit
    (``rows`` fewer), channel block by block (:func:`pbrdf_cl.compute.tables.summed_over_rows`)."""
    if rows < len(ch):
        yield from summed_over_rows(plan.size, len(ch), rows, lambda m0, m1: _numpy_blocks(
            eng, plan, ch.take(slice(m0, m1)), "float64", shadowing, room, None, m1 - m0), out, dtype)
        return
    v = plan.values
    tn, td, K, fd = numpy_channel_tables(ch, v, shadowing)
    w = channel_weights(ch)[:, None, None, None]
    a, b, c = (x[:, None, None, None] for x in ch.abc.T)
    aop = ch.aop[:, None, None, None]
    nnk, nm, ni = tn.shape[1], K.shape[1], fd.shape[1]
    step = max(1, room // (len(ch) * nm * ni * NUMPY_BYTES))
    for r0 in range(0, nnk, step):
        r1 = min(nnk, r0 + step)
        value = reference.channel_combine(tn[:, r0:r1, None, None], td[:, r0:r1, None, None], K[:, None, :, None],
                                          fd[:, None, None, :], a, b, c, aop)
        r = reference.channel_residual(value, ch.obs[:, None, None, None], aop)
        values = np.sum(w * r * r, axis=0).reshape(-1)
        start = r0 * nm * ni
        host = out[start:start + values.size] if out is not None else np.empty(values.size, DTYPES[dtype])
        host[...] = values
        yield start, host


def device_channel_tables(eng, ch, v, dtype, shadowing):
    """The device buffers of ``objective_channel_rows``' tables and channel data, in its argument
    order: tn, td, K, fd, obs, w, abc, aop, M."""
    kern = eng.program("pbrdf_tables.cl", dtype, {"PBRDF_SHADOWING": reference.SHADOWING[shadowing]})
    npdt = DTYPES[dtype]
    C = len(ch)
    geo = [eng.to_device(a, dtype) for a in (ch.theta_i, ch.theta_r, ch.phi)]

    def table(kname, outs, p1, p2, *extra):
        return factor_table(eng, kern, kname, outs, geo, C, p1, p2, npdt, *extra)
    ints = [eng.to_device(a, np.int32) for a in (ch.comp, ch.kind)]
    tn, td = table("channel_table", 2, v["n"], v["k"], eng.to_device(np.ascontiguousarray(ch.u).ravel(), dtype),
                   eng.to_device(np.ascontiguousarray(ch.v).ravel(), dtype), *ints)
    K, = table("scale_table", 1, v["sigma"], v["ks"], npdt(-1.0))  # 1/K
    fd, = table("diffuse_table", 1, v["kd"], v["c"], npdt(1.0))
    return (tn, td, K, fd, eng.to_device(ch.obs, dtype), eng.to_device(channel_weights(ch), dtype),
            eng.to_device(np.ascontiguousarray(ch.abc).ravel(), dtype),
            eng.to_device(ch.aop, np.int32), np.int32(C))
