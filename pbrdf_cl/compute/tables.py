"""The factor tables of ``kernels/pbrdf_tables.cl`` on a device: one launch of a table kernel over a
list of geometries and the pairs of two parameter axes (:func:`factor_table`), for the grid
(:mod:`pbrdf_cl.compute.dense`), the channels' objective (:mod:`pbrdf_cl.compute.channels`) and the
image fits' per-pixel tables (:mod:`pbrdf_cl.fitting.images.pixel_stages`) alike; and the blocks of
measurements whose tables the objective makes one after another (:func:`row_blocks`,
:func:`summed_over_rows`) where those of all do not fit in its memory budget."""
from __future__ import annotations

import numpy as np

from ..device.engine import DTYPES


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


def row_blocks(n_rows, rows):
    """The (first, last + 1) measurements of each block of at most ``rows``."""
    return [(m0, min(n_rows, m0 + rows)) for m0 in range(0, n_rows, max(1, int(rows)))]


def summed_over_rows(P, n_rows, rows, blocks, out, dtype):
    """(0, SSE) of a parameter grid of ``P`` vectors whose measurements come in blocks of ``rows``
    (the numpy backend's objective where the tables of all do not fit): ``blocks(m0, m1)`` yields
    (flat start, float64 SSE) of measurements m0..m1, summed here in float64 block by block."""
    acc = np.zeros(P)
    for m0, m1 in row_blocks(n_rows, rows):
        for start, values in blocks(m0, m1):
            acc[start:start + values.size] += values
    host = out if out is not None else np.empty(P, DTYPES[dtype])
    host[...] = acc
    yield 0, host
