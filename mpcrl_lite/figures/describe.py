r"""Figures in words: the text alternative of a figure, read from what it draws.

A screen reader, a page whose images do not load and a search all need words for a figure.
The words are on the figure already: its title (``suptitle``, which in this package carries
the key numbers, e.g. ``J = 1458.5 NOK/day``), its panels' titles or axis labels, their
legends (the series) and the data range of each panel. :func:`describe_figure` puts them in
one paragraph; :func:`plain_text` turns the figures' mathtext (``$\bar P$``, ``$\theta_s^1$``)
into the Unicode a reader shows (``P̄``, ``θ_s^1``).

The explorers (:mod:`mpcrl_lite.classroom.widgets`) set it as their picture's ``alt``; the
notebooks' kernels attach it to every figure they display (:mod:`mpcrl_lite.publish.alt_text`).
"""

from __future__ import annotations

import math
import re
import unicodedata
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["describe_figure", "plain_text"]

#: TeX commands of the figures' labels and the characters they stand for.
_SYMBOLS = {
    "alpha": "α", "beta": "β", "gamma": "γ", "delta": "δ", "Delta": "Δ", "epsilon": "ε",
    "eta": "η", "theta": "θ", "lambda": "λ", "mu": "μ", "nu": "ν", "pi": "π", "rho": "ρ",
    "sigma": "σ", "Sigma": "Σ", "tau": "τ", "phi": "φ", "varphi": "φ", "omega": "ω",
    "nabla": "∇", "pm": "±", "times": "×", "cdot": "·", "le": "≤", "leq": "≤", "ge": "≥",
    "geq": "≥", "approx": "≈", "infty": "∞", "star": "*", "to": "→", "rightarrow": "→",
    "sum": "Σ", "ell": "ℓ",
}
#: Accents: a combining character after the letter.
_ACCENTS = {"bar": "\u0304", "overline": "\u0304", "hat": "\u0302", "tilde": "\u0303"}


def plain_text(text: str) -> str:
    r"""One line of plain text from a label with mathtext: ``$\bar P$`` -> ``P̄``,
    ``$\phi_b$`` -> ``φ_b``, ``\mathrm{x}`` -> ``x``; dollars and braces dropped, white space
    collapsed."""

    def accent(match: re.Match) -> str:
        return match.group(2) + _ACCENTS[match.group(1)]

    text = re.sub(r"\\(?:mathrm|mathit|mathbf|text|operatorname)\s*\{([^{}]*)\}", r"\1", text)
    text = re.sub(r"\\([A-Za-z]+)", lambda m: _SYMBOLS.get(m.group(1), m.group(0)), text)
    text = re.sub(r"\\(bar|overline|hat|tilde)\s*\{?\s*([^\s\\{}])\s*\}?", accent, text)
    text = re.sub(r"\\([A-Za-z]+)", r"\1", text)
    text = text.replace("$", "").replace("{", "").replace("}", "").replace("\\", "")
    return unicodedata.normalize("NFC", " ".join(text.split()))


def _number(x: float) -> str:
    if x == 0 or not math.isfinite(x):
        return f"{x:g}"
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}"


def _data_range(ax) -> str:
    """``'from a to b'`` over the finite y data of the panel's lines and points, or ''."""
    values = []
    for line in ax.get_lines():
        if not line.get_visible():
            continue
        y = np.asarray(line.get_ydata(), dtype=float).ravel()
        values.append(y[np.isfinite(y)])
    for collection in ax.collections:
        offsets = np.asarray(collection.get_offsets(), dtype=float)
        if offsets.ndim == 2 and offsets.shape[1] == 2 and offsets.size:
            y = offsets[:, 1]
            values.append(y[np.isfinite(y)])
    data = np.concatenate(values) if values else np.empty(0)
    if data.size == 0:
        return ""
    low, high = float(data.min()), float(data.max())
    if math.isclose(low, high):
        return f"at {_number(low)}"
    return f"from {_number(low)} to {_number(high)}"


def _series(ax) -> list[str]:
    legend = ax.get_legend()
    return [plain_text(t.get_text()) for t in legend.get_texts()] if legend else []


def describe_figure(fig: Figure, ranges: bool = True) -> str:
    """What ``fig`` shows, in words: its title, then per panel its title (or its y label
    against its x label), its series (the legend) and, if ``ranges``, the range of its data.

    A figure with no words at all is described by its number of panels, so the result is
    never empty.
    """
    suptitle = getattr(fig, "_suptitle", None)
    title = plain_text(suptitle.get_text()) if suptitle is not None else ""
    panels: list[str] = []
    figure_series = [plain_text(t.get_text()) for legend in fig.legends
                     for t in legend.get_texts()]
    for ax in fig.get_axes():
        if not ax.get_visible() or ax.get_label() == "<colorbar>":
            continue
        words = [plain_text(ax.get_title(loc)) for loc in ("left", "center", "right")]
        name = "; ".join(w for w in words if w)
        ylabel, xlabel = plain_text(ax.get_ylabel()), plain_text(ax.get_xlabel())
        if not name:
            name = f"{ylabel} against {xlabel}" if ylabel and xlabel else ylabel or xlabel
        elif ylabel and name.lower() in ylabel.lower():
            name = f"{ylabel} against {xlabel}" if xlabel else ylabel
        elif ylabel and ylabel.lower() not in name.lower():
            name = f"{name}, {ylabel} against {xlabel}" if xlabel else f"{name}, {ylabel}"
        if not name:
            continue
        extra = []
        series = _series(ax)
        if series:
            extra.append("series " + ", ".join(series))
        span = _data_range(ax) if ranges else ""
        if span:
            extra.append(f"values {span}")
        text = f"{name} ({'; '.join(extra)})" if extra else name
        if text not in panels:
            panels.append(text)
    tail = f" Series: {', '.join(figure_series)}." if figure_series else ""
    joined = ("; " if any(p.endswith(")") for p in panels) else ", ").join(panels)
    if title and panels:
        return f"Figure: {title}. Panels: {joined}.{tail}"
    if title:
        return f"Figure: {title}.{tail}"
    if panels:
        return f"Figure: {joined}.{tail}"
    count = len(fig.get_axes())
    return f"Figure with {count} untitled panel{'s' if count != 1 else ''}.{tail}"
