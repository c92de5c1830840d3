"""The interactive explorer (``pbrdf-cl explore``, ``pbrdf_cl.explore()``): a local web page
(Panel/Bokeh, the optional ``explore`` extra) with the six parameters on sliders and the model's
curves, polar plot and maps updating live, measurements with a background fit, a Sobol' map and a
measurement design on demand, exports and the state in the URL.

``state`` holds what needs no browser (and no panel); ``figures``, ``page`` and ``server`` import
panel and bokeh, so import them only through :func:`require_panel` or after it."""
from __future__ import annotations

from ..errors import CommandError

INSTALL_HINT = "pip install 'pbrdf-cl[explore]'"


def require_panel():
    """Import panel, or raise :class:`pbrdf_cl.CommandError` in one line saying how to install it."""
    try:
        import bokeh  # noqa: F401
        import panel  # noqa: F401
    except ImportError as exc:
        raise CommandError(f"the explorer needs panel and bokeh ({exc.name} is missing): {INSTALL_HINT}") from None


def explore(data=None, *, engine=None, query=None):
    """The interactive explorer's page, for a notebook (``pbrdf-cl explore`` serves the same page).

    Parameters
    ----------
    data : str or path, optional
        A measurement CSV to load (its points drawn, fitted on demand).
    engine : pbrdf_cl.Engine, optional
        The device the page computes on (default: the chosen device).
    query : str, optional
        A URL query holding the page's state (as the page's address bar shows it).

    Returns
    -------
    panel.viewable.Viewable
        The page; display it in a notebook, or ``.servable()`` it.

    Raises
    ------
    pbrdf_cl.CommandError
        Without panel and bokeh (the ``explore`` extra), one line saying how to install them.

    Examples
    --------
    >>> page = pbrdf_cl.explore(data="examples/steel_435nm.csv")  # doctest: +SKIP
    """
    require_panel()  # one line naming the extra when panel is missing, before importing the page
    from .server import explore_app
    return explore_app(data, engine=engine, query=query)
