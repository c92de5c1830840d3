"""The stages of the inversion, each alone; the Candidate type; the finite-difference helper;
FitResult's status; honest fits on degenerate data (too few geometries, exact fits)."""
import dataclasses

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import cli, results
from pbrdf_cl.compute import dense
from pbrdf_cl.fitting import common
from pbrdf_cl.fitting import setup as fit_setup
from pbrdf_cl.fitting.sample import basins, inversion, result, stages, uncertainty
from pbrdf_cl.io.measurements import from_arrays

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15 / 0.9, c=-0.3)  # kd as kd/ks
NAMES = ("n", "k", "sigma", "kd", "c")
LO = np.array([fit_setup.DEFAULT_BOUNDS[n][0] for n in NAMES])
HI = np.array([fit_setup.DEFAULT_BOUNDS[n][1] for n in NAMES])


def steel_residuals(noise=0.0, seed=0, with_std=True):
    dop = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", **STEEL)
    if noise:
        dop = np.clip(dop + np.random.default_rng(seed).normal(0, noise, dop.size), 0, 1)
    std = np.full(dop.size, noise if noise and with_std else 1.0)
    meas = from_arrays(TI, TR, dop, 180.0, std if noise and with_std else None)
    return meas, stages.Residuals(stages.Model(meas, "paper"), NAMES, {"ks": 1.0}, meas.dop, std)


def sse_at(resid, x):
    r = resid.rows(np.atleast_2d(x))[0]
    return float(r @ r)


# --- Candidate, StageResult, Result --------------------------------------------------------

def test_candidate_is_frozen_and_moves_only_downhill():
    seed = np.array([1.0, 2.0])
    c = stages.Candidate(3.0, np.array([1.5, 2.5]), seed)
    assert c.converged is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.sse = 1.0
    assert c.better(3.0, np.zeros(2)) is c and c.better(4.0, np.zeros(2)) is c  # not lower: itself
    d = c.better(np.float64(2.5), np.zeros(2))
    assert d.sse == 2.5 and type(d.sse) is float and d.seed is seed and np.array_equal(d.x, [0, 0])
    ranked = stages.ranked([c, d, stages.Candidate(2.5, np.ones(2), seed)])
    assert [r.sse for r in ranked] == [2.5, 2.5, 3.0] and ranked[0] is d  # stable on ties


def test_result_attributes_can_be_assigned_and_dense_result_is_the_same_class():
    assert dense.Result is results.Result and issubclass(result.FitResult, results.Result)
    r = results.Result(a=1)
    r.b = 2
    assert r["b"] == 2 and r.a == 1 and sorted(dir(r)) == ["a", "b"]
    del r.a
    assert "a" not in r
    with pytest.raises(AttributeError):
        r.a  # noqa: B018 - the attribute access is what raises
    with pytest.raises(AttributeError):
        del r.a


# --- the finite-difference helper ----------------------------------------------------------

def cubic_rows(calls):
    A = np.array([[1.0, 2.0, -1.0], [0.5, -3.0, 2.0], [2.0, 0.0, 1.0], [-1.0, 1.0, 1.0]])

    def rows(X):
        calls.append(X.copy())
        return (X @ A.T) ** 3 / 3 + X[:, :1] ** 2

    def jac(x):  # analytic, (d, M)
        return (A * ((A @ x) ** 2)[:, None]).T + np.outer([2 * x[0], 0, 0], np.ones(4))
    return rows, jac


# forward differences err by O(h) (h ~ 1.5e-8 relative), central ones by O(h^2) (h = 2e-6 of the
# bound range) inside and by O(h) where a bound makes them one-sided
@pytest.mark.parametrize("scheme,rtol,rtol_bound", [("2-point", 1e-6, 1e-6), ("central", 1e-9, 2e-5)])
def test_fd_jacobian_batches_points_and_agrees_with_the_derivative(scheme, rtol, rtol_bound):
    calls = []
    rows, jac = cubic_rows(calls)
    lo, hi = np.full(3, -1.0), np.full(3, 1.0)
    X = np.array([[0.2, -0.3, 0.5], [0.9, 0.1, -0.7], [1.0, -1.0, 0.0]])  # the last on two bounds
    R, J = common.fd_jacobian(rows, X, lo, hi, scheme)
    assert len(calls) == 1 and len(calls[0]) == 3 * (4 if scheme == "2-point" else 7)
    assert np.all(calls[0] >= lo) and np.all(calls[0] <= hi)  # steps never leave the bounds
    np.testing.assert_array_equal(R, rows(X))
    for p in range(3):
        tol = rtol_bound if p == 2 else rtol
        np.testing.assert_allclose(J[p], jac(X[p]), rtol=tol, atol=tol)
        R1, J1 = common.fd_jacobian(rows, X[p:p + 1], lo, hi, scheme)  # alone: the same numbers
        np.testing.assert_array_equal(J1[0], J[p])
    with pytest.raises(ValueError, match="scheme must be '2-point' or 'central', got 'five-point'"):
        common.fd_jacobian(rows, X, lo, hi, "five-point")


# --- each stage alone ----------------------------------------------------------------------

def test_grid_stage_is_the_objective_on_the_grid_and_its_profiles():
    meas, resid = steel_residuals(noise=0.002, seed=1)
    axes = {n: fit_setup.grid_axis(n, fit_setup.DEFAULT_BOUNDS[n], count) for n, count in zip(NAMES, (5, 4, 3, 3, 2))}
    st = stages.grid_stage(meas, list(NAMES), axes, {"ks": 1.0}, backend="numpy")
    grid = st.value
    assert grid.sse.shape == (5, 4, 3, 3, 2) and st.nfev == 360 and st.seconds >= 0
    X = np.stack(np.meshgrid(*axes.values(), indexing="ij"), axis=-1).reshape(-1, 5)
    r = resid.rows(X)
    np.testing.assert_allclose(grid.sse.ravel(), np.einsum("pm,pm->p", r, r), rtol=2e-5)
    np.testing.assert_array_equal(grid.profiles["k"], grid.sse.min(axis=(0, 2, 3, 4)))


def test_basin_stage_seeds_at_the_grid_minima_with_their_steps():
    a, b = np.linspace(0, 1, 11), np.array([0.0, 0.1, 0.3, 0.6, 1.0])
    sse = np.minimum((a[:, None] - 0.2) ** 2, (a[:, None] - 0.9) ** 2 + 0.01) + (b[None, :] - 0.3) ** 2
    grid = stages.GridStage(sse, {"a": a, "b": b}, basins.grid_profiles(sse, ["a", "b"]))
    st = stages.basin_stage(grid, ["a", "b"], n_basins=2, rise=1.0, profile_seeds=0)
    assert st.value.indices == [(2, 2), (9, 2)] and st.nfev == 0
    np.testing.assert_allclose(st.value.seeds[0], [0.2, 0.3])
    np.testing.assert_allclose(st.value.steps[1], [0.1, 0.3])  # the larger step on either side


def test_local_stages_alone_descend_from_a_seed_to_the_truth():
    meas, resid = steel_residuals()
    truth = np.array([STEEL[n] for n in NAMES])
    seed = truth + np.array([0.15, -0.2, 0.03, 0.02, 0.05])
    step = np.array([0.2, 0.3, 0.05, 0.05, 0.1])
    d = stages.direct_stage(resid.rows, LO, HI, [seed], [step], evals=20)
    (cd,) = d.value
    assert d.nfev == 20 * 5 + 1 and cd.sse <= sse_at(resid, seed) and np.array_equal(cd.seed, seed)
    assert np.all(np.abs(cd.x - seed) <= 1.5 * step + 1e-12)  # inside its box
    b = stages.bobyqa_stage(resid.rows, LO, HI, [cd], [step], evals=20)
    assert b.value[0].sse <= cd.sse and b.nfev <= 100 and b.value[0].seed is seed
    s = stages.screen_stage(resid.rows, LO, HI, b.value, iterations=30)
    assert s.value[0].sse <= b.value[0].sse and s.nfev == 6 * 31
    ls = stages.least_squares_stage(resid.rows, LO, HI, s.value)
    (best,) = ls.value
    assert best.converged is True and best.sse < 1e-20
    np.testing.assert_allclose(best.x, truth, rtol=1e-7)
    starved = stages.least_squares_stage(resid.rows, LO, HI, [stages.Candidate(np.inf, seed, seed)], max_nfev=0.4)
    assert starved.value[0].converged is False and starved.nfev <= 3 * 6
    fb = stages.final_bobyqa_stage(resid.rows, LO, HI, starved.value[0], evals=200)
    assert fb.value.sse < starved.value[0].sse and fb.nfev <= 200 * 5 + 1


def test_intensity_stage_alone_separates_ks_and_kd():
    truth = dict(STEEL, kd=0.15)
    dop = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", **truth, ks=0.9)
    f00 = pbrdf_cl.brdf(TI, TR, 180.0, backend="numpy", **truth, ks=0.9)
    meas = from_arrays(TI, TR, dop, 180.0, None, f00)
    mdl, std = stages.Model(meas, "paper"), np.ones(30)
    ratio = np.array([STEEL[n] for n in NAMES])  # kd as kd/ks
    ks0 = stages.intensity_start(mdl, dict(zip(NAMES, ratio), ks=1.0), f00, 0.05 * f00, fit_setup.DEFAULT_BOUNDS["ks"])
    assert ks0 == pytest.approx(0.9, rel=1e-12)  # the exact scale: DOP fixes kd/ks
    resid = stages.Residuals(mdl, NAMES + ("ks",), {}, dop, std, f00, 0.05 * f00)
    lo, hi = np.append(LO, 1e-3), np.append(HI, 1e3)
    x0 = np.append(ratio, ks0 * 1.1)  # from the DOP optimum, ks 10% off
    st = stages.intensity_stage(resid, lo, hi, x0, np.full(6, 0.01))
    assert st.value.converged is True and st.nfev < stages.INTENSITY_MAXEVAL and st.value.sse < 1e-12
    p = resid.params(st.value.x)
    assert p["ks"] == pytest.approx(0.9, rel=1e-4) and p["kd"] == pytest.approx(0.15, rel=1e-4)
    starved = stages.intensity_stage(resid, lo, hi, x0, np.full(6, 0.01), maxeval=20)
    assert starved.value.converged is False and starved.nfev == 20


def linear_problem(noise):
    """r = (A x - b) / std: the covariance is std^2 (A^T A)^-1 when std is the noise."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(40, 3))
    truth = np.array([0.3, -0.2, 0.5])
    b = A @ truth + (rng.normal(0, noise, 40) if noise else 0.0)

    class Linear:
        free = ("a", "b", "c")

        def rows(self, X):
            return X @ A.T - b
    return Linear(), A, b


def test_uncertainty_stage_alone_gives_the_linear_covariance():
    resid, A, b = linear_problem(1.0)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    lo, hi = np.full(3, -50.0), np.full(3, 50.0)
    empty = stages.GridStage(None, {}, {})
    st = uncertainty.uncertainty_stage(resid, x, lo, hi, empty, float(np.sum((A @ x - b) ** 2)), 40, sigma_known=True)
    u = st.value
    se = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    np.testing.assert_allclose(u.stderr, se, rtol=1e-6)
    assert u.dof == 37 and st.nfev == 7 and u.noise_floor is None
    for i, n in enumerate(resid.free):
        np.testing.assert_allclose(u.ci95_jacobian[n], (x[i] - 1.959964 * se[i], x[i] + 1.959964 * se[i]), rtol=1e-5)
        # (the posterior interval is read off a mesh of 0.05 standard errors)
        np.testing.assert_allclose(u.ci95[n], u.ci95_jacobian[n], rtol=0, atol=1e-3 * se[i])


def test_uncertainty_stage_floors_the_noise_of_an_exact_fit():
    resid, A, b = linear_problem(0.0)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    lo, hi = np.full(3, -50.0), np.full(3, 50.0)
    empty = stages.GridStage(None, {}, {})
    bare = uncertainty.uncertainty_stage(resid, x, lo, hi, empty, 0.0, 40, sigma_known=False).value
    assert np.all(bare.stderr < 1e-12)  # without a floor an exact fit collapses the intervals
    u = uncertainty.uncertainty_stage(resid, x, lo, hi, empty, 0.0, 40, sigma_known=False, noise_floor=0.01).value
    se = 0.01 * np.sqrt(np.diag(np.linalg.inv(A.T @ A)))
    assert u.noise_floor == 0.01
    np.testing.assert_allclose(u.stderr, se, rtol=1e-6)
    for i, n in enumerate(resid.free):  # Gaussian: the noise is taken as known, at the floor
        lo_i, hi_i = u.ci95[n]
        assert hi_i - lo_i == pytest.approx(2 * 1.959964 * se[i], rel=1e-3)


# --- FitResult.success / status / message --------------------------------------------------

def test_fit_status_of_a_converged_fit_and_of_a_starved_one(monkeypatch):
    meas, _ = steel_residuals(noise=0.002, seed=2)
    r = pbrdf_cl.fit(meas)
    assert r.success is True and r.status in (1, 2) and r.message == result.FIT_STATUS[r.status]
    assert "status" not in r.summary()
    r.label = "steel"  # attribute assignment
    assert r["label"] == "steel"
    monkeypatch.setattr(stages, "SCREEN_ITERATIONS", 0)  # no descent of the candidates
    monkeypatch.setattr(stages, "LS_MAX_NFEV", 0.4)         # least squares: 2 evaluations
    monkeypatch.setattr(stages, "FINAL_BOBYQA", 2)          # the final BOBYQA: 10
    starved = pbrdf_cl.fit(meas)
    assert starved.nfev["final_bobyqa"] > 0
    assert starved.success is False and starved.status == 0 and starved.message.startswith("stopped:")
    assert f"status 0: {result.FIT_STATUS[0]}" in starved.summary()


def test_fit_status_rules():
    good, bad = stages.Candidate(1.0, np.zeros(2), np.zeros(2), True), stages.Candidate(1e300, np.zeros(2), np.zeros(2))
    assert result.fit_status(good, False, None) == 1 and result.fit_status(good, True, None) == 2
    assert result.fit_status(bad, False, None) == -1
    assert result.fit_status(good, False, stages.Candidate(1.0, np.zeros(3), np.zeros(3), False)) == 0
    assert result.fit_status(dataclasses.replace(good, converged=False), True, None) == 0


# --- degenerate data -----------------------------------------------------------------------

def test_fewer_distinct_geometries_than_free_parameters_is_refused(tmp_path, capsys):
    path = tmp_path / "seven.csv"
    path.write_text("theta_i,theta_r,dop\n" + "40,40,0.1\n" * 7)
    with pytest.raises(ValueError, match=r"1 distinct geometry \(theta_i, theta_r, phi\) for 5 free parameters "
                                         r"\(n, k, sigma, kd, c\): .*fix parameters"):
        pbrdf_cl.fit(path)
    assert cli.main(["fit", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "1 distinct geometry" in err and "--fix c=" in err
    # three geometries, each measured three times: enough for two free parameters
    ti, tr = np.repeat([30.0, 40.0, 50.0], 3), np.repeat([25.0, 40.0, 55.0], 3)
    dop = pbrdf_cl.dop(ti, tr, 180.0, backend="numpy", **STEEL)
    assert inversion.distinct_geometries(from_arrays(ti, tr, dop)) == 3
    with pytest.raises(ValueError, match="3 distinct geometries .* for 4 free parameters"):
        pbrdf_cl.fit(dict(theta_i=ti, theta_r=tr, dop=dop), fixed=dict(c=-0.3))
    r = pbrdf_cl.fit(dict(theta_i=ti, theta_r=tr, dop=dop), fixed=dict(sigma=0.5, kd=STEEL["kd"], c=-0.3))
    assert r.free == ["n", "k"] and all(hi - lo > 1e-3 for lo, hi in r.ci95.values())


def test_exact_fit_without_uncertainties_uses_the_stated_noise_floor():
    dop = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", **STEEL)
    r = pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=dop))
    assert r.sse < 1e-20 and r.success
    floor_notes = [n for n in r.notes if "noise floor" in n]
    assert len(floor_notes) == 1 and f"DOP noise of std {common.DOP_NOISE_FLOOR:.2g}" in floor_notes[0]
    for name in NAMES:
        lo, hi = r.ci95[name]
        assert lo <= STEEL[name] <= hi and hi - lo > 0.01 * (HI - LO)[NAMES.index(name)], (name, lo, hi)
        j_lo, j_hi = r.ci95_jacobian[name]
        assert j_hi - j_lo > 1e-4 and r.stderr[name] > 0
    # the same data written with 3 decimals: the floor is still the default (0.001 / sqrt(12) is
    # smaller), and with 1 decimal it is the rounding error's
    assert common.dop_noise_floor(np.round(dop, 3)) == common.DOP_NOISE_FLOOR
    assert common.dop_noise_floor(np.round(dop, 1)) == pytest.approx(0.1 / np.sqrt(12), rel=1e-12)
    # given uncertainties, no floor: they say what the noise is
    known = pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=dop, dop_std=np.full(30, 1e-4)))
    assert not any("noise floor" in n for n in known.notes)


def test_dop_resolution_reads_the_decimals():
    assert common.dop_resolution([0.1, 0.25, 0.3]) == 0.01
    assert common.dop_resolution([0.0, 1.0]) == 1.0
    assert common.dop_resolution([0.1234, 0.5]) == pytest.approx(1e-4)
    assert common.dop_resolution(np.random.default_rng(0).random(20)) == 0.0


def test_bounds_and_fixed_values_follow_the_api_domain_rules():
    data = dict(theta_i=TI, theta_r=TR, dop=np.full(30, 0.1))
    with pytest.raises(ValueError, match=r"^bounds: n low = 0.0 is outside the model's domain \(n must be > 0\)$"):
        pbrdf_cl.fit(data, bounds=dict(n=(0, 2)))
    with pytest.raises(ValueError, match=r"^fixed: k = -1.0 is outside the model's domain \(k must be >= 0\)$"):
        pbrdf_cl.fit(data, fixed=dict(k=-1))
    with pytest.raises(ValueError, match=r"^fixed: c = inf is outside the model's domain \(c must be in \[-1, 0\]\)$"):
        pbrdf_cl.fit(data, fixed=dict(c=float("inf")))
