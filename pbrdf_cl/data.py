"""Measured DOP data: CSV reading and validation with line numbers.

CSV format: a header line naming the columns, then one measurement per line.  Required columns
``theta_i``, ``theta_r`` (degrees) and ``dop``; optional ``phi`` (degrees, default 180),
``dop_std`` (per-point standard deviation, used as weights), ``f00`` (measured BRDF, 1/sr, or
``s0``, any intensity proportional to it) with optional ``f00_std``.  Blank lines and ``#``
comments (whole-line or trailing) are ignored.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .api import RULES

REQUIRED = ("theta_i", "theta_r", "dop")
OPTIONAL = ("phi", "dop_std", "f00", "s0", "f00_std")


@dataclass
class Measurements:
    """Validated measurements (1-d float64 arrays of equal length)."""
    theta_i: np.ndarray
    theta_r: np.ndarray
    dop: np.ndarray
    phi: np.ndarray
    dop_std: np.ndarray | None = None
    f00: np.ndarray | None = None
    f00_std: np.ndarray | None = None
    source: str = "arrays"
    lines: np.ndarray | None = field(default=None, repr=False)

    def __len__(self):
        return self.dop.size

    @property
    def weights(self):
        return None if self.dop_std is None else 1.0 / self.dop_std ** 2

    def as_dict(self):
        d = dict(theta_i=self.theta_i, theta_r=self.theta_r, phi=self.phi, dop=self.dop)
        if self.dop_std is not None:
            d["dop_std"] = self.dop_std
        return d


def _where(source, lines, i):
    return f"{source}, line {lines[i]}" if lines is not None else f"{source}, row {i}"


def _validate(cols, source, lines):
    n = len(cols["dop"])
    for name, values in cols.items():
        a = values
        bad = ~np.isfinite(a)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{_where(source, lines, i)}: {name} is {float(a[i])!r}; every value must be a finite number")
    checks = {"theta_i": RULES["theta_i"], "theta_r": RULES["theta_r"],
              "dop": (lambda a: (a >= 0) & (a <= 1), "in [0, 1]"),
              "dop_std": (lambda a: a > 0, "> 0"),
              "f00": (lambda a: a >= 0, ">= 0"),
              "f00_std": (lambda a: a > 0, "> 0")}
    for name, (ok, rule) in checks.items():
        if name in cols:
            good = ok(cols[name])
            if not good.all():
                i = int(np.argmax(~good))
                raise ValueError(f"{_where(source, lines, i)}: {name} = {float(cols[name][i])!r} is not {rule}")
    if n == 0:
        raise ValueError(f"{source}: no measurements")


def from_arrays(theta_i, theta_r, dop, phi=180.0, dop_std=None, f00=None, f00_std=None, source="arrays",
                _lines=None):
    """Validated :class:`Measurements` from arrays (broadcast to a common length)."""
    named = dict(theta_i=theta_i, theta_r=theta_r, dop=dop, phi=phi, dop_std=dop_std, f00=f00, f00_std=f00_std)
    cols = {}
    for name, v in named.items():
        if v is None:
            continue
        try:
            cols[name] = np.atleast_1d(np.asarray(v, dtype=np.float64))
        except (TypeError, ValueError):
            raise ValueError(f"{source}: {name} must be numbers, got {v!r}") from None
        if cols[name].ndim != 1:
            raise ValueError(f"{source}: {name} must be 1-d, got shape {cols[name].shape}")
    try:
        arrays = np.broadcast_arrays(*cols.values())
    except ValueError:
        lengths = ", ".join(f"{k}: {v.size}" for k, v in cols.items())
        raise ValueError(f"{source}: columns differ in length ({lengths})") from None
    cols = {k: np.array(a, dtype=np.float64) for k, a in zip(cols, arrays)}
    _validate(cols, source, _lines)
    if "f00_std" in cols and "f00" not in cols:
        raise ValueError(f"{source}: f00_std is given without f00")
    return Measurements(theta_i=cols["theta_i"], theta_r=cols["theta_r"], dop=cols["dop"], phi=cols["phi"],
                        dop_std=cols.get("dop_std"), f00=cols.get("f00"), f00_std=cols.get("f00_std"),
                        source=source, lines=_lines)


def read_csv(path) -> Measurements:
    """Read and validate a measurement CSV (see the module docstring); errors name the line."""
    path = str(path)
    header, rows, lines = None, [], []
    with open(path, encoding="utf-8") as fh:
        for lineno, raw in enumerate(fh, start=1):
            text = raw.split("#", 1)[0].strip()
            if not text:
                continue
            fields = [f.strip() for f in text.split(",")]
            if header is None:
                header = [f.lower() for f in fields]
                for name in header:
                    if name not in REQUIRED + OPTIONAL:
                        raise ValueError(f"{path}, line {lineno}: unknown column {name!r}; columns are "
                                         f"{', '.join(REQUIRED)} and optionally {', '.join(OPTIONAL)}")
                if len(set(header)) != len(header):
                    raise ValueError(f"{path}, line {lineno}: a column is named twice")
                missing = [c for c in REQUIRED if c not in header]
                if missing:
                    raise ValueError(f"{path}, line {lineno}: missing column {missing[0]!r} "
                                     f"(the header must name {', '.join(REQUIRED)})")
                if "f00" in header and "s0" in header:
                    raise ValueError(f"{path}, line {lineno}: give f00 or s0, not both")
                continue
            if len(fields) != len(header):
                raise ValueError(f"{path}, line {lineno}: {len(fields)} values for {len(header)} columns")
            row = []
            for name, f in zip(header, fields):
                try:
                    row.append(float(f))
                except ValueError:
                    raise ValueError(f"{path}, line {lineno}: {name} = {f!r} is not a number") from None
            rows.append(row)
            lines.append(lineno)
    if header is None:
        raise ValueError(f"{path}: empty file (no header line)")
    if not rows:
        raise ValueError(f"{path}: no measurements after the header")
    table = np.array(rows, dtype=np.float64)
    cols = {name: table[:, i] for i, name in enumerate(header)}
    if "s0" in cols:
        cols["f00"] = cols.pop("s0")
    return from_arrays(cols["theta_i"], cols["theta_r"], cols["dop"], cols.get("phi", 180.0), cols.get("dop_std"),
                       cols.get("f00"), cols.get("f00_std"), source=path, _lines=np.array(lines))


def write_csv(path, meas: Measurements, header_comment: str = ""):
    """Write measurements as a CSV readable by :func:`read_csv`."""
    cols = [("theta_i", meas.theta_i), ("theta_r", meas.theta_r), ("phi", meas.phi), ("dop", meas.dop)]
    if meas.dop_std is not None:
        cols.append(("dop_std", meas.dop_std))
    if meas.f00 is not None:
        cols.append(("f00", meas.f00))
    if meas.f00_std is not None:
        cols.append(("f00_std", meas.f00_std))
    with open(path, "w", encoding="utf-8") as fh:
        for line in header_comment.strip().splitlines():
            fh.write(f"# {line}\n")
        fh.write(",".join(c for c, _ in cols) + "\n")
        for i in range(len(meas)):
            fh.write(",".join(f"{v[i]:.10g}" for _, v in cols) + "\n")


def as_measurements(data) -> "Measurements":
    """Measurements from a CSV path, a dict of arrays or a Measurements object (validated)."""
    if isinstance(data, Measurements):
        return data
    if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__"):
        return read_csv(data)
    if isinstance(data, dict):
        unknown = set(data) - {"theta_i", "theta_r", "dop", "phi", "dop_std", "f00", "s0", "f00_std"}
        if unknown:
            raise ValueError(f"data: unknown column {sorted(unknown)[0]!r}")
        for need in ("theta_i", "theta_r", "dop"):
            if need not in data:
                raise ValueError(f"data: missing column {need!r}")
        return from_arrays(data["theta_i"], data["theta_r"], data["dop"], data.get("phi", 180.0),
                           data.get("dop_std"), data.get("f00", data.get("s0")), data.get("f00_std"), source="data")
    raise ValueError("data must be a CSV path, a dict of arrays or a Measurements object")
