"""pbrdf_cl.sobol / morris: SALib's indices on the device's model runs, checked against SALib itself."""
import warnings

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.analysis import sensitivity
from pbrdf_cl.model import reference

SALib = pytest.importorskip("SALib")
from SALib.analyze import morris as salib_morris  # noqa: E402
from SALib.analyze import sobol as salib_sobol  # noqa: E402
from SALib.sample import sobol as salib_sample  # noqa: E402

RANGES = {"n": (1.2, 2.5), "k": (0.01, 3.0, "log"), "sigma": (0.1, 0.6), "kd": (0.0, 0.5), "c": (-1.0, 0.0)}
GEOMETRY = {"theta_i": [30.0, 55.0], "theta_r": [10.0, 40.0, 65.0]}


def reference_outputs(ds, ti, tr, phi=180.0, quantity="dop"):
    """The reference model's outputs for the Dataset's samples at one geometry (independent of
    the device path: reference.evaluate on the sample columns)."""
    p = {n: ds.samples.sel(parameter=n).values if n in ds.parameter.values else ds.attrs[f"fixed_{n}"]
         for n in ("n", "k", "sigma", "ks", "kd", "c")}
    return reference.evaluate(quantity, ti, tr, phi, p["n"], p["k"], p["sigma"], p["ks"], p["kd"], p["c"])


def salib_problem(ds, log_space=False):
    names = list(ds.parameter.values)
    bounds = []
    for n in names:
        lo, hi = ds.attrs[f"range_{n}"]
        log = ds.attrs[f"scale_{n}"] == "log"
        bounds.append([np.log(lo), np.log(hi)] if log and log_space else [lo, hi])
    return {"num_vars": len(names), "names": names, "bounds": bounds}


@pytest.mark.parametrize("second_order", [False, True])
def test_sobol_equals_salib_on_the_reference_outputs(engine, second_order):
    """float64, same seed: S1, ST and their bootstrap intervals equal SALib.analyze.sobol run on
    the reference model's outputs for the same samples, at every sampled geometry."""
    seed = 11
    ds = pbrdf_cl.sobol(RANGES, GEOMETRY, N=128, seed=seed, dtype="float64", second_order=second_order,
                        engine=engine)
    keys = ("S1", "ST", "S1_conf", "ST_conf") + (("S2", "S2_conf") if second_order else ())
    for ti in ds.theta_i.values:
        for tr in ds.theta_r.values:
            y = reference_outputs(ds, ti, tr)
            want = salib_sobol.analyze(salib_problem(ds), y, calc_second_order=second_order, seed=seed)
            got = ds.sel(theta_i=ti, theta_r=tr)
            for key in keys:
                np.testing.assert_allclose(got[key].values, want[key], rtol=0, atol=1e-9, err_msg=key)
    assert ds.S1.dims == ("parameter", "theta_i", "theta_r")
    if second_order:
        assert ds.S2.dims == ("parameter", "parameter_2", "theta_i", "theta_r")


def test_samples_are_salibs_sampler(engine):
    """The samples are SALib's Saltelli/Sobol' samples for the seed; a log-uniform range is the
    exponential of SALib's sample over the log bounds."""
    ds = pbrdf_cl.sobol(RANGES, {"theta_i": 40, "theta_r": 30}, N=64, seed=5, engine=engine)
    ranges = sensitivity.check_ranges(RANGES)
    X = salib_sample.sample(sensitivity._problem(ranges), 64, calc_second_order=False, seed=5)
    want = X.copy()
    want[:, 1] = np.exp(X[:, 1])
    np.testing.assert_array_equal(ds.samples.values, want)
    assert ds.attrs["runs_per_geometry"] == 64 * (len(RANGES) + 2)
    assert ds.S1.dims == ("parameter",)  # single-valued geometry: scalar coordinates
    assert float(ds.theta_i) == 40.0 and float(ds.phi) == 180.0


def test_morris_equals_salib(engine):
    seed = 4
    ds = pbrdf_cl.morris(RANGES, GEOMETRY, N=40, seed=seed, dtype="float64", engine=engine)
    X = ds.samples.values.copy()
    X[:, 1] = np.log(X[:, 1])  # SALib's space: the log-uniform k sampled in log k
    for ti in ds.theta_i.values:
        for tr in ds.theta_r.values:
            y = reference_outputs(ds, ti, tr)
            want = salib_morris.analyze(salib_problem(ds, log_space=True), X, y, seed=seed)
            got = ds.sel(theta_i=ti, theta_r=tr)
            for key, salib in (("mu", "mu"), ("mu_star", "mu_star"), ("ee_std", "sigma"),
                               ("mu_star_conf", "mu_star_conf")):
                np.testing.assert_allclose(got[key].values, np.asarray(want[salib]), rtol=0, atol=1e-9, err_msg=key)
    assert "sigma" not in ds.data_vars  # SALib's sigma is ee_std: sigma is the roughness


def test_blocks_of_geometries_give_the_same_maps(engine):
    """A memory budget that splits the geometries into many blocks changes nothing but the
    rounding of the matrix products (the BLAS blocks differ with the shapes)."""
    kw = dict(N=64, seed=2, dtype="float64", engine=engine)
    geometry = {"theta_i": "20:60@5", "theta_r": "0:80@7"}
    whole = pbrdf_cl.sobol(RANGES, geometry, **kw)
    runs = whole.attrs["runs_per_geometry"]
    terms = sensitivity._SobolTerms(len(RANGES), 64, False, np.ones((100, 64)), 1.96)
    per_geometry = runs * 8 + terms.block_bytes(runs)
    blocks = pbrdf_cl.sobol(RANGES, geometry, memory_budget=3 * per_geometry, **kw)
    assert whole.attrs["blocks"] == 1 and blocks.attrs["blocks"] == 12  # 35 geometries, 3 per block
    for key in ("S1", "ST", "S1_conf", "ST_conf"):
        np.testing.assert_allclose(whole[key].values, blocks[key].values, rtol=1e-13, atol=1e-15)


def test_float32_runs_agree_with_float64(engine):
    kw = dict(N=256, seed=3, engine=engine)
    a = pbrdf_cl.sobol(RANGES, GEOMETRY, dtype="float32", **kw)
    b = pbrdf_cl.sobol(RANGES, GEOMETRY, dtype="float64", **kw)
    for key in ("S1", "ST"):
        np.testing.assert_allclose(a[key].values, b[key].values, atol=1e-4)
    np.testing.assert_allclose(a.S1_conf.values, b.S1_conf.values, rtol=1e-2, atol=1e-5)


def test_numpy_backend_equals_device(engine):
    kw = dict(N=64, seed=8, dtype="float64")
    a = pbrdf_cl.sobol(RANGES, GEOMETRY, engine=engine, **kw)
    b = pbrdf_cl.sobol(RANGES, GEOMETRY, backend="numpy", **kw)
    for key in ("S1", "ST", "S1_conf", "ST_conf"):
        np.testing.assert_allclose(a[key].values, b[key].values, atol=1e-9)


def test_sigma_has_no_effect_without_a_diffuse_term(engine):
    """With kd = 0 the DOP is (Rs - Rp) / (Rs + Rp): the roughness cancels, so its indices are
    exactly zero, while n and k share the whole variance (S1 + interactions = 1)."""
    ds = pbrdf_cl.sobol({"n": (1.2, 2.5), "k": (0.0, 3.0), "sigma": (0.1, 0.6)}, GEOMETRY, fixed={"kd": 0.0},
                        N=256, seed=1, dtype="float64", engine=engine)
    np.testing.assert_array_equal(ds.S1.sel(parameter="sigma").values, 0.0)
    np.testing.assert_array_equal(ds.ST.sel(parameter="sigma").values, 0.0)
    assert float(ds.ST.sel(parameter=["n", "k"]).sum("parameter").min()) > 0.9


def test_constant_output_gives_zero_indices_like_salib(engine):
    """Only c varies and kd = 0: the output does not depend on it; SALib returns zeros (with a
    warning), so do we (without NaN)."""
    ds = pbrdf_cl.sobol({"c": (-1.0, 0.0)}, {"theta_i": 40, "theta_r": [20.0, 50.0]},
                        fixed={"n": 1.6, "k": 2.1, "sigma": 0.4, "kd": 0.0}, N=32, seed=1, dtype="float64",
                        engine=engine)
    y = reference_outputs(ds, 40.0, 20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = salib_sobol.analyze(salib_problem(ds), y, calc_second_order=False, seed=1)
    for key in ("S1", "ST", "S1_conf", "ST_conf"):
        assert np.all(ds[key].values == 0.0), key
        assert float(np.asarray(want[key])[0]) == 0.0
    assert ds.constant.dims == ("theta_r",) and ds.constant.values.tolist() == [1, 1]  # marked as meaning nothing


def test_constant_geometries_are_flagged_and_only_those(engine):
    """At theta_i = theta_r = 0 the DOP is 0 for every material: flagged `constant` (Sobol' and
    Morris), while every other geometry varies; the summary counts the flagged ones."""
    geometry = {"theta_i": [0.0, 40.0], "theta_r": [0.0, 30.0]}
    for method in ("sobol", "morris"):
        ds = pbrdf_cl.sobol(RANGES, geometry, N=32, seed=1, method=method, engine=engine)
        assert ds.constant.dims == ("theta_i", "theta_r")
        assert ds.constant.values.tolist() == [[1, 0], [0, 0]], method
        assert "1 geometries where dop does not vary" in sensitivity.summary(ds)


def test_ks_and_kd_both_ranged_for_the_dop_and_options_of_the_other_method(engine):
    """ks and kd both ranged: the DOP sees only kd/ks; one warning line naming them and the fix, kept
    in the result's notes and printed by the summary; not for F00, which separates them.  Morris
    with second_order, Sobol' with num_levels: refused in one line (they were ignored)."""
    ranges = {"n": (1.2, 2.5), "sigma": (0.1, 0.6), "ks": (0.5, 2.0), "kd": (0.0, 0.5)}
    kw = dict(fixed={"k": 2.0}, N=16, seed=1, engine=engine)
    for method in ("sobol", "morris"):
        with pytest.warns(sensitivity.SensitivityWarning, match=r"ks and kd both have a range.*kd/ks.*fixed=") as rec:
            ds = pbrdf_cl.sobol(ranges, {"theta_i": 40, "theta_r": [20.0, 50.0]}, method=method, **kw)
        assert len(rec) == 1 and "\n" not in str(rec[0].message)
        assert "ks and kd both have a range" in ds.attrs["notes"]
        assert "note: ks and kd both have a range" in sensitivity.summary(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error", sensitivity.SensitivityWarning)
        ds = pbrdf_cl.sobol(ranges, {"theta_i": 40, "theta_r": [20.0, 50.0]}, quantity="f00", **kw)
        assert ds.attrs["notes"] == ""
        pbrdf_cl.sobol({k: v for k, v in ranges.items() if k != "ks"}, {"theta_i": 40, "theta_r": 20.0}, **kw)
    with pytest.raises(ValueError, match="^second_order: Morris screening has no second-order indices"):
        pbrdf_cl.morris(ranges, {"theta_i": 40, "theta_r": 20.0}, second_order=True, **kw)
    with pytest.raises(ValueError, match="^num_levels = 6: only Morris screening has levels"):
        pbrdf_cl.sobol(ranges, {"theta_i": 40, "theta_r": 20.0}, num_levels=6, **kw)


def test_brdf_quantity_and_attrs(engine):
    ds = pbrdf_cl.sobol({"sigma": (0.1, 0.6), "ks": (0.5, 2.0)}, {"theta_i": 40, "theta_r": [10.0, 40.0]},
                        fixed={"n": 1.6, "k": 2.0}, quantity="f00", N=64, seed=2, engine=engine)
    assert ds.attrs["quantity"] == "brdf" and ds.attrs["model_runs"] == 64 * 4 * 2
    assert ds.attrs["fixed_kd"] == 0.0 and ds.attrs["range_ks"] == [0.5, 2.0]
    # the specular peak (theta_r = 40) is controlled by the roughness more than off it
    s = ds.ST.sel(parameter="sigma")
    assert float(s.sel(theta_r=40.0)) > 0.5


@pytest.mark.parametrize("kwargs, match", [
    (dict(ranges={"q": (0, 1)}), "unknown parameter 'q'"),
    (dict(ranges={"n": (2.0, 1.0)}), r"ranges\['n'\]: low must be below high"),
    (dict(ranges={"n": (0.0, 2.0)}), "n must be > 0"),
    (dict(ranges={"kd": (0.0, 1.0, "log")}), "log-uniform range needs low > 0"),
    (dict(ranges={"k": (0.1, 1.0, "ln")}), "scale must be 'linear' or 'log'"),
    (dict(ranges={"n": (1.2, "x")}), "is not a number"),
    (dict(ranges={"n": (1.2, 2)}), "^k and sigma need a range or a fixed value"),
    (dict(fixed={"n": 1.5}), "'n' has a range and a fixed value"),
    (dict(geometry={"theta_i": 40}), "theta_r is required"),
    (dict(geometry={"theta_i": 40, "theta_r": [10, 95]}), "theta_r must be in"),
    (dict(geometry={"theta_i": 40, "theta_r": "0:85@x"}), "theta_r"),
    (dict(geometry={"theta_i": 40, "theta_r": 20, "thetar": 3}), "unknown axis 'thetar'"),
    (dict(quantity="aop"), "an angle modulo its period"),
    (dict(quantity="stokes"), "not one value per point"),
    (dict(N=1), "N must be an integer >= 2"),
    (dict(method="fast"), "method must be one of"),
    (dict(memory_budget="lots"), "memory_budget"),
])
def test_bad_input_names_the_field(kwargs, match):
    args = dict(ranges={"n": (1.2, 2.0), "k": (0.0, 2.0), "sigma": (0.1, 0.5)},
                geometry={"theta_i": 40, "theta_r": [10.0, 30.0]}, N=8, backend="numpy")
    args.update(kwargs)
    with pytest.raises(ValueError, match=match) as info:
        pbrdf_cl.sobol(**args)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("quantity", ["dop", "brdf", "aop", "stokes"])
def test_outer_equals_the_reference_pair_by_pair(engine, quantity, dtype, monkeypatch):
    """dense.outer: every (geometry, parameter set) pair equals reference.evaluate at that pair,
    with parameter sets that are not a multiple of the vector width and several launches."""
    from pbrdf_cl.compute import dense
    monkeypatch.setattr(dense, "OUTER_LAUNCH_PAIRS", 3 * 37)
    rng = np.random.default_rng(7)
    G, S = 9, 37
    geo = dict(theta_i=rng.uniform(0, 85, G), theta_r=rng.uniform(0, 85, G), phi=rng.uniform(0, 360, G))
    sets = dict(n=rng.uniform(1.1, 3, S), k=rng.uniform(0, 4, S), sigma=rng.uniform(0.05, 1, S),
                ks=rng.uniform(0.5, 2, S), kd=rng.uniform(0, 1, S), c=rng.uniform(-1, 0, S))
    got = dense.outer(engine, quantity, geo, sets, dtype, rows=(2, 9))
    assert got.shape == (7, S) + pbrdf_cl.quantities.get(quantity).trailing
    assert got.dtype == np.dtype(dtype)
    want = reference.evaluate(quantity, *(geo[n][2:, None] for n in ("theta_i", "theta_r", "phi")),
                              *(sets[n][None, :] for n in ("n", "k", "sigma", "ks", "kd", "c")))
    if quantity == "aop":  # degrees modulo 180; float32 compared where the DOP is not tiny (as test_quantities)
        dop = reference.evaluate("dop", *(geo[n][2:, None] for n in ("theta_i", "theta_r", "phi")),
                                 *(sets[n][None, :] for n in ("n", "k", "sigma", "ks", "kd", "c")))
        far = dop > 1e-2 if dtype == "float32" else np.isfinite(want)
        assert far.sum() > 100
        diff = pbrdf_cl.quantities.wrap(got[far].astype(float) - want[far], 180.0)
        assert np.abs(diff).max() <= (2e-3 if dtype == "float32" else 1e-9)
    else:
        scale = np.abs(want).max()
        np.testing.assert_allclose(got, want, rtol=2e-5 if dtype == "float32" else 1e-12,
                                   atol=(2e-6 if dtype == "float32" else 1e-14) * scale)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_peak_memory_stays_within_the_budget(engine, dtype):
    """Host allocations (tracemalloc sees numpy's) peak within memory_budget plus what does not
    grow with the geometries' block: the samples, the bootstrap counts and the result."""
    import tracemalloc
    budget = 4 << 20
    pbrdf_cl.sobol(RANGES, {"theta_i": 40, "theta_r": [1.0, 2.0]}, N=16, engine=engine, dtype=dtype)  # built
    tracemalloc.start()
    try:
        ds = pbrdf_cl.sobol(RANGES, {"theta_i": "0:80@20", "theta_r": "0:85@30"}, N=1024, seed=1, dtype=dtype,
                            memory_budget=budget, engine=engine)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    runs = ds.attrs["runs_per_geometry"]
    fixed = (100 * 1024 * 8  # bootstrap counts
             + 2 * 6 * runs * 8  # the sampler's rows and the parameter sets
             + sum(v.nbytes for v in ds.data_vars.values()))
    assert ds.attrs["blocks"] > 20
    assert peak <= budget + fixed + (512 << 10), (peak, budget, fixed)
