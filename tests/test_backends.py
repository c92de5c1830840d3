"""Runs on any machine: the device probe and its caches, the default device order, unusable
devices (a faked build failure, as the PyPI PoCL 3.0 gives on CPUs its LLVM 14 does not know),
the numpy backend's dense paths, Intel-runtime registration, and the CLI's one-line reports of
environment problems."""
import json
import os
import subprocess
import sys
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.compute import dense as G
from pbrdf_cl.device import choice as C
from pbrdf_cl.device import drivers, fallback, sources
from pbrdf_cl.device import engine as E
from pbrdf_cl.model import reference

from conftest import DEVICES, requires_opencl

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)
EVERY_DEVICE = "/"  # a substring of every "platform / device": the fake failure hits them all


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """Empty probe caches (process and disk), no warnings given yet, no default engine."""
    monkeypatch.setenv("PBRDF_CL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(C, "_PROBES", {})
    monkeypatch.setattr(C, "_WARNED", set())
    monkeypatch.setattr(fallback, "_default_engine", None)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    return tmp_path / "cache"


def _id(dev):
    return next(f"{p}:{i}" for p, i, _, d in pbrdf_cl.list_devices() if d.int_ptr == dev.int_ptr)


# --------------------------------------------------------------------------------------------
# the probe

def test_probe_returns_specs_check_values(engine, fresh):
    r = E.probe(engine.device)
    assert r.usable and not r.cached and "check values" in r.reason
    assert set(r.values) == ({"float32", "float64"} if E.has_fp64(engine.device) else {"float32"})
    for dtype, values in r.values.items():
        # SPEC's table is rounded to 6 decimals; the kernels agree with the reference to 2e-5 / 1e-10
        np.testing.assert_allclose(values, C.PROBE_SPEC, atol=5e-7 + C.PROBE_TOLERANCE[dtype])
    np.testing.assert_allclose(reference.evaluate("dop", *C.PROBE_POINTS.T), C.PROBE_SPEC, atol=5e-7)


def test_probe_is_cached_in_the_process_and_on_disk(engine, fresh):
    first = E.probe(engine.device)
    assert not first.cached and first.seconds > 0
    assert E.probe(engine.device) is first  # the process cache
    entries = json.loads((fresh / f"probe-v{C.PROBE_CACHE_VERSION}.json").read_text())
    assert list(entries) == [C._probe_key(engine.device)]
    E.clear_probe_cache()
    again = E.probe(engine.device)  # a new process would read this from disk
    assert again.cached and again.usable == first.usable and again.reason == first.reason
    assert again.values == first.values
    # the key changes with the kernel sources: other kernels are probed afresh
    key = C._probe_key(engine.device)
    sources._KERNELS_SHA256, saved = "0" * 64, E.kernels_sha256()
    try:
        assert C._probe_key(engine.device) != key
    finally:
        sources._KERNELS_SHA256 = saved


def test_probe_cache_folder_that_cannot_be_written_is_harmless(engine, monkeypatch):
    monkeypatch.setenv("PBRDF_CL_CACHE_DIR", "/dev/null/pbrdf-cl")
    monkeypatch.setattr(C, "_PROBES", {})
    assert E.probe(engine.device).usable


def test_first_error_line_finds_the_error_in_a_build_log():
    log = ("clBuildProgram failed: BUILD_PROGRAM_FAILURE - clBuildProgram failed: BUILD_PROGRAM_FAILURE\n\n"
           "Build on <pyopencl.Device 'pthread-AMD EPYC' on 'Portable Computing Language'>:\n\n"
           "error: unknown target CPU 'generic'\nnote: valid target CPU values are: nocona, core2\n"
           "Device pthread-AMD EPYC failed to build the program\n(options: -I /x)\n")
    assert E.first_error_line(log) == "error: unknown target CPU 'generic'"
    assert E.first_error_line("/root/.cache/pocl/kcache/tempfile_3rv0n1.cl:1:2: error: boom") == "error: boom"
    assert E.first_error_line("") == "unknown error"


# --------------------------------------------------------------------------------------------
# choosing a device

def test_default_order_gpu_then_pocl_then_other_cpus_never_the_simulator():
    dt = E.cl.device_type

    class Plat:
        def __init__(self, name, version=""):
            self.name, self.version = name, version

    class Dev:
        def __init__(self, kind):
            self.type = kind
    pocl30, pocl31 = Plat("Portable Computing Language", "OpenCL 3.0 PoCL 3.0"), \
        Plat("Portable Computing Language", "OpenCL 3.0 PoCL 3.1+debian")
    rows = [(Plat("Intel(R) OpenCL"), Dev(dt.CPU)), (pocl30, Dev(dt.CPU)), (Plat("Other"), Dev(dt.ACCELERATOR)),
            (pocl31, Dev(dt.CPU)), (Plat("NVIDIA CUDA"), Dev(dt.GPU))]
    order = sorted(rows, key=lambda pd: C._rank(*pd))
    assert [(p.name, p.version) for p, _ in order] == [
        ("NVIDIA CUDA", ""), ("Portable Computing Language", "OpenCL 3.0 PoCL 3.1+debian"),
        ("Portable Computing Language", "OpenCL 3.0 PoCL 3.0"), ("Intel(R) OpenCL", ""), ("Other", "")]
    assert E.is_simulator(Plat("Oclgrind")) and not E.is_simulator(pocl30)


@requires_opencl
def test_default_device_is_the_first_usable_candidate(fresh):
    first = E.candidates()[0]
    if E.probe(first).usable:
        assert E.select_device().int_ptr == first.int_ptr
    assert not E.is_simulator(E.select_device().platform)


@requires_opencl
def test_unusable_device_is_skipped_with_one_warning_and_refused_when_chosen(engine, fresh, monkeypatch):
    dev = engine.device
    monkeypatch.setenv(C.FAKE_FAILURE_ENV, dev.name.strip())
    r = E.probe(dev)
    assert not r.usable and "\n" not in r.reason
    assert r.reason.startswith("float32 build failed: error: unknown target CPU 'generic'")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            chosen = E.select_device()
        except E.OpenCLUnavailableError as exc:
            chosen = None
            assert "unknown target CPU" in str(exc) and "pocl-opencl-icd" in str(exc)
        E.select_device() if chosen is not None else None  # a second choice warns no more
    skipped = [str(w.message) for w in caught if issubclass(w.category, E.DeviceWarning)]
    mine = [m for m in skipped if f"({E.describe(dev)})" in m]
    order = [d.int_ptr for d in E.candidates()]
    if chosen is None or order.index(dev.int_ptr) < order.index(chosen.int_ptr):  # it was tried, and skipped
        assert len(mine) == 1 and "\n" not in mine[0]
        assert mine[0].startswith(f"skipping OpenCL device {_id(dev)} (") and "unknown target CPU" in mine[0]
    else:
        assert not mine  # a usable device came first: this one was never probed for the default
    assert chosen is None or chosen.int_ptr != dev.int_ptr
    # an explicit choice is an error that says so, whichever way it is made
    for make in (lambda: pbrdf_cl.Engine(_id(dev)), lambda: pbrdf_cl.Engine(dev)):
        with pytest.raises(E.DeviceUnusableError, match=r"cannot run pbrdf-cl: float32 build failed: error: "
                                                         r"unknown target CPU 'generic'.*pbrdf-cl devices"):
            make()
    monkeypatch.setenv("PYOPENCL_CTX", _id(dev))
    with pytest.raises(E.DeviceUnusableError, match=r"PYOPENCL_CTX=.*cannot run pbrdf-cl"):
        E.get_default_engine()


def test_no_usable_device_falls_back_to_numpy_once_and_opencl_refuses(fresh, monkeypatch):
    monkeypatch.setenv(C.FAKE_FAILURE_ENV, EVERY_DEVICE)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = pbrdf_cl.dop(40, [20.0, 45.0], **STEEL)
        d2 = pbrdf_cl.dop(40, 45.0, **STEEL, dtype="float32")
        eng = pbrdf_cl.get_default_engine()
    assert eng.is_numpy and "unknown target CPU" in eng.reason
    np.testing.assert_array_equal(d, pbrdf_cl.dop(40, [20.0, 45.0], **STEEL, backend="numpy"))
    assert d2.dtype == np.float32 and abs(float(d2) - 0.167590) < 5e-7
    notes = [str(w.message) for w in caught if issubclass(w.category, E.DeviceWarning)]
    fallback = [m for m in notes if m.startswith("computing on the numpy backend")]
    assert len(fallback) == 1 and "\n" not in fallback[0]
    assert "pocl-opencl-icd" in fallback[0] and "pbrdf-cl[intel-cpu]" in fallback[0]
    for call in (lambda: pbrdf_cl.dop(40, 45, **STEEL, backend="opencl"),
                 lambda: pbrdf_cl.grid(dict(theta_r=[10.0, 20.0]), dict(theta_i=40, **STEEL), backend="opencl"),
                 lambda: E.get_default_engine("opencl")):
        with pytest.raises(E.OpenCLUnavailableError, match="backend='opencl': no usable OpenCL device"):
            call()


# --------------------------------------------------------------------------------------------
# the numpy backend: the same factor tables, with reference.py, within the memory budget

def test_boxes_cover_the_array_in_order_within_the_limit():
    for shape, limit in (((3, 4, 5), 7), ((3, 4, 5), 60), ((1, 1, 9), 2), ((2, 3), 1), ((5, 1, 4, 3), 13)):
        seen = np.zeros(int(np.prod(shape)), int)
        expect = 0
        for start, box in G._boxes(shape, limit):
            size = int(np.prod([s.stop - s.start for s in box]))
            assert start == expect and size <= limit
            flat = np.arange(seen.size).reshape(shape)[box].reshape(-1)
            np.testing.assert_array_equal(flat, np.arange(start, start + size))  # contiguous
            seen[flat] += 1
            expect += size
        assert (seen == 1).all()


AXES = dict(theta_i=np.array([15.0, 40, 70]), theta_r=np.linspace(0, 85, 6), phi=np.array([120.0, 180]),
            n=np.array([1.2, 1.6, 3.0]), k=np.array([0.0, 2.1]), sigma=np.array([0.08, 0.3, 0.9]),
            ks=np.array([0.5, 1.0]), kd=np.array([0.0, 0.2, 2.0]), c=np.array([-0.7, 0.0]))


@pytest.mark.parametrize("shadowing", ["paper", "smith", "none"])
@pytest.mark.parametrize("quantity", ["dop", "f00"])
def test_numpy_dense_paths_equal_the_reference_point_by_point(quantity, shadowing):
    mesh = np.meshgrid(*AXES.values(), indexing="ij")
    want = reference.evaluate("dop" if quantity == "dop" else "brdf", *mesh, shadowing=shadowing)
    for budget in (G.DEFAULT_BUDGET, 40_000):  # one box, and many boxes and geometry blocks
        got = pbrdf_cl.grid(AXES, quantity=quantity, dtype="float64", shadowing=shadowing, backend="numpy",
                            memory_budget=budget)
        assert got.dims == tuple(AXES) and got.dtype == np.float64
        np.testing.assert_allclose(got.values, want, rtol=1e-13, atol=1e-300)
    over = ("theta_r", "sigma", "c")
    red = pbrdf_cl.reduce_grid(AXES, over=over, quantity=quantity, dtype="float64", shadowing=shadowing,
                               backend="numpy", memory_budget=60_000)
    ax = tuple(list(AXES).index(n) for n in over)
    np.testing.assert_allclose(red["min"].values, want.min(axis=ax), rtol=1e-13)
    np.testing.assert_allclose(red["mean"].values, want.mean(axis=ax), rtol=1e-12)
    moved = np.moveaxis(want, ax, (-3, -2, -1))
    arg = np.unravel_index(moved.reshape(moved.shape[:-3] + (-1,)).argmin(axis=-1), [AXES[n].size for n in over])
    for name, idx in zip(over, arg):
        np.testing.assert_array_equal(red[f"argmin_{name}"].values, AXES[name][idx])


@pytest.mark.parametrize("quantity", ["dop", "f00"])
def test_numpy_backend_equals_every_device(engine, quantity):
    kw = dict(quantity=quantity, dtype="float64", shadowing="smith")
    np.testing.assert_allclose(pbrdf_cl.grid(AXES, engine=engine, **kw).values,
                               pbrdf_cl.grid(AXES, backend="numpy", memory_budget=50_000, **kw).values, rtol=1e-12)
    a = pbrdf_cl.reduce_grid(AXES, over=["n", "kd"], engine=engine, **kw)
    b = pbrdf_cl.reduce_grid(AXES, over=["n", "kd"], backend="numpy", **kw)
    for v in a.data_vars:
        np.testing.assert_allclose(a[v].values, b[v].values, rtol=1e-12)


def test_numpy_objective_equals_the_reference_and_the_device():
    ti, tr = np.repeat([30.0, 40.0, 50.0], 4), np.tile([20.0, 35.0, 50.0, 65.0], 3)
    dop = reference.evaluate("dop", ti, tr, 180.0, *STEEL.values())
    data = dict(theta_i=ti, theta_r=tr, dop=dop + 0.001 * np.sin(np.arange(ti.size)), dop_std=np.full(ti.size, 0.002))
    grid = dict(n=np.linspace(1, 3, 7), k=np.linspace(0, 4, 9), sigma=np.array([0.2, 0.5]), ks=0.9,
                kd=np.array([0.0, 0.15, 0.4]), c=np.array([-0.3, 0.0]))
    res = pbrdf_cl.objective(data, grid=grid, dtype="float64", backend="numpy", memory_budget=30_000)
    mesh = np.meshgrid(grid["n"], grid["k"], grid["sigma"], grid["kd"], grid["c"], indexing="ij")
    d = reference.evaluate("dop", ti[:, None], tr[:, None], 180.0, *(m.reshape(1, -1) for m in mesh[:3]), 0.9,
                           mesh[3].reshape(1, -1), mesh[4].reshape(1, -1))
    want = (((d - data["dop"][:, None]) / 0.002) ** 2).sum(axis=0).reshape(mesh[0].shape)
    np.testing.assert_allclose(res.sse.values, want, rtol=1e-12)
    assert res.best["sse"][0] == pytest.approx(want.min(), rel=1e-12)
    pts = dict(n=mesh[0].ravel()[:20], k=mesh[1].ravel()[:20], sigma=mesh[2].ravel()[:20], ks=0.9,
               kd=mesh[3].ravel()[:20], c=mesh[4].ravel()[:20])
    by_points = pbrdf_cl.objective(data, points=pts, dtype="float64", backend="numpy")
    np.testing.assert_allclose(by_points.sse, want.ravel()[:20], rtol=1e-12)
    if DEVICES:
        dev = pbrdf_cl.objective(data, grid=grid, dtype="float64", backend="opencl")
        np.testing.assert_allclose(dev.sse.values, res.sse.values, rtol=1e-11)


def test_numpy_grid_stays_within_its_memory_budget():
    axes = dict(theta_i=np.linspace(10, 80, 8), theta_r=np.linspace(0, 85, 50), sigma=np.linspace(0.05, 1, 50),
                kd=np.linspace(0, 1, 40), c=np.linspace(-1, 0, 5))  # 4M points: 32 MB of float64
    budget = 1 << 20
    tracemalloc.start()
    try:
        da = pbrdf_cl.grid(axes, dict(n=1.6, k=2.1), dtype="float64", backend="numpy", memory_budget=budget)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak - da.values.nbytes <= 2 * budget, (peak, da.values.nbytes)


def test_fit_and_map_run_on_the_numpy_backend():
    from pbrdf_cl.analysis import maps
    res = pbrdf_cl.fit(ROOT / "examples" / "steel_435nm.csv", backend="numpy")
    ref = pbrdf_cl.fit(ROOT / "examples" / "steel_435nm.csv") if DEVICES else res
    assert res.chi2 == pytest.approx(ref.chi2, rel=1e-3, abs=1e-6)
    ds = maps.make_map("theta_r=0:85@16", "sigma=0.05:1@8", dict(theta_i=40, **{k: v for k, v in STEEL.items()
                                                                                if k != "sigma"}),
                       derivative="sigma", backend="numpy")
    want = reference.evaluate("dop", 40.0, ds.theta_r.values[None, :], 180.0, 1.6, 2.139, ds.sigma.values[:, None],
                              0.9, 0.15, -0.3)
    np.testing.assert_allclose(ds["dop"].values, want, rtol=1e-13)


# --------------------------------------------------------------------------------------------
# Intel's CPU runtime from pip

def test_intel_runtime_is_registered_beside_the_other_drivers(monkeypatch, tmp_path):
    system = tmp_path / "vendors"
    system.mkdir()
    (system / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    (system / "notes.txt").write_text("not an ICD file")
    lib = tmp_path / "env" / "lib" / "libintelocl.so"
    lib.parent.mkdir(parents=True)
    lib.write_bytes(b"")
    monkeypatch.setattr(drivers, "find_intel_runtime", lambda: (lib, []))
    monkeypatch.setattr(drivers, "_registered", None)
    monkeypatch.setenv("PBRDF_CL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("OCL_ICD_VENDORS", str(system))
    done = drivers.register_pip_drivers()
    folder = Path(os.environ["OCL_ICD_VENDORS"])
    assert done["vendors"] == str(folder) and done["previous_vendors"] == str(system)
    assert folder.is_relative_to(tmp_path / "cache")
    assert sorted(f.name for f in folder.iterdir()) == ["nvidia.icd", "pbrdf-cl-intel-cpu.icd"]
    assert (folder / "pbrdf-cl-intel-cpu.icd").read_text().strip() == str(lib)
    assert (folder / "nvidia.icd").read_text() == "libnvidia-opencl.so.1\n"
    assert drivers.register_pip_drivers() is done  # once per process
    # without OCL_ICD_VENDORS the loader's own folder is copied
    monkeypatch.setattr(drivers, "_registered", None)
    monkeypatch.delenv("OCL_ICD_VENDORS")
    monkeypatch.setattr(drivers, "SYSTEM_VENDORS", str(system))
    drivers.register_pip_drivers()
    assert (Path(os.environ["OCL_ICD_VENDORS"]) / "nvidia.icd").is_file()
    # and it can be turned off
    monkeypatch.setattr(drivers, "_registered", None)
    monkeypatch.setenv("OCL_ICD_VENDORS", str(system))
    monkeypatch.setenv("PBRDF_CL_NO_DRIVER_REGISTRATION", "1")
    assert drivers.register_pip_drivers() == {} and os.environ["OCL_ICD_VENDORS"] == str(system)


@pytest.mark.skipif(drivers.find_intel_runtime() is None,
                    reason="Intel's CPU runtime (pbrdf-cl[intel-cpu]) is not installed")
def test_installed_intel_runtime_is_found_usable_and_matches_the_reference():
    code = ("import pbrdf_cl, pbrdf_cl.device.engine as e, numpy as np\n"
            "devs = [d for *_, d in e.list_devices() if 'Intel' in d.platform.name]\n"
            "assert devs, e.list_devices()\n"
            "r = e.probe(devs[0]); assert r.usable, r.reason\n"
            "eng = pbrdf_cl.Engine(devs[0])\n"
            "x = np.linspace(0, 85, 200)\n"
            "d = pbrdf_cl.dop(40, x, engine=eng, n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)\n"
            "w = pbrdf_cl.dop(40, x, backend='numpy', n=1.6, k=2.139, sigma=0.5, ks=0.9, kd=0.15, c=-0.3)\n"
            "assert np.max(np.abs(d - w)) < 1e-12\n"
            "print(eng.description)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, PYTHONPATH=PACKAGE_ROOT, OCL_ICD_VENDORS=str(ROOT / "nonexistent")))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("Intel(R) OpenCL /")


# --------------------------------------------------------------------------------------------
# the command line: every command on the numpy backend, one line per environment problem

def run_cli(*args, env=None, cwd=None, timeout=600):
    full = dict(os.environ, PYTHONPATH=PACKAGE_ROOT)
    full.pop("PYTHONWARNINGS", None)
    full.update(env or {})
    return subprocess.run([sys.executable, "-m", "pbrdf_cl", *args], capture_output=True, text=True,
                          timeout=timeout, env=full, cwd=cwd)


def one_line_error(proc, *words):
    assert proc.returncode != 0, proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("pbrdf-cl: error: ")]
    assert len(errors) == 1, proc.stderr
    for w in words:
        assert w in errors[0], errors[0]
    return errors[0]


EVAL = ["eval", "--theta-i", "40", "--theta-r", "20:65:5", "--n", "1.6", "--k", "2.139", "--sigma", "0.5",
        "--ks", "0.9", "--kd", "0.15", "--c", "-0.3", "--json"]


def test_every_command_runs_on_the_numpy_backend_when_no_device_is_usable(tmp_path):
    env = {C.FAKE_FAILURE_ENV: EVERY_DEVICE, "PBRDF_CL_CACHE_DIR": str(tmp_path / "cache")}
    spec = tmp_path / "spec.toml"
    spec.write_text('[axes]\ntheta_r = "0:80:20"\nsigma = [0.2, 0.5]\n[fixed]\ntheta_i = 40\nn = 1.6\nk = 2.1\n')
    runs = {
        "devices": ["devices"],
        "eval": EVAL,
        "fit": ["fit", str(ROOT / "examples" / "steel_435nm.csv"), "--quiet", "--json", str(tmp_path / "fit.json")],
        "map": ["map", "--x", "theta_r=0:85@32", "--y", "sigma=0.05:1@16", "--fix", "theta_i=40", "n=1.6", "k=2.1",
                "kd=0.2", "--derivative", "sigma", "--out", str(tmp_path / "map.png")],
        "sweep": ["sweep", str(spec), "--out", str(tmp_path / "s.zarr"), "--quiet"],
        "bench": ["bench", "--quick", "--json", str(tmp_path / "bench.json")],
    }
    for name, args in runs.items():
        proc = run_cli(*args, env=env, cwd=tmp_path)
        assert proc.returncode == 0, (name, proc.stderr)
        assert "Traceback" not in proc.stderr, (name, proc.stderr)
        notes = [ln for ln in proc.stderr.splitlines() if "computing on the numpy backend" in ln]
        if name == "devices":
            assert "UNUSABLE: float32 build failed: error: unknown target CPU 'generic'" in proc.stdout
            assert "no usable OpenCL device" in proc.stdout and "pocl-opencl-icd" in proc.stdout
        else:
            assert len(notes) == 1 and notes[0].startswith("pbrdf-cl: warning: "), (name, proc.stderr)
    out = json.loads(run_cli(*EVAL, env=env).stdout)
    assert out["backend"] == "numpy" and abs(out["rows"][5]["dop"] - 0.167590) < 5e-7
    bench = json.loads((tmp_path / "bench.json").read_text())
    assert bench["device"].startswith("numpy") and all(r["rate"] > 0 for r in bench["rows"])
    fit = json.loads((tmp_path / "fit.json").read_text())["fits"]["six-param"]
    assert fit["reduced_chi2"] < 3
    # --backend opencl turns the fallback into an error
    one_line_error(run_cli(*EVAL, "--backend", "opencl", env=env), "backend='opencl': no usable OpenCL device",
                   "unknown target CPU")


def test_cli_reports_environment_problems_in_one_line(tmp_path):
    env = {"PBRDF_CL_CACHE_DIR": str(tmp_path / "cache")}
    # no OpenCL at all
    one_line_error(run_cli(*EVAL, "--backend", "opencl", env={**env, "OCL_ICD_VENDORS": str(tmp_path / "none"),
                                                              "PBRDF_CL_NO_DRIVER_REGISTRATION": "1"}),
                   "no OpenCL platform found", "remedies")
    # an explicit device that is unusable, or absent
    if DEVICES:
        one_line_error(run_cli(*EVAL, "--device", _id(DEVICES[0]), env={**env, C.FAKE_FAILURE_ENV: EVERY_DEVICE}),
                       "cannot run pbrdf-cl", "unknown target CPU")
    one_line_error(run_cli(*EVAL, "--device", "99:0", env=env), "no OpenCL device 99:0")
    # outputs that cannot be written: refused before any work
    blocked = "/dev/null/out"
    one_line_error(run_cli("reproduce", "--out", blocked, env=env), "--out", "cannot write into", "choose a writable")
    one_line_error(run_cli("fit", str(ROOT / "examples" / "steel_435nm.csv"), "--json", blocked + "/f.json",
                           env=env), "--json", "cannot write")
    one_line_error(run_cli("map", "--x", "theta_r=0:85@8", "--y", "sigma=0.1:1@8", "--fix", "theta_i=40", "n=1.6",
                           "k=2", "--out", blocked + "/m.png", env=env), "--out", "cannot write")
    one_line_error(run_cli("sweep", str(ROOT / "examples" / "sweep_sigma_theta.toml"), "--out", blocked + "/s.zarr",
                           env=env), "--out", "cannot write")


def _default_device_is_pocl():
    try:
        return E.is_pocl(E.select_device().platform)
    except (E.OpenCLUnavailableError, ValueError):
        return False


@pytest.mark.skipif(not DEVICES or not _default_device_is_pocl(),
                    reason="the default device is not PoCL: only PoCL devices hide behind an unwritable PoCL cache")
def test_cli_unwritable_pocl_cache_is_one_line(tmp_path):
    proc = run_cli(*EVAL, env={"POCL_CACHE_DIR": "/dev/null/pocl", "PBRDF_CL_CACHE_DIR": str(tmp_path)})
    one_line_error(proc, "POCL_CACHE_DIR '/dev/null/pocl' cannot be written", "writable folder")
    proc = run_cli(*EVAL, "--backend", "numpy", env={"POCL_CACHE_DIR": "/dev/null/pocl"})
    assert proc.returncode == 0, proc.stderr


def _platform_name_of_two_devices():
    """A platform name (lower case) that two usable test devices share, or None."""
    names = [d.platform.name.strip().lower() for d in DEVICES]
    return next((n for n in names if names.count(n) >= 2), None)


SHARED_NAME = _platform_name_of_two_devices()


@pytest.mark.skipif(SHARED_NAME is None, reason="needs two usable devices whose platforms share a name")
def test_a_name_matching_several_devices_picks_the_first_usable_one(fresh, monkeypatch):
    matching = [d for d in E.candidates() if d.platform.name.strip().lower() == SHARED_NAME and E.probe(d).usable]
    first, second = matching[:2]
    monkeypatch.setenv(C.FAKE_FAILURE_ENV, E.describe(first))
    assert pbrdf_cl.Engine(SHARED_NAME).device.int_ptr == second.int_ptr
    monkeypatch.setenv(C.FAKE_FAILURE_ENV, SHARED_NAME)
    with pytest.raises(E.DeviceUnusableError, match=rf"device='{SHARED_NAME}'.*cannot run pbrdf-cl"):
        pbrdf_cl.Engine(SHARED_NAME)
