r"""The computations behind the classroom explorers: one day in closed loop, one MPC input
swept, one value fit, and the MPC solvers they share.

Each function returns data (a :class:`~mpcrl_lite.sim.record.Record`, a dict of arrays); the
explorers of :mod:`mpcrl_lite.classroom.widgets` call them on every slider release, the notebooks call
them directly, and :mod:`mpcrl_lite.figures.plots` draws what they return. Nothing is simulated here
that the package does not simulate elsewhere: days run through the one closed loop
(:func:`mpcrl_lite.sim.closed_loop.run_month` for the MPC, :func:`~mpcrl_lite.sim.closed_loop.rollout`
for a rule), and value fits use the critic's features
(:func:`mpcrl_lite.learning.lstd.value_baseline_features`) and :func:`~mpcrl_lite.learning.lstd.lstd_v`.

How the MPC is solved comes from :class:`~mpcrl_lite.config.MPCConfig`: by default the
package's ``MPCConfig()`` (``tau = 0.1``, the learning setting); ``mpc_config`` replaces it,
and the ``tau`` and ``backend`` arguments override single fields. Solvers are built once per
MPC formulation and config (:func:`cached_solver`).

============================  =============================================================
function                      returns
============================  =============================================================
:func:`price_window`          the forecast window the MPC sees at one hour of one day
:func:`threshold_rule`        a price-threshold rule, as a policy for the closed loop
:func:`rule_day`              one day of the true system under that rule
:func:`simulate_day`          one day of the MPC in closed loop
:func:`policy_curve`          the MPC policy as a function of one input
:func:`value_fit`             an LSTD value fit of a record next to its Monte-Carlo returns
:func:`cached_solver`         a solver for a system's MPC and an MPCConfig, built once
============================  =============================================================
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import PRICE_UNIT, VALUE_FEATURE_SETS, ConfigWarning, MPCConfig, SystemConfig
from ..learning.lstd import (
    LSTDResult,
    lstd_v,
    monte_carlo_returns,
    value_baseline_features,
)
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..mpc.solution import SolverBackend
from ..sim.closed_loop import Policy, rollout, run_month
from ..sim.record import MonthRecord, Record
from ..system.battery import project_action
from ..system.prices import Prices, sell_prices
from ..theta import Theta

__all__ = [
    "POLICY_RANGES",
    "POLICY_VARIABLES",
    "TAUS",
    "DayPrices",
    "cached_solver",
    "policy_curve",
    "price_window",
    "replace_system",
    "resolve_mpc_config",
    "rule_day",
    "simulate_day",
    "threshold_rule",
    "value_fit",
]

#: Barrier parameters offered by the explorers, from strongly smoothed to nearly exact.
TAUS: tuple[float, ...] = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5)

#: Inputs :func:`policy_curve` can sweep, with their axis labels.
POLICY_VARIABLES: dict[str, str] = {
    "theta_s": r"sell-price correction $\theta_s^1$ of agent 1 (" + PRICE_UNIT + ")",
    "soc": r"state of charge $soc^1$ of agent 1",
    "price": r"buying price $\phi_b$ of the current hour (" + PRICE_UNIT + ")",
}
#: The range swept by default for each of :data:`POLICY_VARIABLES` (it shows the switch).
POLICY_RANGES: dict[str, tuple[float, float]] = {
    "theta_s": (-20.0, 20.0),
    "soc": (0.0, 1.0),
    "price": (0.0, 120.0),
}


@dataclass(frozen=True, eq=False)
class DayPrices:
    """One day of a month, with the month's continuation after midnight.

    :func:`mpcrl_lite.sim.closed_loop.run_month` simulates every day of the prices it is given;
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


# -- solvers --------------------------------------------------------------------------------
_SOLVER_CACHE: OrderedDict[tuple, SolverBackend] = OrderedDict()
_SOLVER_CACHE_SIZE = 24


def resolve_mpc_config(
    mpc_config: MPCConfig | float | None = None, tau: float | None = None,
    backend: str | None = None,
) -> MPCConfig:
    """The MPC settings: ``mpc_config`` (default ``MPCConfig()``) with ``tau`` and ``backend``
    replaced where given.

    A number in place of ``mpc_config`` is a barrier ``tau`` (the older calls
    ``cached_solver(system, tau, backend)``).
    """
    if mpc_config is not None and not isinstance(mpc_config, MPCConfig):
        if isinstance(mpc_config, bool) or not isinstance(mpc_config, (int, float)):
            raise ValueError(f"mpc_config={mpc_config!r}: expected an MPCConfig (or a tau)")
        if tau is not None:
            raise ValueError(f"tau given twice ({mpc_config!r} and tau={tau!r}): expected one")
        mpc_config, tau = None, float(mpc_config)
    config = MPCConfig() if mpc_config is None else mpc_config
    changes = {k: v for k, v in (("tau", tau), ("backend", backend)) if v is not None}
    return config.replace(**changes) if changes else config


def _mpc_key(system: SystemConfig) -> tuple:
    """The fields of ``system`` that the MPC formulation depends on (not noise or prices)."""
    return (
        system.n, system.N, system.U_bar, system.P_bar, system.omega, system.omega_f,
        system.soc_low, system.soc_high, system.gamma,
    )


def cached_solver(
    system: SystemConfig, mpc_config: MPCConfig | float | None = None,
    backend: str | None = None, *, tau: float | None = None,
) -> SolverBackend:
    """A solver for ``system``'s MPC solved as ``mpc_config`` says, built once, then reused.

    The MPC's formulation depends on ``n``, ``N``, the bounds ``U_bar``, ``P_bar``, the slack
    weights, the soc band and ``gamma``; the noise and the prices enter only as data, so
    changing them never rebuilds anything. The cache is keyed on those fields and on the
    whole :class:`~mpcrl_lite.config.MPCConfig` (tolerance, iteration limit, ... included);
    the most recent 24 solvers are kept.

    Parameters
    ----------
    system : SystemConfig
    mpc_config : MPCConfig, optional
        Default ``MPCConfig()``; a number is taken as ``tau`` (older calls).
    backend : str, optional
        Replaces ``mpc_config.backend`` (a name of :data:`mpcrl_lite.config.BACKENDS`).
    tau : float, optional
        Replaces ``mpc_config.tau``.

    Returns
    -------
    SolverBackend
        ``solve_batch`` and ``sensitivity`` (see :mod:`mpcrl_lite.mpc.backends.registry`).
    """
    config = resolve_mpc_config(mpc_config, tau, backend)
    key = (_mpc_key(system), config)
    solver = _SOLVER_CACHE.get(key)
    if solver is None:
        solver = make_solver(MPC(system), config)
        _SOLVER_CACHE[key] = solver
        while len(_SOLVER_CACHE) > _SOLVER_CACHE_SIZE:
            _SOLVER_CACHE.popitem(last=False)
    else:
        _SOLVER_CACHE.move_to_end(key)
    return solver


def replace_system(system: SystemConfig, **changes: Any) -> SystemConfig:
    """``system.replace(**changes)`` without the warning that a large ``P_bar`` never binds
    (the explorers offer such values on purpose)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return system.replace(**changes)


# -- prices and a rule ----------------------------------------------------------------------
def price_window(prices: Prices, day: int, hour: int, N: int) -> dict[str, np.ndarray]:
    """``{'buy': (N,), 'sell': (N,)}``: the forecast the MPC sees at ``hour`` of ``day``
    (:meth:`Prices.window`, reading on into the next day after midnight)."""
    if not 0 <= int(day) < prices.days:
        raise ValueError(f"day={day!r}: expected an integer in [0, {prices.days})")
    buy, sell = prices.window(int(hour), int(N))
    return {"buy": buy[int(day)], "sell": sell[int(day)]}


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
    (:func:`mpcrl_lite.system.battery.project_action`), which shares it equally.

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
        For :func:`mpcrl_lite.sim.closed_loop.rollout` (or ``closed_loop.simulate``).
    """
    buy = np.asarray(buy, dtype=float)

    def policy(hour: int, soc: np.ndarray) -> np.ndarray:
        price = buy[:, hour][:, None]
        a = np.where((price <= buy_below) & (soc < soc_max), system.U_bar, 0.0)
        a = np.where((price >= sell_above) & (soc > soc_min), -system.U_bar, a)
        return project_action(a, system)

    return policy


def rule_day(
    system: SystemConfig | None = None, day: int = 0, seed: int = 0, buy_below: float = 20.0,
    sell_above: float = 60.0, soc_min: float = 0.3, soc_max: float = 0.7,
    prices: Prices | None = None,
) -> Record:
    """One day of the true system under :func:`threshold_rule` (a record with ``D = 1``).

    ``prices`` default :meth:`Prices.default` for ``system``; the noise is drawn from
    ``numpy.random.default_rng(seed)``, so a seed gives the same noise whatever the rule.
    """
    system = SystemConfig() if system is None else system
    month = Prices.default(system) if prices is None else prices
    if not 0 <= int(day) < month.days:
        raise ValueError(f"day={day!r}: expected an integer in [0, {month.days})")
    buy, sell = month.buy[day : day + 1], month.sell[day : day + 1]
    rule = threshold_rule(buy, buy_below, sell_above, system, soc_min, soc_max)
    return rollout(rule, buy, sell, system, np.random.default_rng(seed))


# -- the MPC --------------------------------------------------------------------------------
def simulate_day(
    system: SystemConfig | None = None,
    day: int = 0,
    seed: int = 0,
    theta: Theta | None = None,
    tau: float | None = None,
    backend: str | None = None,
    prices: Prices | None = None,
    *,
    mpc_config: MPCConfig | None = None,
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
    tau, backend : optional
        Override ``mpc_config.tau`` and ``mpc_config.backend``.
    prices : Prices, optional
        The month, default :meth:`Prices.default` for ``system`` (with its price scale).
    mpc_config : MPCConfig, optional
        How the MPC is solved, default ``MPCConfig()``.

    Returns
    -------
    MonthRecord
        A month of one day (arrays with ``D = 1``).
    """
    system = SystemConfig() if system is None else system
    month = Prices.default(system) if prices is None else prices
    theta = Theta.nominal(system) if theta is None else theta
    solver = cached_solver(system, resolve_mpc_config(mpc_config, tau, backend))
    view = DayPrices(month, int(day))
    return run_month(theta, solver, view, system, np.random.default_rng(seed),
                     exploration_std=0.0, sensitivities=False)


def policy_curve(
    variable: str = "theta_s",
    values: Sequence[float] | np.ndarray | None = None,
    tau: float | None = None,
    system: SystemConfig | None = None,
    theta: Theta | None = None,
    soc: Sequence[float] | np.ndarray | None = None,
    hour: int = 0,
    day: int = 0,
    backend: str | None = None,
    prices: Prices | None = None,
    *,
    mpc_config: MPCConfig | None = None,
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
        The values of ``variable``; default 41 points over :data:`POLICY_RANGES`.
    tau, backend : optional
        Override ``mpc_config.tau`` and ``mpc_config.backend``.
    system, theta, prices
        Defaults: ``SystemConfig()``, theta0, the shipped month.
    soc : array, shape ``(n,)``, optional
        The state; default ``system.soc0`` for every battery.
    hour, day : int
        Where the forecast window is taken from.
    mpc_config : MPCConfig, optional
        How the MPC is solved, default ``MPCConfig()``.

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
        values = np.linspace(*POLICY_RANGES[variable], 41)
    x = np.asarray(values, dtype=float).reshape(-1)
    state = np.full(system.n, system.soc0) if soc is None else np.asarray(soc, float).copy()
    buy, sell = month.window(int(hour), system.N)
    buy, sell = buy[int(day)], sell[int(day)]
    config = resolve_mpc_config(mpc_config, tau, backend)
    solver = cached_solver(system, config)
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
            sells[:, 0] = sell_prices(x, month.sell_ratio)
        sol = solver.solve_batch(socs, buys, sells, theta)
        actions, success = np.array(sol.action), np.array(sol.success)
    actions = np.where(success[:, None], actions, np.nan)
    return {
        "x": x, "policy": actions, "success": success, "variable": variable,
        "tau": float(config.tau), "label": POLICY_VARIABLES[variable],
    }


# -- values ---------------------------------------------------------------------------------
def value_fit(record: Record, features: str = "paper", days: int | None = None,
              gamma: float | None = None) -> dict[str, Any]:
    """LSTD value of the policy that generated ``record``, next to its Monte-Carlo returns.

    Each day is an episode (its last hour does not bootstrap), as in the learning loop, and
    the features are the critic's (:func:`mpcrl_lite.learning.lstd.value_baseline_features`).

    Parameters
    ----------
    record : Record
        Transitions ``(soc_k, L~_k, soc_{k+1})`` of ``H`` hours and ``D`` days.
    features : str
        A key of :data:`mpcrl_lite.config.VALUE_FEATURE_SETS`.
    days : int, optional
        Use only the first ``days`` days (default all).
    gamma : float, optional
        Discount factor (default ``record.system.gamma``).

    Returns
    -------
    dict
        ``fit`` (:class:`~mpcrl_lite.learning.lstd.LSTDResult`), ``V`` and ``G`` (H, days): the fitted
        value at every visited state and the Monte-Carlo return from it, ``rmse`` and ``r2``
        of ``V`` against ``G``, ``features``, ``gamma``, ``days``.
    """
    if features not in VALUE_FEATURE_SETS:
        raise ValueError(f"features={features!r}: expected one of {list(VALUE_FEATURE_SETS)}")
    H, D = record.stage_cost.shape
    days = D if days is None else int(days)
    if not 1 <= days <= D:
        raise ValueError(f"days={days!r}: expected an integer in [1, {D}]")
    gamma = record.system.gamma if gamma is None else float(gamma)
    phi_all = value_baseline_features(record.soc[:, :days], features,  # (H + 1, days, m)
                                      record.buy[:, :days])
    phi, phi_next = phi_all[:-1], phi_all[1:]
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], (H, days))
    cost = record.stage_cost[:, :days]
    fit: LSTDResult = lstd_v(phi, cost, phi_next, gamma, done=done)
    V = fit.value(phi)
    G = monte_carlo_returns(cost, gamma)
    rmse = float(np.sqrt(np.mean((V - G) ** 2)))
    r2 = float(1.0 - np.sum((V - G) ** 2) / np.sum((G - G.mean()) ** 2))
    return {"fit": fit, "V": V, "G": G, "rmse": rmse, "r2": r2, "features": features,
            "gamma": gamma, "days": days}
