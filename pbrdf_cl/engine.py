"""OpenCL engine: one object owning the context, queue, built programs and kernels.

Device choice, in order: an explicit ``device`` argument, then the ``PYOPENCL_CTX``
environment variable, then the first CPU device of a PoCL platform, then any other
device that is not the Oclgrind simulator.  A device is named by a ``cl.Device``,
by ``"P"`` or ``"P:D"`` (platform and device indices, as ``pbrdf-cl devices`` lists
them), or by a case-insensitive substring of "platform name / device name"
(``"pocl"``, ``"nvidia"``, ``"oclgrind"``).

Programs are built once per (precision, shadowing variant) with ``-D`` options and
kept, with their ``cl.Kernel`` objects, for the life of the engine.
"""
from __future__ import annotations

import os
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from . import reference

try:
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - pyopencl is a hard dependency
    cl = None
    _IMPORT_ERROR = exc
else:
    _IMPORT_ERROR = None

POINT_INPUTS = ("theta_i", "theta_r", "phi", "n", "k", "sigma", "ks", "kd", "c")
DTYPES = {"float32": np.float32, "float64": np.float64}
#: Vector width of the explicitly vectorised kernels (float16 / double8 were fastest on PoCL 3.0).
VECTOR_WIDTH = {"float32": 16, "float64": 8}
#: Work-group size of the vector per-point kernels.
VECTOR_LOCAL_SIZE = 8
#: Points per kernel launch; bounds the temporary device memory of one call.
LAUNCH_POINTS = 1 << 22

_HOW_TO_GET_ONE = ("install a CPU OpenCL driver with `pip install pocl-binary-distribution`, "
                   "or evaluate with backend=\"numpy\" (the float64 reference)")


class OpenCLUnavailableError(RuntimeError):
    """No usable OpenCL platform or device."""


def kernel_dir() -> Path:
    """The folder holding the OpenCL sources: the installed ``pbrdf_cl.kernels`` package
    resource, or the source tree's top-level ``kernels/`` when running from a checkout."""
    try:
        folder = resources.files("pbrdf_cl.kernels")
        if folder.joinpath("pbrdf.h").is_file():
            return Path(str(folder))
    except ModuleNotFoundError:
        pass
    folder = Path(__file__).resolve().parent.parent / "kernels"
    if (folder / "pbrdf.h").is_file():
        return folder
    raise FileNotFoundError("the OpenCL sources of pbrdf_cl (pbrdf_cl/kernels/pbrdf.h) are missing "
                            "from this installation; reinstall the package")


def _platforms():
    if cl is None:
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({_IMPORT_ERROR}); {_HOW_TO_GET_ONE}")
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise OpenCLUnavailableError(f"no OpenCL platform found ({exc}); {_HOW_TO_GET_ONE}") from None
    if not platforms:
        raise OpenCLUnavailableError(f"no OpenCL platform found; {_HOW_TO_GET_ONE}")
    return platforms


def list_devices():
    """All OpenCL devices as a list of ``(platform_index, device_index, platform, device)``."""
    out = []
    for ip, plat in enumerate(_platforms()):
        try:
            devices = plat.get_devices()
        except cl.Error:
            continue
        for idev, dev in enumerate(devices):
            out.append((ip, idev, plat, dev))
    return out


def _is_simulator(plat) -> bool:
    return "oclgrind" in plat.name.lower()


def select_device(device=None):
    """Pick a ``cl.Device`` (see the module docstring for the order)."""
    if cl is not None and isinstance(device, cl.Device):
        return device
    spec = device if device is not None else os.environ.get("PYOPENCL_CTX") or None
    found = list_devices()
    if not found:
        raise OpenCLUnavailableError(f"OpenCL platforms exist but have no devices; {_HOW_TO_GET_ONE}")
    if spec is not None:
        spec = str(spec).strip()
        where = "device" if device is not None else "PYOPENCL_CTX"
        parts = spec.split(":")
        if all(p.isdigit() for p in parts) and 1 <= len(parts) <= 2:
            ip, idev = int(parts[0]), int(parts[1]) if len(parts) == 2 else 0
            for p_, d_, _, dev in found:
                if (p_, d_) == (ip, idev):
                    return dev
            raise ValueError(f"{where}={spec!r}: no OpenCL device {ip}:{idev}; "
                             f"`pbrdf-cl devices` lists the ones present")
        for _, _, plat, dev in found:
            if spec.lower() in f"{plat.name} / {dev.name}".lower():
                return dev
        raise ValueError(f"{where}={spec!r} matches no OpenCL platform or device name; "
                         f"`pbrdf-cl devices` lists the ones present")
    real = [(plat, dev) for _, _, plat, dev in found if not _is_simulator(plat)]
    for plat, dev in real:
        if dev.type & cl.device_type.CPU and "portable computing language" in plat.name.lower():
            return dev
    for plat, dev in real:
        if dev.type & cl.device_type.CPU:
            return dev
    if real:
        return real[0][1]
    return found[0][3]


def has_fp64(device) -> bool:
    return bool(device.double_fp_config) or "cl_khr_fp64" in device.extensions


class Engine:
    """Owns an OpenCL context and queue on one device and the programs built for it.

    Parameters
    ----------
    device : cl.Device, str or None
        See :func:`select_device`.
    profiling : bool
        Create the queue with profiling enabled (``last_event_seconds`` then reports the
        device time of the last launch).
    """

    def __init__(self, device=None, *, profiling=False):
        self.device = select_device(device)
        self.context = cl.Context([self.device])
        props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self.profiling = profiling
        self.fp64 = has_fp64(self.device)
        #: DOP and F00 use the vector build of the per-point kernels (False: one point per work-item)
        self.vectorise = True
        self._kernels = {}
        self._last_event = None

    def __repr__(self):
        return (f"Engine(device={self.device.name.strip()!r}, "
                f"platform={self.device.platform.name.strip()!r}, fp64={self.fp64})")

    def program(self, filename: str, dtype: str, defines=None, prefix: str = ""):
        """The kernels of ``kernels/<filename>`` built for ``dtype`` with ``-D`` ``defines`` (and
        ``prefix`` source text prepended), as a dict name -> ``cl.Kernel``; built once per key."""
        defines = dict(defines or {})
        key = (filename, dtype, tuple(sorted(defines.items())), prefix)
        if key not in self._kernels:
            if dtype == "float64" and not self.fp64:
                raise ValueError(f"dtype='float64': device {self.device.name.strip()!r} has no float64 "
                                 "support; use dtype='float32' or another device")
            # -w: PoCL's clang otherwise prints ABI notes about wide vectors to stderr
            opts = ["-I", str(kernel_dir()), "-w", f"-DPB_VW={VECTOR_WIDTH[dtype]}"]
            if dtype == "float64":
                opts.append("-DPBRDF_DOUBLE")
            opts += [f"-D{name}" if value is None else f"-D{name}={value}" for name, value in defines.items()]
            src = prefix + (kernel_dir() / filename).read_text()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", cl.CompilerWarning)
                program = cl.Program(self.context, src).build(options=opts)
            self._kernels[key] = {k.function_name: k for k in program.all_kernels()}
        return self._kernels[key]

    def kernel(self, name: str, dtype: str, shadowing: str):
        """The ``cl.Kernel`` ``name`` of ``pbrdf_points.cl`` for this precision and variant (built once);
        names ending in ``_vec`` come from the vector build (``VECTOR_WIDTH`` points per work-item)."""
        defines = {"PBRDF_SHADOWING": reference.SHADOWING[shadowing]}
        if name.endswith("_vec"):
            defines["PB_VECTOR_REAL"] = VECTOR_WIDTH[dtype]
        return self.program("pbrdf_points.cl", dtype, defines)[name]

    def launch(self, kernel, global_size, *args, local_size=None):
        """Set ``args`` and enqueue ``kernel`` over ``global_size`` (padded up to a multiple of
        ``local_size`` when one is given: kernels check their bounds); returns the event."""
        kernel.set_args(*args)
        global_size = tuple(int(g) for g in global_size)
        if local_size is not None:
            local_size = tuple(int(v) for v in local_size)
            global_size = tuple(-(-g // v) * v for g, v in zip(global_size, local_size))
        self._last_event = cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size)
        return self._last_event

    def to_device(self, array, dtype):
        """A read-only device copy of ``array`` as ``dtype`` (contiguous)."""
        a = np.ascontiguousarray(array, dtype=DTYPES[dtype] if isinstance(dtype, str) else dtype)
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)

    def empty(self, nbytes):
        return cl.Buffer(self.context, cl.mem_flags.READ_WRITE, max(int(nbytes), 1))

    def read(self, buf, out):
        """Copy the device buffer ``buf`` into the contiguous host array ``out`` (blocking); returns ``out``."""
        cl.enqueue_copy(self.queue, out, buf)
        return out

    def evaluate(self, quantity: str, inputs: dict, shape, dtype="float64", shadowing="paper"):
        """Evaluate ``quantity`` ("dop", "brdf", "mueller") element-wise.

        ``inputs`` maps each name of :data:`POINT_INPUTS` to an array that is either of
        ``shape`` (already broadcast) or of size 1.  Angles in degrees.  Returns an array of
        ``shape`` (``shape + (4, 4)`` for "mueller") in ``dtype``.  No validation here.
        """
        npdt = DTYPES[dtype]
        vec = quantity in ("dop", "brdf") and self.vectorise
        lanes = VECTOR_WIDTH[dtype] if vec else 1
        kern = self.kernel(f"{quantity}_points" + ("_vec" if vec else ""), dtype, shadowing)
        size = int(np.prod(shape, dtype=np.int64))
        width = 16 if quantity == "mueller" else 1
        out = np.empty(size * width, dtype=npdt)
        if size == 0:
            return out.reshape(tuple(shape) + ((4, 4) if width == 16 else ()))
        flat = {name: np.ascontiguousarray(inputs[name], dtype=npdt).reshape(-1) for name in POINT_INPUTS}
        step = LAUNCH_POINTS // lanes * lanes
        for start in range(0, size, step):
            count = min(step, size - start)
            padded = -(-count // lanes) * lanes  # the vector kernels take whole vectors
            out_buf = self.empty(padded * width * out.itemsize)
            args = [out_buf, np.int32(padded // lanes)]
            for name in POINT_INPUTS:
                a = flat[name]
                part = a if a.size == 1 else a[start:start + count]
                if a.size != 1 and padded != count:  # a full input, even when this chunk holds one point
                    part = np.concatenate([part, np.repeat(part[-1:], padded - count)])
                args += [self.to_device(part, npdt), np.int32(0 if a.size == 1 else 1)]
            # a small work-group: PoCL keeps every work-item's private state of a group on one
            # thread's stack, and the vector kernels' state overflows it in large groups
            self.launch(kern, (padded // lanes,), *args, local_size=(VECTOR_LOCAL_SIZE,) if vec else None)
            self.read(out_buf, out[start * width:(start + count) * width])
        self.queue.finish()
        return out.reshape(tuple(shape) + ((4, 4) if width == 16 else ()))

    @property
    def last_event_seconds(self):
        """Device time of the last kernel launch (needs ``profiling=True``)."""
        if not self.profiling or self._last_event is None:
            return None
        ev = self._last_event
        return (ev.profile.end - ev.profile.start) * 1e-9


_default_engine = None


def get_default_engine() -> Engine:
    """The engine used by the module-level functions (created on first use)."""
    global _default_engine
    if _default_engine is None:
        _default_engine = Engine()
    return _default_engine


def set_default_engine(engine) -> None:
    """Replace the default engine (``None`` to create a fresh one on next use)."""
    global _default_engine
    _default_engine = engine
