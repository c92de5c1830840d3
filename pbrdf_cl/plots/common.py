"""What every figure shares: the figure or axes a function draws into (the caller's, or a new one
that needs no backend), writing it only where a path is given, and the axis labels of the model's
inputs.

The package never chooses matplotlib's backend: a figure it makes itself is a plain
``matplotlib.figure.Figure`` (not one of pyplot's, so nothing to close, and no display needed:
``savefig`` writes PNG, PDF and SVG through matplotlib's own canvases), and a notebook's backend is
left as it is."""
from __future__ import annotations

from ..model import inputs

#: Axis labels with units of the model's inputs (the registry's, :data:`pbrdf_cl.model.inputs.LABELS`).
LABELS = inputs.LABELS


def figure(fig=None, **kw):
    """``fig`` (the caller's figure or subfigure, drawn into as it is), or a new
    ``matplotlib.figure.Figure(**kw)``: no pyplot, so no backend is chosen and nothing is left open."""
    if fig is not None:
        return fig
    from matplotlib.figure import Figure
    return Figure(**kw)


def axes(ax=None, **kw):
    """``ax`` (the caller's axes), or the one axes of a new :func:`figure` ``(**kw)``."""
    if ax is not None:
        return ax
    return figure(**kw).subplots()


def save(fig, path, **kw):
    """Write the whole figure ``fig`` belongs to (the top one, where ``fig`` is a subfigure) to
    ``path`` (its suffix says the format) with ``savefig(**kw)``; nothing where ``path`` is None."""
    if path is not None:
        fig.figure.savefig(path, **kw)


def width_inches(fig):
    """The width of ``fig`` in inches (of its own box, for a subfigure)."""
    if hasattr(fig, "get_figwidth"):
        return fig.get_figwidth()
    return fig.bbox.width / fig.figure.dpi
