"""Sweeps into Zarr stores: equal to pbrdf_cl.grid, resumable after Ctrl-C and kill -9 with a
bit-identical result, the same store from a dask LocalCluster, bounded memory, clear spec errors."""
import importlib
import json
import os
import signal
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import pbrdf_cl
from pbrdf_cl import cli
from pbrdf_cl.analysis.sweeps import SpecError, SweepSpec, load_spec, read_done

S = importlib.import_module("pbrdf_cl.analysis.sweeps")
ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)
STEEL = dict(n=1.6, k=2.139, ks=0.9, kd=0.15, c=-0.3)

# 40 chunks: 8 x 5 over (theta_i, theta_r), the last theta_r chunk shorter (19 = 4 + 4 + 4 + 4 + 3)
SPEC_TOML = """\
title = "test sweep"
quantity = "dop"
dtype = "float32"
memory_budget = "1 MiB"

[axes]
theta_i = "10:80:10"
theta_r = {start = 0, stop = 85, num = 19}
sigma = {start = 0.05, stop = 1, num = 24}
kd = [0.0, 0.1, 0.3]

[fixed]
n = 1.6
k = 2.139
c = -0.3

[chunks]
theta_i = 1
theta_r = 4
"""


def files(store):
    """Every file of a store: relative path -> bytes."""
    store = Path(store)
    return {str(p.relative_to(store)): p.read_bytes() for p in sorted(store.rglob("*")) if p.is_file()}


def n_done(store):
    folder = Path(store, "_sweep", "done")
    return sum(f.isdigit() for f in os.listdir(folder)) if folder.is_dir() else 0


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("spec") / "spec.toml"
    path.write_text(SPEC_TOML)
    return path


@pytest.fixture(scope="module")
def reference(spec_file, tmp_path_factory):
    """An uninterrupted local run of SPEC_TOML."""
    store = tmp_path_factory.mktemp("ref") / "ref.zarr"
    res = pbrdf_cl.sweep(spec_file, store, progress=False)
    assert res.complete and res.chunks_computed == 40 and res.chunks_skipped == 0
    return store


def test_spec_forms_and_canonical_hash():
    base = dict(axes=dict(theta_r="0:80:20", sigma=[0.1, 0.2]), fixed=dict(theta_i=40, **STEEL))
    spec = SweepSpec(base)
    np.testing.assert_array_equal(spec.axes["theta_r"], [0, 20, 40, 60, 80])
    same = [dict(base, axes=dict(theta_r=[0, 20, 40, 60, 80], sigma="0.1,0.2")),
            dict(base, axes=dict(theta_r={"start": 0, "stop": 80, "num": 5}, sigma=[0.1, 0.2])),
            dict(base, axes=dict(theta_r={"start": 0, "stop": 80, "step": 20}, sigma=[0.1, 0.2]), title="x",
                 memory_budget="64 MiB"),
            dict(base, axes=dict(theta_r=np.linspace(0, 80, 5), sigma=(0.1, 0.2)))]  # arrays from Python
    for d in same:  # the identity is the values, not how they were written (nor the budget or title)
        assert SweepSpec(d).sha256 == spec.sha256
    assert SweepSpec(dict(base, dtype="float64")).sha256 != spec.sha256
    assert SweepSpec(dict(base, memory_budget="1.5 MiB")).memory_budget == 3 << 19
    assert spec.fixed == dict(theta_i=40.0, phi=180.0, **STEEL)  # defaults filled in
    ident = json.loads(spec.canonical_json)["axes"]["theta_r"]  # count, ends and SHA-256: the values are coordinates
    assert ident == S.axis_identity([0.0, 20.0, 40.0, 60.0, 80.0]) and ident["count"] == 5 and ident["last"] == 80.0
    assert S.axis_identity([0.0, 20.0, 40.0, 60.0, 80.0 + 1e-12])["sha256"] != ident["sha256"]


def test_auto_chunks_split_leading_axes_within_budget():
    spec = SweepSpec(dict(axes=dict(theta_i="10:80:10", theta_r={"start": 0, "stop": 85, "num": 64},
                                    sigma={"start": 0.05, "stop": 1, "num": 100}),
                          fixed=dict(n=1.6, k=2.1), memory_budget=65536, dtype="float64"))
    # 4096 points per chunk at most: sigma whole (100), theta_r split into 40s, theta_i into 1s
    assert spec.chunks == (1, 40, 100) and spec.chunk_grid == (8, 2, 1) and spec.n_chunks == 16
    assert spec.chunk_points * 8 <= spec.memory_budget // 2
    pts = SweepSpec(dict(axes=spec.axes, fixed=dict(n=1.6, k=2.1), chunks=dict(points=700)))
    assert pts.chunks == (1, 7, 100)
    red = SweepSpec(dict(axes=spec.axes, fixed=dict(n=1.6, k=2.1), reduce=dict(over=["theta_r"]),
                         chunks=dict(points=700)))
    assert red.dims == ("theta_i", "sigma") and red.chunks == (1, 10) and red.chunk_points == 640


@pytest.mark.parametrize("quantity,dtype,chunks", [("dop", "float32", {"theta_i": 3, "sigma": 7}),
                                                   ("f00", "float64", {"points": 50})],
                         ids=["dop-f32-axis-chunks", "f00-f64-point-chunks"])
def test_small_sweep_equals_grid(tmp_path, quantity, dtype, chunks):
    axes = dict(theta_i=[20.0, 35.0, 50.0, 65.0], theta_r="0:85:17", n=[1.2, 1.6], sigma=[0.1, 0.2, 0.3, 0.5, 0.7, 0.8,
                                                                                         0.9, 1.0])
    spec = SweepSpec(dict(axes=axes, fixed=dict(k=2.1, kd=0.2, c=-0.3), quantity=quantity, dtype=dtype,
                          chunks=chunks))
    assert spec.n_chunks > 1
    res = pbrdf_cl.sweep(spec, tmp_path / "s.zarr", progress=False)
    assert res.complete and res.chunks_computed == spec.n_chunks and res.points_computed == spec.points
    ds = xr.open_zarr(tmp_path / "s.zarr")
    want = pbrdf_cl.grid(spec.axes, spec.fixed, quantity=quantity, dtype=dtype)
    got = ds[spec.quantity]  # the canonical name ("f00" is the alias of "brdf")
    assert got.dims == want.dims and got.dtype == want.dtype
    np.testing.assert_array_equal(got.values, want.values)  # the same kernels on sub-boxes: bit-identical
    assert got.encoding["chunks"] == spec.chunks  # one Zarr chunk per compute chunk
    for n in want.dims:
        np.testing.assert_array_equal(ds[n].values, want[n].values)
        assert ds[n].attrs["units"] == want[n].attrs["units"]
    assert ds.attrs["sweep_spec_sha256"] == spec.sha256 and json.loads(ds.attrs["sweep_spec"]) == spec.canonical()
    assert ds.attrs["sweep_complete"] is True and ds.attrs["fixed_k"] == 2.1
    assert ds.attrs["quantity"] == spec.quantity == pbrdf_cl.quantities.canonical(quantity)
    assert "_sweep" not in ds.variables


def test_url_store(tmp_path):
    """A store given by URL goes through zarr's fsspec stores (an object store on a cluster)."""
    spec = SweepSpec(dict(axes=dict(theta_r="0:85:5", sigma=[0.1, 0.3, 0.5]), fixed=dict(theta_i=40, **STEEL),
                          chunks=dict(theta_r=4)))
    url = f"memory://sweep-{os.getpid()}-{time.monotonic_ns()}.zarr"
    res = pbrdf_cl.sweep(spec, url, progress=False)
    assert res.store == url and res.complete and read_done(spec, url).all()
    assert pbrdf_cl.sweep(spec, url, progress=False).chunks_skipped == spec.n_chunks
    np.testing.assert_array_equal(xr.open_zarr(url).dop.values, pbrdf_cl.grid(spec.axes, spec.fixed).values)
    local = pbrdf_cl.sweep(spec, f"file://{tmp_path}/f.zarr", progress=False)  # file:// is a local path
    assert local.store == str(tmp_path / "f.zarr") and (tmp_path / "f.zarr" / "_sweep" / "done").is_dir()


def test_reduction_sweep_equals_reduce_grid(tmp_path):
    spec = SweepSpec(dict(axes=dict(theta_i="10:80:10", theta_r={"start": 0, "stop": 85, "num": 33},
                                    sigma={"start": 0.05, "stop": 1, "num": 20}, kd=[0.0, 0.2, 0.5]),
                          fixed=dict(n=1.6, k=2.1, c=-0.3), reduce=dict(over=["theta_r", "kd"]),
                          chunks=dict(theta_i=3, sigma=8)))
    assert spec.dims == ("theta_i", "sigma") and spec.n_chunks == 9
    ds = pbrdf_cl.sweep(spec, tmp_path / "r.zarr", progress=False).open()
    want = pbrdf_cl.reduce_grid(spec.axes, spec.fixed, over=["theta_r", "kd"])
    assert set(ds.data_vars) == {"min", "mean", "argmin_theta_r", "argmin_kd"}
    np.testing.assert_array_equal(ds["min"].values, want["min"].values)
    np.testing.assert_array_equal(ds["argmin_theta_r"].values, want["argmin_theta_r"].values)
    np.testing.assert_array_equal(ds["argmin_kd"].values, want["argmin_kd"].values)
    np.testing.assert_allclose(ds["mean"].values, want["mean"].values, rtol=1e-6)  # summation order may differ
    assert ds["argmin_theta_r"].attrs["units"] == "deg" and ds.attrs["reduced_over"] == ["theta_r", "kd"]


def test_memory_stays_within_the_budget(tmp_path):
    spec = SweepSpec(dict(axes=dict(theta_i={"start": 10, "stop": 80, "num": 32},
                                    theta_r={"start": 0, "stop": 85, "num": 64},
                                    n=[1.2, 1.6, 2.0, 2.5], k=[0.0, 1.0, 2.1, 3.0],
                                    sigma={"start": 0.05, "stop": 1, "num": 64}),
                          fixed=dict(kd=0.1, c=-0.3), memory_budget="512 KiB"))
    assert spec.points * 4 >= 10 * spec.memory_budget  # the whole sweep would not fit
    pbrdf_cl.sweep(spec, tmp_path / "warm.zarr", progress=False)  # build the kernels first
    tracemalloc.start()
    try:
        pbrdf_cl.sweep(spec, tmp_path / "m.zarr", progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # host memory: one chunk's values (<= half the budget) and its encoded copy; the device's half
    # (PoCL buffers, allocated by the driver) is not traced here
    assert peak <= spec.memory_budget + (256 << 10), peak
    assert files(tmp_path / "m.zarr") == files(tmp_path / "warm.zarr")


def test_ctrl_c_then_resume_is_bit_identical(spec_file, reference, tmp_path, monkeypatch):
    calls = []
    compute = S.compute_chunk

    def interrupted(spec, eng, i):
        calls.append(i)
        if len(calls) == 7:
            raise KeyboardInterrupt
        return compute(spec, eng, i)
    monkeypatch.setattr(S, "compute_chunk", interrupted)
    store = tmp_path / "s.zarr"
    with pytest.raises(KeyboardInterrupt):
        pbrdf_cl.sweep(spec_file, store, progress=False)
    spec = load_spec(spec_file)
    assert read_done(spec, store).sum() == 6 and not xr.open_zarr(store).attrs["sweep_complete"]
    calls.clear()
    monkeypatch.setattr(S, "compute_chunk", lambda spec, eng, i: calls.append(i) or compute(spec, eng, i))
    res = pbrdf_cl.sweep(spec_file, store, progress=False)
    assert res.chunks_skipped == 6 and res.chunks_computed == 34 and res.complete
    assert sorted(calls) == list(range(6, 40))  # only the missing chunks (6 was interrupted)
    assert files(store) == files(reference)


def test_written_but_unmarked_chunk_is_recomputed(spec_file, reference, tmp_path):
    """Write-then-mark: a chunk without its done mark counts as missing, whatever its data holds."""
    store = tmp_path / "s.zarr"
    pbrdf_cl.sweep(spec_file, store, progress=False)
    spec = load_spec(spec_file)
    for i in (5, 39):  # an inner chunk and the (short) last one
        key = ".".join(str(j) for j in spec.chunk_index(i))
        (store / "dop" / key).write_bytes(b"torn write")
        (store / "_sweep" / "done" / str(i)).unlink()
    (store / "dop" / "0.0.0.0.1f2e3d4c.partial").write_bytes(b"left by a kill")
    res = pbrdf_cl.sweep(spec_file, store, progress=False)
    assert res.chunks_computed == 2 and res.chunks_skipped == 38
    assert files(store) == files(reference)


def test_kill_9_then_resume_is_bit_identical(spec_file, reference, tmp_path):
    store = tmp_path / "killed.zarr"
    cmd = [sys.executable, "-m", "pbrdf_cl", "sweep", str(spec_file), "--out", str(store), "--quiet"]
    env = dict(os.environ, PYTHONPATH=PACKAGE_ROOT, PYTHONWARNINGS="ignore")
    proc = subprocess.Popen(cmd, env=dict(env, **{S.DELAY_ENV: "0.08"}), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while n_done(store) < 4 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        assert proc.poll() is None, proc.communicate()
        os.kill(proc.pid, signal.SIGKILL)  # half the delay lies between the write and the mark
    finally:
        proc.kill()
        proc.communicate()
    done = n_done(store)
    assert proc.returncode == -signal.SIGKILL and 4 <= done < 40
    again = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120, check=False)
    assert again.returncode == 0, again.stderr
    assert f"sweep: {40 - done} of 40 chunks computed ({done} already done)" in again.stdout
    assert not list(store.rglob("*.partial"))
    assert files(store) == files(reference)


def test_local_cluster_gives_the_same_store(spec_file, reference, tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    store = tmp_path / "cluster.zarr"
    # start locally, stop after 10 chunks, finish on a 2-worker cluster: the results land in one store
    compute, calls = S.compute_chunk, []

    def interrupted(spec, eng, i):
        calls.append(i)
        if len(calls) > 10:
            raise KeyboardInterrupt
        return compute(spec, eng, i)
    monkeypatch.setattr(S, "compute_chunk", interrupted)
    with pytest.raises(KeyboardInterrupt):
        pbrdf_cl.sweep(spec_file, store, progress=False)
    monkeypatch.undo()

    def timeout(*_):
        raise TimeoutError("the LocalCluster sweep hung")
    old = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(120)
    cluster = client = None
    try:
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
        client = distributed.Client(cluster)
        res = pbrdf_cl.sweep(spec_file, store, client=client, progress=False)
        engines = client.run(lambda: len(sys.modules["pbrdf_cl.store.cluster"]._ENGINES))
        runners = client.run(lambda: len(sys.modules["pbrdf_cl.analysis.sweeps"]._RUNNERS))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    assert res.chunks_skipped == 10 and res.chunks_computed == 30 and res.complete
    # every worker that computed chunks built one engine (and opened the store once), then reused them
    assert len(engines) == 2 and set(engines.values()) <= {0, 1} and sum(engines.values()) >= 1
    assert engines == runners
    assert files(store) == files(reference)


def test_example_spec_runs(tmp_path):
    spec = load_spec(ROOT / "examples" / "sweep_sigma_theta.toml")
    assert spec.n_chunks == 32 and spec.points == 8 * 86 * 4 * 64
    res = pbrdf_cl.sweep(spec, tmp_path / "ex.zarr", progress=False)
    ds = res.open()
    assert res.complete and ds.dop.shape == (8, 86, 4, 64) and ds.attrs["title"].startswith("DOP of 45# steel")
    assert float(ds.dop.sel(theta_i=40, theta_r=40, phi=180, sigma=0.5, method="nearest")) == pytest.approx(
        float(pbrdf_cl.dop(40, 40, n=1.6, k=2.139, sigma=ds.sigma.sel(sigma=0.5, method="nearest").item(),
                           ks=0.9, kd=0.15, c=-0.3)), abs=2e-6)


BAD = [
    ({"axes": {"sigmaa": [0.1]}}, "axes.sigmaa: unknown axis; valid names are theta_i"),
    ({"axes": {"sigma": "1:0:0.1"}}, 'axes.sigma = "1:0:0.1": the step 0.1 goes up from 1 but the stop 0 is below it; '
                                     "write 1:0:-0.1 to count down, or 0:1:0.1"),
    ({"axes": {"sigma": {"start": 0.1, "stop": 1, "num": 0}}},
     "axes.sigma = {start = 0.1, stop = 1, num = 0}: count 0 is not an integer >= 2; write 0.1:1@N with N >= 2"),
    ({"axes": {"sigma": {"start": 0.1, "stop": 1, "step": 0.2}}},
     "axes.sigma = {start = 0.1, stop = 1, step = 0.2}: steps of 0.2 from 0.1 miss the stop 1 (the last is 0.9); "
     "write 0.1:0.9:0.2, or 0.1:1@5 for 5 values from 0.1 to 1"),
    ({"axes": {"sigma": []}}, "axes.sigma: empty list"),
    ({"axes": {"sigma": "0.1:1:0"}}, 'axes.sigma = "0.1:1:0": the step must not be 0; write 0.1:1:STEP, or 0.1:1@N'),
    ({"axes": {"sigma": [0.1, 0.3, 0.2]}}, "axes.sigma: values must be strictly increasing or decreasing"),
    ({"axes": {"theta_r": "0:95:5"}}, "axes.theta_r: theta_r must be in [0, 90) degrees, got 90.0"),
    ({"axes": {"theta_r": "0:85:256"}}, 'axes.theta_r = "0:85:256": step 256 is larger than the range 0..85; '
                                        "for 256 values write 0:85@256"),
    ({"axes": {"sigma": 0.5}}, "axes.sigma: a single value; give it under [fixed]"),
    ({"fixed": {"n": "high"}}, "fixed.n: 'high' is not a number"),
    ({"fixed": {"sigma": 0.5}}, "fixed.sigma: sigma is also an axis"),
    ({"quantity": "stokes"}, "quantity: 'stokes' is not available for sweep: a vector per point"),
    ({"quantity": "s1"}, "quantity: unknown quantity 's1'; valid names are dop, brdf, aop"),
    ({"dtype": "float16"}, "dtype: must be float32 or float64"),
    ({"axes_": {}}, "unknown key 'axes_'; valid keys are"),
    ({"memory_budget": "lots"}, "memory_budget: 'lots' is not a size"),
    ({"chunks": {"theta_r": 20}, "memory_budget": 4096},
     ("chunks: a chunk of 20 x 50 = 1000 points x 4 bytes = 3.906 KiB is larger than the budget for one chunk's "
      "values, half of memory_budget = 4 KiB")),
    ({"chunks": {"points": 10 ** 6}, "memory_budget": "1 MiB"}, "chunks.points: a chunk of 1000000 points x 4 bytes"),
    ({"chunks": {"phi": 2}}, "chunks.phi: not an axis of this sweep (theta_r, sigma)"),
    ({"chunks": {"points": 100, "sigma": 2}}, "chunks: give either points = N or per-axis sizes, not both"),
    ({"reduce": {"over": ["kd"]}}, "reduce.over: 'kd' is not an axis of this sweep"),
    ({"reduce": {"over": ["theta_r"]}, "chunks": {"theta_r": 5}}, "chunks.theta_r: theta_r is reduced"),
]


@pytest.mark.parametrize("change,message", BAD, ids=[m.split(":")[0] + f"-{i}" for i, (_, m) in enumerate(BAD)])
def test_bad_specs_are_refused_with_the_field_named(change, message):
    d = dict(axes=dict(theta_r="0:85:1.7", sigma={"start": 0.05, "stop": 1, "num": 50}),
             fixed=dict(theta_i=40, **STEEL))
    for key, value in change.items():
        if key in ("axes", "fixed"):
            d[key] = {**d[key], **value}
        else:
            d[key] = value
    with pytest.raises(SpecError) as err:
        SweepSpec(d)
    assert message in str(err.value)


def test_store_of_another_spec_or_kernels_or_a_foreign_folder_is_refused(spec_file, reference, tmp_path, capsys,
                                                                          monkeypatch):
    other = tmp_path / "other.toml"
    other.write_text(SPEC_TOML.replace('num = 24', 'num = 25').replace('dtype = "float32"', 'dtype = "float64"'))
    before = files(reference)
    with pytest.raises(SpecError) as err:
        pbrdf_cl.sweep(other, reference, progress=False)
    msg = str(err.value)
    assert "was started with a different spec" in msg and "choose another --out, or delete" in msg
    assert 'dtype: "float32" in the store, "float64" now' in msg and "axes.sigma: 24 values" in msg
    assert files(reference) == before  # untouched
    monkeypatch.setattr(pbrdf_cl.device.sources, "_KERNELS_SHA256", "0" * 64)  # as if another pbrdf-cl ran it
    with pytest.raises(SpecError, match="was started with other OpenCL kernel sources"):
        pbrdf_cl.sweep(spec_file, reference, progress=False)
    with pytest.raises(SpecError, match="other OpenCL kernel sources"):  # what a cluster worker checks
        S._Runner(load_spec(spec_file), str(reference))
    monkeypatch.undo()
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    assert cli.main(["sweep", str(spec_file), "--out", str(tmp_path / "foreign"), "--quiet"]) == 1
    assert "is not a pbrdf-cl sweep store" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[axes]\nsigma = "1:0:0.1"\n')
    assert cli.main(["sweep", str(bad), "--out", str(tmp_path / "x.zarr")]) == 1
    assert capsys.readouterr().err.strip() == ('pbrdf-cl: error: axes.sigma = "1:0:0.1": the step 0.1 goes up from 1 '
                                               "but the stop 0 is below it; write 1:0:-0.1 to count down, or 0:1:0.1")
    assert not (tmp_path / "x.zarr").exists()
    assert cli.main(["sweep", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "y.zarr")]) == 1
    assert "cannot read the spec" in capsys.readouterr().err


def test_cli_sweep_resumes_a_complete_store(spec_file, reference, capsys):
    assert cli.main(["sweep", str(spec_file), "--out", str(reference), "--quiet"]) == 0
    assert "sweep: 0 of 40 chunks computed (40 already done)" in capsys.readouterr().out
