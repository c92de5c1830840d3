"""Figures of per-pixel fits (:func:`pbrdf_cl.batch.fit_batch`, ``pbrdf-cl fit-image --png``):
the parameter maps with the widths of their 95% intervals, and the fit status of every pixel."""
from __future__ import annotations

import numpy as np

#: Largest side, in pixels, of a map drawn (larger images are drawn every s-th pixel).
MAX_SIDE = 1024

#: Colours of the status codes (``pbrdf_cl.batch.STATUS``).
STATUS_COLOURS = {1: "#2ca02c", 2: "#bcbd22", 3: "#ff7f0e", 4: "#9467bd", 0: "#d62728", -1: "#7f7f7f",
                  -2: "#c7c7c7", -3: "#000000"}


def _units(attrs):
    u = attrs.get("units", "")
    return "dimensionless" if u in ("", "1") else u


def _image(da, step):
    """A 2-d numpy image of a (y, x) or (pixel,) variable, every ``step``-th pixel (read lazily)."""
    if da.ndim == 1:
        return np.asarray(da[::step].values)[None, :]
    return np.asarray(da[::step, ::step].values)


def plot_batch_maps(ds, path, *, truth=None, max_side=MAX_SIDE):
    """Draw the maps of a per-pixel fit into a PNG: per fitted parameter, its value and the width
    of its 95% interval (and, given the truth, the true map beside the fitted one on the same
    colour scale, with the share of pixels whose interval covers it), and a panel of the fit
    status.

    Parameters
    ----------
    ds : xarray.Dataset
        A result of :func:`pbrdf_cl.batch.fit_batch` or :func:`pbrdf_cl.batch_store.fit_batch_to_store`
        over one or two pixel dimensions (``attrs["free"]`` names the fitted parameters).
    path : str or path
        The PNG to write (matplotlib's Agg backend).
    truth : xarray.Dataset, optional
        Maps ``true_<name>`` over the same pixels (a synthetic stack of
        :func:`pbrdf_cl.imagestack.synthetic_stack`).
    max_side : int, default 1024
        Images with more pixels along a side are drawn every s-th pixel (said in the title), so
        that a store of any size is read only in part.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    ValueError
        A result without ``status`` or parameters, or with more than two pixel dimensions.

    Examples
    --------
    >>> import numpy as np, pbrdf_cl, tempfile, os
    >>> from pbrdf_cl.batch import fit_batch
    >>> ti, tr = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
    >>> dop = np.broadcast_to(pbrdf_cl.dop(ti, tr, n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3), (2, 3, 30))
    >>> res = fit_batch(dict(dop=dop, theta_i=ti, theta_r=tr))
    >>> out = plot_batch_maps(res, os.path.join(tempfile.mkdtemp(), "maps.png"))
    >>> out.endswith("maps.png")
    True
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    from .batch import STATUS

    if "status" not in ds:
        raise ValueError("plot_batch_maps: the dataset has no 'status': not a result of fit_batch")
    names = str(ds.attrs.get("free", "")).split() or [str(p) for p in ds.coords.get("param", [])]
    names = [n for n in names if n in ds]
    if not names:
        raise ValueError("plot_batch_maps: the dataset has no fitted parameter maps")
    dims = ds["status"].dims
    if len(dims) > 2:
        raise ValueError(f"plot_batch_maps: maps need one or two pixel dimensions, got {dims}")
    side = max(ds["status"].shape)
    step = max(1, -(-side // int(max_side)))
    sub = "" if step == 1 else f" (every {step}th pixel)"
    shape = ds["status"].shape
    aspect = (shape[0] / shape[1]) if len(shape) == 2 else 0.2
    w = 4.2
    h = max(1.2, min(4.2, w * aspect)) + 0.6
    ncol = 3 if truth is not None else 2
    fig, axes = plt.subplots(len(names) + 1, ncol, figsize=(ncol * w + 1.2, h * (len(names) + 1)), squeeze=False,
                             constrained_layout=True)
    ylab, xlab = (dims if len(dims) == 2 else ("", dims[0]))
    for row, n in enumerate(names):
        value = _image(ds[n], step)
        ci = ds[f"{n}_ci95"] if f"{n}_ci95" in ds else None
        long = ds[n].attrs.get("long_name", "")
        panels = [(value, f"{n}: {long}{sub}" if long else f"{n}{sub}", "viridis", f"{n} ({_units(ds[n].attrs)})")]
        if truth is not None and f"true_{n}" in truth:
            true = _image(truth[f"true_{n}"], step)
            cover = ""
            if ci is not None:
                lo, hi = _image(ci.isel(bound=0), step), _image(ci.isel(bound=1), step)
                fitted = np.isfinite(lo)
                cover = f"; 95% intervals cover it in {np.mean(((lo <= true) & (true <= hi))[fitted]):.1%} of pixels"
            panels.insert(0, (true, f"{n}: truth{cover}{sub}", "viridis", f"{n} ({_units(ds[n].attrs)})"))
        if ci is not None:
            lo, hi = _image(ci.isel(bound=0), step), _image(ci.isel(bound=1), step)
            panels.append((hi - lo, f"{n}: width of the 95% interval (high - low){sub}", "magma",
                           f"width of {n} ({_units(ds[n].attrs)})"))
        shared_scale = [p[0] for p in panels[:-1]] if len(panels) == 3 else [panels[0][0]]
        both = np.concatenate([a[np.isfinite(a)].ravel() for a in shared_scale])
        for col in range(ncol):
            ax = axes[row, col]
            if col >= len(panels):
                ax.set_axis_off()
                continue
            img, title, cmap, label = panels[col]
            finite = both if col < len(shared_scale) else img[np.isfinite(img)]  # truth and value share a scale
            kw = {}
            if finite.size:
                kw = dict(vmin=float(finite.min()), vmax=float(finite.max()) if finite.max() > finite.min()
                          else float(finite.min()) + 1e-12)
            im = ax.imshow(img, cmap=cmap, interpolation="nearest", aspect="auto" if len(dims) == 1 else "equal", **kw)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel(xlab)
            ax.set_ylabel(ylab)
            fig.colorbar(im, ax=ax, label=label, shrink=0.9)
    # status: one colour per code, a legend with each code's name and its pixels
    status = _image(ds["status"], step).astype(int)
    codes = sorted(STATUS)
    colours = [STATUS_COLOURS.get(c, "#ffffff") for c in codes]
    cmap = ListedColormap(colours)
    norm = BoundaryNorm([c - 0.5 for c in codes] + [codes[-1] + 0.5], cmap.N)
    ax = axes[-1, 0]
    ax.imshow(status, cmap=cmap, norm=norm, interpolation="nearest", aspect="auto" if len(dims) == 1 else "equal")
    ax.set_title(f"fit status{sub}", fontsize=9)
    ax.set_xlabel(xlab)
    ax.set_ylabel(ylab)
    counts = {c: int((status == c).sum()) for c in codes}
    handles = [Patch(color=STATUS_COLOURS.get(c, "#ffffff"), label=f"{c}: {STATUS[c][0]} ({counts[c]})")
               for c in codes if counts[c]]
    legend_ax = axes[-1, 1]
    legend_ax.set_axis_off()
    for ax in axes[-1, 2:]:
        ax.set_axis_off()
    legend_ax.legend(handles=handles, loc="center left", title="status (pixels drawn)", fontsize=8,
                     title_fontsize=9, frameon=False)
    model = ds.attrs.get("model", "")
    fig.suptitle(f"per-pixel fit{f' ({model} model)' if model else ''}: {' x '.join(map(str, shape))} pixels",
                 fontsize=11)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path)
