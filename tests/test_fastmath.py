"""Accuracy of the elementary functions of kernels/pb_math.h (the inline exp, log, erfc, hypot,
sincos of both precisions) against numpy/scipy: float32 against float64 at the same float32
arguments, float64 against numpy (erfc: scipy's erfcx times exp(-x^2) in long double), in scalar
and vector builds, plus pb_sincosd (exact degree reduction) in both precisions.  The bounds are
those stated in pb_math.h's header comment."""

import numpy as np
import pyopencl as cl
import pytest
from scipy.special import erfc, erfcx

from pbrdf_cl.device import engine as engine_mod
from pbrdf_cl.model import reference

FUNCS = {"exp": 0, "log": 1, "erfc": 2, "hypot": 3, "sincos_pi4": 4, "sincosd": 5, "sqrt": 6, "exp_normal": 7,
         "log_normal": 8}

SOURCE = """
#include "pbrdf.h"
#ifdef PB_VECTOR_REAL
#define LD(p) PB_CAT(vload, PB_VECTOR_REAL)(i, p)
#define ST(v, p) PB_CAT(vstore, PB_VECTOR_REAL)(v, i, p)
#else
#define LD(p) (p)[i]
#define ST(v, p) ((p)[i] = (v))
#endif
__kernel void fm(__global const PB_SCALAR *x, __global const PB_SCALAR *y,
                 __global PB_SCALAR *o0, __global PB_SCALAR *o1, const int n)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const real a = LD(x), b = LD(y);
    real r, c = (real)0;
#if FN == 0
    r = pb_exp(a);
#elif FN == 1
    r = pb_log(a);
#elif FN == 2
    r = pb_erfc(a);
#elif FN == 3
    r = pb_hypot(a, b);
#elif FN == 4
    r = pb_sincos_pi4(a, &c);
#elif FN == 5
    r = pb_sincosd(a, &c);
#elif FN == 7
    r = pb_exp_normal(a);
#elif FN == 8
    r = pb_log_normal(a);
#else
    r = pb_sqrt(a);
#endif
    ST(r, o0);
    ST(c, o1);
}
"""


def make_runner(engine):
    """run(func, x, y=None, dtype, width, builtin) -> (result, second result) as float64 arrays;
    ``width`` None: the scalar build, "vector": the vector build of the device's width (the one its
    kernels use, :attr:`pbrdf_cl.Engine.vector_width`), built as the package's programs are."""
    built = {}

    def run(func, x, y=None, dtype="float32", width=None, builtin=False):
        npdt = np.dtype(engine_mod.DTYPES[dtype])
        width = engine.vector_width[dtype] if width == "vector" else width
        key = (func, dtype, width, builtin)
        if key not in built:
            defines = {"FN": FUNCS[func]}
            defines.update({"PB_VECTOR_REAL": width} if width else {})
            defines.update({"PB_BUILTIN_MATH": None} if builtin else {})
            built[key] = engine.source_program("test_fastmath", SOURCE, dtype, defines)["fm"]
        lanes = width or 1
        x = np.asarray(x, dtype=npdt).ravel()
        y = np.zeros_like(x) if y is None else np.asarray(y, dtype=npdt).ravel()
        n = x.size
        pad = -(-n // lanes) * lanes
        xs = np.concatenate([x, np.ones(pad - n, npdt)])
        ys = np.concatenate([y, np.ones(pad - n, npdt)])
        mf = cl.mem_flags
        bx = cl.Buffer(engine.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=xs)
        by = cl.Buffer(engine.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=ys)
        o0 = cl.Buffer(engine.context, mf.READ_WRITE, xs.nbytes)
        o1 = cl.Buffer(engine.context, mf.READ_WRITE, xs.nbytes)
        built[key](engine.queue, (pad // lanes,), None, bx, by, o0, o1, np.int32(pad // lanes))
        r0, r1 = np.empty_like(xs), np.empty_like(xs)
        cl.enqueue_copy(engine.queue, r0, o0)
        cl.enqueue_copy(engine.queue, r1, o1)
        return r0[:n].astype(np.float64), r1[:n].astype(np.float64)
    return run


@pytest.fixture(scope="module")
def run(engine):
    return make_runner(engine)


WIDTHS = [None, "vector"]
F32 = np.float32
TINY = float(np.finfo(F32).tiny)  # 2^-126


def f32(x):
    """Values as float32, and back to float64 (the arguments the kernel sees)."""
    return np.asarray(x, dtype=F32).astype(np.float64)


def rel_err(got, want):
    return np.abs(got - want) / np.abs(want)


@pytest.mark.parametrize("width", WIDTHS)
def test_exp(run, rng, width):
    x = f32(np.concatenate([np.linspace(-104, 89, 400001), rng.uniform(-20, 20, 100000),
                            rng.uniform(-1e-3, 1e-3, 10000)]))
    got, _ = run("exp", x, width=width)
    want = np.exp(x)
    normal = (want >= TINY) & (want <= np.finfo(F32).max)
    assert rel_err(got[normal], want[normal]).max() <= 1.2e-7
    # gradual underflow: within one denormal step and a relative 2e-7; overflow: inf
    low = want < TINY
    assert np.all(np.abs(got[low] - want[low]) <= 1.2e-7 * want[low] + 2.0 ** -149)
    assert np.all(np.isinf(got[want > np.finfo(F32).max]))
    special, _ = run("exp", [-np.inf, np.inf, np.nan, -1e30, 1e30, 0.0, -0.0, -104.0, 89.0], width=width)
    assert special[0] == 0 and special[1] == np.inf and np.isnan(special[2])
    assert special[3] == 0 and special[4] == np.inf and special[5] == 1 and special[6] == 1
    assert special[7] == 0 and special[8] == np.inf


@pytest.mark.parametrize("width", WIDTHS)
def test_log(run, rng, width):
    every = np.arange(1, 0x7F800000, 97, dtype=np.uint32).view(F32).astype(np.float64)  # denormals too
    x = np.concatenate([every, f32(rng.uniform(0.5, 2, 200000)), f32(1 + rng.uniform(-1e-4, 1e-4, 10000))])
    got, _ = run("log", x, width=width)
    want = np.log(x)
    nz = want != 0
    assert rel_err(got[nz], want[nz]).max() <= 1.0e-7 and np.all(got[~nz] == 0)
    special, _ = run("log", [0.0, -0.0, -1.0, -np.inf, np.inf, np.nan, 1.0, 2.0 ** -149], width=width)
    assert special[0] == -np.inf and special[1] == -np.inf
    assert np.all(np.isnan(special[2:4])) and special[4] == np.inf and np.isnan(special[5])
    assert special[6] == 0 and special[7] == pytest.approx(-149 * np.log(2), rel=1e-7)


@pytest.mark.parametrize("width", WIDTHS)
def test_erfc(run, rng, width):
    x = f32(np.concatenate([np.linspace(0, 10.5, 400001), rng.uniform(0, 9, 200000), rng.uniform(0, 1e-3, 1000)]))
    got, _ = run("erfc", x, width=width)
    want = erfc(x)
    normal = want >= TINY
    assert rel_err(got[normal], want[normal]).max() <= 4.0e-7
    assert np.all(np.abs(got[~normal] - want[~normal]) <= 4.0e-7 * want[~normal] + 2.0 ** -149)
    special, _ = run("erfc", [np.inf, np.nan, 0.0, 11.0, 1e30], width=width)
    assert special[0] == 0 and np.isnan(special[1]) and special[2] == 1 and special[3] == 0 and special[4] == 0


@pytest.mark.parametrize("width", WIDTHS)
def test_hypot_and_sqrt(run, rng, width):
    x = f32(10.0 ** rng.uniform(-18, 18, 200000) * rng.choice([-1, 1], 200000))
    y = f32(10.0 ** rng.uniform(-18, 18, 200000))
    got, _ = run("hypot", x, y, width=width)
    assert rel_err(got, np.hypot(x, y)).max() <= 1.2e-7
    s, _ = run("sqrt", np.abs(x), width=width)
    np.testing.assert_array_equal(s, f32(np.sqrt(np.abs(x))))  # correctly rounded


@pytest.mark.parametrize("width", WIDTHS)
def test_sincos_pi4(run, rng, width):
    y = f32(np.concatenate([np.linspace(-np.pi / 4, np.pi / 4, 200001), rng.uniform(-1e-3, 1e-3, 1000)]))
    y = y[np.abs(y) <= np.pi / 4]
    s, c = run("sincos_pi4", y, width=width)
    nz = y != 0
    assert rel_err(s[nz], np.sin(y[nz])).max() <= 1.2e-7 and np.all(s[~nz] == 0)
    assert rel_err(c, np.cos(y)).max() <= 1.2e-7


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("width", WIDTHS)
def test_sincosd(run, rng, width, dtype):
    """sin and cos of degrees with the exact reduction: relative accuracy near multiples of 90."""
    conv = f32 if dtype == "float32" else np.asarray
    k = np.arange(-8, 9) * 90.0
    near = (k[:, None] + np.array([-0.1, -1e-3, 0, 1e-3, 0.1, 45])).ravel()
    x = conv(np.concatenate([rng.uniform(-720, 720, 100000), near,
                             rng.uniform(0, 89.9, 10000), [1e7 + 0.5, -3e6 + 45, 123456.75]]))
    s, c = run("sincosd", x, dtype=dtype, width=width)
    ws, wc = reference.sincosd(x)
    bound = 2.0e-7 if dtype == "float32" else 4e-16
    for got, want in ((s, ws), (c, wc)):
        exact = want == 0
        assert np.all(got[exact] == 0)
        assert rel_err(got[~exact], want[~exact]).max() <= bound


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("width", WIDTHS)
def test_exp_and_log_of_normal_results(run, rng, width, dtype):
    """pb_exp_normal and pb_log_normal (no clamps, no special cases) are pb_exp and pb_log bit for bit
    where the results and arguments are normal, as pb_math.h states."""
    lo, hi = (-87.0, 88.0) if dtype == "float32" else (-708.0, 709.0)
    x = np.concatenate([np.linspace(lo, hi, 200001), rng.uniform(-81, 0, 100000), [lo, hi, 0.0, -0.0]])
    np.testing.assert_array_equal(run("exp_normal", x, dtype=dtype, width=width)[0],
                                  run("exp", x, dtype=dtype, width=width)[0])
    tiny, big = (np.finfo(np.dtype(dtype)).tiny, np.finfo(np.dtype(dtype)).max)
    y = np.concatenate([np.exp(rng.uniform(np.log(tiny), np.log(big), 300000)), rng.uniform(1e-14, 1, 100000),
                        [tiny, big, 1.0]]).astype(dtype)
    np.testing.assert_array_equal(run("log_normal", y, dtype=dtype, width=width)[0],
                                  run("log", y, dtype=dtype, width=width)[0])


@pytest.mark.parametrize("width", WIDTHS)
def test_builtin_math_build(run, width):
    """-DPB_BUILTIN_MATH switches the float32 build back to the OpenCL builtins."""
    x = f32(np.linspace(-20, 20, 1001))
    got, _ = run("exp", x, width=width, builtin=True)
    assert rel_err(got, np.exp(x)).max() <= 4e-7


# ---- float64 -------------------------------------------------------------------------------------
WIDTHS64 = [None, "vector"]
DBL_TINY = float(np.finfo(np.float64).tiny)  # 2^-1022


@pytest.mark.parametrize("width", WIDTHS64)
def test_exp_float64(run, rng, width):
    x = np.concatenate([np.linspace(-745, 709.7, 400001), rng.uniform(-20, 20, 200000),
                        rng.uniform(-1e-3, 1e-3, 10000)])
    got, _ = run("exp", x, dtype="float64", width=width)
    want = np.exp(x)
    normal = want >= DBL_TINY
    assert rel_err(got[normal], want[normal]).max() <= 3e-16
    assert np.all(np.abs(got[~normal] - want[~normal]) <= 3e-16 * want[~normal] + 2.0 ** -1074)
    special, _ = run("exp", [-np.inf, np.inf, np.nan, -1e300, 1e300, 0.0, -746.0, 710.0], dtype="float64", width=width)
    assert special[0] == 0 and special[1] == np.inf and np.isnan(special[2])
    assert special[3] == 0 and special[4] == np.inf and special[5] == 1 and special[6] == 0 and special[7] == np.inf


@pytest.mark.parametrize("width", WIDTHS64)
def test_log_float64(run, rng, width):
    x = np.concatenate([10.0 ** rng.uniform(-323, 308, 300000), rng.uniform(0.5, 2, 200000),
                        1 + rng.uniform(-1e-6, 1e-6, 10000), [5e-324, 2.0 ** -1022, np.finfo(np.float64).max]])
    got, _ = run("log", x, dtype="float64", width=width)
    want = np.log(x)
    nz = want != 0
    assert rel_err(got[nz], want[nz]).max() <= 3e-16 and np.all(got[~nz] == 0)
    special, _ = run("log", [0.0, -0.0, -1.0, -np.inf, np.inf, np.nan, 1.0], dtype="float64", width=width)
    assert special[0] == -np.inf and special[1] == -np.inf
    assert np.all(np.isnan(special[2:4])) and special[4] == np.inf and np.isnan(special[5]) and special[6] == 0


@pytest.mark.parametrize("width", WIDTHS64)
def test_erfc_float64(run, rng, width):
    """Against erfcx(x) exp(-x^2) with x^2 in long double: scipy's erfc itself loses x^2 ulps
    (7e-15 at x = 9) to the rounding of x^2."""
    x = np.concatenate([np.linspace(0, 26, 400001), rng.uniform(0, 9, 200000), rng.uniform(0, 1e-3, 1000)])
    got, _ = run("erfc", x, dtype="float64", width=width)
    xl = x.astype(np.longdouble)
    want = (erfcx(x).astype(np.longdouble) * np.exp(-xl * xl)).astype(np.float64)
    assert want.min() > DBL_TINY
    assert rel_err(got, want).max() <= 1.5e-15
    special, _ = run("erfc", [np.inf, np.nan, 0.0, 27.5, 1e300], dtype="float64", width=width)
    assert special[0] == 0 and np.isnan(special[1]) and special[2] == 1 and special[3] == 0 and special[4] == 0


@pytest.mark.parametrize("width", WIDTHS64)
def test_hypot_and_sqrt_float64(run, rng, width):
    x = 10.0 ** rng.uniform(-150, 150, 200000) * rng.choice([-1, 1], 200000)
    y = 10.0 ** rng.uniform(-150, 150, 200000)
    got, _ = run("hypot", x, y, dtype="float64", width=width)
    assert rel_err(got, np.hypot(x, y)).max() <= 3e-16
    s, _ = run("sqrt", np.abs(x), dtype="float64", width=width)
    np.testing.assert_array_equal(s, np.sqrt(np.abs(x)))  # correctly rounded


@pytest.mark.parametrize("width", WIDTHS64)
def test_sincos_pi4_float64(run, rng, width):
    y = np.concatenate([np.linspace(-np.pi / 4, np.pi / 4, 200001), rng.uniform(-1e-3, 1e-3, 1000)])
    s, c = run("sincos_pi4", y, dtype="float64", width=width)
    nz = y != 0
    assert rel_err(s[nz], np.sin(y[nz])).max() <= 3e-16 and np.all(s[~nz] == 0)
    assert rel_err(c, np.cos(y)).max() <= 3e-16


@pytest.mark.parametrize("width", WIDTHS64)
def test_builtin_math_build_float64(run, width):
    """-DPB_BUILTIN_MATH switches the float64 build back to the OpenCL builtins too."""
    x = np.linspace(0, 9, 1001)
    got, _ = run("erfc", x, dtype="float64", width=width, builtin=True)
    fast, _ = run("erfc", x, dtype="float64", width=width)
    assert rel_err(got, erfc(x)).max() <= 1e-13
    assert np.any(got != fast)  # a different implementation, not the inline one
