"""Parameter-set files: one material's six parameters as JSON or TOML, written by the explorer
(``pbrdf-cl explore``) and read by ``pbrdf-cl eval --params`` and ``pbrdf-cl map --params``.

A file is one flat table of numbers, any of ``n k sigma ks kd c``::

    n = 1.6
    k = 2.139
    sigma = 0.5
    ks = 0.9
    kd = 0.15
    c = -0.3

(JSON: ``{"n": 1.6, "k": 2.139, ...}``).  Other keys are refused, naming the key and the nearest
parameter name.
"""
from __future__ import annotations

import json
from pathlib import Path

from ..model import inputs
from ..ranges import did_you_mean

#: The parameters a file may hold, in the model's order.
NAMES = inputs.PARAMETERS


def params_text(values, fmt="json"):
    """The text of a parameter-set file.

    Parameters
    ----------
    values : dict
        Name -> number for the parameters of :data:`NAMES` (others are left out).
    fmt : {"json", "toml"}
        The format.

    Returns
    -------
    str
        The file's text, ending with a newline.

    Examples
    --------
    >>> print(params_text(dict(n=1.6, k=2.139), "toml"), end="")
    n = 1.6
    k = 2.139
    """
    table = {k: float(values[k]) for k in NAMES if k in values}
    if fmt == "json":
        return json.dumps(table, indent=2) + "\n"
    if fmt == "toml":
        return "".join(f"{k} = {v!r}\n" for k, v in table.items())
    raise ValueError(f"format must be json or toml, got {fmt!r}")


def read_params(path):
    """Read a parameter-set file (``.json`` or ``.toml``).

    Parameters
    ----------
    path : str or path
        The file.

    Returns
    -------
    dict
        Name -> float, for the parameters the file gives.

    Raises
    ------
    ValueError
        One line naming the file and what is wrong (a key that is no parameter, a value that is
        not a number, a file that is neither JSON nor TOML).

    Examples
    --------
    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "steel.json")
    >>> _ = open(p, "w").write(params_text(dict(n=1.6, k=2.139, sigma=0.5)))
    >>> read_params(p)
    {'n': 1.6, 'k': 2.139, 'sigma': 0.5}
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8-sig")
    suffix = path.suffix.lower()
    try:
        import tomllib
    except ImportError:  # Python < 3.11
        import tomli as tomllib
    if suffix not in (".json", ".toml"):
        raise ValueError(f"{path}: a parameter file is .json or .toml, got {suffix or 'no suffix'!r}")
    try:
        table = json.loads(text) if suffix == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"{path}: not valid {suffix[1:].upper()}: {str(exc).splitlines()[0]}") from None
    if not isinstance(table, dict):
        raise ValueError(f"{path}: a parameter file is one table of name = number, got {type(table).__name__}")
    out = {}
    for key, value in table.items():
        if key not in NAMES:
            near = did_you_mean(key, NAMES)
            raise ValueError(f"{path}: unknown parameter {key!r}" + (f"; did you mean {near}?" if near else "")
                             + f" (the parameters are {', '.join(NAMES)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{path}: {key} = {value!r} is not a number")
        out[key] = float(value)
    return out

