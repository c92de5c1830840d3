"""A checked image-fit job (:class:`BatchJob`): the stack, the setup, the blocks of rows within the
memory budget and the fit of one block, the unit of work of :func:`pbrdf_cl.fit_batch` in memory,
into a store, or on ``dask.distributed`` workers."""
from __future__ import annotations

import numpy as np

from ...compute import pointwise
from ...io.source import INCIDENT, MEASURED, POLARIMETRIC, Source, check_block, data_notes
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
#: Bytes a run keeps per block whatever its size (its row range, its done mark, its place in the
#: work list; a store's marks and digests): a stack of more blocks than the budget holds is refused.
BLOCK_BOOK_BYTES = 256


class BatchJob:
    """A checked :func:`pbrdf_cl.fit_batch` job: the source stack (:class:`~pbrdf_cl.io.source.Source`),
    the setup (:class:`~pbrdf_cl.fitting.images.pixels.BatchSetup`), its blocks of rows and the fit of one
    block (:meth:`fit_rows`), so that a store or a Dask worker can run blocks on their own."""

    def __init__(self, data, model="six-param", bounds=None, fixed=None, shadowing="paper", *,
                 memory_budget=BLOCK_BUDGET, n_starts=N_STARTS, grid_shape=None, quantities=None):
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
        src = self.source
        fitted, notes = choose_quantities(src, quantities)
        channels = fitted != ("dop",) or any(n in src.vars for n in INCIDENT)
        sigma_known = check_stds(src, fitted)
        floor = DOP_NOISE_FLOOR  # each pixel's own floor may be higher: Block.noise_floor
        use_f00 = fs.fits_intensity("f00" in src.vars) and not channels
        if channels and "f00" in src.vars:
            notes.append("the intensities (f00 or s0) are not fitted with polarimetric channels per pixel: ks is "
                         "held and kd is kd/ks (pbrdf_cl.fit of one pixel's rows separates them)")
        self.setup = BatchSetup(fs.model, fs.shadowing, fs.bounds, fs.fixed, axes, use_f00, n_starts, sigma_known,
                                floor, fitted, channels)
        self.order, self.rstart = regions(grid_values(self.setup), free)
        self.check_size()  # before any pixel is read
        #: What the data show of the usual mistakes (phi not given, phi = 0, radians), from the
        #: first row of pixels, and which measured quantities are fitted: the result's
        #: ``attrs["data_notes"]`` and the goodness summary's causes.
        self.notes = data_notes(src) + notes

    @property
    def names(self):
        """The fitted parameters, in the order of the outputs."""
        return self.setup.free + (["ks"] if self.setup.use_f00 else [])

    @property
    def width(self):
        """The residuals per pixel: M measurements, or, with polarimetric channels, M per fitted quantity."""
        return self.source.M * (len(self.setup.quantities) if self.setup.channels else 1)

    def pixel_bytes(self):
        """Host and device bytes one pixel of a block needs (the largest stage)."""
        M, D, S = self.width, len(self.names), self.setup.n_starts
        v = grid_values(self.setup)
        # the block's data (float64 and the kernels' copies), the descents' vectors and J^T J, and
        # the geodesic acceleration's scratch (two slots of M Jacobian rows per float32 start)
        per = 8 * M * (36 if self.setup.channels else 12) + 8 * S * D * (D + 3) * 2 + (
            4 * 2 * M * (D + 1) * S if GEODESIC else 0)
        if not self.source.shared:
            nnk, nm, ni = v["n"].size * v["k"].size, v["sigma"].size, v["kd"].size * v["c"].size
            per += 4 * M * (2 * nnk + nm + ni)
        per += 8 * (self.rstart.size - 1) * 2
        return per

    def fixed_bytes(self):
        """Bytes a block needs whatever its size: with shared geometry the grid's DOP table and its
        making (the per-point path's inputs and output; measured with tracemalloc: 26 MB at the
        default grid and 30 measurements)."""
        return 32 * len(self.order) * self.width if self.source.shared else 0

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
            px = min(px, (2 ** 31 - 1) // (self.width * v["n"].size * v["k"].size) - 64)
        return int(max(1, min(self.source.shape[0], px // max(row, 1))))

    def check_size(self):
        """Refuse, in one line and before any pixel is read, a stack whose blocks cannot keep within
        the memory budget: a row of pixels too large for one block (:meth:`rows_per_block`), or so
        many blocks that a run's bookkeeping of them (:data:`BLOCK_BOOK_BYTES` each: the row range,
        the done mark, the work list) exceeds the budget."""
        from ... import sizes
        step = self.rows_per_block()
        n = -(-self.source.shape[0] // step)
        sizes.check_budget(n * BLOCK_BOOK_BYTES, f"the bookkeeping of {self.source.n_pixels} pixels in {n} blocks "
                           f"of {step} rows", self.memory_budget, "fit a part of the stack at a time (ds.isel(...))",
                           "raise memory_budget (larger blocks, fewer of them; fit-image --memory-budget)")

    def result_bytes(self):
        """Bytes of the in-memory result of every pixel (its outputs, and their blocks while they are
        joined)."""
        per = sum(a.nbytes for a in empty_outputs(1, len(self.names)).values())
        return 2 * per * self.source.n_pixels

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

    #: whether :meth:`prepare` does anything (it needs an engine in the calling process, and a
    #: cluster's client where the blocks go to workers)
    prepares = False

    def prepare(self, eng, progress=False, client=None, device=None, backend="auto"):
        """What must run before any block, from the calling process (with ``client``, on the
        workers of that cluster, each with its engine for ``device`` and ``backend``): nothing here
        (a :class:`pbrdf_cl.fitting.images.labels.LabelJob` finds its labels' shared values)."""

    def fit_rows(self, eng, r0, r1):
        """Fit the pixels of rows r0..r1: a dict of flat per-pixel result arrays."""
        return fit_block(eng, self.setup, self.read_rows(r0, r1), self.order, self.rstart, self.names)

    def store_settings(self):
        """What a store's settings (:func:`pbrdf_cl.fitting.images.store.settings`) add for this
        kind of job: the fitted quantities where they are polarimetric channels (a
        :class:`pbrdf_cl.fitting.images.labels.LabelJob` adds its labels)."""
        return {"quantities": list(self.setup.quantities)} if self.setup.channels else {}

    def dataset(self, out, seconds=None):
        """The result Dataset from the concatenated outputs of :meth:`fit_rows`; ``attrs["quantities"]``
        names the quantities fitted."""
        ds = make_dataset(self, out, seconds)
        ds.attrs["quantities"] = " ".join(self.setup.quantities)
        if self.setup.channels:
            what = ", ".join(self.setup.quantities)
            ds.attrs["incident"] = ("the incident states in_s1, in_s2, in_s3 of the stack" if any(
                n in self.source.vars for n in INCIDENT) else "unpolarised")
            for name, text in (("sse", f"sum of squared residuals of {what}"),
                               ("n_valid", f"valid measured numbers ({what})"),
                               ("r2", f"share of the variance of {what} the fit explains (R^2)")):
                ds[name].attrs["long_name"] = text
            ds["chi2"].attrs["long_name"] = "weighted sum of squared residuals" + (
                " (chi2)" if self.setup.sigma_known else " (std = 1: no uncertainties given)")
        return ds

    def empty_outputs(self, rows):
        """Outputs of :meth:`fit_rows` for ``rows`` rows not fitted, with the right keys, shapes and
        dtypes (a store's template)."""
        return empty_outputs(rows * int(np.prod(self.source.shape[1:], dtype=np.int64)), len(self.names))


def choose_quantities(source, quantities):
    """The measured quantities fitted (a tuple in :data:`~pbrdf_cl.io.source.MEASURED`'s order)
    and notes on those left out: ``quantities`` as given (a sequence, or one string of names
    separated by commas or spaces), else the stack's polarimetric quantities where it gives the
    source's state (``in_s1``..``in_s3``) or has no ``dop``, else its ``dop``."""
    measured = source.measured
    polar = [n for n in measured if n in POLARIMETRIC]
    incident = any(n in source.vars for n in INCIDENT)
    if quantities is None:
        chosen = polar if polar and ("dop" not in measured or incident) else ["dop"]
    else:
        names = quantities.replace(",", " ").split() if isinstance(quantities, str) else [str(q) for q in quantities]
        for n in names:
            if n not in MEASURED:
                from ...ranges import did_you_mean
                near = did_you_mean(n, MEASURED)
                raise ValueError(f"quantities: {n!r} is not a measured quantity" + (f"; did you mean {near!r}?" if near
                                 else "") + f" ({', '.join(MEASURED[:5])}, m01 .. m33)")
            if n not in measured:
                raise ValueError(f"quantities: {n!r} is not in the stack, which has {', '.join(measured)}")
        if not names:
            raise ValueError(f"quantities: give at least one of the stack's {', '.join(measured)}")
        chosen = [n for n in measured if n in names]
    left = [n for n in measured if n not in chosen]
    notes = []
    if left and quantities is None:
        why = ("the source's state is not given (in_s1, in_s2, in_s3): the DOP is fitted, as for unpolarised light"
               if chosen == ["dop"] else f"{', '.join(chosen)} are fitted (a camera's dop is sqrt(s1^2 + s2^2) of "
               "the same frames)")
        notes.append(f"{', '.join(left)} not fitted: {why}; quantities= (fit-image --quantities) chooses")
    return tuple(chosen), notes


def check_stds(source, fitted):
    """Whether every fitted quantity has its standard deviation (``<name>_std``; the fit's weights
    and chi2): all of them or none, an AoP among other quantities needs its own (one line each)."""
    have = [n for n in fitted if f"{n}_std" in source.vars]
    if have and len(have) < len(fitted):
        lack = [n for n in fitted if n not in have]
        raise ValueError(f"data: standard deviations are given for {', '.join(have)} but not for {', '.join(lack)}; "
                         "give <name>_std for every fitted quantity or for none")
    if "aop" in fitted and len(fitted) > 1 and not have:
        raise ValueError(f"data: aop_std is needed where the AoP is fitted with other quantities "
                         f"({', '.join(n for n in fitted if n != 'aop')}): degrees are not their units")
    return bool(have)
