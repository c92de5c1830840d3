"""pbrdf_cl.design: measurement design from the Fisher information (Jacobians, predicted widths,
the greedy + exchange search, the criteria, intensities, boxes, the figure, errors, the CLI)."""

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.analysis import designs as dz  # the module (pbrdf_cl.design is the function)
from pbrdf_cl.fitting import common
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.fitting.sample import stages
from pbrdf_cl.io.measurements import as_measurements
from pbrdf_cl.model import reference
from pbrdf_cl.plots.design import plot_design

from conftest import requires_opencl

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
NAMES = ["n", "k", "sigma", "kd", "c", "ks"]
SMALL = {"theta_i": "10:80:10", "theta_r": "0:85:5", "phi": 180}  # 8 x 18 candidates


@pytest.fixture(scope="module")
def steel():
    return dz.design(STEEL, noise=0.005, backend="numpy")


def _bounds(names):
    b = {**fit_setup.DEFAULT_BOUNDS}
    return np.array([b[n][0] for n in names]), np.array([b[n][1] for n in names])


def _reference_jacobian(geo, names, rel=1e-5):
    """Central differences of reference.evaluate (dop, brdf) in the fit's coordinates (kd = kd/ks),
    with a step unlike design's."""
    x0 = dict(STEEL, kd=STEEL["kd"] / STEEL["ks"])
    out = {}
    for q in ("dop", "brdf"):
        cols = []
        for n in names:
            h = rel * max(1.0, abs(x0[n]))
            vals = []
            for s in (+1, -1):
                x = dict(x0)
                x[n] += s * h
                p = dict(x, kd=x["kd"] * x["ks"])
                vals.append(reference.evaluate(q, geo["theta_i"], geo["theta_r"], geo["phi"],
                                               *(p[m] for m in ("n", "k", "sigma", "ks", "kd", "c"))))
            cols.append((vals[0] - vals[1]) / (2 * h))
        out[q] = np.stack(cols, axis=-1)
    return out


def _check_jacobian(eng):
    geo, _ = dz.check_points("g", {"theta_i": [20, 40, 65], "theta_r": "0:85:17", "phi": [150, 180]})
    mat = {n: np.array([v]) for n, v in STEEL.items()}
    lo, hi = _bounds(NAMES)
    dop, f00, Jd, Jf = dz.jacobians(eng, geo, mat, NAMES, lo, hi)
    ref = _reference_jacobian(geo, NAMES)
    truth = reference.evaluate("dop", geo["theta_i"], geo["theta_r"], geo["phi"],
                               *(STEEL[m] for m in ("n", "k", "sigma", "ks", "kd", "c")))
    np.testing.assert_allclose(dop[0], truth, rtol=1e-12, atol=1e-14)
    five = slice(0, 5)  # DOP does not depend on ks at fixed kd/ks (below)
    scale = np.abs(ref["dop"][:, five]).max(axis=0)
    np.testing.assert_allclose(Jd[0, :, five] / scale, ref["dop"][:, five] / scale, atol=1e-6)
    scale = np.abs(ref["brdf"]).max(axis=0)
    np.testing.assert_allclose(Jf[0] / scale, ref["brdf"] / scale, atol=1e-6)
    # DOP depends on kd and ks only through kd/ks; F00 is proportional to ks at fixed kd/ks
    assert np.abs(Jd[0, :, NAMES.index("ks")]).max() < 1e-8 * np.abs(Jd[0]).max()
    np.testing.assert_allclose(Jf[0, :, NAMES.index("ks")], f00[0] / STEEL["ks"], rtol=1e-7)


def test_jacobian_numpy_equals_finite_differences_of_the_reference():
    _check_jacobian(pbrdf_cl.NumpyEngine())


@requires_opencl
def test_jacobian_opencl_equals_finite_differences_of_the_reference(engine):
    if not engine.fp64:
        pytest.skip("the device has no float64")
    _check_jacobian(engine)


def _fit_widths(geo, free, intensity, noise=0.005, rel=fit_setup.F00_REL_STD, ks_fixed=False):
    """Predicted widths computed independently with inversion's Residuals and fd_jacobian
    (``ks_fixed``: ks held at the material's value, kd absolute, as fit with fixed ks or kd)."""
    geo = {k: np.asarray(v, float) for k, v in geo.items()}
    dop = reference.evaluate("dop", geo["theta_i"], geo["theta_r"], geo["phi"],
                             *(STEEL[m] for m in ("n", "k", "sigma", "ks", "kd", "c")))
    f00 = reference.evaluate("brdf", geo["theta_i"], geo["theta_r"], geo["phi"],
                             *(STEEL[m] for m in ("n", "k", "sigma", "ks", "kd", "c")))
    meas = as_measurements(dict(geo, dop=dop, dop_std=np.full(dop.shape, noise)))
    model = stages.Model(meas, "paper")
    base = dict(STEEL)
    ratio = not ks_fixed
    if intensity:
        res = stages.Residuals(model, free, base, dop, meas.dop_std, f00, rel * f00)
    elif ks_fixed:
        res = stages.Residuals(model, free, base, dop, meas.dop_std)
    else:
        base["ks"], base["kd"] = 1.0, STEEL["kd"] / STEEL["ks"]
        res = stages.Residuals(model, free, base, dop, meas.dop_std)
    x = np.array([STEEL["kd"] / STEEL["ks"] if n == "kd" and ratio else STEEL[n] for n in free])
    lo, hi = _bounds(free)
    _, J = common.fd_jacobian(res.rows, x[None], lo, hi, "central")
    cov = np.linalg.pinv(J[0] @ J[0].T, rcond=1e-15)
    half = 1.959963984540054 * np.sqrt(np.diag(cov))
    return dict(zip(free, np.minimum(hi, x + half) - np.maximum(lo, x - half)))


def test_predicted_widths_equal_an_independent_computation(steel):
    chosen = dict(theta_i=steel.theta_i, theta_r=steel.theta_r, phi=steel.phi)
    for geo, widths in ((chosen, steel.ci95_width), (steel.reference, steel.ci95_width_reference)):
        want = _fit_widths(geo, steel.free, False)
        for n in steel.free:
            assert widths[n] == pytest.approx(want[n], rel=1e-5), n
    want = _fit_widths(chosen, steel.free + ["ks"], True)
    got = steel.comparisons["chosen_other"]["widths"]
    assert set(got) == set(want)
    for n in want:
        assert got[n] == pytest.approx(want[n], rel=1e-5), n


def test_fixing_ks_or_kd_gives_the_fits_design(steel, capsys):
    """fixed={"ks": 1} is what DOP-only work does: the same design as leaving ks to its default;
    with ks or kd fixed at the material's value the widths are those of fit with it fixed (kd
    absolute), and the comparisons with an F00 column, which such a fit ignores, are left out
    with a note."""
    five = {n: v for n, v in STEEL.items() if n != "ks"}
    kw = dict(candidates=SMALL, noise=0.005, n_measurements=12, backend="numpy")
    free = dz.design(five, **kw)
    one = dz.design(five, fixed={"ks": 1.0}, **kw)
    np.testing.assert_array_equal(one.theta_i, free.theta_i)
    np.testing.assert_array_equal(one.theta_r, free.theta_r)
    assert one.free == ["n", "k", "sigma", "kd", "c"] and one.ci95_width == pytest.approx(free.ci95_width, rel=1e-9)
    assert "chosen_other" not in one.comparisons and "reference_other" not in one.comparisons
    assert any("no comparison with an F00 column" in n and "ks fixed" in n for n in one.notes)
    assert "no comparison with an F00 column" in one.summary() and "kd is absolute, ks fixed at 1" in one.summary()
    for fixed, names in (({"ks": 0.9}, ["n", "k", "sigma", "kd", "c"]), ({"kd": 0.15}, ["n", "k", "sigma", "c"])):
        r = dz.design(STEEL, fixed=fixed, **kw)
        assert r.free == names and "chosen_other" not in r.comparisons
        want = _fit_widths(dict(theta_i=r.theta_i, theta_r=r.theta_r, phi=r.phi), names, False, ks_fixed=True)
        for n in names:
            assert r.ci95_width[n] == pytest.approx(want[n], rel=1e-5), (fixed, n)
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5,kd=0.15,c=-0.3", "--fix", "ks=1",
                   "--candidates", "theta_i=10:80:10", "theta_r=0:85:5", "--n", "12", "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "measurement design: 12 measurements" in out and "no comparison with an F00" in out


def test_predicted_widths_report_the_null_space_as_undetermined():
    """A parameter whose scaled Jacobian column is zero, or lies in the span of the others (relative
    to each one's bound range, not in raw units), is undetermined: its interval spans the bounds,
    never a tiny width; the others keep the pseudo-inverse's widths."""
    rng = np.random.default_rng(4)
    lo, hi = np.array([0.0, 1e-3, -1.0, 0.0]), np.array([5.0, 1e3, 0.0, 10.0])
    span = hi - lo
    x = lo + 0.4 * span
    J = 20 * rng.standard_normal((40, 4)) / span  # every parameter determined, to a few % of its range
    w, se, und = dz.predicted_widths(J, x, lo, hi)
    cov = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(w, 2 * 1.959963984540054 * np.sqrt(np.diag(cov)), rtol=1e-9)
    assert not und.any() and np.all(w < 0.5 * span)
    zero = J.copy()
    zero[:, 2] = 0.0
    w, se, und = dz.predicted_widths(zero, x, lo, hi)
    assert und.tolist() == [False, False, True, False] and w[2] == span[2] and np.isinf(se[2])
    keep = [0, 1, 3]
    np.testing.assert_allclose(w[keep], 2 * 1.959963984540054 * np.sqrt(np.diag(np.linalg.inv(
        J[:, keep].T @ J[:, keep]))), rtol=1e-9)
    span_of = J.copy()  # column 3 in the span of columns 0 and 1, in scaled units (raw scales 1e4 apart)
    span_of[:, 3] = (0.7 * span_of[:, 0] * span[0] - 0.3 * span_of[:, 1] * span[1]) / span[3]
    w, se, und = dz.predicted_widths(span_of, x, lo, hi)
    # the null direction (0.7, -0.3, 0, -1) / 1.257 in scaled parameters: each moves by its share of
    # its range (0.56, 0.24, 0, 0.80) unseen by the data; x lies at 0.4 of each range
    assert und[3] and w[3] == span[3] and np.isinf(se[[0, 1, 3]]).all()
    assert w[0] >= 0.95 * span[0] and w[1] >= 0.47 * span[1]
    assert not und[2] and np.isfinite(se[2]) and w[2] < 0.2 * span[2]
    tiny = J.copy()  # a genuine but weak column (1e-4 of the others): wide, not part of the null space
    tiny[:, 1] *= 1e-4
    w, se, und = dz.predicted_widths(tiny, x, lo, hi)
    assert np.isfinite(se).all() and se[1] > 100 * se[0] / span[0] * span[1]


def test_design_reports_undetermined_parameters(tmp_path, capsys):
    """At kd = 0 the DOP does not depend on sigma or c: the design reports them undetermined (their
    whole bound range, flagged, in the result, the summary, the Dataset, the CLI and the figure's
    hatched bars with a legend), where the pseudo-inverse alone gave widths of 1e-8; F00 rows do
    determine sigma."""
    kw = dict(candidates=SMALL, noise=0.005, n_measurements=12, backend="numpy")
    r = dz.design(dict(STEEL, kd=0.0), **kw)
    bounds = fit_setup.DEFAULT_BOUNDS
    assert r.undetermined == ["sigma", "c"] and set(r.undetermined_reference) >= {"sigma", "c"}
    for n in ("sigma", "c"):
        assert r.ci95_width[n] == pytest.approx(bounds[n][1] - bounds[n][0], rel=1e-12), n
    for n in ("n", "k", "kd"):
        assert r.ci95_width[n] < 0.5 * (bounds[n][1] - bounds[n][0]), n
    assert "sigma" not in r.comparisons["chosen_other"]["undetermined"]  # F00 depends on sigma
    assert "c" in r.comparisons["chosen_other"]["undetermined"]
    text = r.summary()
    assert "undet." in text and any("sigma, c" in n and "kd = 0" in n for n in r.notes)
    ds = r.to_dataset()
    assert ds.undetermined.sel(parameter="sigma").item() == 1 and ds.undetermined.sel(parameter="n").item() == 0
    fig = plot_design(r, tmp_path / "d.png")
    ax, axb = fig.axes[0], next(a for a in fig.axes if a.get_xlabel() == "parameter")
    assert ax.get_xlabel().startswith("theta_i") and ax.get_ylabel().startswith("theta_r")
    hatched = [p for p in axb.patches if p.get_hatch()]
    cells = sum(len(c["undetermined"]) for k, c in r.comparisons.items()
                if k in ("chosen", "chosen_other", "reference", "reference_other"))
    assert len(hatched) == cells > 0
    assert any("undetermined" in t.get_text() for t in axb.get_legend().get_texts())
    t = dz.design(dict(STEEL, kd=0.0), target=("sigma",), **kw)
    assert any("target sigma cannot be determined" in n for n in t.notes)
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5,kd=0,c=-0.3", "--candidates",
                   "theta_i=10:80:10", "theta_r=0:85:5", "--n", "12", "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "undet." in out and "undetermined by the chosen set: sigma, c" in out


@pytest.mark.parametrize("r", [1, 2])
@pytest.mark.parametrize("kind", ["A", "D"])
def test_rank_updates_equal_direct_inverses(kind, r):
    """The greedy step's additions and the exchange's swaps (Woodbury, block-eliminated) against
    inverses of the updated information, for one and two rows per geometry."""
    rng = np.random.default_rng(3 + r)
    M, N, d = 2, 7, 5
    A = rng.standard_normal((M, N, r, d))
    info = np.einsum("mnrd,mnre->mde", A[:, :4], A[:, :4]) + np.eye(d)
    C = np.linalg.inv(info)
    crit = dz._Criterion(kind, [0, 2])
    R = crit.factor(C)
    base = crit.value(C)
    add = crit.change(C, R, A, np.ones(r))
    Vaa, Zaa, La = crit.forms(C, R, A)
    KA = np.matmul(A, C[:, None])
    ci = 1
    Vci = np.matmul(KA, np.swapaxes(A[:, ci], -1, -2)[:, None])
    Zci = np.matmul(La, np.swapaxes(La[:, ci], -1, -2)[:, None])
    swap = dz._swap_change(kind, Vaa, Zaa, La, Vci, Zci, ci)
    for m in range(M):
        for c in range(N):
            plus = info[m] + A[m, c].T @ A[m, c]
            assert base[m] + add[m, c] == pytest.approx(crit.value(np.linalg.inv(plus)[None])[0], rel=1e-9)
            if c != ci:
                sw = plus - A[m, ci].T @ A[m, ci]
                assert base[m] + swap[m, c] == pytest.approx(crit.value(np.linalg.inv(sw)[None])[0],
                                                             rel=1e-8, abs=1e-10)
    # a swap that leaves the information singular is refused
    lone = np.zeros((1, 2, r, 2))
    lone[0, 0, 0, 0], lone[0, 1, 0, 1] = 1.0, 1.0
    C1 = np.eye(2)[None]  # the information of the two rows: the identity
    crit1 = dz._Criterion(kind, [0])
    V1, Z1, L1 = crit1.forms(C1, crit1.factor(C1), lone)
    K1 = np.matmul(lone, C1[:, None])
    s1 = dz._swap_change(kind, V1, Z1, L1, np.matmul(K1, np.swapaxes(lone[:, 0], -1, -2)[:, None]),
                         np.matmul(L1, np.swapaxes(L1[:, 0], -1, -2)[:, None]), 0)
    assert np.isinf(s1[0, 1])  # removing the only row along parameter 0 for one along parameter 1


def test_exchange_never_worse_than_greedy_and_better_than_the_paper(steel):
    assert steel.criterion_value <= steel.criterion_greedy
    assert steel.criterion_value < steel.criterion_reference
    assert len(steel.theta_i) == 30
    pts = set(zip(steel.theta_i, steel.theta_r, steel.phi))
    assert len(pts) == 30  # distinct geometries
    for n in ("n", "k"):
        assert steel.ci95_width[n] < steel.ci95_width_reference[n]
    # the criterion of the greedy choice alone, recomputed from its widths' design
    g = dz.design(STEEL, candidates=SMALL, noise=0.005, n_measurements=12, backend="numpy")
    assert g.criterion_value <= g.criterion_greedy
    ref = g.reference
    assert len(ref["theta_i"]) == 30 and set(ref["theta_i"]) == {30.0, 40.0, 50.0}
    assert g.comparisons["one_incidence"]["n_points"] == 10
    assert g.comparisons["two_incidences"]["n_points"] == 20
    # a second incidence narrows the intervals of the first alone
    one, two = g.comparisons["one_incidence"]["widths"], g.comparisons["two_incidences"]["widths"]
    assert two["n"] < one["n"]
    assert g.information.shape == (8, 18)
    summary = g.summary()
    assert "paper 30/40/50" in summary and "chosen (A)" in summary


def test_criterion_d_and_repeats():
    r = dz.design(STEEL, candidates=SMALL, noise=0.005, n_measurements=10, criterion="D", backend="numpy")
    assert r.criterion == "D" and np.isfinite(r.criterion_value) and r.criterion_value <= r.criterion_greedy
    assert r.criterion_value < r.criterion_reference
    rep = dz.design(STEEL, candidates=[(40, 20), (40, 45), (60, 70), (30, 10), (70, 80), (50, 40)], noise=0.005,
                    n_measurements=9, repeats=True, backend="numpy")
    assert len(rep.theta_i) == 9 and len(set(zip(rep.theta_i, rep.theta_r))) <= 6
    assert rep.information.shape == (6,)


def test_intensity_frees_ks_and_narrows_kd_and_sigma(steel):
    r = dz.design(STEEL, candidates=SMALL, noise=0.005, n_measurements=12, intensity=True, backend="numpy")
    assert r.free == ["n", "k", "sigma", "kd", "c", "ks"] and "ks" in r.ci95_width
    with_f00, dop_only = r.comparisons["chosen"]["widths"], r.comparisons["chosen_other"]["widths"]
    assert "ks" not in dop_only
    for n in ("sigma", "kd", "c"):
        assert with_f00[n] < dop_only[n], n
    ref_f00 = steel.comparisons["reference_other"]["widths"]
    assert ref_f00["kd"] < steel.ci95_width_reference["kd"] and ref_f00["sigma"] < steel.ci95_width_reference["sigma"]
    assert r.target == ["n", "k"]
    ks = dz.design(STEEL, candidates=SMALL, n_measurements=12, intensity=True, target=("ks",), backend="numpy")
    assert ks.target == ["ks"] and ks.ci95_width["ks"] <= r.ci95_width["ks"] * 1.0001


def test_box_of_materials():
    box = dict(n=(1.3, 2.2), k=(0.5, 3.0, "log"), sigma=0.5, kd=0.15, c=-0.3)
    r = dz.design(box, candidates=SMALL, noise=0.005, n_measurements=12, materials=6, seed=2, backend="numpy")
    assert r.n_materials == 6
    assert r.materials["n"].shape == (6,) and np.all((r.materials["n"] >= 1.3) & (r.materials["n"] <= 2.2))
    assert len(np.unique(r.materials["k"])) == 6
    for n in r.free:
        assert r.ci95_width_materials[n].shape == (6,)
        assert r.ci95_width[n] == pytest.approx(np.median(r.ci95_width_materials[n]))
    again = dz.design(box, candidates=SMALL, noise=0.005, n_measurements=12, materials=6, seed=2, backend="numpy")
    np.testing.assert_array_equal(again.theta_i, r.theta_i)
    assert r.criterion_value <= r.criterion_greedy


def test_figure_and_dataset(steel, tmp_path):
    png = tmp_path / "design.png"
    plot_design(steel, png)
    assert png.stat().st_size > 10_000
    nc = tmp_path / "design.nc"
    steel.to_dataset().to_netcdf(nc)
    import xarray as xr
    with xr.open_dataset(nc) as ds:
        np.testing.assert_array_equal(ds.theta_i.values, steel.theta_i)
        assert ds.ci95_width.sel(parameter="n").item() == pytest.approx(steel.ci95_width["n"])
        assert ds.information.dims == ("candidate_theta_i", "candidate_theta_r")
        assert ds.attrs["target"] == "n,k"


@pytest.mark.parametrize("kwargs, words", [
    (dict(target=("n", "q")), ["target", "'q'"]),
    (dict(target=("sigma",), fixed={"sigma": 0.5}), ["target", "'sigma'", "fixed"]),
    (dict(target=("ks",)), ["target", "'ks'", "intensity"]),
    (dict(n_measurements=5), ["n_measurements", "5"]),
    (dict(n_measurements=200, candidates={"theta_i": 40, "theta_r": "0:85:5"}), ["n_measurements", "200", "18"]),
    (dict(noise=0), ["noise", "0"]),
    (dict(noise=-0.01), ["noise", "-0.01"]),
    (dict(noise=5), ["noise", "below 1, the DOP's whole range", "got 5", "0.5% is 0.005"]),
    (dict(intensity_noise=float("nan")), ["intensity_noise", "nan"]),
    (dict(criterion="E"), ["criterion", "'E'"]),
    (dict(candidates={"theta_q": 40}), ["candidates", "theta_q"]),
    (dict(candidates=[(40, 20, 180, 3)]), ["candidates", "shape"]),
    (dict(reference=[[40, "x"]]), ["reference"]),
    (dict(params=dict(n=1.6, k=2.139)), ["sigma"]),
    (dict(params=dict(STEEL, n=7.0)), ["params", "n = 7", "bounds"]),
    (dict(params=dict(STEEL, n=(2, 1))), ["params", "'n'", "low"]),
    (dict(fixed={"sigma": 0.3}), ["fixed", "sigma", "0.3"]),
    (dict(intensity=True, fixed={"ks": 0.9}), ["intensity", "ks", "fixed"]),
    (dict(materials=0), ["materials", "0"]),
])
def test_errors_name_the_argument(kwargs, words):
    kw = dict(params=STEEL, backend="numpy", candidates=SMALL)
    kw.update(kwargs)
    with pytest.raises(ValueError) as err:
        dz.design(kw.pop("params"), **kw)
    text = str(err.value)
    assert "\n" not in text
    for w in words:
        assert w in text, (w, text)


def test_predicted_widths_agree_with_fit_on_simulated_data(steel):
    """A small version of scripts/check_design.py: 8 data sets at the chosen geometries."""
    rng = np.random.default_rng(11)
    geo = dict(theta_i=steel.theta_i, theta_r=steel.theta_r, phi=steel.phi)
    truth = pbrdf_cl.dop(geo["theta_i"], geo["theta_r"], geo["phi"], **STEEL, dtype="float64", backend="numpy")
    ratios = []
    for _ in range(8):
        data = dict(geo, dop=truth + 0.005 * rng.standard_normal(truth.shape), dop_std=np.full(truth.shape, 0.005))
        fit = pbrdf_cl.fit(data, backend="numpy")
        assert fit.free == steel.free
        ratios.append([steel.ci95_width[n] / (fit.ci95_jacobian[n][1] - fit.ci95_jacobian[n][0]) for n in fit.free])
    med = np.median(ratios, axis=0)
    assert np.all((med > 0.75) & (med < 1.33)), dict(zip(steel.free, med))


def test_cli_design(tmp_path, capsys):
    nc, png = tmp_path / "d.nc", tmp_path / "d.png"
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5,kd=0.15,c=-0.3", "ks=0.9", "--candidates",
                   "theta_i=10:80:10", "--candidates", "theta_r=0:85:5", "--noise", "0.005", "--n", "12",
                   "--out", str(nc), "--png", str(png), "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "measurement design: 12 measurements" in out and "paper 30/40/50" in out
    assert nc.stat().st_size > 0 and png.stat().st_size > 0
    import xarray as xr
    with xr.open_dataset(nc) as ds:
        assert ds.sizes["measurement"] == 12
    rc = cli.main(["design", "--params", "n=1.6,k=2.139", "--box", "sigma=0.3:0.6", "--candidates",
                   "theta_i=20:70:10", "theta_r=0:80:10", "--n", "8", "--materials", "4", "--criterion", "D",
                   "--backend", "numpy"])
    out = capsys.readouterr().out
    assert rc == 0 and "median over 4 materials" in out and "criterion D" in out
    store = tmp_path / "d.zarr"  # a Zarr store as for pbrdf-cl sobol
    rc = cli.main(["design", "--params", "n=1.6,k=2.139,sigma=0.5", "--candidates", "theta_i=20:70:10",
                   "theta_r=0:80:10", "--n", "8", "--out", str(store), "--backend", "numpy"])
    assert rc == 0
    with xr.open_zarr(store) as ds:
        assert ds.sizes["measurement"] == 8


@pytest.mark.parametrize("argv, words", [
    (["--params", "n=1.6,k=2.139,sigma=0.5", "--target", "n,x"], ["target", "'x'"]),
    (["--params", "n=1.6,k=2.139,sigma=0.5", "--noise", "-1"], ["noise"]),
    (["--params", "n=1.6,k=2.139,sigma=0.5", "--candidates", "theta_q=1"], ["--candidates", "theta_q"]),
    (["--params", "n=1.6,k=2.139", "--box", "n=1:2"], ["--box", "n", "--params"]),
    (["--params", "n=1.6,k=2.139,sigma=0.5", "--box", "kd=0.3:0.1"], ["--box", "kd=0.3:0.1"]),
    (["--params", "n=1.6,k=2.139,sigma=0.5", "--out", "design.txt"], ["--out design.txt", ".nc", ".zarr"]),
])
def test_cli_design_errors_are_one_line(argv, words, capsys):
    rc = cli.main(["design", *argv, "--backend", "numpy"])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and err.startswith("pbrdf-cl: error:")
    for w in words:
        assert w in err, (w, err)


def test_an_engine_that_is_not_one_is_a_clear_error():
    """engine= takes an Engine or a NumpyEngine; a device name there is one line saying what to do."""
    with pytest.raises(ValueError, match="engine must be a pbrdf_cl.Engine or NumpyEngine, got 'nope'"):
        pbrdf_cl.design(dict(n=1.6, k=2.139, sigma=0.5), engine="nope")
    with pytest.raises(ValueError, match="engine must be"):
        pbrdf_cl.dop(40, 30, n=1.6, k=2.0, sigma=0.3, engine="0:1")


def test_large_noise_is_questioned_and_radians_are_warned_once():
    """A DOP noise above a tenth of its range draws one DataWarning (a percentage?); candidates in
    radians draw one UnitsWarning per grid (issue #34: twice before, once per angle, and then even
    where only one of the angles was small)."""
    import warnings
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        dz.design(STEEL, candidates=SMALL, noise=0.3, n_measurements=12, backend="numpy")
    assert [type(w.message) for w in got] == [pbrdf_cl.DataWarning] and "percentage" in str(got[0].message)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        dz.design(STEEL, candidates={"theta_i": "0.2:1.4:0.2", "theta_r": "0:1.4:0.2"}, n_measurements=12,
                  backend="numpy")
        from pbrdf_cl.analysis.sensitivity import check_geometry
        check_geometry({"theta_i": "0.2:1.4:0.2", "theta_r": "0:85:5"})  # degrees: theta_r is not small
    units = [str(w.message) for w in got if isinstance(w.message, pbrdf_cl.UnitsWarning)]
    assert len(units) == 1 and units[0].startswith("candidates: theta_i and theta_r all lie below"), units


def test_joint_page_quotes_the_design_s_widths(steel):
    """docs/joint.md quotes design's predicted widths at the paper's geometry (issue #34: it quoted
    the fitted median, 6.2, as design's 6.6)."""
    import re
    from pathlib import Path
    text = " ".join((Path(__file__).parents[1] / "docs" / "joint.md").read_text().split())
    m = re.search(r"`pbrdf_cl.design` predicts 95% widths of ([0-9.]+) for n and ([0-9.]+) for k", text)
    assert m, "the sentence moved"
    w = steel.ci95_width_reference
    assert (float(m.group(1)), float(m.group(2))) == (round(w["n"], 1), round(w["k"], 1))
