r"""The common scenario every policy is judged on, and the evaluation of a policy on it.

Every policy is evaluated on one :class:`Scenario` -- the same days, prices and noise draws --
with the true dynamics, the low-level controller and the true cost :math:`\tilde L`
(penalties included) of :mod:`mpcrl_lite.system.battery` (:func:`evaluate_policy`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .._util.budget import check_memory, estimate
from ..config import SystemConfig
from ..sim.closed_loop import Policy, simulate
from ..sim.exploration import Projection
from ..sim.record import Record
from ..system.battery import sample_noise
from ..system.prices import Prices

__all__ = ['PolicyResult', 'Scenario', 'evaluate_policy', 'make_scenario']


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
            **({"prices_origin": dict(self.prices.origin)}
               if getattr(self.prices, "origin", None) else {}),
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
    # the days' closed loop must fit in memory: refused before prices and noise are drawn
    check_memory(f"days={days}, n={system.n}", estimate(system.n, int(days), horizon=system.N))
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
