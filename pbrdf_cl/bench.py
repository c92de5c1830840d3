"""Benchmark: evaluations per second of every evaluation path, each with its max abs error
against the float64 numpy reference on a sample.  ``scripts/bench.py`` and ``pbrdf-cl bench``
run :func:`main`; it prints a table and writes the same rows as JSON.

Rates are medians over ``--repeats`` runs.  "kernel" rows time the device work alone
(queue finished, outputs left on the device, as in reductions and the objective);
"end-to-end" rows are what a user gets from the public API (validation, transfers, the numpy
result; their peak extra memory is measured with tracemalloc); a broadcast call (``theta_r[:, None]``
against ``sigma[None, :]``) is timed both ways in the same run, its inputs sent once with their
index rules and gathered launch by launch as before issue #12.  Two limits are measured in the
same run where a C compiler exists: "C loop" (``kernels/pbrdf_host.c``: pbrdf.h itself compiled
by the host's C compiler, vectorised with OpenMP) and "memory roofline" (a loop moving the path's
bytes, read its inputs and write its output, without arithmetic); each end-to-end row reports its
fraction of both (``of_c_loop``, ``of_roofline``); the objective and sweep rows report theirs of
the limits measured for the per-point and grid rows of the same dtype (a pair is one DOP; the
roofline of writing their output).
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .compute import dense
from .compute.pointwise import dop as api_dop
from .device import engine as _engine
from .device.transfers import vector_kernel
from .fitting.objective import objective
from .model import reference

INPUTS = _engine.POINT_INPUTS


#: Flags of the C loop: vectorised, with pb_math.h's rounding (no reassociation) and infinities kept.
HOST_CFLAGS = ["-O3", "-march=native", "-ffast-math", "-fno-associative-math", "-fno-finite-math-only",
               "-fopenmp", "-shared", "-fPIC"]
_HOST_LIBS = {}


def host_library(dtype):
    """``(library, command)`` of ``kernels/pbrdf_host.c`` compiled for ``dtype`` by the host's C
    compiler (``$CC``, ``cc`` or ``gcc``), or ``(None, why not)``."""
    if dtype in _HOST_LIBS:
        return _HOST_LIBS[dtype]
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        _HOST_LIBS[dtype] = (None, "no C compiler (cc, gcc or $CC) on PATH")
        return _HOST_LIBS[dtype]
    folder = tempfile.mkdtemp(prefix="pbrdf-bench-c-")
    target = os.path.join(folder, f"pbrdf_host_{dtype}.so")
    kdir = str(_engine.kernel_dir())
    cmd = [cc, *HOST_CFLAGS, *(["-DPBRDF_DOUBLE"] if dtype == "float64" else []), "-I", kdir,
           os.path.join(kdir, "pbrdf_host.c"), "-o", target, "-lm"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if proc.returncode:
            raise OSError(_engine.first_error_line(proc.stderr or proc.stdout))
        lib = ctypes.CDLL(target)
    except (OSError, subprocess.SubprocessError) as exc:
        _HOST_LIBS[dtype] = (None, f"the C loop did not build ({exc})")
    else:
        lib.pb_host_dop.restype = None
        lib.pb_host_stream.restype = None
        _HOST_LIBS[dtype] = (lib, " ".join(cmd[:-3] + ["pbrdf_host.c"]))
    return _HOST_LIBS[dtype]


def _ptr(a):
    return a.ctypes.data_as(ctypes.c_void_p)


def c_loop_rate(lib, arrays, out, repeats):
    """Points per second of the C loop over ``arrays`` (the 9 inputs) into ``out``."""
    args = [ctypes.c_long(out.size)] + [_ptr(arrays[n]) for n in INPUTS] + [_ptr(out)]
    lib.pb_host_dop(*args)
    return median_rate(lambda: lib.pb_host_dop(*args), out.size, repeats)


def stream_bandwidth(lib, inputs, out, repeats):
    """Bytes per second of reading ``inputs`` (a list of arrays like ``out``) and writing ``out``."""
    ptrs = (ctypes.c_void_p * max(1, len(inputs)))(*[a.ctypes.data for a in inputs])
    args = (ctypes.c_long(out.size), ctypes.c_int(len(inputs)), ptrs, _ptr(out))
    lib.pb_host_stream(*args)
    nbytes = (len(inputs) + 1) * out.nbytes
    return median_rate(lambda: lib.pb_host_stream(*args), nbytes, repeats)


def traced(func):
    """``(func(), peak bytes numpy and Python allocated while it ran)``."""
    tracemalloc.start()
    try:
        result = func()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def random_points(rng, size):
    return dict(theta_i=rng.uniform(0, 89.9, size), theta_r=rng.uniform(0, 89.9, size), phi=rng.uniform(0, 360, size),
                n=rng.uniform(1, 5, size), k=rng.uniform(0, 10, size), sigma=rng.uniform(0.05, 1, size),
                ks=np.ones(size), kd=rng.uniform(0, 5, size), c=rng.uniform(-1, 0, size))


def reference_dop(pts, chunk=1 << 15, threads=2):
    """The float64 reference over ``pts`` in chunks on ``threads`` threads (numpy releases the GIL)."""
    size = pts["theta_i"].size
    out = np.empty(size)

    def work(start):
        sl = slice(start, start + chunk)
        out[sl] = reference.evaluate("dop", *(pts[n][sl] for n in INPUTS))
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(work, range(0, size, chunk)))
    return out


def median_rate(func, work, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        func()
        times.append(time.perf_counter() - t)
    return work / float(np.median(times)), float(np.median(times))


def bench_points(eng, rows, rng, size, repeats, sample):
    pts = random_points(rng, size)
    ref_sample = reference_dop({n: v[:sample] for n, v in pts.items()})
    rate, sec = median_rate(lambda: reference_dop(pts), size, max(1, repeats - 2))
    rows.append(dict(path="numpy reference (32K chunks, 2 threads)", dtype="float64", rate=rate, unit="evals/s",
                     seconds=sec, max_abs_err=0.0, n=size))
    if not eng.has_kernels:
        return  # no kernel to time, nor end-to-end rows worth comparing with the C loop
    for dtype in ("float32", "float64"):
        npdt = _engine.DTYPES[dtype]
        lanes = eng.vector_width[dtype]
        kern = eng.kernel("dop_points_vec", dtype, "paper")
        bufs = [eng.to_device(pts[n], dtype) for n in INPUTS]
        out = eng.empty(size * np.dtype(npdt).itemsize)
        args = [out, np.int32(size // lanes)]
        for b in bufs:
            args += [b, np.int32(1)]

        def run(kern=kern, lanes=lanes, args=args):  # this iteration's kernel and buffers
            eng.launch(kern, (size // lanes,), *args, local_size=(_engine.POINT_LOCAL_SIZE,))
            eng.queue.finish()
        run()
        rate, sec = median_rate(run, size // lanes * lanes, repeats)
        got = api_dop(*(pts[n][:sample] for n in ("theta_i", "theta_r", "phi")),
                      **{n: pts[n][:sample] for n in INPUTS[3:]}, dtype=dtype, engine=eng)
        rows.append(dict(path="per-point kernel (kernel)", dtype=dtype, rate=rate, unit="evals/s", seconds=sec,
                         max_abs_err=float(np.max(np.abs(got - ref_sample))), n=size))
    for dtype in ("float32", "float64"):  # what users get, with inputs of that dtype
        arrays = {n: np.ascontiguousarray(pts[n], _engine.DTYPES[dtype]) for n in INPUTS}

        def call(arrays=arrays, dtype=dtype):
            return api_dop(arrays["theta_i"], arrays["theta_r"], arrays["phi"], **{n: arrays[n] for n in INPUTS[3:]},
                           dtype=dtype, engine=eng)
        got = call()
        rate, sec = median_rate(call, size, repeats)
        want = reference_dop({n: arrays[n][:sample].astype(np.float64) for n in INPUTS})  # at these inputs
        row = dict(path=f"pbrdf_cl.dop, {dtype} inputs (end-to-end)", dtype=dtype, rate=rate, unit="evals/s",
                   seconds=sec, max_abs_err=float(np.max(np.abs(got[:sample] - want))), n=size,
                   peak_extra_mb=traced(call)[1] / 1e6, output_mb=got.nbytes / 1e6)
        rows.append(row)
        _limits(rows, row, dtype, arrays, got, repeats, per_point=True)
    bench_broadcast(eng, rows, rng, size, repeats, sample)


#: The broadcast call's axes: theta_r[:, None] (rows) against sigma[None, :] (BROADCAST_COLUMNS).
BROADCAST_COLUMNS = 4096


def bench_broadcast(eng, rows, rng, size, repeats, sample, dtype="float32"):
    """``pbrdf_cl.dop`` over ``theta_r[:, None]`` x ``sigma[None, :]`` (size / 4096 x 4096 points,
    the other inputs single values, all in ``dtype``): sent once with their index rules (issue
    #12), and gathered launch by launch on the host as before (``Engine.index_rules = False``),
    in the same run, each with its peak extra memory."""
    cols = min(BROADCAST_COLUMNS, size)
    npdt = _engine.DTYPES[dtype]
    th = rng.uniform(0, 89.9, size // cols).astype(npdt)
    sg = rng.uniform(0.05, 1, cols).astype(npdt)
    fixed = dict(n=1.5, k=2.125, ks=1.0, kd=0.25, c=-0.25)  # exact in float32: the reference sees the same inputs

    def call():
        return api_dop(40.0, th[:, None], 150.0, sigma=sg[None, :], dtype=dtype, engine=eng, **fixed)
    idx = np.arange(min(sample, th.size * cols))
    want = reference_dop(dict(theta_i=np.full(idx.size, 40.0), theta_r=th[idx // cols].astype(np.float64),
                              phi=np.full(idx.size, 150.0), sigma=sg[idx % cols].astype(np.float64),
                              **{n: np.full(idx.size, v) for n, v in fixed.items()}))
    for rules, label in ((True, "sent once"), (False, "gathered")):  # with index rules; as before #12
        saved, eng.index_rules = getattr(eng, "index_rules", True), rules
        try:
            got = call()
            rate, sec = median_rate(call, got.size, repeats)
            row = dict(path=f"pbrdf_cl.dop, {th.size} x {cols} broadcast, {label} (end-to-end)", dtype=dtype,
                       rate=rate, unit="evals/s", seconds=sec, n=got.size,
                       max_abs_err=float(np.max(np.abs(got.reshape(-1)[idx] - want))),
                       peak_extra_mb=traced(call)[1] / 1e6, output_mb=got.nbytes / 1e6)
        finally:
            eng.index_rules = saved
        _fractions_of_earlier_limits(rows, row, dtype, np.dtype(npdt).itemsize)
        rows.append(row)


def _limits(rows, row, dtype, arrays, out, repeats, per_point):
    """Rows of the C loop and the memory roofline for ``row``'s path, and its fractions of them."""
    lib, how = host_library(dtype)
    if lib is None:
        print(f"note: the C-loop and roofline rows are skipped: {how}")
        return
    inputs = [arrays[n] for n in INPUTS] if per_point else []
    bw, _ = stream_bandwidth(lib, inputs, out, repeats)
    c_rate = c_loop_rate(lib, arrays, np.empty(arrays["theta_i"].size, out.dtype), repeats)[0] if per_point else None
    itemsize = out.dtype.itemsize
    what = "read 9 inputs, write 1 output" if per_point else "write the output"
    rows.append(dict(path=f"memory roofline ({what}; limit)", dtype=dtype, rate=bw, unit="bytes/s", seconds=0.0,
                     max_abs_err=0.0, n=out.size, compiled=how))
    row["of_roofline"] = row["rate"] * itemsize * (len(inputs) + 1) / bw
    if per_point:
        rows.append(dict(path="C loop, pbrdf.h compiled by the host's cc (limit)", dtype=dtype, rate=c_rate,
                         unit="evals/s", seconds=0.0, max_abs_err=0.0, n=out.size, compiled=how))
    c_rows = [r["rate"] for r in rows if r["path"].startswith("C loop") and r["dtype"] == dtype]
    if c_rows:  # a grid is compared with the per-point C loop measured before it
        row["of_c_loop"] = row["rate"] / c_rows[-1]


def _fractions_of_earlier_limits(rows, row, dtype, bytes_per_unit):
    """``row``'s fractions of the C loop (one DOP per unit of its rate) and of the write roofline
    (``bytes_per_unit`` bytes written per unit) measured by earlier rows of ``dtype``, where there are any."""
    c_rows = [r["rate"] for r in rows if r["path"].startswith("C loop") and r["dtype"] == dtype]
    write = [r["rate"] for r in rows if r["path"].startswith("memory roofline (write") and r["dtype"] == dtype]
    if c_rows:
        row["of_c_loop"] = row["rate"] / c_rows[-1]
    if write:
        row["of_roofline"] = row["rate"] * bytes_per_unit / write[-1]


#: The material of the Mitsuba comparison: one rough conductor (no diffuse term), Mitsuba's Beckmann
#: alpha = sqrt(2) sigma (docs/model.md).  With kd = 0 the DOP is (Rs - Rp) / (Rs + Rp) at the facet
#: angle in both models, whatever their shadowing: the two must agree to float32 rounding.
MITSUBA_MATERIAL = dict(n=1.5, k=2.125, sigma=0.3, ks=1.0, kd=0.0, c=0.0)
#: A diffuse term added to the Mitsuba material for one more row of our kernel: the conductor (kd = 0)
#: takes the conductor's DOP kernel (``dop_conductor_points_vec``), which leaves out the shadowing and
#: the diffuse term its DOP does not depend on; with kd > 0 the whole kernel runs (Mitsuba's
#: roughconductor has no diffuse term to add).
DIFFUSE_MATERIAL = dict(kd=0.2, c=-0.3)
MITSUBA_VARIANT = "llvm_ad_mono_polarized"


def interleaved_rates(funcs, work, repeats, settle=0.2):
    """``{name: (wall rate, CPU rate)}`` of the ``funcs`` (``{name: callable}``), called in turn
    ``repeats`` times after one warm-up each, ``settle`` seconds apart (a thread pool that spins
    after its work, as Dr.Jit's does, slowed the next call by 7-10%): medians of ``work`` per wall
    second, and per CPU second of this process (all its threads) times ``os.cpu_count()`` (the rate
    of a machine given to this process alone: the fairer figure where other work shares the cores).
    The order turns by one at each repeat, so that no call always follows the same one: an
    end-to-end call (fresh arrays of 8.4 M points, its pages faulted in, freed) slowed the call
    after it by up to 8% on a 2-core Xeon, and in a fixed order that was always our kernel."""
    times = {name: [] for name in funcs}
    for func in funcs.values():
        func()
    names = list(funcs)
    for r in range(repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            func = funcs[name]
            time.sleep(settle)
            w, c = time.perf_counter(), time.process_time()
            func()
            times[name].append((time.perf_counter() - w, time.process_time() - c))
    cpus = os.cpu_count() or 1
    return {name: (work / float(np.median([t[0] for t in ts])), work * cpus / float(np.median([t[1] for t in ts])))
            for name, ts in times.items()}


def mitsuba_setup(threads):
    """``(mitsuba, drjit)`` with the variant :data:`MITSUBA_VARIANT` set and Dr.Jit on ``threads``
    threads, or ``(None, why not)``.  Where ``DRJIT_LIBLLVM_PATH`` is unset, a system libLLVM
    (Debian's libllvm19: /usr/lib/<arch>/libLLVM-19.so) is looked for."""
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        import glob
        found = sorted(glob.glob("/usr/lib/*/libLLVM-1[5-9].so") + glob.glob("/usr/lib/*/libLLVM-2[0-9].so"))
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found[-1]
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        return None, "mitsuba is not installed (pip install mitsuba drjit)"
    try:
        mi.set_variant(MITSUBA_VARIANT)
        dr.set_thread_count(threads)
    except Exception as exc:  # noqa: BLE001 - an ImportError without libLLVM, or whatever Dr.Jit raises
        return None, f"Mitsuba's {MITSUBA_VARIANT} variant is unavailable ({str(exc).splitlines()[0]}; " \
                     "it needs a libLLVM, e.g. apt-get install libllvm19, DRJIT_LIBLLVM_PATH naming it)"
    return mi, dr


def mitsuba_dop_function(mi, dr):
    """``(directions, dop)``: ``directions(theta_i, theta_r, phi)`` (Dr.Jit arrays of degrees) gives
    Mitsuba's local ``(wi, wo)``, and ``dop(wi, wo)`` the DOP of its polarized ``roughconductor`` with
    :data:`MITSUBA_MATERIAL` (and S0 too with ``with_s0=True``): the reflected Stokes vector of
    unpolarised light is the Mueller matrix's first column, DOP = |(S1, S2, S3)| / S0."""
    m = MITSUBA_MATERIAL
    bsdf = mi.load_dict(dict(type="roughconductor", distribution="beckmann", alpha=float(np.sqrt(2) * m["sigma"]),
                             eta=m["n"], k=m["k"], sample_visible=False))
    ctx = mi.BSDFContext()

    def directions(ti, tr, ph):
        d = np.pi / 180
        sti = dr.sin(ti * d)
        return (mi.Vector3f(sti * dr.cos(ph * d), sti * dr.sin(ph * d), dr.cos(ti * d)),
                mi.Vector3f(dr.sin(tr * d), 0, dr.cos(tr * d)))

    def dop(wi, wo, with_s0=False):
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        si.wi = wi
        mm = bsdf.eval(ctx, si, wo)
        d = dr.sqrt(dr.square(mm[1, 0]) + dr.square(mm[2, 0]) + dr.square(mm[3, 0])) / mm[0, 0]
        return (d, mm[0, 0]) if with_s0 else d
    return directions, dop


def bench_mitsuba(eng, rows, rng, size, repeats):
    """Rows of Mitsuba 3's polarized rough conductor (Dr.Jit LLVM, :data:`MITSUBA_VARIANT`) beside
    ours on the same points (random theta_i, theta_r, phi; :data:`MITSUBA_MATERIAL`), float32, on
    as many threads as the OpenCL device has compute units, timed in turn.  The material is one
    value in both (Mitsuba's BSDF holds it; our kernel reads it with stride 0, as
    :func:`pbrdf_cl.dop` sends a scalar).  Kernels alone, inputs resident: our per-point kernel on
    device buffers of the three angle arrays (degrees); Mitsuba's BSDF evaluation, DOP and
    ``dr.eval`` from Dr.Jit arrays of its local directions already evaluated (the trigonometry of
    the angles left out of its time), and again from Dr.Jit arrays of the same degrees (the
    directions computed in the same fused kernel: the same inputs as ours).  End to end: numpy
    float32 degrees in, numpy DOP out.  Each row's ``ours_over_mitsuba`` compares it with its
    counterpart (our kernel with Mitsuba's from directions; ``ours_over_mitsuba_degrees`` with
    Mitsuba's from degrees).  One more row times our kernel on the same points with a diffuse term
    (:data:`DIFFUSE_MATERIAL`): the conductor's DOP runs the conductor's kernel, as
    :func:`pbrdf_cl.dop` does (kd = 0: no shadowing, no diffuse term), this one the whole kernel;
    its ratio is to Mitsuba's conductor, which has no diffuse term.  Skipped with a note where
    mitsuba or a libLLVM is missing."""
    if not eng.has_kernels:
        return
    threads = getattr(getattr(eng, "device", None), "max_compute_units", None) or os.cpu_count() or 1
    mi, dr = mitsuba_setup(threads)
    if mi is None:
        print(f"note: the Mitsuba rows are skipped: {dr}")
        return
    directions, mdop = mitsuba_dop_function(mi, dr)
    lanes = eng.vector_width["float32"]
    size = size // lanes * lanes
    geo = {n: v.astype(np.float32) for n, v in random_points(rng, size).items() if n in INPUTS[:3]}
    degrees = [mi.Float(geo[n]) for n in INPUTS[:3]]
    dr.eval(*degrees)
    wi, wo = directions(*degrees)
    dr.eval(wi, wo)
    # the kernel pbrdf_cl.dop runs for each material (the conductor's: its DOP alone)
    kern = eng.kernel(f"{vector_kernel('dop', MITSUBA_MATERIAL)}_points_vec", "float32", "paper")
    kern_diffuse = eng.kernel(f"{vector_kernel('dop', DIFFUSE_MATERIAL)}_points_vec", "float32", "paper")
    out = eng.empty(size * 4)

    def kernel_args(material):
        args = [out, np.int32(size // lanes)]
        for n in INPUTS:
            one = n not in geo  # the material: one value, stride 0
            args += [eng.to_device(np.full(lanes, material[n]) if one else geo[n], "float32"), np.int32(not one)]
        return args
    args, args_diffuse = kernel_args(MITSUBA_MATERIAL), kernel_args({**MITSUBA_MATERIAL, **DIFFUSE_MATERIAL})

    def ours_kernel():
        eng.launch(kern, (size // lanes,), *args, local_size=(_engine.POINT_LOCAL_SIZE,))
        eng.queue.finish()

    def ours_diffuse_kernel():
        eng.launch(kern_diffuse, (size // lanes,), *args_diffuse, local_size=(_engine.POINT_LOCAL_SIZE,))
        eng.queue.finish()

    def mitsuba_kernel():
        dr.eval(mdop(wi, wo))
        dr.sync_thread()

    def mitsuba_degrees_kernel():
        dr.eval(mdop(*directions(*degrees)))
        dr.sync_thread()

    def ours_e2e():
        return api_dop(geo["theta_i"], geo["theta_r"], geo["phi"], dtype="float32", engine=eng, **MITSUBA_MATERIAL)

    def mitsuba_e2e():
        return np.asarray(mdop(*directions(*(mi.Float(geo[n]) for n in INPUTS[:3])))).reshape(-1)
    want, s0 = (np.asarray(a).reshape(-1) for a in mdop(wi, wo, with_s0=True))
    lit = s0 > 1e-10  # where S1^2 + S2^2 of Mitsuba's float32 lobe stays clear of underflow
    agree = float(np.max(np.abs(ours_e2e()[lit] - want[lit]))) if lit.any() else float("nan")
    # the row with the diffuse term: our DOP against the float64 reference on the first points
    few = {n: v[:1 << 16] for n, v in geo.items()}
    material = {**MITSUBA_MATERIAL, **DIFFUSE_MATERIAL}
    agree_diffuse = float(np.max(np.abs(
        api_dop(few["theta_i"], few["theta_r"], few["phi"], dtype="float32", engine=eng, **material)
        - api_dop(few["theta_i"], few["theta_r"], few["phi"], backend="numpy", **material))))
    rates = interleaved_rates(dict(ours_kernel=ours_kernel, ours_diffuse_kernel=ours_diffuse_kernel,
                                   mitsuba_kernel=mitsuba_kernel, mitsuba_degrees_kernel=mitsuba_degrees_kernel,
                                   ours_e2e=ours_e2e, mitsuba_e2e=mitsuba_e2e), size, repeats)
    version = mi.__version__
    diffuse = ", ".join(f"{n} {v:g}" for n, v in DIFFUSE_MATERIAL.items())
    labels = dict(ours_kernel="per-point kernel, Mitsuba's points (kernel)",
                  ours_diffuse_kernel=f"per-point kernel, Mitsuba's points, {diffuse} (kernel)",
                  mitsuba_kernel=f"Mitsuba {version} roughconductor, resident directions (kernel)",
                  mitsuba_degrees_kernel=f"Mitsuba {version} roughconductor, resident degrees (kernel)",
                  ours_e2e="pbrdf_cl.dop, Mitsuba's points (end-to-end)",
                  mitsuba_e2e=f"Mitsuba {version} roughconductor from numpy (end-to-end)")
    pairs = dict(ours_kernel="mitsuba_kernel", ours_diffuse_kernel="mitsuba_kernel", mitsuba_kernel="ours_kernel",
                 mitsuba_degrees_kernel="ours_kernel", ours_e2e="mitsuba_e2e", mitsuba_e2e="ours_e2e")
    for name, (rate, cpu_rate) in rates.items():
        ours, theirs = (name, pairs[name]) if name.startswith("ours") else (pairs[name], name)
        row = dict(path=labels[name], dtype="float32", rate=rate, unit="evals/s", seconds=size / rate, n=size,
                   max_abs_err=agree_diffuse if name == "ours_diffuse_kernel" else agree, cpu_rate=cpu_rate,
                   threads=threads,
                   ours_over_mitsuba=rates[ours][0] / rates[theirs][0],
                   ours_over_mitsuba_cpu=rates[ours][1] / rates[theirs][1])
        if name == "ours_kernel":
            row.update(ours_over_mitsuba_degrees=rate / rates["mitsuba_degrees_kernel"][0],
                       ours_over_mitsuba_degrees_cpu=cpu_rate / rates["mitsuba_degrees_kernel"][1])
        rows.append(row)


GRID_AXES = dict(theta_i=np.linspace(10, 80, 16), theta_r=np.linspace(0, 85, 64), n=np.linspace(1, 3, 16),
                 k=np.linspace(0, 5, 16), sigma=np.linspace(0.05, 1, 32), kd=np.linspace(0, 1, 16),
                 c=np.linspace(-1, 0, 2))  # 268M points


def _grid_sample_error(da, axes, rng, count=2000):
    names = list(da.dims)
    idx = [rng.integers(0, da.sizes[n], count) for n in names]
    got = da.values[tuple(idx)]
    kw = {n: np.asarray(axes[n])[i] for n, i in zip(names, idx)}
    want = api_dop(kw.pop("theta_i"), kw.pop("theta_r"), 180.0, backend="numpy", **kw)
    return float(np.max(np.abs(got - want)))


def _dtypes(eng):
    """The precisions worth a row on ``eng``: float32 and float64, or float64 alone where the engine
    computes in float64 whatever is asked (the numpy backend)."""
    return list(dict.fromkeys(eng.compute_dtype(d) for d in ("float32", "float64")))


def _backend_label(eng):
    """What a row's path says of the backend it ran on: nothing for an OpenCL device."""
    return ", numpy backend" if eng.is_numpy else ""


def _grid_kernel_rate(eng, plan, dtype, repeats):
    """``(grid points per second, seconds)`` of the ``grid_rows`` kernel over ``plan``, the outputs
    left on the device."""
    ng, nnk, nm, ni = dense.family_sizes(plan)
    npdt = _engine.DTYPES[dtype]
    level, row_len = dense.row_level(nnk, nm, ni, ng, 1 << 30)
    prog = dense.grid_program(eng, dtype, (nnk, nm, ni), "uint", "dop", PB_ROW_LEVEL=level, PB_ROW_LEN=row_len)
    tables = dense.Tables(eng, dtype, "paper", "dop", *dense.geometry_list(plan, 0, ng), plan.values)
    chunk_rows = max(1, (1 << 24) // row_len)
    total_rows = plan.size // row_len
    out = eng.empty(chunk_rows * row_len * np.dtype(npdt).itemsize)

    def run():
        for r0 in range(0, total_rows, chunk_rows):
            cnt = min(chunk_rows, total_rows - r0)
            eng.launch(prog["grid_rows"], (cnt,), out, np.uint32(r0), np.uint32(cnt), np.uint32(0), *tables.args())
        eng.queue.finish()
    run()
    return median_rate(run, plan.size, repeats)


def bench_grid(eng, rows, rng, scale, repeats):
    axes = dict(GRID_AXES)
    if scale < 1:
        axes["theta_r"] = axes["theta_r"][::4]
        axes["sigma"] = axes["sigma"][::4]
    plan = dense.GridPlan(axes, {})
    for dtype in _dtypes(eng):
        kernel = _grid_kernel_rate(eng, plan, dtype, repeats) if eng.has_kernels else None
        da = dense.grid(axes, {}, dtype=dtype, engine=eng)
        err = _grid_sample_error(da, axes, rng)
        if kernel is not None:
            rows.append(dict(path="factorised grid (kernel)", dtype=dtype, rate=kernel[0], unit="grid points/s",
                             seconds=kernel[1], max_abs_err=err, n=plan.size))
        rate, sec = median_rate(lambda dtype=dtype: dense.grid(axes, {}, dtype=dtype, engine=eng), plan.size,
                                max(1, repeats - 2))
        row = dict(path=f"pbrdf_cl.grid -> host DataArray (end-to-end{_backend_label(eng)})", dtype=dtype, rate=rate,
                   unit="grid points/s", seconds=sec, max_abs_err=err, n=plan.size,
                   peak_extra_mb=traced(lambda dtype=dtype: dense.grid(axes, {}, dtype=dtype, engine=eng))[1] / 1e6,
                   output_mb=da.values.nbytes / 1e6)
        rows.append(row)
        _limits(rows, row, dtype, None, da.values.reshape(-1), max(1, repeats - 2), per_point=False)
        del da


def bench_objective(eng, rows, rng, scale, repeats):
    ti = np.repeat([30.0, 40.0, 50.0], 10)
    tr = np.tile(np.arange(20.0, 66.0, 5.0), 3)
    truth = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15 / 0.9, c=-0.3)
    dop = api_dop(ti, tr, 180.0, backend="numpy", **truth) + rng.normal(0, 0.002, ti.size)
    data = dict(theta_i=ti, theta_r=tr, dop=np.clip(dop, 0, 1))
    grid = dict(n=np.linspace(1, 5, 64), k=np.linspace(0, 10, 64), sigma=np.linspace(0.05, 1, 32),
                kd=np.linspace(0, 5, 32), c=np.linspace(-1, 0, 16))
    if scale < 1:
        grid["n"], grid["k"] = grid["n"][::4], grid["k"][::4]
    for dtype in _dtypes(eng):
        res = objective(data, grid=grid, dtype=dtype, engine=eng)
        # error: the objective of a sample of parameter vectors against numpy
        idx = rng.integers(0, res.sse.size, 500)
        unr = np.unravel_index(idx, res.sse.shape)
        params = {n: np.asarray(grid[n])[i] for n, i in zip(res.sse.dims, unr)}
        d = api_dop(ti[:, None], tr[:, None], 180.0, backend="numpy", **{n: v[None, :] for n, v in params.items()})
        want = ((d - data["dop"][:, None]) ** 2).sum(axis=0)
        err = float(np.max(np.abs(res.sse.values.ravel()[idx] - want)))
        rate, sec = median_rate(lambda dtype=dtype: objective(data, grid=grid, dtype=dtype, engine=eng,
                                                          return_sse=False),
                                res.n_pairs, repeats)
        row = dict(path=f"objective, grid x 30 measurements (end-to-end, top-10{_backend_label(eng)})", dtype=dtype,
                   rate=rate, unit="pairs/s", seconds=sec, max_abs_err=err, n=res.n_pairs)
        rows.append(row)
        # a pair is one DOP (the C loop's unit); with the whole SSE kept it writes one value per 30 pairs
        _fractions_of_earlier_limits(rows, row, dtype, np.dtype(_engine.DTYPES[dtype]).itemsize / ti.size)


SWEEP_AXES = dict(theta_i=np.linspace(10, 80, 8), theta_r=np.linspace(0, 85, 32), n=np.linspace(1, 3, 16),
                  k=np.linspace(0, 5, 16), sigma=np.linspace(0.05, 1, 16), kd=np.linspace(0, 1, 8),
                  c=np.linspace(-1, 0, 2))  # 16.8M points: 67 MB of float32, 16x a 4 MiB budget


def bench_sweep(eng, device, rows, rng, scale, repeats, workers=2, backend="auto"):
    """pbrdf_cl.sweep into a Zarr store (Zarr writes and the done record included) of a sweep at
    least 10x its memory budget: here, and on a ``workers``-process LocalCluster (0: skipped)."""
    import shutil
    import tempfile

    import xarray as xr

    from .analysis.sweeps import SweepSpec, sweep
    axes, budget = dict(SWEEP_AXES), 4 << 20
    if scale < 1:
        axes["theta_r"], axes["sigma"], budget = axes["theta_r"][::4], axes["sigma"][::4], 256 << 10
    spec = SweepSpec(dict(axes={n: a.tolist() for n, a in axes.items()}, memory_budget=budget))
    assert spec.points * spec.itemsize >= 10 * spec.memory_budget
    folder = tempfile.mkdtemp(prefix="pbrdf-bench-sweep-")
    runs = iter(range(1 << 30))

    def run(**kw):
        store = os.path.join(folder, f"s{next(runs)}.zarr")
        res = sweep(spec, store, progress=False, **kw)
        assert res.complete and res.chunks_computed == spec.n_chunks
        return store

    def measure(label, **kw):
        store = run(**kw)  # warm-up: kernels built (on every worker), store layout checked
        ds = xr.open_zarr(store)
        idx = {n: xr.DataArray(rng.integers(0, ds.sizes[n], 2000), dims="sample") for n in ds[spec.quantity].dims}
        got = ds[spec.quantity].isel(idx).values
        kw_ref = {n: axes[n][idx[n].values] for n in idx}
        want = api_dop(kw_ref.pop("theta_i"), kw_ref.pop("theta_r"), 180.0, backend="numpy", **kw_ref)
        err = float(np.max(np.abs(got - want)))
        shutil.rmtree(store)

        def timed():
            shutil.rmtree(run(**kw))
        rate, sec = median_rate(timed, spec.points, max(1, repeats - 2))
        label += _backend_label(eng)
        row = dict(path=f"sweep -> Zarr store, {label} (end-to-end)", dtype=spec.dtype, rate=rate,
                   unit="grid points/s", seconds=sec, max_abs_err=err, n=spec.points,
                   memory_budget=spec.memory_budget, chunks=spec.n_chunks)
        rows.append(row)
        _fractions_of_earlier_limits(rows, row, spec.dtype, spec.itemsize)
    try:
        measure("here", engine=eng)
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            if workers:
                print("note: the LocalCluster sweep row is skipped: dask.distributed is not installed "
                      "(pip install 'pbrdf-cl[cluster]')")
            workers = 0
        if workers:
            with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
                    Client(cl) as client:
                measure(f"{workers}-worker LocalCluster", client=client, device=device, backend=backend)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


#: The sections of a run, in order (``--only`` picks some).
SECTIONS = ("points", "mitsuba", "grid", "objective", "sweep")


def main(argv=None):
    p = argparse.ArgumentParser(prog="pbrdf-cl bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--device", help="OpenCL device (P:D or a name substring); default as pbrdf_cl.Engine()")
    p.add_argument("--backend", choices=_engine.BACKENDS, default="auto",
                   help="auto (default: the OpenCL device, or numpy without one), opencl, or numpy (the "
                        "reference; kernel rows are skipped and the grid sizes reduced)")
    p.add_argument("--points", type=int, default=1 << 23, help="points for the per-point rows (default 8.4M)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="small sizes, for a smoke test")
    p.add_argument("--json", default="bench.json", help="where to write the JSON (default bench.json)")
    p.add_argument("--sweep-workers", type=int, default=2,
                   help="LocalCluster processes for the sweep row (default 2; 0 skips it; --quick skips it)")
    p.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                   help="run only these sections (default: all): points (the per-point and broadcast rows), mitsuba "
                        "(Mitsuba 3's polarized rough conductor beside the per-point kernel, where mitsuba is "
                        "installed), grid, objective, sweep")
    args = p.parse_args(argv)
    from .errors import CommandError
    from .outputs import check_json_output
    try:  # the report's file, checked before the work rather than after it
        check_json_output("--json", args.json)
    except CommandError as exc:
        print(f"pbrdf-cl: error: {exc}", file=sys.stderr)
        return 1
    size, repeats, scale = args.points, args.repeats, 1.0
    if args.quick:
        size, repeats, scale = 1 << 16, 2, 0.25
    eng = _engine.engine_for(device=args.device or None, backend=args.backend)
    sweep_scale = scale
    if not eng.has_kernels:
        scale = min(scale, 0.25)  # the reference, without kernels, is ~100x slower than a device: smaller grids
    rng = np.random.default_rng(2020)
    rows = []
    t0 = time.perf_counter()
    if "points" in args.only:
        bench_points(eng, rows, rng, size, repeats, min(size, 1 << 18))
    if "mitsuba" in args.only:
        bench_mitsuba(eng, rows, rng, size, repeats)
    if "grid" in args.only:
        bench_grid(eng, rows, rng, scale, repeats)
    if "objective" in args.only:
        bench_objective(eng, rows, rng, scale, repeats)
    if "sweep" in args.only:
        bench_sweep(eng, args.device, rows, rng, sweep_scale, repeats, workers=0 if args.quick else args.sweep_workers,
                    backend=args.backend)
    device = eng.description
    print(f"device: {device}; host: {platform.processor() or platform.machine()}, {os.cpu_count()} cpus")
    print(f"{'path':58s} {'dtype':8s} {'rate':>12s} {'unit':14s} {'max |err|':>10s}  of C loop / roofline, peak")
    for r in rows:
        extra = ""
        if "of_c_loop" in r or "of_roofline" in r:
            extra += f"  {r.get('of_c_loop', float('nan')):.2f} / {r.get('of_roofline', float('nan')):.2f}"
        if "ours_over_mitsuba" in r:
            extra += (f"  ours/Mitsuba {r['ours_over_mitsuba']:.2f}x (per CPU-s: {r['cpu_rate'] / 1e6:.1f} M, "
                      f"{r['ours_over_mitsuba_cpu']:.2f}x)")
        if "ours_over_mitsuba_degrees" in r:
            extra += (f"; over Mitsuba from degrees {r['ours_over_mitsuba_degrees']:.2f}x "
                      f"(per CPU-s {r['ours_over_mitsuba_degrees_cpu']:.2f}x)")
        if "peak_extra_mb" in r:
            extra += f", peak +{r['peak_extra_mb']:.0f} MB (output {r['output_mb']:.0f} MB)"
        print(f"{r['path']:58s} {r['dtype']:8s} {r['rate'] / 1e6:10.1f} M {r['unit']:14s} "
              f"{r['max_abs_err']:10.2e}{extra}")
    report = dict(device=device, cpus=os.cpu_count(), pyopencl=_engine.cl.VERSION_TEXT,
                  seconds=time.perf_counter() - t0, rows=rows)
    with open(args.json, "w") as fh:
        json.dump(report, fh, indent=2)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
