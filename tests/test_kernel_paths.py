"""Kernel paths the everyday sizes never take, on each usable OpenCL device: the 64-bit grid
indices of grids of ``dense.INDEX32_LIMIT`` points or more (forced here by lowering the limit),
bit-identical to the 32-bit ones; and the scalar per-point kernels (``Engine.vectorise = False``)
against the vector ones."""
import numpy as np
import pytest
from test_kernels import f32_tolerance
from test_variants import OBJECTIVE_GRIDS, axis_sets

import pbrdf_cl
from pbrdf_cl.compute import dense as G

from conftest import call, random_inputs


def test_index_limit_is_the_documented_threshold():
    assert G.INDEX32_LIMIT == 2 ** 32 - 2
    assert G._index_type(G.INDEX32_LIMIT - 1) == ("uint", np.uint32)
    assert G._index_type(G.INDEX32_LIMIT) == ("ulong", np.uint64)


@pytest.fixture
def index_types(monkeypatch):
    """The index type of every grid program built (dense.grid_program's ``idx_name``), in order."""
    seen = []
    build = G.grid_program

    def spy(eng, dtype, sizes, idx_name, *args, **kw):
        seen.append(idx_name)
        return build(eng, dtype, sizes, idx_name, *args, **kw)
    monkeypatch.setattr(G, "grid_program", spy)
    return seen


# the shapes of test_variants.py (the same programs, in 32 bits): the row kernels and one point per work-item
SHAPES = axis_sets("out-of-plane")


def _results(eng):
    """Grids (rows and points kernels, DOP and Stokes, both dtypes, in chunks), reductions and
    objectives (every objective kernel; float32: the index arithmetic does not depend on the dtype,
    and each 64-bit program is a build of its own)."""
    out = []
    for axes, fixed in SHAPES:
        for quantity, dtype in (("dop", "float32"), ("stokes", "float64")):
            out.append(G.grid(axes, fixed, quantity, dtype, "smith", engine=eng, memory_budget=6000).values)
        ds = G.reduce_grid(axes, fixed, over=("theta_r", "kd"), quantity="dop", dtype="float32", engine=eng)
        out += [ds[v].values for v in ("min", "mean", "argmin_theta_r", "argmin_kd")]
    rng = np.random.default_rng(3)
    data = dict(theta_i=rng.uniform(10, 70, 9), theta_r=rng.uniform(5, 80, 9), phi=rng.choice([180.0, 120.0], 9))
    data["dop"] = pbrdf_cl.dop(**data, n=1.8, k=1.2, sigma=0.6, kd=0.3, c=-0.4, backend="numpy")
    for grid in OBJECTIVE_GRIDS:
        res = pbrdf_cl.objective(data, grid=grid, dtype="float32", engine=eng, k_best=4, memory_budget=20000)
        out += [res.sse.values, res.best["index"], res.best["sse"]]
    return out


def test_64_bit_indices_give_bit_identical_results(engine, monkeypatch, index_types):
    narrow = _results(engine)
    assert index_types and set(index_types) == {"uint"}
    monkeypatch.setattr(G, "INDEX32_LIMIT", 1)  # every grid is "big": 64-bit indices throughout
    index_types.clear()
    wide = _results(engine)
    assert index_types and set(index_types) == {"ulong"}
    assert len(wide) == len(narrow)
    for i, (a, b) in enumerate(zip(wide, narrow)):
        assert a.dtype == b.dtype, i
        np.testing.assert_array_equal(a, b, err_msg=f"result {i}")


# --------------------------------------------------------------------------------------------
# the scalar per-point kernels

_SCALAR = {}


@pytest.fixture
def scalar(engine):
    """A second engine on ``engine``'s device with the vector kernels off (quantity_points)."""
    key = engine.device.int_ptr
    if key not in _SCALAR:
        _SCALAR[key] = pbrdf_cl.Engine(engine.device)
        _SCALAR[key].vectorise = False
    return _SCALAR[key]


@pytest.mark.parametrize("in_plane", [True, False], ids=["in-plane", "out-of-plane"])
@pytest.mark.parametrize("shadowing", ["paper", "smith"])
def test_scalar_point_kernels_equal_the_vector_ones(engine, scalar, rng, in_plane, shadowing):
    assert engine.vectorise and not scalar.vectorise
    assert engine.checks_domain("dop") and not scalar.checks_domain("dop")
    inp = random_inputs(rng, 3000, in_plane=in_plane)  # with the edge cases of conftest.edge_inputs
    inp32 = {n: v.astype(np.float32).astype(np.float64) for n, v in inp.items()}
    f_ref32 = call(pbrdf_cl.brdf, inp32, shadowing=shadowing, backend="numpy")
    for dtype in ("float64", "float32"):
        d_vec = call(pbrdf_cl.dop, inp, shadowing=shadowing, dtype=dtype, engine=engine)
        d_sca = call(pbrdf_cl.dop, inp, shadowing=shadowing, dtype=dtype, engine=scalar)
        f_vec = call(pbrdf_cl.brdf, inp, shadowing=shadowing, dtype=dtype, engine=engine)
        f_sca = call(pbrdf_cl.brdf, inp, shadowing=shadowing, dtype=dtype, engine=scalar)
        for a in (d_vec, d_sca, f_vec, f_sca):
            assert a.dtype == np.dtype(dtype) and np.all(np.isfinite(a))
        if dtype == "float64":  # both within 1e-12 (DOP) and 1e-11 relative (F00) of the reference
            assert np.max(np.abs(d_sca - d_vec)) <= 2e-12
            np.testing.assert_allclose(f_sca, f_vec, rtol=2e-11, atol=0)
        else:  # both within 2e-5 (DOP) and f32_tolerance (F00) of the reference
            assert np.max(np.abs(d_sca.astype(float) - d_vec)) <= 4e-5
            assert np.all(np.abs(f_sca.astype(float) - f_vec) <= 2 * f32_tolerance(inp32, f_ref32))


@pytest.mark.parametrize("func", [pbrdf_cl.dop, pbrdf_cl.brdf])
def test_scalar_path_relies_on_the_host_checks(scalar, rng, func):
    """Out of the domain the scalar kernels compute whatever they compute: the host's validation
    refuses the inputs first, naming the offender as the vector path does."""
    inp = random_inputs(rng, 50)
    inp["theta_r"][7] = 90.0
    with pytest.raises(ValueError, match=r"theta_r must be in \[0, 90\) degrees, got 90\.0 at index \[7\]"):
        call(func, inp, engine=scalar)


# --------------------------------------------------------------------------------------------
# the DOP of a conductor

@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_the_dop_of_a_conductor_runs_its_own_kernel_with_the_same_values(engine, rng, dtype, monkeypatch):
    """Where kd is one value, 0 (a conductor), the DOP runs the conductor's kernels
    (``dop_conductor_points_vec`` and its broadcast twin), which leave out the shadowing, the
    specular scale and the diffuse term (2 fd / K is 0 there): the same values bit for bit as the
    whole kernel's (kd given as an array of zeros), the reference's, and the same whatever sigma,
    ks and the shadowing."""
    built, kernel = [], type(engine).kernel
    monkeypatch.setattr(type(engine), "kernel", lambda self, name, *a, **k: built.append(name) or kernel(self, name,
                                                                                                       *a, **k))
    inp = random_inputs(rng, 2000)
    m = inp["kd"].size
    zeros = dict(inp, kd=np.zeros(m))
    whole = call(pbrdf_cl.dop, zeros, dtype=dtype, engine=engine)
    assert built[-1] == "dop_points_vec"
    one = dict(inp, kd=0.0)
    fast = call(pbrdf_cl.dop, one, dtype=dtype, engine=engine)
    assert built[-1] == "dop_conductor_points_vec"
    np.testing.assert_array_equal(fast, whole)
    ref = call(pbrdf_cl.dop, zeros, backend="numpy")
    assert np.max(np.abs(fast.astype(float) - ref)) <= (4e-5 if dtype == "float32" else 2e-12)
    other = dict(one, sigma=rng.uniform(0.05, 1.0, m), ks=rng.uniform(0.1, 2, m))
    for shadowing in ("paper", "smith", "none"):
        np.testing.assert_array_equal(call(pbrdf_cl.dop, other, dtype=dtype, engine=engine, shadowing=shadowing), fast)
    # the broadcast twin (inputs read through their index rules): theta_r along a second axis
    ti, tr = inp["theta_i"][:50], inp["theta_r"][:40]
    kw = dict(n=1.5, k=2.125, sigma=0.3, ks=1.0, c=0.0, dtype=dtype, engine=engine)
    twin = pbrdf_cl.dop(ti[:, None], tr[None, :], 180.0, kd=0.0, **kw)
    assert built[-1] == "dop_conductor_bcast_points_vec"
    np.testing.assert_array_equal(twin, pbrdf_cl.dop(ti[:, None], tr[None, :], 180.0, kd=np.zeros((50, 40)), **kw))
    with pytest.raises(ValueError, match="sigma"):  # its inputs are checked as the whole kernel's
        call(pbrdf_cl.dop, dict(one, sigma=np.where(np.arange(m) == 5, -1.0, 0.3)), dtype=dtype, engine=engine)
