"""The float64 reference against SPEC's check values, the complex Fresnel equations,
an independent Jones-matrix construction of the Mueller matrix, and physics properties."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.model import reference as ref

from conftest import call, random_inputs, requires_opencl

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
CHECK = [  # theta_i, theta_r, paper, smith, none (SPEC)
    (30, 20, 0.051841, 0.051840, 0.051841),
    (40, 45, 0.167590, 0.167219, 0.167521),
    (50, 65, 0.337599, 0.332051, 0.340661),
]


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=requires_opencl)])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_spec_check_values(backend, dtype):
    # SPEC rounds to 6 decimals (+-5e-7); float32 adds its own rounding (eps 6e-8, times ~10 steps)
    tol = 5e-7 if dtype == "float64" else 5e-7 + 1e-6
    for ti, tr, *expected in CHECK:
        for shadowing, want in zip(("paper", "smith", "none"), expected):
            got = pbrdf_cl.dop(ti, tr, 180, shadowing=shadowing, backend=backend, dtype=dtype, **STEEL)
            assert abs(float(got) - want) <= tol, (ti, tr, shadowing, got, want)
    f00 = pbrdf_cl.brdf(40, 45, backend=backend, dtype=dtype, **STEEL)
    m = pbrdf_cl.mueller(40, 45, backend=backend, dtype=dtype, **STEEL)
    assert float(f00) == pytest.approx(1.733459e-01, abs=tol)
    assert float(m[0, 0]) == pytest.approx(float(f00), rel=1e-6)
    assert float(m[1, 0]) == pytest.approx(2.905113e-02, abs=5e-9 if dtype == "float64" else 1e-7)


def complex_fresnel(n, k, b):
    N = n + 1j * k
    w = np.sqrt(N ** 2 - np.sin(b) ** 2)
    cb = np.cos(b)
    return (cb - w) / (cb + w), (N ** 2 * cb - w) / (N ** 2 * cb + w)


def test_fresnel_matches_complex_fresnel(rng):
    size = 20000
    n = rng.uniform(0.1, 6, size)
    k = np.where(rng.random(size) < 0.1, 0.0, rng.uniform(0, 12, size))
    b = rng.uniform(0, np.radians(89.95), size)
    f = ref.fresnel(n, k, np.cos(b), np.sin(b))
    rs, rp = complex_fresnel(n, k, b)
    x = rs * np.conj(rp)
    np.testing.assert_allclose(f.Rs, abs(rs) ** 2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(f.Rp, abs(rp) ** 2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(f.diff, abs(rs) ** 2 - abs(rp) ** 2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(f.re_x, x.real, rtol=0, atol=1e-14)
    np.testing.assert_allclose(f.im_x, x.imag, rtol=0, atol=1e-14)
    assert np.all(f.diff >= 0)


def test_geometry_matches_spec_forms(rng):
    ti, tr, phi = rng.uniform(0, 89.9, 5000), rng.uniform(0, 89.9, 5000), rng.uniform(-360, 720, 5000)
    g = ref.geometry(ti, tr, phi)
    ti, tr, phi = np.radians(ti), np.radians(tr), np.radians(phi)
    cos2b = np.cos(ti) * np.cos(tr) + np.sin(ti) * np.sin(tr) * np.cos(phi)
    np.testing.assert_allclose(g.cb, np.sqrt((1 + cos2b) / 2), atol=1e-12)
    np.testing.assert_allclose(g.sb, np.sqrt((1 - cos2b) / 2), atol=1e-12)
    cos_a = (np.cos(ti) + np.cos(tr)) / (2 * g.cb)
    np.testing.assert_allclose(g.tan2a, 1 / cos_a ** 2 - 1, rtol=1e-9, atol=1e-12)
    # in plane: b = (ti + tr)/2, a = |ti - tr|/2
    g = ref.geometry(np.degrees(ti), np.degrees(tr), 180.0)
    np.testing.assert_allclose(g.sb, np.sin((ti + tr) / 2), atol=1e-15)
    np.testing.assert_allclose(g.tan2a, np.tan((ti - tr) / 2) ** 2, rtol=1e-12, atol=1e-15)


def test_sincosd_is_exact_at_quadrants_and_accurate_near_them():
    x = np.array([0.0, 90.0, 180.0, 270.0, -90.0, 360.0, 720.0, 89.9, 179.9, -0.1])
    s, c = ref.sincosd(x)
    np.testing.assert_array_equal(s[:7], [0, 1, 0, -1, -1, 0, 0])
    np.testing.assert_array_equal(c[:7], [1, 0, -1, 0, 0, 1, 1])
    np.testing.assert_allclose(s, np.sin(np.radians(x)), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(c[7:], np.sin(np.radians(90 - x[7:])), rtol=1e-14)


def test_shadowing_variants(rng):
    theta = np.radians(rng.uniform(0.1, 89.9, 2000))
    sigma = rng.uniform(0.05, 1, 2000)
    from scipy.special import erfc
    a = 1 / (np.sqrt(2) * sigma * np.tan(theta))
    smith = np.exp(-a ** 2) / (2 * np.sqrt(np.pi) * a) - erfc(a) / 2
    g = 1 / (sigma ** 2 * np.tan(theta) ** 2)
    paper = np.exp(-g) / (2 * np.sqrt(np.pi) * g) - erfc(np.sqrt(g)) / 2
    np.testing.assert_allclose(ref.shadow_S(np.cos(theta), np.sin(theta), sigma, ref.SHADOW_SMITH), smith,
                               rtol=1e-10, atol=1e-30)
    np.testing.assert_allclose(ref.shadow_S(np.cos(theta), np.sin(theta), sigma, ref.SHADOW_PAPER), paper,
                               rtol=1e-10, atol=1e-30)
    assert ref.shadow_S(1.0, 0.0, 0.5, ref.SHADOW_PAPER) == 0.0
    assert ref.shadow_S(1.0, 0.0, 0.5, ref.SHADOW_SMITH) == 0.0
    # the printed form is not the Smith function: slightly negative at moderate angles (SPEC)
    assert ref.shadow_S(np.cos(0.5), np.sin(0.5), 0.5, ref.SHADOW_PAPER) < 0


def jones_mueller(ti, tr, phi, n, k):
    """Mueller matrix of the facet reflection built from scratch: vectors, cross products,
    complex Fresnel and Stokes definitions (SPEC's psps recipe), independent of reference.py."""
    wi = np.array([np.sin(ti) * np.cos(phi), np.sin(ti) * np.sin(phi), np.cos(ti)])
    wr = np.array([np.sin(tr), 0.0, np.cos(tr)])
    z = np.array([0.0, 0.0, 1.0])
    kin, kout = -wi, wr
    h = (wi + wr) / np.linalg.norm(wi + wr)
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    s_in = unit(np.cross(kin, z))
    p_in = np.cross(kin, s_in)
    s_out = unit(np.cross(kout, z))
    p_out = np.cross(kout, s_out)
    s_f = unit(np.cross(kin, h))
    pf_in = np.cross(kin, s_f)
    pf_out = np.cross(kout, s_f)
    b = np.arccos(np.clip(wi @ h, -1, 1))
    rs, rp = complex_fresnel(n, k, b)
    B_in = np.array([[s_f @ s_in, s_f @ p_in], [pf_in @ s_in, pf_in @ p_in]])
    B_out = np.array([[s_out @ s_f, s_out @ pf_out], [p_out @ s_f, p_out @ pf_out]])
    J = B_out @ np.diag([rs, rp]) @ B_in
    basis = [np.array([1, 0]), np.array([0, 1]), np.array([1, 1]) / np.sqrt(2), np.array([1, 1j]) / np.sqrt(2)]

    def stokes(E):
        return np.array([abs(E[0]) ** 2 + abs(E[1]) ** 2, abs(E[0]) ** 2 - abs(E[1]) ** 2,
                         2 * (E[0] * np.conj(E[1])).real, -2 * (E[0] * np.conj(E[1])).imag])
    S_in = np.array([stokes(e) for e in basis]).T
    S_out = np.array([stokes(J @ e) for e in basis]).T
    return S_out @ np.linalg.inv(S_in)  # for J = diag(rs, rp): M00 = (Rs + Rp)/2


def test_mueller_matches_independent_jones_construction(rng):
    for _ in range(300):
        ti, tr = np.radians(rng.uniform(1, 89, 2))
        phi = np.radians(rng.uniform(0, 360))
        n, k = rng.uniform(0.5, 5), rng.uniform(0, 10)
        g = ref.geometry(*np.degrees([ti, tr, phi]))
        if g.sb < np.sin(np.radians(2)):
            continue
        f = ref.fresnel(n, k, g.cb, g.sb)
        M = ref.mueller(f, ref.frame_rotations(g, np.degrees(phi)), np.log(1.0), 0.0)
        J = jones_mueller(ti, tr, phi, n, k)
        np.testing.assert_allclose(M, J, atol=1e-12)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=requires_opencl)])
def test_physics_properties(rng, backend):
    inp = random_inputs(rng, 3000)
    kw = dict(backend=backend)
    d = call(pbrdf_cl.dop, inp, **kw)
    assert np.all((d >= 0) & (d <= 1))
    # reciprocity of the BRDF
    swapped = dict(inp, theta_i=inp["theta_r"], theta_r=inp["theta_i"])
    np.testing.assert_allclose(call(pbrdf_cl.brdf, swapped, **kw), call(pbrdf_cl.brdf, inp, **kw), rtol=1e-12)
    # DOP depends on ks, kd only through kd/ks
    scaled = dict(inp, ks=2 * inp["ks"], kd=2 * inp["kd"])
    np.testing.assert_allclose(call(pbrdf_cl.dop, scaled, **kw), d, rtol=0, atol=1e-13)
    # the Mueller matrix's first column gives the same DOP; rotations leave |F10, F20| alone
    m = call(pbrdf_cl.mueller, inp, **kw)
    np.testing.assert_allclose(m[..., 0, 0], call(pbrdf_cl.brdf, inp, **kw), rtol=1e-12)
    ok = m[..., 0, 0] > 1e-280
    dm = np.sqrt(m[ok, 1, 0] ** 2 + m[ok, 2, 0] ** 2 + m[ok, 3, 0] ** 2) / m[ok, 0, 0]
    np.testing.assert_allclose(dm, d[ok], rtol=0, atol=1e-12)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=requires_opencl)])
def test_specular_model_is_ref7_and_independent_of_sigma(rng, backend):
    inp = random_inputs(rng, 2000, in_plane=True)
    inp["kd"] = np.zeros_like(inp["kd"])
    b = np.radians(inp["theta_i"] + inp["theta_r"]) / 2
    rs, rp = complex_fresnel(inp["n"], inp["k"], b)
    Rs, Rp = abs(rs) ** 2, abs(rp) ** 2
    # where hardly anything is reflected (n = 1, k = 0) the DOP is a ratio of rounding errors
    lit = Rs + Rp > 1e-12
    ref7 = (Rs - Rp)[lit] / (Rs + Rp)[lit]
    d = call(pbrdf_cl.dop, inp, backend=backend)
    np.testing.assert_allclose(d[lit], ref7, rtol=0, atol=1e-12)
    assert np.all((d >= 0) & (d <= 1))
    other = dict(inp, sigma=rng.uniform(0.05, 1, inp["sigma"].shape), ks=3 * inp["ks"])
    np.testing.assert_allclose(call(pbrdf_cl.dop, other, backend=backend), d, rtol=0, atol=1e-14)
    spec = pbrdf_cl.dop(inp["theta_i"], inp["theta_r"], 180, n=inp["n"], k=inp["k"], model="specular",
                        backend=backend)
    np.testing.assert_allclose(spec, d, rtol=0, atol=1e-15)


def test_in_plane_mueller_has_block_form(rng):
    inp = random_inputs(rng, 500, in_plane=True)
    m = call(pbrdf_cl.mueller, inp, backend="numpy")
    for i, j in [(0, 2), (0, 3), (1, 2), (1, 3), (2, 0), (2, 1), (3, 0), (3, 1)]:
        assert np.all(np.abs(m[..., i, j]) <= 1e-13 * m[..., 0, 0])
    np.testing.assert_allclose(m[..., 2, 3], -m[..., 3, 2], rtol=1e-14)


def test_dop_falls_with_sigma_like_fig5():
    tr = np.arange(20, 66, 5.0)
    curves = [pbrdf_cl.dop(40, tr, **dict(STEEL, sigma=s), backend="numpy") for s in (0.35, 0.5, 0.65)]
    off = np.abs(tr - 40) >= 10
    assert np.all(curves[0][off] > curves[1][off]) and np.all(curves[1][off] > curves[2][off])


def test_diffuse2_over_K_is_2fd_over_K(rng):
    """The per-point DOP kernels' 2 fd / K in one exponential (pb_diffuse2_over_K) is 2 fd exp(-log K)
    to the rounding of the exponents, 0 where kd = 0, both beyond 1e250 where either overflows; the
    DOP from either is the same to float64 rounding, K underflowing included (a sharp lobe far off
    specular)."""
    x = random_inputs(rng, 20000)
    x["sigma"][:2000] = 0.02  # tan^2 a / (2 sigma^2) beyond 710: K underflows, 1/K is inf
    g = ref.geometry(x["theta_i"], x["theta_r"], x["phi"])
    G = ref.shadowing_factor(g, x["sigma"], 1)
    logK = ref.log_specular_scale(g, x["sigma"], x["ks"], G)
    fd = ref.diffuse(g, x["kd"], x["c"])
    with np.errstate(over="ignore", invalid="ignore"):  # 0 * inf where kd = 0
        want = 2.0 * fd * np.exp(-logK)
    got = ref.diffuse2_over_K(g, x["sigma"], x["ks"], G, x["kd"], x["c"])
    lit = x["kd"] > 0
    assert np.all(got[~lit] == 0) and np.all(got[lit] > 0) and (~lit).sum() > 1000
    finite = lit & (np.abs(logK) < 700) & np.isfinite(got)
    assert finite.sum() > 15000 and (lit & ~finite).sum() > 500
    bound = (np.abs(logK) + np.abs(x["c"] * np.log(g.cti * g.ctr)) + 6) * 4.5e-16
    rel = np.abs(got[finite] / want[finite] - 1)
    assert np.all(rel <= bound[finite]), rel.max()
    either = np.isinf(got) | np.isinf(want)  # 2 fd / K beyond 1e250 where one overflows: DOP < 1e-250
    assert np.all(got[either] > 1e250) and np.all(want[either] > 1e250)
    f = ref.fresnel(x["n"], x["k"], g.cb, g.sb)
    np.testing.assert_allclose(ref.dop_of(f, got), ref.dop(f, logK, fd), rtol=0, atol=1e-15)
