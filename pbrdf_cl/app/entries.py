"""The explorer's number entries, checked on the server: :class:`NumberEntry` (a number entry with
arrows, under a label or beside one over a slider).  The browser sends every typed number as it is
(the entry has no bounds there, so nothing is clamped or dropped silently, an emptied entry
included); the server checks it against the field's range, takes it,
or refuses it in one line (``complain``) naming the field and the range, and puts the entry back to
the value in use.  The entries show numbers to six significant digits (``8.4e-07``, not
``0.00000``)."""
from __future__ import annotations

import math

import panel as pn
import param
from bokeh.models import CustomJSTickFormatter
from panel.io.resources import CDN_DIST

from .state import DIGITS, number_text


class LiveFloatSlider(pn.widgets.FloatSlider):
    """A slider whose moves reach the server at once (Panel waits 50 ms for more by default)."""
    _priority_changes = ["value"]


def significant():
    """The browser's formatter of an entry: six significant digits, as :func:`number_text`."""
    return CustomJSTickFormatter(code=f"return Number(Number(tick).toPrecision({DIGITS})).toString()")


def refusal(name, value, limits, current, units="", integer=False):
    """Why ``value`` (a number, or None for an emptied entry) is not a value of the field ``name``
    with the closed range ``limits``, in one line; None when it is."""
    lo, hi = limits
    span = f"[{number_text(lo)}, {number_text(hi)}]{f' ({units})' if units else ''}"
    kept = f"; it stays {number_text(current)}"
    if value is None:
        return f"{name} is empty: give a number in {span}{kept}"
    if not math.isfinite(value):
        return f"{name} = {value} is not a finite number: give one in {span}{kept}"
    if integer and value != int(value):
        return f"{name} = {number_text(value)} is not a whole number: give one in {span}{kept}"
    if not lo <= value <= hi:
        return f"{name} = {number_text(value)} is outside {span}{kept}"
    return None


class NumberEntry(pn.viewable.Viewer):
    """One number of the page: an entry (and optionally a slider over the same range).

    ``value`` is the value in use; the page watches it.  A value typed in the entry is checked
    (:func:`refusal`): a good one becomes the value (and moves the slider), a bad one is given to
    ``complain`` as one line and the entry returns to the value in use.  Setting ``value`` from
    Python moves the slider and the entry.

    Parameters
    ----------
    name : str
        The field's name in messages (``phi``, ``n``).
    label : str
        The label on the page.
    limits : tuple of float
        The closed range of the value (the slider's range).
    value : float
        The first value.
    complain : callable
        Called with the one line of a refused value.
    step : float, optional
        The slider's and the entry's arrows' step; with ``slider``.
    slider : bool
        A slider under the entry (the label beside the entry), else the entry alone (its label above).
    integer : bool
        Whole numbers only.
    units : str
        The units named in messages.
    width : int
        The width on the page.
    """

    value = param.Number(default=0.0)

    def __init__(self, name, label, limits, value, complain, *, step=None, slider=False, integer=False, units="",
                 width=260):
        super().__init__(value=value)
        self.field, self.limits, self.integer, self.units, self.complain = name, tuple(limits), integer, units, complain
        self._syncing = False
        kind = pn.widgets.IntInput if integer else pn.widgets.FloatInput
        options = dict(value=value, step=step or (1 if integer else 0.01))
        if not integer:
            options["format"] = significant()
        if slider:
            self.entry = kind(margin=0, align="end", width=width // 4, css_classes=["slider-edit"],
                              stylesheets=[f"{CDN_DIST}css/editable_slider.css"], **options)
            self.slider = LiveFloatSlider(start=limits[0], end=limits[1], step=step, value=value, show_value=False,
                                          margin=(0, 0, 5, 0), sizing_mode="stretch_width", tags=["composite"])
            self.slider.param.watch(self._slid, "value")
            label_text = pn.widgets.StaticText(value=f"{label}:", margin=(0, 10, 0, 0), align="end")
            self._layout = pn.Column(pn.Row(label_text, self.entry), self.slider, width=width, margin=(5, 10))
        else:
            self.entry = kind(label=label, width=width, **options)
            self.slider = None
            self._layout = self.entry
        self.entry.param.watch(self._typed, "value")
        self.param.watch(self._shown, "value")

    def __panel__(self):
        return self._layout

    def _slid(self, event):
        if not self._syncing:
            self.value = float(event.new)

    def _typed(self, event):
        if self._syncing:
            return
        typed = event.new
        problem = refusal(self.field, typed, self.limits, self.value, self.units, self.integer)
        if problem is None:
            self.value = int(typed) if self.integer else float(typed)
            return
        self.complain(problem)
        self._show_in_use()

    def _shown(self, event):
        self._show_in_use()

    def _show_in_use(self):
        """The entry and the slider back to (or on to) the value in use, without a new value."""
        self._syncing = True
        try:
            self.entry.value = int(self.value) if self.integer else self.value
            if self.slider is not None:
                self.slider.value = min(max(float(self.value), self.limits[0]), self.limits[1])
        finally:
            self._syncing = False
