"""Operations with one implementation per backend: callers ask the engine, the engine picks.

Where a computation differs between the OpenCL device and the numpy reference (a grid's tables
and their combination, the objective's blocks, the per-pixel descents, ...), each backend's
implementation is registered under one operation name::

    @ops.implements("outer", "numpy")
    def _numpy_outer(eng, q, geo, par, rows, dtype, shadowing, flat): ...

    @ops.implements("outer", "opencl")
    def _device_outer(eng, q, geo, par, rows, dtype, shadowing, flat): ...

and callers run ``eng.call("outer", ...)`` without testing which engine they hold
(:meth:`pbrdf_cl.device.opencl.Engine.call`, :meth:`pbrdf_cl.device.numpy_engine.NumpyEngine.call`).
An operation without an implementation for the engine's backend runs on the numpy backend's,
with one :class:`pbrdf_cl.DeviceWarning` saying so (pyFAI's degraded method: opencl -> numpy).
"""
import warnings

from ..errors import DeviceWarning

_REGISTRY = {}  # (operation, backend) -> function(engine, *args, **kwargs)
_WARNED = set()
BACKENDS = ("opencl", "numpy")


def implements(name, backend):
    """Register the decorated function as ``backend``'s implementation of operation ``name``."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")

    def register(func):
        if (name, backend) in _REGISTRY and _REGISTRY[(name, backend)] is not func:
            raise ValueError(f"operation {name!r} has a {backend} implementation already "
                             f"({_REGISTRY[(name, backend)].__qualname__})")
        _REGISTRY[(name, backend)] = func
        return func
    return register


def implementation(name, backend):
    """``(function, backend it is for)``: ``backend``'s implementation of ``name``, else the numpy
    backend's (warning once); ``LookupError`` where there is none."""
    func = _REGISTRY.get((name, backend))
    if func is not None:
        return func, backend
    func = _REGISTRY.get((name, "numpy"))
    if func is None:
        known = sorted({n for n, _ in _REGISTRY})
        raise LookupError(f"no implementation of the operation {name!r} (operations: {', '.join(known)})")
    if (name, backend) not in _WARNED:
        _WARNED.add((name, backend))
        warnings.warn(f"{name}: no {backend} implementation; computing it on the numpy backend (the float64 "
                      "reference, slower)", DeviceWarning, stacklevel=3)
    return func, "numpy"


def operations():
    """Every registered operation name -> the backends that implement it."""
    out = {}
    for name, backend in sorted(_REGISTRY):
        out.setdefault(name, []).append(backend)
    return out
