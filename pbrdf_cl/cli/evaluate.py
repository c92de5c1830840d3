"""``pbrdf-cl eval``: the model's quantities at every combination of the values given."""
from __future__ import annotations

import json
import sys

import numpy as np

from .. import ranges, sizes
from ..compute import pointwise
from ..device import engine as _engine
from ..model import inputs, quantities
from ..model.reference import SHADOWING
from .common import SHADOWING_HELP, device_options, engine_for, error, quantity_choices

#: Every input of the model with its default as the option's text (None: required).
PARAMS = tuple((n, None if i.default is None else f"{i.default:g}") for n, i in inputs.REGISTRY.items())


def parse_values(option: str, text: str) -> np.ndarray:
    """``"40"``, ``"20,30,45"``, ``"20:65:5"`` or ``"0:85@256"`` -> 1-d float array (:mod:`pbrdf_cl.ranges`)."""
    return ranges.parse_values(text, option)


def cmd_eval(args) -> int:
    from ..io.params import read_params
    try:
        from_file = read_params(args.params) if args.params else {}  # the options given win
    except (OSError, ValueError) as exc:
        return error(f"--params {args.params}: {exc.strerror}" if isinstance(exc, OSError) else exc)
    values = {}
    for name, default in PARAMS:
        text = getattr(args, name)
        if text is None:
            text = repr(from_file[name]) if name in from_file else default
        if text is None and not (name == "sigma" and args.model == "specular" and args.quantity == "dop"):
            print(f"pbrdf-cl: error: --{name.replace('_', '-')} is required", file=sys.stderr)
            return 2
        values[name] = parse_values(f"--{name.replace('_', '-')}", text) if text is not None else None
    names = [n for n, _ in PARAMS if values[n] is not None]
    shape = tuple(values[n].size for n in names)
    total = int(np.prod(shape, dtype=np.int64))
    width = quantities.get(args.quantity, "points", "--quantity").width
    sizes.check_memory(total * (16 * len(names) + 16 * width + (400 if args.json else 0)),
                       f"pbrdf-cl eval of {' x '.join(map(str, shape))} = {total} rows",
                       "give fewer values per option; for large Cartesian products use pbrdf-cl map or "
                       "pbrdf-cl sweep (a Zarr store)")
    # the rows of the Cartesian product (the last option varies fastest), as columns: no Python list
    idx = np.unravel_index(np.arange(total), shape) if total else [np.zeros(0, int)] * len(names)
    cols = {n: values[n][i] for n, i in zip(names, idx)}
    rows = range(total)
    kw = dict(shadowing=args.shadowing, dtype=args.dtype, model=args.model, engine=engine_for(args))
    pos = {n: cols[n] for n in inputs.GEOMETRY}
    par = {n: cols[n] for n in inputs.PARAMETERS if n in cols}
    try:
        q = quantities.get(args.quantity, "points", "--quantity")
        if args.incident is None:
            result = pointwise.evaluate(q.name, pos["theta_i"], pos["theta_r"], pos["phi"], **par, **kw)
        else:
            result = pointwise.stokes(pos["theta_i"], pos["theta_r"], pos["phi"], **par, **kw,
                                      incident=incident_state(args.incident, q.name))
    except (ValueError, FloatingPointError, _engine.OpenCLUnavailableError) as exc:
        return error(exc)
    out_name = q.name
    if args.json:
        records = [{**{n: float(cols[n][i]) for n in names},
                    out_name: result[i].tolist() if q.trailing else float(result[i])}
                   for i in range(len(rows))]
        print(json.dumps(dict(quantity=out_name, shadowing=args.shadowing, dtype=args.dtype,
                              backend=kw["engine"].backend,
                              device=kw["engine"].description, model=args.model,
                              incident=None if args.incident is None else list(incident_state(args.incident, out_name)),
                              rows=records), indent=2))
        return 0
    header = [n for n in names]
    what = {"mueller": "mueller (row-major, 16 values)", "stokes": "stokes (S0 S1 S2 S3)"}.get(out_name, out_name)
    if args.incident is not None:
        what += f" for incident ({args.incident})"
    print("  ".join(f"{h:>8s}" for h in header) + f"  {what}" + (f" ({q.units})" if q.units != "1" else ""))
    for i in range(len(rows)):
        lead = "  ".join(f"{cols[n][i]:8.4g}" for n in names)
        if q.trailing:
            val = " ".join(f"{v: .6e}" for v in result[i].ravel())
        else:
            val = f"{result[i]:.8g}"
        print(f"{lead}  {val}")
    return 0


def incident_state(text, quantity):
    """``--incident S1,S2,S3`` (the incident light's normalised Stokes vector) as three numbers;
    one-line refusals (a quantity other than the Stokes vector, not three numbers)."""
    if quantity != "stokes":
        raise ValueError(f"--incident gives the Stokes vector of the reflected light (S0 S1 S2 S3) under that "
                         f"state: use --quantity stokes, not {quantity}")
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise ValueError(f"--incident {text!r}: give the normalised Stokes vector S1,S2,S3 of the incident light, "
                         "e.g. 1,0,0 (linear along s), 0,1,0 (at 45 degrees), 0,0,1 (circular)")
    return values


def eval_parser(sub):
    """The `pbrdf-cl eval` sub-command."""
    e = sub.add_parser("eval", help="evaluate DOP, F00, AoP, the Stokes vector or the Mueller matrix",
                       description=f"Each value option takes {ranges.GRAMMAR}; see the docs, "
                       "docs/guide/cli.md, Ranges and name=value. The output has one row per combination.")
    for name, default in PARAMS:
        unit = " (degrees)" if name in ("theta_i", "theta_r", "phi") else ""
        e.add_argument(f"--{name.replace('_', '-')}", dest=name, metavar="V",
                       help=f"{name}{unit}" + (f", default {default}" if default else ", required"))
    e.add_argument("--quantity", choices=quantity_choices("points"), default="dop", type=str.lower,
                   help="AoP in degrees (NaN where undefined), F00 and Stokes in 1/sr")
    e.add_argument("--shadowing", choices=sorted(SHADOWING), default="paper", help=SHADOWING_HELP)
    e.add_argument("--model", choices=pointwise.MODELS, default="six-param",
                   help="six-param, or specular: the ref. [7] model (kd = 0; the DOP then needs no --sigma)")
    e.add_argument("--dtype", choices=("float32", "float64"), default="float64", help="precision")
    e.add_argument("--incident", metavar="S1,S2,S3", help="with --quantity stokes: the incident light's normalised "
                   "Stokes vector in its beam's s/p frame (1,0,0: linear along s; 0,1,0: at +45 degrees; 0,0,1: "
                   "circular); default unpolarised")
    e.add_argument("--params", metavar="FILE", help="n, k, sigma, ks, kd, c from a JSON or TOML file (as `pbrdf-cl "
                   "explore` exports a set); the options given here win")
    device_options(e)
    e.add_argument("--json", action="store_true", help="JSON output")
    e.set_defaults(func=cmd_eval)
