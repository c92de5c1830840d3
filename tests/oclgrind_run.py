"""Run every kernel of pbrdf_cl on small inputs under the Oclgrind simulator.

Used by test_oclgrind.py in a subprocess; Oclgrind prints its reports (out-of-bounds accesses,
data races, ...) to stderr.  ``--negative`` runs a deliberately broken kernel instead, to show
that the harness sees such reports.
"""
import sys

import numpy as np

import pbrdf_cl
from pbrdf_cl.device import engine as engine_mod
from pbrdf_cl.device import transfers


def main():
    eng = pbrdf_cl.Engine("oclgrind")
    if "--negative" in sys.argv:
        import pyopencl as cl
        prg = cl.Program(eng.context, "__kernel void k(__global float *a) {"
                         " int i = get_global_id(0); a[i + 1] = 2 * a[i]; }").build()
        buf = cl.Buffer(eng.context, cl.mem_flags.READ_WRITE, 8 * 4)
        prg.k(eng.queue, (8,), None, buf)
        eng.queue.finish()
        return
    rng = np.random.default_rng(3)
    size = 33  # with LAUNCH_POINTS = 16, the last chunk holds a single point
    ti = np.concatenate([[0.0, 40.0, 89.9, 89.9], rng.uniform(0, 89.9, size - 4)])
    tr = np.concatenate([[0.0, 40.0, 89.9, 0.0], rng.uniform(0, 89.9, size - 4)])
    phi = np.concatenate([[180.0, 180.0, 0.0, 37.0], rng.uniform(0, 360, size - 4)])
    k = rng.uniform(0, 8, size)
    k[:2] = 0.0
    kw = dict(n=1.6, k=k, sigma=0.3, ks=0.9, kd=rng.uniform(0, 1, size), c=-0.3)
    transfers.LAUNCH_POINTS = 16  # exercise the chunked launches too
    for dtype in ("float32", "float64"):
        for shadowing in ("paper", "smith", "none"):
            for func in (pbrdf_cl.dop, pbrdf_cl.brdf, pbrdf_cl.mueller, pbrdf_cl.aop, pbrdf_cl.stokes):
                out = func(ti, tr, phi, dtype=dtype, shadowing=shadowing, engine=eng, **kw)
                ref = func(ti, tr, phi, dtype=dtype, shadowing=shadowing, backend="numpy", **kw)
                scale = np.nanmax(np.abs(ref))
                if func is pbrdf_cl.aop:  # degrees: where it is defined, and NaN where it is not
                    ok = np.array_equal(np.isnan(out), np.isnan(ref)) and np.allclose(out, ref, atol=1e-2,
                                                                                      equal_nan=True)
                else:
                    ok = np.allclose(out, ref, rtol=1e-4, atol=1e-5 * scale)
                if not ok:
                    raise SystemExit(f"{func.__name__} {dtype} {shadowing}: Oclgrind result differs from the reference")
    # the DOP of a conductor (kd one value, 0: the conductor's kernel, no shadowing)
    for dtype in ("float32", "float64"):
        out = pbrdf_cl.dop(ti, tr, phi, dtype=dtype, engine=eng, **dict(kw, kd=0.0))
        ref = pbrdf_cl.dop(ti, tr, phi, backend="numpy", **dict(kw, kd=0.0))
        if not np.allclose(out, ref, rtol=1e-4, atol=1e-5):
            raise SystemExit(f"dop {dtype} with kd = 0: Oclgrind result differs from the reference")
        out = pbrdf_cl.dop(ti[:5, None], tr[None, :7], 150.0, dtype=dtype, engine=eng, **dict(kw, k=2.0, kd=0.0))
        ref = pbrdf_cl.dop(ti[:5, None], tr[None, :7], 150.0, backend="numpy", **dict(kw, k=2.0, kd=0.0))
        if not np.allclose(out, ref, rtol=1e-4, atol=1e-5):
            raise SystemExit(f"broadcast dop {dtype} with kd = 0: Oclgrind result differs from the reference")
    # the broadcast twins (inputs read through their index rules, pbrdf_points.cl): blocks that
    # straddle a vector (theta_r every 17 points), a trailing axis that wraps (sigma, 17 values), a
    # block shorter than a vector (widened: kd every 3 points) and a period shorter than one (phi,
    # 2 values); launches of 16 points start inside the periods; an out-of-bounds read of a table
    # is reported by Oclgrind
    bcasts = 0
    cases = [(dict(theta_r=ti[:5, None], sigma=rng.uniform(0.1, 1, 17)), (5, 17)),
             (dict(theta_r=tr[:7, None, None], kd=rng.uniform(0, 1, (1, 3, 1)), phi=np.array([60.0, 180.0])),
              (7, 3, 2))]
    for dtype in ("float32", "float64"):
        for given, shape in cases:
            inp = dict(theta_i=40.0, theta_r=30.0, phi=150.0, n=1.6, k=2.1, sigma=0.3, ks=1.0, kd=0.2, c=-0.3)
            inp.update(given)
            assert any(r.kind == transfers.BROADCAST for r in transfers.input_plan(shape, inp).values())
            for func in (pbrdf_cl.dop, pbrdf_cl.brdf, pbrdf_cl.aop, pbrdf_cl.mueller):
                args = [inp[n] for n in ("theta_i", "theta_r", "phi")]
                kw = {n: inp[n] for n in ("n", "k", "sigma", "kd", "c")}
                out = func(*args, dtype=dtype, engine=eng, **kw)
                ref = func(*args, dtype=dtype, backend="numpy", **kw)
                tol = 1e-2 if func is pbrdf_cl.aop else 1e-5 * np.nanmax(np.abs(ref))
                if out.shape != ref.shape or not np.allclose(out, ref, rtol=1e-4, atol=tol, equal_nan=True):
                    raise SystemExit(f"broadcast {func.__name__} {dtype} {shape}: Oclgrind result differs from "
                                     "the reference")
                bcasts += 1
    # grid kernels: every row level and the one-point-per-work-item path, reductions, objective
    from pbrdf_cl.compute import dense as G
    fixed = dict(theta_i=40.0, theta_r=30.0, n=1.6, k=2.0, sigma=0.4, kd=0.2, c=-0.3)
    cases = [dict(theta_r=np.linspace(0, 80, 9), kd=np.linspace(0, 1, 17)),        # level 1 + tail
             dict(theta_r=np.linspace(0, 80, 9), sigma=np.linspace(0.1, 1, 5), kd=[0.0, 0.5, 1.0]),  # level 2
             dict(theta_r=np.linspace(0, 80, 9), n=np.linspace(1, 2, 4), k=np.linspace(0, 2, 5)),   # level 3
             dict(theta_r=np.linspace(0, 80, 5), phi=[0.0, 90.0, 180.0])]           # per point
    configs = 0
    for dtype in ("float32", "float64"):
        for axes in cases:
            fx = {n: v for n, v in fixed.items() if n not in axes}
            for quantity in ("dop", "brdf", "aop", "stokes"):
                G.grid(axes, fx, quantity=quantity, dtype=dtype, engine=eng, memory_budget=4096)
            G.reduce_grid(axes, fx, over=[next(iter(axes))], dtype=dtype, engine=eng)
            configs += 5
        data = dict(theta_i=ti[:7], theta_r=tr[:7], phi=phi[:7], dop=np.full(7, 0.2))
        for grid in (dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=0.3, kd=np.linspace(0, 1, 19)),
                     dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=[0.2, 0.4, 0.6, 0.8, 1.0], kd=[0.0, 0.3, 0.6, 0.9]),
                     dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=0.3)):
            pbrdf_cl.objective(data, grid=grid, dtype=dtype, engine=eng)
            configs += 1
        pbrdf_cl.objective(data, points=dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=[0.3, 0.5]), dtype=dtype, engine=eng)
        configs += 1
        # several sets at one geometry (PB_SETS): each row level and the per-vector kernel, every
        # set's SSE that of its own objective; in two measurement blocks (the sums carried over)
        from pbrdf_cl.io.measurements import as_measurements
        datas = [as_measurements(dict(data, dop=np.full(7, v))) for v in (0.1, 0.2, 0.4)]
        for grid in (dict(n=[1.2, 2.0], k=[0.0, 0.5, 1.0, 1.5], sigma=0.3, kd=np.linspace(0, 1, 19)),  # level 1
                     dict(n=[1.2, 1.6, 2.0, 2.4], k=[0.0, 0.5, 1.0, 1.5], sigma=[0.2, 0.4, 0.6, 0.8, 1.0],
                          kd=[0.0, 0.3, 0.6, 0.9]),  # level 2
                     dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=0.3)):  # per vector
            for budget in (1 << 20, 1100 if dtype == "float32" else 2200):  # one chunk; chunks and blocks
                _, sses = G.objective_sets(datas, grid, dtype=dtype, engine=eng, memory_budget=budget)
                for d, sse in zip(datas, sses):
                    if not np.array_equal(sse, G.objective(d, grid=grid, dtype=dtype, engine=eng,
                                                           memory_budget=budget).sse.values):
                        raise SystemExit(f"objective_sets {dtype}: a set's SSE differs from its own objective's")
                configs += 1
        # polarimetric channels (Stokes under a polarized source, an AoP, Mueller elements, an
        # intensity): the channel tables and objective_channel_rows / objective_channels
        from pbrdf_cl.model.measurables import channels as make_channels
        cols = dict(dop=np.full(7, 0.3), aop=np.full(7, 20.0), s1=np.full(7, 0.1), s2=np.full(7, -0.2),
                    m23=np.full(7, 0.1), f00=np.full(7, 0.2))
        chans = make_channels(ti[:7], tr[:7], phi[:7], cols, incident=np.tile([0.0, 1.0, 0.0], (7, 1)))
        for grid in (dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=0.3, kd=np.linspace(0, 1, 19)),
                     dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=[0.2, 0.4, 0.6, 0.8, 1.0], kd=[0.0, 0.3, 0.6, 0.9]),
                     dict(n=[1.2, 2.0], k=[0.0, 1.0], sigma=0.3)):
            got = G.objective(chans, grid=grid, dtype=dtype, engine=eng).sse.values
            ref = G.objective(chans, grid=grid, dtype="float64", backend="numpy").sse.values
            if not np.allclose(got, ref, rtol=1e-3 if dtype == "float32" else 1e-10):
                raise SystemExit(f"channel objective {dtype}: Oclgrind result differs from the reference")
            configs += 1
    # the batch kernels (pbrdf_batch.cl): grid stages with shared and per-pixel geometry, the
    # descent in float32 and float64, with and without intensities; few pixels, short runs
    from pbrdf_cl.fitting.images import corners as Bc
    from pbrdf_cl.fitting.images import pixel_fit as Bt
    Bt.SCREEN_SCHEDULE, Bt.POLISH_ITERATIONS, Bt.EXTRA_ROUNDS, Bt.INTENSITY_ITERATIONS = ((2, 2), (1, 2)), 2, 1, 2
    Bt.ONE_INCIDENCE_SCHEDULE, Bt.ONE_INCIDENCE_POLISH_STARTS = ((2, 2), (1, 2)), 1
    m_ti, m_tr = np.repeat([30.0, 50.0], 4), np.tile([20.0, 35.0, 50.0, 65.0], 2)
    truth = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
    d = np.broadcast_to(pbrdf_cl.dop(m_ti, m_tr, backend="numpy", **truth), (3, 8)).copy()
    f = np.broadcast_to(pbrdf_cl.brdf(m_ti, m_tr, backend="numpy", **truth), (3, 8)).copy()
    shape = dict(n=3, k=3, sigma=2, kd=2, c=2)
    batches = 0
    for data in (dict(dop=d, theta_i=m_ti, theta_r=m_tr),
                 dict(dop=d, theta_i=np.broadcast_to(m_ti, d.shape), theta_r=np.broadcast_to(m_tr, d.shape)),
                 dict(dop=d, f00=f, theta_i=m_ti, theta_r=m_tr)):
        res = pbrdf_cl.fit_batch(data, engine=eng, grid_shape=shape, n_starts=2)
        if not np.isfinite(res.sse.values).all():
            raise SystemExit("fit_batch under Oclgrind: non-finite results")
        batches += 1
    # the corner stage's builds of the descent (PB_LOG_N/K/KD at the index corner, PB_LOG_KD at the
    # mirror corner), every pixel sent to both by an infinite trigger
    Bc.CORNER_TRIGGER, Bc.CORNERS = np.inf, tuple(c._replace(iterations=2) for c in Bc.CORNERS)
    res = pbrdf_cl.fit_batch(dict(dop=d, theta_i=m_ti, theta_r=m_tr), engine=eng, grid_shape=shape, n_starts=2)
    if not np.isfinite(res.sse.values).all():
        raise SystemExit("fit_batch's corner stage under Oclgrind: non-finite results")
    batches += 1
    # the label stage's descents at several held values as one batch: batch_lm's PB_BASE_ROWS build
    # (every pixel its own n, k) and batch_grid_fixed (the tables of two values in one pass), each
    # pixel's result its own alone's
    from pbrdf_cl.fitting.images.job import BatchJob as _Job
    from pbrdf_cl.fitting.images.label_stage import held_setup
    from pbrdf_cl.fitting.images.pixels import Block as _Block
    from pbrdf_cl.fitting.images.pixels import grid_values, regions
    job = _Job(dict(dop=d, theta_i=m_ti, theta_r=m_tr), grid_shape=shape, n_starts=2)
    blk = _Block(job.read_rows(0, 3), job.setup, eng.call("batch_lanes"))
    helds = [held_setup(job.setup, ("n", "k"), t) for t in ([1.5, 2.0], [1.7, 2.3])]
    order, rstart = regions(grid_values(helds[0]), helds[0].free)
    best, _ = eng.call("batch_grid_fixed", helds, blk, order, rstart)
    for c, held in enumerate(helds):
        if not np.array_equal(best[c], eng.call("batch_grid", held, blk, order, rstart)[0]):
            raise SystemExit("batch_grid_fixed under Oclgrind differs from one grid per value")
    X0 = np.tile([0.5, 0.15, -0.3], (1, 3, 1))
    rows = {"n": np.array([1.5, 1.7, 1.5]), "k": np.array([2.0, 2.3, 2.0])}
    for dtype in ("float32", "float64"):
        got = eng.call("batch_lm", helds[0], blk, X0, helds[0].free, dtype, 2, False, fixed_rows=rows).x[0]
        for i, c in enumerate((0, 1, 0)):
            one = eng.call("batch_lm", helds[c], blk, X0, helds[c].free, dtype, 2, False).x[0, i]
            if not np.array_equal(got[i], one):
                raise SystemExit(f"batch_lm {dtype} with fixed_rows under Oclgrind differs from one value held")
    # polarimetric channels (s1, s2 under a 45-degree source and an AoP, out of plane): the value table
    # and the channel minima (shared geometry and states: also the ranking table of the corner stage,
    # whose trigger is still infinite, and its PB_LOG_* builds with PB_CHANNELS), the per-pixel channel
    # tables (per-pixel geometry and states), the PB_CHANNELS builds of the descent; the grid kernels
    # in float64 too
    from pbrdf_cl.fitting.images import pixel_stages as Bs
    from pbrdf_cl.fitting.images.job import BatchJob
    from pbrdf_cl.fitting.images.pixels import Block
    S = pbrdf_cl.stokes(m_ti, m_tr, 150.0, backend="numpy", incident=(0, 1, 0), **truth)
    pol = {f"s{j}": np.broadcast_to(S[:, j] / S[:, 0], (3, 8)).copy() for j in (1, 2)}
    pol["aop"] = np.broadcast_to(0.5 * np.degrees(np.arctan2(S[:, 2], S[:, 1])), (3, 8)).copy()
    pol.update(s1_std=0.01, s2_std=0.01, aop_std=1.0, theta_i=m_ti, theta_r=m_tr, phi=np.full(8, 150.0),
               in_s1=np.zeros(8), in_s2=np.ones(8), in_s3=np.zeros(8))
    per_pixel = dict(pol, **{k: np.broadcast_to(pol[k], (3, 8)) for k in ("theta_i", "theta_r", "in_s2")})
    channel_grids = 0
    for data in (pol, per_pixel):
        res = pbrdf_cl.fit_batch(data, engine=eng, grid_shape=shape, n_starts=2)
        if not np.isfinite(res.sse.values).all():
            raise SystemExit("fit_batch of channels under Oclgrind: non-finite results")
        batches += 1
        Bs.GRID_DTYPE = "float64"
        job = BatchJob(data, grid_shape=shape, n_starts=2)
        blk = Block(job.read_rows(0, 3), job.setup, eng.call("batch_lanes"))
        best, _ = eng.call("batch_grid", job.setup, blk, job.order, job.rstart)
        ref, _ = engine_mod.NumpyEngine().call("batch_grid", job.setup, Block(job.read_rows(0, 3), job.setup, 1),
                                               job.order, job.rstart)
        if not np.allclose(best, ref, rtol=1e-10):
            raise SystemExit("the float64 channel grid under Oclgrind differs from the reference")
        Bs.GRID_DTYPE = "float32"
        channel_grids += 1
    # the outer kernels (parameter sets x geometries: sensitivity maps, design Jacobians): the vector
    # kernels with padded sets (21 sets: not a multiple of the vector width) and several launches,
    # the generic one for the other quantities
    outers = 0
    G.OUTER_LAUNCH_PAIRS = 64
    geo = dict(theta_i=ti[:5], theta_r=tr[:5], phi=phi[:5])
    sets = dict(n=rng.uniform(1.1, 3, 21), k=rng.uniform(0, 3, 21), sigma=rng.uniform(0.1, 0.8, 21),
                ks=np.full(21, 0.9), kd=rng.uniform(0, 1, 21), c=rng.uniform(-1, 0, 21))
    for dtype in ("float32", "float64"):
        for quantity in ("dop", "brdf", "aop", "stokes"):
            out = G.outer(eng, quantity, geo, sets, dtype, rows=(1, 5))
            ref = G.outer(engine_mod.NumpyEngine(), quantity, geo, sets, "float64", rows=(1, 5))
            tol = 1e-2 if quantity == "aop" else 1e-4 * np.nanmax(np.abs(ref))
            if not np.allclose(out, ref, rtol=1e-4, atol=tol, equal_nan=True):
                raise SystemExit(f"outer {quantity} {dtype}: Oclgrind result differs from the reference")
            outers += 1
    print("ran", 2 * 3 * 5, "kernel configurations and", bcasts, "broadcast evaluations and", configs,
          "grid configurations and", batches, "batch fits and 2 batches of held values and", channel_grids,
          "float64 channel grids and", outers,
          "outer evaluations")


if __name__ == "__main__":
    main()
