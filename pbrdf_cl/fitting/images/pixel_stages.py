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

With polarimetric quantities (``blk.spec``: the block's channels, one measured number at one
measurement index; :func:`pbrdf_cl.fitting.images.pixels.channel_spec`) every stage takes the channels
instead of the DOP: the grid from the channels' value table (shared geometry and incident states:
``batch_channel_values``, then ``batch_grid_channels``, each pixel's weighted residuals with an
AoP's wrapped) or their per-pixel tables (``batch_grid_channel_factors``), the ranking table from
the Mueller matrix, the descents through the PB_CHANNELS build of ``batch_lm``; the numpy twins
through ``reference.py`` in float64.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ...compute import dense, pointwise
from ...compute.channels import device_channel_tables, numpy_channel_tables
from ...compute.tables import factor_table
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
#: The precision of the grid stage of polarimetric channels on a device (the tests run it in float64
#: against the numpy twin); the DOP's grid is float32.
GRID_DTYPE = "float32"
#: Channels per block of the numpy twin's value table (bounds its temporaries).
NUMPY_CHANNELS = 32


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
    of ``pbrdf_tables.cl`` combined by ``batch_grid_factors`` (polarimetric channels: see the top)."""
    v = grid_values(setup)
    if blk.spec is not None:
        if blk.shared:
            T = _channel_values_opencl(eng, setup, blk.spec, v, order, GRID_DTYPE)
            return _channel_minima_opencl(eng, blk, T, rstart, GRID_DTYPE)
        return _channel_factors_opencl(eng, setup, blk, v, order, rstart, GRID_DTYPE)
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
    table, (nnk, nm, ni) = _pixel_tables(eng, blk, v, M * P, shadow, dtype)
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
    if blk.spec is not None:
        return _channel_grid_numpy(setup, blk, v, order, rstart)
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


@ops.implements("batch_grid_fixed", "opencl")
def _grid_fixed_opencl(eng, setups, blk, order, rstart):
    """``batch_grid`` of the same pixels under several ``setups`` (one grid of the free parameters,
    other values held: the label stage's candidates), (best (C, R, p), arg (C, R, p)).  Of the DOP at
    shared geometry, one table of every setup's grid points (one per-point launch) streamed past
    the pixels once (regions of setup c: c R .. (c + 1) R; every region's minimum as it is alone);
    else one ``batch_grid`` per setup."""
    if not (blk.shared and blk.spec is None) or len(setups) == 1:
        return _each_grid(eng, setups, blk, order, rstart)
    C, G, R = len(setups), order.size, rstart.size - 1
    assert C * G <= 1 << 24, "batch_grid_table's float32 indices are exact below 2^24 table points"
    T = _table_dop(eng, setups[0], blk.angles, [grid_values(s) for s in setups], order)
    starts = (rstart[:-1][None] + G * np.arange(C)[:, None]).ravel()
    best, arg = eng.call("batch_table_minima", blk, T, np.append(starts, C * G).astype(rstart.dtype))
    return best.reshape(C, R, blk.p), arg.reshape(C, R, blk.p) - G * np.arange(C)[:, None, None]


@ops.implements("batch_grid_fixed", "numpy")
def _each_grid(eng, setups, blk, order, rstart):
    """:func:`_grid_fixed_opencl` as one ``batch_grid`` per setup."""
    out = [eng.call("batch_grid", s, blk, order, rstart) for s in setups]
    return np.stack([b for b, _ in out]), np.stack([a for _, a in out])


@ops.implements("batch_table_minima", "opencl")
def _table_minima_opencl(eng, blk, T, rstart):
    """Each region's least objective over the points of a DOP table ``T`` (G, M) at the shared
    geometry, for every pixel of ``blk``: (best (R, p), arg (R, p), the index into T), region r
    holding T[rstart[r]:rstart[r + 1]].  The objective is expanded as sum w obs^2 - 2 sum w obs T
    + sum w T^2: on a device a float32 kernel (batch_grid_table) that streams T past the pixels'
    data (on the numpy backend one float64 matrix product).  Of channels (T (G, C)), each pixel's
    weighted residuals (batch_grid_channels; an AoP's wrapped)."""
    if blk.spec is not None:
        return _channel_minima_opencl(eng, blk, eng.to_device(T, GRID_DTYPE), rstart, GRID_DTYPE)
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
    if blk.spec is not None:
        return _channel_minima_numpy(blk.w, blk.obs, _channel_flags(blk.spec, blk.shared)[1], T, rstart)
    R = rstart.size - 1
    w, obs = blk.w, blk.obs
    part = np.concatenate([w * obs, w], axis=1) @ np.concatenate([-2.0 * T, T * T], axis=1).T
    part += np.einsum("pm,pm->p", w, obs * obs)[:, None]
    arg = np.stack([rstart[r] + np.argmin(part[:, rstart[r]:rstart[r + 1]], axis=1) for r in range(R)])
    return np.take_along_axis(part.T, arg, axis=0), arg


def _table_dop(eng, setup, angles, v, order):
    """DOP of every grid point at the shared geometry, (G, M) in region order (the engine's
    per-point path: pbrdf.h); ``v`` the grid's values (:func:`grid_values`), or a list of several
    grids of the same shape: their tables one after another, (len(v) G, M)."""
    ti, tr, ph = angles
    vs = v if isinstance(v, list) else [v]
    sizes = [vs[0][n].size for n in PARAMETERS]
    unr = np.unravel_index(order, sizes)
    p = {n: np.concatenate([w[n][unr[i]] for w in vs])[:, None] for i, n in enumerate(PARAMETERS)}
    out = pointwise.dop(ti[None, :], tr[None, :], ph[None, :], shadowing=setup.shadowing, dtype="float32", engine=eng,
                  **p)
    return np.ascontiguousarray(out, np.float32)


@ops.implements("batch_ranking_table", "opencl")
def _ranking_table_opencl(eng, blk, params, shadowing):
    """DOP (q, M) of the parameter sets ``params`` (name -> (q,)) at the block's shared geometry,
    only to rank starts: float32, as the grid stage's table (:func:`pbrdf_cl.compute.dense.outer`);
    of channels (q, C), as the grid stage's value table (:func:`_channel_values_opencl` over the
    grid of the sets' distinct values, at the sets' points)."""
    if blk.spec is not None:
        v, flat = _set_grid(params)
        T = _channel_values_opencl(eng, blk.setup, blk.spec, v, flat, GRID_DTYPE)
        out = np.empty((flat.size, len(blk.spec.obs)), DTYPES[GRID_DTYPE])
        return eng.read(T, out)
    return dense.outer(eng, "dop", dict(zip(ANGLES, blk.angles)), params, "float32", shadowing).T


@ops.implements("batch_ranking_table", "numpy")
def _ranking_table_numpy(eng, blk, params, shadowing):
    """:func:`_ranking_table_opencl` with the float64 reference."""
    if blk.spec is not None:
        v, flat = _set_grid(params)
        return _channel_values_numpy(blk.setup, blk.spec, v, flat)
    return dense.outer(eng, "dop", dict(zip(ANGLES, blk.angles)), params, "float64", shadowing).T


@ops.implements("batch_lm", "opencl")
def device_lm(eng, setup, blk, X0, names, dtype, iterations, intensity, coords=LogKs, fixed_rows=None):
    """The LM kernel (``batch_lm``) from starts X0 (S, p, D) (external coordinates) over ``names``,
    ``intensity``: with the F00 residuals: a :class:`~pbrdf_cl.fitting.images.pixels.Descent` (X (S, p, D),
    sse (S, p), JtJ (S, p, D, D) in the descent's coordinates, settled (S, p)).  ``coords``: the
    descent's coordinates, :class:`~pbrdf_cl.fitting.images.pixels.LogKs` or a corner's
    (:class:`pbrdf_cl.fitting.images.corners.Corner`, its PB_LOG_* build; JtJ then in those).
    ``fixed_rows``: name -> (p,) each pixel's own value of parameters ``setup`` holds (its PB_BASE_ROWS
    build; the label stage's candidates, every pixel of one as if held at its values alone)."""
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
    if fixed_rows:
        defines["PB_BASE_ROWS"] = None
    if not blk.shared:
        defines["PB_PIXEL_GEOMETRY"] = None
    if blk.spec is not None:
        defines["PB_CHANNELS"] = None
        defines["PB_NQ"] = blk.nq  # the channels of one measurement share its geometry's factors
    prog = eng.program("pbrdf_batch.cl", dtype, defines)
    Xi = np.zeros((D, S, P))
    Xi[:, :, :p] = np.moveaxis(coords.to_internal(X0, names), -1, 0)
    Xi[:, :, p:] = ((lo + hi) / 2)[:, None, None]
    Xi = np.ascontiguousarray(Xi.reshape(D, Q), npdt)
    base = np.array([setup.base.get(n, 0.0) for n in PARAMETERS], npdt)
    if fixed_rows:  # (6, P): every pixel's values, the padding's those of the first pixel
        rows = np.repeat(base[:, None].astype(float), P, axis=1)
        for n, v in fixed_rows.items():
            rows[PARAMETERS.index(n), :p] = v
            rows[PARAMETERS.index(n), p:] = v[0] if p else 0.0
        base = np.ascontiguousarray(rows, npdt).ravel()
    import pyopencl as cl
    bX = cl.Buffer(eng.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=Xi)  # in and out
    sse, jtj, settled = np.empty(Q, npdt), np.empty((D * D, Q), npdt), np.empty(Q, npdt)
    bsse, bjtj, bset = eng.empty(sse.nbytes), eng.empty(jtj.nbytes), eng.empty(settled.nbytes)
    geo, chan = _lm_tables(eng, blk, npdt)
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
               chan, local_size=(LOCAL_SIZE,))
    eng.read(bX, Xi)
    eng.read(bsse, sse)
    eng.read(bjtj, jtj)
    eng.read(bset, settled)
    X = coords.to_external(np.moveaxis(Xi.reshape(D, S, P)[:, :, :p], 0, -1), names)
    jtj = np.moveaxis(jtj.reshape(D, D, S, P)[..., :p], (0, 1), (-2, -1)).astype(float)
    return Descent(X, sse.reshape(S, P)[:, :p].astype(float), jtj, settled.reshape(S, P)[:, :p] > 0)


@ops.implements("batch_lm", "numpy")
def _lm_numpy(eng, setup, blk, X0, names, dtype, iterations, intensity, fixed_rows=None):
    """:func:`device_lm` on the numpy backend (float64 whatever ``dtype``):
    :func:`~pbrdf_cl.fitting.common.lm_batch` over every pixel x start (with ``fixed_rows``, over
    the pixels of each distinct row of fixed values in turn, ``setup`` holding them)."""
    if fixed_rows:
        keys = list(fixed_rows)
        vals = np.ascontiguousarray(np.stack([np.asarray(fixed_rows[n], float) for n in keys], axis=1))
        S, p, D = X0.shape
        out = Descent(np.full((S, p, D), np.nan), np.full((S, p), np.nan), np.full((S, p, D, D), np.nan),
                      np.zeros((S, p), bool))
        # the distinct rows told apart by their bits (NaN rows, -0 and +0 each as they are)
        _, first, inv = np.unique(vals.view(np.int64), axis=0, return_index=True, return_inverse=True)
        for g, row in enumerate(vals[first]):
            idx = np.flatnonzero(inv.reshape(-1) == g)
            held = replace(setup, fixed={**setup.fixed, **{n: float(v) for n, v in zip(keys, row)}})
            d = _lm_numpy(eng, held, blk.subset(idx), X0[:, idx], names, dtype, iterations, intensity)
            for a, b in zip(out, d):
                a[:, idx] = b
        return out
    S, p, D = X0.shape
    lo, hi = descent_bounds(setup, names)
    pix = np.tile(np.arange(p), S)
    res = PixelResiduals(setup, blk, names, pix, intensity)
    Xi = internal(X0, names).reshape(S * p, D)
    X, sse, _ = lm_batch(res.rows, Xi, lo, hi, iterations, rows_apart=False)
    r, J = fd_jacobian(res.rows, X, lo, hi, varied=res.varied)
    sse = np.einsum("pm,pm->p", r, r)
    jtj = np.einsum("pim,pjm->pij", J, J)
    return Descent(external(X, names).reshape(S, p, D), sse.reshape(S, p), jtj.reshape(S, p, D, D),
                   np.ones((S, p), bool))


def _lm_tables(eng, blk, npdt):
    """The descent's geometry table (every measurement's pb_geometry values, from the mirror
    reference.geometry; of channels also their frame rotations and vectors u, v: pbrdf_batch.cl's
    pb_chan_at) and the channels' chan[5 c ..] = comp, kind, a, b, c (a placeholder for the DOP)."""
    shared = blk.shared
    ang = blk.angles if shared else [blk.pixel_major(a, np.float64) for a in blk.angles]
    g = reference.geometry(*ang)
    rows = [g.cti, g.sti, g.ctr, g.str, g.cb, g.sb, g.tan2a]
    if blk.spec is None:
        return eng.to_device(np.stack(rows), npdt), eng.to_device(np.zeros(1, npdt), npdt)
    sp = blk.spec
    fr = reference.frame_rotations(g, ang[2])
    uv = np.concatenate([sp.u, sp.v], axis=-1)  # (C, 8) or (p, C, 8)
    uv = [uv[:, j] for j in range(8)] if shared else [blk.pixel_major(uv[..., j], np.float64) for j in range(8)]
    rows += [fr.ci, fr.si, fr.co, fr.so] + uv
    first = (lambda a: a) if shared else (lambda a: a[0])  # comp, kind and a, b, c: the same for every pixel
    chan = np.column_stack([first(sp.comp), first(sp.kind), first(sp.abc)]).astype(float)
    return eng.to_device(np.stack(rows), npdt), eng.to_device(chan.ravel(), npdt)


def _channel_flags(spec, shared):
    """(abc (C, 3), aop (C,) int32) of a block's channels (the same for every pixel)."""
    pick = (lambda a: a) if shared else (lambda a: a[0])
    return np.ascontiguousarray(pick(spec.abc), float), pick(spec.aop).astype(np.int32)


def _channel_values_opencl(eng, setup, spec, v, order, dtype):
    """The device buffer of the channels' values T[q * C + c] at every grid point q (region order)
    from compute.channels' tables (``batch_channel_values``), shared geometry and states."""
    tn, td, K, fd, _, _, abc, aop, C = device_channel_tables(eng, spec, v, dtype, setup.shadowing)
    nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size * v["ks"].size, v["kd"].size * v["c"].size
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": reference.SHADOWING[setup.shadowing]})
    G = order.size
    T = eng.empty(G * int(C) * np.dtype(DTYPES[dtype]).itemsize)
    eng.launch(prog["batch_channel_values"], (G, int(C)), T, np.int32(G), C, eng.to_device(order, np.int32),
               np.int32(nnk), np.int32(nm), np.int32(ni), tn, td, K, fd, abc, aop)
    return T


def _channel_minima_opencl(eng, blk, T, rstart, dtype):
    """(best (R, p), arg (R, p)): each region's least sum_c w_c r_c^2 of every pixel over the value
    table ``T`` (a device buffer (G, C)), r = pb_channel_residual (``batch_grid_channels``)."""
    npdt = DTYPES[dtype]
    R, P, C = rstart.size - 1, blk.P, blk.valid.shape[1]
    best, arg = np.empty((R, P), npdt), np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    _, aop = _channel_flags(blk.spec, blk.shared)
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": reference.SHADOWING[blk.setup.shadowing]})
    eng.launch(prog["batch_grid_channels"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P), np.int32(C),
               T, eng.to_device(rstart, np.int32), np.int32(R), eng.to_device(blk.pixel_major(blk.obs, npdt), npdt),
               eng.to_device(blk.pixel_major(blk.w, npdt), npdt), eng.to_device(aop, np.int32),
               local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p].astype(float), arg[:, :blk.p].astype(np.int64)


def _pixel_tables(eng, blk, v, ng, shadow, dtype):
    """The factor tables of ``pbrdf_tables.cl`` over a block's per-pixel geometry list of ``ng``
    entries (measurements or channels, times P), parameter-major: (``table(kernel, outputs, p1,
    p2, *extra)``, which launches one (:func:`pbrdf_cl.compute.tables.factor_table`), and the
    tables' sizes (n k, sigma ks, kd c) for the combining kernel's build); refuses a block whose
    tables outgrow 32-bit indices."""
    npdt = DTYPES[dtype]
    nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size * v["ks"].size, v["kd"].size * v["c"].size
    if ng * max(nnk, nm, ni) >= 2 ** 31:
        raise ValueError("internal: a block of pixels too large for 32-bit table indices")
    tab = eng.program("pbrdf_tables.cl", dtype, {"PBRDF_SHADOWING": shadow})
    geo = [eng.to_device(blk.pixel_major(a, np.float64), npdt) for a in blk.angles]

    def table(kname, outs, p1, p2, *extra):
        return factor_table(eng, tab, kname, outs, geo, ng, p1, p2, npdt, *extra, parameter_major=True)
    return table, (nnk, nm, ni)


def _channel_factors_opencl(eng, setup, blk, v, order, rstart, dtype):
    """(best, arg) of channels with per-pixel geometry or states: the channel, 1/K and fd tables of
    ``pbrdf_tables.cl`` over the list c * P + p, combined per pixel (``batch_grid_channel_factors``)."""
    npdt = DTYPES[dtype]
    shadow = reference.SHADOWING[setup.shadowing]
    R, P, C, sp = rstart.size - 1, blk.P, blk.valid.shape[1], blk.spec
    table, (nnk, nm, ni) = _pixel_tables(eng, blk, v, C * P, shadow, dtype)
    vec = [np.ascontiguousarray(np.stack([blk.pixel_major(a[..., j], np.float64) for j in range(4)], axis=-1))
           for a in (sp.u, sp.v)]  # (C, P, 4): channel c * P + p's vector
    kinds = [np.repeat(a[0], P).astype(np.int32) for a in (sp.comp, sp.kind)]
    tn, td = table("channel_table", 2, v["n"], v["k"], *(eng.to_device(a.ravel(), npdt) for a in vec),
                   *(eng.to_device(a, np.int32) for a in kinds))
    sc, = table("scale_table", 1, v["sigma"], v["ks"], npdt(-1))
    fd, = table("diffuse_table", 1, v["kd"], v["c"], npdt(1))
    abc, aop = _channel_flags(sp, False)
    prog = eng.program("pbrdf_batch.cl", dtype, {"PBRDF_SHADOWING": shadow, "PB_NNK": nnk, "PB_NM": nm, "PB_NI": ni})
    best, arg = np.empty((R, P), npdt), np.empty((R, P), npdt)
    bbest, barg = eng.empty(best.nbytes), eng.empty(arg.nbytes)
    eng.launch(prog["batch_grid_channel_factors"], (P // eng.vector_width[dtype],), bbest, barg, np.int32(P),
               np.int32(C), tn, td, sc, fd, eng.to_device(order, np.int32), eng.to_device(rstart, np.int32),
               np.int32(R), eng.to_device(blk.pixel_major(blk.obs, npdt), npdt),
               eng.to_device(blk.pixel_major(blk.w, npdt), npdt), eng.to_device(abc.ravel(), npdt),
               eng.to_device(aop, np.int32), local_size=(LOCAL_SIZE,))
    eng.read(bbest, best)
    eng.read(barg, arg)
    return best[:, :blk.p].astype(float), arg[:, :blk.p].astype(np.int64)


def _channel_values_numpy(setup, spec, v, order):
    """The channels' values (G, C) at every grid point (region order) with ``reference.py``, float64
    (compute.channels' numpy tables, combined in blocks of NUMPY_CHANNELS channels)."""
    from dataclasses import replace
    sizes = [v[n].size for n in PARAMETERS]
    unr = np.unravel_index(order, sizes)
    nk = unr[0] * sizes[1] + unr[1]
    s_ = unr[2] * sizes[3] + unr[3]
    j = unr[4] * sizes[5] + unr[5]
    out = np.empty((order.size, len(spec.obs)))
    for c0 in range(0, len(spec.obs), NUMPY_CHANNELS):
        part = spec.take(slice(c0, c0 + NUMPY_CHANNELS))
        part = replace(part, std=np.full(len(part.obs), np.nan))
        tn, td, K, fd = numpy_channel_tables(part, v, setup.shadowing)
        a, b, c = (x[:, None] for x in part.abc.T)
        out[:, c0:c0 + len(part.obs)] = reference.channel_combine(tn[:, nk], td[:, nk], K[:, s_], fd[:, j], a, b, c,
                                                                  part.aop[:, None]).T
    return out


def _channel_minima_numpy(w, obs, aop, T, rstart):
    """:func:`_channel_minima_opencl` in float64 for pixels' weights and data ``w``, ``obs`` (p, C)
    and the channels' AoP flags ``aop`` (C,): the other channels' sums as one matrix product (as the
    DOP's), the AoP's wrapped residuals channel by channel."""
    aop = np.asarray(aop, bool)
    keep = ~aop
    part = np.concatenate([(w * obs)[:, keep], w[:, keep]], axis=1) @ np.concatenate(
        [-2.0 * T[:, keep], T[:, keep] ** 2], axis=1).T
    part += np.einsum("pm,pm->p", w[:, keep], obs[:, keep] ** 2)[:, None]
    for c in np.flatnonzero(aop):
        r = reference.channel_residual(T[None, :, c], obs[:, c:c + 1], True)
        part += w[:, c:c + 1] * r * r
    R = rstart.size - 1
    arg = np.stack([rstart[r] + np.argmin(part[:, rstart[r]:rstart[r + 1]], axis=1) for r in range(R)])
    return np.take_along_axis(part.T, arg, axis=0), arg


def _channel_grid_numpy(setup, blk, v, order, rstart):
    """(best, arg) of channels on the numpy backend: the value table once (shared), or per pixel."""
    aop = _channel_flags(blk.spec, blk.shared)[1]
    if blk.shared:
        return _channel_minima_numpy(blk.w, blk.obs, aop, _channel_values_numpy(setup, blk.spec, v, order), rstart)
    R = rstart.size - 1
    best, arg = np.full((R, blk.p), np.inf), np.zeros((R, blk.p), np.int64)
    for i in range(blk.p):
        if blk.count[i] == 0:
            continue
        T = _channel_values_numpy(setup, blk.spec.take(i), v, order)
        b, a = _channel_minima_numpy(blk.w[i:i + 1], blk.obs[i:i + 1], aop, T, rstart)
        best[:, i], arg[:, i] = b[:, 0], a[:, 0]
    return best, arg



def _set_grid(params):
    """The parameter sets ``params`` (name -> (q,), every parameter) as points of the grid of their
    distinct values: (axes name -> values, the sets' flat indices into it, in PARAMETERS' order)."""
    v, idx = {}, []
    for n in PARAMETERS:
        v[n], i = np.unique(np.asarray(params[n], float), return_inverse=True)
        idx.append(i.reshape(-1))
    return v, np.ravel_multi_index(idx, [v[n].size for n in PARAMETERS]).astype(np.int32)
