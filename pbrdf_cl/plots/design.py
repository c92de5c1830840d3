"""The figure of a measurement design (:func:`plot_design`, ``pbrdf-cl design --png``): the
information map over the candidates with the chosen and the reference geometries, and the
predicted 95% interval widths."""
import numpy as np

from .common import figure, save


def plot_design(result, path=None, *, fig=None):
    """Draw a design: left, the information map over (theta_i, theta_r), theta_i on the
    horizontal axis as in the Sobol' maps (the maximum over phi where phi is an axis; explicit
    candidates as coloured points) with the chosen geometries (circles)
    and the reference's (crosses); right, the predicted 95% interval widths per parameter,
    chosen against reference, each with and without an intensity column (log scale).  A
    parameter a set leaves undetermined (its interval spans the whole bounds) is drawn as a
    hatched, unfilled bar of its bound range, named in the legend.  A design with instruments
    (``instrument=``) gets a third panel: each instrument's widths at the reference geometries
    (solid) and at the chosen ones (faded).

    Parameters
    ----------
    result : pbrdf_cl.DesignResult
        What :func:`pbrdf_cl.design` returned.
    path : str or path, optional
        The PNG to write (``pbrdf-cl design --png``; another suffix, another format); None:
        nothing is written.
    fig : matplotlib.figure.Figure or SubFigure, optional
        Drawn into (two panels side by side, three with instruments); default a new 13 x 5.6 inch
        figure (19.5 x 5.6 with instruments) with constrained layout.

    Returns
    -------
    matplotlib.figure.Figure
        The figure drawn (``fig`` where given).

    Examples
    --------
    >>> r = pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5), noise=0.005, n_measurements=12)  # doctest: +SKIP
    >>> plot_design(r, "design.png")  # doctest: +SKIP
    >>> import matplotlib.pyplot as plt  # doctest: +SKIP
    >>> fig = plot_design(r, fig=plt.figure(figsize=(13, 5.6), layout="constrained"))  # doctest: +SKIP
    """
    from matplotlib.patches import Patch
    compared = bool(result.get("instrument_comparisons"))
    fig = figure(fig, figsize=(19.5 if compared else 13, 5.6), layout="constrained")
    ax, axb, *axi = fig.subplots(1, 3 if compared else 2, gridspec_kw=dict(width_ratios=[1.1, 1, 1][:2 + compared]))
    info = np.asarray(result.information, float)
    axes = result.information_axes
    label = ("relative reduction of the A criterion\nby one more measurement (1)" if result.criterion == "A"
             else "reduction of log det of the target\ncovariance by one more measurement (1)")
    if "theta_i" in axes and "theta_r" in axes:
        names = list(axes)
        img = info
        if "phi" in axes:
            with np.errstate(all="ignore"):
                img = np.nanmax(img, axis=names.index("phi"))
            names.remove("phi")
        if names.index("theta_r") > names.index("theta_i"):
            img = img.T  # rows theta_r, columns theta_i
        ti, tr = axes["theta_i"], axes["theta_r"]
        pos = img[np.isfinite(img) & (img > 0)]
        norm = None
        if pos.size and pos.max() / max(pos.min(), 1e-300) > 100:
            from matplotlib.colors import LogNorm
            norm = LogNorm(vmin=max(pos.min(), pos.max() * 1e-6), vmax=pos.max())
        mesh = ax.pcolormesh(ti, tr, np.where(img > 0, img, np.nan) if norm else img, shading="nearest",
                             cmap="viridis", norm=norm)
    else:
        c = result.candidates
        mesh = ax.scatter(c["theta_i"], c["theta_r"], c=info.reshape(-1), s=18, cmap="viridis")
    fig.colorbar(mesh, ax=ax, label=label)
    ax.plot(result.reference["theta_i"], result.reference["theta_r"], "x", color="tab:red", ms=7, mew=1.5,
            label="paper's geometry" if result.reference_is_paper else "reference")
    ax.plot(result.theta_i, result.theta_r, "o", mfc="none", mec="white", ms=9, mew=1.8,
            label=f"chosen ({len(result.theta_i)})")
    ax.set_xlabel("theta_i (deg)")
    ax.set_ylabel("theta_r (deg)")
    ax.set_title(f"information for {', '.join(result.target)} at the final design (criterion {result.criterion})")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.8)
    comp = result.comparisons
    keys = [k for k in ("chosen", "chosen_other", "reference", "reference_other") if k in comp]
    colours = {"chosen": "tab:blue", "chosen_other": "tab:cyan", "reference": "tab:red",
               "reference_other": "tab:orange"}
    params = result.compared
    span = {n: hi - lo for n, (lo, hi) in result.bounds.items()}
    width = 0.8 / len(keys)
    handles, any_undetermined = [], False
    for i, key in enumerate(keys):
        w, und = comp[key]["widths"], set(comp[key].get("undetermined", ()))
        where = [(j, p) for j, p in enumerate(params) if p in w]
        xs = np.array([j + (i - (len(keys) - 1) / 2) * width for j, _ in where])
        ok = np.array([p not in und for _, p in where], bool)
        heights = np.array([w[p] for _, p in where])
        axb.bar(xs[ok], heights[ok], width, color=colours[key])
        if (~ok).any():
            any_undetermined = True
            axb.bar(xs[~ok], [span.get(p, w[p]) for (_, p), o in zip(where, ok) if not o], width, fill=False,
                    hatch="///", edgecolor=colours[key], linewidth=1.0)
        handles.append(Patch(color=colours[key], label=f"{comp[key]['description']} ({comp[key]['n_points']} points)"))
    if any_undetermined:
        handles.append(Patch(fill=False, hatch="///", edgecolor="0.3",
                             label="hatched: undetermined\n(interval spans the bounds;\nbar = bound range)"))
    axb.set_yscale("log")
    kd_label = "kd" if "ks" in result.get("fixed", {}) else "kd/ks"
    axb.set_xticks(range(len(params)), [(kd_label if p == "kd" else p) for p in params])
    axb.set_xlabel("parameter")
    axb.set_ylabel("predicted 95% interval width (parameter units; dimensionless)")
    ins = result.get("instruments") or [dict(name="DOP", noise=result.noise)]
    axb.set_title(f"{ins[0]['name']} noise {ins[0]['noise']:g}" + (f", F00 relative noise {result.intensity_noise:g}"
                                                    if any(k.endswith("_other") for k in keys) or result.intensity
                                                    else ""))
    lo_y, hi_y = axb.get_ylim()
    axb.set_ylim(lo_y, hi_y * (hi_y / lo_y) ** 0.45)  # room above the bars for the legend
    axb.legend(handles=handles, fontsize=8, loc="upper left", ncol=2)
    if compared:
        _instrument_panel(axi[0], result)
    save(fig, path, dpi=110)
    return fig


def _instrument_panel(ax, result):
    """The instruments compared (``design(instrument=...)``): per free parameter, a bar per
    instrument at the reference geometries (solid) and at the chosen ones (faded); an
    undetermined parameter a hatched, unfilled bar of its bound range."""
    from matplotlib.patches import Patch
    comp, names = result.instrument_comparisons, list(result.free)
    span = {n: hi - lo for n, (lo, hi) in result.bounds.items()}
    bars = [(key, i) for key in ("reference", "chosen") for i in range(len(result.instruments))]
    width = 0.84 / len(bars)
    colours = [f"C{i}" for i in range(len(result.instruments))]
    for b, (key, i) in enumerate(bars):
        c = comp[key][result.instruments[i]["name"]]
        xs = np.arange(len(names)) + (b - (len(bars) - 1) / 2) * width
        und = np.array([n in c["undetermined"] for n in names])
        heights = np.array([span[n] if u else c["widths"][n] for n, u in zip(names, und)])
        ax.bar(xs[~und], heights[~und], width, color=colours[i], alpha=1.0 if key == "reference" else 0.45)
        ax.bar(xs[und], heights[und], width, fill=False, hatch="///", edgecolor=colours[i], linewidth=1.0)
    ax.set_yscale("log")
    kd_label = "kd" if "ks" in result.get("fixed", {}) else "kd/ks"
    ax.set_xticks(range(len(names)), [(kd_label if p == "kd" else p) for p in names])
    ax.set_xlabel("parameter")
    ax.set_ylabel("predicted 95% interval width")
    ref = "paper's geometry" if result.reference_is_paper else "reference"
    ax.set_title(f"instruments (solid: {ref}; faded: chosen)")
    lo_y, hi_y = ax.get_ylim()
    ax.set_ylim(lo_y, hi_y * (hi_y / lo_y) ** 0.3)  # room above the bars for the legend
    ax.legend(handles=[Patch(color=colours[i], label=f"{d['name']}: {d['per_geometry']} channels/geometry, "
                             f"noise {d['noise']:g}") for i, d in enumerate(result.instruments)],
              fontsize=8, loc="upper right")
