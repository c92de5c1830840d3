"""Result objects: dicts whose keys are also attributes, like scipy's ``OptimizeResult``."""
from __future__ import annotations


class Result(dict):
    """A dict with attribute access (read, assignment and deletion), like scipy's ``OptimizeResult``."""

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None

    def __setattr__(self, name, value):
        self[name] = value

    def __delattr__(self, name):
        try:
            del self[name]
        except KeyError:
            raise AttributeError(name) from None

    def __dir__(self):
        return list(self.keys())


class ObjectiveResult(Result):
    """Result of :func:`pbrdf_cl.objective` (attribute access, like scipy's ``OptimizeResult``).

    sse : xarray.DataArray over the parameter axes (grid) or 1-d array (points), or None
    best : dict of the k best parameter vectors (each parameter an array, best first) and their "sse"
    n_pairs : parameter vectors x measurements evaluated
    seconds : wall time
    """

    def __repr__(self):
        best = {k: v[0] for k, v in self["best"].items()} if len(self["best"]["sse"]) else {}
        return f"ObjectiveResult(n_pairs={self['n_pairs']}, seconds={self['seconds']:.3g}, best={best})"
