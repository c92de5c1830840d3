"""The registry of quantities (pbrdf_cl.quantities) and the two quantities added through it: the AoP
and the Stokes vector, on every path, against the Mueller matrix and NIST SCATMECH."""
import re

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import cli, quantities
from pbrdf_cl.analysis import maps
from pbrdf_cl.analysis.sweeps import SpecError, SweepSpec
from pbrdf_cl.device.engine import kernel_dir
from pbrdf_cl.model import reference
from pbrdf_cl.plots import maps as map_plots

from conftest import call, random_inputs, requires_opencl

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
BACKENDS = ["numpy", pytest.param("opencl", marks=requires_opencl)]


def test_every_registered_quantity_has_its_physics_in_both_files():
    header = (kernel_dir() / "pbrdf.h").read_text()
    for q in quantities.REGISTRY.values():
        assert "points" in q.paths
        assert re.search(rf"inline void pb_point_{q.name}\(", header), q.name
        assert callable(getattr(reference, f"point_{q.name}")), q.name
        if "grid" in q.paths:
            assert re.search(rf"inline real pb_grid_{q.name}\(", header), q.name
            assert callable(getattr(reference, f"grid_{q.name}")), q.name
        for path in quantities.PATHS:
            assert (path in q.paths) != (path in q.refused) or path == "objective", (q.name, path)


def test_names_aliases_and_refusals():
    assert quantities.canonical("f00") == "brdf"
    assert quantities.canonical("DOP") == quantities.canonical(" Dop") == "dop"
    assert quantities.names("objective") == ("dop",)
    assert set(quantities.names("grid")) == {"dop", "brdf", "aop", "stokes"}
    with pytest.raises(ValueError,
                       match=r"^quantity: unknown quantity 'dolp' \(did you mean 'dop'\?\); valid names are dop, brdf"):
        quantities.get("dolp")
    with pytest.raises(ValueError, match=r"'aop' is not available for reduce: an angle.*available there: dop, brdf$"):
        quantities.get("aop", "reduce")


def test_an_unknown_quantity_is_an_error_on_every_path(tmp_path, capsys):
    axes, fixed = dict(theta_r=np.linspace(0, 80, 5)), dict(theta_i=40, **STEEL)
    for call_ in (lambda: pbrdf_cl.evaluate("dolp", 40, 30, **STEEL),
                  lambda: pbrdf_cl.grid(axes, fixed, quantity="dolp"),
                  lambda: pbrdf_cl.reduce_grid(axes, fixed, over="theta_r", quantity="dolp"),
                  lambda: maps.make_map(("theta_r", np.linspace(0, 80, 5)), ("n", np.linspace(1, 2, 4)),
                                        dict(theta_i=40, k=2.1, sigma=0.5), quantity="dolp")):
        with pytest.raises(ValueError, match="unknown quantity 'dolp'"):
            call_()
    with pytest.raises(SpecError, match="quantity: unknown quantity 'dolp'"):
        SweepSpec(dict(axes=dict(theta_r=[0.0, 10.0]), fixed=fixed, quantity="dolp"))
    with pytest.raises(SystemExit) as exc:
        cli.main(["eval", "--theta-i", "40", "--theta-r", "30", "--n", "1.6", "--k", "2", "--sigma", "0.5",
                  "--quantity", "dolp"])
    assert exc.value.code == 2 and "invalid choice: 'dolp'" in capsys.readouterr().err


def test_unsupported_paths_say_why():
    axes, fixed = dict(theta_r=np.linspace(0, 80, 5), sigma=[0.2, 0.4]), dict(theta_i=40, n=1.6, k=2.1)
    with pytest.raises(ValueError, match="'aop' is not available for reduce: an angle"):
        pbrdf_cl.reduce_grid(axes, fixed, over="sigma", quantity="aop")
    with pytest.raises(ValueError, match="'stokes' is not available for reduce: a vector per point"):
        pbrdf_cl.reduce_grid(axes, fixed, over="sigma", quantity="stokes")
    with pytest.raises(ValueError, match="'mueller' is not available for grid: a 4x4 matrix"):
        pbrdf_cl.grid(axes, fixed, quantity="mueller")
    with pytest.raises(ValueError, match="'stokes' is not available for map"):
        maps.make_map(("theta_r", np.linspace(0, 80, 5)), ("n", np.linspace(1, 2, 4)),
                      dict(theta_i=40, k=2.1, sigma=0.5), quantity="stokes")


@pytest.mark.parametrize("dtype,tol", [("float64", 1e-12), ("float32", 2e-5)])
def test_stokes_is_the_first_column_of_the_mueller_matrix(rng, each_device, dtype, tol):
    """On each device and in the reference: S = F[:, 0], S3 = 0, DOP = |S1, S2| / S0, S0 = F00."""
    inp = random_inputs(rng, 3000)
    for backend in ("auto", "numpy"):
        s = call(pbrdf_cl.stokes, inp, dtype=dtype, backend=backend)
        m = call(pbrdf_cl.mueller, inp, dtype=dtype, backend=backend)
        assert s.shape == (inp["n"].size, 4) and s.dtype == np.dtype(dtype)
        scale = np.abs(m[:, 0, 0])[:, None]
        assert np.all(np.abs(s - m[:, :, 0]) <= tol * scale)
        assert np.all(s[:, 3] == 0)
        np.testing.assert_allclose(s[:, 0], call(pbrdf_cl.brdf, inp, dtype=dtype, backend=backend), rtol=tol)
    ref = call(pbrdf_cl.stokes, inp, backend="numpy")
    lit = ref[:, 0] > 0  # (S0 underflows to 0 at a few edge points, where the DOP is a ratio of tables)
    assert lit.sum() > 2900
    np.testing.assert_allclose(np.hypot(ref[lit, 1], ref[lit, 2]) / ref[lit, 0],
                               call(pbrdf_cl.dop, inp, backend="numpy")[lit], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_aop_matches_scatmech_out_of_plane(backend):
    """float64 AoP = atan2(M20, M10) / 2 of SCATMECH's psps Mueller matrix, to 1e-9 degrees, where
    its DOP > 1e-3 (AoP is undefined at DOP = 0).  Setup as in test_scatmech.py."""
    scatmech = pytest.importorskip("pySCATMECH.brdf")
    rng = np.random.default_rng(11)
    model = scatmech.BRDF_Model("Facet_BRDF_Model")
    rows = []
    while len(rows) < 200:
        ti, tr = rng.uniform(1, 85, 2)
        phi, n, k, sigma = rng.uniform(0, 360), rng.uniform(1.05, 4), rng.uniform(0, 8), rng.uniform(0.1, 0.8)
        if reference.geometry(ti, tr, phi).sb >= np.sin(np.radians(5)):
            rows.append((ti, tr, phi, n, k, sigma))
    ti, tr, phi, n, k, sigma = np.array(rows).T
    ours = pbrdf_cl.aop(ti, tr, phi, n=n, k=k, sigma=sigma, shadowing="none", backend=backend)
    compared = 0
    for i in range(len(rows)):
        model.setParameters({"lambda": 0.5, "substrate": f"({float(n[i])!r},{float(k[i])!r})",
                             "sdf": "Gaussian_Slope_Distribution_Function",
                             "sdf.s": repr(float(np.sqrt(2) * sigma[i]))})
        M = np.array(model.MuellerBRDF(np.radians(ti[i]), np.radians(tr[i]), np.radians(180 - phi[i]), 0, "psps"))
        if np.hypot(M[1, 0], M[2, 0]) <= 1e-3 * M[0, 0]:
            continue
        theirs = 0.5 * np.degrees(np.arctan2(M[2, 0], M[1, 0]))
        assert abs(quantities.wrap(ours[i] - theirs, 180.0)) <= 1e-9, (rows[i], ours[i], theirs)
        compared += 1
    assert compared > 150


def test_aop_conventions(rng, each_device):
    inp = random_inputs(rng, 4000)
    for dtype in ("float64", "float32"):
        a = call(pbrdf_cl.aop, inp, dtype=dtype)
        ok = ~np.isnan(a)
        assert np.all((a[ok] > -90) & (a[ok] <= 90)), dtype
    # in plane, Rs > Rp: polarised along s, AoP 0 (not -0)
    a = pbrdf_cl.aop(40, np.linspace(1, 85, 30), 180.0, **STEEL)
    assert np.all(a == 0) and not np.signbit(a).any()
    # undefined where the DOP is 0: the facet at normal incidence (b = 0); NaN, not an error
    assert np.isnan(pbrdf_cl.aop(0.0, 0.0, 180.0, n=1.6, k=2.1, sigma=0.3))
    assert float(pbrdf_cl.dop(0.0, 0.0, 180.0, n=1.6, k=2.1, sigma=0.3)) == 0.0
    # the diffuse term is unpolarised: the AoP does not depend on kd, c
    base = call(pbrdf_cl.aop, {**inp, "kd": np.zeros_like(inp["kd"])}, backend="numpy")
    other = call(pbrdf_cl.aop, inp, backend="numpy")
    ok = ~np.isnan(base) & ~np.isnan(other)
    assert ok.sum() > 3500
    np.testing.assert_allclose(other[ok], base[ok], atol=1e-9)
    # float32 against float64 where the DOP is not tiny
    dop = call(pbrdf_cl.dop, inp, backend="numpy")
    far = dop > 1e-2
    diff = quantities.wrap(call(pbrdf_cl.aop, inp, dtype="float32").astype(float) - call(pbrdf_cl.aop, inp), 180.0)
    assert np.abs(diff[far]).max() <= 2e-3


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_grids_of_aop_and_stokes_equal_the_points(backend, dtype):
    axes = dict(theta_i=[20.0, 55.0], theta_r=np.linspace(0, 85, 18), phi=[0.0, 60.0, 150.0, 180.0],
                sigma=[0.1, 0.3, 0.6], kd=np.linspace(0, 1, 20))
    fixed = dict(n=1.6, k=2.1, c=-0.3)
    mesh = dict(zip(axes, np.meshgrid(*axes.values(), indexing="ij")))
    kw = dict(dtype=dtype, backend=backend)
    tol = 1e-12 if dtype == "float64" else 3e-5
    s = pbrdf_cl.grid(axes, fixed, quantity="stokes", **kw)
    assert s.dims == tuple(axes) + ("stokes",) and list(s["stokes"].values) == ["S0", "S1", "S2", "S3"]
    assert s.attrs["units"] == "1/sr" and s.dtype == np.dtype(dtype)
    want = pbrdf_cl.stokes(**mesh, **fixed, **kw)
    scale = np.abs(want[..., :1])
    assert np.all(np.abs(s.values - want) <= tol * scale)
    a = pbrdf_cl.grid(axes, fixed, quantity="aop", **kw)
    assert a.attrs["units"] == "deg"
    want = pbrdf_cl.aop(**mesh, **fixed, **kw)
    np.testing.assert_array_equal(np.isnan(a.values), np.isnan(want))
    assert np.nanmax(np.abs(quantities.wrap(a.values - want, 180.0))) <= (1e-9 if dtype == "float64" else 2e-3)
    # chunked (a small memory budget) writes each chunk into its slice, components included
    np.testing.assert_array_equal(pbrdf_cl.grid(axes, fixed, quantity="stokes", memory_budget=20000, **kw).values,
                                  s.values)
    f = pbrdf_cl.grid(axes, fixed, quantity="f00", **kw)
    assert f.name == "brdf"
    np.testing.assert_allclose(f.values, s.values[..., 0], rtol=tol)  # S0 is F00


def test_aop_map_and_sweep(tmp_path):
    x, y = ("theta_r", np.linspace(0, 85, 30)), ("phi", np.linspace(0, 360, 25))
    fixed = dict(theta_i=40, **STEEL)
    ds = maps.make_map(x, y, fixed, quantity="aop", derivative="phi")
    assert ds.attrs["quantity"] == "aop"
    # the derivative of an angle is taken of its differences wrapped into one period: no +-180 jumps
    d = ds["daop_dphi"].values
    h = 1e-3
    tr, ph = np.meshgrid(x[1], y[1])
    fd = quantities.wrap(pbrdf_cl.aop(40, tr, ph + h, **STEEL) - pbrdf_cl.aop(40, tr, ph - h, **STEEL), 180.0) / (2 * h)
    ok = np.isfinite(fd)
    np.testing.assert_array_equal(np.isfinite(d), ok)
    np.testing.assert_allclose(d[ok], fd[ok], rtol=1e-4, atol=1e-6 * np.abs(fd[ok]).max())
    map_plots.plot_map(ds, tmp_path / "aop.png")
    assert (tmp_path / "aop.png").stat().st_size > 10000
    spec = SweepSpec(dict(axes=dict(theta_r=list(np.linspace(0, 85, 18)), phi=[0.0, 90.0]), fixed=fixed,
                          quantity="aop", dtype="float64", chunks={"points": 9}))
    pbrdf_cl.sweep(spec, tmp_path / "s.zarr", progress=False)
    got = xr.open_zarr(tmp_path / "s.zarr")["aop"]
    assert got.attrs["units"] == "deg"
    np.testing.assert_array_equal(got.values, pbrdf_cl.grid(spec.axes, spec.fixed, quantity="aop",
                                                            dtype="float64").values)


def test_cli_eval_aop_and_stokes(capsys):
    args = ["eval", "--theta-i", "40", "--theta-r", "45", "--phi", "130", "--n", "1.6", "--k", "2.139",
            "--sigma", "0.5", "--ks", "0.9", "--kd", "0.15", "--c", "-0.3", "--backend", "numpy"]
    assert cli.main(args + ["--quantity", "aop"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("aop (deg)")
    assert float(out[-1].split()[-1]) == pytest.approx(float(pbrdf_cl.aop(40, 45, 130, **STEEL)), abs=1e-6)
    assert cli.main(args + ["--quantity", "stokes"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "stokes (S0 S1 S2 S3) (1/sr)" in out[0]
    np.testing.assert_allclose([float(v) for v in out[-1].split()[-4:]], pbrdf_cl.stokes(40, 45, 130, **STEEL),
                               rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_diffuse_term_enters_m00_alone_out_of_plane(rng, backend):
    """F(kd) - F(0) = fd e00 with fd = kd / pi (cos ti cos tr)^c computed here from its definition
    (eq. 15), out of plane; the Stokes vector and the AoP change accordingly (S0 only; AoP not at all)."""
    inp = random_inputs(rng, 500)
    inp["kd"] = rng.uniform(0.05, 3, inp["n"].size)
    ti, tr = np.radians(inp["theta_i"]), np.radians(inp["theta_r"])
    fd = inp["kd"] / np.pi * (np.cos(ti) * np.cos(tr)) ** inp["c"]
    m1 = call(pbrdf_cl.mueller, inp, backend=backend)
    m0 = call(pbrdf_cl.mueller, {**inp, "kd": np.zeros_like(inp["kd"])}, backend=backend)
    diff = m1 - m0
    np.testing.assert_allclose(diff[:, 0, 0], fd, rtol=1e-9)
    diff[:, 0, 0] = 0
    assert np.all(np.abs(diff) <= 1e-12 * np.abs(m1[:, :1, :1]))
    s1, s0 = call(pbrdf_cl.stokes, inp, backend=backend), call(pbrdf_cl.stokes, {**inp, "kd": 0 * inp["kd"]},
                                                                backend=backend)
    np.testing.assert_allclose(s1[:, 0] - s0[:, 0], fd, rtol=1e-9)
    np.testing.assert_array_equal(s1[:, 1:], s0[:, 1:])
