"""Fits of polarimetric data (issue #36): whatever a polarimeter measures (:mod:`pbrdf_cl.model.measurables`:
Stokes parameters under polarized light, Mueller elements, DOP, AoP, intensities, in any mix), through
:func:`pbrdf_cl.fit`'s stages on their channels.

- the device grid stage on the *normalised* channels (absolute Stokes parameters and Mueller
  elements divided by their row's S0 or M00, which, like the DOP, depend on ks and kd only through
  kd/ks): :class:`~pbrdf_cl.model.measurables.Channels` through ``pbrdf_grid.cl``'s
  ``objective_channel_rows``;
- the basins, DIRECT-L, BOBYQA, the Levenberg-Marquardt screen, least squares and the final BOBYQA on
  the weighted residuals of those channels (:class:`ChannelResiduals`, ks held, kd as kd/ks);
- where absolute channels are measured (S0, M00, F00: the data's scale), the intensity stage: every
  channel, ks free, kd fitted as kd/ks, as :func:`pbrdf_cl.fit` does with an F00 column;
- the uncertainties, goodness of fit and notes of :func:`pbrdf_cl.fit`.

Weights: every channel has its standard deviation (``<name>_std``), or none has; without them the
normalised channels (dimensionless, as the DOP) share one noise level estimated from the residuals,
and absolute ones take :data:`~pbrdf_cl.fitting.setup.F00_REL_STD` of their row's intensity.  An
AoP mixed with other quantities needs its ``aop_std`` (degrees are not the others' units).
"""
from __future__ import annotations

import numpy as np

from ...model import reference
from ..channels import ChannelModel
from ..common import one_blas_thread
from ..setup import F00_REL_STD
from .stages import MEMORY_BUDGET, finite_rows

#: What the intervals of a polarimetric fit without given uncertainties assume at least: the noise
#: floor of the DOP (a normalised Stokes parameter or Mueller element is as resolved).
DIMENSIONLESS = ("dop", "s1", "s2", "s3") + tuple(f"m{i}{j}" for i in range(4) for j in range(4))


class ChannelResiduals:
    """Weighted residuals of channels as a function of the free parameters, as
    :class:`~pbrdf_cl.fitting.sample.stages.Residuals` for the DOP: ``rows(X)`` maps (B, d) vectors over
    ``free`` to (B, C) residuals (value - measured, an AoP's wrapped) / std; with ``intensity`` (ks
    among ``free``) the ``kd`` of a vector is the ratio kd/ks.  Non-finite residuals become 1e150."""

    def __init__(self, model, free, base, std, intensity=False):
        self.model, self.free, self.base = model, tuple(free), dict(base)
        self.std, self.intensity = std, intensity

    def params(self, x):
        """Every model parameter at the free parameters ``x`` (a dict)."""
        return self._with(zip(self.free, x))

    def _with(self, values):
        p = dict(self.base)
        p.update(values)
        if self.intensity:
            p["kd"] = p["kd"] * p["ks"]
        return p

    @property
    def observed(self):
        """The measured values fitted (one per channel)."""
        return self.model.ch.obs

    def raw(self, p):
        """The unweighted residuals (value - measured; an AoP's wrapped) at parameters ``p``."""
        ch = self.model.ch
        return reference.channel_residual(self.model.rows(p), ch.obs, ch.aop)

    def weighted(self, p, runs=()):
        """The weighted residuals at every model parameter ``p`` (name -> scalars or (B, 1) arrays;
        ``runs`` as :meth:`~pbrdf_cl.fitting.sample.stages.Residuals.weighted`'s, unused: the channel
        model finds the rows that share factors itself)."""
        return finite_rows(self.raw(p) / self.std)

    def rows(self, X):
        return self.weighted(self._with((n, X[:, j:j + 1]) for j, n in enumerate(self.free)))


def channel_stds(ch, what):
    """(std per channel, whether the stds are given): the channels' own, or, where none is given,
    1 for the normalised channels (one noise level, estimated from the residuals) and
    :data:`F00_REL_STD` of the row's intensity for absolute ones; one-line refusals for stds given
    for some quantities only, and for an AoP without its std among other quantities."""
    given = np.isfinite(ch.std)
    names = list(dict.fromkeys(ch.name))
    if given.all():
        return ch.std.copy(), True
    if given.any():
        have = sorted({n for n, g in zip(ch.name, given) if g})
        lack = sorted({n for n, g in zip(ch.name, given) if not g})
        raise ValueError(f"{what}: standard deviations are given for {', '.join(have)} but not for "
                         f"{', '.join(lack)}; give <name>_std for every quantity or for none")
    if "aop" in names and len(names) > 1:
        raise ValueError(f"{what}: aop_std is needed where the AoP is fitted with other quantities ("
                         f"{', '.join(n for n in names if n != 'aop')}): degrees are not their units")
    std = np.ones(len(ch))
    absolute = ch.absolute
    if absolute.any():
        std[absolute] = F00_REL_STD * np.maximum(np.abs(_row_intensity(ch))[absolute], 1e-300)
    return std, False


def _row_intensity(ch):
    """Each channel's row intensity: the measured S0, M00 or F00 of its row where there is one, else
    its own absolute value."""
    out = np.abs(ch.obs).astype(float)
    for name in ("s0", "m00", "f00"):
        sel = ch.name == name
        if sel.any():
            level = dict(zip(ch.row[sel], ch.obs[sel]))
            hit = np.array([r in level for r in ch.row])
            out[hit] = [level[r] for r in ch.row[hit]]
    return out


def _ks_start(model, p, ch, std, ks_bounds):
    """The ks that best scales the absolute channels' model values at ``p`` (with ks = 1) to
    their measurements (weighted least squares), clipped to ``ks_bounds``."""
    m1 = model.rows(dict(p, ks=1.0))
    w = 1.0 / std ** 2
    return float(np.clip((w * ch.obs * m1).sum() / max((w * m1 * m1).sum(), 1e-300), *ks_bounds))


def _label(ch):
    return ", ".join(dict.fromkeys(ch.name))


def normalised_channels(meas, free):
    """The channels of polarimetric measurements ``meas`` that the grid and the local stages fit:
    (every channel, the normalised ones, their stds, whether the stds are given), with one-line
    refusals (stds for some quantities only, intensities alone, fewer numbers than the ``free``
    parameters)."""
    every = meas.channels()
    channel_stds(every, meas.source)  # refuses stds given for some quantities only, before any work
    ch = every.normalised()
    if not len(ch):
        raise ValueError(f"{meas.source}: the data hold intensities only ({_label(every)}): the fit needs a "
                         "polarization quantity too (dop, aop, s1..s3, or Mueller elements other than m00)")
    if len(ch) <= len(free):
        raise ValueError(f"{meas.source}: {len(ch)} measured numbers for {len(free)} free parameters "
                         f"({', '.join(free)}); at least {len(free) + 1} are needed")
    std, known = channel_stds(ch, meas.source)
    return every, ch, std, known


def channel_residuals(meas, setup):
    """The weighted residuals of the normalised channels of ``meas`` over ``setup``'s free
    parameters (ks held, kd as kd/ks): a :class:`ChannelResiduals`."""
    _, ch, std, _ = normalised_channels(meas, setup.free)
    return ChannelResiduals(ChannelModel(ch, setup.shadowing), setup.free, setup.base, std)


@one_blas_thread
def fit_channels(meas, setup, axes, n_basins=6, *, engine=None, backend="auto", progress=False, grid_result=None,
                 derivative_free=True, absolute=True, memory_budget=MEMORY_BUDGET):
    """:func:`pbrdf_cl.fit` of polarimetric measurements ``meas`` (``meas.polarimetric``) with the
    checked ``setup``: the device grid ``axes`` (or its ``grid_result``, computed already: what
    :func:`pbrdf_cl.fit_joint` shares between its joint and separate fits) and the local stages on
    the normalised channels (``derivative_free`` as
    :func:`~pbrdf_cl.fitting.sample.inversion.fit_on_grid`'s), then, with ``absolute``, the intensity
    stage where absolute channels are measured; the :class:`FitResult`.  ``memory_budget``: the grid
    stage's (:func:`~pbrdf_cl.fitting.sample.stages.grid_stage`)."""
    from ..common import dop_noise_floor
    from .result import Observed, fit_result, fit_status, model_notes
    from .stages import INTENSITY_MAXEVAL, grid_stage, intensity_stage, local_stages
    from .uncertainty import uncertainty_stage
    free, base, lo, hi = setup.free, setup.base, setup.lo, setup.hi
    every, ch, std, known = normalised_channels(meas, free)
    if grid_result is None:
        grid_result = grid_stage(meas, free, axes, base, setup.shadowing, engine=engine, backend=backend,
                                 progress=progress, channels=ch, memory_budget=memory_budget)
    grid = grid_result.value
    resid = ChannelResiduals(ChannelModel(ch, setup.shadowing), free, base, std)
    rise = 1.0 if known else float(grid.sse.min()) / (len(ch) - len(free))
    cands, final_ran, st = local_stages(resid.rows, lo, hi, grid, free, n_basins, rise, derivative_free)
    st = {"grid": grid_result, **st}
    best = cands[0]
    final, x_final, lo_f, hi_f = resid, best.x, lo, hi
    use_abs = absolute and every.absolute.any() and setup.fits_intensity(True)
    if use_abs:
        std_all, _ = channel_stds(every, meas.source)
        model_all = ChannelModel(every, setup.shadowing)
        absolute = every.take(every.absolute)
        ks0 = _ks_start(ChannelModel(absolute, setup.shadowing), resid.params(best.x), absolute,
                        std_all[every.absolute], setup.ks_bounds)
        final = ChannelResiduals(model_all, free + ["ks"], base, std_all, intensity=True)
        lo_f, hi_f = np.append(lo, setup.ks_bounds[0]), np.append(hi, setup.ks_bounds[1])
        spacing = np.array([np.median(np.diff(axes[n])) for n in free])
        st["intensity"] = intensity_stage(final, lo_f, hi_f, np.append(best.x, ks0), np.append(spacing, ks0 * 0.1),
                                          INTENSITY_MAXEVAL)
        x_final = st["intensity"].value.x
    floor = None if known else dop_noise_floor(ch.obs)
    unc = uncertainty_stage(final, x_final, lo_f, hi_f, grid, best.sse, len(ch), known, floor).value
    status = fit_status(best, final_ran, st["intensity"].value if use_abs else None)
    raw = resid.raw(resid.params(x_final[:len(free)] if not use_abs else _ratio_x(x_final, free)))
    notes = model_notes(setup.model, setup.fixed, use_abs, meas)
    notes = [n for n in notes if not n.startswith("DOP depends on ks and kd only through kd/ks")]
    if not use_abs:
        notes.insert(0, "normalised Stokes parameters, Mueller elements, the DOP and the AoP depend on ks and kd only "
                        "through kd/ks: ks is fixed at 1 and kd is the ratio kd/ks (absolute S0 or M00 separate them)")
        if every.absolute.any() and absolute:
            notes.append(f"the absolute channels ({_label(every.take(every.absolute))}) entered only as ratios: "
                         "ks or kd is fixed, so they cannot separate ks")
    observed = Observed(ch.obs, raw, known, _label(ch))
    return fit_result(meas, setup.model, setup.shadowing, final, x_final, lo_f, hi_f, unc, cands, grid, st, status,
                      notes, observed)


def _ratio_x(x, free):
    """The free parameters of the normalised channels' residuals from the intensity stage's vector
    (free + ks, kd as kd/ks): the first ``len(free)``, whose kd is already the ratio."""
    return np.asarray(x)[:len(free)]
