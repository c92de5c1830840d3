"""The device stages of an image fit and their numpy twins, as operations of the engine
(:mod:`pbrdf_cl.device.ops`): callers run ``eng.call(name, ...)`` and the engine picks its
backend's implementation.

- ``batch_grid`` (setup, blk, order, rstart): each region's minimum of every pixel's objective on
  the grid (``kernels/pbrdf_batch.cl``; ``dense.NumpyTables`` pixel by pixel on the numpy backend);
- ``batch_table_minima`` (blk, T, rstart): each region's minimum over a DOP table at the shared
  geometry (a float32 kernel; one float64 matrix product);
- ``batch_lm`` (setup, blk, X0, names, dtype, iterations, intensity): bounded Levenberg-Marquardt
  descents of every pixel x start (the ``batch_lm`` kernel, :func:`device_lm`;
  :func:`~pbrdf_cl.fitting.common.lm_batch` with the reference);
- ``batch_lanes`` (): the lanes a block of pixels is padded to (every kernel's; 1 on numpy);
- ``batch_ranking_table`` (blk, params, shadowing): DOP of parameter sets at the shared geometry,
  only to rank starts (float32 on a device, the float64 reference on numpy).
"""
from __future__ import annotations

import numpy as np

from ...compute import dense, pointwise
from ...device import ops
from ...device.engine import DTYPES
from ...io.source import ANGLES
from ...model import reference
from ..common import fd_jacobian, lm_batch
from ..setup import MODEL_PARAMS, PARAMETERS
from .pixels import Descent, LogKs, PixelResiduals, descent_bounds, external, grid_values, internal

#: Geodesic acceleration of the descents (Transtrum and Sethna 2012) without intensities.
GEODESIC = True
#: Work-group size of the batch kernels: each work-item holds a few kB of private arrays, which
#: PoCL's CPU driver allocates for a whole work-group at once (a large group overflows its stack).
LOCAL_SIZE = 4
#: The parameters of batch_lm's vector (its PB_X_<NAME> slots): the fitted ones, then ks.
SLOTS = MODEL_PARAMS["six-param"] + tuple(p for p in PARAMETERS if p not in MODEL_PARAMS["six-param"])


@ops.implements("batch_lanes", "opencl")
def _lanes_opencl(eng):
    """The lanes a block of pixels is padded to: every kernel's lanes divide it."""
    return max(*eng.lm_lanes.values(), *eng.vector_width.values())


@ops.implements("batch_lanes", "numpy")
def _lanes_numpy(eng):
    return 1


@ops.implements("batch_grid", "opencl")
def _grid_opencl(eng, setup, blk, order, rstart):
    """(best (R, p), arg (R, p)): each region's minimum of every pixel's objective over the grid
    (:func:`pbrdf_cl.fitting.images.pixels.regions`) and its region-ordered grid index, on the device
    (float32): with shared geometry through the grid's DOP table, else the per-pixel factor tables
    of ``pbrdf_tables.cl`` combined by ``batch_grid_factors``."""
    v = grid_values(setup)
    if blk.shared:
        return eng.call("batch_table_minima", blk, _table_dop(eng, setup, blk.angles, v, order), rstart)
    shadow = reference.SHADOWING[setup.shadowing]
    dtype = "float32"
    npdt = DTYPES[dtype]
    R = rstart.size - 1
    P, M = blk.P, blk.valid.shape[1]
    w = blk.pixel_major(blk.w, npdt)
    obs = blk.pixel_major(blk.obs, npdt)
    best = np.empty((R, P), npdt)
    arg = np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size * v["ks"].size, v["kd"].size * v["c"].size
    ng = M * P
    if ng * max(nnk, nm, ni) >= 2 ** 31:
        raise ValueError("internal: a block of pixels too large for 32-bit table indices")
    tab = eng.program("pbrdf_tables.cl", dtype, {"PBRDF_SHADOWING": shadow})
    geo = [eng.to_device(blk.pixel_major(a, np.float64), npdt) for a in blk.angles]

    def table(kname, outs, p1, p2, *extra):
        np_ = p1.size * p2.size
        bufs = [eng.empty(ng * np_ * np.dtype(npdt).itemsize) for _ in range(outs)]
        eng.launch(tab[kname], (ng, np_), *bufs, np.int32(ng), np.int32(1), np.int32(ng), *geo,
                   eng.to_device(p1, npdt), eng.to_device(p2, npdt), np.int32(p2.size), *extra)
        return bufs
    s_, d_ = table("fresnel_table", 2, v["n"], v["k"])
    sc, = table("scale_table", 1, v["sigma"], v["ks"], npdt(-1))
    fd, = table("diffuse_table", 1, v["kd"], v["c"], npdt(2))
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": shadow, "PB_NNK": nnk, "PB_NM": nm,
                                                 "PB_NI": ni})
    eng.launch(prog["batch_grid_factors"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P), np.int32(M),
               s_, d_, sc, fd, eng.to_device(order, np.int32), eng.to_device(rstart, np.int32), np.int32(R),
               eng.to_device(obs, npdt), eng.to_device(w, npdt), local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p], arg[:, :blk.p].astype(np.int64)


@ops.implements("batch_grid", "numpy")
def _grid_numpy(eng, setup, blk, order, rstart):
    """:func:`_grid_opencl` with ``reference.py`` (dense.NumpyTables, float64), pixel by pixel."""
    from ...compute.dense import NumpyTables
    v = grid_values(setup)
    R = rstart.size - 1
    sizes = [v[n].size for n in PARAMETERS]
    nnk, nm, ni = sizes[0] * sizes[1], sizes[2] * sizes[3], sizes[4] * sizes[5]
    best = np.full((R, blk.p), np.inf)
    arg = np.zeros((R, blk.p), np.int64)
    M = blk.valid.shape[1]
    shared = None
    for i in range(blk.p):
        if blk.count[i] == 0:
            continue
        if blk.shared and shared is None or not blk.shared:
            ang = [a if blk.shared else a[i] for a in blk.angles]
            t = NumpyTables(setup.shadowing, "dop", *ang, v)
            T = t.combine(t.sum.reshape(M, nnk, 1, 1), t.diff.reshape(M, nnk, 1, 1), t.dif.reshape(M, 1, 1, ni),
                          t.scale.reshape(M, 1, nm, 1)).reshape(M, -1)[:, order]
            if blk.shared:
                shared = T
        T = shared if blk.shared else T
        sse = blk.w[i] @ (T - blk.obs[i][:, None]) ** 2
        for r in range(R):
            part = sse[rstart[r]:rstart[r + 1]]
            j = int(np.argmin(part))
            best[r, i], arg[r, i] = part[j], rstart[r] + j
    return best, arg


@ops.implements("batch_table_minima", "opencl")
def _table_minima_opencl(eng, blk, T, rstart):
    """Each region's least objective over the points of a DOP table ``T`` (G, M) at the shared
    geometry, for every pixel of ``blk``: (best (R, p), arg (R, p), the index into T), region r
    holding T[rstart[r]:rstart[r + 1]].  The objective is expanded as sum w obs^2 - 2 sum w obs T
    + sum w T^2: on a device a float32 kernel (batch_grid_table) that streams T past the pixels'
    data (on the numpy backend one float64 matrix product)."""
    R = rstart.size - 1
    dtype = "float32"
    npdt = DTYPES[dtype]
    P, M = blk.P, blk.valid.shape[1]
    w, obs = blk.pixel_major(blk.w, npdt), blk.pixel_major(blk.obs, npdt)
    best, arg = np.empty((R, P), npdt), np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    a2 = np.ascontiguousarray(-2.0 * w * obs, npdt)
    c = np.ascontiguousarray(np.einsum("mp,mp->p", w.astype(float), obs.astype(float) ** 2), npdt)
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": reference.SHADOWING[blk.setup.shadowing]})
    eng.launch(prog["batch_grid_table"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P), np.int32(M),
               eng.to_device(np.ascontiguousarray(T, npdt), npdt), eng.to_device(rstart, np.int32), np.int32(R),
               eng.to_device(a2, npdt), eng.to_device(w, npdt), eng.to_device(c, npdt), local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p].astype(float), arg[:, :blk.p].astype(np.int64)


@ops.implements("batch_table_minima", "numpy")
def _table_minima_numpy(eng, blk, T, rstart):
    """:func:`_table_minima_opencl` as one float64 matrix product."""
    R = rstart.size - 1
    w, obs = blk.w, blk.obs
    part = np.concatenate([w * obs, w], axis=1) @ np.concatenate([-2.0 * T, T * T], axis=1).T
    part += np.einsum("pm,pm->p", w, obs * obs)[:, None]
    arg = np.stack([rstart[r] + np.argmin(part[:, rstart[r]:rstart[r + 1]], axis=1) for r in range(R)])
    return np.take_along_axis(part.T, arg, axis=0), arg


def _table_dop(eng, setup, angles, v, order):
    """DOP of every grid point at the shared geometry, (G, M) in region order (the engine's
    per-point path: pbrdf.h)."""
    ti, tr, ph = angles
    sizes = [v[n].size for n in PARAMETERS]
    unr = np.unravel_index(order, sizes)
    p = {n: v[n][unr[i]][:, None] for i, n in enumerate(PARAMETERS)}
    out = pointwise.dop(ti[None, :], tr[None, :], ph[None, :], shadowing=setup.shadowing, dtype="float32", engine=eng,
                  **p)
    return np.ascontiguousarray(out, np.float32)


@ops.implements("batch_ranking_table", "opencl")
def _ranking_table_opencl(eng, blk, params, shadowing):
    """DOP (q, M) of the parameter sets ``params`` (name -> (q,)) at the block's shared geometry,
    only to rank starts: float32, as the grid stage's table (:func:`pbrdf_cl.compute.dense.outer`)."""
    return dense.outer(eng, "dop", dict(zip(ANGLES, blk.angles)), params, "float32", shadowing).T


@ops.implements("batch_ranking_table", "numpy")
def _ranking_table_numpy(eng, blk, params, shadowing):
    """:func:`_ranking_table_opencl` with the float64 reference."""
    return dense.outer(eng, "dop", dict(zip(ANGLES, blk.angles)), params, "float64", shadowing).T


@ops.implements("batch_lm", "opencl")
def device_lm(eng, setup, blk, X0, names, dtype, iterations, intensity, coords=LogKs):
    """The LM kernel (``batch_lm``) from starts X0 (S, p, D) (external coordinates) over ``names``,
    ``intensity``: with the F00 residuals: a :class:`~pbrdf_cl.fitting.images.pixels.Descent` (X (S, p, D),
    sse (S, p), JtJ (S, p, D, D) in the descent's coordinates, settled (S, p)).  ``coords``: the
    descent's coordinates, :class:`~pbrdf_cl.fitting.images.pixels.LogKs` or a corner's
    (:class:`pbrdf_cl.fitting.images.corners.Corner`, its PB_LOG_* build; JtJ then in those)."""
    npdt = DTYPES[dtype]
    S, p, D = X0.shape
    P = blk.P
    Q = S * P
    lanes = eng.lm_lanes[dtype]
    lo, hi = coords.bounds(setup, names)
    slot = {n: (names.index(n) if n in names else -1) for n in SLOTS}
    defines = {"PB_VECTOR_REAL": lanes, "PB_D": D, "PBRDF_SHADOWING": reference.SHADOWING[setup.shadowing],
               **{f"PB_X_{n.upper()}": s for n, s in slot.items()}}
    geodesic = GEODESIC and not intensity
    if intensity:
        defines["PB_INTENSITY"] = None
    if geodesic:
        defines["PB_GEODESIC"] = None

    for n in coords.logged:
        defines[f"PB_LOG_{n.upper()}"] = None
    if not blk.shared:
        defines["PB_PIXEL_GEOMETRY"] = None
    prog = eng.program("pbrdf_batch.cl", dtype, defines)
    Xi = np.zeros((D, S, P))
    Xi[:, :, :p] = np.moveaxis(coords.to_internal(X0, names), -1, 0)
    Xi[:, :, p:] = ((lo + hi) / 2)[:, None, None]
    Xi = np.ascontiguousarray(Xi.reshape(D, Q), npdt)
    base = np.array([setup.base.get(n, 0.0) for n in PARAMETERS], npdt)
    import pyopencl as cl
    bX = cl.Buffer(eng.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=Xi)  # in and out
    sse, jtj, settled = np.empty(Q, npdt), np.empty((D * D, Q), npdt), np.empty(Q, npdt)
    bsse, bjtj, bset = eng.empty(sse.nbytes), eng.empty(jtj.nbytes), eng.empty(settled.nbytes)
    # the geometry of every measurement once (reference.geometry: the mirror of pb_geometry)
    g = reference.geometry(*(blk.angles if blk.shared else [blk.pixel_major(a, np.float64) for a in blk.angles]))
    geo = eng.to_device(np.stack([g.cti, g.sti, g.ctr, g.str, g.cb, g.sb, g.tan2a]), npdt)
    obs, w = eng.to_device(blk.pixel_major(blk.obs, npdt), npdt), eng.to_device(blk.pixel_major(blk.w, npdt), npdt)
    if intensity:
        fobs = eng.to_device(blk.pixel_major(blk.fobs, npdt), npdt)
        fw = eng.to_device(blk.pixel_major(blk.fw, npdt), npdt)
    else:
        fobs = fw = eng.to_device(np.zeros(1, npdt), npdt)
    M = blk.valid.shape[1]
    eng.launch(prog["batch_lm"], (Q // lanes,), bX, bsse, bjtj, bset, np.int32(Q), np.int32(P), np.int32(M),
               np.int32(iterations), eng.to_device(base, npdt), eng.to_device(lo, npdt), eng.to_device(hi, npdt),
               geo, obs, w, fobs, fw, eng.empty(2 * M * (D + 1) * Q * np.dtype(npdt).itemsize if geodesic else 1),
               local_size=(LOCAL_SIZE,))
    eng.read(bX, Xi)
    eng.read(bsse, sse)
    eng.read(bjtj, jtj)
    eng.read(bset, settled)
    X = coords.to_external(np.moveaxis(Xi.reshape(D, S, P)[:, :, :p], 0, -1), names)
    jtj = np.moveaxis(jtj.reshape(D, D, S, P)[..., :p], (0, 1), (-2, -1)).astype(float)
    return Descent(X, sse.reshape(S, P)[:, :p].astype(float), jtj, settled.reshape(S, P)[:, :p] > 0)


@ops.implements("batch_lm", "numpy")
def _lm_numpy(eng, setup, blk, X0, names, dtype, iterations, intensity):
    """:func:`device_lm` on the numpy backend (float64 whatever ``dtype``):
    :func:`~pbrdf_cl.fitting.common.lm_batch` over every pixel x start."""
    S, p, D = X0.shape
    lo, hi = descent_bounds(setup, names)
    pix = np.tile(np.arange(p), S)
    res = PixelResiduals(setup, blk, names, pix, intensity)
    Xi = internal(X0, names).reshape(S * p, D)
    X, sse, _ = lm_batch(res.rows, Xi, lo, hi, iterations, rows_apart=False)
    r, J = fd_jacobian(res.rows, X, lo, hi)
    sse = np.einsum("pm,pm->p", r, r)
    jtj = np.einsum("pim,pjm->pij", J, J)
    return Descent(external(X, names).reshape(S, p, D), sse.reshape(S, p), jtj.reshape(S, p, D, D),
                   np.ones((S, p), bool))
