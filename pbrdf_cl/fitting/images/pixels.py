"""What the stages of an image fit share (:mod:`pbrdf_cl.fitting.images.pixel_stages`,
:mod:`~pbrdf_cl.fitting.images.corners`, :mod:`~pbrdf_cl.fitting.images.pixel_fit`,
:mod:`~pbrdf_cl.fitting.images.statistics`): the setup of :func:`pbrdf_cl.fit_batch`
(:class:`BatchSetup`), a block of pixels ready for them (:class:`Block`), the grid's regions and
points, the descents' coordinates (ks as log ks) and what a descent returns (:class:`Descent`),
and the reference model's residual rows of many pixels (:class:`PixelResiduals`)."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from ...io.source import ANGLES, INCIDENT
from ...model import measurables, reference
from ...model.inputs import MEMBERS
from ..channels import ChannelModel
from ..common import dop_resolution, run_starts
from ..setup import F00_REL_STD, PARAMETERS, FitSetup

#: Grid nodes per free parameter of the batched grid stage (coarser than :func:`pbrdf_cl.fit`'s: the
#: regions' minima only seed the descents).
BATCH_GRID = dict(n=12, k=12, sigma=8, kd=8, c=4)
BATCH_SPECULAR_GRID = dict(n=48, k=48)


@dataclass(frozen=True)
class BatchSetup(FitSetup):
    """The checked setup of :func:`pbrdf_cl.fit_batch`: the fit's
    (:class:`~pbrdf_cl.fitting.setup.FitSetup`: model, shadowing, bounds, fixed values) and the
    image fit's own: the grid stage's ``axes`` (free parameter -> nodes), ``use_f00`` (the
    intensities enter the fit: ks free, kd as kd/ks), ``n_starts`` (descents per pixel),
    ``sigma_known`` (dop_std given) and ``noise_floor`` (the least DOP noise assumed without it;
    each pixel's own may be higher: :attr:`Block.noise_floor`), the measured ``quantities`` fitted
    (names of :data:`pbrdf_cl.io.source.MEASURED`) and whether they are fitted as polarimetric
    ``channels`` (:mod:`pbrdf_cl.model.measurables`: anything but the DOP under unpolarised light)."""
    axes: dict
    use_f00: bool
    n_starts: int
    sigma_known: bool
    noise_floor: float
    quantities: tuple = ("dop",)
    channels: bool = False


class Descent(NamedTuple):
    """What a batch of descents returns, arrays over (starts, pixels): the points ``x`` (..., D),
    their objective ``sse``, ``jtj`` (J^T J in the descent's coordinates, (..., D, D)) and
    ``settled`` (the descent stopped improving)."""
    x: np.ndarray
    sse: np.ndarray
    jtj: np.ndarray
    settled: np.ndarray

    def concat(self, other):
        """The starts of this and ``other`` together (along the first axis)."""
        return Descent(*(np.concatenate([a, b]) for a, b in zip(self, other)))


def regions(axes, free):
    """The grid points (flat index over (n, k, sigma, ks, kd, c) of ``axes``, ks of size 1) ordered
    region by region, a region being one half of every free axis (2^d boxes); returns (order,
    rstart), region r holding order[rstart[r]:rstart[r + 1]]."""
    names = PARAMETERS
    sizes = [axes[n].size for n in names]
    idx = np.indices(sizes).reshape(6, -1)
    region = np.zeros(idx.shape[1], np.int64)
    for axis, name in enumerate(names):
        if name in free and sizes[axis] > 1:
            region = region * 2 + (idx[axis] >= sizes[axis] // 2)
    counts = np.bincount(region)
    rstart = np.concatenate([[0], np.cumsum(counts[counts > 0])])
    return np.argsort(region, kind="stable").astype(np.int32), rstart.astype(np.int32)


def grid_values(setup):
    """The grid's parameter values (every parameter: free on its axis, the others fixed) as arrays
    for the tables: dict name -> 1-d array."""
    v = {}
    for name in PARAMETERS:
        v[name] = setup.axes[name] if name in setup.axes else np.array([setup.base[name]], float)
    return v


def grid_points(setup, order, flat):
    """Parameter vectors (over ``setup.free``) of region-ordered grid indices ``flat``."""
    v = grid_values(setup)
    sizes = [v[n].size for n in PARAMETERS]
    unr = np.unravel_index(order[flat], sizes)
    names = PARAMETERS
    return np.stack([v[n][unr[names.index(n)]] for n in setup.free], axis=-1)


def channel_spec(raw, quantities, shared):
    """The polarimetric channels of a block's measurements (:func:`pbrdf_cl.model.measurables.channels`,
    obs 0): ``quantities`` at every measurement m, channel m * len(quantities) + j for the j-th
    quantity in the registry's order; arrays over the C channels where the geometry and incident
    states are ``shared`` ((M,) in ``raw``), else over (pixels, C)."""
    names = [n for n in measurables.REGISTRY if n in quantities]
    p, M = raw[names[0]].shape
    shape = (M,) if shared else (p, M)
    geo = [np.broadcast_to(raw[a], shape).reshape(-1) for a in ANGLES]
    inc = np.stack([np.broadcast_to(raw[n], shape).reshape(-1) if n in raw else np.zeros(int(np.prod(shape)))
                    for n in INCIDENT], axis=-1)
    ch = measurables.channels(*geo, {n: np.zeros(inc.shape[0]) for n in names}, incident=inc)
    if shared:
        return ch
    C = M * len(names)
    return type(ch)(**{f: getattr(ch, f).reshape((p, C) + getattr(ch, f).shape[1:]) for f in ch.__dataclass_fields__})


def is_shared(name, values):
    """Whether the raw field ``name`` of a block is one value per measurement that every pixel
    shares: an angle or an incident state given as (M,) (every other field is per pixel, (p, ...))."""
    return values.ndim == 1 and name in ANGLES + INCIDENT


def take(raw, idx):
    """The pixels ``idx`` (repeats allowed) of a block's raw fields, the shared ones kept (:func:`is_shared`)."""
    return {k: (v if is_shared(k, v) else v[idx]) for k, v in raw.items()}


def concatenate(raws):
    """The pixels of several raw dicts of one stack, in order, the shared fields those of the first
    (:func:`is_shared`)."""
    return {k: (v if is_shared(k, v) else np.concatenate([r[k] for r in raws])) for k, v in raws[0].items()}


class Block:
    """One block of pixels prepared for the stages: flat (p, M) arrays, weights, validity; with
    polarimetric quantities (``setup.channels``) the M measurements are C channels (one number
    measured at one measurement index, :func:`channel_spec`: ``spec``) and the arrays (p, C)."""

    def __init__(self, raw, setup, lanes):
        self.raw, self.setup, self.lanes = raw, setup, lanes
        self._model = None  # channel_model's, made once
        shared_names = ANGLES + tuple(n for n in INCIDENT if n in raw)
        self.shared = all(raw[a].ndim == 1 for a in shared_names)
        if setup.channels:
            self.spec = channel_spec(raw, setup.quantities, self.shared)
            names = [n for n in measurables.REGISTRY if n in setup.quantities]
            self.nq = len(names)  # channels per measurement, consecutive: channel m * nq + j
            dop = np.stack([raw[n] for n in names], axis=2).reshape(raw[names[0]].shape[0], -1)
            stds = [raw.get(f"{n}_std") for n in names]
            std = None if stds[0] is None else np.stack([np.broadcast_to(s, raw[n].shape) for n, s in
                                                         zip(names, stds)], axis=2).reshape(dop.shape)
            self.angles = [getattr(self.spec, a) for a in ANGLES]
        else:
            self.spec = None
            dop = raw["dop"]
            std = raw.get("dop_std")
            self.angles = [raw[a] if self.shared else np.broadcast_to(raw[a], dop.shape) for a in ANGLES]
        self.p = dop.shape[0]
        self.P = -(-self.p // lanes) * lanes  # padded
        mask = raw.get("mask", np.ones(self.p, bool))
        valid = np.isfinite(dop) & mask[:, None]
        if std is not None:
            valid &= np.isfinite(std)
        if setup.use_f00:
            valid &= np.isfinite(raw["f00"])
        self.mask = mask
        self.valid = valid
        self.obs = np.where(valid, dop, 0.0)
        w = valid / (std ** 2 if std is not None else 1.0)
        self.w = np.where(valid, w, 0.0)
        if setup.use_f00:
            f00 = raw["f00"]
            fstd = raw.get("f00_std")
            if fstd is None:
                fstd = F00_REL_STD * np.maximum(np.where(valid, f00, 1.0), 1e-300)
            self.fobs = np.where(valid, f00, 0.0)
            self.fw = np.where(valid, 1.0 / np.where(valid, fstd, 1.0) ** 2, 0.0)
        else:
            self.fobs = self.fw = None
        self.count = valid.sum(axis=1)

    # made when first read (many blocks, a descent's, read none of them)
    @cached_property
    def noise_floor(self):
        """Each pixel's floor of the noise estimate without dop_std, as :func:`pbrdf_cl.fit`'s
        (:func:`pbrdf_cl.fitting.common.dop_noise_floor`): the rounding error of the DOP resolution
        of its valid values (invalid ones are 0 in ``obs``, exact at any resolution), at least
        the setup's ``noise_floor``."""
        return np.maximum(self.setup.noise_floor, dop_resolution(self.obs, axis=1) / np.sqrt(12.0))

    @cached_property
    def distinct(self):
        """Distinct valid (theta_i, theta_r, phi) per pixel; of channels, distinct valid (geometry,
        incident and normalising vectors, component, kind): distinct numbers measured."""
        cols = [np.broadcast_to(a, self.valid.shape) for a in self.angles]
        if self.spec is not None:
            sp = self.spec
            cols += [np.broadcast_to(x, self.valid.shape) for x in (*np.moveaxis(sp.u, -1, 0),
                                                                    *np.moveaxis(sp.v, -1, 0), sp.comp, sp.kind)]
        key = np.stack(cols, axis=-1).astype(np.float64)
        key = np.where(self.valid[..., None], key, np.nan)
        s = np.ascontiguousarray(key).view(np.dtype((np.void, 8 * len(cols))))[..., 0]
        s = np.sort(s, axis=1)
        distinct = 1 + (s[:, 1:] != s[:, :-1]).sum(axis=1)
        return distinct - (~self.valid).any(axis=1)

    @cached_property
    def one_incidence(self):
        """Per pixel, whether its valid measurements share one angle of incidence (their valleys
        are long: :data:`pbrdf_cl.fitting.images.pixel_fit.ONE_INCIDENCE_SCHEDULE`)."""
        ti = np.broadcast_to(self.angles[0], self.valid.shape)
        with np.errstate(invalid="ignore"):
            lo = np.where(self.valid, ti, np.inf).min(axis=1)
            hi = np.where(self.valid, ti, -np.inf).max(axis=1)
        return lo == hi

    def subset(self, idx):
        """The block of pixels ``idx`` (repeats allowed) of this one."""
        return Block(take(self.raw, idx), self.setup, self.lanes)

    def channel_model(self, pix):
        """The reference model of this block's channels for the pixels ``pix`` (repeats allowed):
        :class:`~pbrdf_cl.fitting.channels.ChannelModel` over every channel (shared), or over each
        pixel's (per pixel)."""
        if self.shared:
            if self._model is None:
                self._model = ChannelModel(self.spec, self.setup.shadowing)
            return self._model
        return ChannelModel(self.spec.take(pix), self.setup.shadowing)

    def padded(self, a, fill=0.0):
        """(p, ...) -> (P, ...) padded with ``fill``."""
        out = np.full((self.P,) + a.shape[1:], fill, a.dtype if a.dtype != bool else float)
        out[:self.p] = a
        return out

    def pixel_major(self, a, dtype):
        """(p, M) -> (M, P) contiguous in ``dtype`` (the kernels' layout)."""
        return np.ascontiguousarray(self.padded(a).T, dtype=dtype)


def stack_blocks(blocks, copies):
    """One block of the pixels of ``blocks`` (blocks of one stack: the same setup, lanes and any
    shared geometry), those of ``blocks[i]`` ``copies[i]`` times over, in order: the pixels of
    several batches of descents as one."""
    if len(blocks) == 1:
        b = blocks[0]
        return b if copies[0] == 1 else b.subset(np.tile(np.arange(b.p), copies[0]))
    first = blocks[0]
    return Block(concatenate([b.raw for b, c in zip(blocks, copies) for _ in range(c)]), first.setup, first.lanes)


def _map_ks(X, names, func):
    """A copy of the parameter vectors X with ``func`` applied to their ks coordinate (if any)."""
    X = np.array(X, float)
    if "ks" in names:
        j = names.index("ks")
        X[..., j] = func(X[..., j])
    return X


def internal(X, names):
    """Parameter vectors to the descent's coordinates (ks as log ks)."""
    return _map_ks(X, names, np.log)


def external(X, names):
    """The descent's coordinates back to parameter vectors."""
    return _map_ks(X, names, np.exp)


def descent_bounds(setup, names):
    """(lo, hi) of the descent's coordinates ``names`` (ks as log ks)."""
    free, flo, fhi, ks = setup.free, setup.lo, setup.hi, setup.ks_bounds
    lo = [np.log(ks[0]) if n == "ks" else flo[free.index(n)] for n in names]
    hi = [np.log(ks[1]) if n == "ks" else fhi[free.index(n)] for n in names]
    return np.array(lo), np.array(hi)


class LogKs:
    """The descents' usual coordinates: the parameters, ks as log ks (the kernel's default build);
    :class:`pbrdf_cl.fitting.images.corners.Corner` is the other kind, with the same methods."""
    logged = ()  # the parameters descended as log(p - offset) (PB_LOG_* builds): none

    @staticmethod
    def bounds(setup, names):
        return descent_bounds(setup, names)

    @staticmethod
    def to_internal(X, names):
        return internal(X, names)

    @staticmethod
    def to_external(U, names):
        return external(U, names)


#: The parts of the model's DOP (and intensity) rows that :meth:`PixelResiduals.varied` computes
#: again only when a parameter they depend on moves (and 1/K with the specular part).
DEPENDS = dict(fresnel=MEMBERS["index"], specular=MEMBERS["specular"], minnaert=("c",))
#: The parameters the diffuse term kd/pi (cos ti cos tr)^c depends on (kd is kd/ks with
#: intensities: ks too): :meth:`PixelResiduals.varied` makes it again only when one of them moves.
DIFFUSE = MEMBERS["diffuse"] + ("ks",)


class PixelResiduals:
    """Weighted residual rows of the reference model for many pixels (the numpy backend): rows
    of a (B, D) batch belong to pixels ``pix`` repeated ``B // len(pix)`` times each, as
    :func:`fd_jacobian` lays them out."""

    def __init__(self, setup, blk, names, pix, intensity, weights=None, few_nk=False):
        self.setup, self.blk, self.names, self.pix, self.intensity = setup, blk, names, pix, intensity
        self.w = blk.w if weights is None else weights  # of the DOP residuals
        #: the rows share a few values of (n, k) (a label's pixels and their finite differences):
        #: the Fresnel terms are computed once per value where the geometry is shared
        self.few_nk = few_nk
        self._geometry = None  # of pixels that share it: _shared_geometry's

    def rows(self, X):
        rep = X.shape[0] // self.pix.size
        pix = np.repeat(self.pix, rep)
        blk = self.blk
        p = self._params(X)
        if blk.spec is not None:  # polarimetric channels (no intensities: job.py)
            aop = blk.spec.aop if blk.shared else blk.spec.aop[pix]
            r = reference.channel_residual(blk.channel_model(pix).rows(p), blk.obs[pix], aop) * np.sqrt(self.w[pix])
            return np.where(np.isfinite(r), r, 1e150)
        g = self._shared_geometry()[0] if blk.shared else reference.geometry(*[a[pix] for a in blk.angles])
        return self._residuals(*[self._part(part, p, g) for part in DEPENDS], p["kd"], pix)

    def varied(self, X, cols, h, pix=None):
        """The rows at the points ``X`` (B, D), one a pixel of ``pix`` (default: this object's),
        and at each moved along one coordinate, column ``cols[j]`` by ``h[:, j]`` (forward
        differences): (B, 1 + len(cols), rows' width), the numbers :meth:`rows` gives of the
        stacked points.  Where the pixels share their geometry and the DOP (and intensities) are
        fitted, each part of the model (:data:`DEPENDS`) is computed again only for the moves of
        the parameters it depends on."""
        B, D = X.shape
        pix = self.pix if pix is None else pix
        blk = self.blk
        if blk.spec is not None or not blk.shared or B != pix.size:
            pts = np.repeat(X[:, None, :], len(cols) + 1, axis=1)
            for j, c in enumerate(cols):
                pts[:, j + 1, c] += h[:, j]
            return PixelResiduals(self.setup, blk, self.names, pix, self.intensity, self.w, self.few_nk).rows(
                pts.reshape(-1, D)).reshape(B, len(cols) + 1, -1)
        g = self._shared_geometry()[0]
        p = self._params(X)
        base = {part: self._part(part, p, g) for part in DEPENDS}
        # what the moves share with the base point: the rows' data, and 1/K and the diffuse term
        # where the move leaves them (the same numbers, made once)
        data = (blk.obs[pix], np.sqrt(self.w[pix]))
        with np.errstate(over="ignore"):
            inv_K = np.exp(-base["specular"])
        fd = reference.diffuse_of(p["kd"], base["minnaert"])
        out = [self._residuals(*base.values(), p["kd"], pix, data, inv_K, fd)]
        for j, c in enumerate(cols):
            Xj = X.copy()
            Xj[:, c] += h[:, j]
            pj = self._params(Xj)
            moves = [part for part, deps in DEPENDS.items() if self.names[c] in deps]
            parts = [self._part(part, pj, g) if part in moves else base[part] for part in DEPENDS]
            out.append(self._residuals(*parts, pj["kd"], pix, data, None if "specular" in moves else inv_K,
                                       fd if self.names[c] not in DIFFUSE else None))
        return np.stack(out, axis=1)

    def _shared_geometry(self):
        """(g, beams): the geometry the pixels share ((1, M) fields) and each beam's distinct
        angles, (cos, sin, index of each measurement's), made once."""
        if self._geometry is None:
            g = reference.geometry(*[a[None, :] for a in self.blk.angles])
            beams = []
            for ct, st in ((g.cti, g.sti), (g.ctr, g.str)):
                u, inv = np.unique(np.stack([np.ravel(ct), np.ravel(st)]), axis=1, return_inverse=True)
                beams.append((u[0][None], u[1][None], inv.ravel()))
            self._geometry = (g, beams)
        return self._geometry

    def _params(self, X):
        """The model's parameters (each (B, 1), or the setup's fixed value) at the points X."""
        p = dict(self.setup.base)
        ext = external(X, self.names)
        for j, n in enumerate(self.names):
            p[n] = ext[:, j:j + 1]
        if self.intensity:
            p["kd"] = p["kd"] * p["ks"]
        return p

    def _part(self, part, p, g):
        """One part of the model (:data:`DEPENDS`) at the parameters ``p`` and geometry ``g``."""
        if part == "fresnel":
            return fresnel_rows(p["n"], p["k"], g) if self.few_nk and self.blk.shared else reference.fresnel(
                p["n"], p["k"], g.cb, g.sb)
        if part == "specular":
            return reference.log_specular_scale(g, p["sigma"], p["ks"], self._shadowing(p["sigma"], g))
        return reference.minnaert(g, p["c"])

    def _shadowing(self, sigma, g):
        """:func:`pbrdf_cl.model.reference.shadowing_factor` at ``sigma`` over the geometry ``g``;
        where the pixels share it, each beam's S computed once per distinct angle of that beam
        (the same numbers: every operation is elementwise)."""
        variant = reference.SHADOWING[self.setup.shadowing]
        if not self.blk.shared:
            return reference.shadowing_factor(g, sigma, variant)
        return reference.shadowing_of(*[reference.shadow_S(ct, st, sigma, variant)[:, inv]
                                        for ct, st, inv in self._shared_geometry()[1]])

    def _residuals(self, f, log_k, minnaert, kd, pix, data=None, inv_K=None, fd=None):
        """The weighted residual rows of the pixels ``pix`` from the model's parts and kd; ``data``
        (their DOP and the square roots of its weights), ``inv_K`` (exp(-``log_k``)) and ``fd``
        (the diffuse term of ``kd`` and ``minnaert``) where already made."""
        blk = self.blk
        obs, sw = (blk.obs[pix], np.sqrt(self.w[pix])) if data is None else data
        fd = reference.diffuse_of(kd, minnaert) if fd is None else fd
        with np.errstate(over="ignore"):  # reference.dop's
            r = (reference.dop_at(f, np.exp(-log_k) if inv_K is None else inv_K, fd) - obs) * sw
        if self.intensity:
            r = np.concatenate([r, (reference.brdf(f, log_k, fd) - blk.fobs[pix]) * np.sqrt(blk.fw[pix])], axis=1)
        return np.where(np.isfinite(r), r, 1e150)


#: Up to this many runs of equal (n, k) rows, :func:`fresnel_rows` computes the Fresnel terms once
#: per run without first finding the distinct values among them.
FEW_RUNS = 64


class _RowsOf:
    """The fields of :func:`pbrdf_cl.model.reference.fresnel` computed per distinct (n, k) (``f``),
    each taken back to the rows (``inv``) when it is first read: the DOP and intensity rows read
    three of its five."""

    def __init__(self, f, inv):
        self._f, self._inv = f, inv

    def __getattr__(self, name):
        v = getattr(self._f, name)[self._inv]
        setattr(self, name, v)
        return v


def fresnel_rows(n, k, g):
    """:func:`pbrdf_cl.model.reference.fresnel` of rows of (n, k) (each (B, 1) or a number) over
    the geometry ``g`` shared by the rows ((1, M)), computed once per run of equal rows (once per
    distinct (n, k) where the runs are many) and taken back to the rows (each field as it is
    read): element by element the same numbers (every operation is elementwise)."""
    B = max(np.size(n), np.size(k))
    n1 = np.broadcast_to(np.asarray(n, float), (B, 1))[:, 0]
    k1 = np.broadcast_to(np.asarray(k, float), (B, 1))[:, 0]
    starts = np.flatnonzero(run_starts(n1, k1))  # runs of equal rows
    lengths = np.diff(np.append(starts, B))
    if starts.size <= FEW_RUNS:
        f = reference.fresnel(n1[starts][:, None], k1[starts][:, None], g.cb, g.sb)
        return _RowsOf(f, np.repeat(np.arange(starts.size), lengths))
    # distinct (n, k) (complex numbers sort by real, then imaginary part)
    u, inv = np.unique(n1[starts] + 1j * k1[starts], return_inverse=True)
    f = reference.fresnel(u.real[:, None], u.imag[:, None], g.cb, g.sb)
    return _RowsOf(f, np.repeat(inv.ravel(), lengths))
