"""Dense grids, reductions and the objective against the float64 reference, on every usable
OpenCL device present (the ``each_device`` fixture of conftest.py)."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.compute import dense as G

pytestmark = pytest.mark.usefixtures("each_device")

FIXED = dict(theta_i=40.0, theta_r=30.0, phi=180.0, n=1.6, k=2.1, sigma=0.4, ks=0.9, kd=0.2, c=-0.3)
RANGES = dict(theta_i=(0, 89), theta_r=(0, 89), phi=(0, 360), n=(0.5, 4), k=(0, 8), sigma=(0.05, 1),
              ks=(0.2, 2), kd=(0, 3), c=(-1, 0))


def reference_grid(axes, fixed, quantity="dop"):
    names = [n for n in G.AXES if n in axes]
    mesh = np.meshgrid(*[np.asarray(axes[n], float) for n in names], indexing="ij")
    kw = {n: fixed.get(n, G.DEFAULTS.get(n)) for n in G.AXES if n not in axes}
    kw.update(zip(names, mesh))
    func = pbrdf_cl.dop if quantity == "dop" else pbrdf_cl.brdf
    return func(kw.pop("theta_i"), kw.pop("theta_r"), kw.pop("phi"), backend="numpy", **kw)


def random_axes(rng, names, sizes):
    axes = {}
    for n, size in zip(names, sizes):
        lo, hi = RANGES[n]
        axes[n] = np.sort(rng.uniform(lo, hi, size))
        while size > 1 and np.any(np.diff(axes[n]) <= 0):
            axes[n] = np.sort(rng.uniform(lo, hi, size))
    return axes, {n: v for n, v in FIXED.items() if n not in names}


# axis sets chosen to hit every kernel path: rows over (kd, c) [level 1], over (sigma, ks, kd, c)
# [level 2], over everything after the geometry [level 3], and one point per work-item
CASES = [
    (("theta_i", "theta_r"), (5, 7)),
    (("theta_r", "sigma"), (9, 6)),
    (("theta_i", "kd", "c"), (9, 6, 5)),
    (("theta_r", "phi", "sigma", "kd"), (4, 3, 5, 4)),
    (("n", "k", "sigma", "ks"), (3, 4, 5, 4)),
    (("theta_i", "theta_r", "phi", "n", "k", "sigma", "ks", "kd", "c"), (2, 3, 2, 2, 3, 2, 2, 3, 2)),
    (("phi",), (40,)),
    (("k", "c"), (3, 17)),
    (("theta_r", "n"), (20, 40)),
]


@pytest.mark.parametrize("names,sizes", CASES, ids=["-".join(c[0]) for c in CASES])
def test_grid_equals_reference(rng, names, sizes):
    axes, fixed = random_axes(rng, names, sizes)
    ref = reference_grid(axes, fixed)
    d64 = G.grid(axes, fixed, dtype="float64")
    assert d64.dims == tuple(n for n in G.AXES if n in names) and d64.shape == ref.shape
    assert np.max(np.abs(d64.values - ref)) <= 1e-12
    d32 = G.grid(axes, fixed, dtype="float32")
    assert d32.dtype == np.float32 and np.max(np.abs(d32.values - ref)) <= 2e-5
    f_ref = reference_grid(axes, fixed, "f00")
    np.testing.assert_allclose(G.grid(axes, fixed, quantity="f00", dtype="float64").values, f_ref, rtol=1e-11)
    for n in names:
        np.testing.assert_array_equal(d64[n].values, axes[n])
        assert d64[n].attrs["units"] == G.UNITS[n]
    assert d64.attrs["quantity"] == "dop" and d64.attrs["shadowing"] == "paper"
    for n, v in fixed.items():
        assert d64.attrs[f"fixed_{n}"] == v


def test_row_levels_are_all_exercised():
    seen = set()
    for names, sizes in CASES:
        s = dict.fromkeys(G.AXES, 1)
        s.update(zip(names, sizes))
        fam = (s["theta_i"] * s["theta_r"] * s["phi"], s["n"] * s["k"], s["sigma"] * s["ks"], s["kd"] * s["c"])
        seen.add(G.row_level(fam[1], fam[2], fam[3], fam[0], 1 << 20)[0])
    assert seen == {0, 1, 2, 3}


def test_chunked_equals_unchunked_exactly(rng):
    axes, fixed = random_axes(rng, ("theta_i", "theta_r", "sigma", "kd", "c"), (7, 9, 5, 6, 4))
    whole = G.grid(axes, fixed, dtype="float32")
    for budget in (4096, 20000, 100003):
        np.testing.assert_array_equal(G.grid(axes, fixed, dtype="float32", memory_budget=budget).values, whole.values)
    np.testing.assert_array_equal(G.grid(axes, fixed, quantity="f00", memory_budget=5000).values,
                                  G.grid(axes, fixed, quantity="f00").values)


def test_grid_larger_than_budget_runs_in_bounded_chunks(monkeypatch):
    axes = dict(theta_i=np.linspace(10, 80, 30), theta_r=np.linspace(0, 85, 100), sigma=np.linspace(0.05, 1, 50),
                kd=np.linspace(0, 1, 40), c=np.linspace(-1, 0, 10))
    plan = G.GridPlan(axes, dict(n=1.6, k=2.1))
    budget = 1 << 20  # 1 MiB against a 240 MB result
    eng = pbrdf_cl.get_default_engine()
    sizes = []
    real_empty = type(eng).empty
    monkeypatch.setattr(type(eng), "empty", lambda self, nbytes: sizes.append(nbytes) or real_empty(self, nbytes))
    done, chunks, probe = 0, 0, {}
    picks = set(np.random.default_rng(0).integers(0, plan.size, 50).tolist())
    for start, block in G.grid_blocks(eng, plan, "dop", "float32", "paper", budget):
        assert start == done and block.nbytes <= budget
        for p in picks:
            if start <= p < start + block.size:
                probe[p] = block[p - start]
        done += block.size
        chunks += 1
    assert done == plan.size and chunks > 200
    assert max(sizes) <= budget
    idx = np.array(sorted(probe))
    coords = np.unravel_index(idx, plan.shape)
    want = pbrdf_cl.dop(*(axes[n][c] for n, c in zip(("theta_i", "theta_r"), coords[:2])), 180.0, n=1.6, k=2.1,
                        sigma=axes["sigma"][coords[2]], kd=axes["kd"][coords[3]], c=axes["c"][coords[4]],
                        backend="numpy")
    assert np.max(np.abs(np.array([probe[i] for i in idx]) - want)) <= 2e-5


@pytest.mark.parametrize("over", [("theta_r",), ("sigma", "kd"), ("theta_i", "theta_r", "sigma", "kd", "c")])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_reductions_equal_numpy(rng, over, dtype):
    axes, fixed = random_axes(rng, ("theta_i", "theta_r", "sigma", "kd", "c"), (4, 9, 5, 3, 2))
    full = G.grid(axes, fixed, dtype=dtype).values
    names = [n for n in G.AXES if n in axes]
    red = tuple(names.index(n) for n in over)
    kept = [n for n in names if n not in over]
    moved = np.moveaxis(full, red, tuple(range(len(names) - len(red), len(names))))
    flat = moved.reshape(moved.shape[:len(kept)] + (-1,))
    ds = G.reduce_grid(axes, fixed, over=over, dtype=dtype)
    np.testing.assert_array_equal(ds["min"].values, flat.min(axis=-1))
    tol = 1e-13 if dtype == "float64" else 1e-6
    np.testing.assert_allclose(ds["mean"].values, flat.astype(np.float64).mean(axis=-1), rtol=0, atol=tol)
    arg = np.unravel_index(flat.argmin(axis=-1), [axes[n].size for n in names if n in over])
    for n, a in zip([n for n in names if n in over], arg):
        np.testing.assert_array_equal(ds[f"argmin_{n}"].values, axes[n][a])
    assert list(ds["min"].dims) == kept


def measurements(rng, m=12):
    ti = rng.uniform(10, 70, m)
    tr = rng.uniform(5, 80, m)
    phi = rng.choice([180.0, 150.0, 120.0], m)
    d = pbrdf_cl.dop(ti, tr, phi, n=1.8, k=1.2, sigma=0.4, kd=0.3, c=-0.4, backend="numpy")
    return dict(theta_i=ti, theta_r=tr, phi=phi, dop=np.clip(d + rng.normal(0, 0.01, m), 0, 1),
                dop_std=rng.uniform(0.005, 0.02, m))


def numpy_sse(data, params):
    d = pbrdf_cl.dop(data["theta_i"][:, None], data["theta_r"][:, None], data["phi"][:, None], backend="numpy",
                     **{n: np.asarray(v)[None, :] for n, v in params.items()})
    return (((d - data["dop"][:, None]) / data["dop_std"][:, None]) ** 2).sum(axis=0)


#: Parameter grids that take each of the objective kernels' paths: rows of level 1 (with a tail), of
#: level 2, and one vector per work-item.
OBJECTIVE_GRIDS = [
    dict(n=np.linspace(1, 3, 5), k=np.linspace(0, 3, 4), sigma=np.linspace(0.1, 0.8, 3), kd=np.linspace(0, 1, 20),
         c=np.array([-0.6, -0.2])),
    dict(n=np.linspace(1, 3, 5), k=np.linspace(0, 3, 4), sigma=np.linspace(0.1, 0.8, 6), kd=np.linspace(0, 1, 3)),
    dict(n=np.linspace(1, 3, 5), k=np.linspace(0, 3, 4), sigma=0.4, kd=0.3, c=-0.4),
]
OBJECTIVE_PATHS = ["rows-level1", "rows-level2", "per-vector"]


@pytest.mark.parametrize("grid", OBJECTIVE_GRIDS, ids=OBJECTIVE_PATHS)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_objective_grid_equals_numpy_sse(rng, grid, dtype):
    data = measurements(rng)
    res = pbrdf_cl.objective(data, grid=grid, dtype=dtype, k_best=5)
    axes = [n for n in G.PARAMETERS if np.ndim(grid.get(n, 0)) > 0]
    mesh = np.meshgrid(*[grid[n] for n in axes], indexing="ij")
    params = {n: grid.get(n, {"ks": 1.0, "kd": 0.0, "c": 0.0}.get(n)) for n in G.PARAMETERS}
    params.update({n: m.ravel() for n, m in zip(axes, mesh)})
    want = numpy_sse(data, {n: np.broadcast_to(v, mesh[0].size) for n, v in params.items()}).reshape(mesh[0].shape)
    rtol = 1e-11 if dtype == "float64" else 2e-4
    np.testing.assert_allclose(res.sse.values, want, rtol=rtol)
    order = np.argsort(want.ravel())[:5]
    np.testing.assert_array_equal(res.best["index"], order)
    np.testing.assert_allclose(res.best["sse"], want.ravel()[order], rtol=rtol)
    for n in axes:
        np.testing.assert_array_equal(res.best[n], mesh[axes.index(n)].ravel()[order])
    assert res.n_pairs == mesh[0].size * data["dop"].size


def test_objective_points_equals_numpy_sse(rng):
    data = measurements(rng)
    P = 300
    pts = dict(n=rng.uniform(1, 3, P), k=rng.uniform(0, 3, P), sigma=rng.uniform(0.1, 0.9, P), ks=1.0,
               kd=rng.uniform(0, 1, P), c=rng.uniform(-1, 0, P))
    res = pbrdf_cl.objective(data, points=pts, dtype="float64", k_best=3)
    want = numpy_sse(data, {n: np.broadcast_to(v, P) for n, v in pts.items()})
    np.testing.assert_allclose(res.sse, want, rtol=1e-11)
    np.testing.assert_array_equal(res.best["index"], np.argsort(want)[:3])
    res32 = pbrdf_cl.objective(data, points=pts, dtype="float32")
    np.testing.assert_allclose(res32.sse, want, rtol=2e-4)


def test_objective_chunked_equals_unchunked(rng):
    data = measurements(rng)
    grid = dict(n=np.linspace(1, 3, 9), k=np.linspace(0, 3, 7), sigma=np.linspace(0.1, 0.8, 5),
                kd=np.linspace(0, 1, 32), c=np.array([-0.6, -0.2]))
    whole = pbrdf_cl.objective(data, grid=grid)
    part = pbrdf_cl.objective(data, grid=grid, memory_budget=40000)
    np.testing.assert_array_equal(part.sse.values, whole.sse.values)
    np.testing.assert_array_equal(part.best["index"], whole.best["index"])


def set_measurements(rng, sets, m=40):
    """``sets`` DOP data sets at one geometry (several wavelengths of one run): checked Measurements."""
    from pbrdf_cl.io.measurements import as_measurements
    base = measurements(rng, m)
    out = []
    for i in range(sets):
        d = pbrdf_cl.dop(base["theta_i"], base["theta_r"], base["phi"], n=1.4 + 0.3 * i, k=0.5 * i, sigma=0.4,
                         kd=0.2, c=-0.4, backend="numpy")
        std = None if i == 1 else rng.uniform(0.005, 0.02, m)  # one set without its standard deviations
        out.append(as_measurements(dict(base, dop=np.clip(d + rng.normal(0, 0.01, m), 0, 1), dop_std=std)))
    return out


@pytest.mark.parametrize("grid", OBJECTIVE_GRIDS, ids=OBJECTIVE_PATHS)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("budget", [1 << 26, 6000], ids=["one-chunk", "chunks"])
def test_objective_sets_are_each_sets_objective_bit_for_bit(rng, grid, dtype, budget, monkeypatch):
    """Several sets at one geometry in one pass (each DOP combined once for all): each set's SSE is
    its own objective's, bit for bit, at every row level, in chunks (several chunks of several
    sets: the sets' rows copied out of each chunk), in measurement blocks (40 measurements, blocks of
    32: the sums carried from block to block), and in launches of at most OBJECTIVE_SETS sets."""
    monkeypatch.setattr(G, "OBJECTIVE_SETS", 2)  # 3 sets: one launch of two, one of one
    datas = set_measurements(rng, 3)
    names, sses = G.objective_sets(datas, grid, dtype=dtype, memory_budget=budget)
    assert names == tuple(n for n in G.PARAMETERS if np.ndim(grid.get(n, 0)) > 0)
    for data, sse in zip(datas, sses):
        one = G.objective(data, grid=grid, dtype=dtype, memory_budget=budget).sse
        assert one.dims == names and sse.dtype == one.dtype
        np.testing.assert_array_equal(sse, one.values)
    # the sets differ (else a mix-up of their rows would pass)
    assert not np.array_equal(sses[0], sses[1]) and not np.array_equal(sses[1], sses[2])


def test_objective_sets_on_numpy_and_their_refusals(rng):
    datas = set_measurements(rng, 2, m=9)
    grid = dict(n=np.linspace(1, 3, 4), k=np.linspace(0, 3, 3), sigma=0.4, kd=np.linspace(0, 1, 5))
    _, sses = G.objective_sets(datas, grid, dtype="float64", backend="numpy")
    for data, sse in zip(datas, sses):
        np.testing.assert_array_equal(sse, G.objective(data, grid=grid, dtype="float64", backend="numpy").sse.values)
    other = measurements(rng, m=9)
    from pbrdf_cl.io.measurements import as_measurements
    with pytest.raises(ValueError, match="set 1 is not measured at set 0.s angles"):
        G.objective_sets([datas[0], as_measurements(other)], grid)


@pytest.mark.parametrize("axes,fixed,pattern", [
    (dict(theta_x=[1, 2]), dict(n=1.5, k=0, sigma=0.3, theta_i=40, theta_r=30), "unknown axis 'theta_x'"),
    (dict(theta_r=[]), dict(n=1.5, k=0, sigma=0.3, theta_i=40), "axis theta_r is empty"),
    (dict(theta_r=[10, 30, 20]), dict(n=1.5, k=0, sigma=0.3, theta_i=40),
     "strictly increasing or decreasing; value 20.0 at index 2"),
    (dict(theta_r=[10, 10]), dict(n=1.5, k=0, sigma=0.3, theta_i=40), "strictly"),
    (dict(sigma=[0.1, np.nan]), dict(n=1.5, k=0, theta_r=30, theta_i=40), "sigma must be finite, got nan"),
    (dict(theta_r=[10, 95]), dict(n=1.5, k=0, sigma=0.3, theta_i=40),
     r"theta_r must be in \[0, 90\) degrees, got 95.0"),
    (dict(theta_r=[[10, 20]]), dict(n=1.5, k=0, sigma=0.3, theta_i=40), "must be a 1-d array"),
    (dict(theta_r=[10, 20]), dict(n=1.5, k=0, theta_i=40), "sigma is required"),
    (dict(theta_r=[10, 20]), dict(n=1.5, k=0, sigma=0.3, theta_i=40, theta_r=3), "both as an axis and as a fixed"),
    (dict(theta_r=[10, 20]), dict(n=1.5, k=[0, 1], sigma=0.3, theta_i=40), "fixed value k must be a scalar"),
])
def test_bad_axes_give_clear_errors(axes, fixed, pattern):
    with pytest.raises(ValueError, match=pattern):
        G.grid(axes, fixed)


def test_bad_reduction_and_objective_inputs(rng):
    axes = dict(theta_r=np.linspace(0, 80, 5))
    fixed = dict(theta_i=40, n=1.5, k=1, sigma=0.3)
    with pytest.raises(ValueError, match="'sigma' is not one of the grid's axes"):
        G.reduce_grid(axes, fixed, over=["sigma"])
    with pytest.raises(ValueError, match="name at least one axis"):
        G.reduce_grid(axes, fixed, over=[])
    with pytest.raises(ValueError, match="unknown quantity .s1.; valid names are dop, brdf"):
        G.grid(axes, fixed, quantity="s1")
    data = measurements(rng)
    with pytest.raises(ValueError, match="exactly one of grid"):
        pbrdf_cl.objective(data)
    with pytest.raises(ValueError, match=r"data, row 0: dop = 1.5 is not in \[0, 1\]"):
        pbrdf_cl.objective(dict(data, dop=np.full(12, 1.5)), grid=dict(n=[1, 2], k=[0, 1], sigma=0.3))
    with pytest.raises(ValueError, match=r"data, row 0: dop_std = 0.0 is not > 0"):
        pbrdf_cl.objective(dict(data, dop_std=np.zeros(12)), grid=dict(n=[1, 2], k=[0, 1], sigma=0.3))
    with pytest.raises(ValueError, match="unknown parameter 'theta_i'"):
        pbrdf_cl.objective(data, points=dict(theta_i=[1.0], n=[1.0], k=[0.0], sigma=[0.3]))
    with pytest.raises(ValueError, match="unknown axis 'q'"):
        pbrdf_cl.objective(data, grid=dict(q=[1, 2], n=[1, 2], k=[0, 1], sigma=0.3))


def test_grid_engine_interface_used_by_sweep_and_bench(each_device):
    """The package-internal interface of the grid engine (dense.grid_blocks, Tables, table_bytes, ...):
    blocks land in their slices of ``out``; the tables take exactly table_bytes; the frame table
    only for the quantities that need it."""
    eng = each_device
    axes = dict(theta_r=np.linspace(0, 85, 40), phi=[30.0, 180.0], sigma=np.linspace(0.1, 1, 7))
    plan = G.GridPlan(axes, dict(theta_i=40.0, n=1.6, k=2.1, kd=0.2, c=-0.3))
    ng, nnk, nm, ni = G.family_sizes(plan)
    assert (ng, nnk, nm, ni) == (80, 1, 7, 1)
    for quantity, width in (("dop", 1), ("stokes", 4)):
        out = np.full(plan.size * width, np.nan, np.float32)
        blocks = list(G.grid_blocks(eng, plan, quantity, "float32", "paper", 1500, out=out))
        assert len(blocks) > 1 and blocks[0][0] == 0
        for _, host in blocks:
            assert np.shares_memory(host, out) and host.size % width == 0
        np.testing.assert_array_equal(out.reshape(plan.shape + ((width,) if width > 1 else ())),
                                      G.grid(axes, plan.fixed_values(), quantity=quantity, engine=eng).values)
        tables = G.Tables(eng, "float32", "paper", quantity, *G.geometry_list(plan, 0, ng), plan.values)
        sizes = [b.size for b in tables.args()]
        assert sum(sizes[:4]) + 2 * ng * 4 == G.table_bytes(ng, nnk, nm, ni, 4)
        assert sizes[4] == (2 * ng * 4 if quantity == "stokes" else 1)  # the frame table, or a dummy


def test_one_engine_shared_by_threads(each_device):
    """The engine holds its lock while it sets a shared kernel's arguments and enqueues it: threads
    evaluating different inputs on one engine each get their own values."""
    import threading
    eng = each_device
    rng = np.random.default_rng(5)
    jobs = [dict(theta_r=rng.uniform(0, 85, 20000), sigma=rng.uniform(0.1, 1, 20000)) for _ in range(4)]
    got, errors = [None] * len(jobs), []

    def work(i):
        try:
            for _ in range(5):
                got[i] = pbrdf_cl.dop(40.0, jobs[i]["theta_r"], n=1.6, k=2.1, sigma=jobs[i]["sigma"], engine=eng)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)
    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(jobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for i, job in enumerate(jobs):
        np.testing.assert_allclose(got[i], pbrdf_cl.dop(40.0, job["theta_r"], n=1.6, k=2.1, sigma=job["sigma"],
                                                        backend="numpy"), rtol=1e-12, atol=1e-15)
