"""The OpenCL engine (:class:`Engine`): one object owning a device's context and queues, the
programs built for it and their kernels, the lock around setting a kernel's arguments and
launching it, buffers over host memory (results written in place on a CPU device) and reads.

Programs are built once per (precision, shadowing variant) with ``-D`` options and kept, with
their ``cl.Kernel`` objects, for the life of the engine.  Before a process first builds a program
on a device, the build and one launch of each kernel are tried in a child process
(:mod:`pbrdf_cl.device.trials`), whose verdict is stored on disk: a driver that crashes, aborts or
hangs there takes the child down, not this process.  A program the trial found unusable raises
:class:`ProgramUnusableError` (:mod:`pbrdf_cl.device.fallback` then picks another device).  The
per-point inputs and results travel as :mod:`pbrdf_cl.device.transfers` says; the device is chosen
by :mod:`pbrdf_cl.device.choice`.
"""
from __future__ import annotations

import hashlib
import os
import threading

import numpy as np

from ..errors import DeviceUnusableError, KernelBuildError, ProgramUnusableError
from ..model import quantities, reference
from . import drivers, ops, transfers, trials
from .choice import device_index, has_fp64, is_pocl, select_device, vector_widths
from .drivers import describe, first_error_line
from .numpy_engine import NumpyEngine
from .sources import DTYPES, build, build_options, cl, kernel_dir, kernels_sha256


class Engine:
    """Owns an OpenCL context and queue on one device and the programs built for it.

    Parameters
    ----------
    device : cl.Device, str or None
        See :func:`pbrdf_cl.select_device`.
    profiling : bool
        Create the queue with profiling enabled (``last_event_seconds`` then reports the
        device time of the last launch).
    """

    is_numpy = False
    backend = "opencl"
    #: OpenCL kernels to build, launch and time (False on :class:`NumpyEngine`)
    has_kernels = True
    #: why this engine computes rather than the one asked for: empty (a :class:`NumpyEngine` made
    #: for a fallback says why)
    reason = ""

    def __init__(self, device=None, *, profiling=False):
        #: chosen by the caller (``device``, ``PYOPENCL_CTX``): a program it cannot run is an error,
        #: never a silent move to another device (see :func:`pbrdf_cl.device.fallback.falls_back`)
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
        #: send a broadcast input once with its index rule (:func:`pbrdf_cl.device.transfers.input_plan`);
        #: False gathers it launch by launch on the host, as before issue #12 (for comparisons: tests, the bench)
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
            self._index = device_index(self.device) or ("?", "?")
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
                program = build(self.context, prefix + source, options)
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

    def compute_dtype(self, dtype):
        """The precision a computation asked for in ``dtype`` runs in: ``dtype`` itself (the numpy
        engine's is float64 always)."""
        return dtype

    def checks_domain(self, quantity):
        """Whether :meth:`evaluate`'s kernel for ``quantity`` checks the inputs' domain itself (the
        vector kernels, of the quantities the registry marks ``vector``, write NaN for a point
        outside it), so that the caller need not read the inputs beforehand, only check the result."""
        return quantities.get(quantity, "points").vector and self.vectorise

    def evaluate(self, quantity: str, inputs: dict, shape, dtype="float64", shadowing="paper"):
        """Evaluate ``quantity`` (a name of the registry, :mod:`pbrdf_cl.quantities`) element-wise.

        ``inputs`` maps each name of :data:`pbrdf_cl.device.sources.POINT_INPUTS` to an array (any
        float dtype, any strides) that broadcasts to ``shape``: of ``shape`` itself, a broadcast view
        of it, or as given (``theta_r[:, None]``, a scalar).  Angles in degrees.  Each input is read
        as :func:`pbrdf_cl.device.transfers.input_plan` says: one value, or a short axis (any single
        run of axes) sent once with its index rule, which the kernels apply point by point (never
        expanded, on the host or the device); an input with a value per point is read in place on a
        CPU device when it is contiguous and of ``dtype``, else converted (or gathered, for other
        broadcast patterns) one launch at a time.  The kernels write straight into the returned
        array (host-pointer buffers on a CPU device), so memory beyond the inputs and the result
        stays within a launch's worth, plus each broadcast input's table
        (:func:`pbrdf_cl.device.transfers.broadcast_table`, at most ``transfers.TABLE_POINTS``
        values; a longer one is gathered launch by launch).  Where :meth:`checks_domain`, a point
        outside the model's domain gets NaN; no other validation here.  The result has ``shape``
        and the quantity's trailing axes (``shape + (4, 4)`` for "mueller", ``shape + (4,)`` for
        "stokes"), in ``dtype``.
        """
        return transfers.evaluate(self, quantity, inputs, shape, dtype, shadowing)

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
        return 1 if is_pocl(self.device.platform) else 4096

    def can_use_in_place(self, a, npdt):
        """Whether the device reads the array ``a`` in place (buffer over its memory) as ``npdt``."""
        return (self.host_memory and a.ndim == 1 and a.dtype == npdt and a.flags.c_contiguous
                and a.ctypes.data % self.zero_copy_alignment == 0)

    def output(self, view, accumulate=False):
        """A device buffer whose values end up in the contiguous host array ``view``: on a CPU
        device a buffer over ``view`` itself (the kernel writes there), elsewhere a device
        buffer copied into it.  Returns ``(buffer, done)``; call ``done()`` after the launch
        (or the launches: with ``accumulate`` the kernels may also read what the launches before
        them wrote): it blocks until the values are in ``view``."""
        mf = cl.mem_flags
        if self.host_memory:
            buf = cl.Buffer(self.context, (mf.READ_WRITE if accumulate else mf.WRITE_ONLY) | mf.USE_HOST_PTR,
                            hostbuf=view)

            def done():  # mapping makes the kernel's writes visible to the host (a no-op on PoCL)
                mapped, _ = cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, view.shape, view.dtype)
                mapped.base.release(self.queue)
                self.queue.finish()
            return buf, done
        buf = self.empty(view.nbytes)
        return buf, lambda: self.read(buf, view)

    @property
    def last_event_seconds(self):
        """Device time of the last kernel launch (needs ``profiling=True``)."""
        if not self.profiling or self._last_event is None:
            return None
        ev = self._last_event
        return (ev.profile.end - ev.profile.start) * 1e-9
