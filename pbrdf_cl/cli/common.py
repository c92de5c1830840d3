"""What the commands of ``pbrdf-cl`` share: the one-line error, the engine from ``--device`` and
``--backend``, the options several commands take, the checks of a result's outputs."""
from __future__ import annotations

import sys
from pathlib import Path

from .. import ranges
from ..device import drivers
from ..device import engine as _engine
from ..errors import CommandError, RangeError
from ..model import quantities
from ..model.reference import SHADOWING
from ..outputs import check_figure, check_output


def error(exc) -> int:
    """Report an input or device error the way every subcommand does; exit status 1."""
    print(f"pbrdf-cl: error: {exc}", file=sys.stderr)
    return 1


def interrupted(progress, units, store) -> int:
    """After Ctrl-C in a run into a store (``sweep``, ``fit-image``): the writes the interrupt left
    running land (:func:`pbrdf_cl.store.zarr.settle`), then ``progress()`` ((done, total)) is
    counted and said in one line; exit status 130."""
    from ..store import zarr as zarr_store
    zarr_store.settle()
    try:
        done, total = progress()
        where = f"{done} of {total} {units} are in {store}"
    except Exception:  # noqa: BLE001 - the store may not exist yet
        where = "nothing was written"
    print(f"pbrdf-cl: interrupted; {where}; run the same command again to resume", file=sys.stderr)
    return 130


def engine_for(args):
    """The engine of a subcommand from its ``--backend`` and ``--device``
    (:func:`pbrdf_cl.device.engine.engine_for`); an unusable explicit
    device, ``--backend opencl`` without a usable device, or a fallback to numpy caused by an
    unwritable PoCL cache raise :class:`CommandError`."""
    try:
        eng = _engine.engine_for(device=getattr(args, "device", None) or None, backend=getattr(args, "backend", "auto"))
    except (ValueError, _engine.OpenCLUnavailableError) as exc:
        raise CommandError(str(exc)) from None
    if eng.reason:  # a fallback (the numpy backend, no device being usable): perhaps for want of PoCL's cache
        problem = drivers.pocl_cache_problem()
        if problem:
            raise CommandError(f"{problem}; or pass --backend numpy")
    return eng


def check_result_outputs(args):
    """Refuse before any work (:class:`CommandError`) a ``--out`` that is neither .nc nor .zarr, and an
    ``--out`` or ``--png`` that cannot be written (the sobol and design commands)."""
    if args.out and Path(args.out).suffix.lower() not in (".nc", ".zarr"):
        raise CommandError(f"--out {args.out}: write the result as .nc (netCDF) or .zarr (a Zarr store)")
    check_figure("--png", args.png)
    check_output("--out", args.out)
    check_output("--png", args.png)


SHADOWING_HELP = "shadowing function: paper (the paper's eq. 7-9), smith (Smith's), or none"


def items(values):
    """NAME=VALUE items given space- or comma-separated (``n=1.6,k=2.139 sigma=0.5``)."""
    return [t for v in values or [] for t in v.split(",") if t.strip()]


def quantity_choices(path):
    """The quantity names for ``path``, canonical and aliases (the registry, pbrdf_cl.quantities)."""
    names = quantities.names(path)
    return names + tuple(a for a, c in quantities.ALIASES.items() if c in names)


def device_options(parser, where=""):
    parser.add_argument("--device", help=f"OpenCL device{where}: P:D as `pbrdf-cl devices` lists them, or a name "
                        "substring (default: PYOPENCL_CTX, else the first usable device)")
    parser.add_argument("--backend", choices=_engine.BACKENDS, default="auto",
                        help="auto (default): the OpenCL device, or the numpy reference when no device is usable; "
                        "opencl: the device or an error; numpy: the float64 reference")


def cluster_options(parser, verb):
    """--workers or --scheduler (``verb``: what the cluster does, "run", "fit") and the device
    options of a command whose work may go to a dask cluster (`sweep`, `fit-image`)."""
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N", help=f"{verb} on a local dask cluster of N processes")
    where.add_argument("--scheduler", metavar="ADDR", help=f"{verb} on a dask.distributed cluster (tcp://host:8786)")
    device_options(parser, " here or on every worker")


def model_option(f):
    """--model of `fit` and `fit-image`."""
    f.add_argument("--model", choices=("six-param", "specular"), default="six-param",
                   help="the model to fit (specular: ref. [7], n and k only)")


def fit_settings(f, joint=False):
    """--fix, --bounds and --shadowing of `fit`, `fit-image` and `design`; ``joint``: `fit`'s, whose
    joint fits also take one set's value (SET:NAME=VALUE)."""
    one = (" (every set); in a joint fit SET:NAME={} for one set, SET being its file name without the suffix "
           "(w435:{})") if joint else ""
    f.add_argument("--fix", nargs="*", metavar="NAME=VALUE", help="hold parameters fixed, e.g. sigma=0.45"
                   + one.format("VALUE", "kd=0.1"))
    f.add_argument("--bounds", nargs="*", metavar="NAME=LO:HI", help="search bounds, e.g. n=1:3 k=0:5"
                   + one.format("LO:HI", "n=2:3"))
    f.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=SHADOWING_HELP)


def fit_assignments(args, sets=False):
    """(fixed, bounds) from --fix and --bounds (fit_settings), checked against the parameters.
    With ``sets`` (a joint fit) an item may name its set, ``SET:NAME=VALUE`` (``w435:kd=0.1``):
    it goes to that set's dict (``{"435": {"kd": 0.1}}``), as :func:`pbrdf_cl.fit_joint` takes it."""
    from ..fitting.setup import DEFAULT_BOUNDS
    out = []
    for option, values, kind, check in (("--fix", args.fix, "value", True), ("--bounds", args.bounds, "bounds", False)):
        common, own = [], {}
        for item in values or []:
            name = item.split("=", 1)[0]
            if ":" not in name:
                common.append(item)
            elif not sets:
                raise RangeError(f"{option} {item}: a set name ({name.split(':', 1)[0]}:) is for joint fits "
                                        "(several CSVs, or one with --set-column); give NAME=VALUE")
            else:
                own.setdefault(name.split(":", 1)[0], []).append(item.split(":", 1)[1])
        parsed = ranges.parse_assignments(common, tuple(DEFAULT_BOUNDS), kind, option, check=check)
        for name, items in own.items():
            parsed[name] = ranges.parse_assignments(items, tuple(DEFAULT_BOUNDS), kind, f"{option} {name}:",
                                                    check=check)
        out.append(parsed)
    return tuple(out)
