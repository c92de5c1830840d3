"""The OpenCL sources and how every program is compiled: where the kernels are
(:func:`kernel_dir`), their fingerprint (:func:`kernels_sha256`, part of every cache key), the
precisions (:data:`DTYPES`), the per-point kernels' inputs in argument order
(:data:`POINT_INPUTS`), the vector widths the programs are built for, and the compiler options
(:func:`build_options`, :func:`build`); and ``cl``, pyopencl imported after
:func:`pbrdf_cl.device.drivers.register_pip_drivers`.  No device is touched here."""
from __future__ import annotations

import hashlib
import warnings
from importlib import resources
from pathlib import Path

import numpy as np

from ..model import inputs
from . import drivers

drivers.register_pip_drivers()  # before the first OpenCL call of this process

try:
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - pyopencl is a hard dependency
    cl = None
    #: why pyopencl cannot be imported (None: it can)
    IMPORT_ERROR = exc
else:
    IMPORT_ERROR = None

#: The per-point kernels' inputs, in argument order: every input of the model.
POINT_INPUTS = inputs.NAMES
DTYPES = {"float32": np.float32, "float64": np.float64}
#: Vector width of the explicitly vectorised per-point kernels (float16 / double8 were fastest on
#: PoCL 3.0) and ``PB_VW`` of the row and batch programs, unless
#: :func:`pbrdf_cl.device.choice.vector_widths` narrows them.
VECTOR_WIDTH = {"float32": 16, "float64": 8}
#: Lanes of the batch Levenberg-Marquardt kernel (``batch_lm``: one problem per lane).
LM_LANES = {"float32": 16, "float64": 4}
#: The widths where the driver cannot generate 512-bit vector code (256-bit vectors).
NARROW_VECTOR_WIDTH = {"float32": 8, "float64": 4}
NARROW_LM_LANES = {"float32": 8, "float64": 4}
#: Work-group size of the vector outer-product kernels (``*_outer_vec``: rows of few work-items).
VECTOR_LOCAL_SIZE = 8
#: Work-group size of the vector per-point kernels (``*_points_vec`` and their broadcast twins):
#: 32 work-items, 512 float32 points.  With 8 (four times as many groups to hand out) the float32
#: DOP kernel ran 3% slower on PoCL 3.1 (the same on PoCL 3.0); the values do not depend on it.
POINT_LOCAL_SIZE = 32


def kernel_dir() -> Path:
    """The folder holding the OpenCL sources: the installed ``pbrdf_cl.kernels`` package
    resource, or the source tree's top-level ``kernels/`` when running from a checkout."""
    try:
        folder = resources.files("pbrdf_cl.kernels")
        if folder.joinpath("pbrdf.h").is_file():
            return Path(str(folder))
    except ModuleNotFoundError:
        pass
    folder = Path(__file__).resolve().parents[2] / "kernels"
    if (folder / "pbrdf.h").is_file():
        return folder
    raise FileNotFoundError("the OpenCL sources of pbrdf_cl (pbrdf_cl/kernels/pbrdf.h) are missing "
                            "from this installation; reinstall the package")


_KERNELS_SHA256 = None


def kernels_sha256():
    """SHA-256 of this installation's OpenCL sources (read once per process)."""
    global _KERNELS_SHA256
    if _KERNELS_SHA256 is None:
        h = hashlib.sha256()
        for f in sorted(kernel_dir().iterdir()):
            if f.suffix in (".cl", ".h"):
                h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
        _KERNELS_SHA256 = h.hexdigest()
    return _KERNELS_SHA256


def build_options(dtype, defines=None, width=None):
    """The compiler options of every pbrdf-cl program for ``dtype``, ``-D`` ``defines`` and the row
    programs' vector width ``width`` (default :data:`VECTOR_WIDTH`)."""
    # -w: PoCL's clang otherwise prints ABI notes about wide vectors to stderr
    opts = ["-I", str(kernel_dir()), "-w", f"-DPB_VW={width or VECTOR_WIDTH[dtype]}"]
    if dtype == "float64":
        opts.append("-DPBRDF_DOUBLE")
    opts += [f"-D{name}" if value is None else f"-D{name}={value}" for name, value in (defines or {}).items()]
    return opts


def build(context, source, options):
    """``cl.Program(context, source).build(options)``, compiler warnings silenced."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        return cl.Program(context, source).build(options=options)
