"""The numpy backend as an engine (:class:`NumpyEngine`): what computes where no OpenCL device is
usable, or where ``backend="numpy"`` asks for it.  It offers the interface the OpenCL engine
(:class:`pbrdf_cl.device.opencl.Engine`) offers the rest of the package (``call``, ``evaluate``,
``compute_dtype``, ``has_kernels``, ``reason``, ``lock``, ...), with the float64 reference of
``pbrdf_cl.model.reference``; the operations that differ between the backends are registered
per backend in :mod:`pbrdf_cl.device.ops`."""
from __future__ import annotations

import threading

import numpy as np

from ..model import quantities, reference
from . import ops
from .sources import DTYPES, POINT_INPUTS


class NumpyEngine:
    """The numpy backend: the float64 reference of ``pbrdf_cl.model.reference``, as an engine.

    Every function that takes ``engine=`` accepts one; the dense grids, reductions and the
    objective build the same factor tables with ``reference.py`` and combine them in chunks
    within the same memory budget.  It computes in float64 whatever ``dtype`` is asked for, and
    returns that dtype.

    Parameters
    ----------
    reason : str, default ""
        Why it is in use (empty when asked for by name).
    """

    is_numpy = True
    backend = "numpy"
    fp64 = True
    profiling = False
    last_event_seconds = None
    #: no OpenCL kernels to build, launch or time (:attr:`pbrdf_cl.device.opencl.Engine.has_kernels`)
    has_kernels = False
    #: one value per step: no vectors (the OpenCL engine's widths per dtype)
    vector_width = {"float32": 1, "float64": 1}
    lm_lanes = {"float32": 1, "float64": 1}

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

    def compute_dtype(self, dtype):
        """The precision a computation asked for in ``dtype`` runs in: float64, always (results are
        then cast to ``dtype``)."""
        return "float64"

    def evaluate(self, quantity, inputs, shape, dtype="float64", shadowing="paper"):
        """As :meth:`pbrdf_cl.device.opencl.Engine.evaluate`, with the reference."""
        q = quantities.get(quantity, "points")
        extra = q.trailing
        out = np.asarray(reference.evaluate(q.name, *(np.asarray(inputs[n], dtype=np.float64)
                                                         for n in POINT_INPUTS), shadowing=shadowing))
        lead = out.shape[:out.ndim - len(extra)]
        if lead != tuple(shape):  # every input a single value: one point, broadcast to the shape
            out = np.broadcast_to(out.reshape((-1,) + extra)[0], tuple(shape) + extra)
        out = np.asarray(out, dtype=DTYPES[dtype])
        return out if out.flags.writeable else out.copy()  # a copy only of the broadcast single point
