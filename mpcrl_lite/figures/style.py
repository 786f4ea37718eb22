r"""Conventions and small drawing helpers shared by every figure of :mod:`mpcrl_lite.figures.plots`.

Conventions (those of the paper's figures):

* the first month of learning is **red** (:data:`FIRST_COLOR`), the last month **blue**
  (:data:`LAST_COLOR`); agents have their own colours (:data:`AGENT_COLORS`), never red or
  blue;
* reference lines are dashed: the grid limit ``P_bar`` in black, the soc band
  ``soc_low = 0.1`` / ``soc_high = 0.9`` in grey (the penalised zones outside it are shaded),
  the physical range ``[0, 1]`` as thin solid grey lines; the bounds ``+-U_bar`` of net power
  are dotted grey;
* units: prices in NOK/MWh, powers in MW (net power ``b - s`` is positive when buying), soc
  dimensionless, time in hours, the daily closed-loop cost ``J`` in NOK/day
  (:data:`COST_UNIT`);
* legends that would cover data are drawn beside the axes (:func:`legend_beside`), and
  panels with a reference limit leave room above it (:func:`headroom`);
* every data line and reference line carries a ``gid`` (for example ``"J"``, ``"P_bar"``,
  ``"soc_low"``), so that notebooks and tests find it with :func:`find_lines`.

Nothing here creates data; the helpers draw reference lines and axes decorations.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from .._util.lazy import lazy_module
from .._util.validate import check_int
from ..config import PRICE_UNIT, SystemConfig

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.legend import Legend
    from matplotlib.lines import Line2D

#: matplotlib, imported when a figure is first drawn (a run without figures never
#: loads it)
plt = lazy_module("matplotlib.pyplot")
_figure = lazy_module("matplotlib.figure")
_axes = lazy_module("matplotlib.axes")
_ticker = lazy_module("matplotlib.ticker")

__all__ = [
    "AGENT_COLORS",
    "COST_UNIT",
    "CURRENCY",
    "FIRST_COLOR",
    "LAST_COLOR",
    "MIN_POINTS_FOR_A_LINE",
    "agent_color",
    "axes_or_new",
    "day_axis",
    "find_lines",
    "headroom",
    "legend_beside",
    "p_bar_line",
    "select_days",
    "soc_reference",
    "steps",
    "u_bar_lines",
]

#: Colour of the first month of learning (the paper's red).
FIRST_COLOR = "#d62728"
#: Colour of the last month of learning (the paper's blue).
LAST_COLOR = "#1f77b4"
#: Colours of agents 1, 2, ... (cycled); red and blue are kept for first / last month.
AGENT_COLORS: tuple[str, ...] = (
    "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f",
)
#: The currency of prices and costs.
CURRENCY = PRICE_UNIT.split("/")[0]
#: Unit of a daily closed-loop cost ``J = mean_days sum_k gamma^k L~_k`` (one day = one
#: episode), used for every daily cost in figures and explorers.
COST_UNIT = f"{CURRENCY}/day"
#: Grey of reference lines and of the shaded penalised soc zones.
REF_GREY = "0.45"
ZONE_GREY = "0.92"
#: Days drawn when a figure is not told which.
DEFAULT_DAYS = 5
#: A series with fewer points than this is drawn as points, without a line between them: a
#: line through two evaluations draws a trend nobody measured.
MIN_POINTS_FOR_A_LINE = 3
#: Fraction of the axes height kept free above the highest line of a limited quantity.
HEADROOM = 0.25


def agent_color(i: int) -> str:
    """Colour of agent ``i`` (0-based), cycling through :data:`AGENT_COLORS`."""
    return AGENT_COLORS[i % len(AGENT_COLORS)]


def find_lines(fig_or_ax: Figure | Axes, gid: str) -> list[Line2D]:
    """All lines whose ``gid`` is ``gid``, in every axes of a figure (or in one axes)."""
    axes = fig_or_ax.axes if isinstance(fig_or_ax, _figure.Figure) else [fig_or_ax]
    return [line for ax in axes for line in ax.get_lines() if line.get_gid() == gid]


def _root_figure(ax: Axes) -> Figure:
    fig = ax.figure
    while not isinstance(fig, _figure.Figure):  # axes of a SubFigure
        fig = fig.figure
    return fig


def axes_or_new(
    axes: Sequence[Axes] | Axes | None, shape: tuple[int, int], figsize: tuple[float, float],
    name: str, fig: Figure | None = None, **kwargs,
) -> tuple[Figure, list[Axes]]:
    """The given axes (checked for their number), new axes in ``fig`` (cleared first, with
    constrained layout), or a new pyplot figure with ``shape`` subplots.

    ``kwargs`` go to ``subplots`` (``sharex``, ``gridspec_kw``, ...).
    """
    count = shape[0] * shape[1]
    if axes is not None and fig is not None:
        raise ValueError(f"{name} and fig: expected one of them, not both")
    if fig is not None:
        if not isinstance(fig, _figure.Figure):
            raise ValueError(f"fig: expected a matplotlib Figure, got {type(fig).__name__}")
        fig.clear()
        fig.set_layout_engine("constrained")
        grid = fig.subplots(*shape, squeeze=False, **kwargs)
        return fig, list(grid.ravel())
    if axes is None:
        new, grid = plt.subplots(
            *shape, figsize=figsize, squeeze=False, layout="constrained", **kwargs
        )
        return new, list(grid.ravel())
    given = [axes] if isinstance(axes, _axes.Axes) else list(np.ravel(np.asarray(axes, dtype=object)))
    if len(given) != count or not all(isinstance(a, _axes.Axes) for a in given):
        raise ValueError(f"{name}: expected {count} matplotlib Axes, got {len(given)} object(s)")
    return _root_figure(given[0]), given


def select_days(days: int | Sequence[int] | None, available: int) -> list[int]:
    """Day indices from ``None`` (the first five, or fewer), a count, or explicit indices."""
    if days is None:
        return list(range(min(DEFAULT_DAYS, available)))
    if isinstance(days, numbers.Integral) and not isinstance(days, bool):
        count = check_int("days", days, 1, available)
        return list(range(count))
    if isinstance(days, (str, bytes)) or not isinstance(days, Sequence) or len(days) == 0:
        raise ValueError(
            f"days={days!r}: expected a number of days or a non-empty sequence of day indices"
        )
    return [check_int("day", d, 0, available - 1) for d in days]


def steps(values: np.ndarray) -> np.ndarray:
    """Piecewise-constant hourly values for ``drawstyle='steps-post'``: the last value is
    repeated so that the last hour is drawn over its full width."""
    values = np.asarray(values, dtype=float)
    return np.append(values, values[-1:])


def soc_reference(ax: Axes, system: SystemConfig, label: bool = True) -> None:
    """The soc band (dashed), the penalised zones (shaded) and ``[0, 1]`` (thin solid)."""
    lo, hi = system.soc_low, system.soc_high
    ax.axhspan(0.0, lo, color=ZONE_GREY, zorder=0, lw=0)
    ax.axhspan(hi, 1.0, color=ZONE_GREY, zorder=0, lw=0)
    ax.axhline(lo, color=REF_GREY, ls="--", lw=1.0, gid="soc_low",
               label=f"band {lo:g} / {hi:g}" if label else None)
    ax.axhline(hi, color=REF_GREY, ls="--", lw=1.0, gid="soc_high")
    ax.axhline(0.0, color=REF_GREY, ls="-", lw=0.6, gid="soc_min")
    ax.axhline(1.0, color=REF_GREY, ls="-", lw=0.6, gid="soc_max")
    ax.set_ylim(-0.04, 1.04)
    ax.yaxis.set_major_locator(_ticker.MultipleLocator(0.2))


def p_bar_line(ax: Axes, P_bar: float, lw: float = 1.3) -> None:
    """The grid limit ``P_bar``, dashed black, drawn above the data (the grid power often
    sits exactly at the limit: draw a series that may sit there wider than ``lw``, so that
    it shows on both sides of the dashes)."""
    ax.axhline(P_bar, color="black", ls="--", lw=lw, gid="P_bar", zorder=4,
               label=rf"$\bar P$ = {P_bar:g} MW")


def u_bar_lines(ax: Axes, U_bar: float, zero: bool = True) -> None:
    """The bounds ``+-U_bar`` of a battery's net power (dotted grey) and, with ``zero``, a
    faint line at 0 (buying above it, selling below)."""
    for lim in (U_bar, -U_bar):
        ax.axhline(lim, color=REF_GREY, ls=":", lw=1.0, gid="U_bar")
    if zero:
        ax.axhline(0.0, color="0.75", lw=0.6)


def headroom(ax: Axes, *levels: float, bottom: float = 0.0) -> None:
    """y-limits from ``bottom`` to the highest of ``levels`` plus :data:`HEADROOM` of the
    range, so that no line runs along the top edge of the axes."""
    top = max(float(np.max(level)) for level in levels)
    ax.set_ylim(bottom, top + HEADROOM * max(top - bottom, 1e-9))


def legend_beside(ax: Axes, **kwargs) -> Legend:
    """The legend of ``ax`` to the right of the axes, outside them, so it never covers data
    (constrained layout makes room for it)."""
    options = {"fontsize": 8, "loc": "upper left", "bbox_to_anchor": (1.01, 1.0),
               "frameon": False, "borderaxespad": 0.0, **kwargs}
    return ax.legend(**options)


def day_axis(ax: Axes, n_days: int, hours: int, labels: Sequence[int] | None = None) -> None:
    """Hour ticks and faint day separators for a time axis of ``n_days`` concatenated days;
    ``labels`` are day indices, written above the axes counted from 1."""
    total = n_days * hours
    ax.set_xlim(0, total)
    if n_days == 1:
        ax.xaxis.set_major_locator(_ticker.MultipleLocator(max(1, hours // 8)))
    else:
        ax.xaxis.set_major_locator(_ticker.MultipleLocator(hours))
        ax.xaxis.set_minor_locator(_ticker.MultipleLocator(max(1, hours // 4)))
        for j in range(1, n_days):
            ax.axvline(j * hours, color="0.8", lw=0.8, zorder=0)
    if labels is not None:
        for j, d in enumerate(labels):
            ax.text((j + 0.5) * hours, 1.0, f"day {d + 1}", transform=ax.get_xaxis_transform(),
                    ha="center", va="bottom", fontsize=8, color="0.35")
