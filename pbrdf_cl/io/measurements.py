"""Measured DOP data: CSV reading and validation with line numbers.

CSV format: a header line naming the columns, then one measurement per line.  Required columns
``theta_i``, ``theta_r`` (degrees) and ``dop``; optional ``phi`` (degrees, default 180),
``dop_std`` (per-point standard deviation, used as weights), ``f00`` (measured BRDF, 1/sr, or
``s0``, any intensity proportional to it) with optional ``f00_std``.  Blank lines and ``#``
comments (whole-line or trailing) are ignored.

What spreadsheets and instruments write is read as well:

- UTF-8 with or without a byte-order mark, UTF-16 with one (Excel's "Unicode text"); other
  bytes are read as Latin-1 (they can only be in comments or ignored columns);
- the separator is taken from the header line: commas, else semicolons, else tabs, else runs of
  spaces (or from Excel's ``sep=;`` line before it); with semicolons, tabs or spaces a decimal
  comma (``0,052``) is a decimal point;
- names and values in quotes (``"theta_i"``); names in any case (``DOP``, ``Theta_I``);
- other columns (``wavelength``, ``sample``, ...) are ignored: a :class:`DataWarning` names them
  (with the nearest column name where one is close: ``dop_sd`` -> ``dop_std``), and
  :attr:`Measurements.ignored` lists them; empty trailing fields (``40,30,0.1,``) are dropped.

Errors are one line naming the file, the line and the column.

The same column names, in any case and with other columns ignored the same way, are taken from a
dict of arrays, a pandas (or any) DataFrame with ``.columns`` (index levels count as columns),
an xarray Dataset (data variables and coordinates, broadcast against each other: a gridded
Dataset is flattened) or a numpy structured array: :func:`as_measurements`, which
:func:`pbrdf_cl.fit`, :func:`pbrdf_cl.compare_models` and :func:`pbrdf_cl.objective` call.
"""
from __future__ import annotations

import codecs
import difflib
import os
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..compute.pointwise import RULES
from ..errors import DataWarning
from ..model import measurables
from .polar import check_polar

REQUIRED = ("theta_i", "theta_r", "dop")
OPTIONAL = ("phi", "dop_std", "f00", "s0", "f00_std")
#: The polarimetric columns (:mod:`pbrdf_cl.model.measurables`): the AoP, the Stokes vector, the Mueller
#: elements and their standard deviations, and the incident light's normalised Stokes vector.
POLAR = tuple(n for n in measurables.REGISTRY if n not in ("dop", "f00"))
POLAR_STD = tuple(f"{n}_std" for n in POLAR)
COLUMNS = tuple(dict.fromkeys(REQUIRED + OPTIONAL + POLAR + POLAR_STD + measurables.INCIDENT))
_COLUMNS_TEXT = ("theta_i, theta_r, and dop or any polarimetric quantity (aop, s0..s3, m00..m33, each with "
                 "<name>_std), optionally phi, dop_std, f00 (or s0), f00_std, in_s1..in_s3 (the incident state)")

_SEPARATORS = {",": "commas", ";": "semicolons", "\t": "tabs", None: "spaces"}
_SEP_LINE = re.compile(r"sep=([,;\t])")
_DECIMAL_COMMA = re.compile(r"[+-]?[0-9]*,[0-9]+(?:[eE][+-]?[0-9]+)?")


#: The note of a fit whose data do not give phi (:func:`pbrdf_cl.fit`, :func:`pbrdf_cl.fit_batch`).
PHI_DEFAULT_NOTE = ("phi was not given: every measurement is taken in the plane of incidence (phi = 180, the paper's "
                    "geometry); for out-of-plane measurements give phi (phi_i - phi_r, degrees)")


@dataclass
class Measurements:
    """Validated measurements (1-d float64 arrays of equal length), as :func:`pbrdf_cl.read_csv`
    and :func:`pbrdf_cl.as_measurements` return them.

    Parameters
    ----------
    theta_i, theta_r, phi : numpy.ndarray
        The geometry in degrees.
    dop : numpy.ndarray
        The measured DOP.
    dop_std : numpy.ndarray, optional
        Its standard deviations (the fit's weights).
    f00, f00_std : numpy.ndarray, optional
        An intensity (F00 or S0) and its standard deviations.
    source : str, default "arrays"
        Where the data came from (a file name), for messages.
    lines : numpy.ndarray, optional
        The file's line number of each measurement, for messages.
    ignored : tuple of str
        The names of the columns of the input that were not read (each reported once, when read,
        by a :class:`pbrdf_cl.DataWarning`).
    phi_given : bool, default True
        False where the input had no phi (every point is then taken in plane, phi = 180).
    quantities : dict
        The polarimetric columns (``aop``, ``s0`` .. ``s3``, ``m00`` .. ``m33``): name -> values, NaN
        where not measured at that row (``docs/polarimetry.md``); ``dop`` may then be None.
    stds : dict
        Their standard deviations, name -> values (those given).
    incident : numpy.ndarray, optional
        The incident light's normalised Stokes vector (s1, s2, s3) per row, shape (M, 3); None:
        unpolarized.
    """
    theta_i: np.ndarray
    theta_r: np.ndarray
    dop: np.ndarray
    phi: np.ndarray
    dop_std: np.ndarray | None = None
    f00: np.ndarray | None = None
    f00_std: np.ndarray | None = None
    source: str = "arrays"
    lines: np.ndarray | None = field(default=None, repr=False)
    ignored: tuple = ()
    #: False where the input had no phi (every point is then taken in plane, phi = 180)
    phi_given: bool = True
    #: the polarimetric columns (aop, s0..s3, m00..m33): name -> values, NaN where not measured
    quantities: dict = field(default_factory=dict)
    #: their standard deviations, name -> values (only those given)
    stds: dict = field(default_factory=dict)
    #: the incident light's normalised Stokes vector per row, (M, 3); None: unpolarised
    incident: np.ndarray | None = None

    def __len__(self):
        return self.theta_i.size

    @property
    def polarimetric(self):
        """Whether the data hold more than DOP (and F00) under unpolarised light: a polarimetric
        quantity, or an incident state."""
        return bool(self.quantities) or self.incident is not None

    def columns(self):
        """Every measured quantity: name -> values (NaN where not measured), in the registry's order."""
        cols = dict(self.quantities)
        if self.dop is not None:
            cols["dop"] = self.dop
        if self.f00 is not None:
            cols["f00"] = self.f00
        return {n: cols[n] for n in measurables.REGISTRY if n in cols}

    def channels(self):
        """The measured channels (:class:`pbrdf_cl.model.measurables.Channels`), NaN-free."""
        stds = dict(self.stds)
        if self.dop_std is not None:
            stds["dop"] = self.dop_std
        if self.f00_std is not None:
            stds["f00"] = self.f00_std
        return measurables.channels(self.theta_i, self.theta_r, self.phi, self.columns(), stds, self.incident)

    @property
    def weights(self):
        return None if self.dop_std is None else 1.0 / self.dop_std ** 2

    def as_dict(self):
        d = dict(theta_i=self.theta_i, theta_r=self.theta_r, phi=self.phi, dop=self.dop)
        if self.dop_std is not None:
            d["dop_std"] = self.dop_std
        return d


def duplicates_note(meas):
    """A note where rows repeat an earlier row exactly (geometry and every measured value), else
    None: a fit counts each row as an independent measurement, so copies of one measurement (a
    file appended to itself) narrow the intervals by up to the square root of the copies."""
    cols = [meas.theta_i, meas.theta_r, meas.phi, *meas.columns().values()]
    table = np.column_stack(cols + ([] if meas.incident is None else [meas.incident]))
    _, first, counts = np.unique(table, axis=0, return_index=True, return_counts=True)
    repeats = int(len(meas) - first.size)
    if not repeats:
        return None
    j = int(np.flatnonzero(np.isin(np.arange(len(meas)), first, invert=True))[0])
    same = (table == table[j]) | (np.isnan(table) & np.isnan(table[j]))
    i = int(np.flatnonzero(same.all(axis=1))[0])
    where = _locator("", meas.lines)
    return (f"{repeats} of the {len(meas)} rows repeat an earlier row exactly (geometry and values; e.g. "
            f"{where(j).lstrip(', ')} repeats {where(i).lstrip(', ')}), up to {int(counts.max())} copies: the fit "
            "counts each as an independent measurement; if they are copies of one measurement, remove them (the "
            "intervals are otherwise too narrow)")


def intensity_s0(values):
    """``values`` (column name -> array) with a lone ``s0`` read as the intensity ``f00`` (and
    ``s0_std`` as ``f00_std``): where no other Stokes parameter and no incident state is given, S0 is
    the BRDF for unpolarised light, F00."""
    if "s0" in values and not any(k in values for k in ("s1", "s2", "s3") + measurables.INCIDENT):
        values = dict(values)
        values["f00"] = values.pop("s0")
        if "s0_std" in values:
            values["f00_std"] = values.pop("s0_std")
    return values


def _locator(source, lines):
    if lines is not None:
        return lambda i: f"{source}, line {lines[i]}"
    return lambda i: f"{source}, row {i}"


def _validate(cols, source, locate, polar=False):
    n = len(cols["theta_i"])
    for name, values in cols.items():
        a = values
        bad = ~np.isfinite(a)
        if polar and name not in ("theta_i", "theta_r", "phi"):
            bad = np.isinf(a)  # NaN: not measured at that row
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{locate(i)}: {name} is {float(a[i])!r}; every value must be a finite number")
    checks = {"theta_i": RULES["theta_i"], "theta_r": RULES["theta_r"],
              "dop": (lambda a: (a >= 0) & (a <= 1), "in [0, 1]"),
              "dop_std": (lambda a: a > 0, "> 0"),
              "f00": (lambda a: a >= 0, ">= 0"),
              "f00_std": (lambda a: a > 0, "> 0")}
    for name, (ok, rule) in checks.items():
        if name in cols:
            good = ok(cols[name]) | np.isnan(cols[name])
            if not good.all():
                i = int(np.argmax(~good))
                raise ValueError(f"{locate(i)}: {name} = {float(cols[name][i])!r} is not {rule}")
    if n == 0:
        raise ValueError(f"{source}: no measurements")


def from_arrays(theta_i, theta_r, dop=None, phi=None, dop_std=None, f00=None, f00_std=None, source="arrays",
                _lines=None, _locate=None, **polar):
    """Validated :class:`Measurements` from arrays (broadcast to a common length); without
    ``phi`` every point is in plane (phi = 180) and ``phi_given`` is False.  ``polar``: the
    polarimetric columns by name (``aop``, ``s1``, ``m01``, their ``<name>_std``, ``in_s1``, ...;
    NaN where not measured), then checked by :func:`pbrdf_cl.io.polar.check_polar`."""
    phi_given = phi is not None
    polar = {k: v for k, v in polar.items() if v is not None}
    unknown = sorted(set(polar) - set(POLAR + POLAR_STD + measurables.INCIDENT))
    if unknown:
        raise ValueError(f"{source}: {unknown[0]!r} is not a column of measurements")
    if dop is None and not any(k in POLAR for k in polar) and f00 is None:
        raise ValueError(f"{source}: no measured quantity (give dop or a polarimetric quantity: aop, s1, m01, ...)")
    named = dict(theta_i=theta_i, theta_r=theta_r, dop=dop, phi=180.0 if phi is None else phi, dop_std=dop_std,
                 f00=f00, f00_std=f00_std, **polar)
    cols = {}
    for name, v in named.items():
        if v is None:
            continue
        try:
            cols[name] = np.atleast_1d(np.asarray(v, dtype=np.float64))
        except (TypeError, ValueError):
            raise ValueError(f"{source}: {name} must be numbers, got {_short(v)}") from None
        if cols[name].ndim != 1:
            raise ValueError(f"{source}: {name} must be 1-d, got shape {cols[name].shape}")
    try:
        arrays = np.broadcast_arrays(*cols.values())
    except ValueError:
        lengths = ", ".join(f"{k}: {v.size}" for k, v in cols.items())
        raise ValueError(f"{source}: columns differ in length ({lengths})") from None
    cols = {k: np.array(a, dtype=np.float64) for k, a in zip(cols, arrays)}
    locate = _locate or _locator(source, _lines)
    _validate(cols, source, locate, polar=bool(polar))
    if "f00_std" in cols and "f00" not in cols:
        raise ValueError(f"{source}: f00_std is given without f00")
    extra = check_polar(cols, locate) if polar else {}
    return Measurements(theta_i=cols["theta_i"], theta_r=cols["theta_r"], dop=cols.get("dop"), phi=cols["phi"],
                        dop_std=cols.get("dop_std"), f00=cols.get("f00"), f00_std=cols.get("f00_std"),
                        source=source, lines=_lines, phi_given=phi_given, **extra)


def _short(v):
    text = repr(v).replace("\n", " ")
    return text if len(text) <= 80 else text[:77] + "..."


def _resolve(names, where):
    """The model's columns among ``names`` (any case, surrounding blanks dropped): (canonical name
    -> position, the positions of the other columns).  Refuses a column named twice, f00 with s0,
    and a missing required column (naming an ignored column that looks like it)."""
    used, ignored = {}, []
    for i, raw in enumerate(names):
        key = str(raw).strip().lower()
        if key in COLUMNS:
            if key in used:
                raise ValueError(f"{where}: {str(names[used[key]]).strip()!r} and {str(raw).strip()!r} name the "
                                 "same column; give it once")
            used[key] = i
        else:
            ignored.append(i)
    if "f00" in used and "s0" in used and not any(n in used for n in ("s1", "s2", "s3") + measurables.INCIDENT):
        raise ValueError(f"{where}: give f00 or s0, not both")
    for i in ignored:  # a misspelt quantity is a mistake, not an extra column
        name = str(names[i]).strip()
        near = _nearest(name.lower(), [c for c in POLAR + measurables.INCIDENT + ("dop",) if c not in used])
        if near and len(name) > 1:
            raise ValueError(f"{where}: column {name!r} is not a quantity pbrdf-cl reads; did you mean {near!r}? "
                             f"(rename it, or drop it; the columns are {_COLUMNS_TEXT})")
    polar = any(n in used for n in POLAR + measurables.INCIDENT if n != "s0")
    for need in REQUIRED[:2] if polar else REQUIRED:
        if need not in used:
            near = _nearest(need, [str(names[i]).strip().lower() for i in ignored])
            hint = f"; the column {near!r} is not one of these names" if near else ""
            raise ValueError(f"{where}: missing column {need!r} (the columns are {_COLUMNS_TEXT}){hint}")
    return used, ignored


def _nearest(name, candidates):
    near = difflib.get_close_matches(name, candidates, n=1, cutoff=0.6)
    return near[0] if near else None


def _warn_ignored(where, names, used):
    """One :class:`DataWarning` naming the ignored columns (and the nearest column name of each)."""
    if not names:
        return
    absent = [c for c in COLUMNS if c not in used and not (c in ("f00", "s0") and ("f00" in used or "s0" in used))]
    items = []
    for name in names:
        near = _nearest(name.lower(), absent)
        items.append(f"{name!r} (did you mean {near!r}?)" if near else repr(name))
    s = "s" if len(names) > 1 else ""
    warnings.warn(f"{where}: ignored column{s} {', '.join(items)}: not an input of the model (the columns read "
                  f"are {_COLUMNS_TEXT})", DataWarning, stacklevel=3)


def _decode(path):
    with open(path, "rb") as fh:
        raw = fh.read()
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return raw.decode("utf-16")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _unquote(text):
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "\"'":
        return text[1:-1].strip()
    return text


def _split(text, sep):
    return [_unquote(f) for f in (text.split(sep) if sep else text.split())]


def _is_number(text):
    try:
        float(text.replace(",", "."))
    except ValueError:
        return False
    return True


def _sniff(header):
    for sep in (",", ";", "\t"):
        if sep in header:
            return sep
    return None


def read_csv(path) -> Measurements:
    """Read and validate a measurement CSV (see the module docstring for the forms it takes).

    Parameters
    ----------
    path : str or path
        A CSV with a header naming theta_i, theta_r, dop and optionally phi, dop_std, f00 (or s0),
        f00_std (any case; ``,`` ``;`` tab or spaces; ``#`` comments; other columns ignored with a
        :class:`DataWarning`).

    Returns
    -------
    Measurements

    Raises
    ------
    ValueError
        One line naming the file, the line and the column.

    Examples
    --------
    >>> meas = read_csv("examples/steel_435nm.csv")  # doctest: +SKIP
    >>> len(meas), meas.dop_std is not None  # doctest: +SKIP
    (30, True)
    """
    path = os.fsdecode(path)
    header = sep = used = None
    ignored, rows, lines = [], [], []
    unnamed_filled = set()
    text = _decode(path).replace("\r\n", "\n").replace("\r", "\n")
    for lineno, raw in enumerate(text.split("\n"), start=1):
        body = raw.split("#", 1)[0].strip()
        if not body:
            continue
        if header is None:
            declared = _SEP_LINE.fullmatch(body)
            if declared and sep is None:  # Excel's "sep=;" line before the header
                sep = declared.group(1)
                continue
            sep = sep or _sniff(body)
            header = _split(body, sep)
            if all(_is_number(f) for f in header):
                raise ValueError(f"{path}, line {lineno}: the first line holds numbers, not column names; start "
                                 f"the file with a header line such as theta_i,theta_r,dop")
            used, ignored = _resolve(header, f"{path}, line {lineno}")
            polar = any(n in used for n in POLAR + measurables.INCIDENT)
            header_line = lineno
            continue
        fields = _split(body, sep)
        while len(fields) > len(header) and not fields[-1]:
            fields.pop()  # trailing separators
        if len(fields) < len(header) and not any(header[len(fields):]):
            fields += [""] * (len(header) - len(fields))  # the header's trailing separators
        if len(fields) != len(header):
            hint = ""
            others = [s for s in (",", ";", "\t") if s != sep and s in body]
            if others and len(_split(body, others[0])) == len(header):
                hint = (f" (the header is separated by {_SEPARATORS[sep]}, this line by "
                        f"{_SEPARATORS[others[0]]})")
            n = len(fields)
            raise ValueError(f"{path}, line {lineno}: {n} value{'s' if n != 1 else ''} for {len(header)} "
                             f"columns{hint}")
        row = []
        for name, i in used.items():
            f = fields[i]
            if sep != "," and _DECIMAL_COMMA.fullmatch(f):
                f = f.replace(",", ".")
            if not f and polar and name not in ("theta_i", "theta_r", "phi"):
                row.append(np.nan)  # not measured at this row
                continue
            try:
                row.append(float(f))
            except ValueError:
                what = f"{header[i]} is empty" if not f else f"{header[i]} = {fields[i]!r} is not a number"
                raise ValueError(f"{path}, line {lineno}: {what}") from None
        unnamed_filled.update(i for i in ignored if not header[i] and fields[i])
        rows.append(row)
        lines.append(lineno)
    if header is None:
        raise ValueError(f"{path}: empty file (no header line)")
    if not rows:
        raise ValueError(f"{path}: no measurements after the header")
    names = [header[i] if header[i] else f"column {i + 1} (unnamed)" for i in ignored
             if header[i] or i in unnamed_filled]
    _warn_ignored(f"{path}, line {header_line}", names, used)
    table = np.array(rows, dtype=np.float64)
    cols = intensity_s0({name: table[:, j] for j, name in enumerate(used)})
    meas = from_arrays(**cols, source=path, _lines=np.array(lines))
    meas.ignored = tuple(names)
    return meas


def write_csv(path, meas: Measurements, header_comment: str = ""):
    """Write measurements as a CSV readable by :func:`read_csv`: the geometry, every measured
    quantity (DOP, F00, and the polarimetric ones) with its ``<name>_std`` where given, and the
    incident state (``in_s1, in_s2, in_s3``) where the light is polarized; NaN where a quantity is
    not measured at a row."""
    stds = {**meas.stds, **({"dop": meas.dop_std} if meas.dop_std is not None else {}),
            **({"f00": meas.f00_std} if meas.f00_std is not None else {})}
    cols = [("theta_i", meas.theta_i), ("theta_r", meas.theta_r), ("phi", meas.phi)]
    for name, values in meas.columns().items():
        cols.append((name, values))
        if name in stds:
            cols.append((f"{name}_std", stds[name]))
    if meas.incident is not None:
        cols += [(f"in_s{i + 1}", meas.incident[:, i]) for i in range(3)]
    with open(path, "w", encoding="utf-8") as fh:
        for line in header_comment.strip().splitlines():
            fh.write(f"# {line}\n")
        fh.write(",".join(c for c, _ in cols) + "\n")
        for i in range(len(meas)):
            fh.write(",".join(f"{v[i]:.10g}" for _, v in cols) + "\n")


def _column_values(col):
    """A DataFrame column (pandas Series, polars Series, anything with ``to_numpy`` or
    ``__array__``) as an array; missing values (pandas' NA) as NaN."""
    to_numpy = getattr(col, "to_numpy", None)
    if to_numpy is not None:
        try:
            return to_numpy(dtype=np.float64, na_value=np.nan)
        except (TypeError, ValueError):
            return to_numpy()
    return col


def _dataset_columns(ds):
    """(names, get, locate) of an xarray Dataset: data variables and coordinates, broadcast
    against each other and flattened; ``locate(i)`` names the i-th point by its coordinates."""
    import xarray as xr
    names = list(ds.data_vars) + [c for c in ds.coords if c not in ds.data_vars]
    state = {}

    def get(chosen):
        arrays = xr.broadcast(*[ds[n] for n in chosen])
        state["dims"], state["shape"] = arrays[0].dims, arrays[0].shape
        return [np.asarray(a.values).reshape(-1) for a in arrays]

    def locate(i):
        dims, shape = state.get("dims", ()), state.get("shape", ())
        if not dims:
            return "data"
        parts = []
        for d, j in zip(dims, np.unravel_index(i, shape)):
            if d in ds.coords and ds[d].ndim == 1:
                v = ds[d].values[j]
                parts.append(f"{d}={v:g}" if np.issubdtype(np.asarray(v).dtype, np.number) else f"{d}={v}")
            else:
                parts.append(f"{d}[{j}]")
        return "data, at " + ", ".join(parts)
    return names, get, locate


def _table_columns(data):
    """(names, get, locate) of a dict of arrays, a DataFrame-like table or a structured array, or
    None for anything else."""
    if isinstance(data, Mapping):
        names = list(data.keys())
        return names, lambda chosen: [_column_values(data[n]) for n in chosen], None
    columns = getattr(data, "columns", None)
    if columns is not None and hasattr(data, "__getitem__"):
        names = list(columns)
        index = getattr(data, "index", None)
        levels = [n for n in (getattr(index, "names", None) or []) if n is not None and n not in names]

        def get(chosen):
            return [np.asarray(index.get_level_values(n)) if n in levels else _column_values(data[n]) for n in chosen]
        return names + levels, get, None
    dtype = getattr(data, "dtype", None)
    if dtype is not None and getattr(dtype, "names", None):
        names = list(dtype.names)
        return names, lambda chosen: [np.asarray(data[n]).reshape(-1) for n in chosen], None
    return None


def as_measurements(data) -> "Measurements":
    """Validated measurements from what users have.

    Parameters
    ----------
    data : str or path, dict, DataFrame, xarray.Dataset, numpy structured array or Measurements
        Columns theta_i, theta_r, dop[, phi, dop_std, f00 (or s0), f00_std], names in any case;
        other columns are ignored with a :class:`DataWarning` naming them (module docstring).

    Returns
    -------
    Measurements
        ``data`` itself when it is one.

    Examples
    --------
    >>> len(as_measurements(dict(theta_i=[40, 40], theta_r=[20, 45], DOP=[0.1, 0.2])))
    2
    """
    if isinstance(data, Measurements):
        return data
    if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__"):
        return read_csv(data)
    if hasattr(data, "data_vars") and hasattr(data, "coords"):
        names, get, locate = _dataset_columns(data)
    else:
        found = _table_columns(data)
        if found is None:
            raise ValueError("data must be a CSV path, a dict of arrays, a DataFrame, an xarray Dataset or a "
                             f"Measurements object, got {type(data).__name__}")
        names, get, locate = found
    used, ignored = _resolve(names, "data")
    chosen = list(used)
    values = intensity_s0(dict(zip(chosen, get([names[used[c]] for c in chosen]))))
    shown = [str(names[i]) for i in ignored]
    _warn_ignored("data", shown, used)
    meas = from_arrays(**values, source="data", _locate=locate)
    meas.ignored = tuple(shown)
    return meas


def subset(meas, mask, source):
    """The measurements of ``meas`` where ``mask`` is True, as :class:`Measurements` named ``source``."""
    from dataclasses import replace

    def cut(a):
        return None if a is None else a[mask]
    return replace(meas, theta_i=meas.theta_i[mask], theta_r=meas.theta_r[mask], dop=cut(meas.dop),
                   phi=meas.phi[mask], dop_std=cut(meas.dop_std), f00=cut(meas.f00), f00_std=cut(meas.f00_std),
                   lines=cut(meas.lines), source=source, quantities={k: v[mask] for k, v in meas.quantities.items()},
                   stds={k: v[mask] for k, v in meas.stds.items()}, incident=cut(meas.incident))


def _label_text(v):
    """A set's name from its value in the set column: numbers as %g (435.0 -> "435")."""
    try:
        return f"{float(v):g}"
    except (TypeError, ValueError):
        return str(v).strip()


def _csv_column_text(path, column):
    """(the text of ``column`` on each measurement line, in file order; the header names) of a
    CSV that :func:`read_csv` reads (the same lines: blank lines and comments skipped)."""
    header = sep = None
    out = []
    for raw in _decode(path).replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        body = raw.split("#", 1)[0].strip()
        if not body:
            continue
        if header is None:
            declared = _SEP_LINE.fullmatch(body)
            if declared and sep is None:
                sep = declared.group(1)
                continue
            sep = sep or _sniff(body)
            header = _split(body, sep)
            keys = [h.strip().lower() for h in header]
            if column.lower() not in keys:
                return None, header
            j = keys.index(column.lower())
            continue
        fields = _split(body, sep)
        out.append(fields[j] if j < len(fields) else "")
    return out, header or []


def split_sets(data, column):
    """Split one table of measurements into sets by the values of one of its columns.

    Parameters
    ----------
    data : str or path, dict, DataFrame, xarray.Dataset or numpy structured array
        The measurements of every set (as :func:`as_measurements` takes them) and a column ``column``.
    column : str
        The column naming each measurement's set (any case), e.g. ``"wavelength"`` or ``"sample"``;
        numbers name a set as ``%g`` (435.0 -> "435").

    Returns
    -------
    dict
        Set name -> :class:`Measurements`, in the order the sets first appear.

    Raises
    ------
    ValueError
        One line, where ``data`` has no such column (naming its columns).

    Examples
    --------
    >>> t = dict(theta_i=[40, 40, 40, 40], theta_r=[20, 45, 20, 45], dop=[.1, .2, .1, .3],
    ...          wavelength=[435, 435, 633, 633])
    >>> sorted(split_sets(t, "wavelength"))
    ['435', '633']
    """
    if isinstance(data, Measurements):
        raise ValueError(f"{data.source}: Measurements hold no {column!r} column; give the table itself")
    where = "data"
    if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__"):
        where = os.fsdecode(data)
        labels, names = _csv_column_text(where, column)
    else:
        found = _dataset_columns(data) if hasattr(data, "data_vars") else _table_columns(data)
        if found is None:
            raise ValueError("data must be a CSV path, a dict of arrays, a DataFrame, an xarray Dataset or a "
                             f"structured array to split by {column!r}, got {type(data).__name__}")
        names = [str(n) for n in found[0]]
        keys = [n.strip().lower() for n in names]
        labels = (list(np.asarray(found[1]([found[0][keys.index(column.lower())]])[0]).reshape(-1))
                  if column.lower() in keys else None)
    if labels is None:
        raise ValueError(f"{where}: no column {column!r} to split the sets by (the columns are "
                         f"{', '.join(str(n).strip() for n in names)})")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        meas = as_measurements(data)
    if any(n.strip().lower() != column.lower() for n in meas.ignored):
        for w in seen:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    labels = np.array([_label_text(v) for v in labels], dtype=object)
    order = list(dict.fromkeys(labels))
    return {name: subset(meas, labels == name, f"{meas.source} ({column} = {name})") for name in order}
