"""Figures (matplotlib, Agg backend: no display needed)."""
from __future__ import annotations

import numpy as np


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plot_fit(meas, fits, path):
    """Measured DOP with error bars, each fitted model's curve, and residuals, per incidence angle."""
    from . import api
    plt = _pyplot()
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(8, 7), sharex=True, gridspec_kw=dict(height_ratios=[3, 1.3]))
    incid = np.unique(np.round(meas.theta_i, 6))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ["-", "--", ":"]
    for ci, ti in enumerate(incid):
        sel = np.isclose(meas.theta_i, ti)
        col = colors[ci % len(colors)]
        yerr = meas.dop_std[sel] if meas.dop_std is not None else None
        ax.errorbar(meas.theta_r[sel], meas.dop[sel], yerr=yerr, fmt="o", color=col, ms=4,
                    label=f"data, theta_i = {ti:g} deg")
        phi = float(np.median(meas.phi[sel]))
        tr = np.linspace(max(0.0, meas.theta_r[sel].min() - 5), min(89.0, meas.theta_r[sel].max() + 5), 200)
        for si, (name, r) in enumerate(fits.items()):
            x = dict(r.x)
            if name == "specular":
                curve = api.dop(ti, tr, phi, n=x["n"], k=x["k"], model="specular", shadowing=r.shadowing,
                                backend="numpy")
                res = api.dop(meas.theta_i[sel], meas.theta_r[sel], meas.phi[sel], n=x["n"], k=x["k"],
                              model="specular", backend="numpy") - meas.dop[sel]
            else:
                curve = api.dop(ti, tr, phi, shadowing=r.shadowing, backend="numpy", **x)
                res = api.dop(meas.theta_i[sel], meas.theta_r[sel], meas.phi[sel], shadowing=r.shadowing,
                              backend="numpy", **x) - meas.dop[sel]
            ax.plot(tr, curve, styles[si % 3], color=col, lw=1.2,
                    label=f"{name} fit" if ci == 0 else None)
            axr.plot(meas.theta_r[sel], res, "o" if si == 0 else "x", color=col, ms=4,
                     label=f"{name}" if ci == 0 else None)
    axr.axhline(0, color="0.5", lw=0.8)
    ax.set_ylabel("degree of polarization")
    axr.set_ylabel("model - data")
    axr.set_xlabel("reflection zenith angle theta_r (deg)")
    title = "; ".join(f"{n}: n={r.x['n']:.3g}, k={r.x['k']:.3g}, BIC {r.bic:.1f}" for n, r in fits.items())
    ax.set_title(f"DOP fit ({meas.source.split('/')[-1]})\n{title}", fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    axr.legend(fontsize=7)
    ax.grid(alpha=0.3)
    axr.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
