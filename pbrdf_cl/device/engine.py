"""The device layer's one interface for the rest of the package: the engines and how a call gets one.

Every function that computes takes ``engine=`` and ``backend=`` and asks :func:`resolve_engine`
for the engine (:func:`engine_for` where a device may be named too: the command line, store runs
and their workers); an :class:`Engine` (an OpenCL device) and a :class:`NumpyEngine` (the float64
reference) offer the same interface: ``call(operation, ...)`` runs the operation's implementation
for the engine's backend (:mod:`pbrdf_cl.device.ops`), ``evaluate`` the per-point quantities,
``compute_dtype(dtype)`` the precision a computation runs in, ``has_kernels`` whether there are
OpenCL kernels to launch and time, ``reason`` why a fallback engine computes, ``lock`` one
computation at a time.  Functions that compute on an engine are decorated with
:func:`falls_back`.  The rooms behind this face:

- :mod:`pbrdf_cl.device.sources`: the kernel sources, precisions and compiler options;
- :mod:`pbrdf_cl.device.choice`: listing, probing and choosing devices, the vector widths;
- :mod:`pbrdf_cl.device.opencl`: the OpenCL engine;
- :mod:`pbrdf_cl.device.numpy_engine`: the numpy engine;
- :mod:`pbrdf_cl.device.transfers`: the per-point inputs' index rules and transfers;
- :mod:`pbrdf_cl.device.fallback`: backends, the default engine, the fallbacks;
- :mod:`pbrdf_cl.device.ops`: operations with one implementation per backend;
- :mod:`pbrdf_cl.device.trials`, :mod:`pbrdf_cl.device.drivers`: trial builds in a child
  process; the drivers pip installs and the environment.

A module's settings (``transfers.LAUNCH_POINTS``, ``choice.cpu_flags``, ...) are read where they
are defined: change them there, not through this face.
"""
from ..errors import (
    DeviceUnusableError,
    DeviceWarning,
    KernelBuildError,
    OpenCLUnavailableError,
    ProgramUnusableError,
)
from .choice import (
    DRIVER_MESSAGES,
    ProbeResult,
    candidates,
    clear_probe_cache,
    has_fp64,
    is_pocl,
    is_simulator,
    list_devices,
    narrow_reason,
    probe,
    select_device,
    vector_widths,
)
from .drivers import describe, first_error_line
from .fallback import (
    BACKENDS,
    check_backend,
    engine_for,
    fallback_engine,
    falls_back,
    get_default_engine,
    resolve_engine,
    set_default_engine,
)
from .numpy_engine import NumpyEngine
from .opencl import Engine
from .sources import (
    DTYPES,
    POINT_INPUTS,
    POINT_LOCAL_SIZE,
    VECTOR_LOCAL_SIZE,
    build_options,
    cl,
    kernel_dir,
    kernels_sha256,
)
from .transfers import aligned_empty, compact_values

__all__ = ["BACKENDS", "DRIVER_MESSAGES", "DTYPES", "POINT_INPUTS", "POINT_LOCAL_SIZE", "VECTOR_LOCAL_SIZE",
           "DeviceUnusableError",
           "DeviceWarning", "Engine", "KernelBuildError", "NumpyEngine", "OpenCLUnavailableError", "ProbeResult",
           "ProgramUnusableError", "aligned_empty", "build_options", "candidates", "check_backend", "cl",
           "compact_values",
           "clear_probe_cache", "describe", "engine_for", "fallback_engine", "falls_back", "first_error_line",
           "get_default_engine", "has_fp64", "is_pocl", "is_simulator", "kernel_dir", "kernels_sha256",
           "list_devices", "narrow_reason", "probe", "resolve_engine", "select_device", "set_default_engine",
           "vector_widths"]
