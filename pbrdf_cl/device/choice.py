"""Which OpenCL device computes: listing the devices, probing each, the default order, the
choice, and the vector widths each device's programs are built with.

**Probe.**  A device is *usable* only when it builds ``kernels/pbrdf_probe.cl`` (which includes
``pbrdf.h``) in float32, and in float64 where the device claims it, and returns SPEC's check
values (DOP of the paper's steel at three geometries).  The probe runs in the trial process
(:mod:`pbrdf_cl.device.trials`).  Results are cached per process and on disk
(``~/.cache/pbrdf-cl/probe-v1.json``, see :func:`pbrdf_cl.device.drivers.cache_dir`), keyed by the
platform, the device, its driver version and the SHA-256 of the kernel sources.

**Choice**, in order: an explicit ``device`` argument, then the ``PYOPENCL_CTX`` environment
variable (an explicit choice that is unusable is an error), then the first usable device among
GPUs, PoCL CPU devices (newest PoCL first), other CPU drivers, anything else; never the Oclgrind
simulator unless named.  An unusable device is skipped with one :class:`DeviceWarning` line.  A
device is named by a ``cl.Device``, by ``"P"`` or ``"P:D"`` (platform and device indices, as
``pbrdf-cl devices`` lists them), or by a case-insensitive substring of "platform name / device
name" (``"pocl"``, ``"nvidia"``, ``"intel"``, ``"oclgrind"``).

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
import hashlib
import json
import os
import re
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from ..errors import DeviceUnusableError, DeviceWarning, OpenCLUnavailableError
from ..model import reference
from . import drivers, trials
from .drivers import describe, first_error_line
from .sources import (
    DTYPES,
    IMPORT_ERROR,
    LM_LANES,
    NARROW_LM_LANES,
    NARROW_VECTOR_WIDTH,
    VECTOR_WIDTH,
    build,
    build_options,
    cl,
    kernel_dir,
    kernels_sha256,
)

FAKE_FAILURE_ENV = "PBRDF_CL_FAKE_BUILD_FAILURE"
NARROW_ENV = "PBRDF_CL_NARROW_VECTORS"
#: The end of every message that says no device can be used.
HOW_TO_GET_ONE = "remedies: " + drivers.REMEDIES


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
        raise OpenCLUnavailableError(f"pyopencl cannot be imported ({IMPORT_ERROR}); remedies: `pip install "
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


def is_simulator(plat) -> bool:
    return "oclgrind" in plat.name.lower()


def is_pocl(plat) -> bool:
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
    if dev.type & dt.CPU and is_pocl(plat):
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
    if not (is_pocl(plat) and dev.type & cl.device_type.CPU):
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
    values, why = trials.run_probe(dev, device_index(dev), _probe_source(dev), options, dtypes, PROBE_POINTS)
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
                program = build(context, _probe_source(dev), build_options(dtype, width=widths[dtype]))
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


def device_index(dev):
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


def warn_once(key, message):
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
    real = [(plat, dev) for _, _, plat, dev in found if not is_simulator(plat)]
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
    return f"no usable OpenCL device ({'; '.join(parts)}); {HOW_TO_GET_ONE}"


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
        warn_once(("skip", _probe_key(dev)),
                   f"skipping OpenCL device {_device_id(found, dev)} ({describe(dev)}): {result.reason}")
    exc = OpenCLUnavailableError(_no_device_message(found, skipped))
    exc.skipped = len(skipped)
    raise exc
