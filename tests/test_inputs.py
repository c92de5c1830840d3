"""Memory budgets given as sizes."""
import numpy as np
import pytest

import pbrdf_cl
from conftest import requires_opencl
from pbrdf_cl import dense, ranges, sweeps

TI = np.repeat([30.0, 40.0, 50.0], 4)
TR = np.tile([20.0, 30.0, 40.0, 50.0], 3)
STEEL = dict(n=1.6, k=2.139, sigma=0.5, ks=1.0, kd=0.15, c=-0.3)
DOP = pbrdf_cl.dop(TI, TR, 180.0, backend="numpy", **STEEL)


# --- memory budgets --------------------------------------------------------------------------------

@pytest.mark.parametrize("text,nbytes", [("64 MiB", 64 << 20), ("1 GB", 10 ** 9), ("1.5gib", 3 << 29),
                                         ("4096", 4096), (" 2 KiB ", 2048), (65536, 65536), (1e6, 10 ** 6),
                                         (np.int64(50_000), 50_000)])
def test_sizes(text, nbytes):
    assert ranges.parse_bytes("memory_budget", text) == nbytes
    assert sweeps.parse_bytes("memory_budget", text) == nbytes  # the sweep's parser is the same one


@pytest.mark.parametrize("value,message", [
    ("lots", "memory_budget: 'lots' is not a size such as 268435456, \"256 MiB\" or \"1 GB\""),
    ("64 MB/s", "memory_budget: '64 MB/s' is not a size"),
    (0, "memory_budget: must be > 0 bytes, got 0"),
    (-5, "memory_budget: must be > 0 bytes, got -5"),
    (0.5, "memory_budget: 0.5 is not a size"),
    (None, "memory_budget: None is not a size"),
    (True, "memory_budget: True is not a size"),
])
def test_bad_sizes_are_one_line_naming_memory_budget(value, message):
    for call in (lambda: pbrdf_cl.grid({"theta_r": [10.0, 20.0]}, dict(theta_i=40, n=1.6, k=2, sigma=0.5),
                                       backend="numpy", memory_budget=value),
                 lambda: pbrdf_cl.reduce_grid({"theta_r": [10.0, 20.0], "sigma": [0.3, 0.5]},
                                              dict(theta_i=40, n=1.6, k=2), over="sigma", backend="numpy",
                                              memory_budget=value),
                 lambda: pbrdf_cl.objective(dict(theta_i=TI, theta_r=TR, dop=DOP), grid=dict(n=[1.5, 1.6], k=2.0,
                                            sigma=0.5), backend="numpy", memory_budget=value)):
        with pytest.raises(ValueError) as exc:
            call()
        assert str(exc.value).startswith(message) and "\n" not in str(exc.value)
    with pytest.raises(sweeps.SpecError, match="^" + message.replace("(", r"\(").replace(")", r"\)")):
        sweeps.parse_bytes("memory_budget", value)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("opencl", marks=requires_opencl)])
def test_memory_budget_strings_through_grid_reduce_and_objective(backend):
    axes = {"theta_r": np.linspace(0, 85, 40), "sigma": np.linspace(0.1, 1, 30)}
    fixed = dict(theta_i=40.0, n=1.6, k=2.1)
    whole = dense.grid(axes, fixed, dtype="float64", backend=backend)
    # "48 KiB" forces chunks; the same values as in one piece, and as with the integer budget
    for budget in ("48 KiB", 48 << 10, "1 GB"):
        np.testing.assert_array_equal(dense.grid(axes, fixed, dtype="float64", backend=backend,
                                                 memory_budget=budget).values, whole.values)
    red = dense.reduce_grid(axes, fixed, over="sigma", dtype="float64", backend=backend)
    red_s = dense.reduce_grid(axes, fixed, over="sigma", dtype="float64", backend=backend, memory_budget="48 KiB")
    np.testing.assert_array_equal(red_s["min"].values, red["min"].values)
    # a budget too small is still refused with the number of bytes it came to
    with pytest.raises(ValueError, match=r"memory_budget=200 bytes is too small|more than half of memory_budget=200"):
        dense.grid(axes, fixed, backend=backend, memory_budget="200 B")
    data = dict(theta_i=TI, theta_r=TR, dop=DOP)
    grid = dict(n=np.linspace(1.2, 2.0, 9), k=np.linspace(1.5, 2.5, 9), sigma=np.linspace(0.3, 0.7, 5))
    ref = dense.objective(data, grid=grid, dtype="float64", backend=backend)
    small = dense.objective(data, grid=grid, dtype="float64", backend=backend, memory_budget="40 KB")
    np.testing.assert_array_equal(small.sse.values, ref.sse.values)
