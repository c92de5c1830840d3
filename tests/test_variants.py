"""Every shadowing variant (paper, smith, none) through every dense path against the float64
reference: the grid (DOP, F00, AoP, Stokes), the factor tables, reductions (DOP, F00) and the
objective (grid and points), in float32 and float64, in plane (phi = 180) and out of plane, on
each usable OpenCL device (the ``engine`` fixture) and on the numpy backend; then the user's
entry points with a variant: the fit, a sweep spec's ``shadowing`` key, and the CLI's
``--shadowing``.

Each case also checks that the variants differ there, so that a path which ignored the variant
(or used another one) could not pass."""
import json

import numpy as np
import pytest
from test_kernels import f32_tolerance

import pbrdf_cl
from pbrdf_cl import cli, quantities
from pbrdf_cl.analysis.sweeps import SweepSpec
from pbrdf_cl.compute import dense as G
from pbrdf_cl.fitting.sample import inversion
from pbrdf_cl.io.measurements import read_csv

SHADOWINGS = ["paper", "smith", "none"]
OTHER = {"paper": "smith", "smith": "none", "none": "paper"}  # a variant that differs from each
PLANES = {"in-plane": [180.0], "out-of-plane": [35.0, 125.0, 290.0]}
BASE = dict(n=1.7, k=2.3, ks=0.8)
# kd > 0 throughout (with kd = 0 the DOP does not depend on the shadowing) and sigma where the
# variants differ; ROWS has kd x c = 16 (pbrdf_grid.cl's row kernels), POINTS one point per
# work-item
ROWS = dict(theta_r=np.linspace(0, 88, 9), sigma=np.array([0.3, 0.6, 1.0]), kd=np.array([0.05, 0.3, 1.0, 3.0]),
            c=np.array([-0.9, -0.6, -0.3, 0.0]))
POINTS = dict(theta_i=np.array([25.0, 60.0]), theta_r=np.linspace(5, 85, 7), sigma=np.array([0.25, 0.5, 0.75, 1.0]),
              kd=np.array([0.1, 0.5, 2.0]))


def axis_sets(plane):
    """(axes, fixed) of the two grid shapes, with phi fixed at 180 in plane, an axis out of plane."""
    phi = PLANES[plane]
    out = []
    for axes, fixed in ((ROWS, dict(theta_i=52.0, **BASE)), (POINTS, dict(c=-0.4, **BASE))):
        axes = dict(axes)
        fixed = dict(fixed)
        if len(phi) > 1:
            axes["phi"] = np.array(phi)
        else:
            fixed["phi"] = phi[0]
        out.append((axes, fixed))
    return out


def mesh_inputs(axes, fixed, dtype="float64"):
    """Every canonical input over the grid's mesh (float32-rounded for dtype float32, as the device
    sees them), as float64 arrays of the grid's shape."""
    names = [n for n in G.AXES if n in axes]
    mesh = np.meshgrid(*[np.asarray(axes[n], float) for n in names], indexing="ij")
    inp = {n: np.broadcast_to(float(fixed.get(n, G.DEFAULTS.get(n))), mesh[0].shape) for n in G.AXES if n not in axes}
    inp.update(zip(names, mesh))
    if dtype == "float32":
        inp = {n: np.asarray(v, np.float32).astype(np.float64) for n, v in inp.items()}
    return inp


def reference(quantity, inp, shadowing):
    func = {"dop": pbrdf_cl.dop, "f00": pbrdf_cl.brdf, "aop": pbrdf_cl.aop, "stokes": pbrdf_cl.stokes}[quantity]
    return func(**inp, shadowing=shadowing, backend="numpy")


def tolerance(quantity, dtype, inp, ref):
    """Allowed |value - float64 reference| per point: the tolerances of test_grid.py and
    test_kernels.py (float32 F00: ``f32_tolerance`` at the float32-rounded inputs)."""
    if quantity == "dop":
        return np.full(ref.shape, 1e-12 if dtype == "float64" else 2e-5)
    if dtype == "float64":
        return 1e-11 * np.abs(ref)
    return f32_tolerance(inp, ref)


def backends(engine):
    return [("device", dict(engine=engine)), ("numpy", dict(backend="numpy"))]


# --------------------------------------------------------------------------------------------
# the grid

@pytest.mark.parametrize("plane", list(PLANES))
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_grid_of_every_variant_equals_the_reference(engine, shadowing, plane):
    for axes, fixed in axis_sets(plane):
        for quantity in ("dop", "f00"):
            assert np.max(np.abs(reference(quantity, mesh_inputs(axes, fixed), shadowing)
                                 / reference(quantity, mesh_inputs(axes, fixed), OTHER[shadowing]) - 1)) > 1e-3
            for dtype in ("float64", "float32"):
                inp = mesh_inputs(axes, fixed, dtype)
                ref = reference(quantity, inp, shadowing)
                tol = tolerance(quantity, dtype, inp, ref)
                for where, kw in backends(engine):
                    got = G.grid(axes, fixed, quantity, dtype, shadowing, **kw)
                    assert got.dtype == np.dtype(dtype) and got.shape == ref.shape
                    assert got.attrs["shadowing"] == shadowing
                    bad = np.abs(got.values - ref) > tol
                    assert not bad.any(), (where, quantity, dtype, np.abs(got.values - ref)[bad].max())


@pytest.mark.parametrize("plane", list(PLANES))
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_stokes_and_aop_grids_of_every_variant_equal_the_reference(engine, shadowing, plane):
    axes, fixed = axis_sets(plane)[1]
    for dtype in ("float64", "float32"):
        inp = mesh_inputs(axes, fixed, dtype)
        s_ref = reference("stokes", inp, shadowing)
        a_ref = reference("aop", inp, shadowing)
        scale = np.abs(s_ref[..., :1])  # the components relative to S0
        s_tol = 1e-12 * scale if dtype == "float64" else f32_tolerance(inp, scale[..., 0])[..., None]
        for where, kw in backends(engine):
            s = G.grid(axes, fixed, "stokes", dtype, shadowing, **kw).values
            assert np.all(np.abs(s - s_ref) <= s_tol), (where, dtype)
            a = G.grid(axes, fixed, "aop", dtype, shadowing, **kw).values
            if plane == "in-plane":
                np.testing.assert_array_equal(a, 0.0)  # polarised along s (SPEC)
            a_tol = 1e-9 if dtype == "float64" else 2e-3  # degrees, as in test_quantities.py
            assert np.max(np.abs(quantities.wrap(a - a_ref, 180.0))) <= a_tol, (where, dtype)


# --------------------------------------------------------------------------------------------
# the factor tables

@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_tables_of_every_variant_equal_the_reference_tables(engine, shadowing, dtype):
    """dense.Tables (kernels/pbrdf_tables.cl) entry by entry against the reference's tables
    (dense.NumpyTables, built with reference.py in float64), for in-plane and out-of-plane geometries."""
    ti = np.array([0.0, 30.0, 52.0, 70.0, 85.0, 40.0, 60.0])
    tr = np.array([10.0, 30.0, 20.0, 75.0, 60.0, 45.0, 88.0])
    ph = np.array([180.0, 180.0, 180.0, 180.0, 35.0, 125.0, 290.0])
    v = dict(n=np.array([0.6, 1.7, 4.0]), k=np.array([0.0, 2.3]), sigma=np.array([0.1, 0.45, 1.0]),
             ks=np.array([0.5, 1.2]), kd=np.array([0.0, 0.3, 2.0]), c=np.array([-0.8, 0.0]))
    npdt = np.dtype(np.float32 if dtype == "float32" else np.float64)
    if dtype == "float32":  # the reference at the inputs the device sees
        ti, tr, ph = (a.astype(np.float32).astype(float) for a in (ti, tr, ph))
        v = {n: a.astype(np.float32).astype(float) for n, a in v.items()}
    other = G.NumpyTables(OTHER[shadowing], "dop", ti, tr, ph, v)
    for quantity in ("dop", "stokes"):  # 1/K and fd2 (the DOP), K, fd and the frame (the Stokes vector)
        dev = G.Tables(engine, dtype, shadowing, quantity, ti, tr, ph, v)
        ref = G.NumpyTables(shadowing, quantity, ti, tr, ph, v)

        def read(buf, like):
            return engine.read(buf, np.empty(np.shape(like), npdt)).astype(np.float64)
        rtol = 1e-12 if dtype == "float64" else 1e-5
        for name in ("sum", "diff", "dif"):
            np.testing.assert_allclose(read(getattr(dev, name), getattr(ref, name)), getattr(ref, name),
                                       rtol=rtol, atol=rtol * np.abs(getattr(ref, name)).max(), err_msg=name)
        # the scale exp(+-log K): float32 carries log K's absolute error into a relative one
        g = pbrdf_cl.model.reference.geometry(ti[:, None], tr[:, None], ph[:, None])
        e = g.tan2a / (2 * np.repeat(v["sigma"], v["ks"].size)[None, :] ** 2)
        scale = read(dev.scale, ref.scale)
        if dtype == "float32":  # beyond float32's range (1/K at grazing angles): inf, as the grid expects
            over = ref.scale > np.finfo(np.float32).max
            assert np.all(np.isinf(scale[over]))
            scale, want, e = scale[~over], ref.scale[~over], e[~over]
            assert np.all(np.abs(scale - want) <= rtol * (1 + e) * want + 1e-36)
        else:
            np.testing.assert_allclose(scale, ref.scale, rtol=rtol, atol=0)
        if quantity == "dop":
            assert np.max(np.abs(ref.scale / other.scale - 1)) > 1e-3  # the variants differ here
        else:
            frame = read(dev.frame, np.empty(2 * ti.size)).reshape(-1, 2)
            atol = 1e-12 if dtype == "float64" else 1e-5
            np.testing.assert_allclose(frame[:, 0], ref.C[:, 0], rtol=0, atol=atol)
            np.testing.assert_allclose(frame[:, 1], ref.S[:, 0], rtol=0, atol=atol)
            np.testing.assert_array_equal(frame[:4], [[1.0, 0.0]] * 4)  # in plane: no rotation


# --------------------------------------------------------------------------------------------
# reductions

@pytest.mark.parametrize("plane", list(PLANES))
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_reductions_of_every_variant_equal_the_reference(engine, shadowing, plane):
    """min, mean and argmin of DOP and F00 over (theta_r, kd) against the reference grid: a minimum
    or mean of values each within ``tol`` of the reference is within the maximum (mean) ``tol``;
    the reference at the argmin is within twice the maximum ``tol`` of the reference minimum."""
    axes, fixed = axis_sets(plane)[0]
    over = ("theta_r", "kd")
    names = [n for n in G.AXES if n in axes]
    red = tuple(names.index(n) for n in over)
    kept = [n for n in names if n not in over]

    def flat(a):  # the reduced axes last, as one
        moved = np.moveaxis(a, red, tuple(range(len(names) - len(red), len(names))))
        return moved.reshape(moved.shape[:len(kept)] + (-1,))
    for quantity in ("dop", "f00"):
        for dtype in ("float64", "float32"):
            inp = mesh_inputs(axes, fixed, dtype)
            ref = flat(reference(quantity, inp, shadowing))
            tol = flat(tolerance(quantity, dtype, inp, reference(quantity, inp, shadowing)))
            assert np.max(np.abs(ref.min(axis=-1) - flat(reference(quantity, inp, OTHER[shadowing])).min(axis=-1))
                          / np.abs(ref.min(axis=-1))) > 1e-3
            for where, kw in backends(engine):
                ds = G.reduce_grid(axes, fixed, over=over, quantity=quantity, dtype=dtype, shadowing=shadowing, **kw)
                assert list(ds["min"].dims) == kept and ds.attrs["shadowing"] == shadowing
                assert np.all(np.abs(ds["min"].values - ref.min(axis=-1)) <= tol.max(axis=-1)), (where, quantity, dtype)
                assert np.all(np.abs(ds["mean"].values - ref.mean(axis=-1)) <= tol.mean(axis=-1)), \
                    (where, quantity, dtype)
                ix = np.ravel_multi_index([np.searchsorted(axes[n], ds[f"argmin_{n}"].values) for n in over],
                                          [axes[n].size for n in over])
                at = np.take_along_axis(ref, ix[..., None], axis=-1)[..., 0]
                assert np.all(at - ref.min(axis=-1) <= 2 * tol.max(axis=-1)), (where, quantity, dtype)


# --------------------------------------------------------------------------------------------
# the objective

def measurements(plane, shadowing, m=14):
    rng = np.random.default_rng(17)
    ti, tr = rng.uniform(10, 70, m), rng.uniform(5, 80, m)
    phi = rng.choice(PLANES[plane], m)
    d = pbrdf_cl.dop(ti, tr, phi, n=1.8, k=1.2, sigma=0.6, kd=0.3, c=-0.4, shadowing=shadowing, backend="numpy")
    return dict(theta_i=ti, theta_r=tr, phi=phi, dop=np.clip(d + rng.normal(0, 0.01, m), 0, 1),
                dop_std=rng.uniform(0.005, 0.02, m))


def reference_sse(data, params, shadowing):
    d = pbrdf_cl.dop(data["theta_i"][:, None], data["theta_r"][:, None], data["phi"][:, None], backend="numpy",
                     shadowing=shadowing, **{n: np.asarray(v)[None, :] for n, v in params.items()})
    return (((d - data["dop"][:, None]) / data["dop_std"][:, None]) ** 2).sum(axis=0)


OBJECTIVE_GRIDS = [  # the row kernel (kd x c = 20 per row) and one parameter vector per work-item
    dict(n=np.linspace(1, 3, 4), k=np.linspace(0, 3, 3), sigma=np.array([0.3, 0.6, 0.9]), kd=np.linspace(0, 1, 10),
         c=np.array([-0.6, -0.2])),
    dict(n=np.linspace(1, 3, 5), k=np.linspace(0, 3, 4), sigma=np.array([0.4, 0.8]), kd=0.3, c=-0.4),
]


@pytest.mark.parametrize("plane", list(PLANES))
@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_objective_of_every_variant_equals_the_reference_sse(engine, shadowing, plane):
    data = measurements(plane, shadowing)
    for grid in OBJECTIVE_GRIDS:
        axes = [n for n in G.PARAMETERS if np.ndim(grid.get(n, 0)) > 0]
        mesh = np.meshgrid(*[grid[n] for n in axes], indexing="ij")
        params = {n: np.full(mesh[0].size, float(grid.get(n, 1.0 if n == "ks" else 0.0)))
                  for n in G.PARAMETERS if n not in axes}
        params.update({n: m.ravel() for n, m in zip(axes, mesh)})
        want = reference_sse(data, params, shadowing).reshape(mesh[0].shape)
        assert np.max(np.abs(reference_sse(data, params, OTHER[shadowing]).reshape(mesh[0].shape) / want - 1)) > 1e-2
        for dtype in ("float64", "float32"):
            rtol = 1e-11 if dtype == "float64" else 2e-4
            for where, kw in backends(engine):
                res = pbrdf_cl.objective(data, grid=grid, dtype=dtype, shadowing=shadowing, k_best=3, **kw)
                np.testing.assert_allclose(res.sse.values, want, rtol=rtol, err_msg=f"{where} {dtype}")
                assert res.sse.attrs["shadowing"] == shadowing
                np.testing.assert_array_equal(res.best["index"], np.argsort(want.ravel())[:3])
    # explicit parameter vectors (the objective_points kernel)
    pts = {n: np.asarray(v) for n, v in params.items()}
    want = reference_sse(data, pts, shadowing)
    for dtype in ("float64", "float32"):
        rtol = 1e-11 if dtype == "float64" else 2e-4
        for where, kw in backends(engine):
            res = pbrdf_cl.objective(data, points=pts, dtype=dtype, shadowing=shadowing, **kw)
            np.testing.assert_allclose(res.sse, want, rtol=rtol, err_msg=f"{where} {dtype}")


# --------------------------------------------------------------------------------------------
# the fit, sweeps and the CLI with a variant

TI = np.repeat([30.0, 40.0, 50.0], 10)
TR = np.tile(np.arange(20.0, 66.0, 5.0), 3)
TRUTH = dict(n=1.6, k=2.139, sigma=0.5, kd=0.15 / 0.9, c=-0.3)
SMALL_GRID = dict(n=12, k=16, sigma=8, kd=8, c=6)


@pytest.mark.parametrize("shadowing", SHADOWINGS)
def test_fit_with_each_variant_recovers_the_truth(each_device, shadowing, monkeypatch):
    data = dict(theta_i=TI, theta_r=TR, dop=pbrdf_cl.dop(TI, TR, 180.0, shadowing=shadowing, backend="numpy", **TRUTH))
    used = []  # the grid stage's objective (of one set, dense.objective_sets): on the device, with the fit's variant
    objective = G.objective_sets
    monkeypatch.setattr(G, "objective_sets", lambda *a, **kw: used.append(kw) or objective(*a, **kw))
    r = pbrdf_cl.fit(data, shadowing=shadowing, grid_shape=SMALL_GRID, engine=each_device)
    assert [(kw["shadowing"], kw["engine"]) for kw in used] == [(shadowing, each_device)]
    assert r.shadowing == shadowing and r.sse <= 1e-12
    for name, v in TRUTH.items():
        assert r.x[name] == pytest.approx(v, rel=1e-5, abs=1e-6), name
    # the same data under another variant: no exact fit (the variant reaches the model)
    wrong = pbrdf_cl.fit(data, shadowing=OTHER[shadowing], grid_shape=SMALL_GRID, engine=each_device)
    assert wrong.sse > 1e-8


SWEEP_AXES = dict(theta_i=[25.0, 50.0, 70.0], theta_r="0:85:17", sigma=[0.3, 0.6, 1.0], kd=[0.1, 0.5])
SWEEP_FIXED = dict(n=1.6, k=2.139, ks=0.9, c=-0.3)


@pytest.mark.parametrize("shadowing,quantity", [("smith", "dop"), ("none", "f00"), ("paper", "dop")])
def test_sweep_with_a_shadowing_key_equals_grid_with_it(each_device, tmp_path, shadowing, quantity):
    spec = SweepSpec(dict(axes=SWEEP_AXES, fixed=SWEEP_FIXED, quantity=quantity, shadowing=shadowing,
                          chunks=dict(theta_i=1, theta_r=6)))
    assert spec.shadowing == shadowing and spec.n_chunks > 1
    ds = pbrdf_cl.sweep(spec, tmp_path / "s.zarr", engine=each_device, progress=False).open()
    want = pbrdf_cl.grid(spec.axes, spec.fixed, quantity=quantity, shadowing=shadowing, engine=each_device)
    other = pbrdf_cl.grid(spec.axes, spec.fixed, quantity=quantity, shadowing=OTHER[shadowing], engine=each_device)
    assert np.max(np.abs(want.values - other.values) / np.abs(want.values)) > 1e-3
    got = ds[spec.quantity]
    np.testing.assert_array_equal(got.values, want.values)
    assert ds.attrs["shadowing"] == shadowing and json.loads(ds.attrs["sweep_spec"])["shadowing"] == shadowing
    # a reduction sweep with the key equals reduce_grid with it
    rspec = SweepSpec(dict(axes=SWEEP_AXES, fixed=SWEEP_FIXED, quantity=quantity, shadowing=shadowing,
                           reduce=dict(over=["theta_r", "kd"]), chunks=dict(theta_i=1)))
    red = pbrdf_cl.sweep(rspec, tmp_path / "r.zarr", engine=each_device, progress=False).open()
    rwant = pbrdf_cl.reduce_grid(rspec.axes, rspec.fixed, over=["theta_r", "kd"], quantity=quantity,
                                 shadowing=shadowing, engine=each_device)
    np.testing.assert_array_equal(red["min"].values, rwant["min"].values)
    np.testing.assert_array_equal(red["argmin_theta_r"].values, rwant["argmin_theta_r"].values)


def test_cli_map_with_smith_gives_the_api_numbers(each_device, tmp_path, capsys):
    npz = tmp_path / "m.npz"
    assert cli.main(["map", "--x", "theta_r=0:85@12", "--y", "sigma=0.2:1@5", "--fix", "theta_i=40", "n=1.6",
                     "k=2.139", "ks=0.9", "kd=0.15", "c=-0.3", "--shadowing", "smith", "--out",
                     str(tmp_path / "m.png"), "--npz", str(npz)]) == 0
    saved = np.load(npz)
    assert json.loads(str(saved["attrs"]))["shadowing"] == "smith"
    axes = dict(theta_r=np.linspace(0, 85, 12), sigma=np.linspace(0.2, 1, 5))
    fixed = dict(theta_i=40.0, n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3)
    want = pbrdf_cl.grid(axes, fixed, dtype="float64", shadowing="smith", engine=each_device).values.T  # (y, x)
    np.testing.assert_array_equal(saved["dop"], want)
    paper = pbrdf_cl.grid(axes, fixed, dtype="float64", engine=each_device).values.T
    assert np.max(np.abs(saved["dop"] - paper)) > 1e-3
    np.testing.assert_allclose(saved["dop"], reference("dop", mesh_inputs(axes, fixed), "smith").T, rtol=0, atol=1e-12)


def test_cli_fit_with_none_gives_the_api_numbers(each_device, tmp_path, capsys):
    from pathlib import Path
    csv = Path(__file__).resolve().parent.parent / "examples" / "steel_435nm.csv"
    out = tmp_path / "fit.json"
    assert cli.main(["fit", str(csv), "--shadowing", "none", "--fix", "sigma=0.5", "c=-0.3", "--json", str(out),
                     "--quiet", "--compare"]) == 0
    fits = json.loads(out.read_text())["fits"]
    api = inversion.compare_models(read_csv(csv), shadowing="none", fixed=dict(sigma=0.5, c=-0.3), engine=each_device)
    paper = inversion.fit(read_csv(csv), shadowing="paper", fixed=dict(sigma=0.5, c=-0.3), engine=each_device)
    for model in ("six-param", "specular"):
        got, want = fits[model], api[model]
        assert got["shadowing"] == want.shadowing == "none"
        assert got["x"] == {n: float(v) for n, v in want.x.items()}, model
        assert got["sse"] == want.sse
    assert fits["six-param"]["x"] != {n: float(v) for n, v in paper.x.items()}
