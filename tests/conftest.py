"""Shared fixtures.

OpenCL devices: the kernel-versus-reference tests (those using the ``engine`` or ``each_device``
fixture) run on every usable OpenCL device present except the Oclgrind simulator, each held to
the same tolerances.  ``PYOPENCL_TEST``, if set, picks the devices as pyopencl's ``ctx_factory`` does
(``"0:0,1;intel:i5"``: platforms and their devices, by number or name substring), and
``PBRDF_TEST_DEVICES`` (comma-separated substrings of "platform / device") restricts them further,
so that the same suite runs unchanged on whichever device the environment names (a GPU, a CPU).  Without a
usable device those tests are skipped, saying why, unless ``PBRDF_REQUIRE_OPENCL=1`` (as ``.ci/run`` sets), which
makes the session fail instead.  The header of the run names the devices.
"""
import os
import tempfile
import warnings

import numpy as np
import pytest

os.environ.setdefault("POCL_CACHE_DIR", os.path.join(tempfile.gettempdir(), "pbrdf-cl-pocl-cache"))

import pbrdf_cl  # noqa: E402
from pbrdf_cl.device import engine as engine_mod  # noqa: E402
from pbrdf_cl.device import fallback  # noqa: E402


def _test_devices():
    """(devices, why none): the usable non-simulator devices, in the default order."""
    try:
        found = engine_mod.list_devices()
    except engine_mod.OpenCLUnavailableError as exc:
        return [], str(exc)
    usable = [d for d in engine_mod.candidates(found) if engine_mod.probe(d).usable]
    if os.environ.get("PYOPENCL_TEST"):
        from pyopencl.tools import get_test_platforms_and_devices
        try:
            named = {d.int_ptr for _, devs in get_test_platforms_and_devices() for d in devs}
        except RuntimeError as exc:  # a name that matches nothing, or bad syntax
            return [], f"PYOPENCL_TEST={os.environ['PYOPENCL_TEST']!r}: {exc}"
        usable = [d for d in usable if d.int_ptr in named]
        if not usable:
            return [], f"no usable OpenCL device matches PYOPENCL_TEST={os.environ['PYOPENCL_TEST']!r}"
    wanted = [w.strip().lower() for w in os.environ.get("PBRDF_TEST_DEVICES", "").split(",") if w.strip()]
    if wanted:
        usable = [d for d in usable if any(w in engine_mod.describe(d).lower() for w in wanted)]
    if usable:
        return usable, ""
    if wanted:
        return [], f"no usable OpenCL device matches PBRDF_TEST_DEVICES={os.environ['PBRDF_TEST_DEVICES']!r}"
    try:
        engine_mod.select_device(None)
    except (engine_mod.OpenCLUnavailableError, ValueError) as exc:
        return [], str(exc)
    return [], "no usable OpenCL device"

with warnings.catch_warnings():
    warnings.simplefilter("ignore", engine_mod.DeviceWarning)
    DEVICES, NO_DEVICE = _test_devices()
_ENGINES = {}


def device_id(dev):
    return engine_mod.describe(dev).replace(" ", "_")


def pytest_report_header(config):
    if DEVICES:
        return [f"pbrdf-cl OpenCL test devices: {'; '.join(engine_mod.describe(d) for d in DEVICES)} "
                f"(default: {engine_mod.describe(DEVICES[0])})"]
    return [f"pbrdf-cl OpenCL test devices: none ({NO_DEVICE})"]


def pytest_sessionstart(session):
    if not DEVICES and os.environ.get("PBRDF_REQUIRE_OPENCL") == "1":
        raise pytest.UsageError(f"PBRDF_REQUIRE_OPENCL=1 but {NO_DEVICE}")

PARAMS = ("n", "k", "sigma", "ks", "kd", "c")


def random_inputs(rng, size, in_plane=False):
    """Random valid inputs over the whole domain, angles in degrees, plus hand-picked edge cases."""
    d = dict(
        theta_i=rng.uniform(0, 89.9, size),
        theta_r=rng.uniform(0, 89.9, size),
        phi=np.full(size, 180.0) if in_plane else rng.uniform(0, 360, size),
        n=rng.uniform(0.2, 5, size),
        k=np.where(rng.random(size) < 0.1, 0.0, rng.uniform(0, 10, size)),
        sigma=rng.uniform(0.05, 1.0, size),
        ks=rng.uniform(0.1, 2, size),
        kd=np.where(rng.random(size) < 0.1, 0.0, rng.uniform(0, 5, size)),
        c=rng.uniform(-1, 0, size),
    )
    edges = edge_inputs()
    if in_plane:
        edges["phi"] = np.full_like(edges["phi"], 180.0)
    return {name: np.concatenate([d[name], edges[name]]) for name in d}


def edge_inputs():
    """theta = 0, alpha = 0 (specular), grazing 89.9, retro-reflection, k = 0, tiny sigma, kd = 0."""
    rows = [
        # ti, tr, phi, n, k, sigma, ks, kd, c
        (0, 0, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (0, 0, 37, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (0, 45, 180, 1.6, 0, 0.5, 1, 0.1, -0.3),
        (45, 0, 90, 1.6, 0, 0.5, 1, 0.0, -0.3),
        (40, 40, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (40, 40, 180, 1.6, 2.1, 1e-4, 1, 0.1, -0.3),
        (40, 40, 0, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (89.9, 89.9, 180, 1.6, 2.1, 0.5, 1, 0.1, -0.3),
        (89.9, 89.9, 0, 1.6, 2.1, 0.5, 1, 0.1, -1.0),
        (89.9, 0, 180, 1.2, 0, 1.0, 1, 0.1, -0.9),
        (89.9, 89.9, 180, 1.0, 0, 0.3, 1, 0.0, 0.0),
        (30, 60, 180, 1.0, 0, 0.3, 1, 0.0, 0.0),
        (30, 60, 180, 0.5, 0, 0.3, 1, 0.2, 0.0),
        (30, 31, 180, 1.5, 0, 1e-3, 1, 0.2, -0.5),
        (30, 70, 180, 1.5, 3, 1e-3, 1, 0.2, -0.5),
        (10, 80, 250, 4.0, 10, 0.05, 2, 5, -1),
    ]
    cols = np.array(rows, dtype=np.float64).T
    return dict(zip(("theta_i", "theta_r", "phi") + PARAMS, cols))


def call(func, inp, **kw):
    return func(inp["theta_i"], inp["theta_r"], inp["phi"], **{p: inp[p] for p in PARAMS}, **kw)


#: for ``pytest.param("opencl", marks=requires_opencl)``: skip where no device is usable
SKIP_REASON = "no usable OpenCL device (the run's header says why)"
requires_opencl = pytest.mark.skipif(not DEVICES, reason=SKIP_REASON)


@pytest.fixture(scope="session", params=DEVICES or [None], ids=[device_id(d) for d in DEVICES] or ["no-device"])
def engine(request):
    """An OpenCL engine on each usable device in turn (see the module docstring)."""
    if request.param is None:
        pytest.skip(SKIP_REASON)
    key = request.param.int_ptr
    if key not in _ENGINES:
        _ENGINES[key] = pbrdf_cl.Engine(request.param)
    return _ENGINES[key]


@pytest.fixture
def each_device(engine):
    """Make ``engine`` (each usable device in turn) the default engine for one test."""
    saved = fallback._default_engine
    pbrdf_cl.set_default_engine(engine)
    yield engine
    pbrdf_cl.set_default_engine(saved)


@pytest.fixture
def rng():
    return np.random.default_rng(20200509)
