"""The registry of output quantities: one record per quantity, read by every path.

A quantity's physics is two functions in ``kernels/pbrdf.h`` and their mirrors in
``pbrdf_cl/model/reference.py``, named after it: ``pb_point_<name>`` / ``point_<name>`` (one point, from
the geometry, Fresnel factors, log K and the diffuse term) and, for the dense grids,
``pb_grid_<name>`` / ``grid_<name>`` (from the factor tables).  The record below says everything
else: how to build the kernels (``-DPB_QUANTITY=<name>``, its width, which tables and factors),
its units and labels, and which paths support it (points, grid, reduce, objective, sweep, map)
with the reason where one does not.  Adding a quantity = those two physics functions, one record
here, and tests.

Names are canonical; :func:`get` also takes the aliases (``"f00"`` is ``"brdf"``) and any case,
and raises a one-line ``ValueError`` for an unknown name (with the nearest name) or an
unsupported path.
"""
from __future__ import annotations

from dataclasses import dataclass, field

PATHS = ("points", "grid", "reduce", "objective", "sweep", "map")


@dataclass(frozen=True)
class Quantity:
    """One output quantity.

    name : canonical name (the kernels' ``PB_QUANTITY``; ``pb_point_<name>``, ``pb_grid_<name>``)
    long_name, units, symbol : for DataArray attrs and figure axes (``label``: symbol and units)
    components : names along the trailing axis (empty: one value per point); ``trailing`` is its shape
    scale_sign : the grid tables' scale is exp(scale_sign * log K): -1 gives 1/K, +1 gives K
    diffuse_factor : the grid tables' diffuse term is diffuse_factor * fd
    frame : whether the grid needs the outgoing frame's rotation table (C, S)
    vector : the per-point path has a vector kernel ``<name>_points_vec`` (which checks the domain
        itself, writing NaN outside it); otherwise the generic ``quantity_points``
    grid_vector : pbrdf_grid.cl's row kernels have a vector body for it (``pb_dop_combine_v``)
    undefined_nan : NaN marks points where the quantity is undefined (not an error)
    paths : where it is available; ``refused`` gives the reason for each path it is not
    period : the quantity is an angle modulo ``period`` (differences are wrapped into one period)
    cmap, vmin, vmax : the colour map of figures and its fixed range (None: from the data)
    """

    name: str
    long_name: str
    units: str
    symbol: str
    components: tuple = ()
    trailing: tuple = ()
    scale_sign: float = 1.0
    diffuse_factor: float = 1.0
    frame: bool = False
    vector: bool = False
    grid_vector: bool = False
    undefined_nan: bool = False
    paths: tuple = ("points", "grid", "reduce", "sweep", "map")
    refused: dict = field(default_factory=dict)
    period: float | None = None
    cmap: str = "viridis"
    vmin: float | None = None
    vmax: float | None = None
    aliases: tuple = ()

    @property
    def label(self):
        """The symbol with its units, for colour bars: "F00 (1/sr)", "DOP"."""
        return self.symbol if self.units == "1" else f"{self.symbol} ({self.units})"

    @property
    def width(self):
        """Values per point (the product of ``trailing``)."""
        w = 1
        for n in self.trailing:
            w *= n
        return w

    def defines(self):
        """The kernels' -D defines for this quantity (grid and generic point kernels)."""
        d = {"PB_QUANTITY": self.name, "PB_WIDTH": self.width}
        if self.frame:
            d["PB_FRAME"] = None
        if self.grid_vector:
            d["PB_GRID_VECTOR"] = None
        return d


_ANGLE = "an angle: its mean and minimum are not meaningful; reduce a grid of it yourself (a circular mean)"
_VECTOR = "a vector per point: reduce or map one component yourself from pbrdf_cl.grid(..., quantity='stokes')"

REGISTRY = {q.name: q for q in (
    Quantity("dop", "degree of polarization", "1", "DOP", scale_sign=-1.0, diffuse_factor=2.0, vector=True,
             grid_vector=True,
             paths=("points", "grid", "reduce", "objective", "sweep", "map")),  # colours over the data's range
    Quantity("brdf", "BRDF F00", "1/sr", "F00", vector=True, aliases=("f00",)),
    Quantity("aop", "angle of linear polarization (psps frame of the reflected beam)", "deg", "AoP",
             frame=True, undefined_nan=True, paths=("points", "grid", "sweep", "map"),
             refused={"reduce": _ANGLE}, period=180.0, cmap="twilight", vmin=-90.0, vmax=90.0),
    Quantity("stokes", "Stokes vector of the reflected light for unpolarised incidence", "1/sr",
             "S", components=("S0", "S1", "S2", "S3"), trailing=(4,), frame=True,
             paths=("points", "grid"), refused={"reduce": _VECTOR, "map": _VECTOR, "sweep": _VECTOR}),
    Quantity("mueller", "Mueller-matrix BRDF (psps frames)", "1/sr", "F", trailing=(4, 4),
             paths=("points",),
             refused={p: "a 4x4 matrix per point: on grids use quantity='stokes' (its first column) or "
                      "evaluate pbrdf_cl.mueller over broadcast arrays" for p in ("grid", "reduce", "sweep", "map")}),
)}
ALIASES = {a: q.name for q in REGISTRY.values() for a in q.aliases}
NAMES = tuple(REGISTRY)


def names(path=None):
    """Canonical names of the quantities available on ``path`` (all of them for None).

    Parameters
    ----------
    path : {None, "points", "grid", "sweep", "map", "reduce", "objective"}
        Where the quantities are to be computed.

    Returns
    -------
    tuple of str
    """
    return tuple(n for n, q in REGISTRY.items() if path is None or path in q.paths)


def get(name, path=None, where="quantity"):
    """The ``Quantity`` record of ``name`` (canonical or alias).

    Parameters
    ----------
    name : str
        A quantity's name or alias (``"dop"``, ``"f00"``, ...), in any case.
    path : str, optional
        With a path (see :func:`names`), a ``ValueError`` saying why unless it is available there.
    where : str, default "quantity"
        Names the argument in messages.

    Returns
    -------
    Quantity
        The registry's record: name, units, labels, colour map, the paths it supports.
    """
    low = name.strip().lower() if isinstance(name, str) else name
    key = ALIASES.get(low, low) if isinstance(low, str) else low
    q = REGISTRY.get(key) if isinstance(key, str) else None
    if q is None:
        import difflib
        avail = names(path)
        close = difflib.get_close_matches(str(low), list(REGISTRY) + list(ALIASES), n=1, cutoff=0.6)
        raise ValueError(f"{where}: unknown quantity {name!r}" + (f" (did you mean {close[0]!r}?)" if close else "")
                         + f"; valid names are {', '.join(avail)}"
                         + (f" (aliases: {', '.join(f'{a}={c}' for a, c in ALIASES.items())})" if ALIASES else ""))
    if path is not None and path not in q.paths:
        why = q.refused.get(path, "not implemented")
        raise ValueError(f"{where}: {q.name!r} is not available for {path}: {why}; available there: "
                         f"{', '.join(names(path))}")
    return q


def canonical(name, path=None, where="quantity"):
    """The canonical name of ``name`` (``"f00"`` -> ``"brdf"``).

    Parameters
    ----------
    name, path, where
        As for :func:`get`.

    Returns
    -------
    str
    """
    return get(name, path, where).name


def wrap(difference, period):
    """``difference`` of an angle modulo ``period`` into [-period/2, period/2) (None: unchanged)."""
    if period is None:
        return difference
    half = 0.5 * period
    return (difference + half) % period - half
