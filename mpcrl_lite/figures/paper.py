r"""The paper's figures 1-7, drawn from a learning run (:class:`~mpcrl_lite.learning.history.History`)
or a month of prices (:class:`~mpcrl_lite.system.prices.Prices`).

Every function takes an optional ``ax`` (or ``axes``) to draw into, otherwise it creates a
figure, and returns the :class:`matplotlib.figure.Figure`; nothing here simulates, learns or
calls ``plt.show()``. The conventions (colours, reference lines, units, gids) are those of
:mod:`mpcrl_lite.figures.style`; all functions are also importable from :mod:`mpcrl_lite.figures.plots`.

=========================================  ==================================================
function                                   figure
=========================================  ==================================================
:func:`fig1_trajectories`                  paper Fig. 1: soc and policy, first vs last month
:func:`fig2_performance`                   paper Fig. 2: closed-loop cost ``J`` per month
:func:`fig3_gradient_norm`                 paper Fig. 3: ``||grad_theta J||`` per month
:func:`fig4_grid_power`                    paper Fig. 4: grid power ``P_k`` vs ``P_bar``
:func:`fig5_policy_and_agent_costs`        paper Fig. 5: learned policy, ``J^i`` per agent
:func:`fig6_prices`                        paper Fig. 6: the buying price of five days
:func:`fig7_theta`                         paper Fig. 7: one part of theta per month
:func:`save_paper_figures`                 all seven as PNG files
=========================================  ==================================================
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._util.lazy import lazy_module
from .._util.validate import check_instance, check_int
from ..config import PRICE_UNIT
from ..learning.durable import atomic_output
from ..learning.history import History
from ..system.prices import Prices
from ..theta import PARTS
from .style import (
    COST_UNIT,
    CURRENCY,
    FIRST_COLOR,
    LAST_COLOR,
    MIN_POINTS_FOR_A_LINE,
    agent_color,
    axes_or_new,
    day_axis,
    p_bar_line,
    select_days,
    soc_reference,
    steps,
    u_bar_lines,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: matplotlib, imported when a figure is first drawn (a run without figures never
#: loads it)
plt = lazy_module("matplotlib.pyplot")
_ticker = lazy_module("matplotlib.ticker")

__all__ = [
    "PAPER_FIGURES",
    "fig1_trajectories",
    "fig2_performance",
    "fig3_gradient_norm",
    "fig4_grid_power",
    "fig5_policy_and_agent_costs",
    "fig6_prices",
    "fig7_theta",
    "save_paper_figures",
]

#: File names written by :func:`save_paper_figures`, in figure order.
PAPER_FIGURES: tuple[str, ...] = (
    "fig1_trajectories.png",
    "fig2_performance.png",
    "fig3_gradient_norm.png",
    "fig4_grid_power.png",
    "fig5_policy_and_agent_costs.png",
    "fig6_prices.png",
    "fig7_theta_delta.png",
)
#: Mathtext names of theta's parts (paper notation), for labels.
_PART_TEX = {
    "alpha": r"\theta_\alpha", "delta": r"\theta_\delta", "b": r"\theta_b", "s": r"\theta_s",
    "phi1": r"\phi_1", "phi2": r"\phi_2", "phi3": r"\phi_3",
    "T1": r"T_1", "T2": r"T_2", "T3": r"T_3",
}
#: Units of theta's parts: alpha and delta act on soc, b and s on prices, the rest on cost.
_PART_UNIT = {
    "alpha": "1/MWh", "delta": "–", "b": PRICE_UNIT, "s": PRICE_UNIT,
    **{name: CURRENCY for name in ("phi1", "phi2", "phi3", "T1", "T2", "T3")},
}


def _history_months(history: History, need_records: bool = False) -> int:
    check_instance("history", history, History)
    if history.months == 0:
        raise ValueError("history has no months recorded")
    if need_records and (history.first_month is None or history.last_month is None):
        raise ValueError("history holds no month trajectories (first_month/last_month is None)")
    return history.months


def _concat_days(values: np.ndarray, days: Sequence[int], i: int | None = None) -> np.ndarray:
    """Hourly values ``(H, D[, n])`` of the chosen days, one after the other, shape (len*H,)."""
    picked = values[:, days] if i is None else values[:, days, i]
    return picked.T.reshape(-1)


def _concat_soc(soc: np.ndarray, days: Sequence[int], i: int) -> tuple[np.ndarray, np.ndarray]:
    """soc of agent ``i`` over the chosen days, each day's ``H + 1`` points followed by a
    gap (NaN): the battery restarts at ``soc0`` every morning, so days are not joined."""
    H = soc.shape[0] - 1
    t = [np.r_[j * H + np.arange(H + 1), np.nan] for j in range(len(days))]
    y = [np.r_[soc[:, d, i], np.nan] for d in days]
    return np.concatenate(t), np.concatenate(y)


def _first_and_last(ax: Axes, x: np.ndarray, y: np.ndarray) -> None:
    """The first month's point of a per-month series marked red, the last month's blue."""
    ax.plot(x[0], y[0], "o", color=FIRST_COLOR, ms=8, zorder=3, label="first month")
    ax.plot(x[-1], y[-1], "o", color=LAST_COLOR, ms=8, zorder=3, label="last month")


def _agent_series(
    ax: Axes, x: np.ndarray, values: np.ndarray, gid: str, tex: str, lw: float,
) -> None:
    """One line per agent of ``values`` (len(x), n) over the months; gids ``"<gid>[i]"`` and
    labels ``$<tex>^i$``, agents counted from 1."""
    for i in range(values.shape[1]):
        ax.plot(x, values[:, i], color=agent_color(i), lw=lw, marker="o", ms=3,
                gid=f"{gid}[{i + 1}]", label=f"${tex}^{{{i + 1}}}$")


def _month_axis(
    ax: Axes, months: int, ylabel: str, title: str, grid: str = "0.9", legend_size: int = 8,
) -> None:
    """Labels, grid and legend of axes whose x axis is the RL step (month), with a tick at
    every month when there are at most 12."""
    ax.set_xlabel("RL step (month)")
    ax.set_ylabel(ylabel)
    ax.set_title(title, loc="left", fontsize=11)
    ax.grid(True, color=grid, lw=0.6)
    ax.legend(fontsize=legend_size, framealpha=0.9)
    if months <= 12:
        ax.xaxis.set_major_locator(_ticker.MultipleLocator(1))


def fig1_trajectories(
    history: History,
    days: int | Sequence[int] | None = None,
    axes: Sequence[Axes] | None = None,
) -> Figure:
    """Paper Fig. 1: soc and policy of every agent over a few days, first vs last month.

    A grid of ``n`` rows (agents) by 2 columns: left ``soc^i`` (with the band 0.1 / 0.9),
    right the MPC policy ``pi^i(s)`` as net power (MW, with ``+-U_bar``). The chosen days are
    drawn one after the other on a common time axis; soc restarts at ``soc0`` each morning,
    so each day's soc curve is drawn separately. Red: first month, blue: last month.

    Parameters
    ----------
    history : History
        A run with ``first_month`` and ``last_month``.
    days : int or sequence of int, optional
        The first ``days`` days, or explicit day indices; default the first five (fewer if
        the month is shorter).
    axes : sequence of ``2 n`` Axes, optional
        Row-major (agent 1 soc, agent 1 policy, agent 2 soc, ...); default a new figure.

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Line gids: ``"soc[i] first"``, ``"soc[i] last"``, ``"policy[i] first"``,
    ``"policy[i] last"`` (agents counted from 1) and the soc / ``U_bar`` references.
    """
    _history_months(history, need_records=True)
    first, last = history.first_month, history.last_month
    H, D, n = last.policy.shape
    chosen = select_days(days, min(D, first.policy.shape[1]))
    system = history.system
    fig, flat = axes_or_new(axes, (n, 2), (11.0, 1.9 * n + 1.0), "axes", sharex=True)
    t_pol = np.arange(len(chosen) * H + 1)
    months = {"first": (first, FIRST_COLOR, "first month"),
              "last": (last, LAST_COLOR, f"last month (month {history.months})")}
    for i in range(n):
        ax_s, ax_p = flat[2 * i], flat[2 * i + 1]
        soc_reference(ax_s, system, label=(i == 0))
        u_bar_lines(ax_p, max(system.battery("U_bar")))
        for key, (rec, color, label) in months.items():
            t, y = _concat_soc(rec.soc, chosen, i)
            ax_s.plot(t, y, color=color, lw=1.4, gid=f"soc[{i + 1}] {key}",
                      label=label if i == 0 else None)
            ax_p.plot(t_pol, steps(_concat_days(rec.policy, chosen, i)), drawstyle="steps-post",
                      color=color, lw=1.1, alpha=0.85, gid=f"policy[{i + 1}] {key}")
        ax_s.set_ylabel(f"soc$^{i + 1}$ (–)")
        ax_p.set_ylabel(rf"$\pi^{i + 1}$ (MW)")
        ax_p.set_ylim(-1.15 * max(system.battery("U_bar")), 1.15 * max(system.battery("U_bar")))
        for ax in (ax_s, ax_p):
            day_axis(ax, len(chosen), H, labels=chosen if i == 0 else None)
    flat[-2].set_xlabel("time (h)")
    flat[-1].set_xlabel("time (h)")
    flat[0].set_title("state of charge", loc="left", fontsize=11, pad=14)
    flat[1].set_title("policy (net power b − s)", loc="left", fontsize=11, pad=14)
    handles, labels = flat[0].get_legend_handles_labels()
    if axes is None:
        fig.legend(handles, labels, loc="outside upper center", ncol=len(labels), frameon=False)
        fig.align_ylabels()
    else:
        flat[0].legend(fontsize=8, loc="lower left")
    return fig


def fig2_performance(
    history: History, rolling: int | None = 10, ax: Axes | None = None,
) -> Figure:
    r"""Paper Fig. 2: closed-loop cost ``J`` of every month (RL step).

    ``J = mean over days of sum_k gamma^k L~(s_k, a_k)`` (paper eq. 4, each day an
    episode). The first month's point is red, the last month's blue. When the history holds
    an evaluation series (``history.J_eval`` at ``history.eval_month``: the parameters of a
    month on ``K = learning.eval_draws`` fixed noise draws, without exploration, the mean of
    the draws' J), it is drawn as a second line with square markers; it is not disturbed by
    each month's own noise and shows the trend. Where the history holds its 95 % confidence
    interval over the K draws (``J_eval_ci_low``, ``J_eval_ci_high``; K >= 2), the interval is
    drawn as a band around it. With fewer than :data:`MIN_POINTS_FOR_A_LINE` evaluations they
    are drawn as points with error bars, without a line between them.

    Parameters
    ----------
    history : History
    rolling : int or None, default 10
        Also draw the mean of ``rolling`` consecutive months, centred on them (only when
        there are more months than that); ``None`` or 1 draws none.
    ax : Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Line gids: ``"J"``, ``"J_rolling"`` and ``"J_eval"`` (months counted from 1, as for
    ``"J"``); the band's gid is ``"J_eval_ci"``.
    """
    months = _history_months(history)
    if rolling is not None:
        rolling = check_int("rolling", rolling, 1)
    fig, (ax,) = axes_or_new(ax, (1, 1), (7.0, 4.0), "ax")
    x = np.arange(1, months + 1)
    J = np.asarray(history.J, dtype=float)
    ax.plot(x, J, color="0.35", lw=1.2, marker="o", ms=3, gid="J", label="J per month")
    if rolling is not None and 1 < rolling < months:
        # centred: each mean is drawn at the middle of its months, so it neither lags behind
        # a falling J nor sits above it
        window = np.ones(rolling) / rolling
        mean = np.convolve(J, window, mode="valid")
        ax.plot(np.convolve(x, window, mode="valid"), mean, color="black", lw=2.2,
                gid="J_rolling", label=f"mean of {rolling} months (centred)")
    if history.J_eval:
        if len(history.eval_month) != len(history.J_eval):
            raise ValueError(
                f"history has {len(history.J_eval)} J_eval values but "
                f"{len(history.eval_month)} eval_month entries"
            )
        x_eval = np.asarray(history.eval_month, dtype=float) + 1.0  # months counted from 1
        draws = history.learning.eval_draws
        low = np.asarray(getattr(history, "J_eval_ci_low", []), dtype=float)
        high = np.asarray(getattr(history, "J_eval_ci_high", []), dtype=float)
        J_eval = np.asarray(history.J_eval, dtype=float)
        # with fewer than MIN_POINTS_FOR_A_LINE evaluations a line (and a band) between them
        # would draw a trend nobody measured: points with error bars instead
        few = x_eval.size < MIN_POINTS_FOR_A_LINE
        if low.shape == high.shape == x_eval.shape and np.isfinite(low).any():
            if few:
                bars = ax.errorbar(x_eval, J_eval, yerr=[J_eval - low, high - J_eval], fmt="none",
                                   ecolor="0.35", capsize=4, lw=1.4, zorder=3.4,
                                   label=f"95 % CI over the {draws} draws")
                bars.lines[2][0].set_gid("J_eval_ci")
            else:
                ax.fill_between(x_eval, low, high, color="0.6", alpha=0.35, lw=0, zorder=1,
                                gid="J_eval_ci", label=f"95 % CI over the {draws} draws")
        label = ("evaluation (fixed draw)" if draws == 1
                 else f"evaluation (mean of {draws} fixed draws)")
        # above the larger first/last month markers, which sit at the same months
        ax.plot(x_eval, J_eval, color="black", ls="none" if few else "--",
                lw=1.4, marker="s", ms=4.5, mfc="white", mec="black", mew=1.0, zorder=3.5,
                gid="J_eval", label=label)
    _first_and_last(ax, x, J)
    _month_axis(ax, months, f"closed-loop cost J ({COST_UNIT})", "Closed-loop performance")
    return fig


def fig3_gradient_norm(history: History, ax: Axes | None = None) -> Figure:
    r"""Paper Fig. 3: norm of the policy gradient ``||grad_theta J(pi_theta)||`` per month.

    Logarithmic scale; months whose gradient is zero (no usable samples) are not drawn.

    Parameters
    ----------
    history : History
    ax : Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Line gid: ``"grad_norm"``.
    """
    months = _history_months(history)
    fig, (ax,) = axes_or_new(ax, (1, 1), (7.0, 4.0), "ax")
    x = np.arange(1, months + 1)
    g = np.asarray(history.grad_norm, dtype=float)
    ax.plot(x, g, color="0.25", lw=1.2, marker="o", ms=3, gid="grad_norm")
    _first_and_last(ax, x, g)
    ax.set_yscale("log")
    _month_axis(ax, months, r"$\Vert\nabla_\theta J(\pi_\theta)\Vert$",
                "Norm of the policy gradient", grid="0.88")
    return fig


def fig4_grid_power(
    history: History,
    days: int | Sequence[int] | None = None,
    ax: Axes | None = None,
) -> Figure:
    """Paper Fig. 4: grid power over a few days of the last month, against ``P_bar``.

    Two series per hour ``k``:

    * applied ``P_k = max(sum_i b^i_k, sum_i s^i_k)`` (solid, blue = last month): the power
      actually exchanged at point T, after the low-level controller has absorbed the noise
      ``Delta`` (it can exceed ``P_bar`` when a battery would leave ``[0, 1]``);
    * planned (dotted): the largest ``sum_i b`` or ``sum_i s`` the MPC planned over its
      horizon at hour ``k``, the quantity its constraint ``P <= P_bar`` acts on.

    Hours where the applied power exceeds ``P_bar`` are shaded, and a note (text gid
    ``"P_applied_months"``) gives, over all months, the largest applied power
    (``history.max_P_applied``) and the share of hour-days above ``P_bar`` in the first and
    the last month (``history.hours_above_P_bar``). The paper's claim ``P <= P_bar`` is about
    the MPC's planned powers; the applied ones can exceed it through the low-level controller.

    Parameters
    ----------
    history : History
    days : int or sequence of int, optional
        The first ``days`` days, or explicit day indices; default five (fewer if the month is
        shorter).
    ax : Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Line gids: ``"grid_power"``, ``"planned_power"``, ``"P_bar"``.
    """
    _history_months(history, need_records=True)
    rec = history.last_month
    H, D = rec.grid_power.shape
    chosen = select_days(days, D)
    P_bar = history.system.P_bar
    fig, (ax,) = axes_or_new(ax, (1, 1), (10.0, 4.0), "ax")
    t = np.arange(len(chosen) * H + 1)
    applied = _concat_days(rec.grid_power, chosen)
    planned = _concat_days(rec.planned_power, chosen)
    p_bar_line(ax, P_bar)
    # shade each run of consecutive hours with P_k > P_bar
    over = np.r_[False, applied > P_bar + 1e-9, False].astype(int)
    starts, ends = np.flatnonzero(np.diff(over) == 1), np.flatnonzero(np.diff(over) == -1)
    for j, (k0, k1) in enumerate(zip(starts, ends)):
        ax.axvspan(k0, k1, color="#fdd0a2", alpha=0.8, lw=0, zorder=0, gid="P_over",
                   label=r"applied $> \bar P$" if j == 0 else None)
    ax.plot(t, steps(planned), drawstyle="steps-post", color="0.55", ls=":", lw=2.2,
            gid="planned_power", label="planned by the MPC (max over horizon)")
    ax.plot(t, steps(applied), drawstyle="steps-post", color=LAST_COLOR, lw=1.8,
            gid="grid_power", label=r"applied $P_k$")
    # headroom above the data for the legend
    ax.set_ylim(0.0, 1.45 * max(P_bar, float(applied.max()), float(planned.max())))
    ax.set_xlabel("time (h)")
    ax.set_ylabel("grid power P (MW)")
    ax.set_title(f"Power exchanged with the grid, last month (month {history.months})",
                 loc="left", fontsize=11, pad=14)
    day_axis(ax, len(chosen), H, labels=chosen)
    ax.legend(fontsize=8, loc="upper right", ncol=2, framealpha=0.9)
    note = _applied_power_note(history)
    if note:
        ax.text(0.01, 0.97, note, transform=ax.transAxes, fontsize=7.5, va="top", ha="left",
                gid="P_applied_months",
                bbox={"boxstyle": "round", "fc": "white", "ec": "0.8", "alpha": 0.9})
    return fig


def _applied_power_note(history: History) -> str:
    """Per-month applied grid power in one or two lines ('' without the series)."""
    top = np.asarray(history.max_P_applied, dtype=float)
    lines = []
    if top.size and np.isfinite(top).any():
        m = int(np.nanargmax(top))
        lines.append(f"max applied P over all months: {top[m]:.2f} MW (month {m + 1})")
    above = np.asarray(getattr(history, "hours_above_P_bar", []), dtype=float)
    if above.size == history.months and np.isfinite(above[[0, -1]]).all():
        hour_days = history.system.hours_per_day * history.learning.days_per_month
        first, last = 100.0 * above[0] / hour_days, 100.0 * above[-1] / hour_days
        lines.append(rf"hour-days with applied $P > \bar P$: {first:.1f} % (month 1), "
                     f"{last:.1f} % (month {history.months})")
    return "\n".join(lines)


def fig5_policy_and_agent_costs(
    history: History, axes: Sequence[Axes] | None = None,
) -> Figure:
    """Paper Fig. 5: the learned policy (left) and the cost ``J^i`` of every agent (right).

    Left: every action ``pi^i(s_k)`` of the last month against the hour of day ``k``. Each
    hour holds one narrow column per agent, and within it the days are spread from left to
    right (day 1 leftmost), so no point hides another. A scatter against the hour was chosen
    over a time series (which shows a handful of days only) and over a histogram (which
    loses the time of day): a (nearly) bang-bang policy -- the structure expected with a
    linear economic cost and linear stochastic dynamics -- shows as rows of points at a few
    levels, ``+-U_bar``, the share of the grid limit ``P_bar`` when several agents trade at
    once, and 0, with few points in between; and where the levels switch shows how the
    policy follows the daily price cycle.

    Right: ``J^i`` per month (paper eq. 5), one line per agent.

    Parameters
    ----------
    history : History
        A run with ``last_month``.
    axes : sequence of 2 Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Gids: the scatter collections ``"policy[i]"`` and the lines ``"J[i]"`` (agents counted
    from 1), references ``"U_bar"``.
    """
    months = _history_months(history, need_records=True)
    rec = history.last_month
    H, D, n = rec.policy.shape
    system = history.system
    fig, (ax_pi, ax_J) = axes_or_new(
        axes, (1, 2), (12.0, 4.4), "axes", gridspec_kw={"width_ratios": [1.3, 1.0]},
    )
    slot = 0.84 / n  # width of one agent's column within an hour
    # x = hour + agent column + day position: a deterministic spread, days left to right
    spread = (np.arange(D) / max(D - 1, 1) - 0.5) * 0.8 * slot if D > 1 else np.zeros(1)
    centre = 0.5 + (np.arange(n) - (n - 1) / 2) * slot
    u_bar_lines(ax_pi, max(system.battery("U_bar")))
    x_day = (np.arange(H)[:, None] + spread[None, :]).reshape(-1)  # (H*D,), hour-major
    for i in range(n):
        ax_pi.scatter(x_day + centre[i], rec.policy[:, :, i].reshape(-1), s=6,
                      color=agent_color(i), alpha=0.7, lw=0, gid=f"policy[{i + 1}]",
                      label=f"agent {i + 1}")
    ax_pi.set_xlim(0, H)
    ax_pi.xaxis.set_major_locator(_ticker.MultipleLocator(max(1, H // 8)))
    ax_pi.set_ylim(-1.15 * max(system.battery("U_bar")), 1.15 * max(system.battery("U_bar")))
    ax_pi.set_xlabel("hour of day (h)")
    ax_pi.set_ylabel(r"policy $\pi^i(s)$ = b − s (MW)")
    ax_pi.set_title(f"Learned policy, last month ({D} days)", loc="left", fontsize=11)
    ax_pi.legend(fontsize=8, loc="lower right", bbox_to_anchor=(1.0, 1.0), markerscale=2.5,
                 ncol=n, frameon=False, borderaxespad=0.2)
    ax_pi.grid(True, axis="x", color="0.92", lw=0.6)

    x = np.arange(1, months + 1)
    J_i = np.asarray(history.J_per_agent, dtype=float).reshape(months, -1)
    _agent_series(ax_J, x, J_i, "J", "J", lw=1.5)
    _month_axis(ax_J, months, f"cost per agent $J^i$ ({COST_UNIT})", "Closed-loop cost per agent")
    return fig


def fig6_prices(
    prices: Prices,
    days: int | Sequence[int] | None = None,
    ax: Axes | None = None,
) -> Figure:
    """Paper Fig. 6: the 24-hour buying price ``phi_b`` of a few days.

    One line per day; the value drawn at hour ``k`` is the price of ``[k, k+1)``.

    Parameters
    ----------
    prices : Prices
    days : int or sequence of int, optional
        The first ``days`` days, or explicit day indices; default five (fewer if there are
        fewer days).
    ax : Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Notes
    -----
    Line gids: ``"buy day d"`` (days counted from 1).
    """
    check_instance("prices", prices, Prices)
    chosen = select_days(days, prices.days)
    fig, (ax,) = axes_or_new(ax, (1, 1), (7.0, 4.0), "ax")
    colors = plt.get_cmap("viridis")(np.linspace(0.0, 0.85, len(chosen)))
    hours = np.arange(prices.buy.shape[1])
    for color, d in zip(colors, chosen):
        ax.plot(hours, prices.buy[d], color=color, lw=1.7, marker="o", ms=3,
                gid=f"buy day {d + 1}", label=f"day {d + 1}")
    ax.set_xlim(-0.5, hours[-1] + 0.5)
    ax.xaxis.set_major_locator(_ticker.MultipleLocator(3))
    ax.set_xlabel("hour of day (h)")
    ax.set_ylabel(rf"buying price $\phi_b$ ({prices.unit})")
    ax.set_title("Buying price", loc="left", fontsize=11)
    ax.annotate(f"source: {prices.source}", xy=(0.0, 0.0), xycoords="axes fraction",
                xytext=(0, -34), textcoords="offset points", ha="left", va="top", fontsize=7,
                color="0.45")
    ax.grid(True, color="0.9", lw=0.6)
    ax.legend(fontsize=8, framealpha=0.9, ncol=1 if len(chosen) <= 6 else 2)
    return fig


def fig7_theta(history: History, part: str = "delta", ax: Axes | None = None) -> Figure:
    """Paper Fig. 7: one part of theta (one entry per agent) over the months.

    Point ``m`` is the value used during month ``m + 1``; the last point is theta after the
    last update (:meth:`History.theta_part`), so month 0 is ``theta_0``. When every agent
    holds the same value in every month (``LearningConfig.tie_agents``, the default) the
    agents' lines would lie on top of each other, the last one hiding the rest: one line is
    drawn instead, labelled as the tied value of all agents.

    Parameters
    ----------
    history : History
    part : str, default "delta"
        One of :data:`mpcrl_lite.theta.PARTS`.
    ax : Axes, optional

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        If ``part`` is not a part of theta.

    Notes
    -----
    Line gids: ``"theta_<part>[i]"`` (agents counted from 1), or ``"theta_<part>[tied]"``
    for the one line of tied agents.
    """
    if part not in PARTS:
        raise ValueError(f"part={part!r}: expected one of {PARTS}")
    months = _history_months(history)
    if not history.theta_final:
        raise ValueError("history has no theta_final (no update was recorded)")
    values = history.theta_part(part)
    fig, (ax,) = axes_or_new(ax, (1, 1), (7.0, 4.0), "ax")
    x = np.arange(values.shape[0])  # theta_0 at 0, then after each month's update
    tex = _PART_TEX[part]
    n = values.shape[1]
    if n > 1 and np.allclose(values, values[:, :1], rtol=1e-12, atol=0.0):
        # tied agents: n coinciding lines would show one colour under n legend entries
        ax.plot(x, values[:, 0], color="0.2", lw=1.6, marker="o", ms=3,
                gid=f"theta_{part}[tied]", label=f"${tex}^i$, all {n} agents (tied)")
    else:
        _agent_series(ax, x, values, f"theta_{part}", tex, lw=1.6)
    _month_axis(ax, months, f"${tex}$ ({_PART_UNIT[part]})", f"Convergence of ${tex}^i$",
                legend_size=9)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)
    return fig


def save_paper_figures(
    history: History,
    directory: str | Path,
    prices: Prices | None = None,
    dpi: int = 110,
) -> list[Path]:
    """Write paper Figs. 1-7 as PNG files into ``directory``.

    Parameters
    ----------
    history : History
        A run with ``first_month`` and ``last_month``.
    directory : str or Path
        Created if missing.
    prices : Prices, optional
        For Fig. 6; default the shipped month for ``history.system``, as many days as the
        recorded month (:meth:`Prices.month`).
    dpi : int, default 110

    Returns
    -------
    list of Path
        The files, named as in :data:`PAPER_FIGURES`, in figure order.
    """
    _history_months(history, need_records=True)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if prices is None:
        prices = Prices.month(history.system, history.last_month.policy.shape[1])
    makers = (
        lambda: fig1_trajectories(history),
        lambda: fig2_performance(history),
        lambda: fig3_gradient_norm(history),
        lambda: fig4_grid_power(history),
        lambda: fig5_policy_and_agent_costs(history),
        lambda: fig6_prices(prices),
        lambda: fig7_theta(history, "delta"),
    )
    paths = []
    for name, make in zip(PAPER_FIGURES, makers):
        fig = make()
        try:
            path = directory / name
            # a kill never leaves half a figure; saved as laid out (constrained layout keeps
            # every label on the canvas), since cropping to the content costs a second layout
            with atomic_output(path) as tmp:
                fig.savefig(tmp, dpi=dpi)
            paths.append(path)
        finally:
            plt.close(fig)
    return paths
