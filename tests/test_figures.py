"""Figures users read: nothing clipped, contour labels inside the axes and apart, a floor for
log-scaled BRDF maps, legends that say what is drawn, visible error bars, units xarray shows well."""
import itertools
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib import colors
from matplotlib.container import ErrorbarContainer
from matplotlib.layout_engine import ConstrainedLayoutEngine

import pbrdf_cl
from pbrdf_cl.analysis import maps, paper
from pbrdf_cl.compute import dense
from pbrdf_cl.io.measurements import from_arrays
from pbrdf_cl.plots import fit as plots
from pbrdf_cl.plots import maps as map_plots

STEEL = dict(n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3)


def renderer(fig):
    """The figure drawn again, as it was saved, on an Agg canvas (a closed figure has none)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def assert_nothing_clipped(fig):
    """The figure uses constrained layout and everything drawn (titles, labels, tick labels,
    legends, colour bars, contour labels: the figure's tight bounding box) lies inside it."""
    assert isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)
    tight = fig.get_tightbbox(renderer(fig))  # inches
    w, h = fig.get_size_inches()
    tol = 1.0 / fig.dpi
    assert tight.x0 >= -tol and tight.y0 >= -tol and tight.x1 <= w + tol and tight.y1 <= h + tol, \
        f"drawn {tight} outside the figure's {w} x {h} inches"
    return tight


def contour_labels(fig):
    return [t for ax in fig.axes for c in ax.collections if hasattr(c, "labelTexts") for t in c.labelTexts]


def assert_labels_readable(fig):
    """Contour labels inside their axes (away from the edges) and not overlapping each other."""
    r = renderer(fig)
    labels = contour_labels(fig)
    for t in labels:
        e, a = t.get_window_extent(r), t.axes.get_window_extent(r)
        assert a.x0 < e.x0 and e.x1 < a.x1 and a.y0 < e.y0 and e.y1 < a.y1, f"label {t.get_text()} leaves its axes"
    for s, t in itertools.combinations(labels, 2):
        if s.axes is t.axes:
            assert not s.get_window_extent(r).overlaps(t.get_window_extent(r)), \
                f"labels {s.get_text()} and {t.get_text()} overlap"
    return labels


def dop_map(derivative=None, quantity="dop", fixed=STEEL, y="sigma=0.02:1@64"):
    return maps.make_map("theta_r=0:85@64", y, dict(theta_i=40, **fixed), quantity=quantity, derivative=derivative,
                         backend="numpy")


@pytest.mark.parametrize("derivative", [None, "sigma"])
def test_dop_maps_use_constrained_layout_and_label_contours_inside(tmp_path, derivative):
    fig = map_plots.plot_map(dop_map(derivative), tmp_path / "m.png")
    assert_nothing_clipped(fig)
    labels = assert_labels_readable(fig)
    assert len(labels) >= 3
    # at least LABEL_MARGIN of the axes from every edge, LABEL_SPACING apart
    ax = fig.axes[0]
    frac = np.array([ax.transAxes.inverted().transform(ax.transData.transform(t.get_position())) for t in labels])
    assert frac.min() >= map_plots.LABEL_MARGIN - 1e-9 and frac.max() <= 1 - map_plots.LABEL_MARGIN + 1e-9
    d = np.hypot(*(frac[:, None, :] - frac[None, :, :]).transpose(2, 0, 1))
    assert d[np.triu_indices(len(frac), 1)].min() >= map_plots.LABEL_SPACING - 1e-9
    # one label per level at most, levels round numbers
    values = [float(t.get_text()) for t in labels]
    assert len(set(values)) == len(values)
    assert all(abs(v * 20 - round(v * 20)) < 1e-9 for v in values), values


def test_dop_map_colours_span_the_data_and_the_derivative_has_no_false_zero_line(tmp_path):
    """The DOP's colour bar runs over the data (0 .. 0.43 here), not to 1; the derivative's zero
    line is where dDOP/dsigma changes sign, not along the first row (sigma = 0.05, where the DOP
    rises by decades from row to row)."""
    ds = maps.make_map("theta_r=0:85@128", "sigma=0.05:1@128", dict(theta_i=40, **STEEL), derivative="sigma",
                       backend="numpy")
    z = ds["dop"].values
    fig = map_plots.plot_map(ds, tmp_path / "m.png")
    norm = fig.axes[0].collections[0].norm
    assert norm.vmin == pytest.approx(z.min()) and norm.vmax == pytest.approx(z.max()) and z.max() < 0.45
    d = ds["ddop_dsigma"].values
    first = d[0]
    with np.errstate(all="ignore"):
        rising = ds["dop"].values[1] > ds["dop"].values[0] * (1 + 1e-3)
    assert rising.sum() > 80 and (first[rising] > 0).all()
    assert_nothing_clipped(fig)


def test_a_long_title_is_wrapped_not_clipped(tmp_path):
    ds = dop_map()
    fig = map_plots.plot_map(ds, tmp_path / "m.png")
    assert "\n" in fig.get_suptitle()  # one 6.2-inch panel: the fixed values go on a second line
    assert_nothing_clipped(fig)


def test_brdf_map_with_kd_0_has_a_log_floor(tmp_path):
    ds = dop_map(quantity="brdf", fixed=dict(n=1.6, k=2.139, kd=0.0), derivative="sigma")
    z = ds["brdf"].values
    assert z.min() < z.max() * 1e-10  # the map spans more than ten decades ...
    fig = map_plots.plot_map(ds, tmp_path / "b.png")
    mesh = fig.axes[0].collections[0]
    norm = mesh.norm
    assert isinstance(norm, colors.LogNorm)
    assert norm.vmax == pytest.approx(z.max()) and norm.vmin == pytest.approx(z.max() / 10 ** map_plots.LOG_DECADES)
    cbar = mesh.colorbar
    assert cbar.extend == "min"  # the clipped values: the triangle below the bar
    assert f"clipped below max/1e{map_plots.LOG_DECADES} = {norm.vmin:.2g}" in cbar.ax.get_ylabel()
    # contour levels are decades within the shown range, labelled as plain numbers
    levels = fig.axes[0].collections[1].levels
    np.testing.assert_allclose(np.log10(levels), np.round(np.log10(levels)))
    assert levels.min() >= norm.vmin
    assert_nothing_clipped(fig)
    assert_labels_readable(fig)
    # the derivative's symmetric-log colour bar: ticks apart (0 and decades only)
    d_cbar = fig.axes[1].collections[0].colorbar
    ticks = d_cbar.get_ticks()
    pos = d_cbar.norm(ticks)
    assert 0.0 in ticks and np.diff(np.sort(pos)).min() >= 0.07 - 1e-9


def test_brdf_map_within_two_decades_stays_linear_and_a_narrow_log_map_is_not_clipped():
    assert map_plots._norm_for(np.linspace(1.0, 50.0, 10), "brdf") == (None, "")
    norm, note = map_plots._norm_for(np.geomspace(1e-3, 10.0, 10), "brdf")
    assert isinstance(norm, colors.LogNorm) and norm.vmin == pytest.approx(1e-3) and note == "log scale"
    norm, note = map_plots._norm_for(np.array([0.0, 1e-9, 1.0, 20.0]), "brdf")
    assert norm.vmin == pytest.approx(20.0 / 10 ** map_plots.LOG_DECADES) and "clipped" in note
    assert map_plots._norm_for(np.geomspace(1e-9, 1.0, 10), "dop") == (None, "")


def test_aop_map(tmp_path):
    ds = dop_map(quantity="aop", fixed=dict(n=1.6, k=2.139, sigma=0.3, kd=0.1), y="phi=0:360@48")
    fig = map_plots.plot_map(ds, tmp_path / "a.png")
    assert_nothing_clipped(fig)
    np.testing.assert_array_equal(fig.axes[0].collections[0].colorbar.get_ticks(), [-90, -45, 0, 45, 90])
    assert not contour_labels(fig)  # an angle: no contour lines across its wrap


def fake_fits():
    six = dict(n=1.6, k=2.139, sigma=0.5, ks=1.0, kd=0.15, c=-0.3)
    return {"six-param": SimpleNamespace(x=six, shadowing="paper", bic=10.0),
            "specular": SimpleNamespace(x=dict(n=3.0, k=3.5), shadowing="paper", bic=20.0)}


def steel_data(with_std=True):
    ti, tr = np.repeat([30.0, 40.0, 50.0], 10), np.tile(np.arange(20.0, 66.0, 5.0), 3)
    rng = np.random.default_rng(3)
    dop = pbrdf_cl.dop(ti, tr, backend="numpy", **fake_fits()["six-param"].x) + rng.normal(0, 0.002, ti.size)
    return from_arrays(ti, tr, dop, dop_std=np.full(ti.size, 0.002) if with_std else None, source="dir/steel.csv")


def test_fit_plot_error_bars_and_legends(tmp_path):
    meas = steel_data()
    fig = plots.plot_fit(meas, fake_fits(), tmp_path / "fit.png")
    assert_nothing_clipped(fig)
    ax, axr = fig.axes
    # error bars: on the data (top) and on every residual (bottom), +-1 dop_std long
    for a, per_group in ((ax, 1), (axr, 2)):
        bars = [c for c in a.containers if isinstance(c, ErrorbarContainer)]
        assert len(bars) == 3 * per_group
        for c in bars:
            segs = c.lines[2][0].get_segments()
            assert len(segs) == 10
            np.testing.assert_allclose([s[1, 1] - s[0, 1] for s in segs], 2 * 0.002)
    # the bars stick out of the markers on the residual scale: 0.002 is many points tall there
    px = abs(axr.transData.transform((0, 0.002))[1] - axr.transData.transform((0, 0))[1]) * 72 / fig.dpi
    assert px > 8
    # top legend: one data entry per theta_i (its colour) and the models' line styles in black
    top = ax.get_legend()
    labels = [t.get_text() for t in top.get_texts()]
    assert labels == ["data ± 1 sd, theta_i = 30 deg", "data ± 1 sd, theta_i = 40 deg",
                      "data ± 1 sd, theta_i = 50 deg", "six-param fit", "specular fit"]
    handles = top.legend_handles
    assert [colors.to_hex(h.get_color()) for h in handles[3:]] == ["#000000", "#000000"]
    assert [h.get_linestyle() for h in handles[3:]] == ["-", "--"]
    # residual legend: the models' markers (neutral colour); the colours are theta_i's, as its title says
    bottom = axr.get_legend()
    assert [t.get_text() for t in bottom.get_texts()] == ["six-param", "specular"]
    assert [h.get_marker() for h in bottom.legend_handles] == ["o", "x"]
    assert all(colors.to_hex(h.get_color()) == "#000000" for h in bottom.legend_handles)
    assert "colour: theta_i as above" in bottom.get_title().get_text()
    # the residual points of one theta_i share the top panel's colour of that theta_i
    top_colors = [colors.to_hex(c.lines[0].get_color()) for c in ax.containers]
    res_colors = [colors.to_hex(c.lines[0].get_color()) for c in axr.containers]
    assert res_colors == [c for c in top_colors for _ in range(2)]


def test_fit_plot_without_dop_std_says_so(tmp_path):
    fig = plots.plot_fit(steel_data(with_std=False), fake_fits(), tmp_path / "fit.png")
    ax, axr = fig.axes
    assert "no dop_std: no error bars" in axr.get_legend().get_title().get_text()
    assert [t.get_text() for t in ax.get_legend().get_texts()][0] == "data, theta_i = 30 deg"


def test_paper_figures_label_what_is_drawn(tmp_path):
    fig = paper.fig4(tmp_path)
    assert_nothing_clipped(fig)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels[:3] == ["model, theta_i = 30 deg", "model, theta_i = 40 deg", "model, theta_i = 50 deg"]
    assert labels[3].startswith("model at the measured geometries") and "not data" in labels[3]
    assert not any(label.startswith("data") for label in labels)
    fig = paper.fig5(tmp_path)
    assert_nothing_clipped(fig)
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == \
        ["model, sigma = 0.35", "model, sigma = 0.5", "model, sigma = 0.65"]


def test_paper_map_of_three_panels_labels_contours_inside(tmp_path, monkeypatch):
    from matplotlib.figure import Figure
    saved, savefig = [], Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: (saved.append(fig), savefig(fig, *a, **k)))
    paper.map_theta_i_theta_r(tmp_path, resolution=64, engine=pbrdf_cl.NumpyEngine())
    (fig,) = saved
    assert_nothing_clipped(fig)
    labels = assert_labels_readable(fig)
    assert {t.axes for t in labels} == set(fig.axes[:3])  # every panel has labels


def test_sigma_units_read_well_in_xarray():
    assert dense.UNITS["sigma"] == "1"
    assert dense.LONG_NAMES["sigma"] == "per-axis rms slope"
    da = pbrdf_cl.grid({"sigma": [0.2, 0.5]}, dict(theta_i=40, theta_r=30, n=1.6, k=2), backend="numpy")
    assert da["sigma"].attrs == {"units": "1", "long_name": "per-axis rms slope"}
    import matplotlib.pyplot as plt
    grid = pbrdf_cl.grid({"theta_r": [10.0, 20.0, 30.0], "sigma": [0.2, 0.5]}, dict(theta_i=40, n=1.6, k=2),
                         backend="numpy")
    line = grid.isel(sigma=1).plot()[0]
    assert line.axes.get_title() == "sigma = 0.5 [1]"  # xarray's own title, no "[1 (per-axis rms slope)]"
    plt.figure()
    mesh = grid.plot()
    assert mesh.axes.get_xlabel() == "per-axis rms slope [1]"
    plt.close("all")
