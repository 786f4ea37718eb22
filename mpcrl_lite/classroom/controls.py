r"""Labelled, accessible controls for the explorers of :mod:`mpcrl_lite.classroom.widgets`.

The sliders of ipywidgets 8 give their handle no accessible name (a screen reader announces
"slider 18"), and an ipywidgets label whose ``tooltip`` is not set carries ``title="null"``.
The controls made here avoid both:

* :class:`StepSlider` is a slider over an ordered list of values, drawn as a native
  ``<input type="range">`` (through :mod:`anywidget`) with a visible ``<label for=...>``, an
  ``aria-label``, an ``aria-valuetext`` that reads the shown value, and a tooltip. It sends
  its value when released (or per key press), never while dragged, unless
  ``continuous_update`` is set; values increase from left to right. The keys that move it
  (arrows, Home, End, Page Up/Down) stay with it: the notebook's shortcuts never see them;
* drop-downs and number boxes are the ipywidgets ones, whose views tie the label to the
  input (``<label for=...>``), with their tooltip always set.

Every control returned here has :func:`accessible_name` non-empty and ``tooltip`` set. Nothing
needs a kernel to build or drive them: setting ``control.value`` from code runs the same
observers as using it in a notebook.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import anywidget
import ipywidgets as widgets
import traitlets

__all__ = [
    "IntStepSlider",
    "StepSlider",
    "accessible_name",
    "choice_slider",
    "day_slider",
    "dropdown",
    "float_slider",
    "int_box",
    "int_slider",
    "log_slider",
]

#: The view of :class:`StepSlider`: a labelled native range input and a readout.
_ESM = """
function render({ model, el }) {
  const id = `mpcrl-step-slider-${Math.random().toString(36).slice(2)}`;
  const label = document.createElement("label");
  const input = document.createElement("input");
  const readout = document.createElement("output");
  label.htmlFor = id;
  input.id = id;
  input.type = "range";
  input.min = "0";
  input.step = "1";
  readout.htmlFor = id;
  readout.setAttribute("aria-hidden", "true");  // the slider itself reads its value
  el.classList.add("mpcrl-step-slider");
  // The keys that move a range input belong to it, not to the notebook around it. JupyterLab
  // and Notebook 7 (Lumino) match no shortcut on a key whose target is marked so -- Notebook 7
  // reads keys in the capture phase, before the input -- and the moving keys stop here for
  // hosts that listen to the bubbling key (the arrows select cells in command mode).
  input.setAttribute("data-lm-suppress-shortcuts", "true");
  const MOVING = new Set(["ArrowLeft", "ArrowRight", "ArrowUp", "ArrowDown", "Home", "End",
                          "PageUp", "PageDown"]);
  input.addEventListener("keydown", (event) => {
    if (MOVING.has(event.key)) event.stopPropagation();
  });
  el.append(label, input, readout);

  const index = () => {
    const options = model.get("options");
    const value = model.get("value");
    let best = 0;
    options.forEach((o, i) => {
      if (Math.abs(o - value) < Math.abs(options[best] - value)) best = i;
    });
    return best;
  };
  const show = (i) => {
    const text = model.get("labels")[i] ?? String(model.get("options")[i]);
    readout.textContent = text;
    input.setAttribute("aria-valuetext", text);
  };
  const sync = () => {
    label.textContent = model.get("description");
    input.setAttribute("aria-label", model.get("aria_label") || model.get("description"));
    const tip = model.get("tooltip");
    for (const node of [label, input]) {
      if (tip) node.title = tip; else node.removeAttribute("title");
    }
    input.max = String(model.get("options").length - 1);
    input.disabled = model.get("disabled");
    input.value = String(index());
    show(index());
  };
  const commit = () => {
    model.set("value", model.get("options")[Number(input.value)]);
    model.save_changes();
  };
  input.addEventListener("input", () => {
    show(Number(input.value));
    if (model.get("continuous_update")) commit();
  });
  input.addEventListener("change", commit);
  model.on("change", sync);
  sync();
  return () => model.off("change", sync);
}
export default { render };
"""

_CSS = """
.mpcrl-step-slider { display: flex; align-items: center; gap: 0.5em; margin: 2px 1em 2px 0;
  font-size: var(--jp-widgets-font-size, 13px); color: var(--jp-widgets-label-color, inherit); }
.mpcrl-step-slider label { min-width: 10em; text-align: right; }
.mpcrl-step-slider input { width: 10em; }
.mpcrl-step-slider output { min-width: 3.5em; font-variant-numeric: tabular-nums; }
"""


class StepSlider(anywidget.AnyWidget):
    """A slider over ``options`` (numbers, increasing from left to right) with an accessible
    name; ``value`` is always one of the options.

    Attributes (synchronized with the view)
    ----------------------------------------
    value : float
        The chosen option.
    options : list of float
        The values the slider can take, strictly increasing.
    labels : list of str
        What the readout shows (and a screen reader reads) for each option.
    description : str
        The visible label.
    aria_label : str
        The name announced by a screen reader (default: ``description``).
    tooltip : str
        Shown on hover over the label and the slider (default: ``description``).
    continuous_update : bool, default False
        Send the value while dragging, not only on release.
    disabled : bool
    """

    _esm = _ESM
    _css = _CSS
    _kind: type = float
    value = traitlets.Float().tag(sync=True)
    options = traitlets.List(traitlets.Float(), minlen=1).tag(sync=True)
    labels = traitlets.List(traitlets.Unicode()).tag(sync=True)
    description = traitlets.Unicode("").tag(sync=True)
    aria_label = traitlets.Unicode("").tag(sync=True)
    continuous_update = traitlets.Bool(False).tag(sync=True)
    disabled = traitlets.Bool(False).tag(sync=True)

    def __init__(self, options: Sequence[float], value: float, labels: Sequence[str],
                 description: str, aria_label: str = "", tooltip: str = "",
                 **kwargs: Any) -> None:
        options = [self._kind(o) for o in options]
        if not options or any(b <= a for a, b in itertools.pairwise(options)):
            raise ValueError(f"options={options!r}: expected a non-empty increasing list")
        if len(labels) != len(options):
            raise ValueError(f"labels: expected {len(options)} (one per option), "
                             f"got {len(labels)}")
        super().__init__(options=options, labels=list(labels), description=description,
                         aria_label=aria_label or description, tooltip=tooltip or description,
                         value=_option(options, value, description), **kwargs)

    @traitlets.validate("value")
    def _check_value(self, proposal: dict) -> float:
        return _option(self.options, proposal["value"], self.description or "value")

    @property
    def index(self) -> int:
        """Position of ``value`` in ``options`` (0 = leftmost)."""
        return self.options.index(self.value)


class IntStepSlider(StepSlider):
    """A :class:`StepSlider` over integers (``value`` and ``options`` are ints)."""

    _kind = int
    value = traitlets.Int().tag(sync=True)
    options = traitlets.List(traitlets.Int(), minlen=1).tag(sync=True)


def _option(options: Sequence[float], value: Any, name: str) -> Any:
    """The option equal to ``value`` (to round-off), else a ValueError naming both."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r}: expected a number") from None
    best = min(options, key=lambda o: abs(o - x))
    if not math.isclose(best, x, rel_tol=1e-9, abs_tol=1e-12):
        shown = ", ".join(f"{o:g}" for o in options[:6]) + (", ..." if len(options) > 6 else "")
        raise ValueError(f"{name}={value!r}: expected one of the slider's values {shown} "
                         f"(from {options[0]:g} to {options[-1]:g})")
    return best


def accessible_name(control: widgets.Widget) -> str:
    """The name a screen reader announces for ``control``: the ``aria_label`` of a
    :class:`StepSlider`, the description (tied to the input by ``<label for>``) otherwise."""
    return str(getattr(control, "aria_label", "") or getattr(control, "description", "") or "")


def float_slider(description: str, value: float, low: float, high: float, step: float,
                 fmt: str = ".2f", aria_label: str = "", tooltip: str = "") -> StepSlider:
    """A slider over ``low, low + step, ..., high`` (rounded to 10 decimals)."""
    count = round((high - low) / step) + 1
    options = [round(low + k * step, 10) for k in range(count)]
    return StepSlider(options, value, [format(x, fmt) for x in options], description,
                      aria_label, tooltip)


def int_slider(description: str, value: int, low: int, high: int, aria_label: str = "",
               tooltip: str = "", labels: Sequence[str] | None = None) -> IntStepSlider:
    """A slider over the integers ``low .. high``; ``value`` is an int. ``labels`` (one per
    integer) default to the numbers."""
    options = list(range(int(low), int(high) + 1))
    shown = [str(k) for k in options] if labels is None else list(labels)
    return IntStepSlider(options, value, shown, description, aria_label, tooltip)


def day_slider(value: int, days: int, tooltip: str = "") -> IntStepSlider:
    """The day of a month of ``days`` days: ``value`` is the day index (``0 .. days - 1``, as
    everywhere in the package), the slider shows and reads days from 1 ("8 of 30")."""
    options = list(range(int(days)))
    labels = [f"{d + 1} of {days}" for d in options]
    return IntStepSlider(options, value, labels, "day", "day of the month",
                         tooltip or "Day of the month, counted from 1")


def log_slider(description: str, value: float, values: Sequence[float], aria_label: str = "",
               tooltip: str = "") -> StepSlider:
    """A slider over ``values`` (e.g. powers of ten) in increasing order, equally spaced on
    the slider; ``value`` is added to them if it is not one of them."""
    options = sorted({float(v) for v in values} | {float(value)})
    return StepSlider(options, value, [f"{v:.0e}" for v in options], description, aria_label,
                      tooltip)


def choice_slider(description: str, value: float, values: Sequence[float],
                  aria_label: str = "", tooltip: str = "", fmt: str = "g") -> StepSlider:
    """A slider over the given ``values`` in increasing order (``value`` added if missing)."""
    options = sorted({float(v) for v in values} | {float(value)})
    return StepSlider(options, value, [format(v, fmt) for v in options], description,
                      aria_label, tooltip)


def dropdown(description: str, options: Sequence[str], value: str,
             tooltip: str) -> widgets.Dropdown:
    """A drop-down whose label names it and whose tooltip is set (no ``title="null"``)."""
    return widgets.Dropdown(options=list(options), value=value, description=description,
                            tooltip=tooltip, style={"description_width": "initial"})


def int_box(description: str, value: int, low: int, high: int,
            tooltip: str) -> widgets.BoundedIntText:
    """A number box for an integer in ``[low, high]``, sent on Enter or when left."""
    return widgets.BoundedIntText(value=value, min=low, max=high, description=description,
                                  tooltip=tooltip, continuous_update=False,
                                  style={"description_width": "initial"},
                                  layout=widgets.Layout(width="16em"))
