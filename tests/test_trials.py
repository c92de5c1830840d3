"""The guard against drivers that crash (issue #25): trial builds in a child process, stored
verdicts, the fallback to the next device or numpy, the explicit-device error, and the vector widths
chosen per driver.  A child that really dies is made by the test switch PBRDF_CL_FAKE_TRIAL_CRASH
(SIGSEGV, an "LLVM ERROR" line then abort, a hang), so every test runs on any machine with a device."""
import json
import os
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest

import pbrdf_cl
from pbrdf_cl.device import choice, sources, trials
from pbrdf_cl.device import engine as E

from conftest import DEVICES, requires_opencl

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_ROOT = str(Path(pbrdf_cl.__file__).resolve().parent.parent)
CSV = str(ROOT / "examples" / "steel_435nm.csv")
GRID = dict(n=np.linspace(1, 4, 12), k=np.linspace(0, 5, 12), sigma=0.5, kd=0.15, c=-0.3)

# the objective of the example on a small grid, in a fresh process; prints the SSE, the device
# warnings and what the trial machinery did
SCRIPT = f"""
import json, warnings
import numpy as np
import pbrdf_cl
from pbrdf_cl.device import trials
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    r = pbrdf_cl.objective({CSV!r}, grid=dict(n=np.linspace(1, 4, 12), k=np.linspace(0, 5, 12), sigma=0.5,
                                                kd=0.15, c=-0.3))
print(json.dumps(dict(sse=np.asarray(r.sse).ravel().tolist(), stats=trials.STATS,
                      warnings=[str(w.message) for w in caught if issubclass(w.category, pbrdf_cl.DeviceWarning)])))
"""


def run(args, env, timeout=600):
    full = dict(os.environ, PYTHONPATH=PACKAGE_ROOT)
    full.pop("PYOPENCL_CTX", None)
    full.pop("PYTHONWARNINGS", None)
    full.update(env)
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=timeout, env=full)


def device_id(dev):
    return next(f"{p}:{i}" for p, i, _, d in pbrdf_cl.list_devices() if d.int_ptr == dev.int_ptr)


@pytest.fixture
def store(tmp_path, monkeypatch):
    """A fresh verdict store and probe cache for this process and its children."""
    monkeypatch.setenv("PBRDF_CL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(trials, "_MEMORY", {})
    trials._close_child()  # a child of this process compiles into the PoCL cache of its start
    yield tmp_path / "cache"
    trials._close_child()


# ---------------------------------------------------------------------------------------------
# verdict keys and the switches (no device needed)

def test_a_verdict_stands_for_builds_that_differ_only_in_sizes():
    def opts(**d):
        return ["-I", "/anywhere/kernels", "-w", "-DPB_VW=16"] + [f"-D{k}={v}" for k, v in d.items()]
    same = [opts(PB_NNK=256, PB_NM=40, PB_NI=3), opts(PB_NNK=512, PB_NM=44, PB_NI=5)]
    assert trials.family(same[0]) == trials.family(same[1])
    assert trials.family(same[0])[0] == ["-w", "-DPB_VW=16", "-DPB_NNK=n*vw", "-DPB_NM=>vw", "-DPB_NI=<vw"]
    # a size crossing the vector width or its multiples builds other loops: another family
    for other in (opts(PB_NNK=256, PB_NM=40, PB_NI=1), opts(PB_NNK=250, PB_NM=40, PB_NI=3),
                  opts(PB_NNK=256, PB_NM=40, PB_NI=16), opts(PB_NNK=256, PB_NM=40, PB_NI=3, PB_ROW_LEVEL=2)):
        assert trials.family(other) != trials.family(same[0])
    # the include folder is not part of it (the sources' hash is); a prefix's numbers are sizes
    assert trials.family(["-I", "/a", "-w"]) == trials.family(["-I", "/b", "-w"])
    assert trials.family([], "#define PB_NKEPT 2\n")[1] == trials.family([], "#define PB_NKEPT 3\n")[1]
    # the fallback's bookkeeping: one program whatever vector width a device builds it with
    assert trials.program_key("pbrdf_grid.cl", opts(PB_NNK=256)) == \
        trials.program_key("pbrdf_grid.cl", [o.replace("PB_VW=16", "PB_VW=8") for o in opts(PB_NNK=256)])
    assert trials.label("pbrdf_grid.cl", "float32", opts(PB_NNK=256, PB_ROW_LEVEL=1) + ["-DPB_OBJECTIVE"]) == \
        "pbrdf_grid.cl (float32, PB_ROW_LEVEL=1, PB_OBJECTIVE)"


def test_switches_are_checked_in_one_line(monkeypatch):
    monkeypatch.setenv(trials.FAKE_ENV, "pocl:grid")
    with pytest.raises(ValueError, match=r"^PBRDF_CL_FAKE_TRIAL_CRASH='pocl:grid': expected <device>:<program>:<how>"):
        trials.fake_way("x", "y")
    monkeypatch.setenv(trials.FAKE_ENV, "pocl:grid:segv")
    assert trials.fake_way("PoCL / pthread", "pbrdf_grid.cl (float32)") == "segv"
    assert trials.fake_way("NVIDIA / GPU", "pbrdf_grid.cl (float32)") is None
    monkeypatch.setenv(trials.TIMEOUT_ENV, "soon")
    with pytest.raises(ValueError, match=r"^PBRDF_CL_TRIAL_TIMEOUT='soon' is not a number of seconds$"):
        trials.timeout()
    monkeypatch.setenv(trials.TIMEOUT_ENV, "2.5")
    assert trials.timeout() == 2.5


def _fake_device(pocl, llvm, cpu=True):
    plat = types.SimpleNamespace(name="Portable Computing Language" if pocl else "Intel(R) OpenCL",
                                 version=f"OpenCL 3.0 PoCL 3.0-rc2  Linux, Release, RELOC, LLVM {llvm}.0.6, SLEEF")
    return types.SimpleNamespace(platform=plat, type=E.cl.device_type.CPU if cpu else E.cl.device_type.GPU)


def test_vector_widths_are_256_bit_only_where_llvm_14_meets_avx512(monkeypatch):
    monkeypatch.delenv(choice.NARROW_ENV, raising=False)
    monkeypatch.setattr(choice, "cpu_flags", lambda: frozenset({"avx2", "avx512f"}))
    assert E.vector_widths(_fake_device(True, 14)) == ({"float32": 8, "float64": 4}, {"float32": 8, "float64": 4})
    assert "LLVM 14 on an AVX-512 CPU" in E.narrow_reason(_fake_device(True, 14))
    for dev in (_fake_device(True, 15), _fake_device(False, 14), _fake_device(True, 14, cpu=False)):
        assert E.narrow_reason(dev) is None
        assert E.vector_widths(dev) == (sources.VECTOR_WIDTH, sources.LM_LANES)
    monkeypatch.setattr(choice, "cpu_flags", lambda: frozenset({"avx2"}))  # an AVX2 host: 512-bit code is split
    assert E.narrow_reason(_fake_device(True, 14)) is None
    monkeypatch.setenv(choice.NARROW_ENV, "1")
    assert E.vector_widths(_fake_device(True, 15))[0] == sources.NARROW_VECTOR_WIDTH


# ---------------------------------------------------------------------------------------------
# a child that dies

@requires_opencl
@pytest.mark.parametrize("how,words", [("segv", ["signal 11 (SIGSEGV)"]),
                                       ("llvm", ["LLVM ERROR: Do not know how to scalarize", "signal 6 (SIGABRT)"])])
def test_a_program_that_kills_its_trial_falls_back_to_numpy_with_one_warning_per_device(tmp_path, how, words):
    env = {trials.FAKE_ENV: f":pbrdf_grid.cl:{how}", "PBRDF_CL_CACHE_DIR": str(tmp_path / "cache")}
    proc = run(["-c", SCRIPT], env)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    out = json.loads(proc.stdout)
    want = np.asarray(pbrdf_cl.objective(CSV, grid=GRID, backend="numpy").sse).ravel()
    np.testing.assert_allclose(out["sse"], want, rtol=1e-5)
    usable = [d for d in E.candidates() if E.probe(d).usable]  # every device the fallback tries (not only the
    assert len(out["warnings"]) == len(usable), out["warnings"]  # tests' own, which PBRDF_TEST_DEVICES may narrow)
    for dev, line in zip(usable, out["warnings"]):
        assert line.startswith(f"OpenCL device {device_id(dev)} ({E.describe(dev)}) cannot run pbrdf_grid.cl "
                               "(float32, "), line
        assert all(w in line for w in words) and "\n" not in line, line
    assert out["warnings"][-1].endswith("computing it on the numpy backend (the float64 reference, slower)")
    assert out["stats"]["children"] == len(usable)  # one child at a time, each killed by one device's trial
    # the verdicts are stored, and a second process trusts them without a child
    with_store = dict(os.environ, PBRDF_CL_CACHE_DIR=env["PBRDF_CL_CACHE_DIR"])
    stored = run(["-c", "import json; from pbrdf_cl.device import trials; print(json.dumps([v.__dict__ for v in "
                  "trials.stored_verdicts()]))"], with_store)
    bad = [v for v in json.loads(stored.stdout) if not v["usable"]]
    assert len(bad) == len(usable) and all(all(w in v["reason"] for w in words) for v in bad)
    again = json.loads(run(["-c", SCRIPT], env).stdout)
    assert again["stats"] == {"children": 0, "trials": 0}
    assert again["warnings"] == out["warnings"] and again["sse"] == out["sse"]


@pytest.mark.skipif(len(DEVICES) < 2, reason="needs two usable OpenCL devices")
def test_the_work_moves_to_the_next_usable_device(tmp_path):
    first, second = DEVICES[:2]
    env = {trials.FAKE_ENV: f"{E.describe(first)}:pbrdf_grid.cl:segv", "PBRDF_CL_CACHE_DIR": str(tmp_path / "c")}
    out = json.loads(run(["-c", SCRIPT], env).stdout)
    assert len(out["warnings"]) == 1
    assert out["warnings"][0].startswith(f"OpenCL device {device_id(first)} ({E.describe(first)}) cannot run "
                                         "pbrdf_grid.cl")
    assert out["warnings"][0].endswith(f"computing it on OpenCL device {device_id(second)} ({E.describe(second)})")
    want = np.asarray(pbrdf_cl.objective(CSV, grid=GRID, engine=E.Engine(second)).sse).ravel()
    assert out["sse"] == want.tolist()


@requires_opencl
def test_an_explicit_device_that_cannot_run_a_program_is_a_one_line_error(tmp_path):
    dev = DEVICES[0]
    env = {trials.FAKE_ENV: f"{E.describe(dev)}:objective:llvm", "PBRDF_CL_CACHE_DIR": str(tmp_path / "cache")}
    for args, extra in ((["fit", CSV, "--device", device_id(dev)], {}),
                        (["fit", CSV], {"PYOPENCL_CTX": device_id(dev)})):
        proc = run(["-m", "pbrdf_cl", *args], {**env, **extra})
        assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("pbrdf-cl: error: ")]
        assert len(errors) == 1 and proc.stdout == "", proc.stderr
        assert errors[0].startswith(f"pbrdf-cl: error: OpenCL device {device_id(dev)} ({E.describe(dev)}) cannot "
                                    "run pbrdf_grid.cl (float32, ")
        assert "PB_OBJECTIVE" in errors[0] and "LLVM ERROR" in errors[0] and "signal 6 (SIGABRT)" in errors[0]
    listed = run(["-m", "pbrdf_cl", "devices"], env)
    assert listed.returncode == 0
    lines = listed.stdout.splitlines()
    at = next(i for i, ln in enumerate(lines) if ln.lstrip("* ").startswith(device_id(dev) + " "))
    block = "\n".join(lines[at:at + 6])
    assert "trials: " in block and "UNUSABLE pbrdf_grid.cl (float32, " in block and "LLVM ERROR" in block
    listed = json.loads(run(["-m", "pbrdf_cl", "devices", "--json"], env).stdout)
    row = next(r for r in listed if r["id"] == device_id(dev))
    assert any(not t["usable"] and "SIGABRT" in t["reason"] for t in row["trials"])
    forgot = run(["-m", "pbrdf_cl", "devices", "--forget", "--json"], env)
    assert all(not r["trials"] for r in json.loads(forgot.stdout))


@requires_opencl
def test_a_hanging_trial_is_killed_at_the_time_limit(store, monkeypatch):
    dev = DEVICES[0]
    monkeypatch.setenv(trials.FAKE_ENV, f"{E.describe(dev)}:pbrdf_grid.cl:hang")
    monkeypatch.setenv(trials.TIMEOUT_ENV, "2")
    eng = E.Engine(dev)  # explicit: the error, not a fallback
    t0 = time.monotonic()
    with pytest.raises(E.ProgramUnusableError,
                       match=r"cannot run pbrdf_grid\.cl \(float32, .*\): timed out after 2 s$"):
        pbrdf_cl.objective(CSV, grid=GRID, engine=eng)
    assert time.monotonic() - t0 < 60
    assert not any(p.name.startswith("pbrdf-trial-") for p in Path(os.environ["POCL_CACHE_DIR"]).glob("*")
                   if str(os.getpid()) in p.name)  # the killed child's cache folder is gone


@requires_opencl
def test_a_crashed_trial_leaves_nothing_in_the_shared_cache(store, monkeypatch, tmp_path):
    shared = tmp_path / "pocl"
    monkeypatch.setenv("POCL_CACHE_DIR", str(shared))
    dev = DEVICES[0]
    source = (E.kernel_dir() / "pbrdf_tables.cl").read_text()
    options = E.build_options("float32", {"PBRDF_SHADOWING": 1})
    def check():
        return trials.check_program(dev, None, E.kernels_sha256(), "pbrdf_tables.cl", "float32", source,
                                             options)
    def entries():
        return sorted(p.relative_to(shared) for p in shared.glob("??/*"))
    monkeypatch.setenv(trials.FAKE_ENV, ":pbrdf_tables.cl:abort")  # dies after the build, which PoCL cached
    verdict = check()
    assert not verdict.usable and verdict.reason.endswith("signal 6 (SIGABRT)")
    assert entries() == [] and not list(shared.glob("pbrdf-trial-*"))
    monkeypatch.delenv(trials.FAKE_ENV)
    verdict = check()
    assert verdict.usable and verdict.reason == "built and launched 5 kernels"
    if E.is_pocl(dev.platform):  # what the trial compiled is the parent's now
        assert len(entries()) == 1 and not list(shared.glob("pbrdf-trial-*/??"))
    assert check() is verdict  # this process's memory
    monkeypatch.setattr(trials, "_MEMORY", {})
    again = check()
    assert again.cached and again.usable  # the store on disk


@requires_opencl
def test_a_crashing_probe_makes_the_device_unusable(tmp_path):
    env = {trials.FAKE_ENV: ":pbrdf_probe.cl:segv", "PBRDF_CL_CACHE_DIR": str(tmp_path / "cache")}
    listed = run(["-m", "pbrdf_cl", "devices"], env)
    assert listed.returncode == 0 and "Traceback" not in listed.stderr
    assert listed.stdout.count("UNUSABLE: the probe crashed the driver: ") == len(pbrdf_cl.list_devices())
    assert "signal 11 (SIGSEGV)" in listed.stdout and "no usable OpenCL device" in listed.stdout
    proc = run(["-m", "pbrdf_cl", "eval", "--theta-i", "40", "--theta-r", "45", "--n", "1.6", "--k", "2.139",
                "--sigma", "0.5", "--ks", "0.9", "--kd", "0.15", "--c", "-0.3", "--json"], env)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    assert abs(json.loads(proc.stdout)["rows"][0]["dop"] - 0.167590) < 5e-7
    assert sum("computing on the numpy backend" in ln for ln in proc.stderr.splitlines()) == 1


# ---------------------------------------------------------------------------------------------
# narrower vectors change no value

def test_narrow_vectors_change_no_value(engine):
    """Each lane computes alone: 256-bit vectors give every value of 512-bit ones, bit for bit (on
    devices that can build both; where the driver needs 256-bit vectors both are that)."""
    if E.narrow_reason(engine.device):
        pytest.skip(f"this device builds 256-bit vectors only: {E.narrow_reason(engine.device)}")
    narrow = E.Engine(engine.device)
    narrow.vector_width, narrow.lm_lanes = dict(sources.NARROW_VECTOR_WIDTH), dict(sources.NARROW_LM_LANES)
    rng = np.random.default_rng(3)
    ti, tr, ph, sg = (rng.uniform(0, 89, 301), rng.uniform(0, 89, 301), rng.uniform(0, 360, 301),
                      rng.uniform(0.05, 1, 301))
    geo = dict(theta_i=np.repeat([30.0, 40, 50], 10), theta_r=np.tile(np.arange(20.0, 66, 5), 3))
    stack = pbrdf_cl.dop(geo["theta_i"], geo["theta_r"], n=1.6, k=2.139, sigma=0.5, kd=0.15, c=-0.3,
                         backend="numpy") + rng.normal(0, 0.003, (2, 3, 30))
    for dtype in ("float32", "float64") if engine.fp64 else ("float32",):
        outs = []
        for eng in (engine, narrow):
            o = dict(dop=pbrdf_cl.dop(ti, tr, ph, n=1.6, k=2.1, sigma=sg, kd=0.2, c=-0.3, dtype=dtype, engine=eng),
                     bcast=pbrdf_cl.brdf(ti[:, None], tr[None, :13], 150, n=1.6, k=2.1, sigma=0.3, kd=0.2, c=-0.3,
                                         dtype=dtype, engine=eng),
                     sse=np.asarray(pbrdf_cl.objective(CSV, grid=GRID, dtype=dtype, engine=eng).sse))
            if dtype == "float32":
                fit = pbrdf_cl.fit_batch(dict(dop=stack, **geo), engine=eng)
                o.update({v: fit[v].values for v in ("n", "k", "sigma", "kd", "c", "sse", "status")})
            outs.append(o)
        for name in outs[0]:
            np.testing.assert_array_equal(outs[0][name], outs[1][name], err_msg=f"{name} ({dtype})")
