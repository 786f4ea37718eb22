r"""Interactive explorers for the notebooks, built from ipywidgets.

Every builder returns an :class:`ipywidgets.VBox` subclass that can be displayed in a notebook
and driven from code, so it is testable without a running kernel:

* ``explorer.controls`` -- ``{name: widget}``; set ``explorer.controls['P_bar'].value = 1.0``
  and the explorer recomputes (synchronously) as if the slider had been released;
* ``explorer.result`` -- the data of the latest update (a
  :class:`~mpcrl_lite.history.MonthRecord`, a :class:`~mpcrl_lite.record.Record` or a
  dict of arrays);
* ``explorer.figure`` -- the :class:`matplotlib.figure.Figure` it drew, shown through
  ``explorer.image`` (PNG bytes in an :class:`ipywidgets.Image`);
* ``explorer.last_update_s`` -- the wall time of the latest update (simulation + drawing).

Sliders use ``continuous_update=False``: an MPC is solved when a slider is *released*, never
while it is dragged. Figures are plain :class:`~matplotlib.figure.Figure` objects (not
pyplot), so nothing is displayed twice by the inline backend.

============================  =============================================================
builder                       what it shows
============================  =============================================================
:func:`price_day_picker`      the prices of a day and the MPC's forecast window at an hour
:func:`rule_explorer`         one day of the true system under a price-threshold rule
:func:`day_explorer`          one day of the MPC in closed loop (P_bar, noise, prices, tau, N)
:func:`tau_explorer`          the MPC policy as a function of one input, for a barrier tau
:func:`lstd_explorer`         LSTD value fits of a recorded month against Monte-Carlo returns
============================  =============================================================

The explorers are thin: the data come from helpers that the notebooks also call directly
(:func:`threshold_rule`, :func:`simulate_day`, :func:`policy_curve`, :func:`value_fit`,
:func:`state_features`, :func:`cached_solver`), and the pictures from ``draw_*`` functions that
draw into a given figure (:func:`draw_day`, :func:`draw_plan`, :func:`draw_prices`,
:func:`draw_policy_curve`, :func:`draw_value_fit`). The paper's figures live in
:mod:`mpcrl_lite.plots`.
"""

from __future__ import annotations

import io
import time
import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import ipywidgets as widgets
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .closed_loop import Policy, rollout, run_month
from .config import PRICE_UNIT, ConfigWarning, MPCConfig, SystemConfig
from .lstd import FEATURE_SETS, LSTDResult, lstd_v, monte_carlo_returns, state_features
from .model import project_action
from .mpc import MPC
from .prices import HOURS_PER_DAY, Prices
from .record import MonthRecord, Trajectory
from .solvers import make_solver
from .theta import Theta

__all__ = [
    "TAUS",
    "POLICY_VARIABLES",
    "DayPrices",
    "cached_solver",
    "threshold_rule",
    "simulate_day",
    "policy_curve",
    "FEATURE_SETS",
    "state_features",
    "value_fit",
    "draw_day",
    "draw_prices",
    "draw_plan",
    "draw_policy_curve",
    "draw_value_fit",
    "Explorer",
    "PriceDayPicker",
    "RuleExplorer",
    "DayExplorer",
    "TauExplorer",
    "LSTDExplorer",
    "price_day_picker",
    "rule_explorer",
    "day_explorer",
    "tau_explorer",
    "lstd_explorer",
]

#: Barrier parameters offered by the explorers, from strongly smoothed to nearly exact.
TAUS: tuple[float, ...] = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5)

#: Inputs :func:`policy_curve` can sweep, with their axis labels.
POLICY_VARIABLES: dict[str, str] = {
    "theta_s": r"sell-price correction $\theta_s^1$ of agent 1 (" + PRICE_UNIT + ")",
    "soc": r"state of charge $soc^1$ of agent 1",
    "price": r"buying price $\phi_b$ of the current hour (" + PRICE_UNIT + ")",
}

_AGENT_COLORS = ("#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")
_SLIDER_STYLE = {"description_width": "initial"}


def _color(i: int) -> str:
    return _AGENT_COLORS[i % len(_AGENT_COLORS)]


# ----------------------------------------------------------------------------------------------
# Data helpers
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class DayPrices:
    """One day of a month, with the month's continuation after midnight.

    :func:`mpcrl_lite.experiment.run_month` simulates every day of the prices it is given;
    this view has one day, so one day costs 24 MPC solves, while the MPC's forecast window
    still reads on into the *next* day of the month (as in a full month), not back into the
    same day.

    Attributes
    ----------
    month : Prices
        The whole month.
    day : int
        The day simulated, in ``[0, month.days)``.
    """

    month: Prices
    day: int

    def __post_init__(self) -> None:
        if not 0 <= int(self.day) < self.month.days:
            raise ValueError(f"day={self.day!r}: expected an integer in [0, {self.month.days})")

    @property
    def days(self) -> int:
        """Always 1."""
        return 1

    @property
    def buy(self) -> np.ndarray:
        """Buying prices of the day, shape ``(1, 24)``."""
        return self.month.buy[self.day : self.day + 1]

    @property
    def sell(self) -> np.ndarray:
        """Selling prices of the day, shape ``(1, 24)``."""
        return self.month.sell[self.day : self.day + 1]

    @property
    def sell_ratio(self) -> float:
        return self.month.sell_ratio

    @property
    def unit(self) -> str:
        return self.month.unit

    def window(self, hour: int, N: int) -> tuple[np.ndarray, np.ndarray]:
        """The month's forecast window of this day, shapes ``(1, N)``."""
        buy, sell = self.month.window(hour, N)
        return buy[self.day : self.day + 1], sell[self.day : self.day + 1]


_SOLVER_CACHE: OrderedDict[tuple, Any] = OrderedDict()
_SOLVER_CACHE_SIZE = 24


def _mpc_key(system: SystemConfig) -> tuple:
    """The fields of ``system`` that the MPC formulation depends on (not noise or prices)."""
    return (
        system.n, system.N, system.U_bar, system.P_bar, system.omega, system.omega_f,
        system.soc_low, system.soc_high, system.gamma,
    )


def cached_solver(system: SystemConfig, tau: float = 1e-4, backend: str = "auto"):
    """A solver for ``system``'s MPC with barrier ``tau``, built once and then reused.

    The MPC's formulation depends on ``n``, ``N``, the bounds ``U_bar``, ``P_bar``, the slack
    weights, the soc band and ``gamma``; the noise and the prices enter only as data, so
    changing them never rebuilds anything. The most recent 24 solvers are kept.

    Parameters
    ----------
    system : SystemConfig
    tau : float
        Barrier parameter (``MPCConfig.tau``).
    backend : str
        ``'auto'``, ``'ipopt'`` or ``'batch'`` (``MPCConfig.backend``).

    Returns
    -------
    solver
        An object with ``solve_batch`` and ``sensitivity`` (see :mod:`mpcrl_lite.solvers`).
    """
    key = (_mpc_key(system), float(tau), backend)
    solver = _SOLVER_CACHE.get(key)
    if solver is None:
        solver = make_solver(MPC(system), MPCConfig(tau=tau, backend=backend))
        _SOLVER_CACHE[key] = solver
        while len(_SOLVER_CACHE) > _SOLVER_CACHE_SIZE:
            _SOLVER_CACHE.popitem(last=False)
    else:
        _SOLVER_CACHE.move_to_end(key)
    return solver


def _replace(system: SystemConfig, **changes: Any) -> SystemConfig:
    """``system.replace`` without the warning that a large P_bar never binds (the explorers
    offer such values on purpose)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return system.replace(**changes)


def threshold_rule(
    buy: np.ndarray,
    buy_below: float,
    sell_above: float,
    system: SystemConfig,
    soc_min: float = 0.3,
    soc_max: float = 0.7,
) -> Policy:
    """A simple rule: charge at full power when cheap, discharge at full power when expensive.

    At hour ``k`` of day ``d`` each battery commands

    * ``a = +U_bar`` if ``buy[d, k] <= buy_below`` and ``soc < soc_max`` (charge when cheap),
    * ``a = -U_bar`` if ``buy[d, k] >= sell_above`` and ``soc > soc_min`` (discharge when
      expensive),
    * ``a = 0`` otherwise,

    and the commands are projected onto the grid limit ``P_bar``
    (:func:`mpcrl_lite.model.project_action`), which shares it equally.

    Parameters
    ----------
    buy : array, shape ``(days, 24)``
        Buying prices of the days simulated.
    buy_below, sell_above : float
        Price thresholds in NOK/MWh.
    system : SystemConfig
    soc_min, soc_max : float
        Stop discharging at ``soc_min`` and charging at ``soc_max``. With the band edges
        (0.1, 0.9) the noise pushes the batteries into the penalised zones; a margin avoids
        most of that.

    Returns
    -------
    policy : callable ``(hour, soc (days, n)) -> a (days, n)``
        For :func:`mpcrl_lite.model.rollout`.
    """
    buy = np.asarray(buy, dtype=float)

    def policy(hour: int, soc: np.ndarray) -> np.ndarray:
        price = buy[:, hour][:, None]
        a = np.where((price <= buy_below) & (soc < soc_max), system.U_bar, 0.0)
        a = np.where((price >= sell_above) & (soc > soc_min), -system.U_bar, a)
        return project_action(a, system)

    return policy


def simulate_day(
    system: SystemConfig | None = None,
    day: int = 0,
    seed: int = 0,
    theta: Theta | None = None,
    tau: float = 1e-4,
    backend: str = "auto",
    prices: Prices | None = None,
) -> MonthRecord:
    """One day of the MPC in closed loop (no exploration, no sensitivities).

    Parameters
    ----------
    system : SystemConfig, optional
        Default ``SystemConfig()``.
    day : int
        Day of the month, in ``[0, prices.days)``.
    seed : int
        Seed of the noise; the same seed gives the same noise whatever the other settings.
    theta : Theta, optional
        MPC parameters, default :meth:`Theta.nominal` (theta0).
    tau, backend
        How the MPC is solved (:class:`~mpcrl_lite.config.MPCConfig`).
    prices : Prices, optional
        The month, default :meth:`Prices.default` for ``system`` (with its price scale).

    Returns
    -------
    MonthRecord
        A month of one day (arrays with ``D = 1``).
    """
    system = SystemConfig() if system is None else system
    month = Prices.default(system) if prices is None else prices
    theta = Theta.nominal(system) if theta is None else theta
    solver = cached_solver(system, tau, backend)
    view = DayPrices(month, int(day))
    return run_month(theta, solver, view, system, np.random.default_rng(seed),  # type: ignore[arg-type]
                     exploration_std=0.0, sensitivities=False)


def policy_curve(
    variable: str = "theta_s",
    values: Sequence[float] | np.ndarray | None = None,
    tau: float = 1e-4,
    system: SystemConfig | None = None,
    theta: Theta | None = None,
    soc: Sequence[float] | np.ndarray | None = None,
    hour: int = 0,
    day: int = 0,
    backend: str = "auto",
    prices: Prices | None = None,
) -> dict[str, Any]:
    """The MPC policy ``pi_theta(s)`` as a function of one input, the others held fixed.

    Parameters
    ----------
    variable : {'theta_s', 'soc', 'price'}
        What is varied: agent 1's selling-price correction ``theta_s^1`` (a parameter of
        the MPC), agent 1's state of charge, or the buying price of the current hour (the
        first entry of the forecast window; the selling price follows as ``sell_ratio``
        times it).
    values : array, optional
        The values of ``variable``; default 41 points over a range that shows the switch.
    tau : float
        Barrier parameter.
    system, theta, prices
        Defaults: ``SystemConfig()``, theta0, the shipped month.
    soc : array, shape ``(n,)``, optional
        The state; default ``system.soc0`` for every battery.
    hour, day : int
        Where the forecast window is taken from.
    backend : str
        Solver back-end.

    Returns
    -------
    dict
        ``x`` (k,), ``policy`` (k, n) with NaN where a solve failed, ``success`` (k,),
        ``variable``, ``tau``, ``label`` (axis label).
    """
    if variable not in POLICY_VARIABLES:
        raise ValueError(f"variable={variable!r}: expected one of {list(POLICY_VARIABLES)}")
    system = SystemConfig() if system is None else system
    theta = Theta.nominal(system) if theta is None else theta
    month = Prices.default(system) if prices is None else prices
    if values is None:
        values = {
            "theta_s": np.linspace(-20.0, 20.0, 41),
            "soc": np.linspace(0.0, 1.0, 41),
            "price": np.linspace(0.0, 120.0, 41),
        }[variable]
    x = np.asarray(values, dtype=float).reshape(-1)
    state = np.full(system.n, system.soc0) if soc is None else np.asarray(soc, float).copy()
    buy, sell = month.window(int(hour), system.N)
    buy, sell = buy[int(day)], sell[int(day)]
    solver = cached_solver(system, tau, backend)
    k = x.size
    if variable == "theta_s":
        actions, success = np.zeros((k, system.n)), np.zeros(k, dtype=bool)
        for j, value in enumerate(x):
            s_part = theta.s.copy()
            s_part[0] = value
            sol = solver.solve_batch(state[None], buy[None], sell[None], theta.replace(s=s_part))
            actions[j], success[j] = sol.action[0], sol.success[0]
    else:
        socs = np.broadcast_to(state, (k, system.n)).copy()
        buys = np.broadcast_to(buy, (k, system.N)).copy()
        sells = np.broadcast_to(sell, (k, system.N)).copy()
        if variable == "soc":
            socs[:, 0] = x
        else:
            buys[:, 0] = x
            sells[:, 0] = month.sell_ratio * x
        sol = solver.solve_batch(socs, buys, sells, theta)
        actions, success = np.array(sol.action), np.array(sol.success)
    actions = np.where(success[:, None], actions, np.nan)
    return {
        "x": x, "policy": actions, "success": success, "variable": variable, "tau": float(tau),
        "label": POLICY_VARIABLES[variable],
    }


def value_fit(record: MonthRecord, features: str = "paper", days: int | None = None,
              gamma: float | None = None) -> dict[str, Any]:
    """LSTD value of the policy that generated ``record``, next to its Monte-Carlo returns.

    Each day is an episode (its last hour does not bootstrap), as in the learning loop.

    Parameters
    ----------
    record : MonthRecord
        Transitions ``(soc_k, L~_k, soc_{k+1})`` of ``H`` hours and ``D`` days.
    features : str
        A key of :data:`FEATURE_SETS`.
    days : int, optional
        Use only the first ``days`` days (default all).
    gamma : float, optional
        Discount factor (default ``record.system.gamma``).

    Returns
    -------
    dict
        ``fit`` (:class:`~mpcrl_lite.lstd.LSTDResult`), ``V`` and ``G`` (H, days): the fitted
        value at every visited state and the Monte-Carlo return from it, ``rmse`` and ``r2``
        of ``V`` against ``G``, ``features``, ``gamma``, ``days``.
    """
    H, D = record.stage_cost.shape
    days = D if days is None else int(days)
    if not 1 <= days <= D:
        raise ValueError(f"days={days!r}: expected an integer in [1, {D}]")
    gamma = record.system.gamma if gamma is None else float(gamma)
    soc = record.soc[:, :days]
    hours = np.broadcast_to(np.arange(H + 1)[:, None], soc.shape[:2])
    phi = state_features(soc[:-1], hours[:-1], features)
    # the hour index of soc_H is H: its indicator features are all zero, and it is terminal
    phi_next = state_features(soc[1:], np.minimum(hours[1:], H - 1), features)
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], (H, days))
    cost = record.stage_cost[:, :days]
    fit: LSTDResult = lstd_v(phi, cost, phi_next, gamma, done=done)
    V = fit.value(phi)
    G = monte_carlo_returns(cost, gamma)
    rmse = float(np.sqrt(np.mean((V - G) ** 2)))
    r2 = float(1.0 - np.sum((V - G) ** 2) / np.sum((G - G.mean()) ** 2))
    return {"fit": fit, "V": V, "G": G, "rmse": rmse, "r2": r2, "features": features,
            "gamma": gamma, "days": days}


# ----------------------------------------------------------------------------------------------
# Drawing (onto a given Figure; no pyplot state)
# ----------------------------------------------------------------------------------------------
def _soc_band(ax, system: SystemConfig) -> None:
    ax.axhspan(0.0, system.soc_low, color="0.92", lw=0, zorder=0)
    ax.axhspan(system.soc_high, 1.0, color="0.92", lw=0, zorder=0)
    for level in (system.soc_low, system.soc_high):
        ax.axhline(level, color="0.45", ls="--", lw=0.9)
    ax.set_ylim(-0.03, 1.03)


def _steps(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, dtype=float)
    return np.append(values, values[-1:])


def _axes(fig: Figure, rows: int, ratios: Sequence[float], sharex: bool = True) -> list:
    """The figure's axes, cleared, when it already has this layout; else a new layout.

    Reusing the axes (and a fixed margin layout instead of ``tight_layout``) keeps a redraw
    cheap, which matters for an explorer that redraws on every slider release.
    """
    if len(fig.axes) == rows and getattr(fig, "_explorer_layout", None) == (rows, tuple(ratios)):
        for ax in fig.axes:
            ax.cla()
        return list(fig.axes)
    fig.clear()
    axes = fig.subplots(rows, 1, sharex=sharex, squeeze=False,
                        gridspec_kw={"height_ratios": list(ratios)})[:, 0]
    fig.subplots_adjust(left=0.11, right=0.97, top=0.94, bottom=0.08, hspace=0.14)
    fig._explorer_layout = (rows, tuple(ratios))  # type: ignore[attr-defined]
    return list(axes)


def draw_prices(fig: Figure, month: Prices, day: int, hour: int, N: int) -> Figure:
    """Prices of ``day`` and the next day, with the forecast window at ``hour`` shaded."""
    (ax,) = _axes(fig, 1, (1.0,))
    nxt = (day + 1) % month.days
    two = np.concatenate([month.buy[day], month.buy[nxt]])
    t = np.arange(2 * HOURS_PER_DAY + 1)
    ax.plot(t, _steps(two), drawstyle="steps-post", color="0.15", lw=1.6, label=r"buy $\phi_b$")
    ax.plot(t, _steps(month.sell_ratio * two), drawstyle="steps-post", color="0.15", lw=1.1,
            ls="--", label=r"sell $\phi_s$")
    ax.axvspan(hour, hour + N, color="#1f77b4", alpha=0.15, lw=0,
               label=f"MPC window at {hour:02d}:00 (N = {N} h)")
    ax.axvline(HOURS_PER_DAY, color="0.6", lw=0.8)
    ax.text(HOURS_PER_DAY / 2, 1.0, f"day {day + 1}", transform=ax.get_xaxis_transform(),
            ha="center", va="bottom", fontsize=9)
    ax.text(1.5 * HOURS_PER_DAY, 1.0, f"day {nxt + 1} (next)",
            transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=9)
    ax.set_xlim(0, 2 * HOURS_PER_DAY)
    ax.set_xticks(range(0, 2 * HOURS_PER_DAY + 1, 6))
    ax.set_xlabel("hour counted from the day's midnight (h)")
    ax.set_ylabel(f"price ({month.unit})")
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(True, color="0.9", lw=0.6)
    fig.subplots_adjust(bottom=0.15, top=0.9)
    return fig


def draw_day(fig: Figure, traj: Trajectory | MonthRecord, buy: np.ndarray, day: int = 0,
             title: str = "", policy: np.ndarray | None = None,
             planned: np.ndarray | None = None) -> Figure:
    """soc, net power, grid power and buying price of one day of ``traj``, drawn into ``fig``.

    Parameters
    ----------
    fig : Figure
        Redrawn in place (its axes are reused when it already has this layout).
    traj : Trajectory or MonthRecord
        A simulated batch of days.
    buy : array, shape ``(24,)``
        Buying prices of the day.
    day : int
        Which day of the batch.
    title : str
    policy : array, shape ``(H, n)``, optional
        Commanded net power, drawn dashed next to the applied one.
    planned : array, shape ``(H,)``, optional
        Largest grid power the MPC planned over its horizon at each hour.

    Returns
    -------
    Figure
        ``fig``.
    """
    system = traj.system
    ax_soc, ax_a, ax_p, ax_price = _axes(fig, 4, (1.3, 1.1, 0.9, 0.8))
    H = traj.b.shape[0]
    n = traj.b.shape[2]
    hours = np.arange(H + 1)
    _soc_band(ax_soc, system)
    for i in range(n):
        ax_soc.plot(hours, traj.soc[:, day, i], color=_color(i), lw=1.6, label=f"agent {i + 1}")
    ax_soc.set_ylabel("soc")
    ax_soc.legend(fontsize=8, ncol=n, loc="lower left")
    if title:
        ax_soc.set_title(title, loc="left", fontsize=10)
    for lim in (system.U_bar, -system.U_bar):
        ax_a.axhline(lim, color="0.45", ls=":", lw=0.9)
    for i in range(n):
        ax_a.plot(hours, _steps(traj.b[:, day, i] - traj.s[:, day, i]), drawstyle="steps-post",
                  color=_color(i), lw=1.6)
        if policy is not None:
            ax_a.plot(hours, _steps(policy[:, i]), drawstyle="steps-post", color=_color(i),
                      ls="--", lw=1.0)
    ax_a.set_ylabel("b − s (MW)")
    ax_p.axhline(system.P_bar, color="black", ls="--", lw=1.2,
                 label=rf"$\bar P$ = {system.P_bar:g}")
    ax_p.plot(hours, _steps(traj.grid_power[:, day]), drawstyle="steps-post", color="0.15",
              lw=1.6, label=r"$P_k$ applied")
    if planned is not None:
        ax_p.plot(hours, _steps(planned), drawstyle="steps-post", color="#1f77b4", lw=1.0,
                  label="max planned")
    ax_p.set_ylim(0, 1.15 * max(system.P_bar, float(np.max(traj.grid_power[:, day]))))
    ax_p.set_ylabel("grid (MW)")
    ax_p.legend(fontsize=8, ncol=3, loc="upper left")
    ax_price.plot(hours, _steps(buy), drawstyle="steps-post", color="0.15", lw=1.4)
    ax_price.set_ylabel(f"buy ({PRICE_UNIT})", fontsize=8)
    ax_price.set_xlabel("hour of day (h)")
    ax_price.set_xlim(0, H)
    ax_price.set_xticks(range(0, H + 1, 3))
    return fig


def draw_plan(fig: Figure, plan: Any, system: SystemConfig, buy: np.ndarray | None = None,
              title: str = "") -> Figure:
    """An MPC plan (:class:`mpcrl_lite.mpc.Plan`) over its horizon: predicted soc, net power
    per agent, and the grid sums ``sum_i b``, ``sum_i s`` against ``P_bar`` (with the buying
    price of each stage when ``buy`` is given)."""
    ax_soc, ax_a, ax_p = _axes(fig, 3, (1.1, 1.0, 1.0))
    N, n = plan.b.shape
    j = np.arange(N + 1)
    _soc_band(ax_soc, system)
    ax_soc.set_ylim(min(-0.03, float(plan.soc.min()) - 0.05),
                    max(1.03, float(plan.soc.max()) + 0.05))
    for i in range(n):
        ax_soc.plot(j, plan.soc[:, i], color=_color(i), marker="o", ms=3, lw=1.5,
                    label=f"agent {i + 1}")
    ax_soc.set_ylabel("planned soc")
    ax_soc.legend(fontsize=8, ncol=n, loc="best")
    if title:
        ax_soc.set_title(title, loc="left", fontsize=10)
    for lim in (system.U_bar, -system.U_bar):
        ax_a.axhline(lim, color="0.45", ls=":", lw=0.9)
    for i in range(n):
        ax_a.plot(j, _steps(plan.b[:, i] - plan.s[:, i]), drawstyle="steps-post",
                  color=_color(i), lw=1.5 + 0.8 * (n - 1 - i))
    ax_a.set_ylabel("planned b − s (MW)")
    ax_p.axhline(system.P_bar, color="black", ls="--", lw=1.2,
                 label=rf"$\bar P$ = {system.P_bar:g}")
    ax_p.plot(j, _steps(plan.b.sum(axis=1)), drawstyle="steps-post", color="#d62728", lw=1.5,
              label=r"$\sum_i b^i_j$")
    ax_p.plot(j, _steps(plan.s.sum(axis=1)), drawstyle="steps-post", color="#1f77b4", lw=1.5,
              label=r"$\sum_i s^i_j$")
    ax_p.set_ylim(0, 1.5 * max(system.P_bar, float(plan.b.sum(axis=1).max()),
                               float(plan.s.sum(axis=1).max())))
    ax_p.set_ylabel("grid (MW)")
    ax_p.set_xlabel("prediction step j (h from now)")
    ax_p.legend(fontsize=8, ncol=3, loc="upper left", framealpha=0.9)
    if buy is not None:
        twin = ax_p.twinx()
        twin.plot(j, _steps(buy), drawstyle="steps-post", color="0.5", lw=1.0, ls=":")
        twin.set_ylabel(f"buy ({PRICE_UNIT})", fontsize=8, color="0.4")
    ax_p.set_xlim(0, N)
    return fig


def draw_policy_curve(fig: Figure, curve: dict[str, Any], reference: dict[str, Any] | None = None
                      ) -> Figure:
    """Agent 1's policy versus the swept input (top) and its slope by finite differences on
    the grid of the curve (bottom); ``reference`` (another :func:`policy_curve`) dashed."""
    ax_pi, ax_d = _axes(fig, 2, (1.4, 1.0))
    for c, style, width in ((reference, "--", 1.0), (curve, "-", 2.0)):
        if c is None:
            continue
        label = rf"$\tau$ = {c['tau']:.0e}"
        ax_pi.plot(c["x"], c["policy"][:, 0], ls=style, lw=width, color="black", marker="o",
                   ms=2.5 if style == "-" else 0, label=label)
        ax_d.plot(c["x"], np.gradient(c["policy"][:, 0], c["x"]), ls=style, lw=width,
                  color="black", label=label)
    ax_pi.set_ylabel(r"$\pi^1$ = b − s (MW)")
    ax_pi.legend(fontsize=8)
    ax_pi.grid(True, color="0.9", lw=0.6)
    ax_d.set_ylabel(r"slope $\Delta\pi^1/\Delta x$ on the grid")
    ax_d.set_xlabel(curve["label"])
    ax_d.grid(True, color="0.9", lw=0.6)
    return fig


def draw_value_fit(fig: Figure, fit: dict[str, Any]) -> Figure:
    """LSTD value against Monte-Carlo returns: every visited state (left) and the means over
    days hour by hour (right)."""
    if len(fig.axes) != 2 or getattr(fig, "_explorer_layout", None) != "fit":
        fig.clear()
        fig.subplots(1, 2)
        fig.subplots_adjust(left=0.1, right=0.97, top=0.88, bottom=0.14, wspace=0.3)
        fig._explorer_layout = "fit"  # type: ignore[attr-defined]
    ax_s, ax_h = fig.axes
    ax_s.cla()
    ax_h.cla()
    V, G = fit["V"], fit["G"]
    H = V.shape[0]
    hours = np.broadcast_to(np.arange(H)[:, None], V.shape)
    ax_s.scatter(G.ravel(), V.ravel(), c=hours.ravel(), cmap="viridis", s=6, lw=0)
    lo, hi = float(min(G.min(), V.min())), float(max(G.max(), V.max()))
    ax_s.plot([lo, hi], [lo, hi], color="0.4", ls="--", lw=1.0)
    ax_s.set_xlabel("Monte-Carlo return $G_k$ (NOK)")
    ax_s.set_ylabel("LSTD value $V(s_k)$ (NOK)")
    ax_s.set_title(f"each state (colour: hour); $R^2$ = {fit['r2']:.2f}", loc="left", fontsize=9)
    ax_h.plot(np.arange(H), G.mean(axis=1), color="black", lw=1.8, label="mean $G_k$")
    ax_h.plot(np.arange(H), V.mean(axis=1), color="#1f77b4", lw=1.5, ls="--",
              label="mean $V(s_k)$")
    ax_h.set_xlabel("hour k")
    ax_h.set_ylabel("NOK")
    ax_h.set_title(f"features: {fit['features']}, {fit['days']} day(s), "
                   rf"$\gamma$ = {fit['gamma']:g}", loc="left", fontsize=9)
    ax_h.legend(fontsize=8)
    ax_h.grid(True, color="0.9", lw=0.6)
    return fig


# ----------------------------------------------------------------------------------------------
# Explorers
# ----------------------------------------------------------------------------------------------
def _png(fig: Figure, dpi: int) -> bytes:
    FigureCanvasAgg(fig)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return buffer.getvalue()


class Explorer(widgets.VBox):
    """Controls on top, a status line, then the figure (as a PNG image).

    Subclasses implement :meth:`compute` (returns the new ``result``) and :meth:`draw`.
    Changing any control's value calls :meth:`update`.
    """

    dpi = 90

    def __init__(self, controls: dict[str, widgets.Widget], figsize: tuple[float, float],
                 columns: int = 2, render: bool = True) -> None:
        self.controls = controls
        self.figure = Figure(figsize=figsize)
        self.image = widgets.Image(format="png", layout=widgets.Layout(width="auto"))
        self.status = widgets.HTML()
        self.render = render
        self.result: Any = None
        self.error: Exception | None = None
        self.last_update_s = float("nan")
        self.updates = 0
        rows = [
            widgets.HBox(list(controls.values())[i : i + columns])
            for i in range(0, len(controls), columns)
        ]
        super().__init__(children=[*rows, self.status, self.image])
        for control in controls.values():
            control.observe(self._on_change, names="value")
        self.update()

    def _on_change(self, _change: dict) -> None:
        try:
            self.update()
        except Exception:  # already shown in the status line; keep the widget alive
            pass

    @property
    def values(self) -> dict[str, Any]:
        """Current value of every control."""
        return {name: control.value for name, control in self.controls.items()}

    def compute(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def draw(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def describe(self) -> str:
        """One line of HTML about the latest result."""
        return ""

    def update(self) -> None:
        """Recompute with the current control values and redraw."""
        t0 = time.perf_counter()
        self.status.value = "<i>computing…</i>"
        try:
            self.result = self.compute()
            self.error = None
        except Exception as err:  # shown in the status line (and kept in ``error``)
            self.error = err
            self.status.value = f"<b style='color:#b00'>error:</b> {err}"
            raise
        self.draw()
        if self.render:
            self.image.value = _png(self.figure, self.dpi)
        self.updates += 1
        self.last_update_s = time.perf_counter() - t0
        self.status.value = f"{self.describe()} <small>({self.last_update_s:.2f} s)</small>"


def _float_slider(description: str, value: float, low: float, high: float, step: float,
                  fmt: str = ".2f") -> widgets.FloatSlider:
    return widgets.FloatSlider(
        value=value, min=low, max=high, step=step, description=description,
        continuous_update=False, readout_format=fmt, style=_SLIDER_STYLE,
    )


def _int_slider(description: str, value: int, low: int, high: int) -> widgets.IntSlider:
    return widgets.IntSlider(value=value, min=low, max=high, description=description,
                             continuous_update=False, style=_SLIDER_STYLE)


def _tau_slider(value: float, taus: Sequence[float]) -> widgets.SelectionSlider:
    options = [(f"{t:.0e}", float(t)) for t in taus]
    if float(value) not in [t for _, t in options]:
        options.append((f"{value:.0e}", float(value)))
        options.sort(key=lambda o: -o[1])
    return widgets.SelectionSlider(options=options, value=float(value), description="tau",
                                   continuous_update=False, style=_SLIDER_STYLE)


class PriceDayPicker(Explorer):
    """Prices of one day and the MPC's forecast window (see :func:`price_day_picker`)."""

    def __init__(self, prices: Prices, day: int, hour: int, N: int, render: bool) -> None:
        self.prices = prices
        controls = {
            "day": _int_slider("day (0-based)", day, 0, prices.days - 1),
            "hour": _int_slider("hour k", hour, 0, HOURS_PER_DAY - 1),
            "N": _int_slider("horizon N", N, 1, HOURS_PER_DAY),
        }
        super().__init__(controls, figsize=(8.0, 3.4), columns=3, render=render)

    def compute(self) -> dict[str, np.ndarray]:
        v = self.values
        buy, sell = self.prices.window(v["hour"], v["N"])
        return {"buy": buy[v["day"]], "sell": sell[v["day"]]}

    def draw(self) -> None:
        v = self.values
        draw_prices(self.figure, self.prices, v["day"], v["hour"], v["N"])

    def describe(self) -> str:
        buy = self.result["buy"]
        return (f"window: {buy.size} prices, buy from {buy.min():.1f} to {buy.max():.1f} "
                f"{self.prices.unit}")


class RuleExplorer(Explorer):
    """One day under :func:`threshold_rule` (see :func:`rule_explorer`)."""

    def __init__(self, system: SystemConfig, prices: Prices | None, day: int, seed: int,
                 buy_below: float, sell_above: float, soc_min: float, soc_max: float,
                 render: bool) -> None:
        self.system = system
        self.prices = prices
        controls = {
            "buy_below": _float_slider(f"buy below ({PRICE_UNIT})", buy_below, 0.0, 130.0, 1.0,
                                       ".0f"),
            "sell_above": _float_slider(f"sell above ({PRICE_UNIT})", sell_above, 0.0, 130.0,
                                        1.0, ".0f"),
            "soc_min": _float_slider("stop selling at soc", soc_min, 0.0, 1.0, 0.05),
            "soc_max": _float_slider("stop buying at soc", soc_max, 0.0, 1.0, 0.05),
            "noise_var": _float_slider("noise variance", system.noise_var, 0.0, 1.5, 0.05),
            "day": _int_slider("day (0-based)", day, 0, 29 if prices is None else prices.days - 1),
            "seed": widgets.BoundedIntText(value=seed, min=0, max=10**6, description="seed"),
        }
        super().__init__(controls, figsize=(8.0, 7.5), columns=2, render=render)

    def compute(self) -> Trajectory:
        v = self.values
        system = _replace(self.system, noise_var=v["noise_var"])
        month = Prices.default(system) if self.prices is None else self.prices
        buy, sell = month.buy[v["day"] : v["day"] + 1], month.sell[v["day"] : v["day"] + 1]
        rule = threshold_rule(buy, v["buy_below"], v["sell_above"], system, v["soc_min"],
                              v["soc_max"])
        return rollout(rule, buy, sell, system, np.random.default_rng(v["seed"]))

    def draw(self) -> None:
        t = self.result
        draw_day(self.figure, t, self._buy(), title=self._title(), policy=t.a[:, 0])

    def _buy(self) -> np.ndarray:
        v = self.values
        month = Prices.default(self.system) if self.prices is None else self.prices
        return month.buy[v["day"]]

    def _title(self) -> str:
        t = self.result
        return (f"rule, day {self.values['day'] + 1}: J = {t.J():.1f} NOK, "
                f"{t.hours_soc_below()} agent-hours below 0.1")

    def describe(self) -> str:
        t = self.result
        return (f"J = {t.J():.1f} NOK; agent-hours soc &lt; 0.1: {t.hours_soc_below()}, "
                f"&gt; 0.9: {t.hours_soc_above()}; low-level interventions: "
                f"{int(np.count_nonzero(np.abs(t.correction) > 1e-12))}")


class DayExplorer(Explorer):
    """One day of the MPC in closed loop (see :func:`day_explorer`)."""

    def __init__(self, system: SystemConfig, theta: Theta | dict[str, Theta] | None,
                 prices: Prices | None, day: int, seed: int, tau: float, backend: str,
                 render: bool) -> None:
        self.system = system
        self.thetas = theta if isinstance(theta, dict) else None
        self.theta = None if isinstance(theta, dict) else theta
        self.prices = prices
        self.backend = backend
        # at P_bar >= n U_bar the grid limit can no longer bind
        top = max(system.n * system.U_bar, system.P_bar)
        controls = {
            "P_bar": _float_slider("P_bar (MW)", system.P_bar, 0.1, round(top, 1), 0.1, ".1f"),
            "noise_var": _float_slider("noise variance", system.noise_var, 0.0, 1.5, 0.05),
            "price_scale": _float_slider("price scale", system.price_scale, 0.25, 4.0, 0.25),
            "tau": _tau_slider(tau, TAUS),
            "N": _int_slider("horizon N (h)", system.N, 1, 24),
            "day": _int_slider("day (0-based)", day, 0,
                               29 if prices is None else prices.days - 1),
            "seed": widgets.BoundedIntText(value=seed, min=0, max=10**6, description="seed"),
        }
        if self.thetas is not None:
            if not self.thetas:
                raise ValueError("theta: expected a Theta or a non-empty {name: Theta} dict")
            controls["theta"] = widgets.Dropdown(options=list(self.thetas),
                                                 value=next(iter(self.thetas)),
                                                 description="theta")
        super().__init__(controls, figsize=(8.0, 7.5), columns=2, render=render)

    def current_theta(self, system: SystemConfig) -> Theta:
        """The MPC parameters in use: the chosen one, the given one or theta0."""
        if self.thetas is not None:
            return self.thetas[self.values["theta"]]
        return self.theta if self.theta is not None else Theta.nominal(system)

    def current_system(self) -> SystemConfig:
        """The system with the controls' values."""
        v = self.values
        return _replace(self.system, P_bar=float(v["P_bar"]), noise_var=float(v["noise_var"]),
                        price_scale=float(v["price_scale"]), N=int(v["N"]))

    def compute(self) -> MonthRecord:
        v = self.values
        system = self.current_system()
        month = Prices.default(system) if self.prices is None else self.prices.scaled(
            float(v["price_scale"]))
        theta = self.current_theta(system)
        return simulate_day(system, v["day"], v["seed"], theta, float(v["tau"]), self.backend,
                            month)

    @property
    def summary(self) -> dict[str, Any]:
        """``result.summary()`` of the latest day."""
        return self.result.summary()

    def draw(self) -> None:
        r = self.result
        s = r.summary()
        title = (f"MPC, day {self.values['day'] + 1}: J = {s['J']:.1f} NOK, "
                 f"max planned P = {s['max_P_mpc']:.3f} MW")
        draw_day(self.figure, r.trajectory, r.buy[:, 0], title=title, policy=r.policy[:, 0],
                 planned=r.planned_power[:, 0])

    def describe(self) -> str:
        s = self.result.summary()
        return (f"J = {s['J']:.1f} NOK; agent-hours soc &lt; 0.1: {s['hours_soc_below_0_1']}; "
                f"max planned P = {s['max_P_mpc']:.3f} MW, applied {s['max_P_applied']:.3f} MW; "
                f"solver failures: {s['solver_failures']}")


class TauExplorer(Explorer):
    """The MPC policy versus one input, for a chosen barrier parameter (see
    :func:`tau_explorer`)."""

    def __init__(self, system: SystemConfig, theta: Theta | None, variable: str,
                 taus: Sequence[float], tau: float, points: int, hour: int, day: int,
                 backend: str, render: bool) -> None:
        self.system = system
        self.theta = theta
        self.points = int(points)
        self.backend = backend
        self.taus = tuple(float(t) for t in taus)
        self.reference: dict[str, Any] | None = None
        self._reference_key: tuple | None = None
        controls = {
            "tau": _tau_slider(tau, self.taus),
            "variable": widgets.Dropdown(options=list(POLICY_VARIABLES), value=variable,
                                         description="vary"),
            "hour": _int_slider("hour k", hour, 0, HOURS_PER_DAY - 1),
            "day": _int_slider("day (0-based)", day, 0, 29),
            "P_bar": _float_slider("P_bar (MW)", system.P_bar, 0.1,
                                   round(max(system.n * system.U_bar, system.P_bar), 1), 0.1,
                                   ".1f"),
        }
        super().__init__(controls, figsize=(7.0, 5.6), columns=3, render=render)

    def _curve(self, tau: float) -> dict[str, Any]:
        v = self.values
        system = _replace(self.system, P_bar=float(v["P_bar"]))
        values = np.linspace(*{"theta_s": (-20.0, 20.0), "soc": (0.0, 1.0),
                               "price": (0.0, 120.0)}[v["variable"]], self.points)
        return policy_curve(v["variable"], values, tau, system, self.theta, hour=v["hour"],
                            day=v["day"], backend=self.backend)

    def compute(self) -> dict[str, Any]:
        v = self.values
        key = (v["variable"], v["hour"], v["day"], v["P_bar"])
        smallest = min(self.taus)
        if self._reference_key != key:
            self.reference = self._curve(smallest)
            self._reference_key = key
        if float(v["tau"]) == smallest:
            return self.reference  # type: ignore[return-value]
        return self._curve(float(v["tau"]))

    def draw(self) -> None:
        ref = self.reference if self.result is not self.reference else None
        draw_policy_curve(self.figure, self.result, ref)

    def describe(self) -> str:
        c = self.result
        slope = np.nanmax(np.abs(np.gradient(c["policy"][:, 0], c["x"])))
        return (f"tau = {c['tau']:.0e}: steepest slope of pi^1 = {slope:.3g} per unit; "
                f"failed solves: {int(np.count_nonzero(~c['success']))}")


class LSTDExplorer(Explorer):
    """LSTD value fits of a recorded month (see :func:`lstd_explorer`)."""

    def __init__(self, record: MonthRecord, features: str, render: bool) -> None:
        self.record = record
        D = record.stage_cost.shape[1]
        controls = {
            "features": widgets.Dropdown(options=list(FEATURE_SETS), value=features,
                                         description="features"),
            "days": _int_slider("days used", D, 1, D),
            "gamma": widgets.SelectionSlider(options=[0.9, 0.95, 0.99, 1.0],
                                             value=record.system.gamma, description="gamma",
                                             continuous_update=False, style=_SLIDER_STYLE),
        }
        super().__init__(controls, figsize=(9.0, 3.8), columns=3, render=render)

    def compute(self) -> dict[str, Any]:
        v = self.values
        return value_fit(self.record, v["features"], v["days"], v["gamma"])

    def draw(self) -> None:
        draw_value_fit(self.figure, self.result)

    def describe(self) -> str:
        r = self.result
        return (f"RMSE of V against the returns: {r['rmse']:.1f} NOK, R<sup>2</sup> = "
                f"{r['r2']:.3f}; condition of the LSTD matrix {r['fit'].condition:.2g}")


# ----------------------------------------------------------------------------------------------
# Builders
# ----------------------------------------------------------------------------------------------
def price_day_picker(prices: Prices | None = None, day: int = 0, hour: int = 18, N: int = 12,
                     render: bool = True) -> PriceDayPicker:
    """Pick a day and an hour; see the day's prices and what the MPC forecasts from there.

    Controls: ``day``, ``hour``, ``N``. ``result`` = ``{'buy': (N,), 'sell': (N,)}``, the
    window the MPC sees at that hour (reading on into the next day after midnight).
    """
    prices = Prices.default() if prices is None else prices
    return PriceDayPicker(prices, day, hour, N, render)


def rule_explorer(system: SystemConfig | None = None, prices: Prices | None = None,
                  day: int = 0, seed: int = 0, buy_below: float = 20.0,
                  sell_above: float = 60.0, soc_min: float = 0.3, soc_max: float = 0.7,
                  render: bool = True) -> RuleExplorer:
    """One day of the true system under :func:`threshold_rule`.

    Controls: ``buy_below``, ``sell_above`` (NOK/MWh), ``soc_min``, ``soc_max``,
    ``noise_var``, ``day``, ``seed``.
    ``result`` is the :class:`~mpcrl_lite.record.Record` of the day.
    """
    system = SystemConfig() if system is None else system
    return RuleExplorer(system, prices, day, seed, buy_below, sell_above, soc_min, soc_max,
                        render)


def day_explorer(system: SystemConfig | None = None,
                 theta: Theta | dict[str, Theta] | None = None,
                 prices: Prices | None = None, day: int = 0, seed: int = 0, tau: float = 1e-4,
                 backend: str = "auto", render: bool = True) -> DayExplorer:
    """One day of the MPC in closed loop, re-solved when a slider is released.

    Controls: ``P_bar``, ``noise_var``, ``price_scale``, ``tau``, ``N``, ``day``, ``seed``
    (and ``theta`` when several are given). ``result`` is the day's
    :class:`~mpcrl_lite.history.MonthRecord` (``D = 1``), so
    ``explorer.result.summary()['max_P_mpc'] <= controls['P_bar'].value`` can be checked.
    The noise depends on ``seed`` only, so two settings are compared on the same draws.

    Parameters
    ----------
    system : SystemConfig, optional
        Starting values (default ``SystemConfig()``).
    theta : Theta or dict of Theta, optional
        MPC parameters (default theta0 of the current system), e.g. a learned
        ``history.final_theta()``; a dict ``{name: Theta}`` adds a ``theta`` drop-down to
        switch between them on the same noise.
    prices : Prices, optional
        The month (default the shipped one; ``price_scale`` multiplies it).
    day, seed, tau, backend
        Starting values.
    render : bool
        Draw the PNG (set False to compute only).
    """
    system = SystemConfig() if system is None else system
    return DayExplorer(system, theta, prices, day, seed, tau, backend, render)


def tau_explorer(system: SystemConfig | None = None, theta: Theta | None = None,
                 variable: str = "theta_s", taus: Sequence[float] = TAUS, tau: float = 1e-2,
                 points: int = 41, hour: int = 0, day: int = 0, backend: str = "auto",
                 render: bool = True) -> TauExplorer:
    """The MPC policy of agent 1 as a function of one input, for a barrier parameter ``tau``.

    The chosen ``tau`` is drawn solid, the smallest of ``taus`` dashed as the nearly exact
    reference. Controls: ``tau``, ``variable`` (see :data:`POLICY_VARIABLES`), ``hour``,
    ``day``, ``P_bar``. ``result`` is a :func:`policy_curve` dict.
    """
    if variable not in POLICY_VARIABLES:
        raise ValueError(f"variable={variable!r}: expected one of {list(POLICY_VARIABLES)}")
    system = SystemConfig() if system is None else system
    return TauExplorer(system, theta, variable, taus, tau, points, hour, day, backend, render)


def lstd_explorer(record: MonthRecord, features: str = "paper", render: bool = True
                  ) -> LSTDExplorer:
    """Fit the value of the policy behind ``record`` by LSTD and compare it with the
    Monte-Carlo returns; no MPC is solved, so updates are instant.

    Controls: ``features`` (see :data:`FEATURE_SETS`), ``days`` (how many of the recorded days
    are used), ``gamma``. ``result`` is a :func:`value_fit` dict.
    """
    if features not in FEATURE_SETS:
        raise ValueError(f"features={features!r}: expected one of {list(FEATURE_SETS)}")
    return LSTDExplorer(record, features, render)
