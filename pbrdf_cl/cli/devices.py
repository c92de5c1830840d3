"""``pbrdf-cl devices``: the OpenCL platforms and devices, their probe results and the verdicts of
their programs' trial builds."""
from __future__ import annotations

import json
import os
import warnings

from ..device import drivers, trials
from ..device import engine as _engine
from .common import error


def _device_type(bits: int) -> str:
    dt = _engine.cl.device_type
    names = [name for name in ("CPU", "GPU", "ACCELERATOR") if bits & getattr(dt, name)]
    return "/".join(names) or "OTHER"


def _verdict_lines(verdicts):
    """What ``pbrdf-cl devices`` says of one device's stored trial verdicts."""
    if not verdicts:
        return []
    bad = [v for v in verdicts if not v.usable]
    lines = [f"trials: {len(verdicts) - len(bad)} of {len(verdicts)} programs built and ran in the trial process"]
    for v in bad:
        lines.append(f"  UNUSABLE {v.program}: {v.reason} ({v.when.replace('T', ' ')})")
    return lines


def cmd_devices(args) -> int:
    if args.forget:
        _engine.clear_probe_cache(disk=True)
        trials.forget(disk=True)
    try:
        found = _engine.list_devices()
    except _engine.OpenCLUnavailableError as exc:
        return error(exc)
    default, why_none = None, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", _engine.DeviceWarning)  # the list says it all
        try:
            default = _engine.select_device(args.device)
        except (_engine.OpenCLUnavailableError, ValueError) as exc:
            why_none = str(exc)
    rows = []
    dev_of = {f"{ip}:{idev}": dev for ip, idev, _, dev in found}
    for ip, idev, plat, dev in found:
        result = _engine.probe(dev)
        rows.append(dict(id=f"{ip}:{idev}", platform=plat.name.strip(), device=dev.name.strip(),
                         type=_device_type(dev.type), fp64=_engine.has_fp64(dev),
                         compute_units=dev.max_compute_units, version=dev.version.strip(),
                         driver=dev.driver_version.strip(), usable=result.usable, probe=result.reason,
                         probe_seconds=round(result.seconds, 4), probe_cached=result.cached,
                         simulator=_engine.is_simulator(plat),
                         default=default is not None and dev.int_ptr == default.int_ptr,
                         vector_width=_engine.vector_widths(dev)[0], narrow_vectors=_engine.narrow_reason(dev),
                         trials=[dict(program=v.program, usable=v.usable, reason=v.reason,
                                      seconds=round(v.seconds, 3), when=v.when)
                                 for v in trials.stored_verdicts(dev)]))
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    for r in rows:
        mark = "*" if r["default"] else " "
        print(f"{mark} {r['id']:5s} {r['platform']} / {r['device']}  [{r['type']}, "
              f"{r['compute_units']} CUs, fp64={'yes' if r['fp64'] else 'no'}, {r['version']}, driver {r['driver']}]")
        state = "usable" if r["usable"] else "UNUSABLE"
        extra = "; a simulator, never the default" if r["simulator"] else ""
        when = "probe cached" if r["probe_cached"] else f"probe {r['probe_seconds']:.2f} s"
        print(f"        {state}: {r['probe']} ({when}{extra})")
        if r["narrow_vectors"]:
            print(f"        256-bit vectors in every vector program: {r['narrow_vectors']}")
        for line in _verdict_lines(trials.stored_verdicts(dev_of[r['id']])):
            print(f"        {line}")
    if _engine.DRIVER_MESSAGES:
        print("the drivers printed, while listed and probed:")
        for line in _engine.DRIVER_MESSAGES[:20]:
            print(f"        {line}")
    if default is not None:
        print("* = the default device (choose another with --device P:D or PYOPENCL_CTX=P:D)")
    elif args.device or os.environ.get("PYOPENCL_CTX"):
        print(f"the chosen device cannot be used: {why_none}")
    else:
        problem = drivers.pocl_cache_problem()
        if problem:
            print(f"PoCL's devices are hidden: {problem}")
        print("no usable OpenCL device: every command computes on the numpy backend (the float64 reference, "
              f"slower) until one is installed; remedies: {drivers.REMEDIES}")
    return 0


def devices_parser(sub):
    """The `pbrdf-cl devices` sub-command."""
    d = sub.add_parser("devices", help="list OpenCL platforms and devices, their probe results and the verdicts "
                       "of their programs' trial builds")
    d.add_argument("--device", help="mark this device as the one chosen (P:D or a name substring)")
    d.add_argument("--json", action="store_true", help="JSON output")
    d.add_argument("--forget", action="store_true", help="forget the stored probe results and trial verdicts "
                   "first (each is made again when next needed)")
    d.set_defaults(func=cmd_devices)
