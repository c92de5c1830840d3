"""OpenCL engine: one object owning the context, queue, built programs and kernels; the device
probe; the choice of device; and the numpy engine every function falls back to.

**Probe.**  A device is *usable* only when it builds ``kernels/pbrdf_probe.cl`` (which includes
``pbrdf.h``) in float32, and in float64 where the device claims it, and returns SPEC's check
values (DOP of the paper's steel at three geometries).  Results are cached per process and on
disk (``~/.cache/pbrdf-cl/probe-v1.json``, see :func:`pbrdf_cl.device.drivers.cache_dir`), keyed by the
platform, the device, its driver version and the SHA-256 of the kernel sources.

**Choice**, in order: an explicit ``device`` argument, then the ``PYOPENCL_CTX`` environment
variable (an explicit choice that is unusable is an error), then the first usable device among
GPUs, PoCL CPU devices (newest PoCL first), other CPU drivers, anything else; never the Oclgrind
simulator unless named.  An unusable device is skipped with one :class:`DeviceWarning` line.  A
device is named by a ``cl.Device``, by ``"P"`` or ``"P:D"`` (platform and device indices, as
``pbrdf-cl devices`` lists them), or by a case-insensitive substring of "platform name / device
name" (``"pocl"``, ``"nvidia"``, ``"intel"``, ``"oclgrind"``).

**Backends.**  ``backend="auto"`` (the default everywhere) computes on the chosen OpenCL device,
or, when no device is usable, on :class:`NumpyEngine` (the float64 reference of
``reference.py``), saying so once with the reason and the remedies; ``"opencl"`` makes that an
error; ``"numpy"`` always uses the reference.  :func:`resolve_engine` implements this.

Programs are built once per (precision, shadowing variant) with ``-D`` options and kept, with
their ``cl.Kernel`` objects, for the life of the engine.  Before a process first builds a program on
a device (and before it probes one), the build and one launch of each kernel are tried in a child
process (:mod:`pbrdf_cl.device.trials`), whose verdict is stored on disk: a driver that crashes, aborts or
hangs there takes the child down, not this process.  A program the trial found unusable raises
:class:`ProgramUnusableError`; the functions marked :func:`falls_back` then compute on the next
usable device, else on the numpy backend, with one :class:`DeviceWarning` line (an explicitly
chosen device makes it an error instead).

**Vector widths.**  The vector per-point kernels compute ``PB_VECTOR_REAL`` points per work-item,
the row and batch programs (``pbrdf_grid.cl``, ``pbrdf_batch.cl``) ``PB_VW`` values, and
``batch_lm`` as many problems as it has lanes: 512-bit vectors (``float16``/``double8``), except on
PoCL built with LLVM 14 or older on an AVX-512 CPU, where they are 256-bit (:func:`vector_widths`):
its code generator aborts on some 512-bit programs, and programs of 512-bit vectors that it loads
back from its cache have no kernels.

Testing aid: ``PBRDF_CL_FAKE_BUILD_FAILURE=<substring>`` makes the probe program of every device
whose "platform / device" name contains the substring (case-insensitive) fail to build, as the
PyPI PoCL 3.0 does on CPUs its LLVM does not know.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import inspect
import json
import math
import os
import re
import threading
import time
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from . import drivers, ops
from ..model import quantities
from ..model import reference
from . import trials
from .drivers import describe, first_error_line  # noqa: F401 (engine.describe, engine.first_error_line stay)
from ..errors import (DeviceUnusableError, DeviceWarning, KernelBuildError, OpenCLUnavailableError,  # noqa: F401
                      ProgramUnusableError)

drivers.register_pip_drivers()  # before the first OpenCL call of this process

try:
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - pyopencl is a hard dependency
    cl = None
    _IMPORT_ERROR = exc
else:
    _IMPORT_ERROR = None

POINT_INPUTS = ("theta_i", "theta_r", "phi", "n", "k", "sigma", "ks", "kd", "c")
DTYPES = {"float32": np.float32, "float64": np.float64}
BACKENDS = ("auto", "opencl", "numpy")
#: Vector width of the explicitly vectorised per-point kernels (float16 / double8 were fastest on
#: PoCL 3.0) and ``PB_VW`` of the row and batch programs, unless :func:`vector_widths` narrows them.
VECTOR_WIDTH = {"float32": 16, "float64": 8}
#: Lanes of the batch Levenberg-Marquardt kernel (``batch_lm``: one problem per lane).
LM_LANES = {"float32": 16, "float64": 4}
#: The widths where the driver cannot generate 512-bit vector code (256-bit vectors).
NARROW_VECTOR_WIDTH = {"float32": 8, "float64": 4}
NARROW_LM_LANES = {"float32": 8, "float64": 4}
#: Work-group size of the vector per-point kernels.
VECTOR_LOCAL_SIZE = 8
#: Points per kernel launch; bounds the temporary device memory of one call.
LAUNCH_POINTS = 1 << 22
#: The most points of a launch of the broadcast kernels: their 32-bit index arithmetic counts on
#: it (see :data:`RULE_MAX`).
RULE_LAUNCH_MAX = 1 << 22
#: Points per launch when inputs must be converted or gathered first (another dtype, a broadcast
#: view that is not one run of axes): bounds the host memory of the converted copies (9 inputs x
#: 2^19 x 8 bytes = 38 MB).
CONVERT_POINTS = 1 << 19
#: The most values of a broadcast input's table (:func:`broadcast_table`, a copy sent once): a
#: larger one is gathered launch by launch instead, so that memory stays within the same bound.
TABLE_POINTS = 1 << 19
FAKE_FAILURE_ENV = "PBRDF_CL_FAKE_BUILD_FAILURE"
NARROW_ENV = "PBRDF_CL_NARROW_VECTORS"

_HOW_TO_GET_ONE = "remedies: " + drivers.REMEDIES


def kernel_dir() -> Path:
    """The folder holding the OpenCL sources: the installed ``pbrdf_cl.kernels`` package
    resource, or the source tree's top-level ``kernels/`` when running from a checkout."""
    try:
        folder = resources.files("pbrdf_cl.kernels")
        if folder.joinpath("pbrdf.h").is_file():
            return Path(str(folder))
    except ModuleNotFoundError:
        pass
    folder = Path(__file__).resolve().parents[2] / "kernels"
    if (folder / "pbrdf.h").is_file():
        return folder
    raise FileNotFoundError("the OpenCL sources of pbrdf_cl (pbrdf_cl/kernels/pbrdf.h) are missing "
                            "from this installation; reinstall the package")


_KERNELS_SHA256 = None


def kernels_sha256():
    """SHA-256 of this installation's OpenCL sources (read once per process)."""
    global _KERNELS_SHA256
    if _KERNELS_SHA256 is None:
        h = hashlib.sha256()
        for f in sorted(kernel_dir().iterdir()):
            if f.suffix in (".cl", ".h"):
                h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
        _KERNELS_SHA256 = h.hexdigest()
    return _KERNELS_SHA256


def build_options(dtype, defines=None, width=None):
    """The compiler options of every pbrdf-cl program for ``dtype``, ``-D`` ``defines`` and the row
    programs' vector width ``width`` (default :data:`VECTOR_WIDTH`)."""
    # -w: PoCL's clang otherwise prints ABI notes about wide vectors to stderr
    opts = ["-I", str(kernel_dir()), "-w", f"-DPB_VW={width or VECTOR_WIDTH[dtype]}"]
    if dtype == "float64":
        opts.append("-DPBRDF_DOUBLE")
    opts += [f"-D{name}" if value is None else f"-D{name}={value}" for name, value in (defines or {}).items()]
    return opts


def _build(context, source, options):
    """``cl.Program(context, source).build(options)``, compiler warnings silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return cl.Program(context, source).build(options=options)


class _CapturedStderr:
    """Redirect the process's C-level stderr (file descriptor 2) into a temporary file, so that
    what a driver prints while it is probed ("1 error generated.", LLVM's complaints) does not
    reach the user's terminal; ``text`` holds it afterwards."""

    def __enter__(self):
        import sys
        import tempfile
        self.text = ""
        try:
            sys.stderr.flush()
            self._file = tempfile.TemporaryFile(mode="w+b")
            self._saved = os.dup(2)
            os.dup2(self._file.fileno(), 2)
        except (OSError, ValueError):
            self._saved = None
        return self

    def __exit__(self, *exc):
        if self._saved is not None:
            os.dup2(self._saved, 2)
            os.close(self._saved)
            self._file.seek(0)
            self.text = self._file.read().decode(errors="replace")
            self._file.close()
        return False


def _platforms():
    bundled = "`pip install pocl-binary-distribution` (PoCL from PyPI, for CPUs its LLVM knows), "
    if cl is None:
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({_IMPORT_ERROR}); remedies: `pip install "
                                     f"pyopencl`, {bundled}{drivers.REMEDIES}")
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise OpenCLUnavailableError(f"no OpenCL platform found ({first_error_line(exc)}); remedies: {bundled}"
                                     f"{drivers.REMEDIES}") from None
    if not platforms:
        raise OpenCLUnavailableError(f"no OpenCL platform found; remedies: {bundled}{drivers.REMEDIES}")
    return platforms


#: What the drivers printed to stderr while they were listed and probed (kept, not shown;
#: ``pbrdf-cl devices`` prints it): LLVM's complaints about an unknown CPU, for instance.
DRIVER_MESSAGES = []


def list_devices():
    """All OpenCL devices, usable or not (see :func:`probe`).

    Returns
    -------
    list of (int, int, pyopencl.Platform, pyopencl.Device)
        ``(platform_index, device_index, platform, device)``, the indices as ``P:D`` names them.

    Raises
    ------
    OpenCLUnavailableError
        Where pyopencl cannot load or no OpenCL platform exists (the message names the remedies).

    Examples
    --------
    >>> [d.name for _, _, _, d in pbrdf_cl.list_devices()]  # doctest: +SKIP
    """
    out = []
    with _CapturedStderr() as captured:  # the first call initialises every driver
        platforms = _platforms()
        for ip, plat in enumerate(platforms):
            try:
                devices = plat.get_devices()
            except cl.Error:
                continue
            for idev, dev in enumerate(devices):
                out.append((ip, idev, plat, dev))
    _keep_messages(captured.text)
    return out


def _keep_messages(text):
    for line in text.splitlines():
        if line.strip() and line.strip() not in DRIVER_MESSAGES:
            DRIVER_MESSAGES.append(line.strip())


def _is_simulator(plat) -> bool:
    return "oclgrind" in plat.name.lower()


def _is_pocl(plat) -> bool:
    return "portable computing language" in plat.name.lower()


def _pocl_version(plat):
    m = re.search(r"PoCL (\d+)\.(\d+)", plat.version)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


def _rank(plat, dev):
    """Sort key of the default order: GPUs, PoCL CPU devices (newest PoCL first), other CPU
    drivers, anything else."""
    dt = cl.device_type
    if dev.type & dt.GPU:
        return (0, (0, 0))
    if dev.type & dt.CPU and _is_pocl(plat):
        v = _pocl_version(plat)
        return (1, (-v[0], -v[1]))
    if dev.type & dt.CPU:
        return (2, (0, 0))
    return (3, (0, 0))


def has_fp64(device) -> bool:
    return bool(device.double_fp_config) or "cl_khr_fp64" in device.extensions


_CPU_FLAGS = None


def cpu_flags():
    """The flags of this machine's CPU (``/proc/cpuinfo``; empty where it cannot be read)."""
    global _CPU_FLAGS
    if _CPU_FLAGS is None:
        try:
            text = Path("/proc/cpuinfo").read_text()
        except OSError:
            text = ""
        m = re.search(r"^flags\s*:(.*)$", text, re.M)
        _CPU_FLAGS = frozenset(m.group(1).split()) if m else frozenset()
    return _CPU_FLAGS


def llvm_version(plat):
    """The major version of the LLVM a PoCL platform was built with (its version string names it),
    or None."""
    m = re.search(r"LLVM (\d+)", plat.version)
    return int(m.group(1)) if m else None


def narrow_reason(dev):
    """Why every vector program must use 256-bit vectors on ``dev``, or None.  PoCL built with
    LLVM 14 (the PyPI wheel's PoCL 3.0) generates code with the host's AVX-512 features; on such a
    host (measured on a Zen 4) its code generator aborts ("LLVM ERROR: Do not know how to scalarize
    this operator's operand!") or segfaults on the objective's and the batch programs' float16 /
    double8 arithmetic, and a per-point program of float16 / double8 that it loads back from its
    cache has no kernels (and aborts the process at exit).  The same programs with float8 /
    double4 build in seconds, load from the cache and give the same values.  LLVM 15 (PoCL 3.1)
    has neither fault.  ``PBRDF_CL_NARROW_VECTORS=1`` narrows them on every device, ``=0`` on none
    (for measurements, and a way out should another driver fail alike)."""
    forced = os.environ.get(NARROW_ENV, "").strip()
    if forced in ("0", "1"):
        return f"{NARROW_ENV}={forced}" if forced == "1" else None
    plat = dev.platform
    if not (_is_pocl(plat) and dev.type & cl.device_type.CPU):
        return None
    llvm = llvm_version(plat)
    if llvm is None or llvm >= 15 or "avx512f" not in cpu_flags():
        return None
    return f"PoCL with LLVM {llvm} on an AVX-512 CPU cannot generate or cache 512-bit vector code for every program"


def vector_widths(dev):
    """``(vector widths, LM lanes)`` per dtype for the programs built on ``dev``: :data:`VECTOR_WIDTH`
    and :data:`LM_LANES`, or their 256-bit forms where :func:`narrow_reason` says so."""
    if narrow_reason(dev):
        return dict(NARROW_VECTOR_WIDTH), dict(NARROW_LM_LANES)
    return dict(VECTOR_WIDTH), dict(LM_LANES)


# ---------------------------------------------------------------------------------------------
# the probe

#: SPEC's check points: the paper's steel at (30, 20), (40, 45), (50, 65) degrees, phi = 180.
PROBE_POINTS = np.array([[30.0, 20.0, 180.0, 1.6, 2.139, 0.5, 0.9, 0.15, -0.3],
                         [40.0, 45.0, 180.0, 1.6, 2.139, 0.5, 0.9, 0.15, -0.3],
                         [50.0, 65.0, 180.0, 1.6, 2.139, 0.5, 0.9, 0.15, -0.3]])
#: SPEC's check values (paper shadowing), rounded to 6 decimals there.
PROBE_SPEC = np.array([0.051841, 0.167590, 0.337599])
#: Largest |probe - float64 reference| accepted.
PROBE_TOLERANCE = {"float32": 2e-5, "float64": 1e-10}
PROBE_CACHE_VERSION = 1


@dataclasses.dataclass
class ProbeResult:
    """Whether a device can run pbrdf-cl.  ``reason``: one line (why not, or what was checked);
    ``values``: the probe's DOP per precision; ``seconds``: the time the probe took when it ran;
    ``cached``: this answer came from the disk cache."""

    usable: bool
    reason: str
    fp64: bool = False
    values: dict = dataclasses.field(default_factory=dict)
    seconds: float = 0.0
    cached: bool = False


def _fake_failure(dev) -> bool:
    fake = os.environ.get(FAKE_FAILURE_ENV, "").strip().lower()
    return bool(fake) and fake in describe(dev).lower()


def _probe_key(dev):
    plat = dev.platform
    parts = dict(platform=plat.name.strip(), platform_version=plat.version.strip(), device=dev.name.strip(),
                 vendor=dev.vendor.strip(), driver=dev.driver_version.strip(), version=dev.version.strip(),
                 kernels=kernels_sha256(), fake=_fake_failure(dev), v=PROBE_CACHE_VERSION,
                 trial_fake=trials.fake_way(describe(dev), "pbrdf_probe.cl"))
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


_PROBES = {}
_PROBE_LOCK = threading.Lock()


PROBE_STORE = drivers.RecordStore(f"probe-v{PROBE_CACHE_VERSION}.json", ProbeResult)


def _probe_file():
    return PROBE_STORE.path


def _run_probe(dev) -> ProbeResult:
    if not trials.enabled():
        with _CapturedStderr() as captured:
            result = _run_probe_quietly(dev)
        _keep_messages(captured.text)
        if not result.usable and captured.text.strip() and "error" not in result.reason.lower():
            result.reason += f" ({first_error_line(captured.text)})"
        return result
    return _run_probe_in_child(dev)


def _probe_source(dev):
    source = (kernel_dir() / "pbrdf_probe.cl").read_text()
    if _fake_failure(dev):
        source = f"#error unknown target CPU 'generic' (simulated by {FAKE_FAILURE_ENV})\n" + source
    return source


def _check_probe_values(values, t0):
    """The probe's verdict on the DOP each precision returned."""
    want = reference.evaluate("dop", *PROBE_POINTS.T)
    for dtype, got in values.items():
        out = np.asarray(got, dtype=np.float64)
        err = float(np.max(np.abs(out - want)))
        if not np.isfinite(err) or err > PROBE_TOLERANCE[dtype]:
            return ProbeResult(False, f"{dtype} probe returned DOP {np.array2string(out, precision=6)}, "
                               f"SPEC's check values are {PROBE_SPEC.tolist()} (error {err:.2g})",
                               values=values, seconds=time.perf_counter() - t0)
    checked = " and ".join(values)
    return ProbeResult(True, f"{checked} give SPEC's check values", fp64="float64" in values, values=values,
                       seconds=time.perf_counter() - t0)


def _run_probe_in_child(dev) -> ProbeResult:
    """The probe, built and run in the trial process: a driver that crashes there is unusable."""
    t0 = time.perf_counter()
    dtypes = ("float32", "float64") if has_fp64(dev) else ("float32",)
    widths, _ = vector_widths(dev)
    options = {dt: build_options(dt, width=widths[dt]) for dt in dtypes}
    values, why = trials.run_probe(dev, _device_index(dev), _probe_source(dev), options, dtypes, PROBE_POINTS)
    _keep_messages(trials.last_child_text())
    if why:
        return ProbeResult(False, why if "build failed" in why or "crashed" in why else f"probe failed: {why}",
                           values=values or {}, seconds=time.perf_counter() - t0)
    if set(values) != set(dtypes):
        return ProbeResult(False, f"probe failed: no values for {sorted(set(dtypes) - set(values))}",
                           values=values, seconds=time.perf_counter() - t0)
    return _check_probe_values(values, t0)


def _run_probe_quietly(dev) -> ProbeResult:
    """The probe in this process (only with trials switched off, ``PBRDF_CL_TRIALS=0``)."""
    t0 = time.perf_counter()
    values = {}
    try:
        context = cl.Context([dev])
        queue = cl.CommandQueue(context)
        dtypes = ("float32", "float64") if has_fp64(dev) else ("float32",)
        widths, _ = vector_widths(dev)
        for dtype in dtypes:
            try:
                program = _build(context, _probe_source(dev), build_options(dtype, width=widths[dtype]))
            except cl.Error as exc:
                return ProbeResult(False, f"{dtype} build failed: {first_error_line(exc)}",
                                   seconds=time.perf_counter() - t0)
            npdt = DTYPES[dtype]
            pts = np.ascontiguousarray(PROBE_POINTS, dtype=npdt)
            buf_in = cl.Buffer(context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=pts)
            out = np.full(len(pts), np.nan, dtype=npdt)
            buf_out = cl.Buffer(context, cl.mem_flags.WRITE_ONLY, out.nbytes)
            program.pbrdf_probe(queue, (len(pts),), None, buf_out, buf_in, np.int32(len(pts)))
            cl.enqueue_copy(queue, out, buf_out)
            queue.finish()
            values[dtype] = out.astype(float).tolist()
    except cl.Error as exc:
        return ProbeResult(False, f"probe failed: {first_error_line(exc)}", values=values,
                           seconds=time.perf_counter() - t0)
    return _check_probe_values(values, t0)


def _device_index(dev):
    """``(platform index, device index)`` of ``dev`` in :func:`list_devices`' order, or None."""
    for ip, idev, _, d in list_devices():
        if d.int_ptr == dev.int_ptr:
            return ip, idev
    return None


def probe(dev, *, use_cache=True) -> ProbeResult:
    """Whether a device can build and run pbrdf-cl's kernels (see the module docstring).

    Parameters
    ----------
    dev : pyopencl.Device
    use_cache : bool, default True
        Use the per-process and on-disk caches (keyed by platform, device, driver and the kernel
        sources' SHA-256); False probes afresh.

    Returns
    -------
    ProbeResult
        ``usable``, ``reason`` (the first line of a build log where it is not), ``seconds``, ``cached``.

    Examples
    --------
    >>> pbrdf_cl.probe(pbrdf_cl.Engine().device).usable  # doctest: +SKIP
    True
    """
    key = _probe_key(dev)
    with _PROBE_LOCK:
        if use_cache and key in _PROBES:
            return _PROBES[key]
        hit = PROBE_STORE.get(key, cached=True) if use_cache else None
        if hit is not None:
            _PROBES[key] = hit
            return hit
        result = _run_probe(dev)
        _PROBES[key] = result
        PROBE_STORE.put(key, result)
        return result


def clear_probe_cache(disk=False):
    """Forget the probe results of this process (and, with ``disk``, the disk cache)."""
    with _PROBE_LOCK:
        _PROBES.clear()
        if disk:
            PROBE_STORE.clear()


# ---------------------------------------------------------------------------------------------
# choosing a device

_WARNED = set()


def _warn_once(key, message):
    if key not in _WARNED:
        _WARNED.add(key)
        warnings.warn(message, DeviceWarning, stacklevel=4)


def _device_id(found, dev):
    for ip, idev, _, d in found:
        if d.int_ptr == dev.int_ptr:
            return f"{ip}:{idev}"
    return "?"


def _unusable_error(where, found, dev, result):
    return DeviceUnusableError(
        f"{where}: OpenCL device {_device_id(found, dev)} ({describe(dev)}) cannot run pbrdf-cl: {result.reason}; "
        f"choose another (`pbrdf-cl devices` lists them with their probe results) or: {drivers.REMEDIES}")


def _find(spec, where, found):
    parts = spec.split(":")
    if all(p.isdigit() for p in parts) and 1 <= len(parts) <= 2:
        ip, idev = int(parts[0]), int(parts[1]) if len(parts) == 2 else 0
        for p_, d_, _, dev in found:
            if (p_, d_) == (ip, idev):
                return [dev]
        raise ValueError(f"{where}={spec!r}: no OpenCL device {ip}:{idev}; "
                         f"`pbrdf-cl devices` lists the ones present")
    matches = [(plat, dev) for _, _, plat, dev in found if spec.lower() in f"{plat.name} / {dev.name}".lower()]
    if not matches:
        raise ValueError(f"{where}={spec!r} matches no OpenCL platform or device name; "
                         f"`pbrdf-cl devices` lists the ones present")
    return [dev for _, dev in sorted(matches, key=lambda pd: _rank(*pd))]


def candidates(found=None):
    """The devices the default choice considers, in its order (never the simulator)."""
    found = list_devices() if found is None else found
    real = [(plat, dev) for _, _, plat, dev in found if not _is_simulator(plat)]
    return [dev for plat, dev in sorted(real, key=lambda pd: _rank(*pd))]


def _no_device_message(found, skipped):
    parts = [f"{describe(d)}: {r.reason}" for d, r in skipped]
    if not found:
        parts.append("the OpenCL platforms present have no devices")
    elif not skipped:
        parts.append("only the Oclgrind simulator is present")
    problem = drivers.pocl_cache_problem()
    if problem:
        parts.append(problem)
    return f"no usable OpenCL device ({'; '.join(parts)}); {_HOW_TO_GET_ONE}"


def select_device(device=None):
    """Pick a usable OpenCL device (see the module docstring for the default order).

    Parameters
    ----------
    device : pyopencl.Device or str, optional
        A device, ``"P:D"`` as ``pbrdf-cl devices`` lists them, or a substring of its
        "platform / device" name; None: ``PYOPENCL_CTX``, else the first usable device.

    Returns
    -------
    pyopencl.Device

    Raises
    ------
    OpenCLUnavailableError
        When no device is usable; :class:`DeviceUnusableError` when an explicit choice is not;
        ``ValueError`` when it names no device.

    Examples
    --------
    >>> pbrdf_cl.select_device("pthread")  # doctest: +SKIP
    """
    explicit = device if device is not None else (os.environ.get("PYOPENCL_CTX") or None)
    where = "device" if device is not None else "PYOPENCL_CTX"
    if cl is not None and isinstance(explicit, cl.Device):
        result = probe(explicit)
        if not result.usable:
            raise _unusable_error(where, list_devices(), explicit, result)
        return explicit
    found = list_devices()
    if explicit is not None:  # a name may match several devices: the first usable one, in the default order
        matches = _find(str(explicit).strip(), where, found)
        results = []
        for dev in matches:
            results.append(probe(dev))
            if results[-1].usable:
                return dev
        raise _unusable_error(f"{where}={str(explicit).strip()!r}", found, matches[0], results[0])
    skipped = []
    for dev in candidates(found):
        result = probe(dev)
        if result.usable:
            return dev
        skipped.append((dev, result))
        _warn_once(("skip", _probe_key(dev)),
                   f"skipping OpenCL device {_device_id(found, dev)} ({describe(dev)}): {result.reason}")
    exc = OpenCLUnavailableError(_no_device_message(found, skipped))
    exc.skipped = len(skipped)
    raise exc


class NumpyEngine:
    """The numpy backend: the float64 reference of :mod:`pbrdf_cl.model.reference`, as an engine.

    Every function that takes ``engine=`` accepts one; the dense grids, reductions and the
    objective build the same factor tables with ``reference.py`` and combine them in chunks
    within the same memory budget.  It computes in float64 whatever ``dtype`` is asked for, and
    returns that dtype.  ``reason``: why it is in use (empty when asked for by name)."""

    is_numpy = True
    backend = "numpy"
    fp64 = True
    profiling = False
    last_event_seconds = None

    def __init__(self, reason=""):
        self.reason = reason
        #: held by callers that want one computation at a time on this engine (e.g. a sweep's chunk)
        self.lock = threading.RLock()

    def __repr__(self):
        return "NumpyEngine(float64 reference" + (f"; {self.reason}" if self.reason else "") + ")"

    def call(self, operation, *args, **kwargs):
        """Run ``operation`` (:mod:`pbrdf_cl.device.ops`) on this engine."""
        func, _ = ops.implementation(operation, self.backend)
        return func(self, *args, **kwargs)

    @property
    def description(self):
        return "numpy backend (float64 reference)"

    def checks_domain(self, quantity):
        return False

    def evaluate(self, quantity, inputs, shape, dtype="float64", shadowing="paper"):
        """As :meth:`Engine.evaluate`, with the reference."""
        q = quantities.get(quantity, "points")
        extra = q.trailing
        out = np.asarray(reference.evaluate(q.name, *(np.asarray(inputs[n], dtype=np.float64)
                                                         for n in POINT_INPUTS), shadowing=shadowing))
        lead = out.shape[:out.ndim - len(extra)]
        if lead != tuple(shape):  # every input a single value: one point, broadcast to the shape
            out = np.broadcast_to(out.reshape((-1,) + extra)[0], tuple(shape) + extra)
        out = np.asarray(out, dtype=DTYPES[dtype])
        return out if out.flags.writeable else out.copy()  # a copy only of the broadcast single point


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

    is_numpy = False
    backend = "opencl"

    def __init__(self, device=None, *, profiling=False):
        #: chosen by the caller (``device``, ``PYOPENCL_CTX``): a program it cannot run is an error,
        #: never a silent move to another device (see :func:`falls_back`)
        self.explicit = device is not None or bool(os.environ.get("PYOPENCL_CTX"))
        self.device = select_device(device)
        #: per dtype: the points per work-item of the vector per-point kernels (``PB_VECTOR_REAL``) and
        #: ``PB_VW`` of the row and batch programs; the lanes of ``batch_lm``
        self.vector_width, self.lm_lanes = vector_widths(self.device)
        self._index = None
        try:
            self.context = cl.Context([self.device])
        except cl.Error as exc:
            raise DeviceUnusableError(f"cannot create an OpenCL context on {describe(self.device)}: "
                                      f"{first_error_line(exc)}") from None
        props = cl.command_queue_properties.PROFILING_ENABLE if profiling else 0
        self.queue = cl.CommandQueue(self.context, properties=props)
        self.profiling = profiling
        self.fp64 = has_fp64(self.device)
        #: DOP and F00 use the vector build of the per-point kernels (False: one point per work-item)
        self.vectorise = True
        #: evaluate through the transfer pipeline of GPUs (pinned staging, copies overlapped with
        #: compute) even on a CPU device; for tests of that path where no GPU is present
        self.force_transfers = False
        #: send a broadcast input once with its index rule (:func:`input_plan`); False gathers it
        #: launch by launch on the host, as before issue #12 (for comparisons: tests, the bench)
        self.index_rules = True
        self._copy_queue = None
        self._kernels = {}
        self._last_event = None
        #: held around building programs and around setting a kernel's arguments and enqueueing it
        #: (a cl.Kernel holds its arguments, and the kernels are shared); re-entrant, so a caller may
        #: hold it across a whole computation
        self.lock = threading.RLock()

    def call(self, operation, *args, **kwargs):
        """Run ``operation`` (:mod:`pbrdf_cl.device.ops`) on this engine: the device's implementation,
        or the numpy backend's where it has none (on a :class:`NumpyEngine`, with one warning)."""
        func, backend = ops.implementation(operation, self.backend)
        return func(self if backend == self.backend else NumpyEngine(f"{operation} has no OpenCL implementation"),
                    *args, **kwargs)

    def __repr__(self):
        return (f"Engine(device={self.device.name.strip()!r}, "
                f"platform={self.device.platform.name.strip()!r}, fp64={self.fp64})")

    @property
    def description(self):
        """``"platform / device"``."""
        return describe(self.device)

    @property
    def index(self):
        """``(platform index, device index)`` as ``pbrdf-cl devices`` lists them."""
        if self._index is None:
            self._index = _device_index(self.device) or ("?", "?")
        return self._index

    def program(self, filename: str, dtype: str, defines=None, prefix: str = ""):
        """The kernels of ``kernels/<filename>`` built for ``dtype`` with ``-D`` ``defines`` (and
        ``prefix`` source text prepended), as a dict name -> ``cl.Kernel``; built once per key."""
        defines = dict(defines or {})
        key = (filename, dtype, tuple(sorted(defines.items())), prefix)
        with self.lock:
            return self._program(key, filename, dtype, defines, prefix)

    def source_program(self, name: str, source: str, dtype: str, defines=None):
        """The kernels of the OpenCL ``source`` (a program of its own, e.g. a test's, which may
        ``#include "pbrdf.h"``) built as :meth:`program` builds the package's: the same options, the
        same trial in the child process first; ``name`` names it in messages."""
        defines = dict(defines or {})
        key = ("<source>", name, hashlib.sha256(source.encode()).hexdigest(), dtype, tuple(sorted(defines.items())))
        with self.lock:
            return self._program(key, name, dtype, defines, "", source)

    def _program(self, key, filename, dtype, defines, prefix, source=None):
        if key not in self._kernels:
            if dtype == "float64" and not self.fp64:
                raise ValueError(f"dtype='float64': device {self.device.name.strip()!r} has no float64 "
                                 "support; use dtype='float32' or another device")
            if source is None:
                source = (kernel_dir() / filename).read_text()
            options = build_options(dtype, defines, self.vector_width[dtype])
            if trials.enabled():
                self._check_trial(filename, dtype, source, options, prefix)
            try:
                program = _build(self.context, prefix + source, options)
            except cl.Error as exc:
                raise KernelBuildError(f"{describe(self.device)} failed to build {filename} ({dtype}): "
                                       f"{first_error_line(exc)}") from None
            kernels = {k.function_name: k for k in program.all_kernels()}
            if not kernels:  # PoCL 3.0 loads some programs back from its cache without their kernels
                raise ProgramUnusableError(
                    f"OpenCL device {self.index[0]}:{self.index[1]} ({self.description}) built "
                    f"{trials.label(filename, dtype, options)} without kernels (a broken entry in the driver's "
                    f"cache? for PoCL, empty {drivers.pocl_cache_dir()})", engine=self,
                    program=trials.program_key(filename, options, prefix))
            self._kernels[key] = kernels
        return self._kernels[key]

    def _check_trial(self, filename, dtype, source, options, prefix):
        """Raise :class:`ProgramUnusableError` unless the trial of this program (stored, or run now
        in the child process) found it usable on this device."""
        verdict = trials.check_program(self.device, self.index, kernels_sha256(), filename, dtype, source,
                                       options, prefix)
        if not verdict.usable:
            where = f"OpenCL device {self.index[0]}:{self.index[1]} ({self.description})"
            raise ProgramUnusableError(f"{where} cannot run {verdict.program}: {verdict.reason}", engine=self,
                                       verdict=verdict, program=trials.program_key(filename, options, prefix))

    def kernel(self, name: str, dtype: str, shadowing: str, quantity=None):
        """The ``cl.Kernel`` ``name`` of ``pbrdf_points.cl`` for this precision and variant (built once);
        names ending in ``_vec`` come from the vector build (:attr:`vector_width` points per work-item);
        ``quantity_points`` is built for the registry's ``quantity`` (its name)."""
        defines = {"PBRDF_SHADOWING": reference.SHADOWING[shadowing]}
        if name.endswith("_vec"):
            defines["PB_VECTOR_REAL"] = self.vector_width[dtype]
        if quantity is not None:
            defines.update(quantities.get(quantity, "points").defines())
        return self.program("pbrdf_points.cl", dtype, defines)[name]

    def launch(self, kernel, global_size, *args, local_size=None, wait_for=None):
        """Set ``args`` and enqueue ``kernel`` over ``global_size`` (padded up to a multiple of
        ``local_size`` when one is given: kernels check their bounds) after the events ``wait_for``;
        returns the event."""
        global_size = tuple(int(g) for g in global_size)
        if local_size is not None:
            local_size = tuple(int(v) for v in local_size)
            global_size = tuple(-(-g // v) * v for g, v in zip(global_size, local_size))
        with self.lock:  # the arguments are the kernel object's until the enqueue has taken them
            kernel.set_args(*args)
            self._last_event = cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size,
                                                          wait_for=wait_for)
        return self._last_event

    def to_device(self, array, dtype):
        """A read-only device copy of ``array`` as ``dtype`` (contiguous)."""
        a = np.ascontiguousarray(array, dtype=DTYPES[dtype] if isinstance(dtype, str) else dtype)
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)

    def empty(self, nbytes):
        return cl.Buffer(self.context, cl.mem_flags.READ_WRITE, max(int(nbytes), 1))

    @property
    def overlaps_transfers(self):
        """Whether results come back through the transfer pipeline (a device with its own memory, or
        :attr:`force_transfers`): reads on :attr:`copy_queue` while the next launch computes."""
        return not self.host_memory or self.force_transfers

    @property
    def copy_queue(self):
        """A second command queue on the device, for transfers that overlap the kernels of :attr:`queue`."""
        if self._copy_queue is None:
            with self.lock:
                if self._copy_queue is None:
                    self._copy_queue = cl.CommandQueue(self.context)
        return self._copy_queue

    def read_later(self, buf, out, after):
        """Enqueue the copy of ``buf`` into the contiguous host array ``out`` on :attr:`copy_queue`
        once the events ``after`` are done; returns its event (``.wait()`` before using ``out``)."""
        return cl.enqueue_copy(self.copy_queue, out, buf, is_blocking=False, wait_for=list(after))

    def read(self, buf, out):
        """Copy the device buffer ``buf`` into the contiguous host array ``out`` (blocking); returns ``out``."""
        cl.enqueue_copy(self.queue, out, buf)
        return out

    def checks_domain(self, quantity):
        """Whether :meth:`evaluate`'s kernel for ``quantity`` checks the inputs' domain itself (the
        vector kernels, of the quantities the registry marks ``vector``, write NaN for a point
        outside it), so that the caller need not read the inputs beforehand, only check the result."""
        return quantities.get(quantity, "points").vector and self.vectorise

    def evaluate(self, quantity: str, inputs: dict, shape, dtype="float64", shadowing="paper"):
        """Evaluate ``quantity`` (a name of the registry, :mod:`pbrdf_cl.quantities`) element-wise.

        ``inputs`` maps each name of :data:`POINT_INPUTS` to an array (any float dtype, any
        strides) that broadcasts to ``shape``: of ``shape`` itself, a broadcast view of it, or as
        given (``theta_r[:, None]``, a scalar).  Angles in degrees.  Each input is read as
        :func:`input_plan` says: one value, or a short axis (any single run of axes) sent once
        with its index rule, which the kernels apply point by point (never expanded, on the host
        or the device); an input with a value per point is read in place on a CPU device when it
        is contiguous and of ``dtype``, else converted (or gathered, for other broadcast
        patterns) one launch at a time.  The kernels write straight into the returned array
        (host-pointer buffers on a CPU device), so memory beyond the inputs and the result stays
        within a launch's worth, plus each broadcast input's table (:func:`broadcast_table`, at
        most :data:`TABLE_POINTS` values; a longer one is gathered launch by launch).  Where
        :meth:`checks_domain`, a point outside the model's domain gets NaN; no
        other validation here.  The result has ``shape`` and the quantity's trailing axes
        (``shape + (4, 4)`` for "mueller", ``shape + (4,)`` for "stokes"), in ``dtype``.
        """
        npdt = np.dtype(DTYPES[dtype])
        q = quantities.get(quantity, "points")
        vec = self.checks_domain(q.name)
        lanes = self.vector_width[dtype] if vec else 1
        shape = tuple(int(n) for n in shape)
        size = math.prod(shape)
        width = q.width
        out = aligned_empty(size * width, npdt)  # page-aligned: every driver writes it in place
        if size == 0:
            return out.reshape(shape + q.trailing)
        plan, flat, values = self._inputs(inputs, shape, npdt, lanes)
        if values:  # a broadcast input: the twin kernel, reading each input through its rule
            kern = (self.kernel(f"{q.name}_bcast_points_vec", dtype, shadowing) if vec
                    else self.kernel("quantity_bcast_points", dtype, shadowing, q.name))
        else:
            kern = (self.kernel(f"{q.name}_points_vec", dtype, shadowing) if vec
                    else self.kernel("quantity_points", dtype, shadowing, q.name))
            plan = None
        if self.overlaps_transfers:
            _TransferPipeline(self, kern, flat, values, plan, npdt, lanes, vec, width).run(size, out)
            return out.reshape(shape + q.trailing)
        host = self.host_memory
        sent = {n: self._input_buffer(v, npdt, host) for n, v in values.items()}  # once per call
        # inputs the device cannot read in place are converted launch by launch: smaller launches
        staged = [n for n, a in flat.items() if a.size != 1 and not self.can_use_in_place(a, npdt)]
        step = min(CONVERT_POINTS if staged else LAUNCH_POINTS, _launch_limit(plan)) // lanes * lanes
        # page-aligned staging arrays, reused by every launch (each completes before the next is filled)
        stage = {n: aligned_empty(min(step, size) + lanes, npdt) for n in staged}

        def parts_of(s0, s1, padded):  # the inputs of points s0..s1, padded to ``padded`` points
            parts = dict(sent)
            for n, a in flat.items():
                if a.size == 1:
                    parts[n] = a
                    continue
                if n in stage:
                    dst = stage[n][:padded]
                    _gather(dst, a, s0, s1)
                else:
                    if padded == s1 - s0:
                        parts[n] = a[s0:s1]
                        continue
                    dst = np.empty(padded, npdt)
                    dst[:s1 - s0] = a[s0:s1]
                dst[s1 - s0:] = dst[s1 - s0 - 1]  # padding: copies of the last point
                parts[n] = dst
            return parts
        for start in range(0, size, step):
            count = min(step, size - start)
            whole = count // lanes * lanes
            if whole:
                self._launch_points(kern, parts_of(start, start + whole, whole), whole,
                                    out[start * width:(start + whole) * width], npdt, lanes, vec, host,
                                    None if plan is None else rule_table(plan, start))
            if whole < count:  # the last few points, padded to a whole vector
                tail = count - whole
                padded = lanes if vec else tail
                tmp = np.empty(padded * width, npdt)
                self._launch_points(kern, parts_of(start + whole, start + count, padded), padded, tmp, npdt, lanes,
                                    vec, host, None if plan is None else rule_table(plan, start + whole))
                out[(start + whole) * width:(start + count) * width] = tmp[:tail * width]
        return out.reshape(shape + q.trailing)

    def _inputs(self, inputs, shape, npdt, lanes):
        """``(plan, flat, values)`` of :meth:`evaluate`'s inputs for kernels of ``lanes`` points
        per work-item: each input's rule (:func:`input_plan`, the broadcast ones as
        :func:`broadcast_table` lays them out; without :attr:`index_rules` one value or one per
        point, as before issue #12), ``flat`` the one-value (a 1-value array of ``npdt``) and
        per-point inputs (1-d, or a strided or broadcast view of ``shape``), ``values`` the
        broadcast ones' tables (contiguous, of ``npdt``)."""
        if self.index_rules:
            plan = input_plan(shape, inputs)
        else:
            plan = {n: IndexRule(SINGLE if np.size(a) == 1 else PER_POINT) for n, a in inputs.items()}
        flat, values = {}, {}
        for name in POINT_INPUTS:
            a = np.asarray(inputs[name])
            if plan[name].kind == BROADCAST:
                laid = broadcast_table(plan[name], compact_values(a, len(shape)), shape, lanes, npdt)
                if laid is not None:
                    plan[name], values[name] = laid
                    continue
                plan[name] = IndexRule(PER_POINT)  # a large table: gathered instead
            if plan[name].kind == SINGLE:
                flat[name] = np.array([a[(0,) * a.ndim]], npdt)  # one value, even of a broadcast view
                continue
            b = a if a.shape == shape else np.broadcast_to(a, shape)
            flat[name] = b.reshape(-1) if b.flags.c_contiguous else b
        return plan, flat, values

    def _input_buffer(self, a, npdt, host):
        """A read-only buffer of the contiguous 1-d array ``a`` of ``npdt``: over ``a`` itself on a
        CPU device, a device copy elsewhere (``a`` itself if it is a buffer already)."""
        if isinstance(a, cl.Buffer):
            return a
        if not host:
            return self.to_device(a, npdt)
        a = np.ascontiguousarray(a, npdt)  # as it is, where evaluate has staged it
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=a)

    @property
    def host_memory(self):
        """Whether the device works in host memory (a CPU device): buffers over numpy arrays are
        read and written in place."""
        return bool(self.device.type & cl.device_type.CPU)

    @property
    def zero_copy_alignment(self):
        """Bytes a host array's address must be a multiple of for the device to use it in place:
        PoCL takes any address; Intel's CPU runtime (and, by assumption, any other driver) copies
        unless it is page-aligned."""
        return 1 if _is_pocl(self.device.platform) else 4096

    def can_use_in_place(self, a, npdt):
        """Whether the device reads the array ``a`` in place (buffer over its memory) as ``npdt``."""
        return (self.host_memory and a.ndim == 1 and a.dtype == npdt and a.flags.c_contiguous
                and a.ctypes.data % self.zero_copy_alignment == 0)

    def output(self, view):
        """A device buffer whose values end up in the contiguous host array ``view``: on a CPU
        device a buffer over ``view`` itself (the kernel writes there), elsewhere a device
        buffer copied into it.  Returns ``(buffer, done)``; call ``done()`` after the launch:
        it blocks until the values are in ``view``."""
        mf = cl.mem_flags
        if self.host_memory:
            buf = cl.Buffer(self.context, mf.WRITE_ONLY | mf.USE_HOST_PTR, hostbuf=view)

            def done():  # mapping makes the kernel's writes visible to the host (a no-op on PoCL)
                mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, view.shape, view.dtype)
                mapped.base.release(self.queue)
                self.queue.finish()
            return buf, done
        buf = self.empty(view.nbytes)
        return buf, lambda: self.read(buf, view)

    def _launch_points(self, kern, parts, n, out, npdt, lanes, vec, host, rules=None):
        """One launch of a per-point kernel over ``n`` points (``parts``: name -> n values or one,
        or a buffer), its result in ``out`` (contiguous, n * width values) when this returns.
        ``rules``: the launch's :func:`rule_table`, for the broadcast twins (None: strides)."""
        out_buf, done = self.output(out)
        args = [out_buf, np.int32(n // lanes)]
        for name in POINT_INPUTS:
            p = parts[name]
            args.append(self._input_buffer(p, npdt, host))
            if rules is None:
                args.append(np.int32(0 if p.size == 1 else 1))
        if rules is not None:
            args.append(self._rules_buffer(rules))
        # a small work-group: PoCL keeps every work-item's private state of a group on one
        # thread's stack, and the vector kernels' state overflows it in large groups
        self.launch(kern, (n // lanes,), *args, local_size=(VECTOR_LOCAL_SIZE,) if vec else None)
        done()

    def _rules_buffer(self, table):
        """A read-only device copy of a launch's :func:`rule_table` (a few hundred bytes)."""
        return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=table)

    @property
    def last_event_seconds(self):
        """Device time of the last kernel launch (needs ``profiling=True``)."""
        if not self.profiling or self._last_event is None:
            return None
        ev = self._last_event
        return (ev.profile.end - ev.profile.start) * 1e-9


class _TransferPipeline:
    """Per-point evaluation on a device with its own memory (a GPU): two slots, each a set of
    pinned (``ALLOC_HOST_PTR``, mapped) host staging arrays and device buffers; while the kernel of
    launch k runs on the engine's queue, a second queue uploads the inputs of launch k + 1 and
    reads back the result of launch k - 1, straight into its slice of the result.  A single value
    and a broadcast input's compact values (``values``, read through the rules of ``plan``) are
    uploaded once.  Memory beyond the inputs and the result: two launches' worth."""

    SLOTS = 2

    def __init__(self, eng, kern, flat, values, plan, npdt, lanes, vec, width):
        self.eng, self.kern, self.flat, self.npdt, self.plan = eng, kern, flat, npdt, plan
        self.lanes, self.vec, self.width = lanes, vec, width
        self.names = [n for n in POINT_INPUTS if n in flat and flat[n].size != 1]
        self.single = {n: eng.to_device(a, npdt) for n, a in {**flat, **values}.items() if n not in self.names}
        self.copies = eng.copy_queue

    def _slot(self, cap):
        mf, ctx, isz = cl.mem_flags, self.eng.context, self.npdt.itemsize
        pinned, host = {}, {}
        for n in self.names:
            pinned[n] = cl.Buffer(ctx, mf.READ_WRITE | mf.ALLOC_HOST_PTR, cap * isz)
            host[n], _ = cl.enqueue_map_buffer(self.copies, pinned[n], cl.map_flags.WRITE | cl.map_flags.READ, 0,
                                               (cap,), self.npdt)
        return dict(pinned=pinned, host=host, done=None,
                    dev={n: cl.Buffer(ctx, mf.READ_ONLY, cap * isz) for n in self.names},
                    out=cl.Buffer(ctx, mf.WRITE_ONLY, cap * self.width * isz))

    def run(self, size, out):
        step = min(LAUNCH_POINTS, _launch_limit(self.plan)) // self.lanes * self.lanes
        cap = min(step, size) + self.lanes
        slots = [self._slot(cap) for _ in range(self.SLOTS)]
        tails = []
        try:
            for k, start in enumerate(range(0, size, step)):
                slot = slots[k % self.SLOTS]
                if slot["done"] is not None:
                    slot["done"].wait()  # its last read is in: its staging and buffers are free
                count = min(step, size - start)
                padded = -(-count // self.lanes) * self.lanes
                uploads = []
                for n in self.names:
                    dst = slot["host"][n][:padded]
                    _gather(dst, self.flat[n], start, start + count)
                    dst[count:] = dst[count - 1]  # padding: copies of the last point
                    uploads.append(cl.enqueue_copy(self.copies, slot["dev"][n], dst, is_blocking=False))
                args = [slot["out"], np.int32(padded // self.lanes)]
                for n in POINT_INPUTS:
                    args.append(slot["dev"][n] if n in slot["dev"] else self.single[n])
                    if self.plan is None:
                        args.append(np.int32(1 if n in slot["dev"] else 0))
                if self.plan is not None:
                    args.append(self.eng._rules_buffer(rule_table(self.plan, start)))
                ran = self.eng.launch(self.kern, (padded // self.lanes,), *args,
                                      local_size=(VECTOR_LOCAL_SIZE,) if self.vec else None, wait_for=uploads)
                w = self.width
                if padded == count:
                    dst = out[start * w:(start + count) * w]
                else:  # the last few points: read whole vectors, keep the real ones
                    dst = np.empty(padded * w, self.npdt)
                    tails.append((dst, start, count))
                slot["done"] = cl.enqueue_copy(self.copies, dst, slot["out"], is_blocking=False, wait_for=[ran])
            self.copies.finish()
            for dst, start, count in tails:
                out[start * self.width:(start + count) * self.width] = dst[:count * self.width]
        finally:
            self.copies.finish()
            for slot in slots:
                for n in self.names:
                    slot["host"][n].base.release(self.copies)
            self.copies.finish()


def aligned_empty(n, dtype, align=4096):
    """``np.empty(n, dtype)`` whose data starts at a multiple of ``align`` bytes."""
    dtype = np.dtype(dtype)
    raw = np.empty(n * dtype.itemsize + align, np.uint8)
    skip = -raw.ctypes.data % align
    return raw[skip:skip + n * dtype.itemsize].view(dtype)


# ---------------------------------------------------------------------------------------------
# broadcast inputs: index rules (issue #12)

#: The kinds of :class:`IndexRule`: one value, one value per point, a broadcast rule.
SINGLE, PER_POINT, BROADCAST = 0, 1, 2
#: The largest ``div`` and ``mod`` of a broadcast rule: with launches of at most
#: :data:`RULE_LAUNCH_MAX` points every numerator of the kernels' index arithmetic stays below 2^31
#: (``PB_UDIV`` in pbrdf_points.cl).
RULE_MAX = 1 << 30
#: The fields of one input's row of the kernels' ``rules`` table, in order (``PB_R_*`` there).
RULE_FIELDS = ("kind", "div", "div_m", "div_s", "mod", "mod_m", "mod_s", "r0", "q0")


@dataclasses.dataclass(frozen=True)
class IndexRule:
    """How the kernels read one input at flat point t (C order) of the broadcast shape S.

    ``kind`` :data:`SINGLE` (0): its one value.  :data:`PER_POINT` (1): value t of the input as
    broadcast to S (read in place, or gathered launch by launch).  :data:`BROADCAST` (2): value
    ``(t // div) % mod`` of its compact values (:func:`compact_values`), where its axes other than
    1 are one run ``axes = (p, q)`` of S's axes, ``div = prod(S[q:])``, ``mod = prod(S[p:q])``."""

    kind: int
    div: int = 1
    mod: int = 1
    axes: tuple = ()


def _launch_limit(plan):
    """The most points of one launch: any number with strides, :data:`RULE_LAUNCH_MAX` with rules."""
    return RULE_LAUNCH_MAX if plan is not None else 1 << 62


def effective_shape(a, ndim):
    """``a``'s shape right-aligned to ``ndim`` axes, with 1 wherever it holds one value: an axis of
    length 1, or one of stride 0 (a broadcast view)."""
    a = np.asarray(a)
    lead = (1,) * (ndim - a.ndim)
    return lead + tuple(1 if n == 1 or st == 0 else n for n, st in zip(a.shape, a.strides))


def compact_values(a, ndim):
    """The values of ``a`` on its :func:`effective_shape` (a stride-0 axis taken once), a view of
    that shape: in C order they are the values a :data:`BROADCAST` rule indexes."""
    a = np.asarray(a)
    a = a.reshape((1,) * (ndim - a.ndim) + a.shape)
    return a[tuple(slice(0, 1) if st == 0 else slice(None) for st in a.strides)]


def input_plan(shape, arrays):
    """The :class:`IndexRule` of each array (by name) broadcast to ``shape``.

    An array (or broadcast view) that holds one value is :data:`SINGLE`; one with a value per
    point, :data:`PER_POINT`; one whose other axes are one contiguous run of ``shape``'s axes (a
    short axis ``theta_r[:, None]`` against ``sigma[None, :]``, a scalar per row or per column, a
    run like (1, B, C, 1) in (A, B, C, D)), :data:`BROADCAST`, sent once with its rule.  Any
    other pattern, (A, 1, C) in (A, B, C) for instance, and a rule whose ``div`` or ``mod``
    exceeds :data:`RULE_MAX`, stays :data:`PER_POINT`: gathered launch by launch, correct but not
    sent once.

    Examples
    --------
    >>> plan = input_plan((3, 4), dict(a=np.ones((3, 1)), b=np.ones(4), c=2.0, d=np.ones((3, 4))))
    >>> [(r.kind, r.div, r.mod) for r in plan.values()]
    [(2, 4, 3), (2, 1, 4), (0, 1, 1), (1, 1, 1)]
    """
    shape = tuple(int(n) for n in shape)
    return {name: _rule(shape, effective_shape(a, len(shape))) for name, a in arrays.items()}


def _rule(shape, eff):
    size = math.prod(eff)
    if size == 1:
        return IndexRule(SINGLE)
    if size == math.prod(shape):
        return IndexRule(PER_POINT)
    run = [j for j, n in enumerate(eff) if n != 1]
    p, q = run[0], run[-1] + 1
    if any(eff[j] != shape[j] for j in range(p, q)):
        return IndexRule(PER_POINT)  # not one run of axes
    div = math.prod(shape[q:])
    if div > RULE_MAX or size > RULE_MAX:
        return IndexRule(PER_POINT)
    return IndexRule(BROADCAST, div, size, (p, q))


def broadcast_table(rule, compact, shape, lanes, dtype):
    """``(rule, table)``: the values the kernels read for the :data:`BROADCAST` ``rule`` of an
    input whose :func:`compact_values` are ``compact``, and the rule they read them with; None
    when the table would hold more than :data:`TABLE_POINTS` values (gather that input instead).

    ``lanes`` = 1 (one point per work-item): the compact values as they are.  ``lanes`` = N (the
    vector kernels, N points per work-item) lays them out so that each work-item's N values are
    one vector load or a choice between two values (``pb_in_rule`` in pbrdf_points.cl): a rule
    with 1 < div < N is widened over its trailing axes to div = 1 (its values repeated div times,
    fewer than N-fold); a div = 1 table repeats its first N - 1 values at its end, a div >= N
    table its first value, so no read wraps or leaves the table.
    """
    p = rule.axes[0]
    if lanes > 1 and 1 < rule.div < lanes:
        compact = np.broadcast_to(compact[(0,) * p], shape[p:])
        rule = IndexRule(BROADCAST, 1, math.prod(shape[p:]), (p, len(shape)))
    halo = 0 if lanes == 1 else lanes - 1 if rule.div == 1 else 1
    if rule.mod + halo > TABLE_POINTS:
        return None
    flat = compact.reshape(-1)
    if halo:
        flat = flat[np.arange(rule.mod + halo) % rule.mod]
    return rule, np.array(flat, dtype)


def udiv_magic(d):
    """``(m, s)`` with ``n // d == ((2 n m) >> 32) >> s`` for every 0 <= n < 2^31 (1 <= d <= 2^31):
    ``s = ceil(log2 d)``, ``m = ceil(2^(31 + s) / d) < 2^32`` (Granlund and Montgomery 1994 with
    31-bit numerators), the kernels' ``PB_UDIV``."""
    s = (int(d) - 1).bit_length()
    return -(-(1 << (31 + s)) // int(d)), s


def rule_table(plan, start):
    """The kernels' ``rules`` table (uint32, :data:`RULE_FIELDS` per input of
    :data:`POINT_INPUTS`) for a launch whose first point is flat point ``start``: a broadcast
    rule's offsets ``r0 = start % div`` and ``q0 = (start // div) % mod`` computed here, exactly,
    so that the kernels' arithmetic stays within 32 bits at any ``start``."""
    table = np.zeros((len(POINT_INPUTS), len(RULE_FIELDS)), np.uint32)
    for j, name in enumerate(POINT_INPUTS):
        r = plan[name]
        table[j] = (r.kind, r.div, *udiv_magic(r.div), r.mod, *udiv_magic(r.mod), start % r.div,
                    (start // r.div) % r.mod)
    return table


def _gather(dst, a, start, stop):
    """Copy points start..stop of the array ``a`` (in C order, any strides: a broadcast view too)
    into the 1-d ``dst``, converting the dtype, without a temporary: the range is split into
    boxes of ``a``, each copied by ``np.copyto``."""
    for offset, box in _flat_boxes(a.shape, start, stop):
        view = a[box]
        np.copyto(dst[offset:offset + view.size].reshape(view.shape), view, casting="unsafe")


def _flat_boxes(shape, start, stop, lead=(), offset=0):
    """The flat range start..stop of an array of ``shape`` (C order) as boxes: yields
    ``(offset into the range, tuple of slices)``, at most 2 * len(shape) of them."""
    if start >= stop:
        return
    if not shape:
        yield offset, lead
        return
    inner = int(np.prod(shape[1:], dtype=np.int64))
    i0, r0 = divmod(start, inner)
    i1, r1 = divmod(stop, inner)
    if i0 == i1:
        yield from _flat_boxes(shape[1:], r0, r1, lead + (slice(i0, i0 + 1),), offset)
        return
    if r0:
        yield from _flat_boxes(shape[1:], r0, inner, lead + (slice(i0, i0 + 1),), offset)
        offset += inner - r0
        i0 += 1
    if i1 > i0:
        yield offset, lead + (slice(i0, i1),) + tuple(slice(0, n) for n in shape[1:])
        offset += (i1 - i0) * inner
    if r1:
        yield from _flat_boxes(shape[1:], 0, r1, lead + (slice(i1, i1 + 1),), offset)


_default_engine = None
_default_lock = threading.Lock()


def _fallback(exc):
    skipped = getattr(exc, "skipped", 0)
    if skipped:  # each was named in a warning line already
        which = "one" if skipped == 1 else skipped
        why = f"no usable OpenCL device (the {which} above cannot run pbrdf-cl); {_HOW_TO_GET_ONE}"
    else:
        why = str(exc)
    _warn_once(("fallback",), f"computing on the numpy backend (the float64 reference, slower): {why}")
    return NumpyEngine(str(exc))


def get_default_engine(backend="auto"):
    """The engine used by the module-level functions (created on first use).

    Parameters
    ----------
    backend : {"auto", "opencl", "numpy"}, default "auto"
        "auto": the first usable OpenCL device, else a :class:`NumpyEngine` (with one
        :class:`DeviceWarning` naming the reason and the remedies); "opencl": that device or
        :class:`OpenCLUnavailableError`; "numpy": a :class:`NumpyEngine`.

    Returns
    -------
    Engine or NumpyEngine

    Examples
    --------
    >>> pbrdf_cl.get_default_engine().description  # doctest: +SKIP
    'Portable Computing Language / pthread-haswell-AMD EPYC ...'
    """
    global _default_engine
    check_backend(backend)
    if backend == "numpy":
        return NumpyEngine()
    with _default_lock:
        if _default_engine is None:
            try:
                _default_engine = Engine()
            except DeviceUnusableError:
                raise  # an explicit choice (PYOPENCL_CTX) is never replaced silently
            except OpenCLUnavailableError as exc:
                _default_engine = _fallback(exc)
        eng = _default_engine
    if backend == "opencl" and eng.is_numpy:
        raise OpenCLUnavailableError(f"backend='opencl': {eng.reason or 'the default engine is the numpy backend'}")
    return eng


# ---------------------------------------------------------------------------------------------
# a program a device cannot run: the next usable device, else the numpy backend

_FALLBACK_LOCK = threading.RLock()
_AUTO_ENGINES = {}      # device int_ptr -> an Engine made for a fallback (reused)
_CANNOT = {}            # program key -> device int_ptrs whose trial of it failed


def _device_name(eng):
    return f"OpenCL device {eng.index[0]}:{eng.index[1]} ({eng.description})"


def fallback_engine(exc, backend="auto", exclude=()):
    """The engine to compute on after ``exc`` (a :class:`ProgramUnusableError`): the next usable
    device in the default order that has not failed this program, else a :class:`NumpyEngine`
    (not with ``backend="opencl"``), skipping the devices ``exclude`` (``int_ptr``s) too.  Warns
    once per device and program.  An explicitly chosen device (``Engine(device)``,
    ``PYOPENCL_CTX``, ``--device``) re-raises ``exc``: a one-line error."""
    failed = exc.engine
    if failed is None or failed.explicit:
        raise exc
    with _FALLBACK_LOCK:
        bad = _CANNOT.setdefault(exc.program, set())
        bad.add(failed.device.int_ptr)
        replacement = None
        for dev in candidates():
            if dev.int_ptr in bad or dev.int_ptr in exclude or not probe(dev).usable:
                continue
            if dev.int_ptr not in _AUTO_ENGINES:
                try:
                    _AUTO_ENGINES[dev.int_ptr] = Engine(dev)
                except OpenCLUnavailableError:
                    bad.add(dev.int_ptr)
                    continue
                _AUTO_ENGINES[dev.int_ptr].explicit = False
            replacement = _AUTO_ENGINES[dev.int_ptr]
            break
        if replacement is None:
            if backend == "opencl":
                raise exc
            replacement = NumpyEngine(str(exc))
        where = "the numpy backend (the float64 reference, slower)" if replacement.is_numpy else \
            _device_name(replacement)
        _warn_once(("program", failed.device.int_ptr, exc.program), f"{exc}; computing it on {where}")
        return replacement


def falls_back(func):
    """Decorate a function that computes on an engine (its ``engine`` or ``eng`` argument): where a
    program it needs is unusable on that engine's device (:class:`ProgramUnusableError`), it is run
    again on :func:`fallback_engine`'s choice.  A generator is run again only if it has yielded
    nothing yet."""
    sig = inspect.signature(func)
    name = "engine" if "engine" in sig.parameters else "eng"

    def bound_call(args, kwargs):
        bound = sig.bind(*args, **kwargs)
        return bound, bound.arguments.get("backend", "auto")

    if inspect.isgeneratorfunction(func):
        @functools.wraps(func)
        def generator(*args, **kwargs):
            bound, backend = bound_call(args, kwargs)
            failed = set()
            while True:
                started = False
                try:
                    for item in func(*bound.args, **bound.kwargs):
                        started = True
                        yield item
                    return
                except ProgramUnusableError as exc:
                    if started or exc.engine is None:
                        raise
                    failed.add(exc.engine.device.int_ptr)
                    bound.arguments[name] = fallback_engine(exc, backend, failed)
        return generator

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        bound, backend = bound_call(args, kwargs)
        failed = set()  # each device at most once per call: the loop ends on the numpy backend
        while True:
            try:
                return func(*bound.args, **bound.kwargs)
            except ProgramUnusableError as exc:
                if exc.engine is None:
                    raise
                failed.add(exc.engine.device.int_ptr)
                bound.arguments[name] = fallback_engine(exc, backend, failed)
    return wrapper


def set_default_engine(engine) -> None:
    """Replace the default engine of the module-level functions.

    Parameters
    ----------
    engine : Engine, NumpyEngine or None
        The new default; None chooses afresh on next use.

    Returns
    -------
    None

    Examples
    --------
    >>> pbrdf_cl.set_default_engine(pbrdf_cl.Engine("1:0"))  # doctest: +SKIP
    """
    global _default_engine
    _default_engine = engine


def check_backend(backend):
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def resolve_engine(engine=None, backend="auto"):
    """The engine a call computes with: ``engine`` if given (an :class:`Engine` or a
    :class:`NumpyEngine`), else the default for ``backend`` (see :func:`get_default_engine`).
    ``backend="numpy"`` always gives the numpy engine; ``backend="opencl"`` refuses a numpy one."""
    check_backend(backend)
    if backend == "numpy":
        return engine if isinstance(engine, NumpyEngine) else NumpyEngine()
    if engine is None:
        return get_default_engine(backend)
    if not isinstance(engine, (Engine, NumpyEngine)):
        raise ValueError(f"engine must be a pbrdf_cl.Engine or NumpyEngine, got {engine!r}; to choose a device by "
                         "name use pbrdf_cl.Engine(device) (or PYOPENCL_CTX), or backend='numpy'")
    if backend == "opencl" and engine.is_numpy:
        raise ValueError("backend='opencl' with a NumpyEngine: pass an OpenCL Engine, or backend='auto'")
    return engine
