"""OpenCL kernels against the float64 reference on thousands of random valid inputs, on every
usable OpenCL device present (the ``each_device`` fixture of conftest.py)."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.model import reference

from conftest import call, edge_inputs, random_inputs

pytestmark = pytest.mark.usefixtures("each_device")

SHADOWINGS = ["paper", "smith", "none"]


@pytest.mark.parametrize("in_plane", [True, False], ids=["in-plane", "out-of-plane"])
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_dop_kernel_matches_reference(rng, shadowing, in_plane):
    inp = random_inputs(rng, 5000, in_plane=in_plane)
    want = call(pbrdf_cl.dop, inp, shadowing=shadowing, backend="numpy")
    d64 = call(pbrdf_cl.dop, inp, shadowing=shadowing, dtype="float64")
    d32 = call(pbrdf_cl.dop, inp, shadowing=shadowing, dtype="float32")
    assert d64.dtype == np.float64 and d32.dtype == np.float32
    assert np.max(np.abs(d64 - want)) <= 1e-12
    assert np.max(np.abs(d32.astype(np.float64) - want)) <= 2e-5


def f32_tolerance(inp, value):
    """Allowed |float32 - float64| for F00 and Mueller elements of size ``value``, evaluated at the
    float32-rounded inputs: 1e-5 relative, growing with the exponent e = tan^2 a / (2 sigma^2) of
    the specular term (exp(-e) turns an absolute float32 error in e into a relative one), and
    float32's underflow (1e-36) for values it cannot represent."""
    g = reference.geometry(inp["theta_i"], inp["theta_r"], inp["phi"])
    e = g.tan2a / (2 * inp["sigma"] ** 2)
    return 1e-5 * (1 + e) * np.abs(value) + 1e-36


@pytest.mark.parametrize("in_plane", [True, False], ids=["in-plane", "out-of-plane"])
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_brdf_and_mueller_kernels_match_reference(rng, shadowing, in_plane):
    inp = random_inputs(rng, 3000, in_plane=in_plane)
    f_ref = call(pbrdf_cl.brdf, inp, shadowing=shadowing, backend="numpy")
    m_ref = call(pbrdf_cl.mueller, inp, shadowing=shadowing, backend="numpy")
    np.testing.assert_allclose(call(pbrdf_cl.brdf, inp, shadowing=shadowing), f_ref, rtol=1e-11, atol=0)
    m64 = call(pbrdf_cl.mueller, inp, shadowing=shadowing)
    scale = m_ref[..., :1, :1]  # elements relative to F00
    assert np.all(np.abs(m64 - m_ref) <= 1e-11 * scale)
    # float32 against the reference at the float32-rounded inputs: the kernel's own arithmetic
    inp32 = {name: v.astype(np.float32).astype(np.float64) for name, v in inp.items()}
    f_ref32 = call(pbrdf_cl.brdf, inp32, shadowing=shadowing, backend="numpy")
    f32 = call(pbrdf_cl.brdf, inp, shadowing=shadowing, dtype="float32")
    assert np.all(np.abs(f32 - f_ref32) <= f32_tolerance(inp32, f_ref32))
    m_ref32 = call(pbrdf_cl.mueller, inp32, shadowing=shadowing, backend="numpy")
    m32 = call(pbrdf_cl.mueller, inp, shadowing=shadowing, dtype="float32")
    tol = f32_tolerance(inp32, m_ref32[..., 0, 0])[..., None, None]
    assert np.all(np.abs(m32 - m_ref32) <= tol)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_edge_inputs_are_finite(dtype, shadowing):
    inp = edge_inputs()
    for func in (pbrdf_cl.dop, pbrdf_cl.brdf, pbrdf_cl.mueller):
        out = call(func, inp, shadowing=shadowing, dtype=dtype)
        assert np.all(np.isfinite(out))
    d = call(pbrdf_cl.dop, inp, shadowing=shadowing, dtype=dtype)
    assert np.all((d >= 0) & (d <= 1))
    # alpha = 0 with a tiny sigma: the specular peak dominates the diffuse term
    assert d[5] == pytest.approx(call(pbrdf_cl.dop, {**inp, "kd": np.zeros(16)}, dtype=dtype)[5], rel=1e-4)


def test_extreme_sigma_dop_is_finite_and_brdf_overflow_is_reported():
    kw = dict(n=1.6, k=2.1, kd=0.1, c=-0.3)
    d = pbrdf_cl.dop([40, 40], [40, 50], 180, sigma=1e-30, dtype="float32", **kw)
    assert np.all(np.isfinite(d)) and d[1] == 0.0
    assert d[0] == pytest.approx(pbrdf_cl.dop(40, 40, 180, sigma=0.5, n=1.6, k=2.1, dtype="float32"))
    with pytest.raises(FloatingPointError, match="float32"):
        pbrdf_cl.brdf(40, 40, 180, sigma=1e-30, dtype="float32", **kw)
    assert np.isfinite(pbrdf_cl.brdf(40, 40, 180, sigma=1e-30, dtype="float64", **kw))


def test_broadcasting_and_scalars(rng):
    ti = np.array([20.0, 40.0, 60.0])[:, None]
    tr = np.linspace(0, 85, 7)[None, :]
    sig = np.array([0.2, 0.5, 0.8])[:, None]
    out = pbrdf_cl.dop(ti, tr, 150.0, n=1.6, k=2.1, sigma=sig, kd=0.2, c=-0.3)
    assert out.shape == (3, 7)
    want = pbrdf_cl.dop(ti, tr, 150.0, n=1.6, k=2.1, sigma=sig, kd=0.2, c=-0.3, backend="numpy")
    assert np.max(np.abs(out - want)) <= 1e-12
    scalar = pbrdf_cl.dop(40.0, 45.0, n=1.6, k=2.1, sigma=0.5)
    assert np.ndim(scalar) == 0
    m = pbrdf_cl.mueller(ti, tr, n=1.6, k=2.1, sigma=0.5)
    assert m.shape == (3, 7, 4, 4)
    assert pbrdf_cl.dop(np.zeros((0,)), 10.0, n=1.6, k=2.1, sigma=0.5).shape == (0,)


def test_launches_larger_than_one_chunk(monkeypatch, rng):
    from pbrdf_cl.device import transfers
    inp = random_inputs(rng, 3000)
    whole = call(pbrdf_cl.dop, inp)
    monkeypatch.setattr(transfers, "LAUNCH_POINTS", 1000)
    np.testing.assert_array_equal(call(pbrdf_cl.dop, inp), whole)
    m = call(pbrdf_cl.mueller, inp)
    monkeypatch.setattr(transfers, "LAUNCH_POINTS", 1 << 22)
    np.testing.assert_array_equal(call(pbrdf_cl.mueller, inp), m)
    # a last chunk of a single point still gets whole vectors of its full-array inputs
    monkeypatch.setattr(transfers, "LAUNCH_POINTS", 32)
    few = {name: v[:33] for name, v in inp.items()}
    for dtype, tol in (("float64", 1e-12), ("float32", 2e-5)):
        got = call(pbrdf_cl.dop, few, dtype=dtype)
        assert np.max(np.abs(got - call(pbrdf_cl.dop, few, backend="numpy"))) <= tol


def test_explicit_engine_and_device_choice(monkeypatch, each_device):
    dev = each_device.device
    found = pbrdf_cl.list_devices()
    ip, idev = next((p, i) for p, i, _, d in found if d.int_ptr == dev.int_ptr)
    e = pbrdf_cl.Engine(f"{ip}:{idev}")
    assert e.device.int_ptr == dev.int_ptr
    key = ("quantity_points", "float32", "paper", "dop")
    assert e.kernel(*key) is e.kernel(*key)
    d = pbrdf_cl.dop(40, 45, n=1.6, k=2.1, sigma=0.5, engine=e)
    assert d == pytest.approx(pbrdf_cl.dop(40, 45, n=1.6, k=2.1, sigma=0.5, backend="numpy"), abs=1e-12)
    by_name = pbrdf_cl.Engine(dev.name.strip())  # a name substring picks the first device of that name
    assert dev.name.strip() in by_name.device.name
    monkeypatch.setenv("PYOPENCL_CTX", f"{ip}:{idev}")
    assert pbrdf_cl.select_device().int_ptr == dev.int_ptr
    monkeypatch.setenv("PYOPENCL_CTX", "no-such-device-xyz")
    with pytest.raises(ValueError, match="PYOPENCL_CTX"):
        pbrdf_cl.select_device()
    monkeypatch.delenv("PYOPENCL_CTX")
    assert "oclgrind" not in pbrdf_cl.select_device().platform.name.lower()
    with pytest.raises(ValueError, match="device"):
        pbrdf_cl.Engine("99:0")
