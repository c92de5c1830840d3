"""Which engine computes a call, and what happens when it cannot: the backends (``"auto"``,
``"opencl"``, ``"numpy"``), the default engine, :func:`resolve_engine`, and the fallbacks.

**Backends.**  ``backend="auto"`` (the default everywhere) computes on the chosen OpenCL device,
or, when no device is usable, on :class:`NumpyEngine` (the float64 reference of
``reference.py``), saying so once with the reason and the remedies; ``"opencl"`` makes that an
error; ``"numpy"`` always uses the reference.  :func:`resolve_engine` implements this, and
:func:`engine_for` adds a device named by the caller: the one place that turns ``(engine, device,
backend)`` into an engine (the command line, store runs and their workers, the benchmark).

**A program a device cannot run.**  Where the trial found a program unusable on the engine's
device (:class:`ProgramUnusableError`), the functions marked :func:`falls_back` compute on the
next usable device, else on the numpy backend, with one :class:`DeviceWarning` line (an
explicitly chosen device makes it an error instead).
"""
from __future__ import annotations

import functools
import inspect
import threading

from ..errors import DeviceUnusableError, OpenCLUnavailableError, ProgramUnusableError
from .choice import HOW_TO_GET_ONE, candidates, probe, warn_once
from .numpy_engine import NumpyEngine
from .opencl import Engine

BACKENDS = ("auto", "opencl", "numpy")

_default_engine = None
_default_lock = threading.Lock()


def _fallback(exc):
    skipped = getattr(exc, "skipped", 0)
    if skipped:  # each was named in a warning line already
        which = "one" if skipped == 1 else skipped
        why = f"no usable OpenCL device (the {which} above cannot run pbrdf-cl); {HOW_TO_GET_ONE}"
    else:
        why = str(exc)
    warn_once(("fallback",), f"computing on the numpy backend (the float64 reference, slower): {why}")
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
        warn_once(("program", failed.device.int_ptr, exc.program), f"{exc}; computing it on {where}")
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

    Parameters
    ----------
    engine : pbrdf_cl.Engine or pbrdf_cl.NumpyEngine, optional
        The engine asked for.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        ``"numpy"`` always gives the numpy engine; ``"opencl"`` refuses a numpy one; ``"auto"``
        takes the OpenCL device, or the numpy engine where none is usable.

    Returns
    -------
    pbrdf_cl.Engine or pbrdf_cl.NumpyEngine
    """
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


def engine_for(engine=None, device=None, backend="auto"):
    """The engine of ``(engine, device, backend)``: the one place a backend's name is turned into an
    engine.  ``engine`` if given (checked against ``backend``, :func:`resolve_engine`); else a
    :class:`NumpyEngine` for ``backend="numpy"``; else an :class:`Engine` of ``device`` (an explicit
    choice: a program it cannot run is an error, never a move); else the default engine for
    ``backend`` (:func:`get_default_engine`).

    Parameters
    ----------
    engine : pbrdf_cl.Engine or pbrdf_cl.NumpyEngine, optional
        The engine asked for; ``device`` is then not used.
    device : str or pyopencl.Device, optional
        An OpenCL device (see :func:`pbrdf_cl.select_device`); not used with ``backend="numpy"``.
    backend : {"auto", "opencl", "numpy"}, default "auto"
        As for :func:`resolve_engine`.

    Returns
    -------
    pbrdf_cl.Engine or pbrdf_cl.NumpyEngine

    Examples
    --------
    >>> engine_for(device="0:0", backend="numpy")
    NumpyEngine(float64 reference)
    """
    check_backend(backend)
    if engine is not None or device is None or backend == "numpy":
        return resolve_engine(engine, backend)
    return Engine(device)
