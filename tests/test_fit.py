"""Inversion: recovery of known parameters, honest intervals, the global stage, validation, CLI."""
import json
import os
import subprocess
import sys
from pathlib import Path

import nlopt
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.cli import fit as cli_fit
from pbrdf_cl.fitting import common
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.fitting.sample import basins, stages, uncertainty
from pbrdf_cl.io.measurements import PHI_DEFAULT_NOTE, from_arrays, read_csv

ROOT = Path(__file__).resolve().parent.parent
TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
TRUTH = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15 / 0.9, c=-0.3)  # the paper's steel, kd as kd/ks


def synthetic(truth=TRUTH, noise=0.0, seed=0, ti=TI, tr=TR, **kw):
    d = pbrdf_cl.dop(ti, tr, 180.0, backend="numpy", **truth, **kw)
    if noise:
        d = np.clip(d + np.random.default_rng(seed).normal(0, noise, d.size), 0, 1)
        return dict(theta_i=ti, theta_r=tr, dop=d, dop_std=np.full(d.size, noise))
    return dict(theta_i=ti, theta_r=tr, dop=d)


def test_noise_free_recovers_truth_exactly():
    r = pbrdf_cl.fit(synthetic())
    assert r.sse <= 1e-12
    for name, v in TRUTH.items():
        lo, hi = r.ci95[name]
        assert lo <= v <= hi
        assert r.x[name] == pytest.approx(v, rel=1e-5, abs=1e-6)
    assert r.x["ks"] == 1.0 and "ks" not in r.free
    assert any("kd/ks" in note for note in r.notes)
    kd_line = next(ln for ln in r.summary().splitlines() if ln.split()[:1] == ["kd"])
    assert kd_line.endswith("(= kd/ks: ks fixed at 1)") and r.kd_ratio == r.x["kd"]
    assert set(r.nfev) >= {"grid", "direct", "bobyqa"} and r.nfev["grid"] == 24 * 32 * 16 * 16 * 8
    assert set(r.seconds) == set(r.nfev) and all(t > 0 for k, t in r.seconds.items() if r.nfev[k] > 0)


@pytest.mark.parametrize("seed", [1, 2])
def test_noisy_data_truth_inside_reported_intervals(seed):
    r = pbrdf_cl.fit(synthetic(noise=0.002, seed=seed))
    for name, v in TRUTH.items():
        lo, hi = r.ci95[name]
        assert lo <= v <= hi, (name, v, lo, hi)
    assert 0.3 < r.reduced_chi2 < 3
    assert r.residuals.shape == (30,) and r.rmse == pytest.approx(np.sqrt(np.mean(r.residuals ** 2)))
    assert r.corr.shape == (5, 5) and np.allclose(np.diag(r.corr), 1)
    # DOP data barely determine n and k: the intervals are wide, and say so
    assert r.ci95["k"][1] - r.ci95["k"][0] > 0.5


def test_grid_seed_beats_a_single_local_start_on_a_false_minimum():
    tr = np.arange(20.0, 66.0, 5.0)
    ti = np.full(tr.size, 40.0)
    truth = dict(n=1.066707353082284, k=2.4674784115974804, sigma=0.8681994056377615, kd=0.8184708030012616,
                 c=-0.31037739981093404)
    data = synthetic(truth, ti=ti, tr=tr)
    meas = from_arrays(data["theta_i"], data["theta_r"], data["dop"])
    mdl = stages.Model(meas, "paper")
    names = ("n", "k", "sigma", "kd", "c")
    lo = np.array([fit_setup.DEFAULT_BOUNDS[n][0] for n in names])
    hi = np.array([fit_setup.DEFAULT_BOUNDS[n][1] for n in names])

    def sse(x):
        r = mdl.dop(dict(zip(names, x), ks=1.0)) - meas.dop
        return float(r @ r)
    _, local, _ = stages._nlopt_min(nlopt.LN_BOBYQA, sse, lo, hi, (lo + hi) / 2, maxeval=4000, step=(hi - lo) / 10)
    r = pbrdf_cl.fit(data)
    assert local > 1e-7          # the single start from the centre stops in a false minimum
    assert r.sse <= 1e-12        # the grid-seeded search finds the truth


def test_specular_model_and_comparison():
    data = synthetic(dict(n=1.24, k=6.6, sigma=0.3, kd=0.0, c=0.0))  # aluminium, no diffuse part
    r = pbrdf_cl.fit(data, model="specular")
    assert r.free == ["n", "k"] and r.sse <= 1e-12
    assert r.x["n"] == pytest.approx(1.24, rel=1e-5) and r.x["k"] == pytest.approx(6.6, rel=1e-5)
    both = pbrdf_cl.compare_models(synthetic(noise=0.002, seed=3))
    six, spec = both["six-param"], both["specular"]
    assert six.sse <= spec.sse * (1 + 1e-9)   # the specular model is the six-param one with kd = 0
    assert np.isfinite(six.aic) and np.isfinite(spec.bic)
    assert "| six-param |" in both["table"] and "| specular (ref. [7]) |" in both["table"]
    assert both["preferred"] == ("six-param" if six.bic <= spec.bic else "specular")


def test_fixed_and_bounds():
    r = pbrdf_cl.fit(synthetic(noise=0.002, seed=4), fixed=dict(sigma=0.5), bounds=dict(n=(1.2, 2.5)))
    assert "sigma" not in r.free and r.x["sigma"] == 0.5
    assert 1.2 <= r.x["n"] <= 2.5 and r.ci95["n"][0] >= 1.2 and r.ci95["n"][1] <= 2.5


def test_fixing_ks_makes_kd_absolute():
    r = pbrdf_cl.fit(synthetic(), fixed=dict(ks=0.9))
    assert r.x["ks"] == 0.9 and r.x["kd"] == pytest.approx(0.15, rel=1e-5)
    assert any("ks is fixed at 0.9" in n for n in r.notes)
    kd_line = next(ln for ln in r.summary().splitlines() if ln.split()[:1] == ["kd"])
    assert kd_line.endswith("(absolute, with ks fixed at 0.9)") and r.kd_ratio == pytest.approx(0.15 / 0.9, rel=1e-5)
    with pytest.raises(ValueError, match="fixed: sigma is not a parameter of the specular model"):
        pbrdf_cl.fit(synthetic(), model="specular", fixed=dict(sigma=0.3))


def test_intensities_separate_ks_and_kd():
    r = pbrdf_cl.fit(ROOT / "examples" / "steel_435nm_with_f00.csv")
    assert "ks" in r.free
    for name, v in dict(ks=0.9, kd=0.15 / 0.9, n=1.6, k=2.139).items():  # the interval under "kd" is kd/ks's
        lo, hi = r.ci95[name]
        assert lo <= v <= hi, (name, v, lo, hi)
    assert not any("kd/ks" in n and "fixed at 1" in n for n in r.notes)
    # which kd is which: x holds the model's absolute kd, kd_ratio the fitted ratio, and the summary,
    # the --quiet lines and the JSON say so beside the ratio's interval
    assert r.kd_ratio == pytest.approx(r.x["kd"] / r.x["ks"], rel=1e-12)
    lines = r.summary().splitlines()
    ratio = next(ln for ln in lines if ln.split()[:1] == ["kd/ks"])
    lo, hi = r.ci95["kd"]
    assert f"{r.kd_ratio:10.5g}" in ratio and f"[{lo:.4g}, {hi:.4g}]" in ratio
    absolute = next(ln for ln in lines if ln.split()[:1] == ["kd"])
    assert f"{r.x['kd']:10.5g}" in absolute and "absolute" in absolute and "interval" not in absolute
    brief = cli_fit._fit_brief(r)
    assert f"kd/ks = {r.kd_ratio:.5g}  [{lo:.4g}, {hi:.4g}]" in brief and f"kd = {r.x['kd']:.5g}" in brief
    record = cli_fit._fit_json(r)
    assert record["kd_ratio"] == r.kd_ratio and record["kd_fitted_as"] == "kd/ks"


def test_identifiability_notes_name_the_weak_direction():
    r = pbrdf_cl.fit(synthetic(dict(TRUTH, kd=0.0), noise=0.002, seed=5))
    text = " ".join(r.notes)
    assert "condition number" in text or "not determined" in text or "poorly determined" in text


# A problem of scripts/bench_fit.py (paper geometry, truth drawn from the default bounds, DOP
# noise 0.002, clipped at 0): its best optimum (k = 0.44) lies in a valley of the k profile that
# none of the grid's best local minima lies in, near the k = 0 bound slice; the better-looking
# basins (k ~ 4.3) are 0.014 worse.
VALLEY_DOP = [
    0.0, 0.0023774091845094624, 0.0012755942370135404,
    0.0, 0.0022830251799971888, 0.0014746615494392653,
    0.0009326697003045872, 0.0014453588031925048, 0.0014516396362489615,
    0.00031618172463758194, 0.0, 0.0004723950235811915,
    0.0, 0.0, 0.0033020193815205758,
    0.00034876008409582084, 0.0009217372351570112, 0.0008408029955753205,
    0.0012710430426641057, 0.0013144341844743253, 0.0006753058302157709,
    0.0, 0.002586434064553625, 0.0,
    0.003039552024052475, 0.0, 0.0,
    0.0034484465777125245, 0.0012991237343859773, 0.0002978636876875187]


def test_profile_valleys_and_bound_slices_seed_a_distant_basin(monkeypatch):
    from scipy.optimize import least_squares
    meas = from_arrays(TI, TR, np.array(VALLEY_DOP), 180.0, np.full(30, 0.002))
    mdl = stages.Model(meas, "paper")
    names = ("n", "k", "sigma", "kd", "c")
    lo = np.array([fit_setup.DEFAULT_BOUNDS[n][0] for n in names])
    hi = np.array([fit_setup.DEFAULT_BOUNDS[n][1] for n in names])
    ref = least_squares(lambda x: (mdl.dop(dict(zip(names, x), ks=1.0)) - meas.dop) / 0.002, [1, 0.44, 1, 5, -1],
                        bounds=(lo, hi), x_scale=hi - lo, ftol=1e-15, xtol=1e-15, gtol=1e-15)
    best = 2 * ref.cost
    r = pbrdf_cl.fit(meas)
    assert r.chi2 <= best * (1 + 1e-9) and r.x["k"] < 1
    # each kind of extra seed finds it alone; the grid's local minima alone lead elsewhere
    monkeypatch.setattr(stages, "PROFILE_SEEDS", 0)
    assert pbrdf_cl.fit(meas).chi2 <= best * (1 + 1e-9)
    monkeypatch.setattr(basins, "bound_seeds", lambda sse, found: [])
    assert pbrdf_cl.fit(meas).chi2 > best + 0.01
    monkeypatch.setattr(stages, "PROFILE_SEEDS", 2)
    assert pbrdf_cl.fit(meas).chi2 <= best * (1 + 1e-9)


def test_grid_profiles_are_the_minima_over_the_other_axes():
    rng = np.random.default_rng(3)
    for shape in [(7,), (6, 5), (4, 5, 6), (5, 4, 3, 6, 2)]:
        sse = rng.random(shape, dtype=np.float32)
        names = list("abcde")[:len(shape)]
        prof = basins.grid_profiles(sse, names)
        for i, n in enumerate(names):
            others = tuple(j for j in range(len(shape)) if j != i)
            np.testing.assert_array_equal(prof[n], sse.min(axis=others) if others else sse)
            assert prof[n].dtype == np.float64


def test_profile_seeds_find_valleys_behind_a_ridge():
    x = np.linspace(0, 1, 21)
    # two valleys along axis 0 (floors at x = 0.2 and 0.8, the second 2 higher, a ridge 34 above it)
    sse = (np.minimum((x - 0.2) ** 2, (x - 0.8) ** 2 + 0.005) * 400)[:, None] + np.linspace(0, 1, 9)[None, :]
    prof = basins.grid_profiles(sse, ["a", "b"])
    assert basins.profile_seeds(sse, prof, ["a", "b"], [(4, 0)], 2, rise=1.0) == [(16, 0)]
    assert basins.profile_seeds(sse, prof, ["a", "b"], [(4, 0)], 2, rise=40.0) == []  # ridge too low
    assert basins.profile_seeds(sse, prof, ["a", "b"], [(4, 0), (15, 2)], 2, rise=1.0) == []  # already a basin
    assert basins.profile_seeds(sse, prof, ["a", "b"], [(4, 0)], 0, rise=1.0) == []


def test_batched_levenberg_marquardt():
    def rosenbrock(X):  # (B, 3) -> (B, 3); x2 does not enter: a vanishing Jacobian column
        return np.stack([1 - X[:, 0], 10 * (X[:, 1] - X[:, 0] ** 2), np.zeros(len(X))], axis=1)
    lo, hi = np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 1.0])
    starts = np.array([[-1.2, 1.0, 0.4], [1.5, -1.5, 0.0], [0.0, 0.0, 1.0]])
    asked = []
    X, sse, rows = common.lm_batch(lambda X: asked.append(len(X)) or rosenbrock(X), starts, lo, hi, 100)
    np.testing.assert_allclose(X[:, :2], 1.0, atol=1e-7)
    np.testing.assert_array_equal(X[:, 2], starts[:, 2])  # no runaway step along the flat direction
    # the rows it reports are the rows it asked for; converged problems stop being evaluated
    assert np.all(sse < 1e-14) and rows == sum(asked) and 3 * 4 * 2 <= rows < 3 * 4 * 101
    # ... without changing the answer: the same with every problem evaluated to the end
    Xall, sseall, rows_all = common.lm_batch(rosenbrock, starts, lo, hi, 100, rows_apart=False)
    np.testing.assert_array_equal(X, Xall)
    np.testing.assert_array_equal(sse, sseall)
    # each problem sees the numbers it would see alone
    for i in range(3):
        Xi, si, _ = common.lm_batch(rosenbrock, starts[i:i + 1], lo, hi, 100)
        np.testing.assert_allclose(Xi[0], X[i], rtol=0, atol=1e-12)
    # the optimum on a bound: x0 <= 0.5 holds x0 there, x1 = x0^2
    X, sse, _ = common.lm_batch(rosenbrock, starts, lo, np.array([0.5, 2.0, 1.0]), 100)
    np.testing.assert_allclose(X[:, :2], [[0.5, 0.25]] * 3, atol=1e-7)
    np.testing.assert_allclose(sse, 0.25, rtol=1e-9)


def test_bound_seeds_are_the_best_points_of_the_bound_slices():
    sse = np.arange(48.0).reshape(6, 8)[::-1] % 7  # some landscape
    seeds = basins.bound_seeds(sse, [])
    for idx in seeds:
        assert any(idx[j] in (0, sse.shape[j] - 1) for j in range(2))
        j = 0 if idx[0] in (0, 5) else 1
        assert sse[idx] == np.take(sse, idx[j], axis=j).min()
    assert len(seeds) == len(set(seeds)) and len(seeds) >= 2
    assert basins.bound_seeds(sse, [(a, b) for a in range(6) for b in range(8)]) == []  # all taken


def test_interval_pieces_interpolate_between_sharp_and_flat():
    from scipy.stats import norm
    from scipy.stats import t as student_t

    def central(cdfs, x=2.0, se=np.inf, lo=1.0, hi=5.0, nodes=()):
        return uncertainty._central_interval(cdfs, x, se, lo, hi, nodes)
    # the local (Laplace) piece: +-1.96 se when se is small, the middle 95% of the bounds when huge
    a, b = central([uncertainty._truncated_cdf(norm, 2.0, 0.01, 1.0, 5.0)], se=0.01)
    assert a == pytest.approx(2 - 1.959964 * 0.01, abs=2e-5) and b == pytest.approx(2 + 1.959964 * 0.01, abs=2e-5)
    a, b = central([uncertainty._truncated_cdf(norm, 2.0, 1e-9, 1.0, 5.0)], se=1e-9)
    assert a < 2 < b and b - a == pytest.approx(2 * 1.959964e-9, rel=1e-3)
    for se in (1e6, np.inf):  # a direction the data do not constrain: the uniform prior
        a, b = central([uncertainty._truncated_cdf(norm, 2.0, se, 1.0, 5.0)], se=se)
        assert a == pytest.approx(1.1, abs=1e-4) and b == pytest.approx(4.9, abs=1e-4)
    a, b = central([uncertainty._truncated_cdf(student_t(5), 2.0, 0.01, 1.0, 5.0)], se=0.01)
    assert b - 2 == pytest.approx(2.570582 * 0.01, rel=1e-3)
    # the grid piece: a flat profile gives the middle 95% of the bounds (also on uneven nodes) ...
    vals = 1 + 4 * np.linspace(0, 1, 24) ** 2
    a, b = central([uncertainty._grid_cdf(np.full(24, 7.0), vals, 30, True)], nodes=vals)
    assert a == pytest.approx(1.1, abs=1e-6) and b == pytest.approx(4.9, abs=1e-6)
    # ... a parabola in chi^2 with curvature 1/se^2 gives +-1.96 se, and the SSE form (unknown noise)
    # with SSE = s2 * chi2 behaves alike for many points
    vals = np.linspace(0, 10, 2001)
    a, b = central([uncertainty._grid_cdf(3.0 + ((vals - 4) / 0.5) ** 2, vals, 30, True)], lo=0, hi=10, nodes=vals)
    assert a == pytest.approx(4 - 1.96 * 0.5, abs=0.01) and b == pytest.approx(4 + 1.96 * 0.5, abs=0.01)
    s2, m = 1e-6, 10000
    a, b = central([uncertainty._grid_cdf(s2 * (m + ((vals - 4) / 0.5) ** 2), vals, m, False)], lo=0, hi=10, nodes=vals)
    assert a == pytest.approx(4 - 1.96 * 0.5, abs=0.02) and b == pytest.approx(4 + 1.96 * 0.5, abs=0.02)
    # the mixture of the two: halfway where they disagree (sharp at 2, flat over [1, 5])
    a, b = central([uncertainty._truncated_cdf(norm, 2.0, 1e-6, 1.0, 5.0), lambda t: np.clip((t - 1) / 4, 0, 1)],
                   se=1e-6)
    assert a == pytest.approx(1.2, abs=1e-6) and b == pytest.approx(4.8, abs=1e-6)


def test_the_standard_cdfs_are_scipy_stats_bit_for_bit():
    """The posterior's local piece takes its CDF from scipy.special (StandardCdf: ndtr, stdtr),
    without scipy.stats' argument handling of each call: the same numbers as norm.cdf and
    t(dof).cdf, bit for bit, infinities and NaN included, and the same truncated CDF."""
    from scipy.stats import norm
    from scipy.stats import t as student_t
    x = np.concatenate([np.random.default_rng(7).normal(0, 4, 5000), [np.inf, -np.inf, 0.0, -0.0, np.nan]])
    np.testing.assert_array_equal(uncertainty.StandardCdf().cdf(x), norm.cdf(x))
    for dof in (1, 4, 27, 300):
        np.testing.assert_array_equal(uncertainty.StandardCdf(dof).cdf(x), student_t(dof).cdf(x))
        mesh = np.linspace(1.0, 5.0, 2001)
        ours = uncertainty._truncated_cdf(uncertainty.StandardCdf(dof), 2.0, 0.3, 1.0, 5.0)
        np.testing.assert_array_equal(ours(mesh), uncertainty._truncated_cdf(student_t(dof), 2.0, 0.3, 1.0, 5.0)(mesh))


def test_sharp_parameter_is_not_blurred_to_the_grid_cell():
    # kd alone, well determined: its grid axis (16 nodes over [0, 5]) is far coarser than its
    # uncertainty, so the interval is the local one, +-1.96 standard errors
    r = pbrdf_cl.fit(synthetic(noise=0.002, seed=7), fixed=dict(n=TRUTH["n"], k=TRUTH["k"], sigma=TRUTH["sigma"],
                                                                 c=TRUTH["c"]))
    a, b = r.ci95["kd"]
    se = r.stderr["kd"]
    assert se < 0.01 and a == pytest.approx(r.x["kd"] - 1.96 * se, rel=1e-3)
    assert b == pytest.approx(r.x["kd"] + 1.96 * se, rel=1e-3)


def test_unconstrained_parameters_get_the_middle_of_their_bounds():
    # with kd = 0 the DOP depends on neither sigma nor c: their 95% intervals are the middle 95% of
    # the bounds (a uniform prior over them), not the whole range
    r = pbrdf_cl.fit(synthetic(dict(TRUTH, kd=0.0), noise=0.002, seed=6), fixed=dict(kd=0.0))
    # (the reported value is arbitrary here and may lie outside the interval, on a bound)
    for name, (lo, hi) in dict(c=(-1.0, 0.0), sigma=(0.05, 1.0)).items():
        assert r.ci95[name] == pytest.approx((lo + 0.025 * (hi - lo), hi - 0.025 * (hi - lo)), abs=1e-3 * (hi - lo))
    assert any("sigma" in note and "not determined" in note for note in r.notes)


def write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("text,pattern", [
    ("theta_i,dop\n40,0.1\n", r"line 1: missing column 'theta_r'"),
    ("theta_i,theta_r,dop,Dop\n40,30,0.1,1\n", r"line 1: 'dop' and 'Dop' name the same column"),
    ("# comment\ntheta_i,theta_r,dop\n40,30,0.1\n40,abc,0.2\n", r"line 4: theta_r = 'abc' is not a number"),
    ("theta_i,theta_r,dop\n40,30,0.1\n40,30,nan\n", r"line 3: dop is nan"),
    ("theta_i,theta_r,dop\n40,30,0.1\n95,30,0.2\n", r"line 3: theta_i = 95.0 is not in \[0, 90\) degrees"),
    ("theta_i,theta_r,dop\n\n40,30,1.2  # too high\n", r"line 3: dop = 1.2 is not in \[0, 1\]"),
    ("theta_i,theta_r,dop,dop_std\n40,30,0.2,0\n", r"line 2: dop_std = 0.0 is not > 0"),
    ("theta_i,theta_r,dop\n40,30\n", r"line 2: 2 values for 3 columns"),
    ("theta_i,theta_r,dop\n", r"no measurements"),
    ("", r"empty file"),
])
def test_csv_validation_names_the_line(tmp_path, text, pattern):
    with pytest.raises(ValueError, match=pattern):
        read_csv(write(tmp_path, text))


def test_fit_validation(tmp_path):
    few = write(tmp_path, "theta_i,theta_r,dop\n40,30,0.1\n40,35,0.12\n40,40,0.15\n")
    with pytest.raises(ValueError, match="3 measurements for 5 free parameters"):
        pbrdf_cl.fit(few)
    data = synthetic()
    with pytest.raises(ValueError, match="bounds: unknown parameter 'q'"):
        pbrdf_cl.fit(data, bounds=dict(q=(0, 1)))
    with pytest.raises(ValueError, match=r"bounds: n = \(3.0, 2.0\) must be finite with low < high"):
        pbrdf_cl.fit(data, bounds=dict(n=(3, 2)))
    with pytest.raises(ValueError, match="fixed: sigma = -1.0 is outside"):
        pbrdf_cl.fit(data, fixed=dict(sigma=-1))
    with pytest.raises(ValueError, match="model must be one of"):
        pbrdf_cl.fit(data, model="torrance")
    with pytest.raises(ValueError, match="data: missing column 'dop'"):
        pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR))


def test_cli_fit_round_trip(tmp_path):
    out, png = tmp_path / "fit.json", tmp_path / "fit.png"
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", str(ROOT / "examples" / "steel_435nm.csv"),
                           "--fix", "sigma=0.5", "--bounds", "n=1:3", "--json", str(out), "--plot", str(png),
                           "--compare"], capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "model: six-param" in proc.stdout and "model: specular" in proc.stdout
    assert "preferred by BIC" in proc.stdout
    res = json.loads(out.read_text())
    six = res["fits"]["six-param"]
    assert six["x"]["sigma"] == 0.5 and "sigma" not in six["free"] and 1 <= six["x"]["n"] <= 3
    assert set(res["fits"]) == {"six-param", "specular"}
    assert len(six["residuals"]) == 30
    from_json = pbrdf_cl.dop(TI, TR, backend="numpy", **six["x"]) - read_csv(ROOT / "examples" / "steel_435nm.csv").dop
    np.testing.assert_allclose(six["residuals"], from_json, atol=1e-12)
    assert png.stat().st_size > 10000 and png.read_bytes()[:4] == b"\x89PNG"
    bad = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", str(ROOT / "examples" / "steel_435nm.csv"),
                          "--bounds", "n=1-3"], capture_output=True, text=True, timeout=120, env=env)
    assert bad.returncode != 0 and "--bounds n=1-3: bounds are low:high, two numbers; write n=1:3" in bad.stderr


def test_cli_fit_one_model_and_quiet(tmp_path):
    """--model fits that model only (a specular fit of 3 points is possible); --quiet prints the values alone."""
    csv = tmp_path / "three.csv"
    truth = dict(n=1.6, k=2.139)
    tr = np.array([20.0, 45.0, 65.0])
    dop = pbrdf_cl.dop(40, tr, model="specular", backend="numpy", **truth)
    csv.write_text("theta_i,theta_r,dop\n" + "".join(f"40,{a:g},{float(d)!r}\n" for a, d in zip(tr, dop)))
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", str(csv), "--model", "specular", "--quiet"],
                          capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    notes = [ln.strip() for ln in lines[1:] if ln.strip().startswith("note:")]
    assert lines[0].startswith("specular: SSE") and [ln.split()[0] for ln in lines[1:3]] == ["n", "k"]
    assert float(lines[1].split()[2]) == pytest.approx(1.6, rel=1e-4)
    assert len(lines) == 3 + len(notes) and notes == [f"note: {PHI_DEFAULT_NOTE}"]  # the CSV has no phi column
    assert "six-param" not in proc.stdout and "preferred" not in proc.stdout


def test_lockstep_batching_gives_each_optimiser_its_own_numbers():
    """Optimisers run in lockstep with batched evaluations see exactly what they see alone."""
    def rosen_rows(X):  # residual form of Rosenbrock, shifted per column, with a ragged call pattern
        return np.stack([10 * (X[:, 1] - X[:, 0] ** 2), 1 - X[:, 0], 0.1 * X[:, 2]], axis=1)
    lo, hi = np.array([-2.0, -1.0, -1.0]), np.array([2.0, 3.0, 1.0])

    def job(x0, algorithm):
        def run(rows):
            sse = lambda x: float(np.sum(rows(x)[0] ** 2))  # noqa: E731
            return stages._nlopt_min(algorithm, sse, lo, hi, x0, maxeval=300, step=np.full(3, 0.3))
        return run
    jobs = [job(np.array([a, b, 0.5]), alg) for a, b in ((-1.5, 2.0), (0.5, -0.5), (1.8, 2.9), (0.0, 0.0))
            for alg in (nlopt.LN_BOBYQA, nlopt.GN_DIRECT_L)]
    alone = [stages._Lockstep(rosen_rows).run([j])[0] for j in jobs]
    runner = stages._Lockstep(rosen_rows)
    together = runner.run(jobs)
    for (xa, fa, na), (xt, ft, nt) in zip(alone, together):
        assert na == nt and fa == ft and np.array_equal(xa, xt)
    assert runner.rows == sum(n for _, _, n in alone)


def test_lockstep_reraises_a_job_error():
    def bad(rows):
        rows(np.zeros(2))
        raise ZeroDivisionError("inside the job")

    def good(rows):
        return [rows(np.full(2, i)) for i in range(5)]
    with pytest.raises(ZeroDivisionError, match="inside the job"):
        stages._Lockstep(lambda X: X * 2).run([good, bad, good])


def test_batched_jacobian_equals_scipy_two_point():
    from scipy.optimize._numdiff import approx_derivative
    rng = np.random.default_rng(3)
    A = rng.normal(size=(7, 4))
    fun = lambda x: np.sin(A @ x) + x.sum()  # noqa: E731
    lo, hi = np.zeros(4), np.ones(4)
    for x in (rng.random(4), np.array([0.0, 1.0, 0.5, 1.0 - 1e-12])):
        r, J = common.fd_jacobian(lambda X: np.array([fun(r) for r in X]), x[None], lo, hi)
        np.testing.assert_array_equal(J[0].T, approx_derivative(fun, x, method="2-point", bounds=(lo, hi)))
        np.testing.assert_array_equal(r[0], fun(x))


def test_grid_basins_from_a_pool_equal_the_whole_grid_search():
    rng = np.random.default_rng(0)
    axes = np.meshgrid(*[np.linspace(0, 1, n) for n in (24, 32, 16, 16, 8)], indexing="ij")
    for trial in range(3):
        sse = sum(np.sin(3 * (i + 1) * a + trial) ** 2 for i, a in enumerate(axes)) + 0.01 * rng.random(axes[0].shape)
        pooled = basins.grid_basins(sse, 6)
        whole = [tuple(int(v) for v in c) for c in basins._grid_minima(sse, np.arange(sse.size), 6)]
        assert pooled == whole and len(pooled) == 6
        for idx in pooled:  # each is a local minimum of the grid
            for ax in range(sse.ndim):
                for s in (-1, 1):
                    nb = list(idx)
                    nb[ax] += s
                    if 0 <= nb[ax] < sse.shape[ax]:
                        assert sse[idx] <= sse[tuple(nb)]


def test_bench_fit_script_reports_every_method(tmp_path):
    """scripts/bench_fit.py runs end to end on a few problems (its numbers are measured by running
    it, not asserted here)."""
    out = tmp_path / "bench_fit.json"
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_fit.py"), "--problems", "2",
                           "--baseline-problems", "1", "--quick", "--json", str(out)],
                          capture_output=True, text=True, timeout=600, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(out.read_text())
    assert len(report) == 2
    for geometry in report.values():
        methods = geometry["summary"]
        assert set(methods) == {"pbrdf_cl.fit", "oracle: least_squares from the truth",
                                "scipy least_squares from the centre", "scipy differential_evolution",
                                "scipy 4-start least_squares"}
        assert methods["pbrdf_cl.fit"]["problems"] == 2 and methods["scipy differential_evolution"]["problems"] == 1
        assert all(m["median_seconds"] > 0 for m in methods.values())
        for m in methods.values():  # a share of the problems
            assert m["optimum_found"] * m["problems"] == pytest.approx(round(m["optimum_found"] * m["problems"]))
        assert methods["pbrdf_cl.fit"]["optimum_found"] == 1.0  # the pipeline finds the optimum of both
        assert set(geometry["coverage_95"]) == {"n", "k", "sigma", "kd", "c"}
        assert all(c * 2 in (0, 1, 2) for c in geometry["coverage_95"].values())  # of 2 problems
        assert all(0 < w <= 1 for w in geometry["mean_width_over_bounds"].values())
    assert "optimum found" in proc.stdout and "interval coverage" in proc.stdout


def test_rows_repeated_exactly_are_noted(tmp_path):
    """The same rows appended three times (issue #34): the fit says that 60 of the 90 rows repeat
    an earlier one (by line), up to 3 copies, since counting them as independent narrows the
    intervals; the file alone draws no such note, nor do repeated geometries with other values."""
    src = (ROOT / "examples" / "steel_435nm.csv").read_text().splitlines()
    head = [line for line in src if line.startswith("#") or not line[:1].isdigit()]
    rows = [line for line in src if line[:1].isdigit()]
    path = tmp_path / "thrice.csv"
    path.write_text("\n".join(head + rows * 3) + "\n")
    r = pbrdf_cl.fit(path)
    dup = [n for n in r.notes if "repeat an earlier row exactly" in n]
    assert len(dup) == 1 and dup[0].startswith(f"{2 * len(rows)} of the {3 * len(rows)} rows") and "3 copies" in dup[0]
    assert f"line {len(head) + len(rows) + 1} repeats line {len(head) + 1}" in dup[0]
    assert not [n for n in pbrdf_cl.fit(ROOT / "examples" / "steel_435nm.csv").notes if "repeat" in n]
    m = read_csv(ROOT / "examples" / "steel_435nm.csv")
    again = from_arrays(np.tile(m.theta_i, 2), np.tile(m.theta_r, 2), np.concatenate([m.dop, m.dop + 1e-3]))
    from pbrdf_cl.io.measurements import duplicates_note
    assert duplicates_note(again) is None and duplicates_note(from_arrays(*(np.tile(a, 2) for a in (
        m.theta_i, m.theta_r, m.dop)))).startswith("30 of the 60 rows")


def test_fit_image_help_offers_no_joint_set_form():
    """``fit-image --help`` describes --fix/--bounds without the joint fit's SET:NAME form, which
    fit-image refuses; ``fit --help`` names it with a set named as its file is (issue #34)."""
    from pbrdf_cl.cli.app import build_parser
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    image, fit = sub.choices["fit-image"].format_help(), sub.choices["fit"].format_help()
    assert "SET:" not in image and "joint" not in image.split("--fix", 1)[1].split("--shadowing")[0]
    assert "SET:NAME=VALUE" in " ".join(fit.split()) and "w435:kd=0.1" in " ".join(fit.split())
