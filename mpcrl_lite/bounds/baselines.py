r"""Baselines: what the learned MPC is measured against, on exactly the same draws.

Every policy is evaluated on one common :class:`Scenario` -- the same days, prices and noise
draws -- with the true dynamics, the low-level controller and the true cost :math:`\tilde L`
(penalties included) of :mod:`mpcrl_lite.system.battery`:

* **clairvoyant** (:func:`clairvoyant`) -- knows each day's noise and prices in advance and
  optimizes the true cost over the day: a linear program per day, a *lower bound* on the cost
  of every policy on these draws (see below);
* **nominal** -- the MPC at :math:`\theta_0` (:meth:`Theta.nominal`), never learning;
* **rule_based** (:class:`RuleBasedPolicy`) -- charge below the day's median price,
  discharge above it, at full power within the bounds and the grid limit;
* **learned** -- the MPC at any given theta, e.g. :meth:`History.final_theta
  <mpcrl_lite.learning.history.History.final_theta>`.
* **causal_dp** (``causal=True``) -- the best causal policy of :mod:`mpcrl_lite.bounds.causal.dp`, a
  dynamic program over the day; every policy is then also reported against its optimum
  :math:`J^\star`: the regret :math:`J - J^\star` and the share of the nominal-to-:math:`J^\star`
  gap closed.

Reported per policy: :math:`J` and :math:`J^i` (discounted daily cost, mean over days), the
hours with soc below 0.1, grid powers, low-level interventions; and, for every learned theta,
the share of the nominal-to-clairvoyant gap closed by learning,
:math:`(J_{nominal} - J_{learned}) / (J_{nominal} - J_{clairvoyant})`.

The clairvoyant lower bound
---------------------------
For one day with known noise :math:`\Delta_{k,i}` and prices (hours :math:`k = 0..23`,
batteries :math:`i`, :math:`soc_{0,i}` given), the clairvoyant splits the applied powers
into a *commanded* part, bound by the input bounds and the grid limit, and the low-level
controller's *extra* power, which is not:

.. math::
   \min \sum_k \gamma^k \sum_i \Big[\phi_{b,k}(u^b_{k,i} + e^b_{k,i})
        - \phi_{s,k}(u^s_{k,i} + e^s_{k,i}) + p\,(\epsilon^{hi}_{k,i} + \epsilon^{lo}_{k,i})\Big]

subject to

.. math::
   soc_{k+1,i} &= soc_{k,i} + \alpha\big(\Delta_{k,i} + u^b_{k,i} + e^b_{k,i}
                 - u^s_{k,i} - e^s_{k,i}\big), \qquad 0 \le soc_{k,i} \le 1, \\
   0 \le u^b_{k,i}, u^s_{k,i} &\le \bar U, \qquad
   \textstyle\sum_i u^b_{k,i} \le \bar P,\quad \sum_i u^s_{k,i} \le \bar P, \\
   \epsilon^{hi}_{k,i} &\ge soc_{k,i} - 0.9,\quad \epsilon^{lo}_{k,i} \ge 0.1 - soc_{k,i},
   \quad \epsilon \ge 0 \quad (k \ge 1;\ \text{the penalty at } soc_0 \text{ is a constant}),

and the controller's reach, with :math:`m^b = \max(-\Delta, 0)`, :math:`m^s = \max(\Delta, 0)`:

.. math::
   0 \le e^b_{k,i} \le m^b_{k,i}\,\min\big(1 - soc_{k+1,i},\
       \epsilon^{lo}_{k+1,i}/0.1,\ \ell^b(soc_{k,i})\big), \qquad
   0 \le e^s_{k,i} \le m^s_{k,i}\,\min\big(soc_{k+1,i},\
       \epsilon^{hi}_{k+1,i}/0.1,\ \ell^s(soc_{k,i})\big),

where :math:`\ell` is the chord of the reach over :math:`soc_k \in [0, 1]` (the penalty
link is left out in the last hour, whose end state is not charged). It is a linear program,
solved per day with HiGHS.

**Why it is a lower bound.** Take any policy -- causal or not -- whose commanded action
:math:`a` obeys the input bounds and the grid limit (the evaluation projects every command,
see :func:`evaluate_policy`; for the MPCs and the rule this changes nothing). The low-level
controller leaves :math:`a` alone unless soc would leave :math:`[0, 1]`. If soc would fall
below 0, it raises the net power to :math:`-soc_k/\alpha - \Delta` and the battery ends the
hour *empty*; if soc would exceed 1, it lowers it to :math:`(1 - soc_k)/\alpha - \Delta` and
the battery ends *full*. So with :math:`u^b = \min(b, a^+)`, :math:`e^b = b - u^b` (and the
same for selling) for the applied powers :math:`b, s`: the commanded parts obey the bounds
and the grid limit; :math:`e^b > 0` only when :math:`soc_{k+1} = 0`, and then
:math:`e^b \le b \le \max(-soc_k/\alpha - \Delta, 0) \le m^b`, :math:`1 - soc_{k+1} = 1`
and :math:`\epsilon^{lo}_{k+1} = 0.1`; :math:`e^s > 0` only when :math:`soc_{k+1} = 1`,
symmetrically. Every reach constraint therefore holds, the soc trajectory (in
:math:`[0, 1]`) follows the dynamics with the applied powers, and with the exact penalties as
:math:`\epsilon` the LP objective equals the closed loop's discounted cost: the closed loop
of any such policy is a feasible point, and the LP optimum is at most its cost on *every*
day of the scenario.

Giving the clairvoyant the controller's extra power is necessary (a closed loop's applied
grid power exceeds :math:`\bar P` when the noise is large, so without it the closed loops
would not be feasible points and the "bound" could fail), but it is the extra power the
controller can really give -- tied to an empty or full battery and to the penalty that comes
with it -- not an unbounded corrective power, so the bound stays tight:
:attr:`ClairvoyantResult.J_replayed`, the cost of replaying the plan in closed loop, is an
achievable cost, and on the paper's system it lies within ~0.5 % of the bound.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from ..config import LearningConfig, MPCConfig, SystemConfig
from ..learning import rundir
from ..learning.history import History
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..sim.closed_loop import MPCPolicy, Policy, simulate
from ..sim.exploration import Projection
from ..sim.record import Record
from ..system.battery import penalty, project_action, sample_noise
from ..system.forecast import forecast_prices
from ..system.prices import Prices
from ..theta import Theta
from .causal.dp import CausalBound, causal_optimum, compare_with_optimum

__all__ = ["ClairvoyantResult", "PolicyResult", "RuleBasedPolicy", "Scenario", "clairvoyant", "clairvoyant_lp", "evaluate_baselines", "evaluate_policy", "make_scenario", "run_baselines_cli"]

# -- the common scenario ----------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Scenario:
    """The days, prices and noise every policy is evaluated on.

    Attributes
    ----------
    system : SystemConfig
    prices : Prices
        ``prices.days`` days; the MPCs' forecast windows run past midnight into the next day
        (cyclically), as in the learning experiment.
    noise : numpy.ndarray, shape ``(hours, days, n)``
        :math:`\\Delta_{k}` of every hour, day and battery.
    soc0 : numpy.ndarray, shape ``(days, n)``
        State of charge at the start of each day.
    seed : int or None
        Seed the noise was drawn with (None for a user-given array).
    """

    system: SystemConfig
    prices: Prices
    noise: np.ndarray
    soc0: np.ndarray
    seed: int | None = None

    def __post_init__(self) -> None:
        sysc = self.system
        # bad input of any kind is a ValueError in this package, wrong types included
        if not isinstance(sysc, SystemConfig):
            raise ValueError(f"system={sysc!r}: expected a SystemConfig")  # noqa: TRY004
        if not isinstance(self.prices, Prices):
            raise ValueError(f"prices={self.prices!r}: expected a Prices")  # noqa: TRY004
        shape = (sysc.hours_per_day, self.prices.days, sysc.n)
        noise = np.array(self.noise, dtype=float)
        if noise.shape != shape:
            raise ValueError(f"noise has shape {noise.shape}: expected (hours, days, n) = {shape}")
        if not np.all(np.isfinite(noise)):
            raise ValueError("noise: expected finite values only")
        soc0 = np.broadcast_to(np.asarray(self.soc0, dtype=float), shape[1:]).copy()
        if np.any((soc0 < 0) | (soc0 > 1)):
            raise ValueError(f"soc0={soc0.tolist()}: expected states of charge in [0, 1]")
        for arr in (noise, soc0):
            arr.setflags(write=False)
        object.__setattr__(self, "noise", noise)
        object.__setattr__(self, "soc0", soc0)

    @property
    def days(self) -> int:
        """Number of days."""
        return self.prices.days

    @property
    def buy(self) -> np.ndarray:
        """Buying prices of each day and hour, shape ``(days, hours)``."""
        return self.prices.buy[:, : self.system.hours_per_day]

    @property
    def sell(self) -> np.ndarray:
        """Selling prices of each day and hour, shape ``(days, hours)``."""
        return self.prices.sell[:, : self.system.hours_per_day]

    def describe(self) -> dict[str, Any]:
        """JSON-friendly description."""
        return {
            "days": self.days,
            "seed": self.seed,
            "prices": self.prices.source,
            "noise_shape": list(self.noise.shape),
            "noise_mean": float(self.noise.mean()),
            "noise_std": float(self.noise.std()),
            "soc0": float(self.soc0.mean()),
        }


def make_scenario(
    system: SystemConfig, days: int, seed: int, prices: Prices | None = None
) -> Scenario:
    """Draw a scenario: ``days`` days of prices (default :meth:`Prices.month`) and noise.

    The noise is ``sample_noise(numpy.random.default_rng(seed), (hours, days, n))``
    (:func:`mpcrl_lite.system.battery.sample_noise`), which is the noise
    :func:`mpcrl_lite.sim.closed_loop.run_month` draws from a generator with that seed when there
    is no exploration (it draws ``(days, n)`` hour by hour from the same stream).

    Parameters
    ----------
    system : SystemConfig
    days : int
        At least 1.
    seed : int
        Non-negative seed.
    prices : Prices, optional
        Must have ``days`` days.

    Returns
    -------
    Scenario
    """
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    if isinstance(days, bool) or not isinstance(days, (int, np.integer)) or days < 1:
        raise ValueError(f"days={days!r}: expected an integer >= 1")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed={seed!r}: expected an integer >= 0")
    if prices is None:
        prices = Prices.month(system, int(days))
    elif prices.days != days:
        raise ValueError(f"prices have {prices.days} days; expected days={days}")
    noise = sample_noise(np.random.default_rng(int(seed)),
                         (system.hours_per_day, int(days), system.n), system)
    return Scenario(system, prices, noise, np.full((int(days), system.n), system.soc0), int(seed))


# -- closed-loop evaluation -------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PolicyResult:
    """A policy's closed loop on a scenario, with its name and figures.

    Attributes
    ----------
    name : str
    trajectory : Record
        Hours x days x batteries (:class:`~mpcrl_lite.sim.record.Record`; also :attr:`record`).
    commanded_power : numpy.ndarray, shape ``(hours, days)``
        :math:`\\max(\\sum_i a_i^+, \\sum_i a_i^-)` of the commanded (projected) actions.
    solver_failures : int
        MPC solves that failed (their hour used the idle fallback).
    wall_time_s : float
    info : dict
        Extra JSON-friendly figures (e.g. the clairvoyant's LP status).
    """

    name: str
    trajectory: Record
    commanded_power: np.ndarray
    solver_failures: int = 0
    wall_time_s: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def record(self) -> Record:
        """The closed loop's :class:`~mpcrl_lite.sim.record.Record`."""
        return self.trajectory

    @property
    def J(self) -> float:
        """Mean over days of the discounted daily cost :math:`\\sum_k \\gamma^k \\tilde L_k`."""
        return self.trajectory.J()

    @property
    def J_per_agent(self) -> np.ndarray:
        """:math:`J^i`, shape ``(n,)``."""
        return self.trajectory.J_per_agent()

    @property
    def J_per_day(self) -> np.ndarray:
        """Discounted cost of each day, shape ``(days,)``."""
        return self.trajectory.J_per_day()

    def summary(self) -> dict[str, Any]:
        """The figures of :func:`evaluate_baselines`, JSON-friendly."""
        t = self.trajectory
        return {
            "J": self.J,
            "J_per_agent": self.J_per_agent.tolist(),
            "J_per_day": self.J_per_day.tolist(),
            "hours_soc_below_0_1": t.hours_soc_below(),
            "hours_soc_above_0_9": t.hours_soc_above(),
            "max_P_commanded": float(self.commanded_power.max()),
            "max_P_applied": float(t.grid_power.max()),
            "low_level_interventions": int(np.count_nonzero(np.abs(t.correction) > 1e-12)),
            "solver_failures": int(self.solver_failures),
            "wall_time_s": float(self.wall_time_s),
            **self.info,
        }


def evaluate_policy(policy: Policy, scenario: Scenario, name: str = "policy") -> PolicyResult:
    """Run ``policy`` in closed loop on the scenario's days, hour by hour.

    :func:`mpcrl_lite.sim.closed_loop.simulate` with the scenario's noise (common random
    numbers) and the command projected onto the input bounds and the grid limit
    (:class:`~mpcrl_lite.sim.exploration.Projection`; a no-op for feasible commands such as the
    MPC's): at hour ``k``, ``a = project_action(policy(k, soc))``, then
    :func:`mpcrl_lite.system.battery.step` with ``noise[k]`` and the prices of the hour.

    Parameters
    ----------
    policy : callable ``(hour, soc (days, n)) -> a (days, n)``
        Or a policy with ``decide`` (:class:`~mpcrl_lite.sim.closed_loop.MPCPolicy`), whose
        failed solves are counted.
    scenario : Scenario
    name : str

    Returns
    -------
    PolicyResult
    """
    if not callable(policy):
        raise ValueError(  # noqa: TRY004
            f"policy={policy!r}: expected a callable policy(hour, soc) -> a"
        )
    sysc = scenario.system
    t0 = time.perf_counter()
    record = simulate(policy, scenario.buy, scenario.sell, sysc, noise=scenario.noise,
                      soc0=scenario.soc0, explore=Projection(sysc))
    a = record.a
    commanded = np.maximum(np.maximum(a, 0).sum(-1), np.maximum(-a, 0).sum(-1))
    failures = int(np.count_nonzero(~record.solver_ok))
    return PolicyResult(name, record, commanded, failures, time.perf_counter() - t0)


class RuleBasedPolicy:
    """Charge below the day's median price, discharge above it, at full power.

    At hour ``k`` of day ``d`` with buying price :math:`\\phi_{b,d,k}` and the day's median
    :math:`\\tilde\\phi_d`, every battery commands ``+U_bar`` if
    :math:`\\phi_{b,d,k} < \\tilde\\phi_d`, ``-U_bar`` if above, 0 on a tie (the day-ahead
    market publishes the whole day's prices, so the rule is causal in practice). With
    ``soc_guard`` the command is limited so that the *expected* next soc (noise at its mean)
    stays in ``[soc_low, soc_high]``: charging at most :math:`(soc_{high} - soc)/\\alpha -
    \\bar\\delta`, discharging at most :math:`(soc - soc_{low})/\\alpha + \\bar\\delta`, never
    below 0. The command is then projected onto the input bounds and the grid limit
    (:func:`~mpcrl_lite.system.battery.project_action`: batteries asking for the same direction share
    :math:`\\bar P` by an equal cut).

    Parameters
    ----------
    prices : Prices
    system : SystemConfig
    soc_guard : bool, default True
    """

    def __init__(self, prices: Prices, system: SystemConfig, soc_guard: bool = True) -> None:
        if not isinstance(soc_guard, bool):
            raise ValueError(f"soc_guard={soc_guard!r}: expected True or False")  # noqa: TRY004
        self.prices, self.system, self.soc_guard = prices, system, soc_guard
        self.median = np.median(prices.buy, axis=1)

    def __call__(self, hour: int, soc: np.ndarray) -> np.ndarray:
        sysc = self.system
        price = self.prices.buy[:, hour]
        direction = np.sign(self.median - price)[:, None]  # +1 buy (cheap), -1 sell
        a = np.broadcast_to(direction * sysc.U_bar, soc.shape).copy()
        if self.soc_guard:
            room_up = np.maximum((sysc.soc_high - soc) / sysc.alpha - sysc.noise_mean, 0.0)
            room_down = np.maximum((soc - sysc.soc_low) / sysc.alpha + sysc.noise_mean, 0.0)
            a = np.clip(a, -room_down, room_up)
        return project_action(a, sysc)


# -- the clairvoyant LP -----------------------------------------------------------------------
@dataclass(frozen=True)
class _LPLayout:
    """Variable blocks of one day's LP, flat offsets; each block is ``(rows, n)``."""

    H: int
    n: int

    def sizes(self) -> dict[str, int]:
        H = self.H
        return {"ub": H, "us": H, "eb": H, "es": H, "soc": H, "ehi": H - 1, "elo": H - 1}

    def block(self, name: str) -> np.ndarray:
        start = 0
        for key, rows in self.sizes().items():
            if key == name:
                return start + np.arange(rows * self.n).reshape(rows, self.n)
            start += rows * self.n
        raise KeyError(name)

    @property
    def size(self) -> int:
        return sum(self.sizes().values()) * self.n


def clairvoyant_lp(
    scenario: Scenario, day: int
) -> tuple[np.ndarray, sp.csr_matrix, np.ndarray, sp.csr_matrix, np.ndarray, list, _LPLayout]:
    """The clairvoyant LP of one day as :func:`scipy.optimize.linprog` data.

    Variables (module docstring), each laid out hour-major ``(hours, n)``: commanded parts
    ``ub``, ``us``; the low-level controller's extra powers ``eb``, ``es``; ``soc_1 ..
    soc_H``; penalty epigraphs ``ehi``, ``elo`` of ``soc_1 .. soc_{H-1}`` (``soc_0`` is fixed
    and its penalty a constant; ``soc_H`` is not charged, as in the closed-loop cost).

    Returns
    -------
    c, A_ub, b_ub, A_eq, b_eq, bounds, layout
        ``min c'z`` s.t. ``A_ub z <= b_ub``, ``A_eq z = b_eq`` and ``bounds``; ``layout``
        locates the blocks in ``z``.
    """
    sysc = scenario.system
    valid_day = isinstance(day, (int, np.integer)) and not isinstance(day, bool)
    if not valid_day or not 0 <= day < scenario.days:
        raise ValueError(f"day={day!r}: expected an integer in [0, {scenario.days})")
    H, n, alpha, U = sysc.hours_per_day, sysc.n, sysc.alpha, sysc.U_bar
    lay = _LPLayout(H, n)
    iub, ius, ieb, ies = (lay.block(k) for k in ("ub", "us", "eb", "es"))
    isoc, ihi, ilo = lay.block("soc"), lay.block("ehi"), lay.block("elo")
    noise = scenario.noise[:, day, :]  # (H, n)
    disc = sysc.gamma ** np.arange(H)
    c = np.zeros(lay.size)
    for var, price in ((iub, scenario.buy[day]), (ieb, scenario.buy[day])):
        c[var] = (disc * price)[:, None]
    for var, price in ((ius, scenario.sell[day]), (ies, scenario.sell[day])):
        c[var] = -(disc * price)[:, None]
    c[ihi] = c[ilo] = sysc.p * disc[1:, None]

    def sparse(terms: list[tuple[np.ndarray, np.ndarray, Any]], rows: int) -> sp.csr_matrix:
        r = np.concatenate([t[0].ravel() for t in terms])
        col = np.concatenate([t[1].ravel() for t in terms])
        v = np.concatenate([np.broadcast_to(t[2], t[0].shape).ravel() for t in terms])
        return sp.csr_matrix((v, (r, col)), shape=(rows, lay.size))

    # dynamics: soc_{k+1} - soc_k - alpha (ub + eb - us - es)_k = alpha Delta_k
    r = np.arange(H * n).reshape(H, n)
    A_eq = sparse([(r, isoc, 1.0), (r, iub, -alpha), (r, ieb, -alpha), (r, ius, alpha),
                   (r, ies, alpha), (r[1:], isoc[:-1], -1.0)], H * n)
    b_eq = alpha * noise.ravel()
    b_eq[:n] += scenario.soc0[day]

    terms: list[tuple[np.ndarray, np.ndarray, Any]] = []
    rhs: list[np.ndarray] = []
    count = 0

    def row(shape: tuple[int, ...]) -> np.ndarray:
        nonlocal count
        index = count + np.arange(int(np.prod(shape))).reshape(shape)
        count += index.size
        return index

    # grid limit on the commanded parts
    for var in (iub, ius):
        g = row((H,))
        terms.append((np.repeat(g, n).reshape(H, n), var, 1.0))
        rhs.append(np.full(H, sysc.P_bar))
    # the controller's reach: extra buying only down at soc_{k+1} = 0, extra selling only up
    # at soc_{k+1} = 1, at most the noise it compensates
    m_buy, m_sell = np.maximum(-noise, 0.0), np.maximum(noise, 0.0)
    soc_prev = (isoc[:-1], scenario.soc0[day])  # soc_k for k >= 1 (variables), soc_0 fixed
    for extra, m, sign in ((ieb, m_buy, 1.0), (ies, m_sell, -1.0)):
        # eb <= m (1 - soc_{k+1});  es <= m soc_{k+1}
        q = row((H, n))
        terms += [(q, extra, 1.0), (q, isoc, sign * m)]
        rhs.append((m if sign > 0 else np.zeros_like(m)).ravel())
        # at soc_k: eb <= max(m - soc_k/alpha, 0) <= chord over soc_k in [0, 1], same for es
        far = np.maximum(m - 1.0 / alpha, 0.0)  # reach from the other end of the range
        near_coef = (far - m) if sign > 0 else (m - far)  # slope of the chord in soc_k
        base = m if sign > 0 else far
        q0 = row((1, n))
        terms.append((q0, extra[:1], 1.0))
        rhs.append((base[:1] + near_coef[:1] * soc_prev[1]).ravel())
        q1 = row((H - 1, n))
        terms += [(q1, extra[1:], 1.0), (q1, soc_prev[0], -near_coef[1:])]
        rhs.append(base[1:].ravel())
    # ... and they put the next soc on the penalty's edge: elo_{k+1} = soc_low, ehi = 1 - soc_high
    if sysc.soc_low > 0:
        q = row((H - 1, n))
        terms += [(q, ieb[:-1], 1.0), (q, ilo, -m_buy[:-1] / sysc.soc_low)]
        rhs.append(np.zeros((H - 1) * n))
    if sysc.soc_high < 1:
        q = row((H - 1, n))
        terms += [(q, ies[:-1], 1.0), (q, ihi, -m_sell[:-1] / (1.0 - sysc.soc_high))]
        rhs.append(np.zeros((H - 1) * n))
    # penalty epigraphs
    q = row((H - 1, n))
    terms += [(q, isoc[:-1], 1.0), (q, ihi, -1.0)]
    rhs.append(np.full((H - 1) * n, sysc.soc_high))
    q = row((H - 1, n))
    terms += [(q, isoc[:-1], -1.0), (q, ilo, -1.0)]
    rhs.append(np.full((H - 1) * n, -sysc.soc_low))
    A_ub = sparse(terms, count)
    b_ub = np.concatenate(rhs)

    upper = np.full(lay.size, np.inf)
    upper[iub] = upper[ius] = U
    upper[ieb], upper[ies] = m_buy, m_sell
    upper[isoc] = 1.0
    bounds = list(zip(np.zeros(lay.size), upper))
    return c, A_ub, b_ub, A_eq, b_eq, bounds, lay


@dataclass(frozen=True, eq=False)
class ClairvoyantResult(PolicyResult):
    """The clairvoyant's plans as a :class:`PolicyResult`: ``trajectory.a`` (and
    ``trajectory.policy``) holds the commanded part ``ub - us``, ``trajectory.b``/``s`` the applied powers and
    ``trajectory.correction`` the controller's extra ``eb - es``.

    Attributes
    ----------
    J_replayed : float
        ``J`` of replaying the plan's applied net powers ``b - s`` as commands in closed loop
        (projected onto the input bounds and the grid limit): an achievable cost of a
        non-causal policy, so the best cost on these draws lies in ``[J, J_replayed]``.
    parts : dict of numpy.ndarray, each ``(hours, days, n)``
        The LP's ``ub``, ``us`` (commanded) and ``eb``, ``es`` (controller's extra).
    """

    J_replayed: float = float("nan")
    parts: dict[str, np.ndarray] = field(default_factory=dict)


def clairvoyant(scenario: Scenario) -> ClairvoyantResult:
    """Solve the clairvoyant LP of every day (HiGHS through :func:`scipy.optimize.linprog`).

    Returns
    -------
    ClairvoyantResult
        ``J`` is the lower bound of the module docstring; per-agent costs are evaluated at
        the LP's applied powers and soc, penalties with :func:`mpcrl_lite.system.battery.penalty`.
    """
    t0 = time.perf_counter()
    sysc = scenario.system
    H, D, n = sysc.hours_per_day, scenario.days, sysc.n
    soc = np.empty((H + 1, D, n))
    soc[0] = scenario.soc0
    parts = {key: np.empty((H, D, n)) for key in ("ub", "us", "eb", "es")}
    statuses = set()
    for d in range(D):
        c, A_ub, b_ub, A_eq, b_eq, bounds, lay = clairvoyant_lp(scenario, d)
        res = linprog(c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=b_eq, bounds=bounds,
                      method="highs")
        if res.status != 0:
            raise RuntimeError(f"clairvoyant LP of day {d} failed: {res.message}")
        z = np.maximum(res.x, 0.0)  # remove -1e-12 rounding on non-negative variables
        for key, part in parts.items():
            part[:, d] = z[lay.block(key)]
        soc[1:, d] = np.clip(z[lay.block("soc")], 0.0, 1.0)
        statuses.add(res.message)
    b, s = parts["ub"] + parts["eb"], parts["us"] + parts["es"]
    buy, sell = scenario.buy.T[:, :, None], scenario.sell.T[:, :, None]  # (H, D, 1)
    agent_cost = buy * b - sell * s + penalty(soc[:-1], sysc)
    commanded = parts["ub"] - parts["us"]
    power = np.maximum(parts["ub"].sum(-1), parts["us"].sum(-1))
    # the plan is the policy: its commands are the actions, its grid power the planned one
    trajectory = Record(
        soc=soc, policy=commanded, a=commanded, b=b, s=s, correction=parts["eb"] - parts["es"],
        agent_cost=agent_cost, stage_cost=agent_cost.sum(-1),
        grid_power=np.maximum(b.sum(-1), s.sum(-1)), planned_power=power,
        noise=np.array(scenario.noise), buy=np.array(scenario.buy.T),
        solver_ok=np.ones((H, D), bool), sens_ok=np.zeros((H, D), bool), system=sysc,
    )
    plan = b - s
    replayed = evaluate_policy(lambda hour, _soc: plan[hour], scenario, "clairvoyant replay").J
    info = {"lp_status": sorted(statuses), "J_replayed": replayed,
            "controller_extra_hours": int(np.count_nonzero(parts["eb"] + parts["es"] > 1e-9))}
    return ClairvoyantResult("clairvoyant", trajectory, power, 0, time.perf_counter() - t0, info,
                             replayed, parts)


# -- all baselines ----------------------------------------------------------------------------
def evaluate_baselines(
    system: SystemConfig,
    mpc_config: MPCConfig | None = None,
    days: int = 30,
    seed: int = 0,
    thetas: Mapping[str, Theta] | None = None,
    prices: Prices | None = None,
    rule_soc_guard: bool = True,
    causal: bool | CausalBound = False,
) -> dict[str, Any]:
    """Evaluate the clairvoyant, nominal, rule-based and given-theta policies on one scenario.

    Parameters
    ----------
    system : SystemConfig
    mpc_config : MPCConfig, optional
        Back-end and barrier parameter of the MPC policies (:func:`make_solver`).
    days : int
        Days of the scenario (the first ``days`` of :meth:`Prices.month` unless ``prices``).
    seed : int
        Seed of the noise (:func:`make_scenario`).
    thetas : mapping of name to Theta, optional
        MPCs to evaluate besides the nominal one, e.g. ``{"learned": history.final_theta()}``;
        the names ``clairvoyant``, ``nominal``, ``rule_based`` and ``causal_dp`` are reserved.
    prices : Prices, optional
    rule_soc_guard : bool, default True
        Passed to :class:`RuleBasedPolicy`.
    causal : bool or CausalBound, default False
        Also measure against the best causal policy (:mod:`mpcrl_lite.bounds.causal.dp`): True solves
        the coupled DP of the scenario's days (about 2 s of CPU per distinct day for three
        batteries), or pass a :class:`~mpcrl_lite.bounds.causal.dp.CausalBound` solved on these prices.
        The DP policy's closed loop is added as ``"causal_dp"`` (not for a bound without value
        tables, e.g. :func:`mpcrl_lite.bounds.causal.table.causal_bound`), and ``"causal"`` holds
        ``J_star`` (mean over the scenario's days), ``grid``, and for every policy the regret
        ``J - J_star`` (NOK/day) and the gap closed ``(J_nominal - J)/(J_nominal - J_star)``.

    Returns
    -------
    dict
        ``{"scenario": {...}, "policies": {name: summary}, "gap_closed": {name: share},
        "system": {...}, "mpc": {...}}`` (and ``"causal"``); each summary holds ``J``,
        ``J_per_agent``, ``J_per_day``, ``hours_soc_below_0_1``, ``hours_soc_above_0_9``, grid
        powers, interventions, solver failures and wall time. ``gap_closed[name]`` is
        :math:`(J_{nominal} - J_{name})/(J_{nominal} - J_{clairvoyant})` (None when the
        nominal MPC is already at the bound).
    """
    mpc_config = mpc_config or MPCConfig()
    thetas = dict(thetas or {})
    reserved = {"clairvoyant", "nominal", "rule_based", "causal_dp"} & set(thetas)
    if reserved:
        raise ValueError(f"thetas uses reserved name(s) {sorted(reserved)}; choose others")
    for name, theta in thetas.items():
        if not isinstance(theta, Theta) or theta.n != system.n:
            raise ValueError(f"thetas[{name!r}]: expected a Theta with n={system.n}")
    if causal is not True and causal is not False and (
            not isinstance(causal, CausalBound) or causal.system != system):
        raise ValueError(f"causal={causal!r}: expected True, False or a CausalBound of this system")
    scenario = make_scenario(system, days, seed, prices)
    if isinstance(causal, CausalBound):
        causal.rows_for(scenario.prices)  # the bound must cover the scenario's days
    results: dict[str, PolicyResult] = {"clairvoyant": clairvoyant(scenario)}
    mpc = MPC(system)
    for name, theta in {"nominal": Theta.nominal(system), **thetas}.items():
        solver = make_solver(mpc, mpc_config, theta)
        seen = forecast_prices(scenario.prices, mpc_config)  # MPCConfig.forecast
        results[name] = evaluate_policy(MPCPolicy(solver, theta, seen), scenario, name)
        results[name].info["backend"] = solver.name
    results["rule_based"] = evaluate_policy(
        RuleBasedPolicy(scenario.prices, system, rule_soc_guard), scenario, "rule_based"
    )
    order = ["clairvoyant", "nominal", "rule_based", *thetas]
    extra: dict[str, Any] = {}
    if causal is not False:
        if causal is True:
            causal = causal_optimum(system, scenario.prices)
        j_star = float(causal.J_star_for(scenario.prices).mean())
        if causal.values is not None:  # a bound without value tables gives J*, no policy
            results["causal_dp"] = evaluate_policy(causal.policy(scenario.prices), scenario,
                                                   "causal_dp")
            order.insert(1, "causal_dp")
        table = compare_with_optimum({name: results[name].J for name in order}, j_star)
        extra["causal"] = {"J_star": j_star, "grid": causal.grid.describe(),
                           "regret": {k: v["regret"] for k, v in table.items()},
                           "gap_closed": {k: v["gap_closed"] for k, v in table.items()}}
    policies = {name: results[name].summary() for name in order}
    j_nom, j_clair = results["nominal"].J, results["clairvoyant"].J
    gap = j_nom - j_clair
    gap_closed = {name: ((j_nom - results[name].J) / gap if gap > 0 else None)
                  for name in order if name not in ("clairvoyant", "nominal")}
    return {
        "scenario": scenario.describe(),
        "policies": policies,
        "gap_closed": gap_closed,
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
        **extra,
    }


#: The file written by :func:`run_baselines_cli`.
BASELINES_JSON = "baselines.json"


def run_baselines_cli(
    system: SystemConfig,
    mpc_config: MPCConfig,
    learning: LearningConfig,
    history_dir: str | Path | None,
    out_dir: str | Path,
    prices: Prices | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """The ``baselines`` command: evaluate and write ``out_dir/baselines.json``.

    The scenario has ``learning.days_per_month`` days and seed ``learning.seed``. With
    ``history_dir`` (a ``learn`` output directory) its final theta is evaluated as
    ``"learned"``; its system must have the same ``n`` (a different configuration otherwise
    only triggers a warning, since evaluating a theta elsewhere can be deliberate).

    ``prices`` (e.g. another month of a Nord Pool export) must have that many days.
    ``out_dir`` is checked before any work: a file, a directory that cannot be written, or
    one that holds ``baselines.json`` already (unless ``force``) is a ``ValueError``
    (:class:`~mpcrl_lite.learning.rundir.RunDirError`). ``baselines.json`` is strict JSON (NaN as
    null), written atomically.

    Returns
    -------
    dict
        As :func:`evaluate_baselines`, plus ``"history"`` (the directory or None).
    """
    thetas: dict[str, Theta] = {}
    if history_dir is not None:
        history = History.load(history_dir)
        if history.system.n != system.n:
            raise ValueError(
                f"history in {history_dir} has n={history.system.n}; expected n={system.n} "
                "(pass --n to match)"
            )
        if history.system != system:
            learned, here = history.system.to_dict(), system.to_dict()
            changed = "; ".join(f"{k}={learned[k]!r} there, {here[k]!r} here"
                                for k in here if learned[k] != here[k])
            warnings.warn(f"history in {history_dir} was learned on a different system "
                          f"({changed}); evaluating it on this one", UserWarning, stacklevel=2)
        if not history.theta_final:
            raise ValueError(f"history in {history_dir} has no final theta (no month finished)")
        thetas["learned"] = history.final_theta()
        if history.mpc.forecast != mpc_config.forecast:
            warnings.warn(f"history in {history_dir} was learned with forecast="
                          f"{history.mpc.forecast!r}; evaluating it with forecast="
                          f"{mpc_config.forecast!r} (pass --forecast to match)", UserWarning,
                          stacklevel=2)
    if rundir.inspect(out_dir, others=[BASELINES_JSON]).others and not force:
        raise rundir.RunDirError(f"--out {out_dir} already holds {BASELINES_JSON}; pass --force "
                                 "to replace it or choose another --out")
    out = rundir.check_output_dir(out_dir)
    result = evaluate_baselines(system, mpc_config, learning.days_per_month, learning.seed, thetas,
                                prices=prices)
    result["history"] = None if history_dir is None else str(history_dir)
    rundir.write_json(out / BASELINES_JSON, result)
    return result
