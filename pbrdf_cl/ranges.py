"""The one grammar of values, ranges and ``name=value`` items: the command line (``pbrdf-cl
eval``, ``fit``, ``map``), sweep spec files and :func:`pbrdf_cl.analysis.maps.make_map` all parse with it.

Values (docs/guide/cli.md, section "Ranges and name=value"):

- ``40``: one number;
- ``20,30,45``: a list of numbers;
- ``20:65:5``: start:stop:step, both ends included; the steps must land on the stop exactly
  (``0:10:3`` is refused: write ``0:9:3``), a negative step counts down (``60:20:-5``);
- ``0:85@256``: start:stop@count, ``count`` (>= 2) evenly spaced values, both ends included.

Bounds are ``low:high`` (``pbrdf-cl fit --bounds n=1:3``); an item is ``name=text``, its name
one of a known list.  Every refusal is a :class:`RangeError` (a ``ValueError``) of one line: where
(the option or field and the text given), what is wrong, and the right spelling.
"""
from __future__ import annotations

import difflib
import math
import numbers
import re

import numpy as np

from .errors import RangeError
from .model import inputs

#: The grammar in a few words, for ``--help`` texts (docs/guide/cli.md has the whole of it).
GRAMMAR = ("a number (40), a list (20,30,45), start:stop:step (20:65:5, ends included) or "
           "start:stop@count (0:85@256: 256 values, ends included)")
#: The relative slack with which the steps of start:stop:step must land on the stop.
STOP_TOLERANCE = 1e-9
_HINT = "write a number (40), a list (20,30,45), start:stop:step (20:65:5) or start:stop@count (0:85@256)"
_COUNT = re.compile(r"[0-9]+")


def fmt(v):
    """A number as a user would write it: ``85``, ``0.05``, ``-0.3``, ``1e-06``."""
    v = float(v)
    return f"{v:.12g}"


def _number(token, what="value"):
    token = token.strip()
    try:
        v = float(token)
    except ValueError:
        raise RangeError(f"{what} {token!r} is not a number; {_HINT}" if token else f"empty {what}; {_HINT}") from None
    if not np.isfinite(v):
        raise RangeError(f"{what} {token!r} is not a finite number; write a finite number such as 40")
    return v


def _label(where, text):
    return f"{where} {text}" if where else text


def _raise(where, text, bad):
    raise RangeError(f"{_label(where, text)}: {bad}") from None


def _step_values(start, stop, step, s0, s1):
    """start:stop:step (``s0``, ``s1``: start and stop as the user wrote them)."""
    if step == 0:
        raise RangeError(f"the step must not be 0; write {s0}:{s1}:STEP, or {s0}:{s1}@N for N values")
    if start == stop:
        raise RangeError(f"start and stop are both {s0}; for the single value write {s0}")
    if (stop - start) * step < 0:
        if step > 0:
            raise RangeError(f"the step {fmt(step)} goes up from {s0} but the stop {s1} is below it; write "
                       f"{s0}:{s1}:{fmt(-step)} to count down, or {s1}:{s0}:{fmt(step)}")
        raise RangeError(f"the step {fmt(step)} goes down from {s0} but the stop {s1} is above it; write "
                   f"{s0}:{s1}:{fmt(-step)}")
    span = abs(stop - start)
    whole = float(step).is_integer() and abs(step) >= 2
    if abs(step) > span * (1 + STOP_TOLERANCE):
        count = f"for {int(abs(step))} values write {s0}:{s1}@{int(abs(step))}" if whole else \
            f"write a step of at most {fmt(span)}, or {s0}:{s1}@N for N values"
        raise RangeError(f"step {fmt(step)} is larger than the range {s0}..{s1}; {count}")
    n = (stop - start) / step
    k = round(n)
    if abs(n - k) > STOP_TOLERANCE * max(1.0, abs(n)):
        last = fmt(start + np.floor(n) * step)
        count = int(abs(step)) if whole else int(np.floor(n)) + 1
        raise RangeError(f"steps of {fmt(step)} from {s0} miss the stop {s1} (the last is {last}); write "
                   f"{s0}:{last}:{fmt(step)}, or {s0}:{s1}@{count} for {count} values from {s0} to {s1}")
    return np.linspace(start, stop, int(k) + 1)


def _count_values(start, stop, count, s0, s1, c):
    """start:stop@count (``s0``, ``s1``, ``c``: as the user wrote them)."""
    if not isinstance(count, int) or count < 2:
        single = f"; for one value write {s0}" if isinstance(count, int) and count == 1 else ""
        raise RangeError(f"count {c} is not an integer >= 2; write {s0}:{s1}@N with N >= 2{single}")
    if start == stop:
        raise RangeError(f"start and stop are both {s0}; for the single value write {s0}")
    return np.linspace(start, stop, count)


def _values(text):
    text = text.strip()
    if not text:
        raise RangeError(f"empty; {_HINT}")
    if "," in text and (":" in text or "@" in text):
        raise RangeError("a list holds numbers only and a range stands alone; write a list (20,30,45) or one range "
                   "(20:65:5, 0:85@256)")
    if "@" in text:
        head, _, c = text.partition("@")
        parts = head.split(":")
        if len(parts) == 3:
            raise RangeError(f"give a step ({head}) or a count ({parts[0]}:{parts[1]}@{c}), not both")
        if len(parts) != 2 or "@" in c:
            raise RangeError("a count range is start:stop@count, e.g. 0:85@256")
        start, stop = _number(parts[0], "start"), _number(parts[1], "stop")
        c = c.strip()
        if not c:
            raise RangeError(f"no count after '@'; write {parts[0].strip()}:{parts[1].strip()}@N with N >= 2")
        count = int(c) if _COUNT.fullmatch(c) else None
        return _count_values(start, stop, count, parts[0].strip(), parts[1].strip(), c)
    if ":" in text:
        parts = text.split(":")
        if len(parts) == 2:
            s0, s1 = parts[0].strip(), parts[1].strip()
            raise RangeError(f"a range needs a step or a count; write {s0}:{s1}:STEP (ends included) "
                       f"or {s0}:{s1}@N for N values")
        if len(parts) != 3:
            raise RangeError("too many ':'; write start:stop:step (20:65:5) or start:stop@count (0:85@256)")
        start, stop, step = (_number(p, w) for p, w in zip(parts, ("start", "stop", "step")))
        return _step_values(start, stop, step, parts[0].strip(), parts[1].strip())
    items = text.split(",")
    if len(items) > 1 and any(not i.strip() for i in items):
        raise RangeError(f"empty item in the list; write {','.join(i.strip() for i in items if i.strip())}")
    return np.array([_number(i, "list item" if len(items) > 1 else "value") for i in items])


def parse_values(text, where=None, label=None):
    """``"40"``, ``"20,30,45"``, ``"20:65:5"`` or ``"0:85@256"`` -> a 1-d float64 array.

    Parameters
    ----------
    text : str
        The values, in the grammar of the guide's "Ranges and name=value".
    where : str, optional
        An option such as ``"--theta-r"``: the :class:`pbrdf_cl.RangeError` message starts with
        it and the text.
    label : str, optional
        Starts the message instead, where given (a sweep spec's ``axes.sigma = "1:0:0.1"``).

    Returns
    -------
    numpy.ndarray"""
    if not isinstance(text, str):
        raise RangeError(f"{label or _label(where, repr(text))}: not a text; {_HINT}")
    try:
        return _values(text)
    except RangeError as bad:
        raise RangeError(f"{label or _label(where, text)}: {bad}") from None


def step_values(start, stop, step, where):
    """start:stop:step given as numbers (a sweep spec's ``{start, stop, step}`` table)."""
    try:
        return _step_values(float(start), float(stop), float(step), fmt(start), fmt(stop))
    except RangeError as bad:
        raise RangeError(f"{where}: {bad}") from None


def count_values(start, stop, count, where):
    """start:stop@count given as numbers (a sweep spec's ``{start, stop, num}`` table)."""
    ok = isinstance(count, (int, np.integer)) and not isinstance(count, bool)
    try:
        return _count_values(float(start), float(stop), int(count) if ok else None, fmt(start), fmt(stop),
                             repr(count))
    except RangeError as bad:
        raise RangeError(f"{where}: {bad}") from None


def _bounds(text, name):
    parts = text.split(":")
    spell = f"{name}=LOW:HIGH" if name else "LOW:HIGH"
    if len(parts) != 2 or "@" in text or "," in text:
        dash = re.fullmatch(r"([-+]?[0-9.]+(?:e[-+]?[0-9]+)?)\s*-\s*([-+]?[0-9.]+(?:e[-+]?[0-9]+)?)", text, re.I)
        if dash:
            spell = f"{name}={dash.group(1)}:{dash.group(2)}" if name else f"{dash.group(1)}:{dash.group(2)}"
        elif len(parts) == 3:
            pair = f"{parts[0].strip()}:{parts[1].strip()}"
            spell = f"{name}={pair}" if name else pair
        raise RangeError(f"bounds are low:high, two numbers; write {spell}")
    lo, hi = _number(parts[0], "low"), _number(parts[1], "high")
    pre = f"{name}=" if name else ""
    if lo > hi:
        raise RangeError(f"low {parts[0].strip()} is above high {parts[1].strip()}; write "
                   f"{pre}{parts[1].strip()}:{parts[0].strip()}")
    if lo == hi:
        raise RangeError(f"low and high are both {parts[0].strip()}; give low < high, or hold {name or 'it'} fixed")
    return lo, hi


def parse_bounds(text, where=None, name=None):
    """``"1:3"`` -> (1.0, 3.0), low < high, both finite."""
    try:
        return _bounds(text.strip(), name)
    except RangeError as bad:
        _raise(where, text, bad)


#: Size units of :func:`parse_bytes` (case-insensitive): decimal kB..TB and binary KiB..TiB.
SIZE_UNITS = {"": 1, "b": 1, "kb": 10 ** 3, "mb": 10 ** 6, "gb": 10 ** 9, "tb": 10 ** 12,
              "kib": 1 << 10, "mib": 1 << 20, "gib": 1 << 30, "tib": 1 << 40}
_SIZE = re.compile(r"\s*([0-9]*\.?[0-9]+(?:[eE][+]?[0-9]+)?)\s*([KMGT]i?B|B)?\s*", re.IGNORECASE)
_SIZE_HINT = 'is not a size such as 268435456, "256 MiB" or "1 GB"'


def parse_bytes(field, value):
    """A size in bytes: ``268435456`` (an integer, or a whole float such as ``1e9``), ``"256 MiB"``,
    ``"1.5GB"``, ``"64kib"`` -> int > 0.  The one parser of sizes (``memory_budget`` of
    :func:`pbrdf_cl.grid`, :func:`pbrdf_cl.reduce_grid`, :func:`pbrdf_cl.objective` and of sweep
    specs).

    Parameters
    ----------
    field : str
        The field or argument, named by the :class:`pbrdf_cl.RangeError` of one line.
    value : int, float or str
        The size.

    Returns
    -------
    int"""
    if isinstance(value, (bool, np.bool_)):
        raise RangeError(f"{field}: {value!r} {_SIZE_HINT}")
    if isinstance(value, numbers.Integral):
        n = int(value)
    elif isinstance(value, numbers.Real):
        if not math.isfinite(value) or value != int(value):
            raise RangeError(f"{field}: {value!r} {_SIZE_HINT} (a whole number of bytes)")
        n = int(value)
    elif isinstance(value, str):
        m = _SIZE.fullmatch(value)
        if not m:
            raise RangeError(f"{field}: {value!r} {_SIZE_HINT}")
        n = int(float(m.group(1)) * SIZE_UNITS[(m.group(2) or "").lower()])
    else:
        raise RangeError(f"{field}: {value!r} {_SIZE_HINT}")
    if n <= 0:
        raise RangeError(f"{field}: must be > 0 bytes, got {value!r}")
    return n


def did_you_mean(name, names):
    """The one of ``names`` closest to ``name`` (lower case, ``-`` read as ``_``; difflib's ratio at
    least 0.6), else None: the suggestion of a refusal of an unknown name."""
    near = difflib.get_close_matches(name.lower().replace("-", "_"), names, n=1, cutoff=0.6)
    return near[0] if near else None


KINDS = ("value", "values", "bounds")


def parse_assignment(item, names, kind="value", where=None, check=False):
    """``"sigma=0.45"`` -> ("sigma", value).

    ``kind``: ``"value"`` (one number), ``"values"`` (the whole grammar: a 1-d array) or
    ``"bounds"`` (``low:high``: a pair).  ``names``: the names allowed (an unknown one is refused
    with the nearest known one suggested).  ``check``: also check the numbers against the model's
    domain (:data:`pbrdf_cl.model.inputs.RULES`)."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    name, sep, text = item.partition("=")
    name = name.strip()
    value = {"value": "VALUE", "values": "VALUES", "bounds": "LOW:HIGH"}[kind]
    if not sep or not name:
        spell = f"{name}={value}" if name in names else f"NAME={value} with NAME one of {', '.join(names)}"
        _raise(where, item, f"not of the form name={value.lower()}; write {spell}")
    if name not in names:
        near = did_you_mean(name, names)
        hint = f"did you mean {near}={text}?" if near else f"names are {', '.join(names)}"
        _raise(where, item, f"unknown name {name!r}; {hint}")
    if not text.strip():
        _raise(where, item, f"no value after '='; write {name}={value}")
    try:
        if kind == "bounds":
            out = _bounds(text.strip(), name)
        elif kind == "values":
            out = _values(text)
        else:
            if ":" in text or "," in text or "@" in text:
                first = re.split("[:,@]", text)[0].strip() or "VALUE"
                raise RangeError(f"one number is expected here; write {name}={first}")
            out = _number(text)
    except RangeError as bad:
        _raise(where, item, bad)
    if check:
        try:
            inputs.refuse_outside(name, np.asarray(out, dtype=np.float64))
        except ValueError as exc:
            _raise(where, item, exc)
    return name, out


def parse_assignments(items, names, kind="value", where=None, check=False):
    """``["theta_i=40", "n=1.6"]`` -> {"theta_i": 40.0, "n": 1.6} with :func:`parse_assignment`;
    a name given twice is refused."""
    out = {}
    for item in items or []:
        name, value = parse_assignment(item, names, kind, where, check)
        if name in out:
            _raise(where, item, f"{name} is given twice; give it once")
        out[name] = value
    return out
