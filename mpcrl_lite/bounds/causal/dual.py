r"""A lower bound on the causal optimum for any number of batteries: Lagrangian relaxation.

The grid limit is the only thing that couples the batteries. Price it by multipliers
``lambda_k, mu_k >= 0`` per hour (and day): for every causal policy whose commands respect the
limit on every path,

.. math:: J(\pi) \ \ge\ \mathbb E\Big[\sum_k \gamma^k\big(\tilde L_k
          + \lambda_k (\textstyle\sum_i a_{k,i}^+ - \bar P)
          + \mu_k (\textstyle\sum_i a_{k,i}^- - \bar P)\big)\Big]
          \ \ge\ D(\lambda, \mu) = n\, V^{\lambda\mu}_0(soc_0)
          - \bar P \sum_k \gamma^k (\lambda_k + \mu_k),

where ``V^{lambda mu}`` is the single-battery DP with the extra stage cost ``lambda_k a^+ +
mu_k a^-`` on the commanded power (the batteries then decouple; a battery's policy gains
nothing from the others' states, whose noise is independent of its own). The per-battery
bound ``|a| <= min(U_bar, P_bar)`` is kept. ``D`` is concave and piecewise linear; its
supergradient is ``gamma^k (n E[a_k^+] - P_bar)`` (and the same with ``a^-``), the
expectation under the relaxed optimal policy, computed exactly by pushing the distribution
of the grid model (:mod:`mpcrl_lite.bounds.causal.dp`) forward through the day. Each day's ``D`` is
maximised by L-BFGS-B from ``lambda = mu = 0``; the best point seen is kept (every point is a
bound). On the paper's month it stops within about 0.02 NOK/day of the maximum (3 000
projected supergradient steps from its point gained at most that). ``lambda = mu = 0`` drops
the coupling: ``n`` independent batteries.

How the grids keep it a bound
-----------------------------
Weak duality needs the relaxed problem solved exactly. On the soc grid and action step of
:func:`mpcrl_lite.bounds.causal.dp.causal_optimum` the single-battery DP is the exact relaxation of the
same grid model (same node rounding, same action set per battery), so ``D <= J_star`` holds to
rounding for every multiplier -- which the tests check. Against the true system (continuous
soc) ``D`` is a bound up to the grid model's own error, which vanishes as the grid is refined;
one battery is cheap, so the bound can be recomputed on far finer grids (``grid=121``, or 241
with ``action_step=0.05``) to show it has converged (``benchmarks/bench_causal.py``).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize

from ...config import PER_BATTERY, ConfigWarning, SystemConfig
from ...system.battery import unchecked_penalty
from ...system.prices import Prices
from .grid import SocGrid, day_prices, distinct_days

__all__ = ["LagrangianBound", "dual_function", "lagrangian_bound"]


class _SingleBattery:
    """The single-battery DP with multipliers on one grid, and its forward distribution."""

    def __init__(self, system: SystemConfig, grid: SocGrid) -> None:
        self.system, self.grid = system, grid
        G, M = grid.points, grid.M
        reach = min(M, grid.B)  # one battery alone may not exceed the grid limit either
        self.allowed = np.abs(grid.steps) <= reach
        self.post = grid.r * np.arange(G)[:, None] + grid.steps[None, :] + M  # (G, 2M+1)
        self.discount = system.gamma ** np.arange(system.hours_per_day)
        # hour 0 starts at soc0, which need not be a node: its post-decision states and costs
        soc0 = np.array([[system.soc0]])
        self.pen0 = float(unchecked_penalty(soc0, system)[0, 0])
        # post-grid coordinates of soc0's post-decision states; E[V_1] there is interpolated
        # between post-grid nodes, as in the coupled DP, and so is the next distribution
        self.coord0 = system.soc0 / grid.h_y + grid.steps + M
        base = np.minimum(np.floor(self.coord0).astype(np.int64), grid.post_nodes.size - 2)
        frac = (self.coord0 - base)[:, None]
        self.w0 = (1.0 - frac) * grid.weights[base] + frac * grid.weights[base + 1]

    def evaluate(self, buy: np.ndarray, sell: np.ndarray, lam: np.ndarray,
                 mu: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """``D`` of one day and its supergradient in ``lam`` and ``mu`` (each ``(H,)``)."""
        s, g = self.system, self.grid
        H, n, gamma = s.hours_per_day, s.n, s.gamma
        choice = np.empty((H, g.points), dtype=np.int64)
        ev = np.zeros(g.post_nodes.size)
        for k in range(H - 1, 0, -1):
            q = g.stage_cost(buy[k], sell[k], lam[k], mu[k]) + gamma * ev[self.post]
            q[:, ~self.allowed] = np.inf
            choice[k] = np.argmin(q, axis=1)
            v = g.penalty + q[np.arange(g.points), choice[k]]
            ev = g.weights @ v
        # hour 0 at soc0: E[V_1] of post-decision states off the nodes is the interpolant
        ev0 = np.interp(self.coord0, np.arange(ev.size), ev)
        q0 = (g.cost_at(np.array([[s.soc0]]), buy[0], sell[0])[0, 0]
              + lam[0] * np.maximum(g.actions, 0.0) + mu[0] * np.maximum(-g.actions, 0.0)
              + gamma * ev0)
        q0[~self.allowed] = np.inf
        t0 = int(np.argmin(q0))
        value = n * (self.pen0 + q0[t0]) - s.P_bar * float(self.discount @ (lam + mu))
        # forward: expected commanded powers of the relaxed policy in the grid model
        buy_power, sell_power = np.empty(H), np.empty(H)
        buy_power[0], sell_power[0] = max(g.actions[t0], 0.0), max(-g.actions[t0], 0.0)
        dist = self.w0[t0]
        for k in range(1, H):
            a = g.actions[choice[k]]
            buy_power[k] = dist @ np.maximum(a, 0.0)
            sell_power[k] = dist @ np.maximum(-a, 0.0)
            if k < H - 1:
                post = self.post[np.arange(g.points), choice[k]]
                dist = np.bincount(post, weights=dist, minlength=g.post_nodes.size) @ g.weights
        return (value, self.discount * (n * buy_power - s.P_bar),
                self.discount * (n * sell_power - s.P_bar))


def battery_groups(system: SystemConfig) -> list[SystemConfig]:
    """The groups of identical batteries of ``system`` (:meth:`SystemConfig.battery_groups`),
    each as a system of its own batteries (``n`` of them, the group's scalar parameters, the
    site's grid limit); ``[system]`` itself when every per-battery field is one scalar."""
    labels = system.battery_groups()
    if not any(isinstance(getattr(system, name), tuple) for name in PER_BATTERY):
        return [system]
    out = []
    for g in range(max(labels) + 1):
        first = labels.index(g)
        own = {name: system.battery(name)[first] for name in PER_BATTERY}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConfigWarning)
            out.append(system.replace(n=labels.count(g), **own))
    return out


class _Site:
    """The sum of the groups' relaxed problems: ``D = sum_g n_g V_g - P_bar sum_k gamma^k
    (lambda_k + mu_k)`` (each group's own DP on its own grid), and its supergradient."""

    def __init__(self, groups: list[_SingleBattery]) -> None:
        self.groups = groups

    def evaluate(self, buy: np.ndarray, sell: np.ndarray, lam: np.ndarray,
                 mu: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        if len(self.groups) == 1:
            return self.groups[0].evaluate(buy, sell, lam, mu)
        # every group's evaluate subtracts the grid term once; it counts once in the sum
        extra = len(self.groups) - 1
        first = self.groups[0]
        P = first.system.P_bar
        value = extra * P * float(first.discount @ (lam + mu))
        d_lam, d_mu = extra * P * first.discount, extra * P * first.discount
        for group in self.groups:
            v, gl, gm = group.evaluate(buy, sell, lam, mu)
            value, d_lam, d_mu = value + v, d_lam + gl, d_mu + gm
        return value, d_lam, d_mu


def dual_function(
    system: SystemConfig, grid: SocGrid, buy: np.ndarray, sell: np.ndarray,
    lam: np.ndarray, mu: np.ndarray,
) -> tuple[float, np.ndarray, np.ndarray]:
    """The dual function ``D(lambda, mu)`` of one day and a supergradient.

    Parameters
    ----------
    system : SystemConfig
    grid : SocGrid
    buy, sell : numpy.ndarray, shape ``(H,)``
        The day's prices.
    lam, mu : numpy.ndarray, shape ``(H,)``
        Non-negative multipliers of the buying and selling sides of the grid limit.

    Returns
    -------
    D : float
        A lower bound on the day's causal optimum in the grid model (module docstring).
    d_lam, d_mu : numpy.ndarray, shape ``(H,)``
        ``gamma^k (n E[a_k^+] - P_bar)`` and ``gamma^k (n E[a_k^-] - P_bar)``.
    """
    H = system.hours_per_day
    arrays = [np.asarray(x, dtype=float) for x in (buy, sell, lam, mu)]
    for name, x in zip(("buy", "sell", "lam", "mu"), arrays, strict=True):
        if x.shape != (H,) or not np.all(np.isfinite(x)):
            raise ValueError(f"{name}: expected {H} finite values, got shape {x.shape}")
    if np.any(arrays[2] < 0) or np.any(arrays[3] < 0):
        raise ValueError("lam, mu: expected non-negative multipliers")
    return _SingleBattery(system, grid).evaluate(*arrays)


@dataclass(frozen=True, eq=False)
class LagrangianBound:
    """The dual bound of every day (:func:`lagrangian_bound`).

    Attributes
    ----------
    system : SystemConfig
    grid : SocGrid
    J_bound_per_day : numpy.ndarray, shape ``(days,)``
        ``max D`` found for each day.
    J_relaxed_per_day : numpy.ndarray, shape ``(days,)``
        ``D(0, 0)``: ``n`` batteries without the grid limit.
    multipliers_buy, multipliers_sell : numpy.ndarray, shape ``(days, H)``
        The maximising ``lambda``, ``mu`` (NOK/MWh of commanded power, at hour ``k``).
    evaluations : numpy.ndarray, shape ``(days,)``
        Evaluations of ``D`` per day.
    wall_time_s : float
    """

    system: SystemConfig
    grid: SocGrid
    J_bound_per_day: np.ndarray
    J_relaxed_per_day: np.ndarray
    multipliers_buy: np.ndarray
    multipliers_sell: np.ndarray
    evaluations: np.ndarray
    wall_time_s: float
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def J_bound(self) -> float:
        """Mean of :attr:`J_bound_per_day`: a lower bound on ``J^star``, NOK/day."""
        return float(self.J_bound_per_day.mean())

    @property
    def J_relaxed(self) -> float:
        """Mean of :attr:`J_relaxed_per_day` (the coupling dropped)."""
        return float(self.J_relaxed_per_day.mean())

    def summary(self) -> dict[str, Any]:
        """JSON-friendly figures."""
        return {"J_bound": self.J_bound, "J_relaxed": self.J_relaxed,
                "J_bound_per_day": self.J_bound_per_day.tolist(),
                "grid": self.grid.describe(), "evaluations": int(self.evaluations.sum()),
                "wall_time_s": self.wall_time_s, **self.info}


def lagrangian_bound(
    system: SystemConfig,
    prices: Prices | None = None,
    grid: int = 41,
    action_step: float = 0.1,
    max_iter: int = 300,
) -> LagrangianBound:
    """Maximise the dual function of every day (module docstring).

    Parameters
    ----------
    system : SystemConfig
        Any ``n``; batteries that differ (per-battery parameters) are relaxed group by group
        of identical batteries (:func:`battery_groups`), each on its own soc grid.
    prices : Prices, optional
        Default :meth:`Prices.default`. Days with equal prices are solved once.
    grid : int, default 41
        Soc nodes (:class:`~mpcrl_lite.bounds.causal.grid.SocGrid`); the defaults are those of
        :func:`~mpcrl_lite.bounds.causal.dp.causal_optimum`, for which ``D <= J_star`` is exact.
    action_step : float, default 0.1
    max_iter : int, default 300
        L-BFGS-B iterations per day.

    Returns
    -------
    LagrangianBound
    """
    buy, sell = day_prices(system, prices)
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 0:
        raise ValueError(f"max_iter={max_iter!r}: expected an integer >= 0")
    groups = battery_groups(system)
    soc_grid = SocGrid(groups[0], grid, action_step)
    battery = _Site([_SingleBattery(g, soc_grid if i == 0 else SocGrid(g, grid, action_step))
                     for i, g in enumerate(groups)])
    H = system.hours_per_day
    t0 = time.perf_counter()
    first, day_of = distinct_days(buy, sell)
    best = np.empty(first.size)
    relaxed = np.empty(first.size)
    lam_best = np.zeros((first.size, 2 * H))
    count = np.zeros(first.size, dtype=np.int64)
    for u, d in enumerate(first):
        record = {"value": -np.inf, "x": np.zeros(2 * H), "calls": 0}

        def negative(x: np.ndarray, d: int = d, record: dict = record) -> tuple[float, np.ndarray]:
            x = np.maximum(x, 0.0)  # L-BFGS-B keeps the bounds; rounding may not
            value, g_lam, g_mu = battery.evaluate(buy[d], sell[d], x[:H], x[H:])
            record["calls"] += 1
            if value > record["value"]:
                record["value"], record["x"] = value, x.copy()
            return -value, -np.concatenate([g_lam, g_mu])

        relaxed[u] = -negative(np.zeros(2 * H))[0]
        if max_iter > 0:
            minimize(negative, np.zeros(2 * H), jac=True, method="L-BFGS-B",
                     bounds=[(0.0, None)] * (2 * H),
                     options={"maxiter": max_iter, "ftol": 1e-12, "gtol": 1e-9})
        best[u], lam_best[u], count[u] = record["value"], record["x"], record["calls"]
    return LagrangianBound(
        system, soc_grid, best[day_of], relaxed[day_of], lam_best[day_of, :H],
        lam_best[day_of, H:], count[day_of], time.perf_counter() - t0,
        {"distinct_days": int(first.size), "max_iter": int(max_iter)})
