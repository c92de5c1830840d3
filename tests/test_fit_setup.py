"""The one setup of a fit (pbrdf_cl.fitting.setup.FitSetup), shared by fit, fit_batch and design:
its parameters, the values it derives, and the same one-line refusals from all three."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.fitting.setup import DEFAULT_BOUNDS, PARAMETERS, FitSetup, Parameter

TI, TR = np.repeat([30.0, 40, 50], 10), np.tile(np.arange(20.0, 66, 5), 3)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3)


def test_parameters_of_a_setup():
    s = FitSetup.check("six-param", bounds={"n": (1, 3), "ks": (0.1, 10)}, fixed={"sigma": 0.4})
    assert s.free == ["n", "k", "kd", "c"] and s.base == {"ks": 1.0, "sigma": 0.4}
    np.testing.assert_array_equal(s.lo, [1.0, 0.0, 0.0, -1.0])
    np.testing.assert_array_equal(s.hi, [3.0, 10.0, 5.0, 0.0])
    assert s.ks_bounds == (0.1, 10.0)
    lo, hi = s.bounds_of(["kd", "ks"])
    np.testing.assert_array_equal(lo, [0.0, 0.1])
    np.testing.assert_array_equal(hi, [5.0, 10.0])
    p = s.params
    assert list(p) == list(PARAMETERS)
    assert p["n"] == Parameter("n", None, (1.0, 3.0), True)
    assert p["sigma"] == Parameter("sigma", 0.4, DEFAULT_BOUNDS["sigma"], False)
    assert p["ks"] == Parameter("ks", 1.0, (0.1, 10.0), False)
    assert s.fits_intensity(True) and not s.fits_intensity(False)
    assert not FitSetup.check(fixed={"ks": 2.0}).fits_intensity(True)
    spec = FitSetup.check("specular")
    assert spec.free == ["n", "k"] and spec.base == {"ks": 1.0, "kd": 0.0, "c": 0.0, "sigma": 0.5}
    assert not spec.fits_intensity(True)
    axes = s.grid_axes({"n": 3, "k": 4, "kd": 2, "c": 2})
    assert list(axes) == s.free and axes["n"][0] == 1.0 and axes["n"][-1] == 3.0 and axes["k"].size == 4


@pytest.mark.parametrize("kw, message", [
    (dict(model="lambert"), "model must be one of"),
    (dict(shadowing="torrance"), "shadowing must be one of"),
    (dict(bounds={"q": (0, 1)}), "bounds: unknown parameter 'q'"),
    (dict(bounds={"n": 2.0}), "bounds: n must be a (low, high) pair"),
    (dict(bounds={"n": (3, 2)}), "bounds: n = (3.0, 2.0) must be finite with low < high"),
    (dict(bounds={"n": (0, 2)}), "bounds: n low = 0.0 is outside the model's domain"),
    (dict(bounds={"ks": (0, 2)}), "bounds: ks low = 0.0 is outside the model's domain"),
    (dict(fixed={"ks": -1}), "fixed: ks = -1.0 is outside the model's domain"),
    (dict(model="specular", fixed={"sigma": 0.3}), "fixed: sigma is not a parameter of the specular model"),
    (dict(fixed=STEEL), "every parameter is fixed: nothing to fit"),
])
def test_one_line_refusals(kw, message):
    with pytest.raises(ValueError) as err:
        FitSetup.check(**kw)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_fit_fit_batch_and_design_refuse_alike():
    """The three front doors check bounds and fixed values through the one setup: the same message."""
    dop = pbrdf_cl.dop(TI, TR, backend="numpy", **STEEL)
    calls = [lambda **kw: pbrdf_cl.fit(dict(theta_i=TI, theta_r=TR, dop=dop), backend="numpy", **kw),
             lambda **kw: pbrdf_cl.fit_batch(dict(dop=dop[None], theta_i=TI, theta_r=TR), backend="numpy", **kw),
             lambda **kw: pbrdf_cl.design(STEEL, backend="numpy", **kw)]
    for kw, message in ((dict(bounds={"n": (0, 2)}), "bounds: n low = 0.0 is outside the model's domain"),
                        (dict(fixed={"ks": -1}), "fixed: ks = -1.0 is outside the model's domain"),
                        (dict(bounds={"ks": (2, 1)}), "bounds: ks = (2.0, 1.0) must be finite with low < high")):
        for call in calls:
            with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
                call(**kw)
