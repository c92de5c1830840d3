"""A checked image-fit job (:class:`BatchJob`): the stack, the setup, the blocks of rows within the
memory budget and the fit of one block, the unit of work of :func:`pbrdf_cl.fit_batch` in memory,
into a store, or on ``dask.distributed`` workers."""
from __future__ import annotations

import numpy as np

from ...compute import pointwise
from ...io.source import Source, check_block, data_notes
from ..common import DOP_NOISE_FLOOR
from ..setup import FitSetup, check_model
from .dataset import empty_outputs, make_dataset
from .pixel_fit import fit_block
from .pixel_stages import GEODESIC
from .pixels import BATCH_GRID, BATCH_SPECULAR_GRID, BatchSetup, grid_values, regions

#: Starts per pixel: the best region minima of the grid.
N_STARTS = 32
#: The memory of one block of pixels (host and device) by default: the image fit's own budget
#: (a block's descents and tables), not the grids' (``pbrdf_cl.compute.dense.DEFAULT_BUDGET``, 1 GiB).
BLOCK_BUDGET = "512 MiB"


class BatchJob:
    """A checked :func:`pbrdf_cl.fit_batch` job: the source stack (:class:`~pbrdf_cl.io.source.Source`),
    the setup (:class:`~pbrdf_cl.fitting.images.pixels.BatchSetup`), its blocks of rows and the fit of one
    block (:meth:`fit_rows`), so that a store or a Dask worker can run blocks on their own."""

    def __init__(self, data, model="six-param", bounds=None, fixed=None, shadowing="paper", *,
                 memory_budget=BLOCK_BUDGET, n_starts=N_STARTS, grid_shape=None):
        from ...ranges import parse_bytes
        check_model(model, shadowing)
        n_starts = int(n_starts)
        if n_starts < 1:
            raise ValueError(f"n_starts must be >= 1, got {n_starts}")
        self.memory_budget = parse_bytes("memory_budget", memory_budget)
        self.source = Source(data)
        fs = FitSetup.check(model, bounds, fixed, shadowing)
        free = fs.free
        shape = {**(BATCH_SPECULAR_GRID if model == "specular" else BATCH_GRID), **(grid_shape or {})}
        unknown = set(grid_shape or {}) - set(free)
        if unknown:
            raise ValueError(f"grid_shape: {sorted(unknown)[0]!r} is not a free parameter ({', '.join(free)})")
        axes = fs.grid_axes(shape)
        if int(np.prod([a.size for a in axes.values()])) >= 2 ** 24:
            raise ValueError("grid_shape: at most 2**24 grid points")
        sigma_known = "dop_std" in self.source.vars
        floor = DOP_NOISE_FLOOR  # each pixel's own floor may be higher: Block.noise_floor
        use_f00 = fs.fits_intensity("f00" in self.source.vars)
        self.setup = BatchSetup(fs.model, fs.shadowing, fs.bounds, fs.fixed, axes, use_f00, n_starts, sigma_known,
                                floor)
        self.order, self.rstart = regions(grid_values(self.setup), free)
        #: What the data show of the usual mistakes (phi not given, phi = 0, radians), from the
        #: first row of pixels: the result's ``attrs["data_notes"]`` and the goodness summary's causes.
        self.notes = data_notes(self.source)

    @property
    def names(self):
        """The fitted parameters, in the order of the outputs."""
        return self.setup.free + (["ks"] if self.setup.use_f00 else [])

    def pixel_bytes(self):
        """Host and device bytes one pixel of a block needs (the largest stage)."""
        M, D, S = self.source.M, len(self.names), self.setup.n_starts
        v = grid_values(self.setup)
        # the block's data (float64 and the kernels' copies), the descents' vectors and J^T J, and
        # the geodesic acceleration's scratch (two slots of M Jacobian rows per float32 start)
        per = 8 * M * 12 + 8 * S * D * (D + 3) * 2 + (4 * 2 * M * (D + 1) * S if GEODESIC else 0)
        if not self.source.shared:
            nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size, v["kd"].size * v["c"].size
            per += 4 * M * (2 * nnk + nm + ni)
        per += 8 * (self.rstart.size - 1) * 2
        return per

    def fixed_bytes(self):
        """Bytes a block needs whatever its size: with shared geometry the grid's DOP table and its
        making (the per-point path's inputs and output; measured with tracemalloc: 26 MB at the
        default grid and 30 measurements)."""
        return 32 * len(self.order) * self.source.M if self.source.shared else 0

    def rows_per_block(self):
        """Rows of the first pixel dimension per block within the memory budget (at least one)."""
        row = int(np.prod(self.source.shape[1:], dtype=np.int64))
        fixed = self.fixed_bytes()
        need = fixed + self.pixel_bytes() * row
        if self.memory_budget < need:
            raise ValueError(f"memory_budget={self.memory_budget} bytes is too small for one row of "
                             f"{row} pixels ({need} bytes with the grid's tables); raise it")
        px = (self.memory_budget - fixed) // self.pixel_bytes()
        if not self.source.shared:  # 32-bit indices of the per-pixel tables
            v = grid_values(self.setup)
            px = min(px, (2 ** 31 - 1) // (self.source.M * v["n"].size * v["k"].size) - 64)
        return int(max(1, min(self.source.shape[0], px // max(row, 1))))

    def blocks(self):
        """(r0, r1) row ranges of the blocks, in order."""
        step = self.rows_per_block()
        return [(r0, min(r0 + step, self.source.shape[0])) for r0 in range(0, self.source.shape[0], step)]

    def read_rows(self, r0, r1):
        """The checked pixels of rows r0..r1 (:meth:`pbrdf_cl.io.source.Source.rows`)."""
        raw = self.source.rows(r0, r1)
        check_block(raw, r0, self.source)
        if r0 == 0:  # angles in radians? (the first block stands for the stack: no extra read)
            pointwise.check_degrees(raw["theta_i"], raw["theta_r"], "data: ")
        return raw

    #: whether :meth:`prepare` does anything (it needs an engine in the calling process)
    prepares = False

    def prepare(self, eng, progress=False):
        """What must run before any block, in the calling process: nothing here (a
        :class:`pbrdf_cl.fitting.images.labels.LabelJob` finds its labels' shared values)."""

    def fit_rows(self, eng, r0, r1):
        """Fit the pixels of rows r0..r1: a dict of flat per-pixel result arrays."""
        return fit_block(eng, self.setup, self.read_rows(r0, r1), self.order, self.rstart, self.names)

    def store_settings(self):
        """What a store's settings (:func:`pbrdf_cl.fitting.images.store.settings`) add for this
        kind of job: nothing (a :class:`pbrdf_cl.fitting.images.labels.LabelJob` adds its labels)."""
        return {}

    def dataset(self, out, seconds=None):
        """The result Dataset from the concatenated outputs of :meth:`fit_rows`."""
        return make_dataset(self, out, seconds)

    def empty_outputs(self, rows):
        """Outputs of :meth:`fit_rows` for ``rows`` rows not fitted, with the right keys, shapes and
        dtypes (a store's template)."""
        return empty_outputs(rows * int(np.prod(self.source.shape[1:], dtype=np.int64)), len(self.names))
