"""Polarimetric data from the command line and in the fit's figure (issue #36, item 5): the model's
value of every measurable quantity under any incident state (``compute/measured.py``) against the
fit's channels, ``pbrdf-cl fit`` of a polarization camera's CSV (summary, --quiet, --json, --plot)
against ``pbrdf_cl.fit``, the figure's panels per quantity and incident state with the fitted curves
of ``pbrdf_cl.stokes``, and bad columns refused in one line."""
import json
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.cli import main
from pbrdf_cl.compute.measured import groups, label, measured, state_text
from pbrdf_cl.model import measurables, reference
from pbrdf_cl.plots.fit import plot_fit

ROOT = Path(__file__).resolve().parents[1]
CAMERA = ROOT / "examples" / "steel_camera_45.csv"
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


@pytest.mark.parametrize("incident", [None, (0.0, 1.0, 0.0), (0.3, -0.5, 0.6)])
def test_measured_is_the_fits_channel_of_every_quantity(incident):
    """measured() (through pbrdf_cl.evaluate and pbrdf_cl.stokes(incident=)) equals the fit's channel
    value (model/measurables.py and reference.channel) of every measurable quantity, normalised and
    absolute, under unpolarized and polarized light."""
    rng = np.random.default_rng(5)
    ti, tr, phi = rng.uniform(5, 80, 30), rng.uniform(5, 80, 30), rng.uniform(0, 360, 30)
    inc = None if incident is None else np.broadcast_to(incident, (30, 3))
    for absolute in (False, True):
        names = [n for n in measurables.REGISTRY if not (absolute and n in ("dop", "aop"))]
        if not absolute:
            names = [n for n in names if n not in ("s0", "m00")]
        ch = measurables.channels(ti, tr, phi, {n: np.zeros(30) for n in names}, incident=inc)
        g = reference.geometry(ch.theta_i, ch.theta_r, ch.phi)
        f = reference.fresnel(STEEL["n"], STEEL["k"], g.cb, g.sb)
        log_k = reference.log_specular_scale(g, STEEL["sigma"], STEEL["ks"],
                                             reference.shadowing_factor(g, STEEL["sigma"], 1))
        want = ch.values(f, reference.frame_rotations(g, ch.phi), log_k, reference.diffuse(g, STEEL["kd"], STEEL["c"]))
        for name in names:
            sel = ch.name == name
            got = measured(name, ti, tr, phi, incident=incident, normalised=not absolute, params=STEEL,
                           backend="numpy")
            if name == "aop":
                np.testing.assert_allclose(np.cos(np.radians(2 * (got - want[sel]))), 1.0, atol=1e-12)
            else:
                np.testing.assert_allclose(got, want[sel], rtol=1e-10, atol=1e-15, err_msg=f"{name} {absolute}")
    # unpolarized DOP and AoP are pbrdf_cl.dop and pbrdf_cl.aop themselves
    assert np.array_equal(measured("dop", ti, tr, phi, params=STEEL), pbrdf_cl.dop(ti, tr, phi, **STEEL))
    assert label("s1") == ("s1 = S1/S0", "1") and label("m23", False) == ("M23", "1/sr")
    assert state_text((0, 1, 0)) == "linear +45 (0, 1, 0)" and state_text((0.5, 0.5, 0)) == "(0.5, 0.5, 0)"


def test_cli_fit_of_a_camera_csv_equals_pbrdf_cl_fit(tmp_path, capsys):
    """pbrdf-cl fit on a camera CSV (s1, s2 under a 45-degree source): the summary names what was
    fitted, --json holds pbrdf_cl.fit's values, --quiet prints them, --plot writes the figure."""
    want = pbrdf_cl.fit(str(CAMERA))
    out, png = tmp_path / "fit.json", tmp_path / "fit.png"
    assert main(["fit", str(CAMERA), "--json", str(out), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert (f"data: {CAMERA} (30 rows, 60 measured numbers: s1, s2 under 1 incident state: linear +45 (0, 1, 0))"
            in text) and "(s1, s2), RMSE" in text
    got = json.loads(out.read_text())["fits"]["six-param"]
    assert got["free"] == want.free and got["sse"] == pytest.approx(want.sse, rel=1e-12)
    for p in want.free:
        assert got["x"][p] == pytest.approx(want.x[p], rel=1e-12, abs=1e-15), p
        assert got["ci95"][p] == pytest.approx(list(want.ci95[p]), rel=1e-12, abs=1e-15), p
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["fit", str(CAMERA), "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    lo, hi = want.ci95["n"]
    assert lines[0] == f"six-param: SSE {want.sse:.4g}" and f"  n = {want.x['n']:.5g}  [{lo:.4g}, {hi:.4g}]" in lines


def _titles(fig):
    return [ax.get_title() for ax in fig.axes if ax.get_title()]


def test_fit_plot_draws_a_panel_per_quantity_and_state_with_the_fitted_stokes():
    """The figure of a camera fit: one panel per quantity (s1, s2) under the 45-degree source, each
    with the data (error bars: the std) and the fitted curves of pbrdf_cl.stokes(incident=) per
    theta_i, and the residuals model - data below it."""
    meas = pbrdf_cl.read_csv(CAMERA)
    r = pbrdf_cl.fit(meas)
    fig = plot_fit(meas, {"six-param": r})
    assert _titles(fig) == ["s1 = S1/S0, source linear +45 (0, 1, 0)", "s2 = S2/S0, source linear +45 (0, 1, 0)"]
    assert len(fig.axes) == 4  # each panel with its residuals
    for j, ax in enumerate(fig.axes[0::2]):
        curves = [line for line in ax.get_lines() if len(line.get_xdata()) == 200]
        assert len(curves) == 3  # theta_i 30, 40, 50
        for ti, line in zip((30, 40, 50), curves):
            tr = np.asarray(line.get_xdata())
            s = pbrdf_cl.stokes(ti, tr, 180, **r.x, incident=(0, 1, 0), backend="numpy")
            np.testing.assert_allclose(line.get_ydata(), s[:, j + 1] / s[:, 0], rtol=1e-12)
    res = fig.axes[1]
    assert res.get_ylabel() == "model - data (1)" and len(res.containers) == 3


def test_fit_plot_of_several_states_and_of_mueller_elements(tmp_path):
    """Two source states: a panel per quantity and state; Mueller elements (normalised, out of plane)
    and an AoP: a panel each, the Mueller element's over every state."""
    ti, tr = np.repeat([30.0, 50.0], 6), np.tile(np.arange(20.0, 80.0, 10.0), 2)
    rows = []
    for inc in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)):
        s = pbrdf_cl.stokes(ti, tr, 150, **STEEL, incident=inc, backend="numpy")
        m = pbrdf_cl.mueller(ti, tr, 150, **STEEL, backend="numpy")
        rows.append(dict(theta_i=ti, theta_r=tr, phi=np.full(12, 150.0), s1=s[:, 1] / s[:, 0], s2=s[:, 2] / s[:, 0],
                         m12=m[:, 1, 2] / m[:, 0, 0], in_s1=np.full(12, inc[0]), in_s2=np.full(12, inc[1]),
                         in_s3=np.zeros(12)))
    data = {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}
    meas = pbrdf_cl.as_measurements(data)
    assert [(g[0], g[2]) for g in groups(meas)] == [("s1", (1.0, 0.0, 0.0)), ("s1", (0.0, 1.0, 0.0)),
                                                    ("s2", (1.0, 0.0, 0.0)), ("s2", (0.0, 1.0, 0.0)), ("m12", None)]
    r = pbrdf_cl.fit(meas)
    assert r.x["n"] == pytest.approx(1.6, rel=1e-5)
    titles = _titles(plot_fit(meas, {"six-param": r}, tmp_path / "states.png"))
    assert titles == ["s1 = S1/S0, source linear s (1, 0, 0)", "s1 = S1/S0, source linear +45 (0, 1, 0)",
                      "s2 = S2/S0, source linear s (1, 0, 0)", "s2 = S2/S0, source linear +45 (0, 1, 0)",
                      "m12 = M12/M00"]
    assert (tmp_path / "states.png").stat().st_size > 0


@pytest.mark.parametrize("header, rows, words", [
    ("theta_i,theta_r,s1,s2_std", ["30,20,0.1,0.01"], "s2_std is given without s2"),
    ("theta_i,theta_r,s1,in_s1,in_s2", ["30,20,0.1,0.9,0.9", "30,25,0.1,0,1"],
     "line 2: the incident state (0.9, 0.9, 0) is not a Stokes vector"),
    ("theta_i,theta_r,s1,s1_std,s2", [f"30,{t},0.1,0.01,0.2" for t in range(20, 60, 5)],
     "standard deviations are given for s1 but not for s2; give <name>_std for every quantity or for none"),
    ("theta_i,theta_r,s1,s2", ["30,20,0.9,0.9"], "line 2: the Stokes vector is longer than 1 (normalised)"),
])
def test_cli_fit_refuses_bad_polarimetric_columns_in_one_line(tmp_path, capsys, header, rows, words):
    path = tmp_path / "bad.csv"
    path.write_text("\n".join([header, *rows]) + "\n")
    assert main(["fit", str(path), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: ") and words in err, err
