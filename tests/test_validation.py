"""Every bad input gets a ValueError naming the argument and the bad value; no silent NaN."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.device import choice, fallback
from pbrdf_cl.device import engine as engine_mod

from conftest import requires_opencl

GOOD = dict(n=1.6, k=2.1, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)


@pytest.mark.parametrize("backend", [pytest.param("opencl", marks=requires_opencl), "numpy"])
@pytest.mark.parametrize("func", [pbrdf_cl.dop, pbrdf_cl.brdf, pbrdf_cl.mueller])
@pytest.mark.parametrize("args,kwargs,pattern", [
    ((90.0, 20.0), {}, r"theta_i must be in \[0, 90\) degrees, got 90\.0"),
    ((-1.0, 20.0), {}, r"theta_i .* got -1\.0"),
    ((40.0, [20.0, 95.0]), {}, r"theta_r .* got 95\.0 at index \[1\]"),
    ((np.nan, 20.0), {}, r"theta_i must be finite, got nan"),
    ((40.0, 20.0, np.inf), {}, r"phi must be finite, got inf"),
    ((40.0, 20.0), {"sigma": 0.0}, r"sigma must be > 0, got 0\.0"),
    ((40.0, 20.0), {"sigma": -0.2}, r"sigma must be > 0, got -0\.2"),
    ((40.0, 20.0), {"k": -0.1}, r"k must be >= 0, got -0\.1"),
    ((40.0, 20.0), {"n": 0.0}, r"n must be > 0, got 0\.0"),
    ((40.0, 20.0), {"ks": 0.0}, r"ks must be > 0, got 0\.0"),
    ((40.0, 20.0), {"kd": -1.0}, r"kd must be >= 0, got -1\.0"),
    ((40.0, 20.0), {"c": np.nan}, r"c must be finite, got nan"),
    ((40.0, 20.0), {"c": 5.0}, r"^c must be in \[-1, 0\], got 5\.0$"),
    ((40.0, [20.0, 30.0]), {"c": [-0.3, -1.5]}, r"^c must be in \[-1, 0\], got -1\.5 at index \[1\]$"),
    ((40.0, 20.0), {"n": "glass"}, r"n must be a number or an array of numbers, got 'glass'"),
    ((40.0, 20.0), {"shadowing": "torrance"}, r"shadowing must be one of .*'torrance'"),
    ((40.0, 20.0), {"dtype": "float16"}, r"dtype must be 'float32' or 'float64', got 'float16'"),
    (([10.0, 20.0, 30.0], [10.0, 20.0]), {}, r"do not broadcast together: theta_i\(3,\), theta_r\(2,\)"),
    ((40.0, 20.0), {"model": "specular"}, r"kd must be 0 in the specular"),
    ((40.0, 20.0), {"model": "torrance"}, r"model must be one of"),
])
def test_bad_input_names_argument_and_value(func, backend, args, kwargs, pattern):
    kw = dict(GOOD, backend=backend)
    kw.update(kwargs)
    with pytest.raises(ValueError, match=pattern):
        func(*args, **kw)


def test_bad_backend_and_missing_sigma():
    with pytest.raises(ValueError, match="backend must be one of"):
        pbrdf_cl.dop(40, 20, n=1.6, k=2, sigma=0.5, backend="cuda")
    with pytest.raises(ValueError, match="sigma is required"):
        pbrdf_cl.dop(40, 20, n=1.6, k=2)
    # the specular model's DOP does not depend on sigma, so it may be left out
    assert 0 < pbrdf_cl.dop(40, 20, n=1.6, k=2, model="specular") < 1


def test_no_platform_gives_an_error_that_says_how_to_get_one(monkeypatch):
    class NoPlatforms:
        Error = Exception
        Device = type("Device", (), {})

        @staticmethod
        def get_platforms():
            raise Exception("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")
    monkeypatch.setattr(choice, "cl", NoPlatforms)
    with pytest.raises(pbrdf_cl.OpenCLUnavailableError,
                       match=r"pip install pocl-binary-distribution.*pocl-opencl-icd.*intel-cpu.*backend=\"numpy\""):
        engine_mod.Engine()
    # ... and backend="auto" computes on the numpy reference instead
    monkeypatch.setattr(fallback, "_default_engine", None)
    monkeypatch.setattr(choice, "_WARNED", set())
    with pytest.warns(engine_mod.DeviceWarning, match="computing on the numpy backend.*no OpenCL platform found"):
        assert pbrdf_cl.get_default_engine().is_numpy
    assert abs(float(pbrdf_cl.dop(40, 45, **GOOD)) - float(pbrdf_cl.dop(40, 45, **GOOD, backend="numpy"))) == 0
    with pytest.raises(pbrdf_cl.OpenCLUnavailableError, match="backend='opencl': no OpenCL platform found"):
        pbrdf_cl.dop(40, 45, **GOOD, backend="opencl")
    monkeypatch.setattr(choice, "cl", None)
    with pytest.raises(pbrdf_cl.OpenCLUnavailableError, match="pocl-binary-distribution"):
        engine_mod.select_device()


@requires_opencl
def test_float64_on_a_device_without_it_is_refused():
    e = pbrdf_cl.Engine()
    e.fp64 = False
    with pytest.raises(ValueError, match="dtype='float64'.*no float64 support"):
        pbrdf_cl.dop(40, 20, n=1.6, k=2, sigma=0.5, engine=e, dtype="float64")


def _layouts(values):
    """``values`` (2-d, more than one check block) as a contiguous, a transposed (Fortran-ordered), a
    strided and, for a first row repeated, a broadcast array."""
    rows, cols = values.shape
    t = np.empty((cols, rows), values.dtype).T
    t[...] = values
    s = np.empty((rows, 2 * cols), values.dtype)[:, ::2]
    s[...] = values
    return dict(contiguous=values.copy(), transposed=t, strided=s,
                broadcast=np.broadcast_to(values[0], values.shape))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_min_and_max_of_every_layout_in_one_pass(dtype):
    from pbrdf_cl.compute import pointwise as api
    rng = np.random.default_rng(4)
    values = rng.uniform(0.1, 1, (300, 1001)).astype(dtype)  # 4.6 blocks of CHECK_BLOCK
    assert values.size > 4 * api.CHECK_BLOCK
    for name, a in _layouts(values).items():
        assert api._min_max(a) == (np.min(a), np.max(a)), name
        if a.flags.writeable:
            a[299, 1000] = np.nan  # the last block
            assert all(np.isnan(api._min_max(a))), name
            assert not api._all_finite(a)


@pytest.mark.parametrize("layout", ["contiguous", "transposed", "strided", "broadcast"])
def test_a_bad_value_in_any_block_of_any_layout_is_named_as_before(layout):
    """The one-pass check (blocks of CHECK_BLOCK elements) names the same argument, value and index
    (in the argument's own shape) as reading the whole array would."""
    for (i, j), value, pattern in [((250, 600), 0.0, r"sigma must be > 0, got 0\.0 at index \[{}, 600\]"),
                                   ((120, 7), np.nan, r"sigma must be finite, got nan at index \[{}, 7\]"),
                                   ((299, 1000), -np.inf, r"sigma must be finite, got -inf at index \[{}, 1000\]")]:
        values = np.full((300, 1001), 0.5)
        values[0 if layout == "broadcast" else i, j] = value
        sigma = _layouts(values)[layout]
        row = 0 if layout == "broadcast" else i
        with pytest.raises(ValueError, match=pattern.format(row)):
            pbrdf_cl.aop(40.0, 30.0, 120.0, n=1.6, k=2.1, sigma=sigma, backend="numpy")
        with pytest.raises(ValueError, match=pattern.format(row)):
            pbrdf_cl.compute.pointwise.check_values("sigma", sigma)
