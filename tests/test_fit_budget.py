"""Fits of big data sets (issue #39, item 4): the grid stage's objective runs over the measurements
in blocks within ``memory_budget`` (on a device also in cache-sized blocks, its float sums running on
from block to block: the same sums, bit for bit); ``pbrdf_cl.fit``, ``fit_joint`` and ``pbrdf-cl fit``
take the budget, and one too small for one measurement is refused in one line naming the least."""
import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.compute import dense
from pbrdf_cl.fitting.sample import stages
from pbrdf_cl.model.measurables import channels as make_channels

from conftest import requires_opencl

STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
GRID = dict(n=np.linspace(1, 5, 6), k=np.linspace(0, 10, 8), sigma=np.linspace(0.05, 1, 5), ks=1.0,
            kd=np.linspace(0, 5, 4), c=np.linspace(-1, 0, 3))
#: bytes of one measurement's float32 tables of GRID (dense.table_bytes: 2 n k + sigma ks + kd c + 2)
ROW32 = (2 * 48 + 5 + 12 + 2) * 4


def measurements(rng, m=200):
    ti, tr, ph = rng.uniform(10, 70, m), rng.uniform(5, 75, m), rng.uniform(120, 240, m)
    dop = pbrdf_cl.dop(ti, tr, ph, backend="numpy", **STEEL) + rng.normal(0, 0.002, m)
    return dict(theta_i=ti, theta_r=tr, phi=ph, dop=dop, dop_std=np.full(m, 0.002))


def test_device_objective_in_blocks_of_measurements_is_the_one_launch_bit_for_bit(engine, rng, monkeypatch):
    data = measurements(rng)
    one = {}
    for dtype in ("float32", "float64") if engine.fp64 else ("float32",):
        monkeypatch.setattr(dense, "OBJECTIVE_BLOCK_BYTES", 1 << 30)
        one[dtype] = pbrdf_cl.objective(data, grid=GRID, dtype=dtype, engine=engine).sse.values
        monkeypatch.setattr(dense, "OBJECTIVE_BLOCK_BYTES", 1)  # OBJECTIVE_BLOCK_ROWS a block: 7 blocks
        blocked = pbrdf_cl.objective(data, grid=GRID, dtype=dtype, engine=engine).sse.values
        assert blocked.tobytes() == one[dtype].tobytes()
        # a budget for 10 measurements' tables at a time, and chunks of the sums too
        small = pbrdf_cl.objective(data, grid=GRID, dtype=dtype, engine=engine,
                                   memory_budget=2 * 10 * ROW32 * (2 if dtype == "float64" else 1) + 1024)
        assert small.sse.values.tobytes() == one[dtype].tobytes()
    ref = pbrdf_cl.objective(data, grid=GRID, dtype="float64", backend="numpy").sse.values
    np.testing.assert_allclose(one["float32"], ref, rtol=2e-4)


def test_device_channel_objective_in_blocks_is_the_one_launch_bit_for_bit(engine, rng, monkeypatch):
    m = 60
    ti, tr, ph = rng.uniform(10, 70, m), rng.uniform(5, 75, m), rng.uniform(120, 240, m)
    cols = dict(dop=rng.uniform(0, 1, m), aop=rng.uniform(-90, 90, m), s1=rng.uniform(-1, 1, m))
    chans = make_channels(ti, tr, ph, cols, incident=np.tile([0.0, 1.0, 0.0], (m, 1)))
    monkeypatch.setattr(dense, "OBJECTIVE_BLOCK_BYTES", 1 << 30)
    one = dense.objective(chans, grid=GRID, engine=engine).sse.values
    monkeypatch.setattr(dense, "OBJECTIVE_BLOCK_BYTES", 1)
    assert dense.objective(chans, grid=GRID, engine=engine).sse.values.tobytes() == one.tobytes()


def test_numpy_objective_in_blocks_of_measurements_sums_them_in_float64(rng):
    """The numpy backend sums each block's SSE in float64, then the blocks: the order of the sum
    changes, so the result agrees to float64 rounding (1e-13 relative), not bit for bit."""
    data = measurements(rng, 120)
    one = pbrdf_cl.objective(data, grid=GRID, dtype="float64", backend="numpy").sse.values
    blocked = pbrdf_cl.objective(data, grid=GRID, dtype="float64", backend="numpy",
                                 memory_budget=2 * 25 * 2 * ROW32 + 4096).sse.values  # float64 tables: 25 a block
    np.testing.assert_allclose(blocked, one, rtol=1e-13)


def test_a_budget_below_one_measurement_is_refused_naming_the_least(rng):
    data = measurements(rng, 20)
    least = 2 * ROW32 + 64 * 4
    with pytest.raises(pbrdf_cl.RangeError, match=rf"^a memory budget of {least - 1} bytes .* one measurement's "
                       rf"tables need {ROW32} bytes; give at least {least} bytes"):
        pbrdf_cl.objective(data, grid=GRID, memory_budget=least - 1)
    assert pbrdf_cl.objective(data, grid=GRID, memory_budget=least).best["sse"].size == 10


@requires_opencl
def test_fit_within_a_small_budget_is_the_fit_within_the_default_bit_for_bit():
    """The steel example (30 measurements) with tables for 5 measurements at a time: every stage
    gets the same grid, so the same result to the last bit."""
    default = pbrdf_cl.fit("examples/steel_435nm.csv")
    row = (2 * 24 * 32 + 16 + 16 * 8 + 2) * 4
    small = pbrdf_cl.fit("examples/steel_435nm.csv", memory_budget=2 * 5 * row + 1024)
    assert [small.x[n] for n in default.free] == [default.x[n] for n in default.free]
    assert small.sse == default.sse and small.ci95 == default.ci95
    with pytest.raises(pbrdf_cl.RangeError, match=r"give at least \d+ bytes"):
        pbrdf_cl.fit("examples/steel_435nm.csv", memory_budget="4 kB")
    with pytest.raises(pbrdf_cl.RangeError, match="memory_budget: 'lots' is not a size"):
        pbrdf_cl.fit("examples/steel_435nm.csv", memory_budget="lots")


@requires_opencl
def test_polarimetric_and_joint_fits_take_the_budget():
    cam = "examples/steel_camera_45.csv"
    assert pbrdf_cl.fit(cam, memory_budget="20 kB").x == pbrdf_cl.fit(cam).x
    sets = {"a": "examples/steel_435nm.csv", "b": "examples/steel_435nm_with_f00.csv"}
    small = pbrdf_cl.fit_joint(sets, memory_budget="40 kB")
    assert small.x == pbrdf_cl.fit_joint(sets).x
    with pytest.raises(pbrdf_cl.RangeError, match=r"give at least \d+ bytes"):
        pbrdf_cl.fit_joint(sets, memory_budget=1000)


def test_default_budget_is_a_size():
    from pbrdf_cl.ranges import parse_bytes
    assert parse_bytes("memory_budget", stages.MEMORY_BUDGET) == 512 << 20


def test_residual_rows_of_a_big_data_set_share_factors_and_come_in_parts_bit_for_bit(rng, monkeypatch):
    """A finite-difference batch over 5,000 measurements (each problem and its steps, one parameter
    moved each): each factor is computed once per distinct row (3 of each problem's 6 Fresnel
    rows), the rows come a few at a time, and every value is the one of the row computed alone."""
    from pbrdf_cl.fitting.common import fd_jacobian
    from pbrdf_cl.io.measurements import from_arrays
    from pbrdf_cl.model import reference
    data = measurements(rng, 5000)
    meas = from_arrays(data["theta_i"], data["theta_r"], data["dop"], data["phi"], data["dop_std"])
    free = ("n", "k", "sigma", "kd", "c")
    res = stages.Residuals(stages.Model(meas, "paper"), free, {"ks": 1.0}, meas.dop, meas.dop_std)
    lo, hi = np.array([1, 0, 0.05, 0, -1.0]), np.array([5, 10, 1, 5, 0.0])
    X = lo + rng.random((4, 5)) * (hi - lo)
    fresnel_rows, real = [], reference.fresnel
    monkeypatch.setattr(reference, "fresnel", lambda n, *a: fresnel_rows.append(np.shape(n)[0]) or real(n, *a))
    R, J = fd_jacobian(res.rows, X, lo, hi)
    assert sum(fresnel_rows) == 4 * 3  # the base point and its n and k steps; sigma, kd and c share its terms
    monkeypatch.setattr(stages, "ROWS_VALUES", 5 * 5000)  # 5 rows at a time
    R5, J5 = fd_jacobian(res.rows, X, lo, hi)
    alone = np.array([res.rows_of(x[None])[0] for x in X])
    assert R.tobytes() == R5.tobytes() == alone.tobytes() and J.tobytes() == J5.tobytes()


@requires_opencl
def test_local_stages_run_with_blas_on_one_thread(monkeypatch):
    """BLAS's threads, woken by every dot product of a residual vector over 10,000 measurements,
    spun between the local stages' calls and took the cores of the model's values."""
    from threadpoolctl import threadpool_info

    from pbrdf_cl.fitting.sample import inversion
    seen, real = [], inversion.local_stages

    def spy(*args, **kwargs):
        seen.append([lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"])
        return real(*args, **kwargs)
    monkeypatch.setattr(inversion, "local_stages", spy)
    pbrdf_cl.fit("examples/steel_435nm.csv")
    assert seen and seen[0] and all(n == 1 for n in seen[0])


@requires_opencl
def test_cli_fit_takes_memory_budget_and_refuses_bad_ones_in_one_line(tmp_path):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    def run(*args):
        return subprocess.run([sys.executable, "-m", "pbrdf_cl", "fit", "examples/steel_435nm.csv", "--quiet", *args],
                              capture_output=True, text=True, timeout=300,
                              env=dict(os.environ, PYTHONWARNINGS="ignore",
                                       PYTHONPATH=str(Path(pbrdf_cl.__file__).resolve().parent.parent)))
    small, default = run("--memory-budget", "20kB", "--json", str(tmp_path / "small.json")), \
        run("--json", str(tmp_path / "default.json"))
    assert small.returncode == 0 == default.returncode, small.stderr + default.stderr
    fits = [json.loads((tmp_path / f"{n}.json").read_text())["fits"]["six-param"] for n in ("small", "default")]
    assert fits[0]["x"] == fits[1]["x"] and small.stdout == default.stdout.replace(f"wrote {tmp_path}/default",
                                                                                  f"wrote {tmp_path}/small")
    for value, words in (("lots", "--memory-budget: 'lots' is not a size"), ("0", "--memory-budget: must be > 0"),
                         ("10kB", "give at least 13712 bytes")):
        proc = run("--memory-budget", value)
        assert proc.returncode == 1 and proc.stderr.count("\n") == 1 and words in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr
