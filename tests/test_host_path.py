"""The host path of the per-point API on every usable OpenCL device: inputs read in place (no
conversion of float32 inputs, no expansion of a broadcast axis), the result written straight into
the returned array, memory bounded by the output plus a launch's worth, the values checked by the
kernel itself and the offender still named exactly."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.bench import traced
from pbrdf_cl.device import transfers as T

from conftest import PARAMS, call, random_inputs

pytestmark = pytest.mark.usefixtures("each_device")


def test_flat_ranges_of_any_array_are_gathered_without_temporaries():
    rng = np.random.default_rng(0)
    for shape in [(7,), (3, 4), (2, 3, 5), (1, 6, 1, 4), (5, 1, 3)]:
        for a in (rng.random(shape), np.broadcast_to(rng.random(shape[-1:]), shape), rng.random(shape[::-1]).T):
            flat = np.ascontiguousarray(a).reshape(-1)
            for s in range(flat.size):
                for e in range(s, flat.size + 1):
                    d = np.empty(e - s, np.float32)
                    T._gather(d, a, s, e)
                    np.testing.assert_array_equal(d, flat[s:e].astype(np.float32))
                    assert len(list(T._flat_boxes(a.shape, s, e))) <= 2 * len(shape)


@pytest.mark.parametrize("src,dtype", [("float32", "float32"), ("float64", "float32"), ("float32", "float64"),
                                       ("float64", "float64")])
def test_any_input_dtype_and_layout_gives_the_reference(rng, monkeypatch, src, dtype):
    monkeypatch.setattr(T, "LAUNCH_POINTS", 4096)  # several launches, and a padded tail
    monkeypatch.setattr(T, "CONVERT_POINTS", 1024)
    inp = {k: v.astype(src) for k, v in random_inputs(rng, 9000).items()}
    want = call(pbrdf_cl.dop, inp, backend="numpy")
    tol = 2e-5 if dtype == "float32" or src == "float32" else 1e-12
    if src == "float32":  # the reference at the float32 inputs
        want = call(pbrdf_cl.dop, {k: v.astype(np.float64) for k, v in inp.items()}, backend="numpy")
    got = call(pbrdf_cl.dop, inp, dtype=dtype)
    assert got.dtype == np.dtype(dtype) and np.max(np.abs(got - want)) <= tol
    # strided (every other point) and broadcast (an axis against another) inputs
    half = {k: v[::2] for k, v in inp.items()}
    np.testing.assert_allclose(call(pbrdf_cl.dop, half, dtype=dtype), got[::2], rtol=0, atol=tol)
    th = np.linspace(0, 89, 61).astype(src)
    sg = np.linspace(0.05, 1, 37).astype(src)
    grid = pbrdf_cl.dop(40, th[:, None], n=1.6, k=2.1, sigma=sg[None, :], kd=0.2, dtype=dtype)
    ref = pbrdf_cl.dop(40, th.astype(float)[:, None], n=1.6, k=2.1, sigma=sg.astype(float)[None, :], kd=0.2,
                       backend="numpy")
    assert grid.shape == (61, 37) and np.max(np.abs(grid - ref)) <= tol


def _aligned(a):
    out = T.aligned_empty(a.size, a.dtype)
    out[...] = a
    return out


def _big_float32_inputs(rng, size=1 << 21):
    inp = {k: _aligned(v.astype(np.float32)) for k, v in random_inputs(rng, size).items()}
    call(pbrdf_cl.dop, {k: v[:100] for k, v in inp.items()}, dtype="float32")  # kernels built
    return inp


def test_float32_inputs_are_read_in_place_and_memory_stays_near_the_output(rng, each_device):
    if not each_device.host_memory:
        pytest.skip(f"{each_device.description} does not work in host memory: its inputs are copied to the "
                    "device (the staged case is test_staged_inputs_take_a_launch_of_memory_beyond_the_output)")
    inp = _big_float32_inputs(rng)
    assert all(each_device.can_use_in_place(v, np.float32) for v in inp.values())  # page-aligned: any driver
    out, peak = traced(lambda: call(pbrdf_cl.dop, inp, dtype="float32"))
    assert out.dtype == np.float32
    assert peak <= out.nbytes + (1 << 20), peak  # the output, and less than 1 MiB besides (inputs: 9x its size)


def test_staged_inputs_take_a_launch_of_memory_beyond_the_output(rng, each_device):
    """Inputs a device cannot read in place (any input of a device outside host memory; on a CPU
    device, per ``zero_copy_alignment``: PoCL takes any address, others page-aligned ones) are
    staged, and so is a broadcast axis, never expanded: the output plus a launch's staging."""
    inp = _big_float32_inputs(rng)
    staging = len(T.POINT_INPUTS) * T.CONVERT_POINTS * 4
    if not each_device.host_memory:  # even page-aligned inputs are staged
        assert not any(each_device.can_use_in_place(v, np.float32) for v in inp.values())
        out, peak = traced(lambda: call(pbrdf_cl.dop, inp, dtype="float32"))
        assert out.dtype == np.float32 and peak <= out.nbytes + staging + (1 << 20), (peak, out.nbytes, staging)
    out, peak = traced(lambda: call(pbrdf_cl.dop, {k: v[1:] for k, v in inp.items()}, dtype="float32"))
    assert peak <= out.nbytes + staging + (1 << 20), (peak, out.nbytes, staging)
    th, sg = np.linspace(0, 89, 2048), np.linspace(0.05, 1, 1024)
    out, peak = traced(lambda: pbrdf_cl.dop(40, th[:, None], n=1.6, k=2.1, sigma=sg[None, :], dtype="float32"))
    assert peak <= out.nbytes + staging + (1 << 20), (peak, out.nbytes, staging)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("func", [pbrdf_cl.dop, pbrdf_cl.brdf])
def test_the_kernel_marks_bad_values_and_the_offender_is_named(rng, monkeypatch, func, dtype):
    monkeypatch.setattr(T, "LAUNCH_POINTS", 2048)
    base = {k: v.astype(np.float32) for k, v in random_inputs(rng, 5000).items()}
    cases = [("theta_r", 4321, 90.0, r"theta_r must be in \[0, 90\) degrees, got 90\.0 at index \[4321\]"),
             ("sigma", 4999, 0.0, r"sigma must be > 0, got 0\.0 at index \[4999\]"),
             ("k", 17, -0.5, r"k must be >= 0, got -0\.5 at index \[17\]"),
             ("phi", 2500, np.nan, r"phi must be finite, got nan at index \[2500\]"),
             ("c", 3000, np.inf, r"c must be finite, got inf at index \[3000\]")]
    for name, index, value, pattern in cases:
        inp = {k: v.copy() for k, v in base.items()}
        inp[name][index] = value
        with pytest.raises(ValueError, match=pattern):
            call(func, inp, dtype=dtype)
    assert set(PARAMS) <= set(base)


def test_the_transfer_pipeline_of_gpus_gives_the_same_values(engine, monkeypatch):
    """The path of devices with their own memory (pinned staging, uploads and reads on a second
    queue overlapping the kernels, two slots; grids read back chunk k while chunk k + 1 computes),
    forced on this device: bit-identical to the in-place path, over many launches and chunks."""
    import pbrdf_cl
    from pbrdf_cl.device import transfers as T
    rng = np.random.default_rng(9)
    n = 20011  # with LAUNCH_POINTS = 4096: five launches, slots reused, a padded tail
    inp = dict(theta_i=rng.uniform(0, 89, n), theta_r=rng.uniform(0, 89, n).astype(np.float32),
               phi=np.broadcast_to(rng.uniform(0, 360, (n, 1)), (n, 3))[:, 1], sigma=rng.uniform(0.05, 1, n))
    monkeypatch.setattr(T, "LAUNCH_POINTS", 4096)
    cases = [(q, d) for d in ("float32", "float64") for q in ("dop", "brdf", "aop", "stokes", "mueller")]
    axes = dict(theta_r=np.linspace(0, 85, 40), phi=[60.0, 180.0], sigma=np.linspace(0.1, 1, 9), kd=[0.0, 0.5])
    fixed = dict(theta_i=40, n=1.6, k=2.1)

    def results():
        points = [pbrdf_cl.evaluate(q, n=1.6, k=2.1, kd=0.2, c=-0.3, dtype=d, engine=engine, **inp) for q, d in cases]
        return points + [pbrdf_cl.grid(axes, fixed, quantity=q, engine=engine, memory_budget=8000).values
                         for q in ("dop", "stokes")]
    in_place = results()  # the same engine (its programs built once), then through the pipeline
    monkeypatch.setattr(engine, "force_transfers", True)
    assert engine.overlaps_transfers
    for i, (a, b) in enumerate(zip(results(), in_place)):
        np.testing.assert_array_equal(a, b, err_msg=str(cases[i] if i < len(cases) else ("grid", i)))
    with pytest.raises(ValueError, match=r"theta_r must be in \[0, 90\) degrees, got 95.0 at index \[7\]"):
        pbrdf_cl.dop(40, np.where(np.arange(50) == 7, 95.0, 30.0), n=1.6, k=2, sigma=0.3, engine=engine)


# ---- broadcast inputs sent once with their index rule (issue #12)

def test_the_plan_classifies_each_input_by_its_axes():
    S = (4, 5, 6, 7)
    shapes = {(): (T.SINGLE,), (1, 1, 1, 1): (T.SINGLE,), S: (T.PER_POINT,), (5, 6, 7): (T.BROADCAST, 1, 210, (1, 4)),
              (7,): (T.BROADCAST, 1, 7, (3, 4)), (4, 1, 1, 1): (T.BROADCAST, 210, 4, (0, 1)),
              (5, 6, 1): (T.BROADCAST, 7, 30, (1, 3)), (1, 5, 1, 1): (T.BROADCAST, 42, 5, (1, 2)),
              (4, 5, 6, 1): (T.BROADCAST, 7, 120, (0, 3)), (6, 7): (T.BROADCAST, 1, 42, (2, 4)),
              (4, 1, 6, 1): (T.PER_POINT,), (5, 1, 7): (T.PER_POINT,), (4, 1, 1, 7): (T.PER_POINT,)}
    plan = T.input_plan(S, {str(s): np.ones(s) for s in shapes})
    for s, want in shapes.items():
        r = plan[str(s)]
        assert (r.kind,) + ((r.div, r.mod, r.axes) if r.kind == T.BROADCAST else ()) == want, (s, r)
    # an axis of length 1 in the output is no break in the run; broadcast views count by their strides
    assert T.input_plan((3, 1, 4, 2), dict(a=np.ones((3, 1, 4, 1))))["a"] == T.IndexRule(T.BROADCAST, 2, 12, (0, 3))
    views = dict(row=np.broadcast_to(np.arange(6.0), (5, 6)), col=np.broadcast_to(np.ones((5, 1)), (5, 6)),
                 one=np.broadcast_to(2.0, (5, 6)), strided=np.ones((5, 12))[:, ::2])
    plan = T.input_plan((5, 6), views)
    assert [plan[n].kind for n in views] == [T.BROADCAST, T.BROADCAST, T.SINGLE, T.PER_POINT]
    assert (plan["row"].div, plan["row"].mod, plan["col"].div, plan["col"].mod) == (1, 6, 6, 5)
    np.testing.assert_array_equal(T.compact_values(views["row"], 2).reshape(-1), np.arange(6.0))
    # a rule whose block would need more than 32-bit kernel arithmetic stays per point
    huge = np.broadcast_to(np.ones((2, 1)), (2, 1 << 31))
    assert T.input_plan((2, 1 << 31), dict(a=huge))["a"].kind == T.PER_POINT


def test_the_division_by_multiplier_is_exact_for_every_31_bit_numerator():
    rng = np.random.default_rng(5)
    ds = sorted({1, 2, 3, 5, 7, 15, 16, 17, 641, 4095, 4096, 4097, 6700417, (1 << 30) - 1, 1 << 30, (1 << 30) + 1,
                 (1 << 31) - 1, 1 << 31} | set(rng.integers(1, 1 << 31, 200).tolist()))
    top = (1 << 31) - 1
    for d in ds:
        m, s = T.udiv_magic(d)
        assert 0 < m < 1 << 32
        n = np.concatenate([np.arange(0, 40), top - np.arange(40), rng.integers(0, 1 << 31, 4000),
                            np.clip(np.arange(-3, 4)[None, :] + d * np.arange(0, 64)[:, None], 0, top).ravel()])
        n = n.astype(np.uint64)
        got = (((n << np.uint64(1)) * np.uint64(m)) >> np.uint64(32)) >> np.uint64(s)  # the kernels' PB_UDIV
        np.testing.assert_array_equal(got, n // np.uint64(d), err_msg=str(d))


def _kernel_index(table, j, offsets):
    """pbrdf_points.cl's pb_rule_index (the scalar kernels' kind-2 index) at launch offsets, in uint32."""
    kind, div, dm, ds, mod, mm, ms, r0, q0 = (np.uint64(v) for v in table[j])

    def udiv(n, m, s):
        return (((n << np.uint64(1)) * m) >> np.uint64(32)) >> s
    u = r0 + offsets
    assert (u < 1 << 31).all()
    q = q0 + udiv(u, dm, ds)
    assert (q < 1 << 31).all()
    return q - udiv(q, mm, ms) * mod


def test_the_rule_table_keeps_32_bit_arithmetic_exact_at_any_start():
    """Launches start anywhere (beyond 2^32 points too): the host's r0 and q0 make the kernels'
    32-bit index equal ``((start + offset) // div) % mod`` for every offset of a launch, across period
    boundaries."""
    offsets = np.arange(T.LAUNCH_POINTS + 16, dtype=np.uint64)
    for div, mod in ((1, 7), (1, 4096), (3, 5), (4095, 2048), (4096, 2048), (1 << 30, 3), (17, (1 << 30) - 1)):
        plan = {n: T.IndexRule(T.SINGLE) for n in T.POINT_INPUTS}
        plan["sigma"] = T.IndexRule(T.BROADCAST, div, mod, (0, 1))
        for start in (0, div * mod - 5, 3 * div * mod + div - 1, (1 << 32) + 12345, (1 << 40) + 7):
            table = T.rule_table(plan, start)
            assert table.dtype == np.uint32 and table.shape == (9, len(T.RULE_FIELDS))
            want = ((np.uint64(start) + offsets) // np.uint64(div)) % np.uint64(mod)
            np.testing.assert_array_equal(_kernel_index(table, T.POINT_INPUTS.index("sigma"), offsets), want,
                                          err_msg=str((div, mod, start)))


def _broadcast_cases(rng):
    """(shape, inputs) pairs: leading and trailing axes, runs of axes, blocks shorter than a vector
    (widened), periods shorter than a vector, a mix of one value, per-point and broadcast inputs,
    and a pattern that is not one run (gathered); odd sizes (padded tails)."""
    u = rng.uniform
    return [
        ((300, 45), dict(theta_r=u(0, 89.9, (300, 1)), sigma=u(0.05, 1, 45))),
        ((7, 3, 257), dict(theta_i=u(0, 89.9, (7, 1, 1)), kd=u(0, 2, (1, 3, 1)), phi=u(0, 360, 257),
                           sigma=u(0.05, 1, (7, 3, 1)))),
        ((1000, 3), dict(theta_r=u(0, 89.9, (1000, 1)), phi=np.array([60.0, 180.0, 300.0]))),
        ((3, 4099), dict(theta_r=u(0, 89.9, (3, 1)), sigma=u(0.05, 1, 4099), n=u(1.1, 3, (3, 4099)),
                         k=np.float32(2.5))),
        ((5, 3, 300), dict(theta_r=u(0, 89.9, (5, 1, 300)), sigma=u(0.05, 1, (1, 3, 1)))),  # (5, 1, 300): gathered
        ((2, 5, 1, 7, 11), dict(theta_r=u(0, 89.9, (5, 1, 7, 1)), sigma=u(0.05, 1, (2, 1, 1, 1, 1)),
                                phi=u(0, 360, 11))),
    ]


def _expanded(inp, shape):
    return {k: np.ascontiguousarray(np.broadcast_to(v, shape)) for k, v in inp.items()}


@pytest.mark.parametrize("transfers", [False, True], ids=["in-place", "transfer-pipeline"])
def test_broadcast_inputs_give_the_expanded_call_bit_for_bit(each_device, monkeypatch, rng, transfers):
    """Sent once with their rules (several launches, so launches start inside periods, and padded
    tails), broadcast inputs give exactly what the same call with every input expanded gives, on
    the same device and dtype; so does the gathered path of before (``index_rules = False``)."""
    monkeypatch.setattr(T, "LAUNCH_POINTS", 4096)
    monkeypatch.setattr(T, "CONVERT_POINTS", 1024)
    monkeypatch.setattr(each_device, "force_transfers", transfers)
    asked = []
    kernel = each_device.kernel
    monkeypatch.setattr(each_device, "kernel", lambda name, *a: asked.append(name) or kernel(name, *a))
    fixed = dict(theta_i=40.0, theta_r=30.0, phi=150.0, n=1.6, k=2.1, sigma=0.4, ks=0.9, kd=0.2, c=-0.3)
    for shape, given in _broadcast_cases(rng):
        inp = {**fixed, **given}
        plan = T.input_plan(shape, inp)
        assert any(r.kind == T.BROADCAST for r in plan.values()), shape
        full = _expanded(inp, shape)
        for dtype in ("float32", "float64"):
            for q in ("dop", "brdf", "aop", "mueller"):
                del asked[:]
                got = pbrdf_cl.evaluate(q, dtype=dtype, **inp)
                assert asked == [f"{q}_bcast_points_vec" if q in ("dop", "brdf") else "quantity_bcast_points"], asked
                want = pbrdf_cl.evaluate(q, dtype=dtype, **full)
                assert got.dtype == np.dtype(dtype) and got.shape == want.shape
                np.testing.assert_array_equal(got, want, err_msg=str((shape, q, dtype)))
            each_device.index_rules = False
            try:
                np.testing.assert_array_equal(pbrdf_cl.dop(dtype=dtype, **inp), pbrdf_cl.dop(dtype=dtype, **full))
            finally:
                each_device.index_rules = True


def test_a_launch_far_into_the_array_reads_the_right_values(each_device, monkeypatch, rng):
    """The twin kernels at a start beyond 2^32 points (launched directly: no such array is made):
    the values at flat points start .. start + 5000 of a (2^21 x 4093)-point broadcast, where
    theta_r changes every 4093 points and sigma repeats every 4093."""
    monkeypatch.setattr(T, "TABLE_POINTS", 1 << 22)  # theta_r's 2^21 values sent as a table
    div = 4093
    th, sg = rng.uniform(0, 89.9, 1 << 21), rng.uniform(0.05, 1, div)
    shape = (th.size, div)
    start = (1 << 32) + 3 * div - 7
    t = start + np.arange(5000)
    for dtype in ("float32", "float64"):
        npdt = np.dtype(T.DTYPES[dtype])
        lanes = each_device.vector_width[dtype]
        inp = dict(theta_i=40.0, theta_r=th[:, None], phi=150.0, n=1.6, k=2.1, sigma=sg[None, :], ks=1.0, kd=0.2,
                   c=-0.3)
        plan, flat, values = T.point_inputs(each_device, inp, shape, npdt, lanes)
        assert plan["theta_r"].kind == plan["sigma"].kind == T.BROADCAST
        parts = {**flat, **values}
        out = np.empty(5000, npdt)
        kern = each_device.kernel("dop_bcast_points_vec", dtype, "paper")
        T.launch_points(each_device, kern, parts, 5000 // lanes * lanes, out[:5000 // lanes * lanes], npdt, lanes,
                        True, each_device.host_memory, T.rule_table(plan, start))
        want = pbrdf_cl.dop(40.0, th[t // div], 150.0, n=1.6, k=2.1, sigma=sg[t % div], kd=0.2, c=-0.3, dtype=dtype)
        np.testing.assert_array_equal(out[:5000 // lanes * lanes], want[:5000 // lanes * lanes])


def test_broadcast_inputs_take_no_memory_beyond_the_output(each_device, rng):
    th, sg = np.linspace(0, 89, 2048), np.linspace(0.05, 1, 1024)
    pbrdf_cl.dop(40, th[:4, None], n=1.6, k=2.1, sigma=sg[None, :], dtype="float32")  # kernels built
    out, peak = traced(lambda: pbrdf_cl.dop(40, th[:, None], n=1.6, k=2.1, sigma=sg[None, :], dtype="float32"))
    assert out.shape == (2048, 1024) and peak <= out.nbytes + (256 << 10), (peak, out.nbytes)
    out, peak = traced(lambda: pbrdf_cl.aop(40, th[:, None], 120.0, n=1.6, k=2.1, sigma=sg[None, :], dtype="float32"))
    assert peak <= out.nbytes + (256 << 10), (peak, out.nbytes)


@pytest.mark.parametrize("func", [pbrdf_cl.dop, pbrdf_cl.brdf, pbrdf_cl.aop])
def test_a_bad_value_in_a_broadcast_input_is_named_with_its_index(each_device, monkeypatch, func):
    monkeypatch.setattr(T, "LAUNCH_POINTS", 4096)
    th, sg = np.linspace(0, 89, 300)[:, None], np.linspace(0.05, 1, 45)[None, :].copy()
    assert T.input_plan((300, 45), dict(theta_r=th, sigma=sg))["sigma"].kind == T.BROADCAST
    sg[0, 44] = 0.0
    with pytest.raises(ValueError, match=r"sigma must be > 0, got 0\.0 at index \[0, 44\]"):
        func(40, th, n=1.6, k=2.1, sigma=sg, kd=0.2, dtype="float32")
    th = th.copy()
    th[217, 0] = np.nan
    with pytest.raises(ValueError, match=r"theta_r must be finite, got nan at index \[217, 0\]"):
        func(40, th, n=1.6, k=2.1, sigma=0.5, kd=0.2)
