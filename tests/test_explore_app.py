"""The interactive explorer (issue #29): its state and numbers without a browser, the parameter-set
files that eval and map read, and the page itself in a real browser (Debian's chromium through
chromedriver, driven by Selenium): a slider moved, the plotted DOP against ``pbrdf_cl.dop``, the
example CSV loaded and fitted, the fitted values against ``pbrdf_cl.fit``'s, the state in the URL."""
import html
import io
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from urllib.parse import parse_qs, urlparse

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.app import state as st
from pbrdf_cl.cli import main
from pbrdf_cl.io.params import params_text, read_params

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "steel_435nm.csv"


def test_importing_pbrdf_cl_does_not_import_panel():
    code = "import sys, pbrdf_cl, pbrdf_cl.analysis.maps; print('panel' in sys.modules, 'bokeh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.stdout.split() == ["False", "False"]


def test_without_panel_one_line_names_the_extra(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "panel", None)  # import panel -> ImportError
    with pytest.raises(pbrdf_cl.CommandError, match=r"pip install 'pbrdf-cl\[explore\]'"):
        pbrdf_cl.explore()
    assert main(["explore", "--no-browser"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pbrdf-cl[explore]" in err and "Traceback" not in err


def test_hemisphere_in_plane_line_is_the_in_plane_dop():
    """The hemisphere seen from above: on the x axis right of the centre phi = 180 (in plane), left
    of it phi = 0; theta_r = 90 x."""
    engine = pbrdf_cl.get_default_engine()
    state = st.State()
    state.settings.map_kind, state.settings.resolution = "hemisphere", 65
    x, y, v = st.hemisphere_map(engine, state)
    row = v[32]  # y = 0
    inside = np.abs(x) * 90 <= st.THETA_MAX
    right, left = (x > 0.05) & inside, (x < -0.05) & inside
    ti = state.settings.theta_i[0]
    assert np.allclose(row[right], pbrdf_cl.dop(ti, 90 * x[right], 180, **st.STEEL), rtol=1e-12)
    assert np.allclose(row[left], pbrdf_cl.dop(ti, 90 * -x[left], 0, **st.STEEL), rtol=1e-12)
    assert np.isnan(v[0, 0])  # a corner: outside the disc


def test_hemisphere_ticks_lie_along_the_facets_s_axis():
    """Off the plane too: for unpolarized light each facet reflects more s than p (Rs > Rp), and the
    diffuse term adds unpolarized light only, so the reflected light is polarized along the
    facet's s axis, unit(k_in x h) with h = unit(w_i + w_r) (SPEC). Each tick on the hemisphere
    map, drawn from the model's AoP through the beam's s and p axes, must be parallel to that
    axis seen from above (the source at azimuth 180, on the left). A mirrored azimuth or a flipped
    AoP sign would turn the off-plane ticks the other way."""
    view = st.State()
    view.settings.map_kind, view.settings.quantity, view.settings.theta_i = "hemisphere", "aop", [40.0]
    view.sets[0] = dict(st.STEEL, kd=0.3)
    x0, y0, x1, y1 = st.aop_ticks(pbrdf_cl.get_default_engine(), view, count=21)
    cx, cy, d = (x0 + x1) / 2, (y0 + y1) / 2, np.stack([x1 - x0, y1 - y0], -1)
    tr, pr = np.radians(90.0 * np.hypot(cx, cy)), np.arctan2(cy, cx)
    ti = np.radians(40.0)
    w_i = np.array([-np.sin(ti), 0.0, np.cos(ti)])
    w_r = np.stack([np.sin(tr) * np.cos(pr), np.sin(tr) * np.sin(pr), np.cos(tr)], -1)
    h = w_i + w_r
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    s_f = np.cross(-w_i, h)
    s_f /= np.linalg.norm(s_f, axis=-1, keepdims=True)
    seen = s_f[:, :2]
    ok = np.linalg.norm(seen, axis=-1) > 0.2  # the axis not nearly vertical: its direction from above is defined
    assert ok.sum() > 150 and (np.abs(cy[ok]) > 0.3).sum() > 40  # well off the plane, both sides
    cross = d[ok, 0] * seen[ok, 1] - d[ok, 1] * seen[ok, 0]
    sin_angle = np.abs(cross) / (np.linalg.norm(d[ok], axis=-1) * np.linalg.norm(seen[ok], axis=-1))
    assert sin_angle.max() < 1e-6, sin_angle.max()


def test_state_survives_the_url_and_bad_urls_are_one_line():
    state = st.State()
    state.sets[1] = dict(st.STEEL, n=2.25, sigma=0.31)
    state.shown, state.solo, state.active = [True, True, False, False], 1, 1
    state.settings.quantity, state.settings.theta_i, state.settings.phi = "aop", (20.0, 60.0), 150.0
    args = {k: v[0] for k, v in parse_qs(st.to_query(state)).items()}
    assert st.from_query(args) == state
    with pytest.raises(ValueError, match=r"^URL: B: n = 9 is outside \[1, 5\]$"):
        st.from_query({**args, "B": "9,2,0.5,1,0,0"})
    with pytest.raises(ValueError, match=r"^URL: q='dopp' is not one of"):
        st.from_query({**args, "q": "dopp"})


def test_parameter_files_round_trip_through_eval_and_map(tmp_path, capsys):
    values = dict(n=1.7, k=2.5, sigma=0.4, ks=0.8, kd=0.2, c=-0.4)
    for fmt in ("json", "toml"):
        path = tmp_path / f"set.{fmt}"
        path.write_text(params_text(values, fmt))
        assert read_params(path) == values
        assert main(["eval", "--theta-i", "40", "--theta-r", "45", "--params", str(path), "--json"]) == 0
        out = capsys.readouterr().out
        import json
        row = json.loads(out)["rows"][0]
        assert row["dop"] == pytest.approx(float(pbrdf_cl.dop(40, 45, **values)), rel=1e-12)
    png = tmp_path / "map.png"
    assert main(["map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:0.9@8", "--fix", "theta_i=40",
                 "--params", str(tmp_path / "set.toml"), "--out", str(png)]) == 0
    assert png.stat().st_size > 0
    bad = tmp_path / "bad.json"
    bad.write_text('{"n": 1.6, "sigmaa": 0.5}')
    assert main(["eval", "--theta-i", "40", "--theta-r", "45", "--params", str(bad)]) == 1
    err = capsys.readouterr().err
    assert err == f"pbrdf-cl: error: {bad}: unknown parameter 'sigmaa'; did you mean sigma? (the parameters are " \
                  "n, k, sigma, ks, kd, c)\n"


def test_page_without_a_browser(tmp_path, capsys):
    """The page object itself: a slider moves the curves to pbrdf_cl.dop's values; a bad CSV is
    the CLI's one line; the view's numbers export."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    page = pbrdf_cl.explore()
    ex = page.explorer
    ex.sliders["sigma"].value = 0.37
    tr = np.asarray(ex.figs.curve_src[0].data["xs"][1])
    expected = pbrdf_cl.dop(40, tr, 180, **dict(st.STEEL, sigma=0.37))
    assert np.array_equal(np.asarray(ex.figs.curve_src[0].data["ys"][1]), expected)
    bad = tmp_path / "bad.csv"
    bad.write_text("theta_i,theta_r,dop\n30,20,0.05\n30,x,0.1\n")
    assert main(["fit", str(bad)]) == 1
    cli_line = capsys.readouterr().err.strip().replace("pbrdf-cl: error: ", "")
    assert not ex.load_path(bad, str(bad))
    assert f"error: {cli_line}" in ex.status.object
    ds = ex.dataset()
    assert ds["curve"].sel(set="A", theta_i=40).values.tolist() == expected.tolist()

    import xarray as xr
    back = xr.open_dataset(io.BytesIO(ex._netcdf().getvalue()))
    assert np.array_equal(back["map"].values, ds["map"].values, equal_nan=True)
    assert "theta_r" in ex._csv().getvalue().splitlines()[1]
    assert read_params_text(ex._params("toml").getvalue(), tmp_path)["sigma"] == 0.37
    png = ex._png().getvalue()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_png_export_draws_the_polar_plot_and_the_aop_ticks():
    """The *view as PNG* figure has the page's polar plot (radius |value| at theta_r from the
    normal) and, for the AoP, the page's orientation ticks over the map, one segment each."""
    from matplotlib.collections import LineCollection

    from pbrdf_cl.plots.explorer import plot_view
    eng = pbrdf_cl.get_default_engine()
    for kind in ("incidence", "hemisphere"):
        view = st.State()
        view.settings.quantity, view.settings.map_kind, view.settings.resolution = "aop", kind, 32
        ds = st.view_dataset(eng, view)
        ticks = st.aop_ticks(eng, view)
        assert ticks[0].size > 50
        for name, values in zip(("tick_x0", "tick_y0", "tick_x1", "tick_y1"), ticks):
            assert np.array_equal(ds[name].values, values)
        fig = plot_view(ds, io.BytesIO())
        polar = [ax for ax in fig.axes if ax.name == "polar"]
        assert len(polar) == 1 and len(polar[0].lines) == ds["curve"].sizes["theta_i"]
        r = polar[0].lines[0].get_ydata()
        assert np.allclose(r, np.abs(ds["curve"].values[0, 0]), equal_nan=True)
        drawn = [c for ax in fig.axes for c in ax.collections
                 if isinstance(c, LineCollection) and c.get_label() == "AoP orientation"]
        assert len(drawn) == 1 and len(drawn[0].get_segments()) == ticks[0].size
    view = st.State()
    view.settings.resolution = 32
    assert "tick_x0" not in st.view_dataset(eng, view)  # DOP: no ticks, as on the page


def test_page_design_and_sobol_use_the_chosen_sizes():
    """The design runs with the page's DOP noise and count, the Sobol' map with its N; each equals
    the library call with those settings; a noise of 0 is refused on the page in design()'s one line."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    import asyncio

    from pbrdf_cl.app.page import Explorer
    ex = Explorer()
    ex.design_noise.value, ex.design_count.value = 0.002, 8
    asyncio.run(ex._on_design(None))
    r = ex.design_result
    assert len(r.theta_i) == 8 and "DOP noise 0.002" in ex.jobs.object
    want = pbrdf_cl.design(st.STEEL, {"theta_i": "10:80:5", "theta_r": "0:85:5"}, noise=0.002, n_measurements=8)
    assert np.array_equal(r.theta_i, want.theta_i) and np.array_equal(r.theta_r, want.theta_r)
    assert r.ci95_width["n"] == pytest.approx(want.ci95_width["n"], rel=1e-9)
    assert list(r.instrument_comparisons["chosen"]) == ["dop", "camera45", "camera4", "mueller"]
    ex.design_instrument.value = "mueller"  # chosen for the polarimeter; every instrument in the table
    asyncio.run(ex._on_design(None))
    r = ex.design_result
    want = pbrdf_cl.design(st.STEEL, {"theta_i": "10:80:5", "theta_r": "0:85:5"}, noise=0.002, n_measurements=8,
                           instrument="mueller,dop,camera45,camera4")
    assert np.array_equal(r.theta_i, want.theta_i) and np.array_equal(r.theta_r, want.theta_r)
    cells = "".join(f"<td>{want.instrument_comparisons[s]['camera4']['widths'][p]:.3g}</td>"
                    for s in ("chosen", "reference") for p in ("n", "k"))
    assert "(mueller noise 0.002)" in ex.jobs.object and f"<tr><td>camera4</td>{cells}</tr>" in ex.jobs.object
    ex.design_noise.value = 0.0
    asyncio.run(ex._on_design(None))
    assert "design: error: noise must be a positive number, got 0.0" in ex.jobs.object and ex.design_result is r
    ex.sobol_n.value = 64
    asyncio.run(ex._on_sobol(None))
    assert ex.sobol_ds.attrs["N"] == 64
    assert ex.load_path(EXAMPLE, EXAMPLE.name)  # its dop_std becomes the design's noise
    assert ex.design_noise.value == pytest.approx(float(np.median(pbrdf_cl.read_csv(EXAMPLE).dop_std)), abs=1e-6)


def test_explore_command_refuses_bad_input_in_one_line(tmp_path, capsys):
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    bad = tmp_path / "bad.csv"
    bad.write_text("theta_i,theta_r\n30,20\n")
    assert main(["fit", str(bad)]) == 1
    fit_err = capsys.readouterr().err
    assert main(["explore", "--no-browser", "--data", str(bad)]) == 1
    assert capsys.readouterr().err == fit_err  # the same line as `pbrdf-cl fit`
    assert main(["explore", "--no-browser", "--port", "70000"]) == 1
    assert capsys.readouterr().err == "pbrdf-cl: error: --port 70000: give a port in 0..65535 (0: any free one)\n"


def _page(query=None):
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from pbrdf_cl.app.page import Explorer
    return Explorer(query=query)


def _red(pane):
    """The text of a pane's red line, or None."""
    text = html.unescape(pane.object)
    return text if "color:#b00020" in text else None


def test_url_refuses_each_bad_value_in_one_line_and_keeps_the_others():
    """A bad show= no longer draws nothing silently; every bad value (and an unknown key) is one
    line naming it, and the link's other values still hold."""
    for args, line in (({"show": "XY"}, "URL: show='XY': 'X', 'Y' are not sets; give letters of ABCD "
                                         "(show=AB: sets A and B)"),
                       ({"phi": "400"}, "URL: phi = 400 is outside [0, 359.5] (degrees)"),
                       ({"phi": "nan"}, "URL: phi = nan is outside [0, 359.5] (degrees)"),
                       ({"ti": "30,95"}, "URL: ti: theta_i = '30,95': angles must be in [0, 90) degrees, got 95"),
                       ({"sho": "AB"}, "URL: unknown key 'sho' (the keys are A, B, C, D, show, active, solo, q, "
                                       "model, shadowing, dtype, ti, phi, map, inc)")):
        with pytest.raises(ValueError) as caught:
            st.from_query({"q": "aop", **args})
        assert str(caught.value) == line
        problems = {}
        state = st.from_query({"q": "aop", "B": "2,2,0.5,1,0,0", **args}, problems)
        assert problems == {next(iter(args)): line}
        assert state.settings.quantity == "aop" and state.sets[1]["n"] == 2.0  # the rest of the link holds
    assert st.from_query({"show": ""}).shown == [False] * 4  # what to_query writes when no set is shown
    ex = _page({"show": "XY", "phi": "400", "q": "aop"})
    assert _red(ex.status) == ("<span style=\"color:#b00020\">error: URL: show='XY': 'X', 'Y' are not sets; "
                               "give letters of ABCD (show=AB: sets A and B); URL: phi = 400 is outside [0, 359.5] "
                               "(degrees)</span>")
    assert set(ex.refused) == {"show", "phi"} and ex.state.visible() == [0] and ex.state.settings.quantity == "aop"


def test_entries_refuse_bad_values_in_one_line_and_snap_back():
    """Every number entry checks what is typed: one red line naming the field and its range, and
    the entry back to the value in use (no 180400 left in it, no NaN); a good value moves its slider."""
    ex = _page()
    for typed, line in ((180400, "phi = 180400 is outside [0, 359.5] (degrees); it stays 180"),
                        (None, "phi is empty: give a number in [0, 359.5] (degrees); it stays 180"),
                        (float("inf"), "phi = inf is not a finite number: give one in [0, 359.5] (degrees); "
                                       "it stays 180")):
        ex.phi.entry.value = typed
        assert _red(ex.status).endswith(f"error: {line}</span>")
        assert ex.phi.value == ex.phi.entry.value == ex.phi.slider.value == ex.state.settings.phi == 180.0
    ex.sliders["n"].entry.value = 9.0
    assert "error: n = 9 is outside [1, 5]; it stays 1.6" in _red(ex.status)
    assert ex.sliders["n"].entry.value == ex.state.sets[0]["n"] == 1.6
    ex.sliders["k"].entry.value = 8.4e-07  # a good value: taken, the slider follows, the red line goes
    assert ex.state.sets[0]["k"] == ex.sliders["k"].slider.value == 8.4e-07 and _red(ex.status) is None
    ex.theta_i.value = "30,95"
    assert "error: theta_i = '30,95': angles must be in [0, 90) degrees, got 95; it stays 30,40,50" in \
        _red(ex.status)
    assert ex.theta_i.value == "30,40,50"
    for entry, typed, line in ((ex.sobol_share, 0.9, "the box's share = 0.9 is outside [0.01, 0.5]; it stays 0.1"),
                               (ex.design_noise, 0.0, "DOP noise = 0 is outside [0.0001, 0.1]; it stays 0.005"),
                               (ex.design_count, 3, "measurements = 3 is outside [5, 200]; it stays 30")):
        before = entry.value
        entry.entry.value = typed
        assert _red(ex.jobs).endswith(f"error: {line}</span>") and entry.value == entry.entry.value == before


def test_upload_names_the_users_file_warns_of_radians_at_once_and_refuses_an_empty_file():
    """The warnings of an uploaded file name it (not the server's temporary copy); radians are said
    at load, in the library's words; an empty file is one line."""
    from pbrdf_cl.compute.pointwise import check_degrees
    ex = _page()
    ex.upload.param.update(filename="empty.csv", value=None)  # what Panel gives for an empty file: value unchanged
    assert _red(ex.status).endswith("error: empty.csv: empty file (no header line)</span>")
    text = b"theta_i,theta_r,dop,extra\n0.5,0.3,0.1,1\n0.5,0.6,0.2,1\n0.7,0.9,0.3,1\n"
    ex.upload.param.update(filename="radians.csv", value=text)
    info = html.unescape(ex.data_info.object)
    with pytest.warns(pbrdf_cl.UnitsWarning) as said:
        check_degrees(ex.meas.theta_i, ex.meas.theta_r, "radians.csv: ")
    assert f"warning: {said[0].message}" in info
    assert "warning: radians.csv, line 1: ignored column 'extra'" in info
    assert tempfile.gettempdir() not in info and ex.meas.source == "radians.csv"


def test_a_note_says_when_shown_sets_draw_the_same_curves():
    """Set B over set A hides it: where their curves are the same (by evaluation: the AoP here),
    the page says so and names what differs; otherwise nothing is said."""
    eng = pbrdf_cl.get_default_engine()
    a, b = dict(st.STEEL), dict(st.STEEL, n=2.3, sigma=0.3, kd=0.5)
    ti, tr = np.array([30.0, 50.0])[:, None], st.theta_r_axis()
    seen = set()
    for quantity in ("aop", "dop"):
        same = np.allclose(pbrdf_cl.evaluate(quantity, ti, tr, 150, **a), pbrdf_cl.evaluate(quantity, ti, tr, 150, **b),
                           rtol=1e-9, atol=1e-12, equal_nan=True)
        label = st.QUANTITIES[quantity][0]
        ex = _page({"A": ",".join(map(str, a.values())), "B": ",".join(map(str, b.values())), "show": "AB",
                    "q": quantity, "phi": "150", "ti": "30,50"})
        note = html.unescape(ex.status.object)
        seen.add(bool(same))
        if same:
            assert f"sets A and B give the same {label} here (they differ in n, sigma, kd): B is drawn over A" in note
            assert "#b00020" not in note  # a note, not an error
        else:
            assert note == ""
    assert seen == {True, False}  # both cases met
    view = st.State()
    view.shown = [True, False, True, False]
    assert st.curves_note(view, st.curves(eng, view)) == "sets A and C are equal: C is drawn over A"
    view.shown = [False] * 4
    assert st.curves_note(view, st.curves(eng, view)) == "no set is shown: choose one under show"


def test_curve_end_labels_do_not_pile_up():
    """The labels at the curves' right ends (theta_r = 89) are at least LABEL_GAP of the value range
    apart, in the order of the curves' ends."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from pbrdf_cl.app.figures import LABEL_GAP, Figures
    view = st.State()
    view.sets[1] = dict(st.STEEL, sigma=0.35)
    view.shown = [True, True, False, False]
    tr = st.theta_r_axis()
    values = st.curves(pbrdf_cl.get_default_engine(), view, tr)
    figs = Figures()
    figs.update_curves(tr, view.settings.theta_i, values, "dop")
    y = np.asarray(figs.label_src.data["y"])
    ends = np.concatenate([v[:, -1] for v in values.values()])
    allv = np.concatenate([v.ravel() for v in values.values()])
    gap = LABEL_GAP * (allv.max() - allv.min())
    assert np.diff(np.sort(ends)).min() < gap  # the curves' ends do lie closer than a label
    assert np.diff(np.sort(y)).min() >= gap * (1 - 1e-9)
    assert np.array_equal(np.argsort(y, kind="stable"), np.argsort(ends, kind="stable"))


def test_no_empty_band_above_the_sobol_maps():
    """The Sobol' maps follow the map in its own column (not a row under the taller of the two
    columns), and the fit table takes no room before there is a fit."""
    ex = _page()
    import panel as pn
    figs = ex.figs

    def shows(column, model):
        return any(getattr(o, "object", None) is model for o in column.select(pn.pane.Bokeh))
    column = next(c for c in ex.layout.select(pn.Column) if any(getattr(o, "object", None) is figs.map_fig
                                                               for o in c.objects))
    assert all(shows(column, fig) for fig in figs.sobol_figs)
    assert not figs.fit_table.visible
    ex._show_fit(pbrdf_cl.fit(str(EXAMPLE)))
    assert figs.fit_table.visible


def test_fit_table_prints_significant_digits():
    """k = 8.4e-07 is printed as 8.4e-07, not 0.00000; the table keeps the numbers themselves too."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from types import SimpleNamespace

    from pbrdf_cl.app.figures import Figures
    figs = Figures()
    r = SimpleNamespace(free=("n", "k"), x=dict(n=1.754941234, k=8.4e-07),
                        ci95=dict(n=(1.280690001, 3.2485), k=(0.0, 1.23456789e-06)))
    figs.update_fit(r, None, None, None)
    d = figs.fit_table_src.data
    assert d["value"] == [1.754941234, 8.4e-07] and d["value_text"] == ["1.75494", "8.4e-07"]
    assert d["low_text"] == ["1.28069", "0"] and d["high_text"] == ["3.2485", "1.23457e-06"]
    assert [c.field for c in figs.fit_table.columns] == ["parameter", "value_text", "low_text", "high_text"]


def test_png_colour_bar_is_as_tall_as_the_map():
    """With residuals the map spans two rows of the figure; its colour bar stays beside it, as tall
    as the map, not as the figure."""
    from pbrdf_cl.plots.explorer import plot_view
    view = st.State()
    view.settings.resolution = 32
    ds = st.view_dataset(pbrdf_cl.get_default_engine(), view, pbrdf_cl.read_csv(EXAMPLE))
    fig = plot_view(ds, io.BytesIO())  # drawn: the positions are those of the PNG
    ax = next(a for a in fig.axes if a.get_title().startswith("set A over"))
    box, bar = ax.get_position(), ax.collections[0].colorbar.ax.get_position()
    pixel = 1 / (fig.get_size_inches()[1] * 110)  # in figure heights
    assert abs(bar.y0 - box.y0) <= pixel and abs(bar.y1 - box.y1) <= pixel and bar.x0 > box.x1


def test_port_in_use_is_one_line_naming_it(capsys):
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    import socket
    with socket.socket() as taken:
        taken.bind(("localhost", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["explore", "--no-browser", "--port", str(port)]) == 1
    err = capsys.readouterr().err
    assert err == (f"pbrdf-cl: error: port {port} is in use (Address already in use); choose another with --port N, "
                   "or --port 0 for a free one\n")


def test_port_0_allows_only_its_own_origin(served):
    """--port 0: only pages of localhost and 127.0.0.1 at the port bound may connect (no "*",
    no Bokeh warning of a wildcard)."""
    import asyncio

    from tornado.httpclient import HTTPClientError, HTTPRequest
    from tornado.websocket import websocket_connect
    proc, url = served
    port = urlparse(url).port

    async def handshake(origin):
        request = HTTPRequest(f"ws://localhost:{port}/explore/ws", headers={"Origin": origin})
        try:
            (await websocket_connect(request)).close()
        except HTTPClientError as exc:
            return exc.code
        return 101
    codes = {o: asyncio.run(handshake(o)) for o in (f"http://localhost:{port}", f"http://127.0.0.1:{port}",
                                                   "http://example.com", f"http://localhost:{port + 1}")}
    assert list(codes.values()) == [101, 101, 403, 403], codes
    assert "wildcard" not in "".join(proc.log_tail)


def read_params_text(text, folder):
    path = folder / "p.toml"
    path.write_text(text)
    return read_params(path)


@pytest.fixture(scope="module")
def served():
    """``pbrdf-cl explore --port 0`` in a child process, for the module: (process, page URL); the
    browser tests' page too."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from pbrdf_cl.app import drive
    proc, url = drive.start_server()  # a server that does not start is an error, not a skip
    yield proc, url
    drive.stop_server(proc)


@pytest.fixture(scope="module")
def browser(served):
    pytest.importorskip("selenium", reason="selenium is not installed (the test extra)")
    from pbrdf_cl.app import drive
    found, why = drive.find_browser()
    if found is None:
        pytest.skip(why)
    try:
        driver = drive.open_browser()
    except Exception as exc:  # noqa: BLE001 - a browser that cannot start here: say why
        pytest.skip(f"chromium did not start: {str(exc).splitlines()[0]}")
    yield driver, served[1]
    driver.quit()


def _slider_values(driver):
    return driver.execute_script("return Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
                                 ".filter(m => m.type == 'Slider').map(m => m.value)")


def test_in_the_browser_slider_fit_and_url(browser, tmp_path):
    from selenium.webdriver.common.keys import Keys

    from pbrdf_cl.app import drive
    driver, url = browser
    driver.get(url)
    before = drive.wait_loaded(driver)
    handle = drive.deep_find(driver, ".noUi-handle")[0]  # the first slider: n
    handle.send_keys(Keys.ARROW_RIGHT, Keys.ARROW_RIGHT)

    def plotted_is_the_dop():
        n = _slider_values(driver)[0]
        data = drive.source_data(driver, "curve_A")  # theta_i 30, 40, 50
        tr = np.asarray(data["xs"][0])
        want = pbrdf_cl.dop(np.array([30.0, 40.0, 50.0])[:, None], tr[None, :], 180, **dict(st.STEEL, n=n))
        return n if n != st.STEEL["n"] and np.allclose(data["ys"], want, rtol=1e-12, atol=0) else None
    n = drive.wait(plotted_is_the_dop, 60, what="curve_A equal to pbrdf_cl.dop at the slider's new n")
    assert n > st.STEEL["n"] and drive.source_data(driver, "curve_A")["ys"] != before["ys"]

    def query():  # the URL follows the views once they are still (250 ms)
        q = {k: v[0] for k, v in parse_qs(urlparse(driver.current_url).query).items()}
        return q if "A" in q and abs(float(q["A"].split(",")[0]) - n) < 1e-6 else None
    drive.wait(query, 30, what="the URL holding the new n")

    upload = drive.file_input(driver)
    bad = tmp_path / "steel_bad.csv"
    bad.write_text("theta_i,theta_r,dop\n30,20,0.05\n30,x,0.1\n")
    upload.send_keys(str(bad))
    shown = drive.wait(lambda: driver.execute_script(
        "return Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
        ".map(m => typeof m.text == 'string' ? m.text : '').find(t => t.includes('error: '))"),
        60, what="the bad file's error")
    assert "error: steel_bad.csv, line 3: theta_r = 'x' is not a number" in html.unescape(html.unescape(shown))
    upload.send_keys(str(EXAMPLE))
    drive.wait(lambda: drive.source_data(driver, "data_points")["x"], 60, what="the measurements")
    drive.button(driver, "Fit").click()
    table = drive.wait(lambda: (lambda d: d if d and d["value"] else None)(drive.source_data(driver, "fit_table")),
                       120, what="the fit")
    res = pbrdf_cl.fit(str(EXAMPLE))
    assert table["parameter"] == list(res.free)
    assert np.allclose(table["value"], [res.x[p] for p in res.free], rtol=1e-9, atol=1e-12)
    assert np.allclose(table["low"], [res.ci95[p][0] for p in res.free], rtol=1e-9, atol=1e-12)

    # a link reopens the same view
    driver.get(driver.current_url)
    drive.wait_loaded(driver)
    assert _slider_values(driver)[0] == pytest.approx(n, abs=1e-6)


def _said(driver, needle):
    """The page's text (HTML, unescaped) that holds ``needle``, or None."""
    found = driver.execute_script(
        "if (!window.Bokeh || !Bokeh.documents.length) return null;"
        "return Object.values(Object.fromEntries(Bokeh.documents[0]._all_models))"
        ".map(m => typeof m.text == 'string' ? m.text : '').find(t => t.includes(arguments[0]))",
        html.escape(needle, quote=True))
    return html.unescape(html.unescape(found)) if found else None


def test_in_the_browser_bad_input_is_said_and_undone(browser, tmp_path):
    """In the page: a link's bad values are one red line and leave the address bar; a value typed
    past its range or emptied is one red line and the entry shows the value in use again; an
    empty or radians CSV is said at once, naming the user's file."""
    from selenium.webdriver.common.keys import Keys

    from pbrdf_cl.app import drive
    driver, url = browser
    driver.get(url + "?show=XY&phi=400&q=aop")
    line = drive.wait(lambda: _said(driver, "error: URL: "), 60, what="the URL's refusal")
    assert "URL: show='XY': 'X', 'Y' are not sets" in line and "URL: phi = 400 is outside [0, 359.5]" in line
    drive.wait(lambda: urlparse(driver.current_url).query == "q=aop", 30, what="the refused values gone from the URL")
    drive.wait_loaded(driver)  # set A drawn: the default of show

    driver.get(url)
    drive.wait_loaded(driver)
    entries = drive.deep_find(driver, "input.bk-input")
    phi, k = entries[7], entries[1]
    assert phi.get_attribute("value") == "180" and k.get_attribute("value") == "2.139"
    phi.send_keys("400", Keys.ENTER)  # typed after the 180 already there
    drive.wait(lambda: _said(driver, "error: phi = 180400 is outside [0, 359.5] (degrees); it stays 180"), 30,
               what="phi's refusal")
    drive.wait(lambda: phi.get_attribute("value") == "180", 30, what="the phi entry back to 180")
    phi.clear()
    phi.send_keys(Keys.ENTER)
    drive.wait(lambda: _said(driver, "error: phi is empty: give a number in [0, 359.5]"), 30, what="phi emptied")
    drive.wait(lambda: phi.get_attribute("value") == "180", 30, what="the phi entry back to 180")
    k.send_keys(Keys.END, Keys.BACKSPACE * 5, "8.4e-7", Keys.ENTER)  # 2.139 -> 8.4e-7, then Enter
    drive.wait(lambda: _slider_values(driver)[1] == 8.4e-07, 30, what="k = 8.4e-07 on its slider")
    assert k.get_attribute("value") == "8.4e-7"

    upload = drive.file_input(driver)
    empty, radians = tmp_path / "empty.csv", tmp_path / "radians.csv"
    empty.write_text("")
    radians.write_text("theta_i,theta_r,dop\n0.5,0.3,0.1\n0.5,0.6,0.2\n0.7,0.9,0.3\n")
    upload.send_keys(str(empty))
    drive.wait(lambda: _said(driver, "error: empty.csv: empty file (no header line)"), 30, what="the empty file")
    upload.send_keys(str(radians))
    drive.wait(lambda: _said(driver, "warning: radians.csv: theta_i and theta_r all lie below"), 30,
               what="the radians warning")


CAMERA = ROOT / "examples" / "steel_camera_45.csv"
AT_45 = (0.0, 1.0, 0.0)


def test_views_under_a_polarized_source_are_pbrdf_cl_stokes():
    """The incident state as a setting: S0..S3, the normalised s1..s3, the DOP and the AoP of the
    curves are those of pbrdf_cl.stokes(incident=) for that state; under unpolarized light the
    views are pbrdf_cl.dop and pbrdf_cl.stokes as before."""
    eng = pbrdf_cl.get_default_engine()
    view = st.State()
    ti, tr = np.asarray(view.settings.theta_i)[:, None], st.theta_r_axis()[None, :]
    plain = pbrdf_cl.stokes(ti, tr, 180, **st.STEEL)
    view.settings.quantity = "s1"
    assert np.array_equal(st.curves(eng, view)[0], plain[..., 1])
    view.settings.quantity = "dop"
    assert np.array_equal(st.curves(eng, view)[0], pbrdf_cl.dop(ti, tr, 180, **st.STEEL))
    view.settings.incident = AT_45
    s = pbrdf_cl.stokes(ti, tr, 180, **st.STEEL, incident=AT_45)
    for quantity, want in (("s0", s[..., 0]), ("s3", s[..., 3]), ("s1n", s[..., 1] / s[..., 0]),
                           ("s3n", s[..., 3] / s[..., 0]), ("dop", np.linalg.norm(s[..., 1:], axis=-1) / s[..., 0]),
                           ("aop", np.degrees(np.arctan2(s[..., 2], s[..., 1])) / 2),
                           ("brdf", pbrdf_cl.brdf(ti, tr, 180, **st.STEEL))):
        view.settings.quantity = quantity
        np.testing.assert_allclose(st.curves(eng, view)[0], want, rtol=1e-12, err_msg=quantity)
    view.settings.quantity = "m23"
    m = pbrdf_cl.mueller(ti, tr, 180, **st.STEEL)
    np.testing.assert_allclose(st.curves(eng, view)[0], m[..., 2, 3] / m[..., 0, 0], rtol=1e-12)
    assert st.source_text(view.settings) == "" and st.QUANTITIES["m23"][:2] == ("m23 = M23/M00", "1")


def test_camera_csv_points_are_in_the_s1_view_of_their_source_and_the_fit_curve_is_pbrdf_cl_stokes():
    """A camera CSV (s1, s2 under a source at +45 degrees): its points are drawn in the s1 and s2
    views at that state and in no other (not under unpolarized light, not in the DOP's view); the
    residuals are data - pbrdf_cl.stokes; the fitted curve is pbrdf_cl.stokes at the fit's parameters."""
    eng = pbrdf_cl.get_default_engine()
    meas = pbrdf_cl.read_csv(CAMERA)
    assert st.first_view(meas) == ("s1n", AT_45)
    view = st.State()
    view.settings.quantity, view.settings.incident = "s1n", AT_45
    p = st.view_points(meas, view.settings)
    assert p.rows.all() and p.name == "s1" and np.array_equal(p.value, meas.quantities["s1"])
    assert np.array_equal(p.std, meas.stds["s1"])
    model, res = st.residuals(eng, view, meas)
    s = pbrdf_cl.stokes(meas.theta_i, meas.theta_r, meas.phi, **st.STEEL, incident=AT_45)
    np.testing.assert_allclose(model, s[:, 1] / s[:, 0], rtol=1e-12)
    np.testing.assert_allclose(res, meas.quantities["s1"] - s[:, 1] / s[:, 0], rtol=1e-12, atol=1e-15)
    for quantity, incident in (("s2n", AT_45), ("s1n", st.UNPOLARIZED), ("s1", AT_45), ("dop", AT_45)):
        view.settings.quantity, view.settings.incident = quantity, incident
        assert st.view_points(meas, view.settings).rows.sum() == (30 if quantity == "s2n" else 0), quantity
    assert st.measures(meas, "s1n") and not st.measures(meas, "dop")
    view.settings.quantity, view.settings.incident, view.settings.resolution = "s1n", AT_45, 16
    ds = st.view_dataset(eng, view, meas)
    assert np.array_equal(ds["data_s1n"].values, meas.quantities["s1"]) and "data_s1n_std" in ds
    assert ds.attrs["source"] == "linear +45 (0, 1, 0)" and ds.attrs["incident"] == [0.0, 1.0, 0.0]
    r = pbrdf_cl.fit(meas)
    tr = st.theta_r_axis()
    want = pbrdf_cl.stokes(np.asarray(view.settings.theta_i)[:, None], tr[None, :], 180, **r.x, incident=AT_45)
    np.testing.assert_allclose(st.fit_curves(eng, view, r, tr), want[..., 1] / want[..., 0], rtol=1e-12)


def test_url_carries_the_incident_state_and_refuses_a_bad_one_in_one_line():
    state = st.State()
    state.settings.quantity, state.settings.incident = "s2n", (0.5, -0.5, 0.5)
    query = st.to_query(state)
    assert "&inc=0.5,-0.5,0.5" in query and "&inc=" not in st.to_query(st.State())  # unpolarized: as before
    assert st.from_query({k: v[0] for k, v in parse_qs(query).items()}) == state
    for text, line in (("0.8,0.8,0", "URL: inc='0.8,0.8,0': incident (0.8, 0.8, 0.0) is not a Stokes vector: "
                                     "s1^2 + s2^2 + s3^2 = 1.28 > 1 (normalised by S0)"),
                       ("0,1", "URL: inc='0,1': give the three numbers s1,s2,s3 of the source, got 2"),
                       ("a,b,c", "URL: inc='a,b,c': not numbers; give s1,s2,s3 of the source (0,1,0: linear at "
                                 "+45 degrees)")):
        problems = {}
        got = st.from_query({"inc": text, "q": "s1n"}, problems)
        assert problems == {"inc": line} and got.settings.incident == st.UNPOLARIZED and got.settings.quantity == "s1n"
    ex = _page({"inc": "0.5,-0.5,0.5", "q": "s2n"})  # a state without a name: offered as its numbers
    assert ex.incident.value == (0.5, -0.5, 0.5) and "(0.5, -0.5, 0.5)" in ex.incident.options
    assert ex.figs.curves_fig.title.text == "s2 = S2/S0 vs theta_r at phi = 180° (in plane), source (0.5, -0.5, 0.5)"


def _two_states_csv(path):
    """s1 of the steel under sources s and +45 (12 rows each) and an AoP in radians (under +45)."""
    ti, tr = np.repeat([30.0, 50.0], 6), np.tile(np.arange(20.0, 80.0, 10.0), 2)
    lines = ["theta_i,theta_r,phi,s1,aop,in_s1,in_s2,in_s3"]
    for inc in ((1.0, 0.0, 0.0), AT_45):
        s = pbrdf_cl.stokes(ti, tr, 180, **st.STEEL, incident=inc)
        aop = np.arctan2(s[:, 2], s[:, 1]) / 2 if inc == AT_45 else np.full(12, np.nan)
        lines += [f"{a:g},{b:g},180,{float(v)!r},{'' if np.isnan(w) else repr(float(w))},{inc[0]:g},{inc[1]:g},0"
                  for a, b, v, w in zip(ti, tr, s[:, 1] / s[:, 0], aop)]
    path.write_text("\n".join(lines) + "\n")


def test_page_shows_an_uploaded_camera_csv_fits_it_and_offers_the_datas_states(tmp_path):
    """Without a browser: an uploaded camera CSV turns the page to the s1 view under its source with
    its points; Fit gives pbrdf_cl.fit's table and the fitted s1 curves; the DOP's view says the data
    hold none. A file of two states offers both, each showing its own points; its AoP in radians is
    one red line. A specular fit draws its curve and moves the sliders (its held sigma, ks, kd, c)."""
    import asyncio
    ex = _page()
    ex.upload.param.update(filename="cam.csv", value=CAMERA.read_bytes())
    assert (ex.quantity.value, ex.incident.value) == ("s1n", AT_45) == (ex.state.settings.quantity,
                                                                         ex.state.settings.incident)
    meas = pbrdf_cl.read_csv(CAMERA)
    assert np.array_equal(ex.figs.data_src.data["y"], meas.quantities["s1"])
    assert "cam.csv: 30 rows of s1 = S1/S0, s2 = S2/S0 under linear +45 (0, 1, 0)" in ex.data_info.object
    asyncio.run(ex._on_fit(None))
    r = pbrdf_cl.fit(meas)
    table = ex.figs.fit_table_src.data
    assert table["parameter"] == list(r.free) and np.allclose(table["value"], [r.x[p] for p in r.free], rtol=1e-9)
    assert "SSE" in ex.fit_notes.object and "(s1, s2)" in ex.fit_notes.object
    tr = np.asarray(ex.figs.fit_src.data["xs"][0])
    s = pbrdf_cl.stokes(30, tr, 180, **r.x, incident=AT_45)
    np.testing.assert_allclose(ex.figs.fit_src.data["ys"][0], s[:, 1] / s[:, 0], rtol=1e-12)
    ex.quantity.value = "dop"
    assert not len(ex.figs.data_src.data["x"]) and not len(ex.figs.fit_src.data["xs"])
    assert ex.figs.res_fig.title.text == "No DOP measured: the data hold s1 = S1/S0, s2 = S2/S0"
    ex.quantity.value = "s1n"
    assert len(ex.figs.fit_src.data["xs"]) == 3  # the fit's curves are back in the view of what it fitted

    path = tmp_path / "states.csv"
    _two_states_csv(path)
    ex.upload.param.update(filename="states.csv", value=path.read_bytes())
    assert ex.fit_result is None and not len(ex.figs.fit_src.data["xs"])
    assert ("linear s (1, 0, 0)" in ex.incident.options and ex.incident.value == AT_45)  # s1 under +45 was shown
    assert "error: " not in (_red(ex.status) or "") and "warning: states.csv: aop: every value lies within" in \
        _red(ex.status)
    for incident in ((1.0, 0.0, 0.0), AT_45):
        ex.incident.value = incident
        s = pbrdf_cl.stokes(ex.meas.theta_i, ex.meas.theta_r, 180, **st.STEEL, incident=incident)
        rows = (ex.meas.incident == incident).all(axis=1)
        np.testing.assert_allclose(ex.figs.data_src.data["y"], (s[:, 1] / s[:, 0])[rows], rtol=1e-12)
        np.testing.assert_allclose(ex.figs.data_src.data["res"], 0.0, atol=1e-12)

    ex.upload.param.update(filename="steel.csv", value=EXAMPLE.read_bytes())
    ex.model.value = "specular"
    asyncio.run(ex._on_fit(None))
    spec = pbrdf_cl.fit(str(EXAMPLE), model="specular")
    tr = np.asarray(ex.figs.fit_src.data["xs"][1])
    np.testing.assert_allclose(ex.figs.fit_src.data["ys"][1], pbrdf_cl.dop(40, tr, 180, **spec.x, model="specular"),
                               rtol=1e-12)
    ex._on_use_fit(None)
    assert ex.state.sets[0]["n"] == pytest.approx(spec.x["n"], rel=1e-12) and ex.state.sets[0]["kd"] == 0.0


def test_in_the_browser_a_camera_csv_is_shown_and_fitted(browser):
    """In the page: an uploaded camera CSV is drawn in the s1 view under its source (the URL says
    q=s1n and inc=0,1,0), and Fit shows the table of pbrdf_cl.fit."""
    from pbrdf_cl.app import drive
    driver, url = browser
    driver.get(url)
    drive.wait_loaded(driver)
    drive.file_input(driver).send_keys(str(CAMERA))
    y = drive.wait(lambda: drive.source_data(driver, "data_points")["y"], 60, what="the camera's points")
    assert np.array_equal(y, pbrdf_cl.read_csv(CAMERA).quantities["s1"])
    drive.button(driver, "Fit").click()
    table = drive.wait(lambda: (lambda d: d if d and d["value"] else None)(drive.source_data(driver, "fit_table")),
                       120, what="the fit")
    r = pbrdf_cl.fit(str(CAMERA))
    assert table["parameter"] == list(r.free)
    for key, want in (("value", [r.x[p] for p in r.free]), ("low", [r.ci95[p][0] for p in r.free]),
                      ("high", [r.ci95[p][1] for p in r.free])):
        np.testing.assert_allclose(table[key], want, rtol=1e-9, atol=1e-12)
    query = drive.wait(lambda: (lambda q: q if q.get("inc") else None)(
        {k: v[0] for k, v in parse_qs(urlparse(driver.current_url).query).items()}), 30, what="the URL's source")
    assert query["q"] == "s1n" and query["inc"] == "0,1,0"


@pytest.fixture
def in_process_server():
    """The explorer's server (``app.server.make_server``, its own settings) on a free port, run
    in a thread of this process: yields the Bokeh server."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    import asyncio
    import threading

    from pbrdf_cl.app.server import make_server
    box, ready = {}, threading.Event()

    def run():
        asyncio.set_event_loop(asyncio.new_event_loop())
        try:
            box["server"] = make_server(0)
            box["server"].start()
        finally:
            ready.set()
        box["server"].io_loop.start()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert ready.wait(120) and "server" in box, "the explorer's server did not start"
    server = box["server"]
    yield server
    server.io_loop.add_callback(server.stop)
    server.io_loop.add_callback(server.io_loop.stop)
    thread.join(30)


def _live_explorers():
    import gc

    from pbrdf_cl.app.page import Explorer
    gc.collect()
    return sum(isinstance(o, Explorer) for o in gc.get_objects())


def test_closed_pages_sessions_are_released(in_process_server):
    """Pages opened and closed one after another (over the websocket, as BokehJS opens them): each
    session is released soon after its page closes (issue #39: a server up for a day grew by
    ~5 MB a page), its page leaves the registry of live pages and no Explorer is left behind."""
    import time

    from bokeh.client import pull_session

    from pbrdf_cl.app import upload  # noqa: F401 - its and Panel's models: the pulled document holds them
    server = in_process_server
    url = f"http://localhost:{server.port}/explore"
    before = _live_explorers()
    seen = 0
    for _ in range(6):
        session = pull_session(url=url)
        seen = max(seen, len(st.PAGES))
        assert session.document.roots, "the page's document came"
        session.close()
    assert seen >= 1 and len(server.get_sessions("/explore")) >= 1  # each load made a served page
    t0 = time.time()
    limit = 12.0  # s: Bokeh's own defaults keep a closed page's session 15 to 32 s
    while (st.PAGES or server.get_sessions("/explore")) and time.time() - t0 < limit:
        time.sleep(0.2)
    assert not server.get_sessions("/explore") and not st.PAGES, (
        f"{len(server.get_sessions('/explore'))} sessions, {len(st.PAGES)} pages still live "
        f"{time.time() - t0:.1f} s after the last page closed")
    assert _live_explorers() <= before  # nothing holds a closed page's Explorer


def test_server_takes_every_upload_the_page_takes(in_process_server):
    """The websocket's limit is set, above the base64 message of the largest file the page takes."""
    from pbrdf_cl.app.upload import MAX_UPLOAD
    limit = in_process_server._tornado.settings["websocket_max_message_size"]
    assert limit >= 4 * MAX_UPLOAD // 3 + 2**20


def test_upload_above_the_limit_is_one_line_and_the_page_stays(tmp_path):
    """Without a browser: a file above the page's limit (the browser sends only its name and size)
    is one red line naming it and the limit, nothing loaded; a file within it loads as before."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    import base64

    from pbrdf_cl.app.upload import MAX_UPLOAD
    ex = pbrdf_cl.explore().explorer
    ex.upload.receive({"name": "big.csv", "size": 31 * 10**6})
    assert ('">error: big.csv is 29.6 MiB, above the page\'s upload limit of 16 MiB; nothing was sent: start the '
            'explorer with --data big.csv (read on the server), or fit it with pbrdf-cl fit</span>') in _red(ex.status)
    assert MAX_UPLOAD == 16 * 2**20 and ex.meas is None and "upload limit" in _red(ex.data_info)
    data = EXAMPLE.read_bytes()
    ex.upload.receive({"name": "steel.csv", "size": len(data), "data": base64.b64encode(data).decode()})
    assert ex.meas is not None and len(ex.meas) == len(pbrdf_cl.read_csv(EXAMPLE))
    ex.meas = None
    ex.upload.receive({"name": "steel.csv", "size": len(data), "data": base64.b64encode(data).decode()})
    assert ex.meas is not None  # the same file again: read again
    ex.upload.receive({"name": "empty.csv", "size": 0, "data": ""})
    assert "error: empty.csv: empty file (no header line)" in _red(ex.status)


def test_in_the_browser_an_upload_above_the_limit_is_refused_and_the_page_lives(browser, tmp_path):
    """In the page: a 31 MB file (above the limit; it used to close the page's connection, the
    page dead) is one red line saying the limit, and the page stays live: a slider still moves the
    curves and a good file still loads."""
    from selenium.webdriver.common.keys import Keys

    from pbrdf_cl.app import drive
    driver, url = browser
    driver.get(url)
    before = drive.wait_loaded(driver)
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.write(EXAMPLE.read_bytes())
        fh.truncate(31 * 10**6)
    drive.file_input(driver).send_keys(str(big))
    line = drive.wait(lambda: _said(driver, "error: big.csv is 29.6 MiB, above the page's upload limit of 16 MiB"),
                      60, what="the big file's refusal")
    assert "nothing was sent" in line
    drive.deep_find(driver, ".noUi-handle")[0].send_keys(Keys.ARROW_RIGHT)
    drive.wait(lambda: drive.source_data(driver, "curve_A")["ys"] != before["ys"], 60,
               what="the curves following the slider after the refusal")
    drive.file_input(driver).send_keys(str(EXAMPLE))
    drive.wait(lambda: drive.source_data(driver, "data_points")["x"], 60, what="the measurements")


def _sent(doc):
    """The document's changes as the server would send them: (source name, columns sent; None:
    the whole data) of each ColumnDataChanged, and the names of other models changed."""
    from bokeh.document.events import ColumnDataChangedEvent, ModelChangedEvent
    out = []
    doc.on_change(lambda e: out.append((e.model.name, e.cols) if isinstance(e, ColumnDataChangedEvent) else
                                       (e.model.name, e.attr) if isinstance(e, ModelChangedEvent) else None))
    return out


def test_an_update_sends_only_what_changed():
    """Issue #37: a slider's move sends the new values only: set A's curves their ys (not the same
    theta_r again), the map its image (not its corner and size), and the hidden sets' empty
    sources nothing; their numbers are those drawn before (the curves and map of the new set)."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from bokeh.document import Document

    from pbrdf_cl.app.figures import Figures
    eng = pbrdf_cl.get_default_engine()
    view = st.State()
    figs, doc = Figures(), Document()
    for model in (figs.curves_fig, figs.polar_fig, figs.map_fig):
        doc.add_root(model)
    tr = st.theta_r_axis()

    def draw():
        figs.update_curves(tr, view.settings.theta_i, st.curves(eng, view, tr), "dop")
        a, b, v = st.incidence_map(eng, view)
        figs.update_map("incidence", a, b, v, "dop")
    draw()
    sent = _sent(doc)
    view.sets[0]["n"] = 1.7
    draw()
    data = [s for s in sent if s and s[0] in ("curve_A", "curve_B", "curve_C", "curve_D", "map")]
    assert data == [("curve_A", ["ys"]), ("map", ["image"])]
    assert np.array_equal(np.asarray(figs.curve_src[0].data["ys"]), st.curves(eng, view, tr)[0])
    assert np.array_equal(figs.map_src.data["image"][0], st.incidence_map(eng, view)[2].astype(np.float32))
    view.settings.theta_i = (20.0, 60.0)  # other curves: their axes too
    draw()
    assert ("curve_A", None) in sent
    assert figs.curve_src[0].data["ti"] == [20.0, 60.0] and len(figs.curve_src[0].data["xs"]) == 2


def test_the_value_axis_bounds_do_not_travel_back_to_the_server():
    """Issue #37: the curves' and residuals' value axes follow the data in the browser; their bounds
    are not sent back to the server after every update (nothing there reads them)."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from bokeh.models import DataRange1d

    from pbrdf_cl.app.figures import Figures
    figs = Figures()
    for fig in (figs.curves_fig, figs.res_fig):
        assert isinstance(fig.y_range, DataRange1d) and fig.y_range.syncable is False


def test_served_slider_moves_are_drawn_once_on_the_next_tick():
    """Issue #37: in a served page a slider's move is drawn in a callback of its own on the next
    tick (after the server's reply to the slider's message), once for every move made until then."""
    pytest.importorskip("panel", reason="the explore extra (panel) is not installed")
    from bokeh.document import Document

    class Served(Document):  # a served session's document: next-tick callbacks kept to be run by hand
        session_context = object()

        def add_next_tick_callback(self, callback):
            self.ticks.append(callback)

        def add_timeout_callback(self, callback, timeout_milliseconds):
            pass

    ex = _page()
    ex.doc = Served()
    ex.doc.ticks = []
    before = [np.array(y) for y in ex.figs.curve_src[0].data["ys"]]
    ex.sliders["n"].value = 1.7
    ex.sliders["k"].value = 2.5
    assert len(ex.doc.ticks) == 1  # one redraw for both moves
    assert all(np.array_equal(a, b) for a, b in zip(before, ex.figs.curve_src[0].data["ys"]))  # not yet
    ex.doc.ticks.pop()()
    moved = st.State()
    moved.sets[0].update(n=1.7, k=2.5)
    assert np.array_equal(np.asarray(ex.figs.curve_src[0].data["ys"]), st.curves(ex.engine, moved)[0])
    ex.sliders["n"].value = 1.8
    assert len(ex.doc.ticks) == 1  # the next move: a redraw of its own
