"""The registry of operations with one implementation per backend (pbrdf_cl.device.ops)."""
import warnings

import pytest

import pbrdf_cl
from pbrdf_cl.device import ops

from conftest import requires_opencl


@pytest.fixture
def registry(monkeypatch):
    monkeypatch.setattr(ops, "_REGISTRY", {})
    monkeypatch.setattr(ops, "_WARNED", set())


def test_each_engine_runs_its_own_implementation(registry, engine):
    ops.implements("twice", "numpy")(lambda eng, x: ("numpy", 2 * x))
    ops.implements("twice", "opencl")(lambda eng, x: ("opencl", 2 * x, eng))
    assert pbrdf_cl.NumpyEngine().call("twice", 3) == ("numpy", 6)
    assert engine.call("twice", 4) == ("opencl", 8, engine)
    assert ops.operations() == {"twice": ["numpy", "opencl"]}


@requires_opencl
def test_an_operation_without_a_device_implementation_runs_on_numpy_once_said(registry, engine):
    ops.implements("half", "numpy")(lambda eng, x: (type(eng).__name__, x / 2))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert engine.call("half", 3) == ("NumpyEngine", 1.5)
        assert engine.call("half", 5) == ("NumpyEngine", 2.5)
    said = [str(w.message) for w in caught if issubclass(w.category, pbrdf_cl.DeviceWarning)]
    assert said == ["half: no opencl implementation; computing it on the numpy backend (the float64 reference, "
                    "slower)"]


def test_unknown_operations_and_double_registrations_are_refused(registry):
    with pytest.raises(LookupError, match=r"^no implementation of the operation 'nothing'"):
        pbrdf_cl.NumpyEngine().call("nothing")
    ops.implements("one", "numpy")(lambda eng: 1)
    with pytest.raises(ValueError, match=r"^operation 'one' has a numpy implementation already"):
        ops.implements("one", "numpy")(lambda eng: 2)
    with pytest.raises(ValueError, match=r"^backend must be one of"):
        ops.implements("one", "cuda")


def test_both_engines_offer_the_same_interface(engine):
    numpy = pbrdf_cl.NumpyEngine()
    for name in ("backend", "call", "evaluate", "checks_domain", "compute_dtype", "has_kernels", "reason",
                 "description", "lock", "fp64", "profiling", "last_event_seconds", "vector_width", "lm_lanes"):
        assert hasattr(numpy, name) and hasattr(engine, name), name
    assert [numpy.compute_dtype(d) for d in ("float32", "float64")] == ["float64", "float64"]
    assert [engine.compute_dtype(d) for d in ("float32", "float64")] == ["float32", "float64"]
    assert engine.has_kernels and not numpy.has_kernels
    assert engine.reason == numpy.reason == "" and pbrdf_cl.NumpyEngine("no device").reason == "no device"
    assert set(numpy.vector_width.values()) == set(numpy.lm_lanes.values()) == {1}
    assert set(engine.vector_width) == set(engine.lm_lanes) == {"float32", "float64"}


def test_the_dense_operations_have_both_implementations():
    from pbrdf_cl.compute import dense  # noqa: F401 (registers them)
    found = ops.operations()
    for name in ("grid_blocks", "reduce_grid", "objective_blocks", "objective_points", "outer"):
        assert found[name] == ["numpy", "opencl"], name
