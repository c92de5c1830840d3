"""pbrdf_cl.design compares instruments (issue #36, item 4): the instruments' channels, their
Jacobians through the engine against an independent computation from pbrdf_cl.mueller, SPEC's
Fisher table, the comparison's text, Dataset and figure, the refusals, the CLI."""

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.analysis import designs as dz
from pbrdf_cl.analysis import instruments as ins
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.model import measurables, reference
from pbrdf_cl.plots.design import plot_design

from conftest import requires_opencl

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
NAMES = ["n", "k", "sigma", "kd", "c", "ks"]  # kd: the ratio kd/ks, as design's coordinates
SMALL = {"theta_i": "10:80:10", "theta_r": "0:85:5", "phi": 180}
FOUR = "dop,camera45,camera4,mueller"
PAPER_150 = {"theta_i": [30, 40, 50], "theta_r": "20:65:5", "phi": 150}


def test_values_of_a_mueller_matrix_are_the_channels_values():
    """Channels.values_of (arithmetic on F = K P + fd e00) equals Channels.values (the reference's
    channel functions from the Fresnel factors, K and fd), for every kind of channel."""
    rng = np.random.default_rng(5)
    M = 30
    ti, tr, phi = rng.uniform(5, 80, M), rng.uniform(0, 85, M), rng.uniform(0, 360, M)
    par = dict(n=rng.uniform(1.2, 3, M), k=rng.uniform(0, 4, M), sigma=rng.uniform(0.1, 0.8, M),
               ks=rng.uniform(0.5, 2, M), kd=rng.uniform(0, 0.5, M), c=rng.uniform(-1, 0, M))
    v = rng.normal(size=(M, 3))
    inc = v / np.linalg.norm(v, axis=1)[:, None] * rng.uniform(0, 1, (M, 1))
    F = pbrdf_cl.mueller(ti, tr, phi, **par, backend="numpy")
    for cols in (["dop", "aop", "s1", "s2", "s3", *measurables.MUELLER[1:]],
                 ["s0", "s1", "s2", "s3", *measurables.MUELLER, "f00"]):
        ch = measurables.channels(ti, tr, phi, {q: np.zeros(M) for q in cols}, incident=inc)
        g = reference.geometry(ch.theta_i, ch.theta_r, ch.phi)
        p = {k: x[ch.row] for k, x in par.items()}
        f = reference.fresnel(p["n"], p["k"], g.cb, g.sb)
        logK = reference.log_specular_scale(g, p["sigma"], p["ks"], reference.shadowing_factor(g, p["sigma"], 1))
        want = ch.values(f, reference.frame_rotations(g, ch.phi), logK, reference.diffuse(g, p["kd"], p["c"]))
        got = ch.values_of(F[ch.row])
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)


def _independent(geo, instrument, x):
    """An instrument's channels at the geometries from pbrdf_cl.mueller (numpy) times each source
    state, in design's coordinates x (kd = kd/ks): (G, c), the registry's order per state."""
    p = dict(zip(NAMES, x))
    p["kd"] = p["kd"] * p["ks"]
    F = pbrdf_cl.mueller(geo["theta_i"], geo["theta_r"], geo["phi"], **p, backend="numpy")
    out = []
    for s in instrument.states:
        S = F @ np.array([1.0, *s])
        for q in instrument.quantities:
            if q == "dop":
                out.append(np.linalg.norm(S[:, 1:], axis=1) / S[:, 0])
            elif q.startswith("s"):
                out.append(S[:, int(q[1])] / S[:, 0])
            else:
                out.append(F[:, int(q[1]), int(q[2])] / F[:, 0, 0])
    return np.stack(out, axis=1)


def _check_instrument_jacobians(eng):
    geo, _ = dz.check_points("g", {"theta_i": [20, 40, 65], "theta_r": "0:85:17", "phi": [150, 180]})
    mat = {n: np.array([v]) for n, v in STEEL.items()}
    lo = np.array([fit_setup.DEFAULT_BOUNDS[n][0] for n in NAMES])
    hi = np.array([fit_setup.DEFAULT_BOUNDS[n][1] for n in NAMES])
    chosen = ins.instruments("dop@45,camera45,camera4,mueller,s3@0+circular", 0.005)
    Y, J = dz.instrument_jacobians(eng, geo, mat, NAMES, lo, hi, chosen)
    x0 = np.array([STEEL["kd"] / STEEL["ks"] if n == "kd" else STEEL[n] for n in NAMES])
    for i, y, j in zip(chosen, Y, J):
        G = geo["theta_i"].size
        assert y.shape == (1, G, i.per_geometry) and j.shape == (1, G, i.per_geometry, len(NAMES))
        np.testing.assert_allclose(y[0], _independent(geo, i, x0), rtol=1e-11, atol=1e-14, err_msg=i.name)
        cols = []
        for a in range(len(NAMES)):  # central differences with a step unlike design's
            h = np.zeros(len(NAMES))
            h[a] = 1e-5 * max(1.0, abs(x0[a]))
            cols.append((_independent(geo, i, x0 + h) - _independent(geo, i, x0 - h)) / (2 * h[a]))
        want = np.stack(cols, axis=-1)[..., :5]  # normalised quantities do not depend on ks at fixed kd/ks (below)
        scale = np.abs(want).max(axis=(0, 1))
        np.testing.assert_allclose(j[0, ..., :5] / scale, want / scale, atol=1e-6, err_msg=i.name)
        assert np.abs(j[0, ..., NAMES.index("ks")]).max() < 1e-8 * np.abs(j[0]).max(), i.name
    # the DOP through the Mueller matrix is the design's DOP Jacobian through the dop kernel
    _, _, Jd, _ = dz.jacobians(eng, geo, mat, NAMES, lo, hi)
    _, (Jm,) = dz.instrument_jacobians(eng, geo, mat, NAMES, lo, hi, [ins.instrument({"quantities": "dop"})])
    five = slice(0, 5)
    np.testing.assert_allclose(Jm[0, :, 0, five], Jd[0, :, five], rtol=1e-6, atol=1e-9 * np.abs(Jd).max())


def test_instrument_jacobians_numpy_equal_finite_differences_of_pbrdf_cl_mueller():
    _check_instrument_jacobians(pbrdf_cl.NumpyEngine())


@requires_opencl
def test_instrument_jacobians_opencl_equal_finite_differences_of_pbrdf_cl_mueller(engine):
    if not engine.fp64:
        pytest.skip("the device has no float64")
    _check_instrument_jacobians(engine)


def _se(result, where="reference"):
    return {i: (c["se"]["n"], c["se"]["k"]) for i, c in result.instrument_comparisons[where].items()}


@pytest.fixture(scope="module")
def compared():
    return pbrdf_cl.design(STEEL, SMALL, n_measurements=8, instrument=FOUR, backend="numpy")


def test_spec_fisher_table_is_reproduced():
    """SPEC's Fisher numbers (n, k standard errors at the paper's 30 in-plane geometries, noise
    0.005 per normalised quantity): reproduced to SPEC's digits where kd/ks = 0.15 (ks held at 1
    and kd 0.15: design's DOP-only coordinates at ks = 1).  For the steel's own kd/ks = 0.15/0.9
    they are 3-7% larger (SPEC's numbers were computed with kd 0.15 taken as the ratio)."""
    spec = {"dop": ("0.53", "2.14"), "camera45": ("0.074", "0.023"), "camera4": ("0.0065", "0.0048"),
            "mueller": ("0.0053", "0.0053")}
    spec150 = {"camera45": ("0.039", "0.035")}
    ratio = dict(STEEL, ks=1.0)
    for reference_set, want in ((None, spec), (PAPER_150, spec150)):
        r = pbrdf_cl.design(ratio, SMALL, n_measurements=8, instrument=FOUR, reference=reference_set,
                            backend="numpy")
        got = _se(r)
        for name, digits in want.items():
            for value, text in zip(got[name], digits):
                places = len(text.split(".")[1])
                assert round(value, places) == float(text), (name, value, text)
    steel = _se(pbrdf_cl.design(STEEL, SMALL, n_measurements=8, instrument=FOUR, backend="numpy"))
    for name, digits in spec.items():
        for value, text in zip(steel[name], digits):
            assert 1.02 < value / float(text) < 1.08, (name, value, text)


def test_widths_are_the_standard_errors_unless_clipped(compared):
    """A width is 2 x 1.96 se where the interval lies inside the bounds; the DOP's k interval at the
    paper's geometry is clipped at k = 0 (SPEC's 'truncated')."""
    ref = compared.instrument_comparisons["reference"]
    for name in ("camera45", "camera4", "mueller"):
        for p in ("n", "k", "sigma", "kd"):
            assert ref[name]["widths"][p] == pytest.approx(2 * dz.Z95 * ref[name]["se"][p], rel=1e-12), (name, p)
    assert ref["dop"]["widths"]["k"] < 2 * dz.Z95 * ref["dop"]["se"]["k"]
    assert ref["dop"]["undetermined"] == ["c"] and "c" in compared.undetermined_reference


def test_dop_instrument_is_the_default_design_bit_for_bit(compared):
    plain = pbrdf_cl.design(STEEL, SMALL, n_measurements=8, backend="numpy")
    for key in ("theta_i", "theta_r", "phi", "information"):
        assert np.array_equal(plain[key], compared[key], equal_nan=True), key
    assert plain.comparisons == compared.comparisons and plain.criterion_value == compared.criterion_value
    assert compared.instrument_comparisons["chosen"]["dop"]["widths"] == plain.ci95_width
    assert plain.instruments == [] and plain.instrument_comparisons == {}
    assert "instruments at the same geometries" not in plain.summary()
    a, b = plain.to_dataset(), compared.to_dataset()
    assert "instrument_width" not in a and set(b.data_vars) - set(a.data_vars) == {
        "instrument_width", "instrument_se", "instrument_undetermined", "instrument_description",
        "instrument_noise", "instrument_channels"}
    for v in a.data_vars:
        assert a[v].equals(b[v]), v


def test_geometries_are_chosen_for_the_first_instrument(compared):
    """Chosen for the Mueller polarimeter, its own A criterion beats the set chosen for the DOP;
    the design's own comparisons are then the Mueller polarimeter's."""
    mine = pbrdf_cl.design(STEEL, SMALL, n_measurements=8, instrument="mueller,dop", backend="numpy")
    span = {p: hi - lo for p, (lo, hi) in mine.bounds.items()}

    def a_criterion(c):
        return sum((c["se"][p] / span[p]) ** 2 for p in ("n", "k"))
    assert a_criterion(mine.instrument_comparisons["chosen"]["mueller"]) < \
        a_criterion(compared.instrument_comparisons["chosen"]["mueller"])
    assert mine.ci95_width == mine.instrument_comparisons["chosen"]["mueller"]["widths"]
    assert mine.ci95_width_reference == compared.instrument_comparisons["reference"]["mueller"]["widths"]
    assert "instrument mueller (the 15 Mueller elements" in mine.summary().splitlines()[0]


def test_own_noise_and_states():
    """An instrument's own noise scales its standard errors; camera@45 is camera45; a camera under
    more source states determines n and k better."""
    r = pbrdf_cl.design(STEEL, SMALL, n_measurements=8, backend="numpy", instrument=[
        "camera45", "camera@45", dict(name="noisy", quantities=("s1", "s2"), states=(45,), noise=0.01),
        "s1+s2@0+45", "camera4"])
    se = {k: c["se"] for k, c in r.instrument_comparisons["reference"].items()}
    assert se["camera@45"] == se["camera45"]
    for p in ("n", "k", "sigma", "kd", "c"):
        assert se["noisy"][p] == pytest.approx(2 * se["camera45"][p], rel=1e-9)
    assert se["camera4"]["n"] < se["s1+s2@0+45"]["n"] < se["camera45"]["n"]
    assert [i["noise"] for i in r.instruments] == [0.005, 0.005, 0.01, 0.005, 0.005]
    assert [i["per_geometry"] for i in r.instruments] == [2, 2, 2, 4, 10]


def test_summary_prints_the_instruments_side_by_side(compared):
    lines = compared.summary().splitlines()
    at = lines.index("instruments at the same geometries: predicted 95% interval widths (standard errors)")
    assert lines[at + 1] == " paper 30/40/50 x 20..65, 30 points:"
    assert lines[at + 2] == ("  instrument     chan.   noise                 n                 k             sigma"
                             "             kd/ks                 c")
    c = compared.instrument_comparisons["reference"]["camera45"]
    row = lines[at + 4]
    assert row.startswith("  camera45           2   0.005")
    assert row.split()[3:5] == [f"{c['widths']['n']:.3g}", f"({c['se']['n']:.3g})"]
    assert lines[at + 3].startswith("  dop                1   0.005") and lines[at + 3].endswith("undet.")
    assert lines[at + 7] == " chosen (A) for dop, 8 points:"
    assert "  mueller: the 15 Mueller elements m_ij = M_ij / M00 (Mueller polarimeter)" in lines
    assert "  camera4: s1, s2 under sources linear at 0, 45, 90, 135 deg and circular" in lines
    with_f00 = pbrdf_cl.design(STEEL, SMALL, n_measurements=8, instrument="camera45", intensity=True,
                               backend="numpy").summary()
    assert "(standard errors), each with F00 rows" in with_f00 and with_f00.count(" ks\n") >= 1


def test_dataset_and_figure(compared, tmp_path):
    ds = compared.to_dataset()
    assert list(ds.instrument.values) == ["dop", "camera45", "camera4", "mueller"]
    assert ds.instrument_se.sel(instrument_set="reference", instrument="mueller", parameter_all="n").item() == \
        compared.instrument_comparisons["reference"]["mueller"]["se"]["n"]
    assert ds.instrument_undetermined.sel(instrument_set="reference", instrument="dop", parameter_all="c").item() == 1
    assert list(ds.instrument_channels.values) == [1, 2, 10, 15]
    ds.to_netcdf(tmp_path / "d.nc")
    fig = plot_design(compared)
    assert len(fig.axes) == 4  # the map, its colour bar, the widths, the instruments
    panel = next(ax for ax in fig.axes if ax.get_title().startswith("instruments"))
    assert panel.get_legend().get_texts()[0].get_text() == "dop: 1 channels/geometry, noise 0.005"
    assert len(panel.patches) == 2 * 4 * 5  # reference and chosen, four instruments, five parameters


@pytest.mark.parametrize("kwargs, words", [
    (dict(instrument="camra45"), ["instrument: unknown 'camra45'", "did you mean 'camera45'?", "camera4, mueller"]),
    (dict(instrument="dop,muller"), ["unknown 'muller'", "did you mean 'mueller'?"]),
    (dict(instrument=dict(quantities="s1+s2", states=[(1, 1, 0)])),
     ["instrument 's1+s2'", "(1.0, 1.0, 0.0) is not a Stokes vector", "= 2 > 1"]),
    (dict(instrument=dict(quantities="s1+s2", states=[(0.5, 0.5)])), ["instrument 's1+s2'", "trailing axis of 3"]),
    (dict(instrument=dict(quantities=("s1",), noise=0)), ["instrument 's1'", "noise must be a positive number, got 0"]),
    (dict(instrument=dict(quantities=("s1",), noise=-0.01)), ["noise must be a positive number, got -0.01"]),
    (dict(instrument=dict(quantities=("s1",), noise=2)), ["noise must be below 1", "got 2"]),
    (dict(instrument="camera", noise=0), ["noise must be a positive number, got 0"]),
    (dict(instrument="s1+s5"), ["instrument 's1+s5'", "unknown quantity 's5'", "s3, m01 .. m33"]),
    (dict(instrument="aop"), ["'aop' cannot be an instrument's channel", "give s1 and s2"]),
    (dict(instrument="s0+s1"), ["'s0' cannot be", "intensity=True"]),
    (dict(instrument="mueller@45"), ["do not depend on the source state"]),
    (dict(instrument="camera@diagonal"), ["unknown source state 'diagonal'"]),
    (dict(instrument="dop,dop"), ["'dop' is named twice"]),
    (dict(instrument=dict(quantites="s1")), ["unknown key 'quantites'", "did you mean 'quantities'?"]),
    (dict(instrument=""), ["instrument: give at least one"]),
])
def test_instrument_refusals_are_one_line(kwargs, words):
    with pytest.raises(ValueError) as err:
        pbrdf_cl.design(STEEL, SMALL, n_measurements=8, backend="numpy", **kwargs)
    text = str(err.value)
    assert "\n" not in text
    for w in words:
        assert w in text, (w, text)


def test_cli_design_compares_instruments(tmp_path, capsys):
    nc = tmp_path / "d.nc"
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5,ks=0.9,kd=0.15,c=-0.3", "--candidates",
                   "theta_i=10:80:10", "theta_r=0:85:5", "--n", "8", "--instrument", FOUR, "--out", str(nc),
                   "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "instruments at the same geometries" in out and "  mueller           15   0.005" in out
    import xarray as xr
    with xr.open_dataset(nc) as ds:
        assert list(ds.instrument.values) == FOUR.split(",")
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--instrument", "camera45", "s1+s2@0+90",
                   "--candidates", "theta_i=10:80:10", "theta_r=0:85:5", "--n", "8", "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "instrument camera45 (s1, s2" in out and "  s1+s2@0+90         4" in out
    assert cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--instrument", "camra45",
                     "--backend", "numpy"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("pbrdf-cl: error: instrument: unknown 'camra45' (did you mean "
                                                   "'camera45'?)")


def test_what_to_measure_page_quotes_the_design_module():
    """docs/guide/what_to_measure.md: its two tables are what design computes (standard errors to
    two significant digits)."""
    import re
    from pathlib import Path
    text = (Path(__file__).parents[1] / "docs" / "guide" / "what_to_measure.md").read_text()
    paper = {"theta_i": [30, 40, 50], "theta_r": "20:65:5"}
    got = {phi: _se(pbrdf_cl.design(STEEL, SMALL, n_measurements=8, instrument=FOUR,
                                    reference=dict(paper, phi=phi), backend="numpy")) for phi in (180, 150)}
    rows = re.findall(r"^\| `(\w+)` \| (\d+) \| ± ([0-9.]+) \| ± ([0-9.]+) \| ± ([0-9.]+) \| ± ([0-9.]+) \|$", text,
                      re.MULTILINE)
    assert [r[0] for r in rows] == FOUR.split(",")
    for name, channels, *values in rows:
        assert int(channels) == ins.REGISTRY[name].per_geometry
        want = [*got[180][name], *got[150][name]]
        assert [float(v) for v in values] == [float(f"{w:.2g}") for w in want], name
    own = re.findall(r"^\| `(\w+)` \| ± ([0-9.]+) \| ± ([0-9.]+) \| (\d+)\.\.(\d+) \|$", text, re.MULTILINE)
    assert [r[0] for r in own] == FOUR.split(",")
    for name, n, k, lo, hi in own:
        r = pbrdf_cl.design(STEEL, noise=0.005, instrument=name, backend="numpy")
        se = r.instrument_comparisons["chosen"][name]["se"]
        assert (float(n), float(k)) == (float(f"{se['n']:.2g}"), float(f"{se['k']:.2g}")), name
        assert (float(lo), float(hi)) == (r.theta_i.min(), r.theta_i.max()), name
