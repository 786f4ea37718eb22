"""The battery system as a Gymnasium environment: one day an episode, any agent.

:class:`BatteryEnv` exposes the true system of :mod:`mpcrl_lite.system.battery` through the
standard reinforcement-learning interface (Gymnasium >= 1.0, ``reset``/``step``), so that an
agent written for that interface (Stable-Baselines3, a student's own loop) can be tried on it
beside the batched closed loop of :func:`mpcrl_lite.sim.closed_loop.simulate`. The dynamics are
not copied: every hour is :func:`~mpcrl_lite.system.battery.step` of one row, after the action
hook :class:`~mpcrl_lite.sim.exploration.Projection` that the closed loop applies to a plain
policy's command (the input bounds and the grid limit).

One episode
-----------
A day ``d`` of a month of prices, ``hours_per_day`` steps. At hour ``k`` the agent sees

* ``soc`` -- the state of charge of every battery, ``Box(0, 1, (n,))``;
* ``hour`` -- ``k``, ``Box(0, hours_per_day - 1, (1,))``;
* ``buy``, ``sell`` -- the buying and selling prices of the MPC's forecast window
  (``prices.window(k, N)`` of day ``d``, after the forecast of ``MPCConfig.forecast``),
  ``Box(min, max, (N,))`` with the month's smallest and largest price as bounds;

and commands the net power of every battery, ``Box(-U_bar, U_bar, (n,))`` (each battery's own
``U_bar^i``; every per-battery parameter of the system is each battery's own). The command is
projected onto the input bounds and the grid limit ``sum_i b_i <= P_bar``,
``sum_i s_i <= P_bar`` (:func:`~mpcrl_lite.system.battery.project_action`; a no-op for a
feasible command such as the MPC's), the noise ``Delta ~ N(noise_mean, noise_var)`` is drawn
from the environment's generator, and the low-level controller keeps soc in ``[0, 1]``. The
reward is minus the stage cost ``-L~(s_k, a_k)`` (paper eqs. 2-3); the day's
``sum_k gamma^k L~`` is its J (``gamma`` is ``system.gamma``, left to the agent). The episode
*terminates* after the last hour (a day has a natural end; nothing is truncated).

``info`` of every step holds the commanded and applied actions, ``grid_limited`` (the
projection changed the command), ``planned_grid_power`` (``max(sum a^+, sum a^-)`` of the
command) and ``grid_power`` (``P_k`` of the powers actually exchanged), the per-battery costs
``agent_cost`` (``L~_i``), ``b``, ``s``, the low-level ``correction`` and the ``noise``.

Seeding
-------
``reset(seed=s)`` seeds the environment's generator (:attr:`np_random`) as Gymnasium does
(``numpy.random.default_rng(s)``'s stream: PCG64 of the seed sequence of ``s``); the day, when
not fixed, and the noise of every hour are drawn from it, in that order. With a fixed day the
noise of a seeded episode is the noise :func:`simulate` draws for one day from
``numpy.random.default_rng(s)``. ``reset(options={"noise": array (hours, n)})`` replays given
noise instead (common random numbers), ``options={"day": d}`` picks the day.

Vectorised over days
--------------------
:func:`make_day_vector_env` (also ``gymnasium.make_vec("mpcrl_lite/Batteries-v0",
num_envs=D, vectorization_mode="vector_entry_point")``) gives a
``gymnasium.vector.SyncVectorEnv`` whose environment ``i`` plays day ``i mod days`` of the
month, each with its own generator (seeded ``seed + i`` by ``reset(seed=seed)``).

:class:`MPCAgent` is the MPC as a policy of this interface: ``agent(observation) -> action``,
solving the MPC from the observed soc and price window with the warm start of
:class:`~mpcrl_lite.sim.closed_loop.MPCPolicy` (which it uses), so that it reproduces the costs
of :func:`~mpcrl_lite.sim.closed_loop.run_month` on the same noise.

Registration: importing :mod:`mpcrl_lite` makes ``gymnasium.make("mpcrl_lite/Batteries-v0",
system=..., mpc=..., prices=..., day=...)`` available without importing Gymnasium itself
(:mod:`mpcrl_lite._util.gym_registration`).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..config import MPCConfig, SystemConfig, check_int
from ..system.battery import project_action, sample_noise, step
from ..system.forecast import forecast_prices
from ..system.prices import Prices
from ..theta import Theta
from .closed_loop import MPCPolicy

__all__ = ["ENV_ID", "BatteryEnv", "MPCAgent", "make_day_vector_env"]

#: The id under which the environment is registered with Gymnasium.
ENV_ID = "mpcrl_lite/Batteries-v0"


class BatteryEnv(gym.Env):
    """The ``n`` batteries on one day of prices (see the module docstring).

    Parameters
    ----------
    system : SystemConfig, optional
        The true system (default ``SystemConfig()``).
    mpc : MPCConfig, optional
        Its ``N`` comes from ``system``; ``mpc.forecast`` sets the price window observed
        (default ``MPCConfig()``: the paper's window, reading on into the next day).
    prices : Prices, optional
        The month (default the shipped one for ``system``, :meth:`Prices.default`).
    day : int, optional
        The day of ``prices`` played by every episode; None (default): drawn uniformly from
        :attr:`np_random` at every reset.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (Gymnasium's attribute)

    def __init__(self, system: SystemConfig | None = None, mpc: MPCConfig | None = None,
                 prices: Prices | None = None, day: int | None = None) -> None:
        system = SystemConfig() if system is None else system
        mpc = MPCConfig() if mpc is None else mpc
        if not isinstance(system, SystemConfig):
            raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
        if not isinstance(mpc, MPCConfig):
            raise ValueError(f"mpc={mpc!r}: expected an MPCConfig")  # noqa: TRY004
        prices = Prices.default(system) if prices is None else prices
        if not isinstance(prices, Prices):
            raise ValueError(f"prices={prices!r}: expected a Prices")  # noqa: TRY004
        self.system, self.mpc_config = system, mpc
        self.prices = forecast_prices(prices, mpc)
        self.fixed_day = None if day is None else check_int("day", day, 0, self.prices.days - 1)
        n, N, H = system.n, system.N, system.hours_per_day
        # the windows of every hour and day, (H, days, N), read once
        windows = [self.prices.window(k, N) for k in range(H)]
        self._buy = np.stack([w[0] for w in windows])
        self._sell = np.stack([w[1] for w in windows])
        low = float(min(self._buy.min(), self._sell.min()))
        high = float(max(self._buy.max(), self._sell.max()))
        self.observation_space = spaces.Dict({
            "soc": spaces.Box(0.0, 1.0, (n,), np.float64),
            "hour": spaces.Box(0.0, float(H - 1), (1,), np.float64),
            "buy": spaces.Box(low, high, (N,), np.float64),
            "sell": spaces.Box(low, high, (N,), np.float64),
        })
        bound = np.array(system.battery("U_bar"), dtype=np.float64)  # each battery's own
        self.action_space = spaces.Box(-bound, bound, (n,), np.float64)
        self.day = 0 if self.fixed_day is None else self.fixed_day
        self.hour = 0
        self.soc = np.array(system.battery("soc0"), dtype=np.float64)
        self._noise: np.ndarray | None = None

    # -- the interface ---------------------------------------------------------------------
    def reset(self, *, seed: int | None = None,
              options: dict[str, Any] | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """Start a day: soc at ``system.soc0``, hour 0. ``options``: ``day`` (an int),
        ``noise`` (``(hours, n)``: replayed instead of drawn)."""
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"day", "noise"}
        if unknown:
            raise ValueError(f"options {sorted(unknown)}: expected some of ['day', 'noise']")
        H, n = self.system.hours_per_day, self.system.n
        if "day" in options:
            self.day = check_int("options['day']", options["day"], 0, self.prices.days - 1)
        elif self.fixed_day is None:
            self.day = int(self.np_random.integers(self.prices.days))
        noise = options.get("noise")
        if noise is not None:
            noise = np.asarray(noise, dtype=float)
            if noise.shape != (H, n) or not np.isfinite(noise).all():
                raise ValueError(f"options['noise'] has shape {noise.shape}: expected finite "
                                 f"values of shape (hours, n) = {(H, n)}")
        self._noise = noise
        self.hour = 0
        self.soc = np.array(self.system.battery("soc0"), dtype=np.float64)
        return self._observation(), {"day": self.day}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        """One hour: the command projected, the noise drawn, the true system advanced."""
        H = self.system.hours_per_day
        if self.hour >= H:
            raise RuntimeError("the day is over: call reset() before step()")
        a = np.asarray(action, dtype=float).reshape(1, -1)
        if a.shape != (1, self.system.n) or not np.isfinite(a).all():
            raise ValueError(f"action={action!r}: expected {self.system.n} finite net powers")
        applied = project_action(a, self.system)
        k, d = self.hour, self.day
        if self._noise is None:
            delta = sample_noise(self.np_random, (1, self.system.n), self.system)
        else:
            delta = self._noise[k][None, :]
        result = step(self.soc[None, :], applied, delta, self.prices.buy[d, k],
                      self.prices.sell[d, k], self.system)
        planned = max(np.maximum(a, 0.0).sum(), np.maximum(-a, 0.0).sum())
        info = {
            "day": d,
            "hour": k,
            "action": a[0],
            "applied_action": applied[0],
            "grid_limited": bool(np.any(applied != a)),
            "planned_grid_power": float(planned),
            "grid_power": float(result.grid_power[0]),
            "agent_cost": result.agent_cost[0],
            "b": result.b[0],
            "s": result.s[0],
            "correction": result.correction[0],
            "noise": delta[0],
        }
        self.soc = result.soc_next[0]
        self.hour = k + 1
        terminated = self.hour == H
        return self._observation(), -float(result.stage_cost[0]), terminated, False, info

    def _observation(self) -> dict[str, np.ndarray]:
        k = min(self.hour, self.system.hours_per_day - 1)  # the last observation repeats hour H-1
        return {
            "soc": self.soc.copy(),
            "hour": np.array([float(k)]),
            "buy": self._buy[k, self.day].copy(),
            "sell": self._sell[k, self.day].copy(),
        }


def make_day_vector_env(num_envs: int | None = None, **kwargs: Any) -> gym.vector.SyncVectorEnv:
    """The environment vectorised over days: environment ``i`` plays day ``i mod days``.

    Parameters
    ----------
    num_envs : int, optional
        Number of environments (default: one per day of the month).
    **kwargs
        ``system``, ``mpc``, ``prices`` of :class:`BatteryEnv` (``day`` is set per
        environment).

    Returns
    -------
    gymnasium.vector.SyncVectorEnv
        ``reset(seed=s)`` seeds environment ``i`` with ``s + i``.
    """
    if "day" in kwargs:
        raise ValueError("day: set per environment by make_day_vector_env; expected no 'day'")
    probe = BatteryEnv(**kwargs)
    days = probe.prices.days
    num_envs = days if num_envs is None else check_int("num_envs", num_envs, 1)
    return gym.vector.SyncVectorEnv(
        [lambda i=i: BatteryEnv(**kwargs, day=i % days) for i in range(num_envs)])


class MPCAgent:
    """The MPC at a fixed theta as a policy of :class:`BatteryEnv`: ``agent(obs) -> action``.

    It solves the MPC of ``env.system`` from the observed soc, hour and price window with
    :class:`~mpcrl_lite.sim.closed_loop.MPCPolicy` (warm start from the previous hour's
    solution, the idle fallback where a solve fails), one day at a time.

    Parameters
    ----------
    env : BatteryEnv
        Supplies the system and the MPC configuration (unwrapped if wrapped).
    theta : Theta, optional
        Default the nominal ``Theta.nominal(system)``.
    solver : optional
        A back-end (:func:`~mpcrl_lite.mpc.backends.registry.make_solver`); default one built
        for ``env``'s system and MPC configuration.
    """

    def __init__(self, env: Any, theta: Theta | None = None, solver: Any = None) -> None:
        from ..mpc.backends.registry import make_solver
        from ..mpc.formulation import MPC

        base = getattr(env, "unwrapped", env)
        if not isinstance(base, BatteryEnv):
            raise ValueError(f"env={env!r}: expected a BatteryEnv")  # noqa: TRY004
        system = base.system
        theta = Theta.nominal(system) if theta is None else theta
        solver = make_solver(MPC(system), base.mpc_config, theta) if solver is None else solver
        self._window = _ObservedWindow()
        self.policy = MPCPolicy(solver, theta, self._window)

    def __call__(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        hour = int(np.rint(observation["hour"][0]))
        self._window.buy = np.asarray(observation["buy"], dtype=float)[None, :]
        self._window.sell = np.asarray(observation["sell"], dtype=float)[None, :]
        soc = np.asarray(observation["soc"], dtype=float)[None, :]
        return self.policy(hour, soc)[0]


class _ObservedWindow:
    """The price window of the current observation, where :class:`MPCPolicy` reads it."""

    buy: np.ndarray
    sell: np.ndarray

    def window(self, hour: int, N: int) -> tuple[np.ndarray, np.ndarray]:
        return self.buy[:, :N], self.sell[:, :N]
