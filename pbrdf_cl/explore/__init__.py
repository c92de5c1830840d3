"""Exploring the parameter space: global sensitivity, measurement design, maps, sweeps, the paper's figures.

The package is callable too: ``pbrdf_cl.explore()`` returns the interactive explorer's page for a
notebook (:func:`pbrdf_cl.app.server.explore_app`; the optional ``explore`` extra), while
``pbrdf_cl.explore.maps`` and the other modules stay importable as before."""
import sys
import types


class _CallableModule(types.ModuleType):
    """This package, callable: ``pbrdf_cl.explore(data=None, engine=None, query=None)``."""

    def __call__(self, data=None, *, engine=None, query=None):
        from ..app import require_panel
        require_panel()  # one line naming the extra when panel is missing, before importing the page
        from ..app.server import explore_app
        return explore_app(data, engine=engine, query=query)


sys.modules[__name__].__class__ = _CallableModule
