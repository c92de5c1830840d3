"""Measurement design from the Fisher information: which geometries to measure.

For a hypothesised material (or a box of materials) and the DOP noise of the instrument,
:func:`design` predicts each parameter's 95% interval width for any set of measurement
geometries, and chooses the ``n_measurements`` geometries out of a candidate set that make the
target parameters' intervals narrowest.

How the widths are predicted (the local linearisation :func:`pbrdf_cl.fit` itself uses for its
``ci95_jacobian``):

* Every candidate geometry contributes whitened Jacobian rows: the central-difference
  derivative of the DOP with respect to the free parameters divided by the DOP noise (one
  row), and with ``intensity`` also that of F00 divided by its standard deviation,
  ``intensity_noise`` times F00 (a second row).  The derivatives come from the device
  (:func:`pbrdf_cl.compute.dense.outer`, float64): the material and its +-h steps (h = 1e-6 of each
  bound range, one-sided at a bound, as :func:`pbrdf_cl.fitting.common.fd_jacobian`) are extra
  parameter sets of ONE evaluation over every candidate geometry.
* With ``instrument=`` (:mod:`pbrdf_cl.analysis.instruments`) a geometry's rows are an
  instrument's channels (normalised Stokes components under source states, normalised Mueller
  elements, the DOP) divided by its noise: their derivatives come from ONE
  :func:`~pbrdf_cl.compute.dense.outer` of "mueller" over the same parameter sets, the channels'
  values from those matrices by arithmetic (:func:`instrument_jacobians`); the unpolarised DOP
  keeps its own rows above.  The geometries are chosen for the first instrument (its rows
  compressed to their QR factor where they outnumber the parameters), and every instrument is
  compared at the chosen and the reference geometries.
* The Fisher information of a set is the sum of its rows' J^T J; the covariance its
  pseudo-inverse (as ``fitting.uncertainty._covariance``); the predicted interval of parameter j is
  ``x_j +- 1.96 se_j`` clipped to the bounds, and its width is reported.
* Without intensities the DOP depends on kd and ks only through kd/ks: ks is held at 1 and the
  ``kd`` reported is the ratio kd/ks (as :func:`pbrdf_cl.fit` does).  With intensities ks is
  free and ``kd`` is still the ratio kd/ks (``fitting.stages.Residuals._with``).  With ks fixed
  (``fixed={"ks": v}``) ``kd`` is the absolute kd, as in :func:`pbrdf_cl.fit`.

How the geometries are chosen: greedy forward selection (a weak Gaussian prior of standard
deviation one bound range per parameter only while the information is singular), then Fedorov
exchange (the best swap of a chosen geometry for a candidate, until no swap improves).  Each
step evaluates every candidate (and every material of a box) at once by rank-r updates of the
covariance (Sherman-Morrison-Woodbury).  Criterion "A" (default): the sum over the target
parameters of variance / (bound range)^2; "D": log det of the target parameters' covariance
(D-optimal when the target is every free parameter; Ds-optimal otherwise).

Assumptions: Gaussian noise of known standard deviation, the model correct, and the material
close enough to the hypothesis that the linearisation holds (for a box: the criterion is the
mean over ``materials`` materials drawn from it).
"""
from __future__ import annotations

import numbers
import time
from dataclasses import dataclass

import numpy as np

from ..compute.dense import DEFAULT_BUDGET, PARAMETERS, outer
from ..device.engine import resolve_engine
from ..fitting.common import X_RESOLUTION, fd_jacobian
from ..fitting.setup import F00_REL_STD, FitSetup
from ..model import reference as _reference
from .design_result import GEOMETRY, DesignResult
from .instruments import instruments as instruments_of
from .sensitivity import check_fixed, check_geometry, check_ranges, geometry_list

CRITERIA = ("A", "D")
#: The paper's geometry (45# steel at 435 nm): theta_i 30/40/50 x theta_r 20..65 step 5, in plane.
PAPER_GEOMETRY = {"theta_i": [30.0, 40.0, 50.0], "theta_r": "20:65:5", "phi": 180.0}
#: The incidence the paper fits alone (its Fig. 5 and the fitted parameters).
PAPER_INCIDENCE = 40.0
DEFAULT_CANDIDATES = {"theta_i": "10:80:5", "theta_r": "0:85:5", "phi": 180.0}
#: The paper's fit at theta_i = 40 (SPEC.md "Numbers from the paper").
PAPER_MATERIAL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
Z95 = 1.959963984540054  # scipy.stats.norm.ppf(0.975)
#: Prior precision (in parameters scaled by their bound ranges) of the greedy start while singular.
PRIOR = 1.0
#: Scaled information counts as non-singular once its condition number is below this; directions
#: whose information is below 1/SINGULAR_COND of the largest are the data's null space.
SINGULAR_COND = 1e12
#: A parameter whose axis has a share of the null space above this (rounding of the eigenvectors
#: lies far below) gets an infinite standard error.
NULL_SHARE_NEGLIGIBLE = 1e-6
#: A predicted interval within this fraction of its whole bound range counts as spanning them:
#: the parameter is undetermined.
UNDETERMINED_RTOL = 1e-9
MAX_SWAPS_PER_POINT = 20


# ----------------------------------------------------------------------------------- inputs

#: A DOP noise above this draws a warning (a tenth of the DOP's range: a percentage given as a number?).
LARGE_NOISE = 0.1


def _positive(name, v):
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real) or not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive number, got {v!r}")
    return float(v)


def check_points(where, spec, default_phi=180.0, check_count=None):
    """A candidate or reference set: a geometry dict (the product grid of
    :func:`pbrdf_cl.analysis.sensitivity.check_geometry`) or explicit points, a sequence of
    (theta_i, theta_r) or (theta_i, theta_r, phi) or an (N, 2|3) array.  Returns
    (dict theta_i/theta_r/phi -> 1-d arrays, grid axes dict or None).  ``check_count``: called
    with the number of points before their arrays are made (a size check)."""
    from ..compute import pointwise
    if isinstance(spec, dict):
        axes, scalars = check_geometry(spec, where)
        if check_count is not None:
            check_count(int(np.prod([a.size for a in axes.values()], dtype=np.int64)))
        geo, shape = geometry_list(axes, scalars)
        return geo, axes
    try:
        a = np.asarray(spec, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: give a dict of theta_i, theta_r (and phi) -> angles, or a list of "
                         f"(theta_i, theta_r[, phi]) points in degrees; got {spec!r:.80}") from None
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] == 0:
        raise ValueError(f"{where}: points must be an (N, 2) or (N, 3) array of (theta_i, theta_r[, phi]) "
                         f"in degrees, got shape {a.shape}")
    if check_count is not None:
        check_count(a.shape[0])
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: the points must be finite numbers")
    geo = {"theta_i": a[:, 0].copy(), "theta_r": a[:, 1].copy(),
           "phi": a[:, 2].copy() if a.shape[1] == 3 else np.full(a.shape[0], default_phi)}
    for n in GEOMETRY:
        try:
            pointwise.check_values(n, geo[n])
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    pointwise.check_degrees(geo["theta_i"], geo["theta_r"], where=f"{where}: ")
    return geo, None


def _materials(params, fixed, count, seed):
    """The hypothesised material(s): (dict name -> (S,) arrays over the six parameters, ranges)."""
    if not isinstance(params, dict) or not params:
        raise ValueError("params: give a dict of n, k, sigma (and kd, c, ks) -> a value, or -> (low, high) "
                         "ranges for a box of materials")
    ranged = {n: v for n, v in params.items() if isinstance(v, (tuple, list, dict))}
    scalars = {n: v for n, v in params.items() if n not in ranged}
    fixed = dict(fixed or {})
    for n, v in fixed.items():
        if n in ranged:
            raise ValueError(f"fixed: {n!r} has a range in params and a fixed value; give one")
        if n in scalars:
            try:
                same = float(scalars[n]) == float(v)
            except (TypeError, ValueError):
                same = False
            if not same:
                raise ValueError(f"fixed: {n} = {v!r} differs from params[{n!r}] = {scalars[n]!r}; give one")
    for n in list(ranged):
        if isinstance(ranged[n], (tuple, list)) and len(ranged[n]) == 1:
            scalars[n] = ranged.pop(n)[0]
    rngs = check_ranges(ranged, "params") if ranged else ()
    vals = check_fixed({**scalars, **fixed}, {r.name for r in rngs}, "params")
    if not rngs:
        return {n: np.array([vals[n]]) for n in PARAMETERS}, rngs
    d = len(rngs)
    rng = np.random.default_rng(seed)  # a seeded Latin hypercube: each range cut into count strata
    u = (np.stack([rng.permutation(count) for _ in range(d)], axis=1) + rng.random((count, d))) / count
    lo = np.array([r.bounds[0] for r in rngs])
    hi = np.array([r.bounds[1] for r in rngs])
    X = lo + u * (hi - lo)
    out = {n: np.full(count, vals[n]) for n in vals}
    for j, r in enumerate(rngs):
        out[r.name] = r.values(X[:, j])
    return {n: out[n] for n in PARAMETERS}, rngs


# -------------------------------------------------------------------------------- Jacobians

def _x_of(mat, names):
    """Material values -> the fit's coordinates: kd as the ratio kd/ks (DOP depends on it alone),
    or as itself where ks is fixed (not among ``names``), as :func:`pbrdf_cl.fit` has it."""
    x = {n: np.asarray(mat[n], float) for n in PARAMETERS}
    if "ks" in names:
        x["kd"] = x["kd"] / x["ks"]
    return np.stack([x[n] for n in names], axis=-1)


def _model_of(X, names, base):
    """Fit coordinates (S, d) -> the model's six parameter arrays (kd = ratio * ks where kd is a
    coordinate; a fixed kd is the material's own, absolute)."""
    p = {n: np.asarray(base[n], float).copy() for n in PARAMETERS}
    for j, n in enumerate(names):
        p[n] = X[:, j]
    if "kd" in names and "ks" in names:
        p["kd"] = p["kd"] * p["ks"]
    return p


def jacobians(eng, geometry, mat, names, lo, hi, shadowing="paper"):
    """Central-difference derivatives of DOP and F00 at every geometry for every material, in the
    fit's coordinates ``names`` (any of n, k, sigma, kd = kd/ks, c, ks): ``fitting.common.fd_jacobian``'s
    central scheme, the materials and all their steps the parameter sets of one
    :func:`pbrdf_cl.compute.dense.outer` call per quantity (float64).

    Returns (dop, f00, J_dop, J_f00): values (M, G) and derivatives (M, G, d)."""
    X = _x_of(mat, names)  # (M, d)
    M = X.shape[0]

    def rows_of(quantity):
        def rows(S):  # parameter vectors (M * steps, d), material by material -> values (M * steps, G)
            basep = {n: np.repeat(np.asarray(mat[n], float), S.shape[0] // M) for n in PARAMETERS}
            return outer(eng, quantity, geometry, _model_of(S, names, basep), "float64", shadowing).T
        return rows
    out = []
    for quantity in ("dop", "brdf"):
        Y, J = fd_jacobian(rows_of(quantity), X, lo, hi, "central")  # (M, G), (M, d, G)
        out += [Y, J.transpose(0, 2, 1)]
    return out[0], out[2], out[1], out[3]


def whitened_rows(dop_J, f00, f00_J, noise, intensity_noise, intensity):
    """Rows (M, G, r, d): dDOP/dx / noise, and with ``intensity`` dF00/dx / (intensity_noise F00)."""
    rows = [dop_J / noise]
    if intensity:
        rows.append(f00_J / (intensity_noise * f00)[..., None])
    return np.stack(rows, axis=2)


#: Memory for one block of geometries of :func:`instrument_jacobians` (Mueller matrices and channel terms).
INSTRUMENT_BLOCK_BYTES = 64 * 2**20


def instrument_jacobians(eng, geometry, mat, names, lo, hi, instruments, shadowing="paper"):
    """Central-difference derivatives of every instrument's channels at every geometry for every
    material, in the fit's coordinates ``names`` (as :func:`jacobians`): the materials and all
    their steps the parameter sets of :func:`pbrdf_cl.compute.dense.outer` of "mueller" (float64,
    geometries in blocks), each instrument's channel values from those Mueller matrices by
    :meth:`Instrument.values <pbrdf_cl.analysis.instruments.Instrument.values>` (arithmetic on the
    model's output: :meth:`~pbrdf_cl.model.measurables.Channels.values_of`).

    Returns (values, J): per instrument, values (M, G, c) and derivatives (M, G, c, d)."""
    X = _x_of(mat, names)
    M, d = X.shape
    G = geometry["theta_i"].size
    sizes = [i.per_geometry for i in instruments]

    def rows(S):  # parameter vectors (B, d) -> every instrument's channels (B, G * sum(c))
        basep = {n: np.repeat(np.asarray(mat[n], float), S.shape[0] // M) for n in PARAMETERS}
        params = _model_of(S, names, basep)
        out = np.empty((S.shape[0], G, sum(sizes)))
        per = max(1, INSTRUMENT_BLOCK_BYTES // (S.shape[0] * 8 * (16 + 8 * max(sizes))))
        for g0 in range(0, G, per):
            g1 = min(G, g0 + per)
            F = outer(eng, "mueller", geometry, params, "float64", shadowing, rows=(g0, g1))  # (g, B, 4, 4)
            out[:, g0:g1] = np.concatenate([i.values(F) for i in instruments], axis=-1).transpose(1, 0, 2)
        return out.reshape(S.shape[0], -1)
    Y, J = fd_jacobian(rows, X, lo, hi, "central")  # (M, G * C), (M, d, G * C)
    Y, J = Y.reshape(M, G, -1), J.reshape(M, d, G, -1).transpose(0, 2, 3, 1)
    edges = np.cumsum([0] + sizes)
    return ([Y[:, :, a:b] for a, b in zip(edges[:-1], edges[1:])],
            [J[:, :, a:b] for a, b in zip(edges[:-1], edges[1:])])


def instrument_rows(J, f00, f00_J, noise, intensity_noise, intensity):
    """Rows (M, G, c (+1), d): an instrument's channel derivatives (M, G, c, d) / its noise, and
    with ``intensity`` the F00 row of :func:`whitened_rows` after them."""
    rows = J / noise
    if intensity:
        rows = np.concatenate([rows, whitened_rows(f00_J, f00, f00_J, 1.0, intensity_noise, True)[:, :, 1:]], axis=2)
    return rows


def predicted_widths(rows, x, lo, hi):
    """Predicted 95% interval widths of one material from its rows (K, d) at the measurements.

    The covariance is the pseudo-inverse of J^T J (as ``fitting.uncertainty._covariance``), taken in
    parameters scaled by their bound ranges, where the directions whose information is below
    1/:data:`SINGULAR_COND` of the largest are the data's null space: combinations of the
    parameters that the measurements do not constrain at all (a Jacobian column that is zero,
    such as sigma's and c's at kd = 0, or one in the span of the others).  The pseudo-inverse
    gives them no variance; here each parameter's half-width is x +- 1.96 se (never narrower than
    the optimiser's resolution) plus its share of that null space times its bound range (a
    parameter along the null space alone moves freely over its bounds), clipped to the bounds.

    Returns (widths (d,), se (d,), undetermined (d,) bool): ``undetermined`` where the interval
    spans the whole bounds (the data do not determine the parameter within them); ``se`` is
    infinite for a parameter with a share of the null space."""
    span = hi - lo
    Js = rows * span[None, :]
    w, V = np.linalg.eigh(Js.T @ Js)
    null = w <= max(float(w[-1]), 0.0) / SINGULAR_COND
    keep = ~null
    cov = ((V[:, keep] / w[keep]) @ V[:, keep].T) * span[:, None] * span[None, :]
    share = np.sqrt(np.sum(V[:, null] ** 2, axis=1))  # |projection of each parameter's axis on the null space|
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    se = np.where(share > NULL_SHARE_NEGLIGIBLE, np.inf, se)
    half = np.maximum(Z95 * np.sqrt(np.clip(np.diag(cov), 0, None)), X_RESOLUTION * span) + share * span
    widths = np.minimum(hi, x + half) - np.maximum(lo, x - half)
    undetermined = widths >= span * (1.0 - UNDETERMINED_RTOL)
    return np.where(undetermined, span, widths), se, undetermined


# ----------------------------------------------------------------------------------- search

class _Criterion:
    """Criterion A or D of covariances C (M, d, d) in scaled parameters, and its change by adding
    rows (with signs) to the information, for many candidates at once."""

    def __init__(self, kind, target_idx):
        self.kind, self.t = kind, np.asarray(target_idx)

    def target_block(self, C):
        """The target parameters' block (M, t, t) of covariances C (M, d, d)."""
        return C[:, self.t[:, None], self.t[None, :]]

    def value(self, C):
        """The criterion of covariances C (M, d, d): (M,)."""
        Ct = self.target_block(C)
        if self.kind == "A":
            return np.trace(Ct, axis1=1, axis2=2)
        sign, ld = np.linalg.slogdet(Ct)
        return np.where(sign > 0, ld, np.inf)

    def factor(self, C):
        """R (M, t, t) with Z = (K_T R)(K_T R)^T the criterion's quadratic form."""
        if self.kind == "A":
            return None
        Ct = self.target_block(C)
        return np.linalg.cholesky(np.linalg.inv(Ct))

    def forms(self, C, R, U):
        """The quadratic forms of rows U (M, N, m, d): V = U C U^T and Z = (U C)_T G (U C)_T^T
        (G the identity for A, the inverse target covariance for D), and L = (U C)_T R."""
        K = np.matmul(U, C[:, None])
        L = K[..., self.t]
        if R is not None:
            L = np.matmul(L, R[:, None])
        return np.matmul(K, np.swapaxes(U, -1, -2)), np.matmul(L, np.swapaxes(L, -1, -2)), L

    def change(self, C, R, U, signs):
        """Change of the criterion (M, N) when rows U (M, N, m, d) are added (signs +1) or removed
        (-1) from the information of covariance C; +inf where the result is singular or invalid."""
        V, Z, _ = self.forms(C, R, U)
        return self.change_of(V, Z, signs)

    def change_of(self, V, Z, signs):
        """:meth:`change` from the forms V, Z (M, N, m, m) (Woodbury: the new covariance is
        C - C U^T S^-1 U C with S = diag(1/signs) + V, so the A criterion falls by trace(S^-1 Z)
        and log det of the target covariance changes by log det(S - Z) - log det S); closed forms
        for m = 1 and 2, batched linear algebra otherwise."""
        signs = np.asarray(signs, float)
        m = signs.size
        # the new information is positive definite iff (-1)^(removed rows) det S > 0
        parity = 1.0 if np.sum(signs < 0) % 2 == 0 else -1.0
        with np.errstate(all="ignore"):
            if m == 1:
                S, z = V[..., 0, 0] + 1.0 / signs[0], Z[..., 0, 0]
                det, scale = S, np.abs(S)
                out = -z / S if self.kind == "A" else np.log((S - z) / S)
            elif m == 2:
                s11, s12, s22 = V[..., 0, 0] + 1.0 / signs[0], V[..., 0, 1], V[..., 1, 1] + 1.0 / signs[1]
                z11, z12, z22 = Z[..., 0, 0], Z[..., 0, 1], Z[..., 1, 1]
                det = s11 * s22 - s12 * s12
                scale = np.abs(s11 * s22) + s12 * s12
                if self.kind == "A":
                    out = -(s22 * z11 - 2 * s12 * z12 + s11 * z22) / det
                else:
                    out = np.log(((s11 - z11) * (s22 - z22) - (s12 - z12) ** 2) / det)
            else:
                S = V + np.diag(1.0 / signs)
                det = np.linalg.det(S)
                scale = np.prod(np.abs(np.diagonal(S, axis1=-2, axis2=-1)), axis=-1)
                if self.kind == "A":
                    ok = parity * det > 0
                    Ssafe = np.where(ok[..., None, None], S, np.eye(m))
                    out = -np.trace(np.linalg.solve(Ssafe, Z), axis1=-2, axis2=-1)
                else:
                    sn, ld = np.linalg.slogdet(S - Z)
                    sd, ldS = np.linalg.slogdet(S)
                    out = np.where(sn * sd > 0, ld - ldS, np.nan)
            bad = ~np.isfinite(out) | ~(parity * det > 1e-12 * scale)
        return np.where(bad, np.inf, out)


def _det(X):
    """Determinants of (..., r, r) arrays, closed forms for r = 1, 2."""
    r = X.shape[-1]
    if r == 1:
        return X[..., 0, 0]
    if r == 2:
        return X[..., 0, 0] * X[..., 1, 1] - X[..., 0, 1] * X[..., 1, 0]
    return np.linalg.det(X)


def _inv_small(X):
    """Inverses of (..., r, r) arrays, closed forms for r = 1, 2 (NaN/inf where singular)."""
    r = X.shape[-1]
    with np.errstate(all="ignore"):
        if r == 1:
            return 1.0 / X
        if r == 2:
            d = _det(X)[..., None, None]
            out = np.empty_like(X)
            out[..., 0, 0], out[..., 1, 1] = X[..., 1, 1], X[..., 0, 0]
            out[..., 0, 1], out[..., 1, 0] = -X[..., 0, 1], -X[..., 1, 0]
            return out / d
    return np.linalg.inv(X)


def _swap_change(kind, Vaa, Zaa, La, Vci, Zci, ci):
    """Change of the criterion (M, N) when chosen geometry ``ci`` is swapped for each candidate:
    the Woodbury update by [a_c; a_i] with signs (+1, -1), its 2r x 2r matrices eliminated
    block-wise through the removed geometry's r x r block (closed forms, no batched LAPACK).
    ``Vaa``, ``Zaa`` (M, N, r, r), ``La`` (M, N, r, t): the candidates' forms; ``Vci``, ``Zci``
    (M, N, r, r): their cross forms with ``ci``.  +inf where the swap leaves the information
    singular, or where removing ``ci`` alone would."""
    r = Vaa.shape[-1]
    eye = np.eye(r)
    swapT = lambda X: np.swapaxes(X, -1, -2)  # noqa: E731
    with np.errstate(all="ignore"):
        Scc, Sci, Sii = Vaa + eye, Vci, (Vaa[:, ci] - eye)[:, None]  # Sii (M, 1, r, r)
        Sii_inv = _inv_small(Sii)
        T = Scc - Sci @ Sii_inv @ swapT(Sci)
        detS = _det(Sii) * _det(T)
        parity = 1.0 if r % 2 == 0 else -1.0
        if kind == "A":
            Li = La[:, ci][:, None]  # (M, 1, r, t)
            Wi = Sii_inv @ Li
            E = La - Sci @ Wi
            out = -(np.sum(E * (_inv_small(T) @ E), axis=(-2, -1)) + np.sum(Li * Wi, axis=(-2, -1)))
        else:
            Xcc, Xci, Xii = Scc - Zaa, Sci - Zci, Sii - Zaa[:, ci][:, None]
            detX = _det(Xii) * _det(Xcc - Xci @ _inv_small(Xii) @ swapT(Xci))
            out = np.log(detX / detS)
        scale = np.abs(_det(Sii)) * np.prod(np.abs(np.diagonal(T, axis1=-2, axis2=-1)), axis=-1)
        bad = ~np.isfinite(out) | ~(parity * detS > 1e-12 * scale)
    return np.where(bad, np.inf, out)


def _pinv(Minfo):
    """Covariances: the pseudo-inverses of informations (M, d, d) (no prior)."""
    return np.linalg.pinv(Minfo, rcond=1e-15, hermitian=True)


def _final_value(crit, Minfo):
    """The mean criterion of informations (M, d, d) from their pseudo-inverse (no prior)."""
    return float(np.mean(crit.value(_pinv(Minfo))))


def _outer(a):
    """The informations (M, d, d) of one geometry's rows (M, r, d)."""
    return np.einsum("mrd,mre->mde", a, a)


def select(A, n, crit, available, repeats=False, exchange=True):
    """Greedy forward selection then Fedorov exchange over candidate rows ``A`` (M, N, r, d) (scaled
    parameters): the indices of the ``n`` chosen, the greedy choice, the number of swaps and which
    materials' information stayed singular (those keep the weak prior throughout)."""
    M, N, r, d = A.shape
    eye = np.eye(d)[None]
    Minfo = np.zeros((M, d, d))
    chosen = []
    taken = np.zeros(N, bool)
    prior = np.ones(M, bool)

    def cov(Mi):
        return np.linalg.inv(Mi + PRIOR * eye * prior[:, None, None])

    def mean_value(Mi):
        return float(np.mean(crit.value(cov(Mi))))

    for step in range(n):
        C = cov(Minfo)
        gain = crit.change(C, crit.factor(C), A, np.ones(r)).mean(axis=0)
        gain = np.where(available & (repeats | ~taken), gain, np.inf)
        best = int(np.argmin(gain))
        if not np.isfinite(gain[best]):
            raise ValueError("candidates: no candidate adds information (every Jacobian row is zero or "
                             "non-finite at these geometries)")
        chosen.append(best)
        taken[best] = True
        Minfo = Minfo + _outer(A[:, best])
        if prior.any() and step + 1 >= d:
            prior = prior & _singular(Minfo)
    greedy = list(chosen)
    swaps = 0
    if not exchange:
        return chosen, greedy, swaps, prior
    f = mean_value(Minfo)
    for _ in range(MAX_SWAPS_PER_POINT * n):
        C = cov(Minfo)
        R = crit.factor(C)
        best = (0.0, None, None)
        ok0 = available & (repeats | ~taken)
        Vaa, Zaa, La = crit.forms(C, R, A)  # the candidates' own forms, shared by every swap
        KA = np.matmul(A, C[:, None])
        for p, ci in enumerate(chosen):
            # the cross forms between every candidate and the chosen geometry ci
            Vci = np.matmul(KA, np.swapaxes(A[:, ci], -1, -2)[:, None])
            Zci = np.matmul(La, np.swapaxes(La[:, ci], -1, -2)[:, None])
            delta = _swap_change(crit.kind, Vaa, Zaa, La, Vci, Zci, ci).mean(axis=0)
            ok = ok0.copy()
            ok[ci] = False
            delta = np.where(ok, delta, np.inf)
            c = int(np.argmin(delta))
            if delta[c] < best[0]:
                best = (float(delta[c]), p, c)
        if best[1] is None or best[0] > -1e-9 * max(1.0, abs(f)):
            break
        _, p, c = best
        old = chosen[p]
        Mnew = Minfo + _outer(A[:, c]) - _outer(A[:, old])
        fnew = mean_value(Mnew)
        if not fnew < f:  # the update's prediction not confirmed (round-off): stop
            break
        Minfo, f = Mnew, fnew
        chosen[p] = c
        taken[old] = old in chosen
        taken[c] = True
        swaps += 1
    return chosen, greedy, swaps, prior


def _singular(Minfo):
    """Per material: is the (scaled) information numerically singular?"""
    w = np.linalg.eigvalsh(Minfo)
    return w[:, 0] <= w[:, -1] / SINGULAR_COND


# ----------------------------------------------------------------------------------- design

@dataclass
class _Problem:
    """The checked inputs of :func:`design`: the options, the fit's ``setup`` (the
    :class:`~pbrdf_cl.fitting.setup.FitSetup` of the six-parameter model: bounds, fixed values,
    free parameters), the material(s) ``mat`` and their fit coordinates ``X`` (M, len(names)), and
    the candidate and reference geometries."""
    criterion: str
    noise: float
    intensity_noise: float
    intensity: bool
    n: int
    repeats: bool
    target: tuple
    setup: FitSetup
    mat: dict
    rngs: tuple
    X: np.ndarray
    cand: dict
    cand_axes: dict | None
    ref: dict
    ref_given: bool
    instruments: list  # of instruments.Instrument; empty: the DOP with ``noise`` (the default)

    @property
    def fx(self):
        """The fixed values."""
        return self.setup.fixed

    @property
    def free5(self):
        """The free parameters besides ks."""
        return self.setup.free

    @property
    def names(self):
        """The Jacobians' coordinates (:func:`_coordinates`)."""
        return _coordinates(self.setup, self.intensity)[0]

    @property
    def free(self):
        """The fit's free parameters (:func:`_coordinates`)."""
        return _coordinates(self.setup, self.intensity)[1]

    @property
    def lo(self):
        """Lower bounds of :attr:`names`."""
        return self.setup.bounds_of(self.names)[0]

    @property
    def hi(self):
        """Upper bounds of :attr:`names`."""
        return self.setup.bounds_of(self.names)[1]

    @property
    def f00_usable(self):
        """Whether the fit would use an intensity column (neither ks nor kd fixed)."""
        return self.setup.fits_intensity(True)


def _check_options(criterion, noise, intensity_noise, intensity, materials, shadowing):
    """Check the scalar options of :func:`design`; returns (noise, intensity_noise) as floats."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be 'A' or 'D', got {criterion!r}")
    noise = _positive("noise", noise)
    if noise >= 1.0:
        raise ValueError(f"noise must be below 1, the DOP's whole range (0 to 1), got {noise:g}: it is the standard "
                         "deviation of one DOP measurement (a percentage? 0.5% is 0.005)")
    if noise > LARGE_NOISE:
        import warnings

        from ..errors import DataWarning
        warnings.warn(f"noise {noise:g} is more than {LARGE_NOISE:g} of the DOP's range (0 to 1): is it a percentage? "
                      "(0.5% is 0.005)", DataWarning, stacklevel=4)
    intensity_noise = _positive("intensity_noise", intensity_noise)
    if not isinstance(intensity, (bool, np.bool_)):
        raise ValueError(f"intensity must be True or False, got {intensity!r}")
    if isinstance(materials, bool) or not isinstance(materials, (int, np.integer)) or materials < 1:
        raise ValueError(f"materials must be a positive integer, got {materials!r}")
    if shadowing not in _reference.SHADOWING:
        raise ValueError(f"shadowing must be one of {sorted(_reference.SHADOWING)}, got {shadowing!r}")
    return noise, intensity_noise


def _coordinates(setup, intensity):
    """(names, free): the Jacobians' coordinates (the setup's free parameters and ks unless it is
    fixed: kd is then kd/ks) and the fit's free parameters (ks only with intensities)."""
    free5 = setup.free
    return free5 + (["ks"] if "ks" not in setup.fixed else []), free5 + (["ks"] if intensity else [])


def _fit_setup(bounds, fixed, intensity):
    """The fit's setup (:class:`~pbrdf_cl.fitting.setup.FitSetup` of the six-parameter model, ks's
    bounds checked too), refusing intensities where a fixed ks or kd makes the fit ignore them."""
    setup = FitSetup.check("six-param", bounds, fixed, need_free=False)
    fx = setup.fixed
    if intensity and ("ks" in fx or "kd" in fx):
        raise ValueError(f"intensity: with {'ks' if 'ks' in fx else 'kd'} fixed the fit ignores intensities "
                         "(it separates ks and kd only with both free); drop it from fixed or intensity=False")
    return setup


def _check_target(target, free, fx):
    """The target parameters as a tuple: each a free parameter, named once."""
    if isinstance(target, str):
        target = (target,)
    target = tuple(target)
    if not target:
        raise ValueError("target: give at least one parameter, e.g. ('n', 'k')")
    for t in target:
        if t not in PARAMETERS:
            raise ValueError(f"target: unknown parameter {t!r}; parameters are {', '.join(PARAMETERS)}")
        if t not in free:
            why = ("is fixed" if t in fx else
                   "is free only with intensity=True (DOP depends on kd/ks alone)" if t == "ks" else "is not free")
            raise ValueError(f"target: {t!r} {why}; free parameters are {', '.join(free)}")
    if len(set(target)) != len(target):
        raise ValueError(f"target: {target!r} names a parameter twice")
    return target


def _check_count(n_measurements, free):
    """The number of measurements as an int, more than the free parameters."""
    if isinstance(n_measurements, bool) or not isinstance(n_measurements, (int, np.integer)):
        raise ValueError(f"n_measurements must be an integer, got {n_measurements!r}")
    n = int(n_measurements)
    if n <= len(free):
        raise ValueError(f"n_measurements: {n} is too few for {len(free)} free parameters ({', '.join(free)}); "
                         f"the fit needs at least {len(free) + 1}")
    return n


def _fix_materials(mat, fx, names, lo, hi):
    """Set the fixed parameters of the material(s) ``mat`` (in place) and check them inside the
    bounds; returns their fit coordinates (M, len(names))."""
    for name in PARAMETERS:
        if name in fx:
            mat[name] = np.full_like(mat[name], fx[name])
    X = _x_of(mat, names)
    for j, name in enumerate(names):
        outside = (X[:, j] < lo[j]) | (X[:, j] > hi[j])
        if np.any(outside):
            v = X[int(np.argmax(outside)), j]
            label = "kd/ks" if name == "kd" and "ks" in names else name
            raise ValueError(f"params: {label} = {v:g} lies outside the fit's bounds ({lo[j]:g}, {hi[j]:g}); "
                             "widen bounds or change params")
    return X


def design_bytes(candidates, materials, rows, free):
    """An estimate of the memory of a design over ``candidates`` geometries for ``materials``
    materials, ``rows`` whitened rows per geometry (1: the DOP; an instrument's channels; + 1 with
    intensities) and ``free`` fitted coordinates: the Jacobians' values and steps, the rows and the
    search's forms, about 8 (256 + 4 rows free) bytes per candidate and material (measured peak
    RSS: 2.1 KiB per candidate for one material and the DOP, 26 KiB for 16, 2.6 KiB with the
    Mueller matrix's 15 channels)."""
    return int(candidates) * int(materials) * 8 * (256 + 4 * int(rows) * int(free))


def _size_check(memory_budget, materials, rows, free):
    """The check of the candidates' count against ``memory_budget`` (:func:`design_bytes`)."""
    from .. import sizes

    def check(count):
        plural = "s" if materials > 1 else ""
        sizes.check_budget(design_bytes(count, materials, rows, free),
                           f"design: {count} candidate geometries x {materials} material{plural}", memory_budget,
                           "give fewer candidates (a coarser grid)" + (", fewer materials" if materials > 1 else ""),
                           "raise memory_budget (pbrdf-cl design --memory-budget)")
    return check


def _problem(params, candidates, noise, n_measurements, target, intensity, fixed, criterion, reference,
             intensity_noise, bounds, materials, repeats, seed, shadowing, instrument=None,
             memory_budget=DEFAULT_BUDGET):
    """Check every input of :func:`design` (in the order its errors are reported) into a :class:`_Problem`."""
    from ..ranges import parse_bytes
    memory_budget = parse_bytes("memory_budget", memory_budget)
    noise, intensity_noise = _check_options(criterion, noise, intensity_noise, intensity, materials, shadowing)
    inst = [] if instrument is None else instruments_of(instrument, noise)
    setup = _fit_setup(bounds, dict(fixed or {}), intensity)  # first: the same refusals as fit's
    mat, rngs = _materials(params, fixed, int(materials), seed)
    fx = setup.fixed
    names, free = _coordinates(setup, intensity)
    target = _check_target(target, free, fx)
    n = _check_count(n_measurements, free)
    rows = (inst[0].per_geometry if inst else 1) + bool(intensity)
    cand, cand_axes = check_points("candidates", DEFAULT_CANDIDATES if candidates is None else candidates,
                                   check_count=_size_check(memory_budget, mat["n"].size, rows, len(names)))
    ref, _ = check_points("reference", PAPER_GEOMETRY if reference is None else reference)
    N = cand["theta_i"].size
    if not repeats and n > N:
        raise ValueError(f"n_measurements: {n} is more than the {N} candidate geometries (repeats=False)")
    X = _fix_materials(mat, fx, names, *setup.bounds_of(names))
    return _Problem(criterion, noise, intensity_noise, intensity, n, repeats, target, setup, mat, rngs, X, cand,
                    cand_axes, ref, reference is not None, inst)


class _Linearisation:
    """The derivatives of DOP and F00 at the candidates then the reference geometries (as
    :func:`jacobians`), and from them the whitened rows and the predicted widths of any set of
    geometries, with or without the intensity rows."""

    def __init__(self, p, eng, shadowing):
        self.p = p
        geo = {g: np.concatenate([p.cand[g], p.ref[g]]) for g in GEOMETRY}
        _, self.f00, self.Jd, self.Jf = jacobians(eng, geo, p.mat, p.names, p.lo, p.hi, shadowing)
        polar = [i for i in p.instruments if not i.unpolarised_dop]  # the DOP's rows are the ones above
        self.Ji = {}
        if polar:
            J = instrument_jacobians(eng, geo, p.mat, p.names, p.lo, p.hi, polar, shadowing)[1]
            self.Ji = {i.name: j for i, j in zip(polar, J)}

    def columns(self, with_int):
        """The parameters of a fit with or without intensities and their columns in the Jacobians."""
        names = self.p.free5 + (["ks"] if with_int else [])
        return names, np.array([self.p.names.index(x) for x in names])

    def rows(self, with_int, scaled, ins=None):
        """Whitened rows (M, G, r, d) of instrument ``ins`` (default the design's: the first
        instrument, or the DOP); ``scaled``: in parameters scaled by their bound ranges."""
        p = self.p
        ins = ins or (p.instruments[0] if p.instruments else None)
        _, cols = self.columns(with_int)
        if ins is None or ins.unpolarised_dop:
            noise = p.noise if ins is None else ins.noise
            R = whitened_rows(self.Jd[..., cols], self.f00, self.Jf[..., cols], noise, p.intensity_noise, with_int)
        else:
            R = instrument_rows(self.Ji[ins.name][..., cols], self.f00, self.Jf[..., cols], ins.noise,
                                p.intensity_noise, with_int)
        return R * (p.hi - p.lo)[cols] if scaled else R

    def widths(self, idx, with_int, ins=None):
        """Median widths over the materials, the per-material widths of a set of indices, the
        parameters undetermined by the set (their median width spans the whole bounds) and the
        median standard errors (infinite along the data's null space)."""
        p = self.p
        names, cols = self.columns(with_int)
        R = _finite(self.rows(with_int, False, ins)[:, idx])
        both = [predicted_widths(R[m].reshape(-1, len(cols)), p.X[m, cols], p.lo[cols], p.hi[cols])[:2]
                for m in range(p.X.shape[0])]
        W = np.stack([w for w, _ in both])
        med, se = np.median(W, axis=0), np.median(np.stack([e for _, e in both]), axis=0)
        span = (p.hi - p.lo)[cols]
        undetermined = [x for j, x in enumerate(names) if med[j] >= span[j] * (1.0 - UNDETERMINED_RTOL)]
        return {x: float(med[j]) for j, x in enumerate(names)}, W, undetermined, dict(zip(names, se.tolist()))


def _finite(A):
    """Rows with their non-finite entries (where the model is undefined) zero."""
    return np.where(np.isfinite(A), A, 0.0)


def _compressed(A):
    """Rows (M, N, r, d) with r > d as the d rows of each geometry's QR factor R: the same
    information (R^T R = A^T A), so that the search's rank-r updates stay small and their
    determinant test meaningful (a geometry with a non-finite row stays non-finite)."""
    if A.shape[2] <= A.shape[3]:
        return A
    ok = np.all(np.isfinite(A), axis=(2, 3))[..., None, None]
    return np.where(ok, np.linalg.qr(np.where(ok, A, 0.0), mode="r"), np.nan)


def _information(A):
    """The informations (M, d, d) of rows (M, K, r, d): the sum of their J^T J."""
    return np.einsum("mkrd,mkre->mde", A, A)


def _select_design(p, A, crit):
    """Choose the design among the candidates' rows ``A`` (M, N, r, d) (scaled parameters): returns
    (the candidates' finite rows, which candidates are usable, then :func:`select`'s chosen,
    greedy, swaps and singular)."""
    available = np.all(np.isfinite(A), axis=(0, 2, 3)) & np.any(A != 0, axis=(0, 2, 3))
    Ac = _finite(A)
    if not p.repeats and int(available.sum()) < p.n:
        raise ValueError(f"n_measurements: {p.n} is more than the {int(available.sum())} candidate geometries "
                         "where the model is defined (repeats=False)")
    return (Ac, available) + select(Ac, p.n, crit, available, bool(p.repeats))


def _information_map(p, crit, Ac, available, Mfin):
    """Each candidate's value at the final design of information ``Mfin``: what one more
    measurement there would gain (shaped as the candidate grid; NaN where unusable).  Returns
    (map, its axes, its label)."""
    Cfin = _pinv(Mfin)
    gain = crit.change(Cfin, crit.factor(Cfin), Ac, np.ones(Ac.shape[2]))
    if p.criterion == "A":
        info = -np.mean(gain / crit.value(Cfin)[:, None], axis=0)
        label = "relative reduction of the A criterion by one more measurement here"
    else:
        info = -np.mean(gain, axis=0)
        label = "reduction of log det of the target covariance by one more measurement here"
    info = np.where(available & np.isfinite(info), info, np.nan)
    if p.cand_axes is None:
        return info, {}, label
    shape = tuple(a.size for a in p.cand_axes.values())
    return info.reshape(shape), dict(p.cand_axes), label


def _comparisons(p, lin, idx_c, idx_r):
    """The predicted widths of the chosen and the reference set, each with the design's rows and
    with the other kind (intensities added or dropped; not added where ks or kd is fixed, since
    the fit then ignores intensities): (comparisons, per-material widths of the chosen set)."""
    other = not p.intensity
    modes = [("", p.intensity, " + F00" if p.intensity else "")]
    if p.f00_usable or not other:
        modes.append(("_other", other, " + F00" if other else ", DOP only"))
    ref_labels = {"": "reference" if p.ref_given else "paper 30/40/50 x 20..65",
                  "_other": "reference" if p.ref_given else "paper"}
    comparisons, W = {}, {}
    for key, with_int, tag in modes:
        w, W[key], u, _ = lin.widths(idx_c, with_int)
        comparisons["chosen" + key] = dict(widths=w, n_points=p.n, description=f"chosen ({p.criterion}){tag}",
                                           undetermined=u)
        w, _, u, _ = lin.widths(idx_r, with_int)
        comparisons["reference" + key] = dict(widths=w, n_points=idx_r.size, description=ref_labels[key] + tag,
                                              undetermined=u)
    return comparisons, W[""]


def _incidence_comparisons(p, lin, crit, A, idx_r):
    """The reference's one incidence alone (the paper's 40 degrees for the paper's set, else the
    middle one) and with the best second incidence of the criterion: comparisons (empty where one
    incidence has too few points)."""
    tag = " + F00" if p.intensity else ""
    incid = np.unique(p.ref["theta_i"])
    first = PAPER_INCIDENCE if (not p.ref_given and PAPER_INCIDENCE in incid) else float(incid[len(incid) // 2])
    one = idx_r[p.ref["theta_i"] == first]
    if one.size <= len(p.free):
        return {}
    w, _, u, _ = lin.widths(one, p.intensity)
    out = {"one_incidence": dict(widths=w, n_points=int(one.size), description=f"ref. theta_i {first:g} alone{tag}",
                                 undetermined=u)}
    best = None
    for second in [v for v in incid if v != first]:
        idx2 = np.concatenate([one, idx_r[p.ref["theta_i"] == second]])
        f2 = _final_value(crit, _information(A[:, idx2]))
        if best is None or f2 < best[0]:
            best = (f2, second, idx2)
    if best is not None:
        w, _, u, _ = lin.widths(best[2], p.intensity)
        out["two_incidences"] = dict(widths=w, n_points=int(best[2].size),
                                     description=f"ref. theta_i {first:g} + {best[1]:g}{tag}", undetermined=u)
    return out


def _instrument_comparisons(p, lin, sets):
    """Every instrument's predicted widths and standard errors at each set of ``sets`` (name ->
    indices), with the design's intensity rows: name -> instrument -> dict(widths, se,
    undetermined, n_points, channels)."""
    out = {}
    for key, idx in sets.items():
        out[key] = {}
        for ins in p.instruments:
            w, _, u, se = lin.widths(idx, p.intensity, ins)
            out[key][ins.name] = dict(widths=w, se=se, undetermined=u, n_points=int(idx.size),
                                      channels=int(idx.size) * ins.per_geometry)
    return out


def _notes(p, comparisons):
    """Sentences on what the design cannot do: the parameters the chosen set leaves undetermined
    (and why, where known), a target among them, and comparisons with F00 left out."""
    notes = []
    und = comparisons["chosen"]["undetermined"]
    if und:
        why = ""
        if np.all(p.mat["kd"] == 0) and any(n in ("sigma", "c") for n in und):
            what = "the DOP" if not p.instruments or p.instruments[0].unpolarised_dop else "a normalised quantity"
            why = (f"; with kd = 0 there is no diffuse term: {what} depends on neither sigma nor c (the specular "
                   "scale cancels), and F00 not on c")
        label = ", ".join("kd/ks" if n == "kd" and "ks" not in p.fx else n for n in und)
        notes.append(f"undetermined by the chosen set: {label} (the predicted 95% interval spans the whole "
                     f"bounds: the data do not determine {'it' if len(und) == 1 else 'them'} within them){why}")
        lost = [t for t in p.target if t in und]
        if lost:
            notes.append(f"the target {', '.join(lost)} cannot be determined at this material by these candidates: "
                         "the choice of geometries does not help it; fix it (fixed=) or change the material or the "
                         "candidates")
    if not p.intensity and not p.f00_usable:
        which = "ks" if "ks" in p.fx else "kd"
        notes.append(f"no comparison with an F00 column: with {which} fixed the fit ignores intensities (it "
                     "separates ks and kd only with both free)")
    return notes


def _subset(geo, idx):
    """Copies of a geometry dict's arrays at indices ``idx`` (all of them for None)."""
    return {g: (geo[g] if idx is None else geo[g][idx]).copy() for g in GEOMETRY}


def design(params, candidates=None, noise=0.005, n_measurements=30, target=("n", "k"), intensity=False, fixed=None,
           *, criterion="A", reference=None, intensity_noise=F00_REL_STD, bounds=None, materials=16,
           repeats=False, seed=0, shadowing="paper", instrument=None, engine=None, backend="auto",
           memory_budget=DEFAULT_BUDGET):
    """Choose the measurement geometries that best determine the target parameters.

    Parameters
    ----------
    params : dict
        The hypothesised material: n, k, sigma (and kd, c, ks; defaults 0, 0, 1) -> a value; or
        any of them -> (low, high) (or (low, high, "log")) for a box of materials, of which
        ``materials`` are drawn (a seeded Latin hypercube) and the criterion
        averaged over them.
    candidates : dict or sequence, optional
        The geometries to choose from (degrees): a dict theta_i, theta_r (, phi) -> a value, a 1-d
        sequence or a range string ("10:80:5", "0:85@18") for their product grid, or explicit
        points, a sequence of (theta_i, theta_r[, phi]) or an (N, 2|3) array.  Default
        theta_i 10..80 and theta_r 0..85 in 5 degree steps, in plane.
    noise : float, default 0.005
        Standard deviation of each DOP measurement; with ``instrument``, of each normalised
        quantity an instrument measures (unless it has its own noise).
    n_measurements : int, default 30
        How many geometries to choose (more than the free parameters).
    target : sequence of str, default ("n", "k")
        The free parameters whose intervals the criterion minimises.
    intensity : bool, default False
        Each geometry also measures F00 with relative standard deviation ``intensity_noise``:
        ks becomes free, and kd is the ratio kd/ks (as :func:`pbrdf_cl.fit` with an f00 column).
    fixed : dict, optional
        Parameters held fixed (known) in the fit: name -> value.
    criterion : {"A", "D"}, default "A"
        "A": the sum over the targets of variance / (bound range)^2; "D": log det of the
        targets' covariance.
    reference : dict or sequence, optional
        A measurement set to compare with (same forms as ``candidates``); default the paper's,
        theta_i 30/40/50 x theta_r 20..65 step 5, in plane.
    intensity_noise : float, default 0.05
        Relative standard deviation of F00 (the fit's assumption without an f00_std column).
    bounds : dict, optional
        The fit's bounds (name -> (low, high)); defaults those of :func:`pbrdf_cl.fit`.
    materials : int, default 16
        Materials drawn from a box.
    repeats : bool, default False
        Allow a geometry to be chosen more than once.
    seed : int, default 0
        Seeds the materials drawn from a box.
    instrument : str, dict or sequence, optional
        What is measured at each geometry (:mod:`pbrdf_cl.analysis.instruments`): ``"dop"`` (the
        DOP, unpolarised source), ``"camera45"`` (alias ``"camera"``: s1, s2 with the source at 45
        degrees), ``"camera4"`` (s1, s2 under 0/45/90/135 degree and circular sources),
        ``"mueller"`` (the 15 Mueller elements normalised by M00), ``"QUANTITIES[@STATES]"`` text
        (``"s1+s2@0+90"``) or a dict (``quantities``, ``states``, ``noise``, ``name``); several
        (a sequence, or comma-separated text) to compare.  The geometries are chosen for the
        first; every one is compared at the chosen and the reference geometries
        (``instrument_comparisons``, a table in :meth:`pbrdf_cl.DesignResult.summary`).  None (default):
        the DOP, as ``"dop"``, without the instrument table.
    shadowing, engine, backend : as for :func:`pbrdf_cl.fit`
    memory_budget : int or str, default "1 GiB"
        The memory the design may take (bytes, or a size such as "4 GiB"): the Jacobians and the
        search over every candidate are held at once, about 2 KiB per candidate and material
        (``design_bytes``); more candidates are refused before any work.

    Returns
    -------
    DesignResult
        ``theta_i``, ``theta_r``, ``phi``, ``ci95_width``, ``ci95_width_reference``,
        ``reference``, ``comparisons``, ``information``, ``criterion``, ``free``, ``target``,
        ``noise``; ``summary()``, ``to_dataset()``.

    Examples
    --------
    >>> import pbrdf_cl
    >>> r = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), noise=0.005, backend="numpy")
    >>> len(r.theta_i), bool(r.ci95_width["n"] < r.ci95_width_reference["n"])
    (30, True)
    >>> r = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), n_measurements=12,
    ...                     instrument="dop,camera45,mueller", backend="numpy")
    >>> se = {i: c["se"]["n"] for i, c in r.instrument_comparisons["reference"].items()}
    >>> bool(se["mueller"] < se["camera45"] < se["dop"])
    True
    """
    t0 = time.perf_counter()
    p = _problem(params, candidates, noise, n_measurements, target, intensity, fixed, criterion, reference,
                 intensity_noise, bounds, materials, repeats, seed, shadowing, instrument, memory_budget)
    eng = resolve_engine(engine, backend)
    lin = _Linearisation(p, eng, shadowing)
    N = p.cand["theta_i"].size
    A = lin.rows(p.intensity, True)
    A = _compressed(A) if p.instruments else A  # an instrument's many channels per geometry
    crit = _Criterion(criterion, [p.free.index(t) for t in p.target])
    Ac, available, chosen, greedy, swaps, singular = _select_design(p, A[:, :N], crit)
    Mfin = _information(Ac[:, chosen])
    info, info_axes, info_label = _information_map(p, crit, Ac, available, Mfin)
    idx_c, idx_r = np.array(chosen), N + np.arange(p.ref["theta_i"].size)
    comparisons, Wc = _comparisons(p, lin, idx_c, idx_r)
    comparisons.update(_incidence_comparisons(p, lin, crit, _finite(A), idx_r))  # as the reference's criterion
    compared = _instrument_comparisons(p, lin, {"chosen": idx_c, "reference": idx_r}) if p.instruments else {}
    return DesignResult(
        **_subset(p.cand, idx_c), indices=idx_c, ci95_width=comparisons["chosen"]["widths"],
        ci95_width_reference=comparisons["reference"]["widths"],
        ci95_width_materials={x: Wc[:, j] for j, x in enumerate(p.free)},
        reference=_subset(p.ref, None), reference_is_paper=not p.ref_given, candidates=_subset(p.cand, None),
        comparisons=comparisons, undetermined=list(comparisons["chosen"]["undetermined"]),
        undetermined_reference=list(comparisons["reference"]["undetermined"]), notes=_notes(p, comparisons),
        information=info, information_axes=info_axes, information_label=info_label,
        criterion=criterion, criterion_value=_final_value(crit, Mfin),
        criterion_greedy=_final_value(crit, _information(Ac[:, greedy])),
        criterion_reference=_final_value(crit, _information(_finite(A[:, N:]))),
        greedy=_subset(p.cand, np.array(greedy)), swaps=swaps, singular=int(np.sum(singular)),
        free=list(p.free), target=list(p.target), noise=p.noise, intensity=bool(intensity),
        intensity_noise=p.intensity_noise, n_materials=p.X.shape[0], materials={k: v.copy() for k, v in p.mat.items()},
        material={k: float(np.median(v)) for k, v in p.mat.items()}, ranges={r.name: (r.low, r.high) for r in p.rngs},
        bounds={x: (float(p.lo[j]), float(p.hi[j])) for j, x in enumerate(p.names) if x in p.free},
        fixed=p.fx, shadowing=shadowing, engine=eng.description, instruments=[i.info() for i in p.instruments],
        instrument_comparisons=compared, seconds=time.perf_counter() - t0)
