"""The host path of the per-point API on every usable OpenCL device: inputs read in place (no
conversion of float32 inputs, no expansion of a broadcast axis), the result written straight into
the returned array, memory bounded by the output plus a launch's worth, the values checked by the
kernel itself and the offender still named exactly."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl import engine as E
from pbrdf_cl.bench import traced
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
                    E._gather(d, a, s, e)
                    np.testing.assert_array_equal(d, flat[s:e].astype(np.float32))
                    assert len(list(E._flat_boxes(a.shape, s, e))) <= 2 * len(shape)


@pytest.mark.parametrize("src,dtype", [("float32", "float32"), ("float64", "float32"), ("float32", "float64"),
                                       ("float64", "float64")])
def test_any_input_dtype_and_layout_gives_the_reference(rng, monkeypatch, src, dtype):
    monkeypatch.setattr(E, "LAUNCH_POINTS", 4096)  # several launches, and a padded tail
    monkeypatch.setattr(E, "CONVERT_POINTS", 1024)
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
    out = E.aligned_empty(a.size, a.dtype)
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
    staging = len(E.POINT_INPUTS) * E.CONVERT_POINTS * 4
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
    monkeypatch.setattr(E, "LAUNCH_POINTS", 2048)
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
    from pbrdf_cl import engine as E
    rng = np.random.default_rng(9)
    n = 20011  # with LAUNCH_POINTS = 4096: five launches, slots reused, a padded tail
    inp = dict(theta_i=rng.uniform(0, 89, n), theta_r=rng.uniform(0, 89, n).astype(np.float32),
               phi=np.broadcast_to(rng.uniform(0, 360, (n, 1)), (n, 3))[:, 1], sigma=rng.uniform(0.05, 1, n))
    monkeypatch.setattr(E, "LAUNCH_POINTS", 4096)
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
