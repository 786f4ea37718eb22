r"""Figures drawn from data only: a :class:`~mpcrl_lite.learning.history.History`, a
:class:`~mpcrl_lite.sim.record.Record` (e.g. a :class:`~mpcrl_lite.learning.history.MonthRecord`),
:class:`~mpcrl_lite.system.prices.Prices`, an MPC :class:`~mpcrl_lite.mpc.formulation.Plan`, or the dicts of
:mod:`mpcrl_lite.classroom.explorers`.

Every function takes an optional ``ax`` (or ``axes``) to draw into, or ``fig`` (a figure to
clear and fill, as the explorers of :mod:`mpcrl_lite.classroom.widgets` do), otherwise it creates a
figure; it returns the :class:`matplotlib.figure.Figure`. Nothing here simulates, learns or
calls ``plt.show()``; the only computations are simple aggregations (a rolling mean, a
concatenation of days, finite differences on a drawn curve).

The conventions shared by all figures (colours, reference lines, units, legends beside the
axes, line ``gid`` s for :func:`find_lines`) are listed in :mod:`mpcrl_lite.figures.style`.

=========================================  ==================================================
function                                   figure
=========================================  ==================================================
:func:`plot_day`                           one day in closed loop (``simulate`` command,
                                           notebooks, day and rule explorers)
:func:`plot_price_window`                  the prices of a day and the MPC's forecast window
:func:`plot_plan`                          one MPC solution over its horizon
:func:`plot_policy_curve`                  the policy against one input (tau explorer)
:func:`plot_value_fit`                     LSTD values against Monte-Carlo returns
:func:`fig1_trajectories` .. :func:`fig7_theta`, :func:`save_paper_figures`
                                           the paper's Figs. 1-7 (:mod:`mpcrl_lite.figures.paper`)
=========================================  ==================================================

The older figure-first names ``draw_day``, ``draw_prices``, ``draw_plan``,
``draw_policy_curve`` and ``draw_value_fit`` call the functions above.

In a notebook, assign the result (``fig = fig2_performance(history)``) or end the line
with ``;``: a returned figure is otherwise displayed twice.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .._util.validate import check_int
from ..config import HOURS_PER_DAY, PRICE_UNIT, SystemConfig
from ..mpc.formulation import Plan
from ..sim.record import Record
from ..system.prices import Prices, sell_prices
from .style import (
    FIRST_COLOR,
    LAST_COLOR,
    REF_GREY,
    agent_color,
    axes_or_new,
    day_axis,
    headroom,
    legend_beside,
    p_bar_line,
    soc_reference,
    steps,
    u_bar_lines,
)

__all__ = ["draw_day", "draw_plan", "draw_policy_curve", "draw_prices", "draw_value_fit", "plot_day", "plot_plan", "plot_policy_curve", "plot_price_window", "plot_value_fit"]

_GRID = {"color": "0.9", "lw": 0.6}


# ----------------------------------------------------------------------------------------------
# One day in closed loop
# ----------------------------------------------------------------------------------------------
def plot_day(
    record: Record,
    day: int = 0,
    prices: Prices | None = None,
    axes: Sequence[Axes] | None = None,
    *,
    fig: Figure | None = None,
    title: str | None = None,
    planned: bool = True,
) -> Figure:
    """One day in closed loop: soc, actions, grid power and prices.

    Four panels sharing the hour axis:

    1. ``soc^i_k`` per agent (``k = 0 .. H``) with the band ``[0.1, 0.9]`` and ``[0, 1]``;
    2. net power per agent: the policy ``pi^i(s_k)`` (dashed) and the applied
       ``b^i_k - s^i_k`` after the low-level controller (solid), with ``+-U_bar``;
    3. grid power ``P_k = max(sum_i b^i_k, sum_i s^i_k)`` against ``P_bar`` and, with
       ``planned``, the largest grid power the MPC planned over its horizon (dotted);
    4. buying and selling prices ``phi_b``, ``phi_s`` of the hour.

    Hourly quantities are drawn as steps over ``[k, k+1)``. Legends stand beside the panels,
    and the grid panel leaves room above ``P_bar`` and the data.

    Parameters
    ----------
    record : Record
        A simulated period (e.g. from :func:`mpcrl_lite.sim.closed_loop.run_month` or
        :func:`mpcrl_lite.classroom.explorers.simulate_day`), arrays ``(H, D, n)``.
    day : int, default 0
        Index of the day in the record, in ``[0, D)``.
    prices : Prices, optional
        Prices to draw; by default the buying prices stored in ``record.buy`` and
        ``sell_ratio * buy``.
    axes : sequence of 4 Axes, optional
        Where to draw; by default a new figure.
    fig : Figure, optional
        A figure to clear and draw into instead (not with ``axes``).
    title : str, optional
        Title of the top panel; default ``"Day d of D: closed loop"`` (days from 1).
    planned : bool, default True
        Draw ``record.planned_power`` (meaningful for an MPC; for another policy it is the
        grid power of its command).

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        If ``day`` is out of range, ``prices`` has fewer days, or ``axes`` has not 4 Axes.

    Notes
    -----
    Line gids: ``"soc[i]"``, ``"policy[i]"``, ``"net_power[i]"`` (agents counted from 1),
    ``"grid_power"``, ``"planned_power"``, ``"buy"``, ``"sell"``, and the references
    ``"soc_low"``, ``"soc_high"``, ``"soc_min"``, ``"soc_max"``, ``"U_bar"``, ``"P_bar"``.
    """
    system = record.system
    H, D, n = record.policy.shape
    day = check_int("day", day, 0, D - 1)
    if prices is not None:
        if day >= prices.days:
            raise ValueError(f"day={day}: prices have only {prices.days} day(s)")
        buy, sell, unit = prices.buy[day], prices.sell[day], prices.unit
    else:
        buy = record.buy[:, day]
        sell, unit = sell_prices(buy, system.sell_ratio), PRICE_UNIT
    fig, (ax_soc, ax_a, ax_p, ax_price) = axes_or_new(
        axes, (4, 1), (8.5, 9.5), "axes", fig=fig, sharex=True,
        gridspec_kw={"height_ratios": [1.25, 1.25, 0.9, 0.9]},
    )
    hours = np.arange(H + 1)

    soc_reference(ax_soc, system)
    for i in range(n):
        ax_soc.plot(hours, record.soc[:, day, i], color=agent_color(i), lw=1.8, marker="o",
                    ms=2.5, gid=f"soc[{i + 1}]", label=f"agent {i + 1}")
    ax_soc.set_ylabel("soc (–)")
    ax_soc.set_title(f"Day {day + 1} of {D}: closed loop" if title is None else title,
                     loc="left", fontsize=11)
    legend_beside(ax_soc)

    u_bar_lines(ax_a, max(system.battery("U_bar")))
    for i in range(n):
        c = agent_color(i)
        ax_a.plot(hours, steps(record.policy[:, day, i]), drawstyle="steps-post", color=c,
                  ls="--", lw=1.1, alpha=0.9, gid=f"policy[{i + 1}]")
        ax_a.plot(hours, steps(record.b[:, day, i] - record.s[:, day, i]),
                  drawstyle="steps-post", color=c, lw=1.8, gid=f"net_power[{i + 1}]")
    ax_a.set_ylabel("net power b − s (MW)")
    # one entry per line style (the colours are the agents of the panel above)
    legend_beside(ax_a, handles=[
        Line2D([], [], color="0.3", ls="--", lw=1.1, label=r"policy $\pi^i(s)$"),
        Line2D([], [], color="0.3", lw=1.8, label="applied b − s\n(after low-level control)"),
        Line2D([], [], color=REF_GREY, ls=":", lw=1.0, label=r"$\pm\bar U$"),
    ], loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax_a.text(1.005, 1.0, "buy", transform=ax_a.transAxes, fontsize=8, va="top", color="0.35")
    ax_a.text(1.005, 0.0, "sell", transform=ax_a.transAxes, fontsize=8, va="bottom", color="0.35")

    p_bar_line(ax_p, system.P_bar)
    applied = record.grid_power[:, day]
    ax_p.plot(hours, steps(applied), drawstyle="steps-post", color="0.45", lw=2.0,
              gid="grid_power", label=r"applied $P_k$")
    levels = [system.P_bar, applied.max()]
    if planned:
        plan = record.planned_power[:, day]
        ax_p.plot(hours, steps(plan), drawstyle="steps-post", color=LAST_COLOR, ls=":", lw=1.8,
                  gid="planned_power", label="planned by the MPC\n(max over horizon)")
        levels.append(plan.max())
    headroom(ax_p, *levels)
    ax_p.set_ylabel("grid power (MW)")
    legend_beside(ax_p)

    ax_price.plot(hours, steps(buy), drawstyle="steps-post", color="0.15", lw=1.6, gid="buy",
                  label=r"buy $\phi_b$")
    ax_price.plot(hours, steps(sell), drawstyle="steps-post", color="0.15", lw=1.2, ls="--",
                  gid="sell", label=r"sell $\phi_s$")
    ax_price.set_ylabel(f"price ({unit})")
    ax_price.set_xlabel("hour of day (h)")
    legend_beside(ax_price)
    day_axis(ax_price, 1, H)

    for ax in (ax_soc, ax_a, ax_p, ax_price):
        ax.grid(True, axis="x", **_GRID)
    if axes is None:
        fig.align_ylabels()
    return fig


# ----------------------------------------------------------------------------------------------
# Prices, one MPC solution, one policy curve, one value fit
# ----------------------------------------------------------------------------------------------
def plot_price_window(
    prices: Prices, day: int, hour: int, N: int, ax: Axes | None = None, *,
    fig: Figure | None = None,
) -> Figure:
    """The buying and selling prices of ``day`` and the next day, with the window of ``N``
    hours that the MPC forecasts from ``hour`` shaded (it reads on past midnight).

    Line gids: ``"buy"``, ``"sell"``; the shaded window is the patch ``"window"``.
    """
    day = check_int("day", day, 0, prices.days - 1)
    hour = check_int("hour", hour, 0, HOURS_PER_DAY - 1)
    N = check_int("N", N, 1, HOURS_PER_DAY)
    fig, (ax,) = axes_or_new(ax, (1, 1), (8.0, 3.4), "ax", fig=fig)
    nxt = (day + 1) % prices.days
    two = np.concatenate([prices.buy[day], prices.buy[nxt]])
    t = np.arange(2 * HOURS_PER_DAY + 1)
    ax.plot(t, steps(two), drawstyle="steps-post", color="0.15", lw=1.6, gid="buy",
            label=r"buy $\phi_b$")
    ax.plot(t, steps(sell_prices(two, prices.sell_ratio)), drawstyle="steps-post", color="0.15", lw=1.1,
            ls="--", gid="sell", label=r"sell $\phi_s$")
    ax.axvspan(hour, hour + N, color=LAST_COLOR, alpha=0.15, lw=0, gid="window",
               label=f"MPC window\nat {hour:02d}:00, N = {N} h")
    ax.axvline(HOURS_PER_DAY, color="0.6", lw=0.8)
    for x, text in ((0.5, f"day {day + 1}"), (1.5, f"day {nxt + 1} (next)")):
        ax.text(x * HOURS_PER_DAY, 1.0, text, transform=ax.get_xaxis_transform(),
                ha="center", va="bottom", fontsize=9)
    ax.set_xlim(0, 2 * HOURS_PER_DAY)
    ax.set_xticks(range(0, 2 * HOURS_PER_DAY + 1, 6))
    ax.set_xlabel("hour counted from the day's midnight (h)")
    ax.set_ylabel(f"price ({prices.unit})")
    legend_beside(ax)
    ax.grid(True, **_GRID)
    return fig


def plot_plan(
    plan: Plan, system: SystemConfig, buy: np.ndarray | None = None, title: str = "",
    axes: Sequence[Axes] | None = None, *, fig: Figure | None = None,
) -> Figure:
    """One MPC solution over its horizon: predicted soc, planned net power per agent, the
    grid sums ``sum_i b_j`` and ``sum_i s_j`` against ``P_bar``, and (with ``buy``, shape
    ``(N,)``) the buying price of each stage in a fourth panel.

    Line gids: ``"soc[i]"``, ``"net_power[i]"``, ``"sum_b"``, ``"sum_s"``, ``"buy"``,
    ``"P_bar"``, ``"U_bar"``.
    """
    N, n = plan.b.shape
    rows = 3 if buy is None else 4
    fig, axs = axes_or_new(axes, (rows, 1), (7.5, 6.5), "axes", fig=fig, sharex=True,
                           gridspec_kw={"height_ratios": [1.1, 1.0, 1.0, 0.7][:rows]})
    ax_soc, ax_a, ax_p = axs[:3]
    j = np.arange(N + 1)
    soc_reference(ax_soc, system)
    ax_soc.set_ylim(min(-0.04, float(plan.soc.min()) - 0.05),
                    max(1.04, float(plan.soc.max()) + 0.05))
    for i in range(n):
        ax_soc.plot(j, plan.soc[:, i], color=agent_color(i), marker="o", ms=3, lw=1.5,
                    gid=f"soc[{i + 1}]", label=f"agent {i + 1}")
    ax_soc.set_ylabel("planned soc (–)")
    legend_beside(ax_soc)
    if title:
        ax_soc.set_title(title, loc="left", fontsize=10)
    u_bar_lines(ax_a, max(system.battery("U_bar")), zero=False)
    for i in range(n):
        # agents that plan the same power overlap: earlier agents drawn wider, underneath
        ax_a.plot(j, steps(plan.b[:, i] - plan.s[:, i]), drawstyle="steps-post",
                  color=agent_color(i), lw=1.5 + 0.8 * (n - 1 - i), gid=f"net_power[{i + 1}]")
    ax_a.set_ylabel("planned b − s (MW)")
    # The sold sum often sits exactly at P_bar, and both sums at 0 in the same steps: thin
    # dashes of P_bar over a narrower sold line over a wider bought line, so that all three
    # show wherever they coincide.
    p_bar_line(ax_p, system.P_bar, lw=1.0)
    sum_b, sum_s = plan.b.sum(axis=1), plan.s.sum(axis=1)
    ax_p.plot(j, steps(sum_b), drawstyle="steps-post", color=FIRST_COLOR, lw=4.0, gid="sum_b",
              zorder=2, solid_capstyle="butt", label=r"$\sum_i b^i_j$ (bought)")
    ax_p.plot(j, steps(sum_s), drawstyle="steps-post", color=LAST_COLOR, lw=2.2, gid="sum_s",
              zorder=3, solid_capstyle="butt", label=r"$\sum_i s^i_j$ (sold)")
    # a little room below 0, where both sums often sit, so that neither is cut by the axes
    headroom(ax_p, system.P_bar, sum_b.max(), sum_s.max(), bottom=-0.06 * system.P_bar)
    ax_p.set_ylabel("grid (MW)")
    legend_beside(ax_p)
    if buy is not None:
        ax_b = axs[3]
        ax_b.plot(j, steps(buy), drawstyle="steps-post", color="0.15", lw=1.2, gid="buy")
        ax_b.set_ylabel(f"buy ({PRICE_UNIT})", fontsize=8)
    axs[-1].set_xlabel("prediction step j (h from now)")
    axs[-1].set_xlim(0, N)
    return fig


def plot_policy_curve(
    curve: dict[str, Any], reference: dict[str, Any] | None = None,
    axes: Sequence[Axes] | None = None, *, fig: Figure | None = None,
) -> Figure:
    """Agent 1's policy against the swept input of :func:`mpcrl_lite.classroom.explorers.policy_curve`
    (top) and its slope by finite differences on the curve's grid (bottom); ``reference``
    (another curve, e.g. the smallest tau) dashed.

    Line gids: ``"policy"``, ``"slope"`` and ``"policy reference"``, ``"slope reference"``.
    """
    fig, (ax_pi, ax_d) = axes_or_new(axes, (2, 1), (7.0, 5.6), "axes", fig=fig, sharex=True,
                                     gridspec_kw={"height_ratios": [1.4, 1.0]})
    for c, style, width, suffix in ((reference, "--", 1.0, " reference"), (curve, "-", 2.0, "")):
        if c is None:
            continue
        label = rf"$\tau$ = {c['tau']:.0e}"
        ax_pi.plot(c["x"], c["policy"][:, 0], ls=style, lw=width, color="black", marker="o",
                   ms=2.5 if style == "-" else 0, gid=f"policy{suffix}", label=label)
        ax_d.plot(c["x"], np.gradient(c["policy"][:, 0], c["x"]), ls=style, lw=width,
                  color="black", gid=f"slope{suffix}", label=label)
    ax_pi.set_ylabel(r"$\pi^1$ = b − s (MW)")
    legend_beside(ax_pi)
    ax_pi.grid(True, **_GRID)
    ax_d.set_ylabel(r"slope $\Delta\pi^1/\Delta x$ on the grid")
    ax_d.set_xlabel(curve["label"])
    ax_d.grid(True, **_GRID)
    return fig


def plot_value_fit(
    fit: dict[str, Any], axes: Sequence[Axes] | None = None, *, fig: Figure | None = None,
) -> Figure:
    """LSTD values against Monte-Carlo returns (a :func:`mpcrl_lite.classroom.explorers.value_fit` dict):
    every visited state coloured by its hour (left) and the means over days hour by hour
    (right). Values are costs to the end of the day, in NOK.

    Line gids: ``"diagonal"``, ``"mean G"``, ``"mean V"``.
    """
    fig, (ax_s, ax_h) = axes_or_new(axes, (1, 2), (9.0, 3.8), "axes", fig=fig)
    V, G = fit["V"], fit["G"]
    H = V.shape[0]
    hours = np.broadcast_to(np.arange(H)[:, None], V.shape)
    points = ax_s.scatter(G.ravel(), V.ravel(), c=hours.ravel(), cmap="viridis", s=6, lw=0)
    fig.colorbar(points, ax=ax_s, label="hour k", pad=0.02)
    lo, hi = float(min(G.min(), V.min())), float(max(G.max(), V.max()))
    ax_s.plot([lo, hi], [lo, hi], color="0.4", ls="--", lw=1.0, gid="diagonal")
    ax_s.set_xlabel("Monte-Carlo return $G_k$ (NOK)")
    ax_s.set_ylabel("LSTD value $V(s_k)$ (NOK)")
    ax_s.set_title(f"each state; $R^2$ = {fit['r2']:.2f}", loc="left", fontsize=9)
    ax_h.plot(np.arange(H), G.mean(axis=1), color="black", lw=1.8, gid="mean G",
              label="mean $G_k$")
    ax_h.plot(np.arange(H), V.mean(axis=1), color=LAST_COLOR, lw=1.5, ls="--", gid="mean V",
              label="mean $V(s_k)$")
    ax_h.set_xlabel("hour k")
    ax_h.set_ylabel("NOK")
    ax_h.set_title(f"features: {fit['features']}, {fit['days']} day(s), "
                   rf"$\gamma$ = {fit['gamma']:g}", loc="left", fontsize=9)
    legend_beside(ax_h)
    ax_h.grid(True, **_GRID)
    return fig


# ----------------------------------------------------------------------------------------------
# Older figure-first names
# ----------------------------------------------------------------------------------------------
def draw_day(fig: Figure, traj: Record, buy: np.ndarray, day: int = 0, title: str = "",
             policy: np.ndarray | None = None, planned: np.ndarray | None = None) -> Figure:
    """:func:`plot_day` of ``traj`` into ``fig`` (the older call).

    ``buy`` (24,) and ``policy`` (H, n) must be the record's own (they are drawn from the
    record); ``planned`` given draws the record's planned grid power.
    """
    own = {"buy": (buy, traj.buy[:, day]),
           "policy": (policy, None if policy is None else traj.policy[:, day])}
    for name, (given, stored) in own.items():
        if given is not None and not np.allclose(np.asarray(given, float), stored):
            raise ValueError(f"{name}: expected the record's own {name} of day {day} (this "
                             "figure draws the record); use plot_day")
    return plot_day(traj, day, fig=fig, title=title or None, planned=planned is not None)


def draw_prices(fig: Figure, month: Prices, day: int, hour: int, N: int) -> Figure:
    """:func:`plot_price_window` into ``fig`` (the older call)."""
    return plot_price_window(month, day, hour, N, fig=fig)


def draw_plan(fig: Figure, plan: Plan, system: SystemConfig, buy: np.ndarray | None = None,
              title: str = "") -> Figure:
    """:func:`plot_plan` into ``fig`` (the older call)."""
    return plot_plan(plan, system, buy, title, fig=fig)


def draw_policy_curve(fig: Figure, curve: dict[str, Any],
                      reference: dict[str, Any] | None = None) -> Figure:
    """:func:`plot_policy_curve` into ``fig`` (the older call)."""
    return plot_policy_curve(curve, reference, fig=fig)


def draw_value_fit(fig: Figure, fit: dict[str, Any]) -> Figure:
    """:func:`plot_value_fit` into ``fig`` (the older call)."""
    return plot_value_fit(fit, fig=fig)
