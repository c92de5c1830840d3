"""What a fit says about itself: whether the model describes the data (and the usual causes when
not), parameters on a bound or outside their own interval (marked in the summary, issue #34 item
4), correlations in brief, a short repr, labelled matrices that are valid covariances and
correlations or NaN with a note (issue #34 item 3), the comparison of models as a result object."""
import warnings
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.compute import pointwise as api
from pbrdf_cl.fitting import report
from pbrdf_cl.fitting.common import OUTSIDE_MARK, OUTSIDE_WHY, valid_covariance
from pbrdf_cl.fitting.sample import result
from pbrdf_cl.io.measurements import read_csv

ROOT = Path(__file__).resolve().parent.parent
STEEL = read_csv(ROOT / "examples" / "steel_435nm.csv")


def steel(**change):
    d = dict(theta_i=STEEL.theta_i, theta_r=STEEL.theta_r, phi=STEEL.phi, dop=STEEL.dop)
    d.update(change)
    return d


@pytest.fixture(scope="module")
def good():
    return pbrdf_cl.fit(STEEL)


def test_a_good_fit_says_it_fits(good):
    assert STEEL.dop_std is not None  # the example has its noise level: chi2 means something
    assert good.fits_data and good.success and good.p_value > 1e-3 and good.r2 > 0.99
    assert not any(n.startswith("the model does not describe") for n in good.notes)
    assert "WARNING" not in good.summary() and "reduced" in good.summary()
    plain = pbrdf_cl.fit(steel())  # without dop_std: no chi2, no p-value
    assert plain.fits_data and plain.p_value is None and "chi2" not in plain.summary()
    text = repr(good)
    assert "\n" not in text and text.startswith("FitResult(model='six-param', success=True, n=")
    assert len(text) < 200


def test_angles_in_radians_are_caught(recwarn):
    r = pbrdf_cl.fit(steel(theta_i=np.radians(STEEL.theta_i), theta_r=np.radians(STEEL.theta_r)))
    assert any(issubclass(w.category, api.UnitsWarning) for w in recwarn.list)
    assert not r.fits_data
    assert r.notes[0].startswith("the model does not describe these data: it explains")
    assert "angles in radians" in r.notes[0]
    assert any("radians? pbrdf-cl takes degrees" in n for n in r.notes)
    assert r.summary().splitlines()[1].startswith("  WARNING: the model does not describe these data")


def test_phi_zero_for_in_plane_data_is_caught():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = pbrdf_cl.fit(steel(phi=np.zeros_like(STEEL.phi)))
    assert not r.fits_data and "the phi convention" in r.notes[0]
    assert any(n.startswith("phi = 0 for every point") for n in r.notes)


def test_chi2_with_given_uncertainties():
    ok = pbrdf_cl.fit(steel(dop_std=STEEL.dop_std))  # the noise the example was made with
    assert ok.fits_data and 1e-3 < ok.p_value and "chi2" in ok.summary() and "p = " in ok.summary()
    bad = pbrdf_cl.fit(steel(dop_std=np.full(len(STEEL), 1e-5)))  # far too small: the model cannot fit that
    assert not bad.fits_data and bad.p_value < 1e-3 and "chi2 =" in bad.notes[0] and "dop_std too small" in bad.notes[0]


def test_a_parameter_on_its_bound_is_noted():
    r = pbrdf_cl.fit(STEEL, bounds={"n": (1.0, 1.4)})  # the truth is 1.6
    assert r.x["n"] == pytest.approx(1.4)
    assert any(n.startswith("n = 1.4 is on its upper bound") for n in r.notes)


def test_best_value_outside_its_interval_is_explained():
    notes = result._bound_notes(["k"], np.array([10.0]), np.array([0.0]), np.array([10.0]),
                                   {"k": (0.254, 9.75)})
    assert notes[0].startswith("k = 10 is on its upper bound")
    assert notes[1].startswith("k's best value 10 lies outside its 95% interval [0.254, 9.75]")


def test_correlations_are_summarised(good):
    names = ["a", "b", "c", "d", "e"]
    corr = np.full((5, 5), 0.99)
    np.fill_diagonal(corr, 1)
    eig = (np.ones(5), np.eye(5))
    notes = report.identifiability_notes(names, np.eye(5), 10.0, eig, np.ones(5), np.full(5, 0.01), corr,
                                             np.ones(5))
    strong = [n for n in notes if n.startswith("strongly correlated")]
    assert strong == ["strongly correlated: a-b (r = +0.990), a-c (r = +0.990), a-d (r = +0.990), and 7 more "
                      "(see .corr)"]
    assert sum("correlated" in n for n in good.notes) <= 1


def test_matrices_are_labelled(good):
    assert list(good.corr.coords["param"].values) == good.free
    assert float(good.corr.sel(param="n", param_2="n")) == pytest.approx(1.0)
    np.testing.assert_allclose(np.sqrt(np.diag(good.cov.values)), [good.stderr[n] for n in good.free], rtol=1e-12)
    assert float(good.corr.sel(param="n", param_2="k")) == pytest.approx(float(good.corr.sel(param="k", param_2="n")))


def test_compare_models_returns_a_result():
    both = pbrdf_cl.compare_models(STEEL)
    assert isinstance(both, result.ComparisonResult)
    assert set(both.fits) == {"six-param", "specular"} and both["six-param"] is both.fits["six-param"]
    assert both.preferred == ("six-param" if both.fits["six-param"].bic <= both.fits["specular"].bic else "specular")
    assert both.summary().splitlines()[-1] == f"  preferred by BIC: {both.preferred}"
    assert "\n" not in repr(both)


def assert_valid_covariance(cov, corr):
    """``cov`` symmetric positive semi-definite and ``corr`` in [-1, 1] with a unit diagonal,
    both exactly symmetric, NaN in the same rows and columns (those of parameters without a
    variance), nowhere else."""
    cov, corr = np.asarray(cov, float), np.asarray(corr, float)
    np.testing.assert_array_equal(cov, cov.T)
    np.testing.assert_array_equal(corr, corr.T)
    nan = np.isnan(cov)
    np.testing.assert_array_equal(nan, np.isnan(corr))
    undefined = np.all(nan, axis=0)
    np.testing.assert_array_equal(nan, undefined[:, None] | undefined[None, :])
    assert np.all(np.abs(corr[~nan]) <= 1.0)
    np.testing.assert_allclose(np.diag(corr)[~undefined], 1.0, rtol=0, atol=1e-12)
    block = cov[np.ix_(~undefined, ~undefined)]
    if block.size:
        w = np.linalg.eigvalsh(block)
        assert w.min() >= -1e-12 * w.max(), w
    return undefined


def test_the_covariance_of_a_fit_that_does_not_describe_its_data_is_valid_or_nan():
    """In-plane data labelled phi = 0 (issue #34 item 3): the pseudo-inverse of the near-singular
    J^T J gave correlations above 1, not symmetric, a covariance with a negative eigenvalue; now
    valid, NaN for the parameters without a variance, and a note says which and why."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = pbrdf_cl.fit(steel(phi=np.zeros_like(STEEL.phi), dop_std=STEEL.dop_std))
    assert not r.fits_data
    undefined = assert_valid_covariance(r.cov, r.corr)
    cov_notes = [n for n in r.notes if "projected onto a valid one" in n or "cannot be computed" in n]
    assert len(cov_notes) == 1, r.notes
    for name, u in zip(r.free, undefined):
        assert np.isnan(r.stderr[name]) == u
        if u:
            assert name in cov_notes[0].split("the variance of ")[1].split(" cannot")[0]
    for note in r.notes:  # the correlations the notes quote are valid too
        for value in note.split("(r = ")[1:]:
            assert abs(float(value.split(")")[0])) <= 1.0
    assert "+- nan" in r.summary() or not undefined.any()


def test_a_valid_covariance_is_kept_as_computed(good):
    """Well-fitted data: the covariance is not regularised (valid_covariance returns it bit for
    bit), the correlations are cov / (se se) with rounding above 1 clipped, and no note."""
    cov = np.asarray(good.cov)
    se = np.array([good.stderr[n] for n in good.free])
    np.testing.assert_array_equal(valid_covariance(cov).cov, cov)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(np.asarray(good.corr), np.clip(cov / np.outer(se, se), -1, 1))
    assert not any("projected onto a valid one" in n or "cannot be computed" in n for n in good.notes)


def test_valid_covariance_repairs_only_what_is_invalid():
    ok = np.array([[4.0, 1.0], [1.0, 1.0]])
    v = valid_covariance(ok)
    np.testing.assert_array_equal(v.cov, ok)
    np.testing.assert_array_equal(v.corr, [[1.0, 0.5], [0.5, 1.0]])
    assert not v.repaired and v.note(["a", "b"]) is None
    # not symmetric, a correlation of 2.1 (not positive semi-definite), a zero and an infinite variance
    bad = np.array([[1.0, 2.0, 0.5, 3.0], [2.1, 1.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0], [3.0, 0.0, 0.0, np.inf]])
    v = valid_covariance(bad)
    assert_valid_covariance(v.cov, v.corr)
    np.testing.assert_array_equal(v.undefined, [False, False, True, True])
    np.testing.assert_allclose(np.diag(v.cov)[:2], [1.0, 1.0], rtol=1e-12)  # the variances are kept
    note = v.note(["a", "b", "c", "d"])
    assert "not symmetric" in note and "not positive semi-definite" in note and "the variance of c, d" in note
    # its own output given again is kept: the NaN rows of c and d leave a and b their variances
    again = valid_covariance(v.cov)
    np.testing.assert_array_equal(again.undefined, v.undefined)
    np.testing.assert_array_equal(again.cov, v.cov)
    # batched: each matrix on its own
    both = valid_covariance(np.stack([np.pad(ok, ((0, 2), (0, 2))) + np.diag([0, 0, 1.0, 1.0]), bad]))
    np.testing.assert_array_equal(both.repaired, [False, True])
    np.testing.assert_array_equal(both.cov[1], v.cov)
    np.testing.assert_array_equal(both.cov[0][:2, :2], ok)


def test_a_best_value_outside_its_interval_is_marked():
    """Table 1's aluminium (issue #34 item 4): k = 10 on its upper bound, its interval [0.254,
    9.75]. Each line of the summary is marked (*) exactly where the best value lies outside its
    interval, ``outside_ci95`` lists them, and one note says why."""
    from pbrdf_cl.analysis import paper
    meas, _ = paper.fig2_data("aluminum")
    r = pbrdf_cl.fit(meas)
    outside = [n for n in r.free if not r.ci95[n][0] <= r.x[n] <= r.ci95[n][1]]
    assert outside, "the aluminium fit no longer puts a value outside its interval: choose another case"
    assert r.outside_ci95 == outside
    lines = {ln.split("=")[0].strip(): ln for ln in r.summary().splitlines() if ln.startswith("  ") and "=" in ln}
    for n in r.free:
        assert (OUTSIDE_MARK in lines[n]) == (n in outside), lines[n]
    notes = [n for n in r.notes if OUTSIDE_MARK in n]
    assert len(notes) == 1 and notes[0].endswith(OUTSIDE_WHY)
    assert all(f"{n}'s best value" in notes[0] for n in outside)
