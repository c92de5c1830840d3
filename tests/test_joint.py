"""Joint fits (issue #28): several data sets, some parameters shared.  Truth recovered on synthetic
three-wavelength data made with the numpy reference, the global optimum against a brute-force
multi-start, shared values equal across sets, per-set fixed and bounds, one-line refusals, the CLI,
to_dataset and the separate fits beside the joint one."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_fit_output import assert_valid_covariance

import pbrdf_cl
from pbrdf_cl.fitting.common import OUTSIDE_FOOTNOTE, OUTSIDE_MARK
from pbrdf_cl.fitting.sets import joint
from pbrdf_cl.io.measurements import from_arrays, split_sets, write_csv

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
GEOMETRY = dict(sigma=0.5, c=-0.3)
#: One sample at three wavelengths: n, k and kd/ks change, sigma and c do not.
OWN = {"435": dict(n=1.6, k=2.139, kd=0.17), "532": dict(n=2.0, k=2.8, kd=0.1), "633": dict(n=2.5, k=3.4, kd=0.06)}


def three_sets(noise=0.003, seed=1, own=OWN, geometry=GEOMETRY):
    rng = np.random.default_rng(seed)
    out = {}
    for s, t in own.items():
        d = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", ks=1.0, **t, **geometry)
        if noise:
            d = np.clip(d + rng.normal(0, noise, d.size), 0, 1)
        out[s] = from_arrays(TI, TR, d, 180.0, np.full(d.size, noise) if noise else None)
    return out


@pytest.fixture(scope="module")
def noisy():
    sets = three_sets()
    return sets, pbrdf_cl.fit_joint(sets)


def test_noise_free_recovers_truth():
    res = pbrdf_cl.fit_joint(three_sets(noise=0.0))
    assert res.sse <= 1e-10
    for s, own in OWN.items():
        truth = {**own, **GEOMETRY}
        for p, v in truth.items():
            lo, hi = res.ci95[s][p]
            assert lo <= v <= hi, (s, p, v, (lo, hi))
        for p in ("n", "k"):
            assert res.x[s][p] == pytest.approx(truth[p], rel=0.05)
    assert res.shared_x["sigma"] == pytest.approx(0.5, rel=0.02)


def test_noisy_intervals_cover_truth_and_shared_values_repeat(noisy):
    _, res = noisy
    assert res.success and res.fits_data
    assert res.shared == ["sigma", "c"] and res.sets == list(OWN)
    for s, own in OWN.items():
        for p, v in {**own, **GEOMETRY}.items():
            lo, hi = res.ci95[s][p]
            assert lo <= v <= hi, (s, p, v, (lo, hi))
        for p in ("sigma", "c"):
            assert res.x[s][p] == res.shared_x[p]
            assert res.ci95[s][p] == res.ci95[res.sets[0]][p]
            assert res.stderr[s][p] == res.stderr[res.sets[0]][p]
        assert res.x[s]["ks"] == 1.0 and "ks" not in res.ci95[s]
    # the fit evaluates: x of each set reproduces its residuals
    for s, m in res.measurements.items():
        r = pbrdf_cl.dop(m.theta_i, m.theta_r, m.phi, backend="numpy", **res.x[s]) - m.dop
        assert float(r @ r) == pytest.approx(res.set_sse[s], rel=1e-9)
    assert res.sse == pytest.approx(sum(res.set_sse.values()))
    assert res.free[:2] == ["sigma", "c"] and "n[435]" in res.free and len(res.free) == 11
    assert "JointResult(" in repr(res) and "shared (one value for every set)" in res.summary()


def _brute_force(sets, starts, seed):
    """Best chi^2 of scipy least_squares on the stacked residuals from random starts."""
    from scipy.optimize import least_squares
    setup = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    lo, hi = setup.lo, setup.hi
    rng = np.random.default_rng(seed)
    best = np.inf
    for _ in range(starts):
        r = least_squares(lambda x: resid.rows(x[None])[0], lo + rng.random(lo.size) * (hi - lo), bounds=(lo, hi),
                          x_scale=hi - lo, ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=2000)
        best = min(best, 2 * r.cost)
    return best


@pytest.mark.parametrize("seed", [3, 11])
def test_global_optimum_against_brute_force_multistart(seed):
    rng = np.random.default_rng(seed)
    geometry = dict(sigma=0.05 + 0.95 * rng.random(), c=-rng.random())
    own = {s: dict(n=1 + 4 * rng.random(), k=10 * rng.random(), kd=5 * rng.random()) for s in "abc"}
    sets = three_sets(seed=seed, own=own, geometry=geometry)
    res = pbrdf_cl.fit_joint(sets)
    best = _brute_force(sets, 12, seed)
    assert res.chi2 <= best * (1 + 1e-6) + 1e-6, (res.chi2, best)


def test_separate_fits_beside_joint(noisy):
    sets, res = noisy
    assert set(res.separate) == set(OWN)
    alone = pbrdf_cl.fit(sets["532"])
    assert res.separate["532"].chi2 == pytest.approx(alone.chi2, rel=1e-6)
    for s in OWN:
        for p, ratio in res.width_ratio[s].items():
            j, sep = res.ci95[s][p], res.separate[s].ci95[p]
            assert ratio == pytest.approx((j[1] - j[0]) / (sep[1] - sep[0]))
    # sharing sigma narrows it against at least one set's separate fit
    assert min(res.width_ratio[s]["sigma"] for s in OWN) < 1
    assert np.isfinite(res.separate_aic) and np.isfinite(res.separate_bic)


def test_joint_and_sample_fits_report_the_same_fields(noisy):
    """One protocol (pbrdf_cl.fitting.report.FitReport): every field in both results, with the
    same kind of value; the joint fit's per-parameter dicts per set."""
    from pbrdf_cl.fitting.report import RESULT_FIELDS
    _, res = noisy
    alone = res.separate["532"]
    for f in RESULT_FIELDS:
        assert f in res and f in alone, f
    for f in ("success", "fits_data", "sigma_known"):
        assert isinstance(res[f], (bool, np.bool_)) and isinstance(alone[f], (bool, np.bool_)), f
    for f in ("chi2", "sse", "aic", "bic", "p_value", "r2", "condition_number"):
        assert np.isscalar(res[f]) and np.isscalar(alone[f]), f
    assert res.dof == res.n_points - len(res.free) and alone.dof == alone.n_points - len(alone.free)
    assert res.cov.shape == (len(res.free),) * 2 and alone.cov.shape == (len(alone.free),) * 2
    assert set(res.x) == set(res.sets) and set(res.x["532"]) == set(alone.x)
    assert set(res.ci95["532"]) == set(alone.ci95)


def test_to_dataset_has_set_dimension(noisy):
    _, res = noisy
    ds = res.to_dataset()
    assert ds["ci95"].dims == ("set", "param", "bound")
    assert list(ds["set"].values) == list(OWN) and ds.sizes["param"] == 6
    assert ds["shared"].sel(param="sigma") and not ds["shared"].sel(param="n")
    assert float(ds["x"].sel(set="633", param="k")) == res.x["633"]["k"]
    assert float(ds["ci95"].sel(set="435", param="n", bound="hi")) == res.ci95["435"]["n"][1]
    assert np.isnan(float(ds["stderr"].sel(set="435", param="ks")))
    assert ds.attrs["shared"] == "sigma,c"


def test_per_set_fixed_and_bounds_are_honoured():
    sets = three_sets()
    res = pbrdf_cl.fit_joint(sets, fixed={"435": {"kd": 0.17}}, bounds={"532": {"n": (1.8, 2.3)}, "k": (0, 6)})
    assert res.x["435"]["kd"] == 0.17 and "kd" not in res.ci95["435"] and "kd[435]" not in res.free
    assert 1.8 <= res.x["532"]["n"] <= 2.3
    lo, hi = res.ci95["532"]["n"]
    assert 1.8 <= lo <= hi <= 2.3
    for s in OWN:
        assert 0 <= res.ci95[s]["k"][0] <= res.ci95[s]["k"][1] <= 6
    # a shared parameter held at one value in every set is held, and reported as shared
    held = pbrdf_cl.fit_joint(sets, fixed={"c": -0.3})
    assert held.shared_x["c"] == -0.3 and "c" not in held.free and all(held.x[s]["c"] == -0.3 for s in OWN)


def test_shared_n_k_for_several_samples():
    own = {"s1": dict(sigma=0.3, kd=0.1), "s2": dict(sigma=0.6, kd=0.2)}
    rng = np.random.default_rng(4)
    sets = {}
    for s, t in own.items():
        d = pbrdf_cl.dop(TI, TR, backend="numpy", n=1.6, k=2.139, c=-0.3, **t) + rng.normal(0, 0.003, TI.size)
        sets[s] = dict(theta_i=TI, theta_r=TR, dop=np.clip(d, 0, 1), dop_std=np.full(TI.size, 0.003))
    res = pbrdf_cl.fit_joint(sets, shared=("n", "k"))
    assert res.shared == ["n", "k"] and res.x["s1"]["n"] == res.x["s2"]["n"]
    assert res.ci95["s1"]["n"][0] <= 1.6 <= res.ci95["s1"]["n"][1]
    assert res.x["s1"]["sigma"] != res.x["s2"]["sigma"]


@pytest.mark.parametrize("kwargs, message", [
    (dict(sets={"a": "x"}), "sets: 1 set (a); a joint fit needs at least two"),
    (dict(shared=("sigma", "q")), "shared: 'q' is not a parameter; the six-param model fits n, k, sigma, kd, c"),
    (dict(shared="sigm,c"), "shared: 'sigm' is not a parameter (did you mean 'sigma'?)"),
    (dict(shared="sigma,c,sigma"), "shared: sigma named twice"),
    (dict(fixed={"435": {"sigma": 0.5}}), "fixed: sigma is shared, so it must be held in every set at one value"),
    (dict(bounds={"435": {"c": (-0.5, 0)}}), "bounds: c is shared, so its bounds must be the same in every set"),
    (dict(fixed={"zz": {"n": 1}}), "fixed: 'zz' is neither a parameter with a value nor a set"),
    (dict(fixed={"633": {"k": -1}}), "set '633': fixed: k = -1.0 is outside the model's domain"),
    (dict(model="specular"), "shared: sigma is not fitted by the specular model (its fitted parameters: n, k)"),
    (dict(sets=42), "sets must be a dict set name -> data"),
])
def test_refusals_are_one_line(kwargs, message):
    args = dict(sets=three_sets(noise=0.0), shared=("sigma", "c"))
    args.update(kwargs)
    with pytest.raises(ValueError) as info:
        pbrdf_cl.fit_joint(args.pop("sets"), **args)
    text = str(info.value)
    assert "\n" not in text
    assert message in text or text.startswith(message), text


def test_share_nothing_gives_the_separate_fits(noisy):
    """``shared=()`` and ``shared=""`` (issue #34): the joint fit is each set fitted on its own, its
    chi2 the sum of each set's ``pbrdf_cl.fit`` (the same optimum), reported as a joint fit, with
    a note saying nothing is shared."""
    sets, _ = noisy
    alone = {s: pbrdf_cl.fit(m) for s, m in sets.items()}
    for shared in ((), "", " , "):
        res = pbrdf_cl.fit_joint(sets, shared=shared)
        assert res.shared == [] and res.success
        assert res.chi2 == pytest.approx(sum(r.chi2 for r in alone.values()), rel=1e-6)
        for s, r in alone.items():
            assert res.x[s]["n"] == pytest.approx(r.x["n"], rel=1e-3), s
        assert any(n.startswith("nothing is shared: the joint fit is each set fitted on its own") for n in res.notes)
        assert "shared: none" in res.summary()


def test_default_shared_follows_the_model_and_the_fixed(noisy):
    """The default (sigma, c) never names a parameter the model does not fit or the user fixed:
    the specular model shares nothing by default (a note says why); sigma fixed in one set leaves
    c shared; a name list may use spaces after its commas, or spaces alone."""
    sets, _ = noisy
    spec = pbrdf_cl.fit_joint(sets, model="specular")
    said = "by default the sets share sigma, c where the specular model fits them and no set holds them apart"
    assert spec.shared == [] and any(said in n for n in spec.notes)
    one = pbrdf_cl.fit_joint(sets, fixed={"435": {"sigma": 0.5}})
    assert one.shared == ["c"] and one.x["435"]["sigma"] == 0.5 and one.x["633"]["sigma"] != 0.5
    spaced = [joint.check_joint_args(sets, text, "six-param", None, None, "paper").shared
              for text in ("sigma, c", "sigma c", " c ,sigma ")]
    assert spaced == [("sigma", "c")] * 3


def test_refuses_dop_std_for_some_sets_only_and_a_set_too_small():
    sets = three_sets()
    sets["633"] = dict(theta_i=TI, theta_r=TR, dop=sets["633"].dop)
    with pytest.raises(ValueError, match="dop_std: given for sets 435, 532 but not for 633; give it for every set"):
        pbrdf_cl.fit_joint(sets)
    small = dict(three_sets(), tiny=dict(theta_i=[40, 40], theta_r=[20, 30], dop=[0.1, 0.2], dop_std=[0.01, 0.01]))
    with pytest.raises(ValueError, match="^set 'tiny': data: 2 measurements for 5 free parameters"):
        pbrdf_cl.fit_joint(small)


def test_split_sets_by_column(tmp_path):
    table = dict(theta_i=np.tile(TI, 2), theta_r=np.tile(TR, 2), dop=np.full(60, 0.1),
                 Wavelength=np.repeat([435.0, 633.0], 30))
    sets = split_sets(table, "wavelength")
    assert list(sets) == ["435", "633"] and len(sets["633"]) == 30
    path = tmp_path / "all.csv"
    path.write_text("theta_i;theta_r;dop;sample\n40;20;0,1;a\n# a comment\n40;45;0,2;b\n40;50;0,3;a\n")
    by_file = split_sets(path, "sample")
    assert list(by_file) == ["a", "b"] and list(by_file["a"].dop) == [0.1, 0.3]
    assert list(by_file["a"].lines) == [2, 5]
    with pytest.raises(ValueError, match="no column 'wl' to split the sets by"):
        split_sets(path, "wl")


def test_cli_joint_round_trip(tmp_path, noisy):
    sets, res = noisy
    paths = []
    rows = ["theta_i,theta_r,phi,dop,dop_std,wavelength"]
    for s, m in sets.items():
        paths.append(str(tmp_path / f"{s}.csv"))
        write_csv(paths[-1], m)
        rows += [f"{a},{b},{p},{float(d)!r},{float(e)!r},{s}"
                 for a, b, p, d, e in zip(m.theta_i, m.theta_r, m.phi, m.dop, m.dop_std)]
    (tmp_path / "all.csv").write_text("\n".join(rows) + "\n")
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    out, png = tmp_path / "joint.json", tmp_path / "joint.png"
    proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", *paths, "--shared", "sigma,c", "--json", str(out),
                           "--plot", str(png)], capture_output=True, text=True, timeout=600, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "joint fit: six-param" in proc.stdout and "shared: sigma, c" in proc.stdout
    got = json.loads(out.read_text())["joint"]
    assert got["sets"] == list(OWN) and got["shared"] == ["sigma", "c"]
    assert got["shared_x"]["sigma"] == pytest.approx(res.shared_x["sigma"], rel=1e-4)
    assert got["x"]["633"]["n"] == pytest.approx(res.x["633"]["n"], rel=1e-3)
    assert set(got["separate"]) == set(OWN) and "ci95" in got["separate"]["435"]
    assert png.stat().st_size > 10000 and png.read_bytes()[:4] == b"\x89PNG"
    quiet = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", str(tmp_path / "all.csv"), "--set-column",
                            "wavelength", "--quiet"], capture_output=True, text=True, timeout=600, env=env)
    assert quiet.returncode == 0, quiet.stderr
    assert "n[633] = " in quiet.stdout and "sigma = " in quiet.stdout
    bad = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", *paths[:2], "--shared", "sigma,q"],
                         capture_output=True, text=True, timeout=120, env=env)
    assert bad.returncode == 1 and bad.stderr.strip().count("\n") == 0 and "shared: 'q'" in bad.stderr
    none = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", *paths[:2], "--shared", "", "--quiet"],
                          capture_output=True, text=True, timeout=600, env=env)
    assert none.returncode == 0, none.stderr
    assert "shared: none" in none.stdout and "n[435] = " in none.stdout and "sigma[532] = " in none.stdout
    one = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", paths[0], "--shared", "n,k"],
                         capture_output=True, text=True, timeout=120, env=env)
    assert one.returncode == 1 and one.stderr.count("\n") == 1
    assert "--shared is for joint fits: give several CSVs (one set each) or one CSV with --set-column" in one.stderr


def test_cli_per_set_fix_and_bounds(tmp_path, noisy):
    """``--fix SET:NAME=VALUE`` and ``--bounds SET:NAME=LO:HI`` reach that set only, as
    ``fit_joint(fixed={set: {...}}, bounds={set: {...}})`` does; a set name in a single fit is
    refused in one line."""
    sets, _ = noisy
    paths = []
    for s, m in sets.items():
        paths.append(str(tmp_path / f"{s}.csv"))
        write_csv(paths[-1], m)
    env = dict(os.environ, PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent), PYTHONWARNINGS="ignore")
    out = tmp_path / "joint.json"
    proc = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", *paths, "--fix", "435:kd=0.2", "--bounds",
                           "633:n=2:2.4", "--json", str(out), "--quiet"], capture_output=True, text=True, timeout=600,
                          env=env)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(out.read_text())["joint"]
    want = pbrdf_cl.fit_joint(sets, fixed={"435": {"kd": 0.2}}, bounds={"633": {"n": (2.0, 2.4)}})
    assert got["x"]["435"]["kd"] == 0.2 and got["x"]["532"]["kd"] != 0.2
    assert 2.0 <= got["x"]["633"]["n"] <= 2.4
    for s in OWN:
        for p, v in want.x[s].items():
            assert got["x"][s][p] == pytest.approx(v, rel=1e-6, abs=1e-9), (s, p)
    single = subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", paths[0], "--fix", "435:kd=0.2"],
                            capture_output=True, text=True, timeout=120, env=env)
    assert single.returncode == 1 and single.stderr.strip().count("\n") == 0
    assert "--fix 435:kd=0.2: a set name" in single.stderr


def bench_problem(index):
    """(truths, sets) of problem ``index`` of ``scripts/bench_joint.py`` (seed 2028)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("bench_joint", Path(__file__).parent.parent / "scripts" /
                                                  "bench_joint.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    rng = np.random.default_rng(2028)
    for _ in range(index + 1):  # the bench's stream: each problem, then its multi-start's 24 random starts
        truths, sets = bench.problem(rng)
        [rng.random(11) for _ in range(24)]
    return truths, sets


def test_global_optimum_where_a_set_switches_valleys():
    """Problem 11 of ``scripts/bench_joint.py`` (seed 2028): the sets' DOP have valleys of nearly
    equal depth, and the descent from each set's best grid node stopped in the wrong ones (chi2
    88.59); fitting each set's own parameters at the starting shared values (the profile stage)
    reaches the optimum that least squares from the truth finds (88.457)."""
    from scipy.optimize import least_squares
    truths, sets = bench_problem(11)
    setup = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    lo, hi = setup.lo, setup.hi
    truth = np.array([truths["a"][p] if "[" not in p else truths[p[p.index("[") + 1:-1]][p[:p.index("[")]]
                      for p in setup.labels])
    ref = least_squares(lambda x: resid.rows(x[None])[0], np.clip(truth, lo, hi), bounds=(lo, hi), x_scale=hi - lo,
                        ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=2000)
    res = pbrdf_cl.fit_joint(sets)
    assert res.chi2 <= 2 * ref.cost * (1 + 1e-6) + 1e-6, (res.chi2, 2 * ref.cost)


def test_global_optimum_at_the_other_end_of_a_flat_valley():
    """Problem 13 of ``scripts/bench_joint.py`` (seed 2028): every parameter is barely determined,
    and the joint optimum (chi2 81.25106 at sigma 0.538, c -0.539, set a at n = 5, k = 8.4) lies
    where set a's other own valley takes the shared values; at the shared values the descent
    reached (81.25202 at c -0.727) that valley is 1.8 units of chi2 higher, so the exchange did
    not move set a.  The valley swap (set a in its other valley, then the joint descent) reaches
    it: the brute-force multi-start's optimum within 1e-6, and the result says set a moved."""
    from scipy.optimize import least_squares
    _, sets = bench_problem(13)
    setup = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    lo, hi = setup.lo, setup.hi
    start = dict(zip(setup.labels, (0.54, -0.54, 5.0, 8.4, 2.2, 1.0, 2.6, 5.0, 1.0, 1.2, 4.4)))
    ref = least_squares(lambda x: resid.rows(x[None])[0], np.array([start[p] for p in setup.labels]),
                        bounds=(lo, hi), x_scale=hi - lo, ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=2000)
    assert 2 * ref.cost < 81.2511
    res = pbrdf_cl.fit_joint(sets)
    assert res.chi2 <= 2 * ref.cost * (1 + 1e-6) + 1e-6, (res.chi2, 2 * ref.cost)
    assert res.x["a"]["n"] > 4.5 and ("a",) in res.exchanged


def test_stacked_sets_give_each_sets_residuals_bit_for_bit():
    """The sets' residuals in one model call (SetStack: joint rows broadcast per set, own rows
    with each row's set gathered) are those of each set evaluated alone, bit for bit: sets of
    unequal sizes (the padding gives zeros), a parameter held at a different value per set."""
    from pbrdf_cl.fitting.sets.stack import SetStack
    sets = three_sets()
    sets["532"] = from_arrays(sets["532"].theta_i[:17], sets["532"].theta_r[:17], sets["532"].dop[:17], 150.0,
                              sets["532"].dop_std[:17])
    setup = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, {"ks": 1.0, "532": {"ks": 0.7}}, "paper")
    resid = joint.JointResiduals(setup)
    assert isinstance(resid.stack, SetStack) and resid.stack.ragged
    rng = np.random.default_rng(5)
    X = setup.lo + rng.random((7, setup.lo.size)) * (setup.hi - setup.lo)
    one_by_one = np.concatenate([p.rows(X[:, ix]) for p, ix in zip(resid.parts, resid.index)], axis=1)
    np.testing.assert_array_equal(resid.rows(X), one_by_one)
    which = np.array([2, 0, 1, 1, 2, 0, 0])
    Y = np.array([X[i, resid.index[w]] for i, w in enumerate(which)])
    own = resid.stack.own_rows(Y, which)
    for i, w in enumerate(which):
        alone = resid.parts[w].rows(Y[i:i + 1])[0]
        np.testing.assert_array_equal(own[i, :alone.size], alone)
        assert np.all(own[i, alone.size:] == 0.0)
    held_in_one = joint.check_joint_args(sets, ("sigma", "c"), "six-param", None, {"435": {"kd": 0.1}}, "paper")
    assert joint.JointResiduals(held_in_one).stack is None  # the sets fit different parameters: one by one


def test_stacked_own_rows_of_big_sets_come_in_blocks(monkeypatch):
    """The stack's own rows of big data sets are computed a few rows at a time, as a set's
    residuals alone (stages.in_row_blocks, ROWS_VALUES values at a time): the same values,
    and no call of the model sees more rows than a block."""
    from pbrdf_cl.fitting.sample import stages
    setup = joint.check_joint_args(three_sets(), ("sigma", "c"), "six-param", None, None, "paper")
    stack = joint.JointResiduals(setup).stack
    rng = np.random.default_rng(2)
    lo, hi = setup.setups["435"].lo, setup.setups["435"].hi
    X = lo + rng.random((9, lo.size)) * (hi - lo)
    which = rng.integers(0, 3, 9)
    whole = stack.own_rows(X, which)
    seen = []
    dop_rows = stages.Model.dop_rows
    monkeypatch.setattr(stages.Model, "dop_rows", lambda self, p, runs=(): seen.append(len(p["n"])) or
                        dop_rows(self, p, runs))
    monkeypatch.setattr(stages, "ROWS_VALUES", 2 * stack.width)
    np.testing.assert_array_equal(stack.tagged_rows(np.column_stack([X, which])), whole)
    assert seen == [2, 2, 2, 2, 1]


def test_the_result_says_which_sets_the_basin_exchange_moved():
    """Problem 4 of the bench: set c's own parameters are moved by the exchange (and the result
    says so, in ``exchanged`` and a note); problem 0: nothing moves, nothing is said."""
    res = pbrdf_cl.fit_joint(bench_problem(4)[1])
    assert res.exchanged and all(set(rnd) <= set(res.sets) for rnd in res.exchanged)
    assert "c" in res.exchanged[0]
    assert any(n.startswith("the basin exchange lowered the chi2 of set c") for n in res.notes), res.notes
    assert res.to_dataset().attrs["exchanged"] == "; ".join(",".join(m) for m in res.exchanged)
    quiet = pbrdf_cl.fit_joint(bench_problem(0)[1])
    assert quiet.exchanged == () and not any("basin exchange" in n for n in quiet.notes)


def test_a_joint_fit_that_does_not_describe_its_data_has_valid_matrices_and_marks():
    """Issue #34 items 3 and 4 for fit_joint: in-plane sets labelled phi = 0 gave correlations of
    9.7 and inf, not symmetric; now the covariance is valid or NaN with a note, the standard
    errors are NaN where it is, and every best value outside its interval is marked (*) in the
    summary, listed in ``outside_ci95`` and flagged in ``to_dataset()``.  Issue #37 round 8: the
    best n, k and kd of each set, on their bounds with no standard error, were such values (the
    uniform prior's central 95%, n in [1.1, 4.9], k in [0.25, 9.75], left them out); now their
    intervals are the grid profile's alone, from the bound to the nodes around its 95%, and hold
    them."""
    sets = {s: from_arrays(m.theta_i, m.theta_r, m.dop, 0.0, m.dop_std) for s, m in three_sets().items()
            if s != "633"}
    r = pbrdf_cl.fit_joint(sets, shared=("sigma", "c"))
    assert not r.fits_data
    undefined = assert_valid_covariance(r.cov, r.corr)
    assert list(r.corr.coords["param"].values) == r.free
    assert sum("projected onto a valid one" in n or "cannot be computed" in n for n in r.notes) == 1
    for label, u in zip(r.free, undefined):
        p, s = (label.split("[")[0], label.split("[")[1].rstrip("]")) if "[" in label else (label, r.sets[0])
        assert np.isnan(r.stderr[s][p]) == u
    text = r.summary()
    ds = r.to_dataset()
    assert ds["outside_ci95"].attrs["long_name"] == OUTSIDE_FOOTNOTE
    for s in r.sets:
        outside = [p for p, (lo, hi) in r.ci95[s].items() if not lo <= r.x[s][p] <= hi]
        assert r.outside_ci95[s] == outside
        for p in r.ci95[s]:
            assert bool(ds["outside_ci95"].sel(set=s, param=p)) == (p in outside)
    for s in r.sets:
        assert r.x[s]["n"] == 1.0 and r.x[s]["k"] < 1e-6 and (r.ci95[s]["n"][0], r.ci95[s]["k"][0]) == (1.0, 0.0)
        assert r.ci95[s]["n"][1] < 1.1 and r.ci95[s]["k"][1] < 0.25
    assert (OUTSIDE_MARK in text) == any(r.outside_ci95.values())
    assert sum(OUTSIDE_MARK in n for n in r.notes) == int(any(r.outside_ci95.values()))


def test_the_stacked_sets_compute_each_factor_once_per_run_bit_for_bit(monkeypatch):
    """The joint rows of several sets side by side, as finite-difference Jacobians ask for them (a
    point, then the point moved along each parameter in turn), compute each factor of the model
    once per run of consecutive rows with the same values of its parameters (stages.same_runs):
    of each point's 12 rows (sigma, c, then n, k, kd of each set moved) the Fresnel terms for 10,
    the specular scale for 3, the diffuse term for 8; the residuals are those of every row
    computed as it comes, bit for bit."""
    from pbrdf_cl.fitting.common import fd_jacobian, fd_steps
    from pbrdf_cl.fitting.sample import stages
    from pbrdf_cl.fitting.sets import joint
    setup = joint.check_joint_args(three_sets(), ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    assert resid.stack is not None
    rng = np.random.default_rng(3)
    X = setup.lo + rng.uniform(0.2, 0.8, (3, setup.lo.size)) * (setup.hi - setup.lo)
    sizes = {}
    for name, compute in (("fresnel", stages.Model._fresnel), ("scale", stages.Model._log_scale),
                          ("diffuse", stages.Model._diffuse)):
        def counted(self, p, name=name, compute=compute):
            sizes.setdefault(name, []).append(int(np.shape(p["n" if name == "fresnel" else "kd" if name == "diffuse"
                                                            else "sigma"])[0]))
            return compute(self, p)
        monkeypatch.setattr(stages.Model, f"_{name if name != 'scale' else 'log_scale'}", counted)
    runs = fd_jacobian(resid.rows, X, setup.lo, setup.hi)
    assert {k: v[-1] for k, v in sizes.items()} == {"fresnel": 3 * 10, "scale": 3 * 3, "diffuse": 3 * 8}
    monkeypatch.setattr(stages, "RUN_ROWS", 10 ** 9)
    alone = fd_jacobian(resid.rows, X, setup.lo, setup.hi)
    for a, b in zip(runs, alone):
        np.testing.assert_array_equal(a, b)
    assert np.all(fd_steps(X, setup.hi) != 0)


def test_the_stacked_own_rows_compute_each_factor_once_per_run_bit_for_bit(monkeypatch):
    """The own rows of several sets (each row one set's vector, its geometry gathered), as the
    batched descents ask for them (a point, then the point moved along each of n, k, sigma, kd, c,
    lanes of the three sets in turn), compute each factor once per run of consecutive rows of one
    set with the same values of its parameters: of each lane's 6 rows the Fresnel terms for 4,
    the specular scale for 3, the diffuse term for 3; the residuals are those of every row
    computed as it comes, and each set's alone, bit for bit."""
    from pbrdf_cl.fitting.common import fd_jacobian
    from pbrdf_cl.fitting.sample import stages
    from pbrdf_cl.fitting.sets import stack as stack_mod
    setup = joint.check_joint_args(three_sets(), ("sigma", "c"), "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    st = resid.stack
    lo, hi = setup.setups["435"].lo, setup.setups["435"].hi
    rng = np.random.default_rng(4)
    X = lo + rng.uniform(0.2, 0.8, (6, lo.size)) * (hi - lo)
    which = np.array([0, 1, 2, 2, 0, 1], dtype=float)
    assert 6 * (lo.size + 1) >= stack_mod.RUN_ROWS

    def rows(Y):  # what lm_batch's extra column gives: the set last
        return st.tagged_rows(np.column_stack([Y, np.repeat(which, lo.size + 1)]))
    sizes = {}
    for name in ("_fresnel", "_log_scale", "_diffuse"):
        compute = getattr(stages.Model, name)

        def counted(self, p, name=name, compute=compute):
            sizes.setdefault(name, []).append(len(self.g.cb))
            return compute(self, p)
        monkeypatch.setattr(stages.Model, name, counted)
    runs = fd_jacobian(rows, X, lo, hi)
    assert {k: v[-1] for k, v in sizes.items()} == {"_fresnel": 6 * 4, "_log_scale": 6 * 3, "_diffuse": 6 * 3}
    monkeypatch.setattr(stack_mod, "RUN_ROWS", 10 ** 9)
    every = fd_jacobian(rows, X, lo, hi)
    for a, b in zip(runs, every):
        np.testing.assert_array_equal(a, b)
    for i, w in enumerate(which.astype(int)):
        alone = fd_jacobian(resid.parts[w].rows, X[i:i + 1], lo, hi)
        np.testing.assert_array_equal(runs[0][i], alone[0][0])
        np.testing.assert_array_equal(runs[1][i], alone[1][0])


def test_sets_at_one_geometry_go_through_the_grid_in_one_pass(monkeypatch):
    """The grid stage of sets measured at one geometry (the same angles, grid and held values) is
    one pass over the grid for all of them (stages.grid_stages), each set's grid that of its own
    grid stage bit for bit; a set measured elsewhere has its own pass."""
    from pbrdf_cl.fitting.sample import inversion, stages
    sets = three_sets()
    m = sets["633"]
    sets["633"] = from_arrays(m.theta_i, m.theta_r, m.dop, 150.0, m.dop_std)  # out of the plane
    setup = joint.check_joint_args(sets, None, "six-param", None, None, "paper")
    resid = joint.JointResiduals(setup)
    shape = dict(inversion.grid_shape_of("six-param"), n=7, k=6, sigma=5, kd=4, c=3)
    passes = []
    grid_stages, grid_stage = joint.grid_stages, joint.grid_stage
    monkeypatch.setattr(joint, "grid_stages", lambda meases, *a, **k: passes.append(len(meases)) or
                        grid_stages(meases, *a, **k))
    monkeypatch.setattr(joint, "grid_stage", lambda *a, **k: passes.append(1) or grid_stage(*a, **k))
    got = joint.set_grids(setup, resid, shape, "paper", None, "auto", False)
    assert list(got) == list(setup.names) and sorted(passes) == [1, 2]
    for s in setup.names:
        alone = stages.grid_stage(setup.meas[s], setup.setups[s].free, setup.setups[s].grid_axes(shape),
                                  setup.setups[s].base, "paper")
        np.testing.assert_array_equal(got[s].value.sse, alone.value.sse)
        assert got[s].nfev == alone.nfev
        for p in alone.value.profiles:
            np.testing.assert_array_equal(got[s].value.profiles[p], alone.value.profiles[p])


@pytest.mark.parametrize("shape", [(5, 7, 4, 6, 3), (1, 9, 2, 5, 1), (6,), (3, 4)])
def test_the_profiles_of_each_own_axis_are_numpys_minima(shape):
    """``each_own_axis`` reduces every axis in place (``axis_min``: halving, odd lengths and a
    leading axis included) and gives numpy's minima bit for bit, NaN propagating alike, whatever
    axes are the sets' own and in whatever order the shared ones lie between them."""
    from pbrdf_cl.fitting.sets.joint import axis_min, each_own_axis

    rng = np.random.default_rng(len(shape))
    a = rng.random(shape, dtype=np.float32)
    a.flat[a.size // 3] = np.nan
    for axis in range(a.ndim):
        np.testing.assert_array_equal(axis_min(a, axis), a.min(axis=axis, keepdims=True))
    for own in ([0, 1, 3], [3, 1], [4], [1, 2, 0, 4], []):
        own = [j for j in own if j < a.ndim]
        got = each_own_axis(a, own)
        assert len(got) == len(own)
        for j, m in zip(own, got):
            others = tuple(x for x in own if x != j)
            np.testing.assert_array_equal(m, a.min(axis=others, keepdims=True) if others else a)
