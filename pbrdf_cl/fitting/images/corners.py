"""The corner stage of an image fit (:func:`corner_polish`): pixels whose best point lies at one
of two corners of the model (:data:`CORNERS`), or whose table of a corner's points comes close to
their objective, descend again in the corner's log coordinates, where the valley is nearly a
straight line."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ...device import ops
from ..common import lm_batch
from ..setup import INDEX_CORNER, PARAMETERS
from .pixel_stages import device_lm
from .pixels import BATCH_GRID, PixelResiduals, descent_bounds

#: Two corners of the model where a descent in the parameters crawls along a valley onto bounds:
#:
#: - "index": n -> 1, k -> 0, kd -> 0, an index-matched surface where the Fresnel terms and the
#:   diffuse term vanish together and the DOP depends on their ratio (and on sigma and c); pixels
#:   of nearly unpolarised light fall into it.
#: - "mirror": sigma at its lower bound with kd -> 0, a near-mirror with a faint diffuse term: off
#:   the specular direction the specular lobe falls as exp(-tan^2(alpha) / (2 sigma^2)) and the
#:   DOP there depends on log kd against 1 / sigma^2, so the fit drives kd towards 0 by decades.
#:
#: Pixels whose best point lies within CORNER of the range from the lower bound of each of a
#: corner's ``near`` parameters (at the mirror corner only kd: at kd = 0 the DOP does not depend on
#: sigma, so a descent that reached it cannot move sigma) continue with the corner's ``logged``
#: parameters as log(p - corner) (floored at CORNER_FLOOR of the ranges), where
#: the valley is nearly a straight line: the corner's ``iterations`` Levenberg-Marquardt iterations (the
#: PB_LOG_* build of the descent; the reference on the numpy backend), kept where they lower the
#: pixel's objective.
CORNER = 0.01
CORNER_FLOOR = 1e-12
#: On the numpy backend a corner's descent (the reference's plain Levenberg-Marquardt, without the
#: device kernel's geodesic acceleration) crawls further down the valley: it runs the corner's
#: iterations again, up to this many rounds, while some pixel's objective still fell by more than
#: NUMPY_CORNER_RTOL in the last round (measured on the index-corner test pixels on a Zen 4: pixel
#: 0 stops 2.8e-6 above fit's objective after 200 iterations, reaches it after 1000).
NUMPY_CORNER_ROUNDS = 8
NUMPY_CORNER_RTOL = 1e-9
#: With shared geometry, every pixel's objective is also evaluated on a small table of each
#: corner's points (one DOP table, then a product with the pixels' data as in the grid stage): a
#: pixel whose best corner point comes within CORNER_TRIGGER of its best objective so far descends
#: from there too (the valleys are too narrow for the grid's nodes and the descents' starts).
#: The index corner's table: (n - 1, k) of CORNER_EPS, kd/ks of CORNER_KD (four steps a decade:
#: the DOP there depends on kd / |n + ik - 1|^2, and half a decade misses the valley), the grid's
#: sigma and c nodes.  The mirror corner's: sigma at its lower bound, kd/ks of MIRROR_KD, the
#: grid's n, k and c nodes.
CORNER_TRIGGER = 1.05
CORNER_KD = np.logspace(-9.0, -2.0, 29)
CORNER_EPS = ((1e-3, 0.0), (0.0, 1e-3), (1e-3, 1e-3))
MIRROR_KD = np.logspace(-9.0, -2.0, 15)


class Corner(NamedTuple):
    """A corner of the model (:data:`CORNERS`), and the descent's coordinates there (the methods
    of :class:`pbrdf_cl.fitting.images.pixels.LogKs`: ``logged`` parameters as log(p - offset))."""
    name: str
    at: tuple       # the parameters at their lower bound in the corner
    near: tuple     # those a pixel's best point must be near to descend there
    logged: tuple   # the parameters descended as log(p - offset) there
    offset: tuple   # of the logged parameters (their lower bounds, which the kernel assumes)
    iterations: int  # of the descent there (the mirror's valley is short: 60 do what 200 do)

    def bounds(self, setup, names):
        """(lo, hi) of the descent's coordinates ``names`` at this corner."""
        return _corner_bounds(setup, names, self)

    def to_internal(self, X, names):
        """Parameter vectors to this corner's coordinates."""
        return _to_corner(X, names, self)

    def to_external(self, U, names):
        """This corner's coordinates back to parameter vectors."""
        return _from_corner(U, names, self)


CORNERS = (Corner("index", INDEX_CORNER, INDEX_CORNER, INDEX_CORNER, (1.0, 0.0, 0.0), 200),
           Corner("mirror", ("sigma", "kd"), ("kd",), ("kd",), (0.0,), 60))


def _corner_table(setup, names, corner):
    """The table points of ``corner``: name -> values (a fixed parameter's one value)."""
    def nodes(n):
        if n not in names:
            return np.array([setup.base[n]], float)
        j = names.index(n)
        return np.linspace(setup.lo[j], setup.hi[j], BATCH_GRID[n])
    if corner.name == "index":
        E, KD, SG, C = np.meshgrid(np.arange(len(CORNER_EPS)), CORNER_KD, nodes("sigma"), nodes("c"), indexing="ij")
        eps = np.array(CORNER_EPS)[E.ravel()]
        return dict(n=1.0 + eps[:, 0], k=eps[:, 1], kd=KD.ravel(), sigma=SG.ravel(), c=C.ravel())
    N, K, KD, C = np.meshgrid(nodes("n"), nodes("k"), MIRROR_KD, nodes("c"), indexing="ij")
    return dict(n=N.ravel(), k=K.ravel(), kd=KD.ravel(), sigma=np.full(N.size, setup.lo[names.index("sigma")]),
                c=C.ravel())


def _corner_table_starts(eng, setup, blk, names, corner, sb):
    """The shared-geometry table's best point of ``corner`` per pixel, for the pixels where it
    comes within CORNER_TRIGGER of ``sb``: (pixels, their starts (q, D))."""
    if not blk.shared:
        return np.empty(0, int), np.empty((0, len(names)))
    pts = _corner_table(setup, names, corner)
    q = next(iter(pts.values())).size
    par = {n: pts[n] if n in pts else np.full(q, setup.base[n]) for n in PARAMETERS}
    # float32 as the grid stage's table (on a device): it only ranks starts for the float64 descent
    T = eng.call("batch_ranking_table", blk, par, setup.shadowing)
    T = np.where(np.isfinite(T), T, 1e3)
    best, arg = eng.call("batch_table_minima", blk, T, np.array([0, q], np.int32))
    j = arg[0]
    pix = np.flatnonzero(best[0] < CORNER_TRIGGER * sb)
    return pix, np.stack([pts[n][j[pix]] for n in names], axis=1)


def _corner_slots(names, corner):
    return [names.index(n) for n in corner.logged], np.array(corner.offset)


def _to_corner(X, names, corner):
    j, off = _corner_slots(names, corner)
    U = np.array(X, float)
    U[..., j] = np.log(np.maximum(U[..., j] - off, CORNER_FLOOR))
    return U


def _from_corner(U, names, corner):
    j, off = _corner_slots(names, corner)
    X = np.array(U, float)
    X[..., j] = off + np.exp(X[..., j])
    return X


def _corner_bounds(setup, names, corner):
    lo, hi = descent_bounds(setup, names)
    j, off = _corner_slots(names, corner)
    lo, hi = lo.copy(), hi.copy()
    lo[j], hi[j] = np.log(CORNER_FLOOR * (hi[j] - lo[j])), np.log(hi[j] - off)
    return lo, hi


def _corner_applies(setup, names, corner):
    """Whether ``corner`` is a corner of this fit's box: its parameters free, the logged ones
    bounded below by the offsets the kernel assumes."""
    if not set(corner.at) <= set(names):
        return False
    j, off = _corner_slots(names, corner)
    return bool(np.array_equal(np.asarray(setup.lo, float)[j], off))


def corner_polish(eng, setup, blk, xb, sb, jb, nfev):
    """For each of :data:`CORNERS`: the pixels at it (:data:`CORNER`), and those whose table
    point comes close to their objective, descended in the corner's coordinates (on the device;
    with the reference on the numpy backend); ``xb`` (p, D), ``sb`` (p,) and ``jb`` (p, D, D: JtJ
    in the descent's coordinates) updated in place where the objective falls."""
    names = list(setup.free)
    for corner in CORNERS:
        if _corner_applies(setup, names, corner):
            _descend_corner(eng, setup, blk, names, corner, xb, sb, jb, nfev)


def _descend_corner(eng, setup, blk, names, corner, xb, sb, jb, nfev):
    lo, hi = np.asarray(setup.lo, float), np.asarray(setup.hi, float)
    j = [names.index(n) for n in corner.near]
    near = np.all(xb[:, j] - lo[j] < CORNER * (hi - lo)[j], axis=1) & np.isfinite(sb)
    extra, X_extra = _corner_table_starts(eng, setup, blk, names, corner, np.where(near, -np.inf, sb))
    pix = np.concatenate([np.flatnonzero(near), extra])  # distinct: the table skips the pixels near
    if not pix.size:
        return
    logged, _ = _corner_slots(names, corner)
    X0 = np.clip(np.concatenate([xb[near], X_extra]), _corner_floor(lo, hi, logged), hi)
    dtype = "float64" if eng.fp64 else "float32"
    X, sse = eng.call("batch_corner_descent", setup, blk, names, corner, pix, X0, dtype, nfev)
    better = np.flatnonzero(sse < sb[pix])
    if not better.size:
        return
    X = np.clip(X[better], lo, hi)
    won = pix[better]
    # the objective and JtJ at the new points in the usual coordinates (no iteration)
    _, s_new, j_new, _ = eng.call("batch_lm", setup, blk.subset(won), X[None], names, dtype, 0, False)
    s_new, j_new = s_new[0], j_new[0]
    keep = s_new < sb[won]
    xb[won[keep]], sb[won[keep]], jb[won[keep]] = X[keep], s_new[keep], j_new[keep]


@ops.implements("batch_corner_descent", "opencl")
def _corner_descent_opencl(eng, setup, blk, names, corner, pix, X0, dtype, nfev):
    """The pixels ``pix`` of ``blk`` descended from X0 (q, D) in the corner's coordinates (the
    PB_LOG_* build of the descent): (X (q, D), sse (q,)); their evaluations added to ``nfev``."""
    X, sse, _, _ = device_lm(eng, setup, blk.subset(pix), X0[None], names, dtype, corner.iterations, False,
                             coords=corner)
    nfev[pix] += (len(names) + 1) * (corner.iterations + 1)
    return X[0], sse[0]


@ops.implements("batch_corner_descent", "numpy")
def _corner_descent_numpy(eng, setup, blk, names, corner, pix, X0, dtype, nfev):
    """:func:`_corner_descent_opencl` with the reference: rounds of the corner's iterations while
    an objective still falls (see :data:`NUMPY_CORNER_ROUNDS`)."""
    ulo, uhi = _corner_bounds(setup, names, corner)
    res = PixelResiduals(setup, blk, names, pix, False)
    U, sse = _to_corner(X0, names, corner), np.full(pix.size, np.inf)
    for _ in range(NUMPY_CORNER_ROUNDS):  # rounds while an objective still falls (see NUMPY_CORNER_ROUNDS)
        U, new, evals = lm_batch(lambda V: res.rows(_from_corner(V, names, corner)), U, ulo, uhi, corner.iterations,
                                 rows_apart=False)  # a pixel's rows are in its place
        nfev[pix] += evals // pix.size
        falling = np.any(new < sse * (1 - NUMPY_CORNER_RTOL))
        sse = new
        if not falling:
            break
    return _from_corner(U, names, corner), sse


def _corner_floor(lo, hi, logged):
    """The lower bounds with the corner's coordinates at their floor above the corner."""
    out = np.array(lo, float)
    out[logged] = lo[logged] + CORNER_FLOOR * (hi - lo)[logged]
    return out
