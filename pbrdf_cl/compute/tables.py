"""The factor tables of ``kernels/pbrdf_tables.cl`` on a device: one launch of a table kernel over a
list of geometries and the pairs of two parameter axes (:func:`factor_table`), for the grid
(:mod:`pbrdf_cl.compute.dense`), the channels' objective (:mod:`pbrdf_cl.compute.channels`) and the
image fits' per-pixel tables (:mod:`pbrdf_cl.fitting.images.pixel_stages`) alike."""
from __future__ import annotations

import numpy as np


def factor_table(eng, kernels, kname, outs, geo, ng, p1, p2, npdt, *extra, parameter_major=False):
    """Launch the table kernel ``kname`` of the built ``pbrdf_tables.cl`` (``kernels``) over ``ng``
    geometries (``geo``: device arrays theta_i, theta_r, phi) and the pairs of the parameter axes
    ``p1`` x ``p2`` (n = p1.size * p2.size, p2 fastest), with the kernel's ``extra`` arguments.

    Returns the ``outs`` device buffers of ng * n values of ``npdt``, laid out geometry by geometry
    (table[g * n + i]) or, with ``parameter_major``, parameter pair by pair (table[i * ng + g]: a
    block of pixels' tables, read by the pixels' vector lanes)."""
    n = p1.size * p2.size
    bufs = [eng.empty(ng * n * np.dtype(npdt).itemsize) for _ in range(outs)]
    strides = (np.int32(1), np.int32(ng)) if parameter_major else (np.int32(n), np.int32(1))
    eng.launch(kernels[kname], (ng, n), *bufs, np.int32(ng), *strides, *geo, eng.to_device(p1, npdt),
               eng.to_device(p2, npdt), np.int32(p2.size), *extra)
    return bufs
