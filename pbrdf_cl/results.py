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
