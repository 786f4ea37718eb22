r"""The one closed loop: a policy acting on the true system, all days advancing together.

Every simulation in the package goes through :func:`simulate`: the learning months and
their evaluations (:func:`run_month`), the baselines on a common scenario
(:func:`mpcrl_lite.bounds.scenario.evaluate_policy`), the decentralized month, the widgets' days,
the benchmarks and the notebooks. What differs between them is attached to the loop, never
copied into it:

* the **policy**: a plain callable ``policy(hour, soc) -> a`` (a rule, a schedule), or an
  object with ``decide(hour, soc) -> Decision`` that also reports solver status, planned
  grid power and sensitivities -- :class:`MPCPolicy` is the MPC as such a policy;
* the **action hook** ``explore(hour, pi, rng) -> a`` turning the policy's output into the
  commanded action: Gaussian exploration (:class:`~mpcrl_lite.sim.exploration.GaussianExploration`)
  or a projection of the command onto the input bounds and the grid limit
  (:class:`~mpcrl_lite.sim.exploration.Projection`); both live in :mod:`mpcrl_lite.sim.exploration`
  and are importable from here too;
* **hour hooks** ``hook(step: HourStep)`` called after every hour (e.g.
  :class:`SensitivityRecorder`, progress bars, timers) and **day-end hooks**
  ``hook(record)`` called with the finished :class:`~mpcrl_lite.sim.record.Record`.

One hour ``k`` of the loop, for all ``D`` days at once (paper, Section II)::

    pi_k  = policy(k, soc_k)                      (D, n)
    a_k   = explore(k, pi_k, rng)  or pi_k        (draws the exploration first ...)
    Delta = sample_noise(rng, (D, n)) or noise[k] (... then the noise)
    soc_{k+1}, b, s, L~_i, P_k = model.step(soc_k, a_k, Delta, phi_b[:, k], phi_s[:, k])

The order of the draws (exploration, then noise, hour by hour) is part of the contract: a
seeded generator reproduces a run exactly, and without exploration the noise of ``H`` hours
equals one draw ``sample_noise(rng, (H, D, n))``, so a scenario drawn at once
(common random numbers) gives the same numbers as a generator used hour by hour.

Runs in lockstep
----------------
``K`` runs that share the true system's dynamics and the MPC can advance as one loop of
``K * D`` days (:mod:`mpcrl_lite.studies.lockstep`): the days of run ``r`` are rows
``r * D .. (r + 1) * D - 1``, :class:`MPCPolicy` and :func:`run_month` take one theta per run
(one solver call for all rows), and ``rng`` is a :class:`RunBlocks` holding each run's own
generator and noise distribution, which draws every block from its run's generator in the
order above. Every computation of the loop is row by row, so each block is bit for bit the
run alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import SystemConfig
from ..system.battery import StepResult, battery_values, sample_noise, step, step_unchecked
from ..theta import Theta
from .exploration import (
    GaussianExploration,
)
from .record import MonthRecord, Record

__all__ = ["ActionHook", "DayHook", "Decision", "HourHook", "HourStep", "MPCPolicy", "Policy", "RunBlocks", "SensitivityRecorder", "draw_J", "evaluate_mpc", "evaluation_rng", "rollout", "run_month", "simulate", "stacked_draws"]

#: A plain policy: ``policy(hour, soc)`` with ``soc`` of shape ``(days, n)`` returns the
#: commanded net powers ``a`` of shape ``(days, n)``.
Policy = Callable[[int, np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class Decision:
    """What a policy decided at one hour for all days.

    Attributes
    ----------
    action : numpy.ndarray, shape ``(days, n)``
        The policy's action :math:`\\pi(s_k)`.
    solver_ok : numpy.ndarray of bool, shape ``(days,)``, optional
        The policy's optimization converged (default: all True).
    planned_power : numpy.ndarray, shape ``(days,)``, optional
        Largest grid power the policy planned over its horizon (default: the grid power
        :math:`\\max(\\sum_i a_i^+, \\sum_i a_i^-)` of ``action``).
    sens_ok : numpy.ndarray of bool, shape ``(days,)``, optional
        A usable sensitivity was computed (default: all False, none was).
    grad : numpy.ndarray, optional
        The policy sensitivity, e.g. ``(days, n_theta, n)`` (see
        :class:`SensitivityRecorder`).
    solution : object, optional
        The solver's solution, for hooks that need more.
    grad_soc0 : numpy.ndarray, shape ``(days, n, n)``, optional
        :math:`\\partial\\pi_o/\\partial soc_i` at ``[d, i, o]`` where the back-end forms it
        (:attr:`~mpcrl_lite.mpc.solution.Sensitivity.grad_soc0`).
    """

    action: np.ndarray
    solver_ok: np.ndarray | None = None
    planned_power: np.ndarray | None = None
    sens_ok: np.ndarray | None = None
    grad: np.ndarray | None = None
    solution: Any = None
    grad_soc0: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class HourStep:
    """One hour of the loop as the hour hooks see it (arrays of all ``days``).

    ``soc`` is the state before the step, ``decision`` the policy's, ``a`` the commanded
    action, ``noise`` the drawn :math:`\\Delta_k`, ``result`` the true system's step
    (:class:`~mpcrl_lite.system.battery.StepResult`) and ``buy``, ``sell`` the prices of the hour.
    """

    hour: int
    soc: np.ndarray
    decision: Decision
    a: np.ndarray
    noise: np.ndarray
    result: StepResult
    buy: np.ndarray
    sell: np.ndarray


#: ``explore(hour, pi (days, n), rng) -> a (days, n)``; may draw from ``rng`` (before the
#: hour's noise is drawn).
ActionHook = Callable[[int, np.ndarray, "np.random.Generator | None"], np.ndarray]
#: ``hook(step)``, called after every hour.
HourHook = Callable[[HourStep], None]
#: ``hook(record)``, called once when the last hour is done.
DayHook = Callable[[Record], None]


class RunBlocks:
    """The generators of ``K`` runs stacked in lockstep, one per equal block of rows.

    Stands in for ``rng`` in :func:`simulate`: a draw of shape ``(K * D, ...)`` is the
    concatenation of each run's draw of shape ``(D, ...)`` from its own generator, so each
    run's generator sees exactly the calls of the run alone (exploration, then noise, per
    hour). :meth:`noise` draws each block from its own system's noise distribution.

    Parameters
    ----------
    rngs : sequence of numpy.random.Generator
        One per run, in the order of the blocks.
    systems : sequence of SystemConfig
        Each run's true system (its ``noise_mean`` and ``noise_var`` are used).
    """

    def __init__(self, rngs: Sequence[np.random.Generator], systems: Sequence[SystemConfig]) -> None:
        self.rngs, self.systems = list(rngs), list(systems)
        if not self.rngs or len(self.systems) != len(self.rngs):
            raise ValueError(f"{len(self.rngs)} generators and {len(self.systems)} systems: "
                             "expected as many of each, at least one")
        for i, rng in enumerate(self.rngs):
            if not isinstance(rng, np.random.Generator):
                raise ValueError(f"rngs[{i}]={rng!r}: expected a numpy.random.Generator")  # noqa: TRY004

    def _block(self, shape: tuple[int, ...]) -> tuple[int, ...]:
        K = len(self.rngs)
        if not shape or shape[0] % K:
            raise ValueError(f"a draw of shape {shape}: expected {K} blocks of equal rows")
        return (shape[0] // K, *shape[1:])

    def standard_normal(self, shape: tuple[int, ...]) -> np.ndarray:
        """Each run's ``rng.standard_normal`` of its block's shape, stacked."""
        block = self._block(tuple(shape))
        return np.concatenate([rng.standard_normal(block) for rng in self.rngs])

    def noise(self, shape: tuple[int, ...]) -> np.ndarray:
        """Each run's :func:`~mpcrl_lite.system.battery.sample_noise` of its block's shape, stacked."""
        block = self._block(tuple(shape))
        return np.concatenate([sample_noise(rng, block, system)
                               for rng, system in zip(self.rngs, self.systems, strict=True)])


    def month_draws(self, shape: tuple[int, int, int], exploration_std: float | None,
                    ) -> tuple[np.ndarray | None, np.ndarray]:
        """Each run's month of draws (:func:`_month_draws`) for its block of the ``D``
        days of ``shape`` ``(H, D, n)``, stacked along the days."""
        H, D, n = shape
        days = self._block((D,))[0]
        draws = [_month_draws(rng, (H, days, n), system, exploration_std)
                 for rng, system in zip(self.rngs, self.systems, strict=True)]
        noise = np.concatenate([d[1] for d in draws], axis=1)
        if exploration_std is None:
            return None, noise
        return np.concatenate([d[0] for d in draws], axis=1), noise


def _draw_noise(rng: Any, shape: tuple[int, int], system: SystemConfig) -> np.ndarray:
    return rng.noise(shape) if isinstance(rng, RunBlocks) else sample_noise(rng, shape, system)


class SensitivityRecorder:
    """Hour hook collecting each hour's ``decision.grad``; :attr:`grad_pi` stacks them into
    ``(H, days, ...)`` (e.g. ``(H, D, n_theta, n)`` for :class:`MPCPolicy`)."""

    #: it only reads the steps: a compiled month may call it after the month
    #: (:func:`run_month`)
    replayable = True

    def __init__(self) -> None:
        self._grads: list[np.ndarray] = []

    def __call__(self, hour_step: HourStep) -> None:
        grad = hour_step.decision.grad
        if grad is None:
            raise ValueError(f"at hour {hour_step.hour}: the policy returned no sensitivity "
                             "(expected a policy computing them, e.g. MPCPolicy(sensitivities=True))")
        self._grads.append(grad)

    @property
    def grad_pi(self) -> np.ndarray:
        """The recorded sensitivities, hour first."""
        return np.stack(self._grads)


# -- the loop -----------------------------------------------------------------------------------
def simulate(
    policy: Any,
    buy: Any,
    sell: Any,
    system: SystemConfig,
    *,
    rng: np.random.Generator | None = None,
    noise: Any = None,
    soc0: Any = None,
    explore: ActionHook | None = None,
    hours: int | None = None,
    on_hour: Sequence[HourHook] = (),
    on_day_end: Sequence[DayHook] = (),
) -> Record:
    """Run ``policy`` on the true system, hour by hour, every day of ``buy`` at once.

    See the module docstring for one hour of the loop and the order of the random draws.

    Parameters
    ----------
    policy : callable ``(hour, soc (days, n)) -> a (days, n)`` or an object with ``decide``
        ``policy.decide(hour, soc)`` is called when it exists (:class:`MPCPolicy`), else
        ``policy(hour, soc)``; either may return the action or a :class:`Decision`. The
        policy gets a copy of the state.
    buy, sell : array_like, shape ``(days, hours_per_day)``
        Prices of each day and hour of the true system's cost (an MPC policy reads its own
        forecast windows).
    system : SystemConfig
        The true system.
    rng : numpy.random.Generator or RunBlocks, optional
        Source of the noise (one ``sample_noise`` of shape ``(days, n)`` per hour) unless
        ``noise`` is given, and of the exploration; a :class:`RunBlocks` for runs in
        lockstep.
    noise : array_like, shape ``(hours, days, n)``, optional
        The noise of every hour, for common random numbers (then ``rng`` is not used for it).
    soc0 : float or array_like of shape ``(n,)`` or ``(days, n)``, optional
        State at the start of the days (default ``system.soc0``).
    explore : callable ``(hour, pi, rng) -> a``, optional
        Turns the policy's output into the commanded action (default: unchanged).
    hours : int, optional
        Hours to simulate, ``1 .. hours_per_day`` (default the whole day).
    on_hour : sequence of callables ``hook(step: HourStep)``
        Called after every hour, in order.
    on_day_end : sequence of callables ``hook(record: Record)``
        Called with the finished record.

    Returns
    -------
    Record
    """
    # bad input of any kind is a ValueError in this package, wrong types included
    if not isinstance(system, SystemConfig):
        raise ValueError(f"system={system!r}: expected a SystemConfig")  # noqa: TRY004
    decide = getattr(policy, "decide", policy)
    if not callable(decide):
        raise ValueError(  # noqa: TRY004
            f"policy={policy!r}: expected a callable policy(hour, soc) -> a"
        )
    if rng is not None and not isinstance(rng, (np.random.Generator, RunBlocks)):
        raise ValueError(f"rng={rng!r}: expected a numpy.random.Generator (np.random.default_rng)")
    H_day, n = system.hours_per_day, system.n
    buy, sell = _prices("buy", buy, H_day), _prices("sell", sell, H_day)
    if sell.shape != buy.shape:
        raise ValueError(f"sell has shape {sell.shape}: expected the shape of buy, {buy.shape}")
    D = buy.shape[0]
    H = H_day if hours is None else hours
    if isinstance(H, bool) or not isinstance(H, (int, np.integer)) or not 1 <= H <= H_day:
        raise ValueError(f"hours={hours!r}: expected an integer in [1, {H_day}]")
    if noise is None:
        if rng is None:
            raise ValueError("rng=None: expected a numpy.random.Generator (or a noise array)")
    else:
        noise = _finite("noise", noise)
        if noise.shape != (H, D, n):
            raise ValueError(f"noise has shape {noise.shape}: expected (hours, days, n) = "
                             f"{(H, D, n)}")
    soc = _initial_soc(soc0, system, D)

    out = {key: np.empty((H, D, n)) for key in
           ("policy", "a", "b", "s", "correction", "agent_cost", "noise")}
    per_day = {key: np.empty((H, D)) for key in ("stage_cost", "grid_power", "planned_power",
                                                 "buy")}
    solver_ok, sens_ok = np.empty((H, D), bool), np.empty((H, D), bool)
    socs = np.empty((H + 1, D, n))
    socs[0] = soc
    # The hour's inputs need no second check where they are known to be good: the soc (checked
    # at the start, clipped to [0, 1] by every step), the prices and a given noise (checked
    # above), a drawn noise, the policy's action (_decision) and the package's exploration
    # of it; an action from another hook goes through step's checks.
    advance = step_unchecked if explore is None or type(explore) is GaussianExploration \
        else step
    for k in range(H):
        decision = _decision(decide(k, soc.copy()), k, (D, n))
        pi = decision.action
        a = pi if explore is None else explore(k, pi, rng)
        delta = _draw_noise(rng, (D, n), system) if noise is None else noise[k]
        res = advance(soc, a, delta, buy[:, k], sell[:, k], system)
        out["policy"][k], out["a"][k], out["noise"][k] = pi, a, delta
        out["b"][k], out["s"][k], out["correction"][k] = res.b, res.s, res.correction
        out["agent_cost"][k] = res.agent_cost
        per_day["stage_cost"][k], per_day["grid_power"][k] = res.stage_cost, res.grid_power
        per_day["planned_power"][k], per_day["buy"][k] = decision.planned_power, buy[:, k]
        solver_ok[k], sens_ok[k] = decision.solver_ok, decision.sens_ok
        if on_hour:
            hour_step = HourStep(k, soc, decision, a, delta, res, buy[:, k], sell[:, k])
            for hook in on_hour:
                hook(hour_step)
        soc = res.soc_next
        socs[k + 1] = soc
    record = Record(soc=socs, solver_ok=solver_ok, sens_ok=sens_ok, system=system, **out,
                    **per_day)
    for hook in on_day_end:
        hook(record)
    return record


def _decision(out: Any, hour: int, shape: tuple[int, int]) -> Decision:
    """A policy's output as a complete :class:`Decision` with a checked action."""
    decision = out if isinstance(out, Decision) else Decision(out)
    action = np.asarray(decision.action, dtype=float)
    if action.shape != shape:
        raise ValueError(f"at hour {hour}: policy output has shape {action.shape}: expected "
                         f"{shape}")
    bad = ~np.isfinite(action)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"at hour {hour}: policy output[{index[0]}, {index[1]}]="
                         f"{action[index]!r}: expected finite values only")
    days = shape[0]
    planned = decision.planned_power
    if planned is None:
        planned = np.maximum(np.maximum(action, 0.0).sum(-1), np.maximum(-action, 0.0).sum(-1))
    return Decision(
        action=action,
        solver_ok=np.ones(days, bool) if decision.solver_ok is None else decision.solver_ok,
        planned_power=planned,
        sens_ok=np.zeros(days, bool) if decision.sens_ok is None else decision.sens_ok,
        grad=decision.grad,
        solution=decision.solution,
        grad_soc0=decision.grad_soc0,
    )


def _finite(name: str, value: Any) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}={value!r}: expected an array of real numbers ({exc})") from None
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values only")
    return arr


def _prices(name: str, value: Any, hours: int) -> np.ndarray:
    arr = _finite(name, value)
    if arr.ndim != 2 or arr.shape[1] != hours or arr.shape[0] < 1:
        raise ValueError(f"{name} has shape {arr.shape}: expected (days, hours_per_day) = "
                         f"(days, {hours}) with days >= 1")
    return arr


def _initial_soc(soc0: Any, system: SystemConfig, days: int) -> np.ndarray:
    n = system.n
    start = _finite("soc0", system.soc0 if soc0 is None else soc0)
    try:
        start = np.broadcast_to(start, (days, n)).copy()
    except ValueError:
        raise ValueError(f"soc0 has shape {start.shape}: expected a scalar, (n,) = ({n},) or "
                         f"(days, n) = ({days}, {n})") from None
    outside = (start < 0.0) | (start > 1.0)
    if outside.any():
        d, i = (int(j) for j in np.argwhere(outside)[0])
        raise ValueError(f"soc0[{d}, {i}]={start[d, i]!r}: expected a state of charge in [0, 1]")
    return start


# -- the MPC as a policy --------------------------------------------------------------------------
class MPCPolicy:
    """The MPC at a fixed theta as a policy over a batch of days.

    At hour ``k`` it solves the MPC of every day (``solver.solve_batch``) with the forecast
    windows ``prices.window(k, N)``, warm-started from the previous hour's solution shifted
    by one stage (:meth:`mpcrl_lite.mpc.formulation.MPC.shift`; where a solve failed, the shifted guess is
    kept for the next hour), and returns :math:`\\pi = \\hat b_0 - \\hat s_0` (the idle
    fallback where a solve failed, counted in :attr:`failures`). The warm start restarts
    whenever the hours are not consecutive (a new run).

    :meth:`decide` also reports the solver status, the largest planned grid power
    :math:`\\max_j \\max(\\sum_i \\hat b_{j,i}, \\sum_i \\hat s_{j,i})` and, with
    ``sensitivities``, :math:`\\nabla_\\theta\\pi` (``solver.sensitivity``).

    Parameters
    ----------
    solver
        A back-end from :func:`mpcrl_lite.mpc.backends.registry.make_solver` (``mpc``, ``solve_batch``,
        ``sensitivity``).
    theta : Theta or sequence of Theta
        One theta for all rows, or one per run of runs stacked in lockstep (equal blocks of
        rows, see the module docstring): then one solver call gets each row's own theta.
    prices
        Anything with ``window(hour, N)`` (a :class:`~mpcrl_lite.system.prices.Prices`), one row
        per day.
    sensitivities : bool, default False
    """

    def __init__(self, solver: Any, theta: Theta | Sequence[Theta], prices: Any,
                 sensitivities: bool = False) -> None:
        thetas = [theta] if isinstance(theta, Theta) else list(theta)
        if not thetas or any(not isinstance(t, Theta) or t.n != solver.mpc.n for t in thetas):
            raise ValueError(f"theta={theta!r}: expected a Theta with n={solver.mpc.n} "
                             "(or a non-empty sequence of them)")
        # one theta per run: the rows' parameter vectors (days, n_theta) at each call
        self._vectors = None if isinstance(theta, Theta) else np.stack(
            [t.to_vector() for t in thetas])
        # the runs' vectors repeated for their rows (made at the first call, which knows them)
        self._theta_rows: np.ndarray | None = None
        if not isinstance(sensitivities, bool):
            raise ValueError(  # noqa: TRY004
                f"sensitivities={sensitivities!r}: expected True or False"
            )
        self.solver, self.theta, self.prices = solver, theta, prices
        self.sensitivities = sensitivities
        self.failures = 0
        self._x: np.ndarray | None = None
        self._hour = -1
        mpc = solver.mpc
        self._ib, self._is = mpc.index("b"), mpc.index("s")

    def decide(self, hour: int, soc: np.ndarray) -> Decision:
        """Solve hour ``hour``'s MPCs at ``soc`` (days, n)."""
        mpc = self.solver.mpc
        buy, sell = self.prices.window(hour, mpc.N)
        warm = None if self._x is None or hour != self._hour + 1 else mpc.shift(self._x)
        theta = self.theta
        if self._vectors is not None:
            theta = self._theta_rows
            if theta is None or len(theta) != len(soc):
                runs = len(self._vectors)
                if len(soc) % runs:
                    raise ValueError(f"{len(soc)} rows for {runs} thetas: expected equal blocks")
                theta = self._theta_rows = np.repeat(self._vectors, len(soc) // runs, axis=0)
        sol = self.solver.solve_batch(soc, buy, sell, theta, x0=warm)
        self.failures += int(np.count_nonzero(~sol.success))
        self._x = sol.x if warm is None else np.where(sol.success[:, None], sol.x, warm)
        self._hour = hour
        x = sol.x
        planned = np.maximum(x[:, self._ib].sum(axis=2), x[:, self._is].sum(axis=2)).max(axis=1)
        grad = sens_ok = grad_soc0 = None
        if self.sensitivities:
            sens = self.solver.sensitivity(sol)
            grad, sens_ok, grad_soc0 = sens.grad, sens.ok, sens.grad_soc0
        return Decision(sol.action, sol.success, planned, sens_ok, grad, sol, grad_soc0)

    def __call__(self, hour: int, soc: np.ndarray) -> np.ndarray:
        """The action :math:`\\pi` only (a plain policy)."""
        return self.decide(hour, soc).action


# -- the MPC in closed loop for a month -----------------------------------------------------------
def run_month(
    theta: Theta | Sequence[Theta],
    solver: Any,
    prices: Any,
    system: SystemConfig,
    rng: np.random.Generator | RunBlocks,
    exploration_std: float = 0.0,
    sensitivities: bool = True,
    soc0: float | np.ndarray | None = None,
    on_hour: Sequence[HourHook] = (),
    exploration_bounds: str = "symmetric",
    exploration_margin: float = 0.0,
) -> MonthRecord:
    """One month of the MPC in closed loop; every day of ``prices`` advances together.

    :func:`simulate` with :class:`MPCPolicy`, :class:`GaussianExploration` (when
    ``exploration_std > 0``) and, with ``sensitivities``, a :class:`SensitivityRecorder`.

    Parameters
    ----------
    theta
        MPC parameters used all month; for ``K`` runs in lockstep one per run, and then the
        record has ``K * days`` days, run by run (the days of ``prices`` repeated, ``rng`` a
        :class:`RunBlocks`).
    solver
        A back-end from :func:`mpcrl_lite.mpc.backends.registry.make_solver`.
    prices
        The month's prices (:class:`~mpcrl_lite.system.prices.Prices`: ``days``, ``buy``, ``sell``,
        ``window``).
    system
        The true system.
    rng
        Draws exploration (if ``exploration_std > 0``) then noise, each (days, n), per hour.
    exploration_std
        Std of the Gaussian exploration added to the MPC action.
    sensitivities
        Compute grad_theta pi at every solution (needed for learning).
    soc0
        Start of day soc (default ``system.soc0``), scalar, (n,) or (days, n).
    on_hour
        More hour hooks (see :func:`simulate`).
    exploration_bounds, exploration_margin
        How the exploration respects the bounds and where it is centred
        (:class:`GaussianExploration`'s ``bounds`` and ``margin``).

    Returns
    -------
    MonthRecord
        ``grad_pi`` of shape ``(H, D, n_theta, n)`` with ``sensitivities``, else None.
    """
    H = system.hours_per_day
    if not isinstance(theta, Theta):
        prices = _TiledPrices(prices, len(theta))
        if soc0 is not None and np.ndim(soc0) == 2:
            soc0 = np.tile(np.asarray(soc0, dtype=float), (len(theta), 1))
    # the whole month in one compiled call where it covers it
    compiled = _compiled_month(theta, solver, prices, system, rng=rng,
                               exploration_std=exploration_std, sensitivities=sensitivities,
                               soc0=soc0, bounds=exploration_bounds, margin=exploration_margin,
                               hooks=on_hour)
    if compiled is not None:
        return compiled
    recorder = SensitivityRecorder() if sensitivities else None
    explore = (GaussianExploration(exploration_std, system, exploration_bounds,
                                   exploration_margin) if exploration_std > 0 else None)
    record = simulate(
        MPCPolicy(solver, theta, prices, sensitivities), prices.buy[:, :H], prices.sell[:, :H],
        system, rng=rng, soc0=soc0, explore=explore,
        on_hour=[*on_hour, recorder] if recorder is not None else on_hour,
    )
    return MonthRecord.from_record(record, None if recorder is None else recorder.grad_pi)


def evaluation_rng(seed: int, draw: int) -> np.random.Generator:
    """The generator of evaluation draw ``draw`` (0, 1, ...) of ``seed``.

    Draw 0 is ``numpy.random.default_rng(seed)`` (the single draw of earlier versions);
    draw ``k > 0`` is seeded with the entropy ``[seed, k]``, so the draws are independent and
    the first ``K`` draws are the same whatever the number of draws asked for.
    """
    if isinstance(draw, bool) or not isinstance(draw, (int, np.integer)) or draw < 0:
        raise ValueError(f"draw={draw!r}: expected an integer >= 0")
    return np.random.default_rng(seed if draw == 0 else [int(seed), int(draw)])


def stacked_draws(prices: Any, system: SystemConfig, noise: Any) -> tuple[np.ndarray, Any]:
    """``noise`` of ``K >= 1`` draws of the month stacked draw by draw, as
    :func:`evaluate_mpc` stacks them (``(H, K * days, n)``: day ``d`` of draw ``k`` is column
    ``k * days + d``), checked, and ``prices`` with its days repeated to match; a
    ``ValueError`` naming the shape expected otherwise."""
    H, n = system.hours_per_day, system.n
    noise = np.asarray(noise, dtype=float)
    days = int(prices.days)
    if noise.ndim != 3 or noise.shape[0] != H or noise.shape[2] != n or noise.shape[1] == 0 \
            or noise.shape[1] % days:
        raise ValueError(f"noise has shape {noise.shape}: expected (hours, K * days, n) = "
                         f"({H}, K * {days}, {n}) for K >= 1 draws of the month")
    if not np.isfinite(noise).all():
        raise ValueError("noise has non-finite entries: expected finite MW")
    return noise, _TiledPrices(prices, noise.shape[1] // days)


class _TiledPrices:
    """``prices`` with its days repeated ``times`` times (``(times * days, ...)``): the
    forecast window of a copy's last day continues with day 0, as in the cyclic month."""

    def __init__(self, prices: Any, times: int) -> None:
        self.prices, self.times = prices, times
        self.buy = np.tile(np.asarray(prices.buy), (times, 1))
        self.sell = np.tile(np.asarray(prices.sell), (times, 1))
        self.days = self.buy.shape[0]

    def window(self, hour: int, N: int) -> tuple[np.ndarray, np.ndarray]:
        buy, sell = self.prices.window(hour, N)
        return np.tile(buy, (self.times, 1)), np.tile(sell, (self.times, 1))


def evaluate_mpc(
    theta: Theta,
    solver: Any,
    prices: Any,
    system: SystemConfig,
    seed: int,
    soc0: float | np.ndarray | None = None,
    draws: int = 1,
) -> MonthRecord:
    """The MPC at ``theta`` on ``draws`` fixed noise draws, without exploration and without
    sensitivities, all in one batched closed loop.

    Draw ``k`` is a month of the days of ``prices`` with the noise
    ``sample_noise(evaluation_rng(seed, k), (H, days, n))``; the draws are stacked as
    ``draws * days`` days (day ``d`` of draw ``k`` is day ``k * days + d`` of the record).
    The same seed gives every theta the same noise (common random numbers), so differences
    of :meth:`Record.J_per_day` are paired; :func:`draw_J` gives each draw's J. With
    ``draws=1`` the noise is that of ``numpy.random.default_rng(seed)`` used hour by hour.

    Returns
    -------
    MonthRecord
        Of ``draws * days`` days, ``grad_pi`` None.
    """
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1:
        raise ValueError(f"draws={draws!r}: expected an integer >= 1")
    if draws == 1:
        return run_month(theta, solver, prices, system, np.random.default_rng(seed),
                         exploration_std=0.0, sensitivities=False, soc0=soc0)
    H, D, n = system.hours_per_day, prices.days, system.n
    noise = np.concatenate([sample_noise(evaluation_rng(seed, k), (H, D, n), system)
                            for k in range(draws)], axis=1)
    if soc0 is not None and np.ndim(soc0) == 2:
        soc0 = np.tile(np.asarray(soc0, dtype=float), (draws, 1))
    tiled = _TiledPrices(prices, draws)
    compiled = _compiled_month(theta, solver, tiled, system, noise=noise, soc0=soc0)
    if compiled is not None:
        return compiled
    record = simulate(MPCPolicy(solver, theta, tiled), tiled.buy[:, :H], tiled.sell[:, :H],
                      system, noise=noise, soc0=soc0)
    return MonthRecord.from_record(record)


def _compiled_month(
    theta: Theta | Sequence[Theta], solver: Any, prices: Any, system: SystemConfig, *,
    rng: Any = None, noise: Any = None, exploration_std: float = 0.0,
    sensitivities: bool = False, soc0: Any = None, bounds: str = "symmetric",
    margin: float = 0.0, hooks: Sequence[HourHook] = (),
) -> MonthRecord | None:
    """The month of :func:`run_month` (noise from ``rng``) or of :func:`evaluate_mpc` (the
    ``noise`` given) in one compiled call (:mod:`mpcrl_lite.sim.compiled_month`), the same
    record to the last bit; None where that does not cover it (the caller then runs the
    Python loop, which also reports bad input).

    Hour ``hooks`` are allowed where each is ``replayable`` (a class attribute: it only reads
    the steps it is given, e.g. :class:`SensitivityRecorder` or
    :class:`~mpcrl_lite.learning.qlearning.ValueRecorder`): they get the month's
    :class:`HourStep` s after it, in the order of the hours, with the same arrays as the
    Python loop's (the solution of every hour included; ``grad_soc0`` is None)."""
    loop_parts = getattr(solver, "loop_parts", None)
    if loop_parts is None or not isinstance(system, SystemConfig) \
            or any(not getattr(hook, "replayable", False) for hook in hooks):
        return None
    from . import compiled_month

    if not compiled_month.ENABLED:
        return None
    H, D, n, N = system.hours_per_day, prices.days, system.n, solver.mpc.N
    explore = exploration_std > 0
    thetas = [theta] if isinstance(theta, Theta) else list(theta)
    if not thetas or any(not isinstance(t, Theta) or t.n != n for t in thetas) \
            or D % len(thetas) or solver.mpc.n != n \
            or (noise is None and not isinstance(rng, (np.random.Generator, RunBlocks))):
        return None
    parts = loop_parts(D)
    if not compiled_month.eligible(parts, n, bounds if explore else None, margin):
        return None
    buy, sell = _prices("buy", prices.buy[:, :H], H), _prices("sell", prices.sell[:, :H], H)
    if sell.shape != buy.shape:
        return None
    soc = _initial_soc(soc0, system, D)
    rows = np.repeat(np.stack([t.to_vector() for t in thetas]), D // len(thetas), axis=0)
    windows = [prices.window(k, N) for k in range(H)]
    wbuy, wsell = np.stack([w[0] for w in windows]), np.stack([w[1] for w in windows])
    if not (np.isfinite(rows).all() and np.isfinite(wbuy).all() and np.isfinite(wsell).all()):
        return None
    e = None
    if noise is None:  # the Python loop's draws: the exploration, then the noise, every hour
        e, noise = _month_draws(rng, (H, D, n), system, exploration_std if explore else None)
    else:
        noise = _finite("noise", noise).copy()
        if noise.shape != (H, D, n):
            return None
    arrays, grad_pi, statuses, kept = compiled_month.run(
        parts, system, solver.mpc, soc, rows, wbuy, wsell, buy, sell, e, noise,
        bool(sensitivities), bounds == "symmetric", keep=bool(hooks))
    if not arrays["solver_ok"].all():
        for k in range(H):  # the warnings of the hours with failed solves, as solve_batch logs
            solver.report_failures(statuses[k])
    if hooks:
        _replay(hooks, arrays, grad_pi, statuses, kept, solver, buy, sell)
    return MonthRecord.from_record(Record(system=system, **arrays), grad_pi)


def _month_draws(rng: np.random.Generator | RunBlocks, shape: tuple[int, int, int],
                 system: SystemConfig, exploration_std: float | None,
                 ) -> tuple[np.ndarray | None, np.ndarray]:
    """A month's exploration (None without) and noise, shape ``(H, D, n)``, as the Python
    loop draws them from ``rng`` hour by hour (the exploration's ``D x n`` standard normals
    times its std, then the noise's, :func:`~mpcrl_lite.system.battery.sample_noise`), in one
    call of the generator: the same numbers to the last bit, since numpy's generator draws a
    block of standard normals one after the other and its ``normal`` is ``mean + std * z``
    of them (``tests/sim/test_compiled_month.py`` compares the two). Runs in lockstep
    (:class:`RunBlocks`): each run's month from its own generator and system."""
    if isinstance(rng, RunBlocks):
        return rng.month_draws(shape, exploration_std)
    H, D, n = shape
    z = rng.standard_normal((H, 1 if exploration_std is None else 2, D, n))
    mean, std = battery_values(system, "noise_mean"), battery_values(system, "noise_std")
    noise = mean + std * z[:, -1]
    return (None if exploration_std is None else float(exploration_std) * z[:, 0]), noise


def _replay(hooks: Sequence[HourHook], arrays: dict[str, np.ndarray], grad: np.ndarray | None,
            statuses: np.ndarray, kept: dict[str, np.ndarray], solver: Any, buy: np.ndarray,
            sell: np.ndarray) -> None:
    """Call the ``replayable`` hour hooks of a compiled month with its hours' steps."""
    from ..mpc.solution import BatchSolution

    for k in range(statuses.shape[0]):
        solution = BatchSolution(
            action=arrays["policy"][k], x=kept["x"][k], lam=kept["lam"][k], mu=kept["mu"][k],
            cost=kept["cost"][k], success=arrays["solver_ok"][k],
            status=solver.status_strings(statuses[k]), iterations=kept["iterations"][k],
            p=kept["p"][k], backend=solver.name)
        decision = Decision(action=arrays["policy"][k], solver_ok=arrays["solver_ok"][k],
                            planned_power=arrays["planned_power"][k],
                            sens_ok=arrays["sens_ok"][k],
                            grad=None if grad is None else grad[k], solution=solution)
        result = StepResult(
            soc_next=arrays["soc"][k + 1], b=arrays["b"][k], s=arrays["s"][k],
            correction=arrays["correction"][k], agent_cost=arrays["agent_cost"][k],
            stage_cost=arrays["stage_cost"][k], grid_power=arrays["grid_power"][k])
        step_ = HourStep(k, arrays["soc"][k], decision, arrays["a"][k], arrays["noise"][k],
                         result, buy[:, k], sell[:, k])
        for hook in hooks:
            hook(step_)


def draw_J(record: Record, draws: int) -> np.ndarray:
    """J of each draw of an :func:`evaluate_mpc` record: the mean over each draw's days of
    :meth:`Record.J_per_day`, shape ``(draws,)``."""
    per_day = record.J_per_day()
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1 \
            or per_day.size % draws:
        raise ValueError(f"draws={draws!r}: expected an integer >= 1 dividing the record's "
                         f"{per_day.size} days")
    return per_day.reshape(draws, -1).mean(axis=1)


def rollout(
    policy: Policy,
    buy: Any,
    sell: Any,
    system: SystemConfig,
    rng: np.random.Generator,
    soc0: Any = None,
) -> Record:
    """A day of the true system under a plain policy, noise drawn hour by hour from ``rng``.

    The same as ``simulate(policy, buy, sell, system, rng=rng, soc0=soc0)``; when the policy
    does not draw from ``rng`` itself, the noise equals one draw
    ``sample_noise(rng, (hours, days, n), system)``.
    """
    if rng is None:
        raise ValueError("rng=None: expected a numpy.random.Generator (np.random.default_rng)")
    return simulate(policy, buy, sell, system, rng=rng, soc0=soc0)
