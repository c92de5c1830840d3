"""The figures of :func:`pbrdf_cl.analysis.paper.reproduce` (``pbrdf-cl reproduce``): Fig. 2 (data
and both models' fits), Fig. 4 and 5 (DOP curves of the steel), the DOP maps over (theta_i,
theta_r); each drawn from the arrays :mod:`pbrdf_cl.analysis.paper` computed, into the caller's axes
(``ax=``; ``fig=`` for the maps' panels) or a new figure, written where a path is given (the first
argument; None: no file) and returned.  The Sobol' map and the design are drawn by
:mod:`pbrdf_cl.plots.sensitivity` and the design's figure, the map over (theta_r, sigma) by
:func:`pbrdf_cl.plots.maps.plot_map`."""
from __future__ import annotations

import numpy as np

from .common import LABELS, axes, figure, save
from .maps import label_contours


def params_text(p):
    """``{"n": 1.6, "k": 2.139}`` -> ``"n=1.6, k=2.139"`` (the parameters as a figure states them)."""
    return ", ".join(f"{k}={v:g}" for k, v in p.items())


#: The size and layout of the figure a curve plot makes where it is given no axes.
CURVES_FIGURE = dict(figsize=(7.5, 5.2), layout="constrained")


def _finish(ax, path, legend=True):
    ax.grid(alpha=0.3)
    if legend:
        ax.legend(fontsize=8)
    save(ax.figure, path, dpi=120)  # the figures are made with layout="constrained": nothing clipped
    return ax


def plot_fig2(path, sample, params, noise, meas, angle, true, six, spec, *, ax=None):
    """Fig. 2 of one sample: the synthetic data (``meas``, generated at ``params`` with DOP noise
    sd ``noise``), the true curve and both models' fits over ``angle`` (specular geometry);
    ``six``, ``spec``: (FitResult, curve) of the six-parameter and the ref. [7] model.  Drawn
    into ``ax`` (default: a new figure's, :data:`CURVES_FIGURE`), written to ``path`` unless it
    is None; returns the axes."""
    (six, curve_six), (spec, curve_spec) = six, spec
    ax = axes(ax, **CURVES_FIGURE)
    ax.errorbar(meas.theta_i, meas.dop, yerr=meas.dop_std, fmt="o", ms=4, color="k", capsize=2,
                label=f"synthetic data ± 1 sd (noise sd {noise:g}: bars within the markers)")
    ax.plot(angle, true, ":", color="0.5", lw=1, label="true model")
    ax.plot(angle, curve_six, "-", color="C0",
            label=f"six-param fit: n={six.x['n']:.3f}, k={six.x['k']:.3f} (BIC {six.bic:.1f})")
    ax.plot(angle, curve_spec, "--", color="C3",
            label=f"ref. [7] fit: n={spec.x['n']:.3f}, k={spec.x['k']:.3f} (BIC {spec.bic:.1f})")
    ax.set_xlabel("incidence angle theta_i = theta_r (deg), in plane")
    ax.set_ylabel("degree of polarization")
    ax.set_xlim(0, 85)
    ax.set_title(f"Fig. 2 ({sample}): DOP vs incidence angle, both models\n"
                 f"data from the six-param model at {params_text(params)}", fontsize=9)
    return _finish(ax, path)


def plot_fig4(path, steel, theta_r, curves, measured_theta_r, measured, *, ax=None):
    """Fig. 4: the DOP of the ``steel`` fit over ``theta_r`` at each incidence angle (``curves``:
    theta_i -> values), with markers at the measured geometries (``measured``: theta_i -> values
    at ``measured_theta_r``): model values only, no data.  Drawn into ``ax`` (default: a new
    figure's), written to ``path`` unless it is None; returns the axes."""
    from matplotlib.lines import Line2D
    ax = axes(ax, **CURVES_FIGURE)
    for i, ti in enumerate(curves):
        ax.plot(theta_r, curves[ti], "-", color=f"C{i}", label=f"model, theta_i = {ti:g} deg")
        ax.plot(measured_theta_r, measured[ti], "o", color=f"C{i}", ms=4)
    step = measured_theta_r[1] - measured_theta_r[0]
    handles, _ = ax.get_legend_handles_labels()
    handles.append(Line2D([], [], ls="none", marker="o", ms=4, color="0.3",
                          label=f"model at the measured geometries (theta_r {measured_theta_r[0]:g}.."
                                f"{measured_theta_r[-1]:g} step {step:g}; not data)"))
    ax.set_xlabel("reflection zenith angle theta_r (deg), in plane")
    ax.set_ylabel("degree of polarization")
    ax.set_title(f"Fig. 4: 45# steel, 435 nm: the six-parameter model at the paper's fit\n({params_text(steel)})",
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=8)
    return _finish(ax, path, legend=False)


def plot_fig5(path, steel, theta_r, sigmas, rows, *, ax=None):
    """Fig. 5: the DOP over ``theta_r`` at theta_i = 40 deg for each roughness of ``sigmas``
    (``rows``, in that order), the other parameters those of ``steel``.  Drawn into ``ax``
    (default: a new figure's), written to ``path`` unless it is None; returns the axes."""
    ax = axes(ax, **CURVES_FIGURE)
    for i, (s, row) in enumerate(zip(sigmas, rows)):
        ax.plot(theta_r, row, "-", color=f"C{i}", label=f"model, sigma = {s:g}")
    ax.set_xlabel("reflection zenith angle theta_r (deg), in plane")
    ax.set_ylabel("degree of polarization")
    others = {k: v for k, v in steel.items() if k != "sigma"}
    ax.set_title(f"Fig. 5: effect of roughness at theta_i = 40 deg ({params_text(others)})", fontsize=9)
    return _finish(ax, path)


def plot_dop_maps(path, da, angles, sigmas, fixed, *, fig=None):
    """The DOP over (theta_i, theta_r) (``da``, a grid over both ``angles`` and ``sigmas``), one
    panel per roughness on one colour scale, with labelled contours; ``fixed``: the other inputs.
    Drawn into ``fig`` (a figure or subfigure; default a new one, 5 inches wide per panel),
    written to ``path`` unless it is None; returns the figure."""
    from matplotlib import colors
    fig = figure(fig, figsize=(5.0 * len(sigmas), 4.6), layout="constrained")
    axs = fig.subplots(1, len(sigmas), sharey=True)
    norm = colors.Normalize(0.0, float(da.max()))
    contours = []
    for ax, s in zip(axs, sigmas):
        z = da.sel(sigma=s).transpose("theta_r", "theta_i").values
        mesh = ax.pcolormesh(angles, angles, z, shading="auto", cmap="viridis", norm=norm)
        cs = ax.contour(angles, angles, z, levels=np.arange(0.1, 1.0, 0.1), colors="white", linewidths=0.7)
        contours.append((ax, cs))
        ax.set_title(f"sigma = {s:g}", fontsize=10)
        ax.set_xlabel(LABELS["theta_i"])
    axs[0].set_ylabel(LABELS["theta_r"])
    cb = fig.colorbar(mesh, ax=list(axs), shrink=0.9)
    cb.set_label("DOP")
    fig.suptitle(f"DOP over (theta_i, theta_r), in plane, {params_text(fixed)}", fontsize=10)
    fig.figure.draw_without_rendering()  # the layout first: labels are placed in the axes' final shape
    for ax, cs in contours:
        label_contours(ax, cs, fmt="%.1f")
    save(fig, path, dpi=110)
    return fig
