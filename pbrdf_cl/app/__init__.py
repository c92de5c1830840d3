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
