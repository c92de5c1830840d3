"""What a fit says about itself: whether the model describes the data (and the usual causes when
not), parameters on a bound or outside their own interval, correlations in brief, a short repr,
labelled matrices, the comparison of models as a result object."""
import warnings
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.compute import pointwise as api
from pbrdf_cl.fitting import result
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
    notes = result.identifiability_notes(names, np.eye(5), 10.0, eig, np.ones(5), np.full(5, 0.01), corr,
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
