"""The figure of a per-pixel fit (pbrdf_cl.plots.images, pbrdf-cl fit-image --png; issue #26 item
15): drawn in the stack's coordinates, undetermined and not-converged pixels marked, missing
pixels in the legend, colour scales that one outlier does not set, titles not cut."""
import numpy as np
import pytest
import xarray as xr
from matplotlib.collections import PatchCollection

from pbrdf_cl.io import imagestack
from pbrdf_cl.plots import images as batch_plots


@pytest.fixture(scope="module")
def result():
    """A fit-like result over the synthetic stack's 12 x 12 pixels (x_mm, y_mm) without running
    the fit: values near the truth, one outlier, undetermined, not-converged and missing pixels."""
    stack = imagestack.synthetic_stack(12, seed=0)
    rng = np.random.default_rng(1)
    names = ["n", "k", "sigma", "kd", "c"]
    shape = (12, 12)
    status = np.ones(shape, np.int8)
    status[0, :3] = -1                      # masked: no values
    status[5, 5] = 0                        # not converged
    status[7, 2:6] = 4                      # underdetermined in k
    ds = xr.Dataset(coords={"x_mm": ("x", stack.x_mm.values, {"units": "mm"}),
                            "y_mm": ("y", stack.y_mm.values, {"units": "mm"}),
                            "bound": ["low", "high"], "param": names})
    determined = np.ones(shape + (5,), bool)
    determined[7, 2:6, 1] = False
    for j, n in enumerate(names):
        v = stack[f"true_{n}"].values + rng.normal(0, 0.01, shape)
        v[status < 0] = np.nan
        w = np.where(determined[..., j], 0.05, 5.0)
        ds[n] = (("y", "x"), v, {"units": "1", "long_name": f"the parameter {n}"})
        ds[f"{n}_ci95"] = (("y", "x", "bound"), np.stack([v - w / 2, v + w / 2], axis=-1))
    ds["n"].values[3, 3] = 40.0             # one outlier
    ds["status"] = (("y", "x"), status)
    ds["determined"] = (("y", "x", "param"), determined & (status >= 0)[..., None])
    ds.attrs.update(free=" ".join(names), model="six-param")
    return ds, stack


def drawn(ds, truth, tmp_path):
    """The figure plot_batch_maps draws and writes (drawn on an Agg canvas here, for its renderer)."""
    fig = batch_plots.plot_batch_maps(ds, tmp_path / "maps.png", truth=truth)
    assert (tmp_path / "maps.png").stat().st_size > 0
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    FigureCanvasAgg(fig).draw()
    return fig


@pytest.fixture
def figure(result, tmp_path):
    return drawn(result[0], result[1], tmp_path)


def panel(fig, title_start):
    (ax,) = [a for a in fig.axes if a.get_title().replace("\n", " ").startswith(title_start)]
    return ax


def test_maps_are_drawn_in_the_stacks_coordinates(figure, result):
    ax = panel(figure, "n: the parameter n")
    assert ax.get_xlabel() == "x_mm (mm)" and ax.get_ylabel() == "y_mm (mm)"
    x, y = result[0].x_mm.values, result[0].y_mm.values
    half = (x[1] - x[0]) / 2
    hy = (y[1] - y[0]) / 2  # y falls down the rows: row 0 at the top
    np.testing.assert_allclose(ax.images[0].get_extent(), [x[0] - half, x[-1] + half, y[-1] + hy, y[0] - hy])


def test_undetermined_and_not_converged_pixels_are_hatched(figure):
    def hatched(ax, hatch):
        cells = 0
        for coll in ax.collections:
            if isinstance(coll, PatchCollection) and coll.get_hatch() == hatch:
                for path in coll.get_paths():
                    x0, x1 = path.vertices[:, 0].min(), path.vertices[:, 0].max()
                    cells += round((x1 - x0) / (100 / 12))  # pixels of 100/12 mm, one row each
        return cells
    k = panel(figure, "k: the parameter k")
    assert hatched(k, "///") == 4 and hatched(k, "xxx") == 1
    assert hatched(panel(figure, "n: the parameter n"), "///") == 0  # n is determined there
    assert hatched(panel(figure, "k: width of the 95%"), "///") == 4
    assert hatched(panel(figure, "k: truth"), "///") == 0
    texts = [t.get_text() for leg in figure.legends + [a.get_legend() for a in figure.axes if a.get_legend()]
             for t in leg.get_texts()]
    texts += [t.get_text() for a in figure.axes for art in a.artists if hasattr(art, "get_texts")
              for t in art.get_texts()]
    assert any(t.startswith("this parameter undetermined") for t in texts)
    assert any(t.startswith("not converged") for t in texts)
    assert any(t.startswith("no value: not fitted") for t in texts)  # the grey of missing pixels


def test_one_outlier_does_not_set_the_colour_scale(figure, result):
    ax = panel(figure, "n: the parameter n")
    lo, hi = ax.images[0].get_clim()
    assert hi < 2.0 < 40.0  # the outlier (40) lies far beyond; the truth (1.405, 1.6) within
    assert lo <= 1.405 and hi >= 1.6
    cb = ax.images[0].colorbar
    assert cb.extend in ("max", "both") and "percentile" in cb.ax.get_ylabel()


def test_titles_are_not_cut_by_colour_bars(figure):
    renderer = figure.canvas.get_renderer()
    bars = [a.images[0].colorbar.ax for a in figure.axes if a.images and a.images[0].colorbar is not None]
    assert len(bars) == 15
    for ax in figure.axes:
        title = ax.title
        if not title.get_text():
            continue
        box = title.get_window_extent(renderer)
        for bar in bars:  # the bar, its ticks and its label
            for part in (bar.get_window_extent(renderer), bar.yaxis.get_tightbbox(renderer)):
                assert not box.overlaps(part), title.get_text()
        assert box.x0 >= 0 and box.x1 <= figure.bbox.width


def test_a_result_without_coordinates_is_drawn_in_pixel_indices(tmp_path, result):
    fig = drawn(result[0].drop_vars(["x_mm", "y_mm"]), None, tmp_path)
    ax = panel(fig, "n: the parameter n")
    assert ax.get_xlabel() == "x (index)" and ax.get_ylabel() == "y (index)"
    np.testing.assert_allclose(ax.images[0].get_extent(), [-0.5, 11.5, 11.5, -0.5])
