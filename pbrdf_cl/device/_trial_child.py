"""The child process of :mod:`pbrdf_cl.device.trials`: builds OpenCL programs and launches each kernel once,
so that a driver that crashes, aborts or hangs takes this process down instead of the user's.

Run as a script (``python _trial_child.py``), never imported by the package: it imports only the
standard library, numpy and pyopencl, so that it starts in a fraction of a second.  Requests come
as JSON lines on stdin, answers go as JSON lines to the file descriptor that was stdout when it
started; file descriptor 1 itself is pointed at stderr, so that nothing a driver prints can break
the protocol.  What the drivers print (LLVM's last words) stays in stderr, which the parent reads.

Requests (``op``):

- ``program``: build ``source`` with ``options`` on ``device`` and launch every kernel of it once
  over one work-item, every argument zero bytes (buffers NULL, sizes 0: each kernel returns at its
  bounds check, but the driver has generated its code, which is where PoCL 3.0 crashes).  Answer:
  ``{"ok": true, "kernels": [...]}`` or ``{"ok": false, "error": "build failed: ..."}``.
- ``probe``: build ``source`` for each of ``dtypes`` and evaluate the probe kernel at ``points``.
  Answer: ``{"ok": true, "values": {dtype: [...]}}`` or ``{"ok": false, "error": ...}``.

The parent's test switch (``fake``: ``abort``, ``segv``, ``hang``, ``llvm``, ``exit``) makes this
process die as a broken driver would, after the build (which the driver may have cached) and before
the first launch.
"""
import json
import os
import select
import signal
import sys
import time


def _fake(how):
    sys.stderr.flush()
    if how == "llvm":
        os.write(2, b"LLVM ERROR: Do not know how to scalarize this operator's operand! (simulated)\n")
        os.abort()
    if how == "abort":
        os.abort()
    if how == "segv":  # as a driver's invalid access ends (a driver may have caught SIGSEGV: undo that)
        signal.signal(signal.SIGSEGV, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGSEGV)
    if how == "exit":
        os._exit(3)
    if how == "hang":
        while True:
            time.sleep(60)


def _device(cl, spec):
    """The device the parent names: platform and device name and driver version must match; its
    list position breaks ties between identical devices."""
    matches = []
    for ip, plat in enumerate(cl.get_platforms()):
        try:
            devices = plat.get_devices()
        except cl.Error:
            continue
        for idev, dev in enumerate(devices):
            if (plat.name.strip(), dev.name.strip(), dev.driver_version.strip()) == \
                    (spec["platform"], spec["device"], spec["driver"]):
                matches.append(((ip, idev) != tuple(spec.get("index", (-1, -1))), dev))
    if not matches:
        raise LookupError(f"device {spec['platform']} / {spec['device']} not found in the child process")
    return sorted(matches, key=lambda m: m[0])[0][1]


def _zero_args(cl, np, kernel):
    """Set every argument of ``kernel`` to zero bytes of the size the driver accepts (largest first,
    so that a driver that does not check a scalar's size still reads zeros): NULL for a buffer, 0 for
    a count; a __local pointer gets a small allocation."""
    for i in range(kernel.num_args):
        for size in (64, 32, 16, 8, 4, 2, 1):
            try:
                kernel.set_arg(i, np.zeros(size, np.uint8))
                break
            except cl.Error:
                continue
        else:
            kernel.set_arg(i, cl.LocalMemory(64))


def _program(cl, np, req):
    dev = _device(cl, req["device"])
    ctx = cl.Context([dev])
    queue = cl.CommandQueue(ctx)
    try:
        prg = cl.Program(ctx, req["source"]).build(options=req["options"])
    except cl.Error as exc:
        return {"ok": False, "error": "build failed", "log": str(exc)}
    if req.get("fake"):  # built (and cached), it dies where PoCL 3.0 does: generating the kernels' code
        _fake(req["fake"])
    names = []
    for kernel in prg.all_kernels():
        _zero_args(cl, np, kernel)
        cl.enqueue_nd_range_kernel(queue, kernel, (1,), None)
        queue.finish()
        names.append(kernel.function_name)
    if not names:
        return {"ok": False, "error": "the build has no kernels"}
    # built again, a driver with a cache (PoCL) loads what it just stored: the parent will
    again = {k.function_name for k in cl.Program(ctx, req["source"]).build(options=req["options"]).all_kernels()}
    if again != set(names):
        return {"ok": False, "error": f"loaded back from the driver's cache it has kernels {sorted(again)} instead "
                                      f"of {sorted(names)}"}
    return {"ok": True, "kernels": names}


def _probe(cl, np, req):
    dev = _device(cl, req["device"])
    ctx = cl.Context([dev])
    queue = cl.CommandQueue(ctx)
    values = {}
    for dtype in req["dtypes"]:
        try:
            prg = cl.Program(ctx, req["source"]).build(options=req["options"][dtype])
        except cl.Error as exc:
            return {"ok": False, "error": f"{dtype} build failed", "log": str(exc), "values": values}
        if req.get("fake"):
            _fake(req["fake"])
        pts = np.ascontiguousarray(req["points"], dtype=dtype)
        mf = cl.mem_flags
        buf_in = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=pts)
        out = np.full(len(pts), np.nan, dtype=dtype)
        buf_out = cl.Buffer(ctx, mf.WRITE_ONLY, out.nbytes)
        prg.pbrdf_probe(queue, (len(pts),), None, buf_out, buf_in, np.int32(len(pts)))
        cl.enqueue_copy(queue, out, buf_out)
        queue.finish()
        values[dtype] = [float(v) for v in out]
    return {"ok": True, "values": values}


def main():
    proto = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # whatever a driver prints goes to stderr, never into the answers
    import ctypes
    for lib in json.loads(os.environ.get("PBRDF_CL_TRIAL_PRELOAD", "[]")):
        try:  # the libraries pbrdf_cl.device.drivers loaded for Intel's runtime, in the same order
            ctypes.CDLL(lib, mode=ctypes.RTLD_GLOBAL)
        except OSError:
            pass
    import numpy as np
    import pyopencl as cl
    idle = float(os.environ.get("PBRDF_CL_TRIAL_IDLE", "600"))
    while True:
        ready, _, _ = select.select([sys.stdin], [], [], idle)
        if not ready:
            return 0  # idle: the parent starts another when it needs one
        line = sys.stdin.readline()
        if not line:
            return 0
        req = json.loads(line)
        print(f"pbrdf-cl trial: {req.get('label', req['op'])}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            answer = (_probe if req["op"] == "probe" else _program)(cl, np, req)
        except (cl.Error, LookupError, ValueError, RuntimeError) as exc:
            answer = {"ok": False, "error": "failed", "log": str(exc)}
        answer["seconds"] = time.perf_counter() - t0
        sys.stderr.flush()
        proto.write(json.dumps(answer) + "\n")
        proto.flush()


if __name__ == "__main__":
    sys.exit(main())
