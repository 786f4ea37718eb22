r"""Decentralized learning: one local MPC and one learner per battery, grid limit by prices.

The paper learns one centralized MPC for all batteries and names decentralized learning as
future work. Here every battery ``i`` has

* its own MPC -- the paper's MPC (eq. 9) with ``n = 1`` -- and its own parameters
  :math:`\theta^i` (10 entries, see :mod:`mpcrl_lite.theta`);
* its own critic and actor: LSTD on its *own* cost :math:`\tilde L_i` with value features of
  its *own* soc, :math:`\Phi_i = [soc_i^2, soc_i, 1]`, and compatible features from its own
  policy sensitivity :math:`\nabla_{\theta^i}\pi^i`; the DPG step updates :math:`\theta^i`
  only.

The batteries share the grid: the limits :math:`\sum_i \hat b^i_j \le \bar P` and
:math:`\sum_i \hat s^i_j \le \bar P` (eq. 9f, at every predicted stage ``j``) couple them.
They are coordinated at every hour by grid-capacity prices per stage, added to every local
cost (:class:`~mpcrl_lite.decentralized.coordination.CoordinatedMPC`; the method, its tolerance, the limit
and the fallback are described in :mod:`mpcrl_lite.decentralized.coordination`). At convergence the local
solutions are the centralized MPC's solution for the stacked
:math:`\theta = (\theta^1, \dots, \theta^n)` (:func:`join_theta`): decentralizing changes
who computes the policy and how it learns, not the policy.

This module is the learner on top of it: the decentralized month in closed loop
(:func:`run_month_decentralized`), :class:`DecentralizedExperiment` and
:func:`compare_learners`. The coordination's names (:class:`CoordinatedMPC`,
:class:`CoordinatedSolution`, :func:`split_theta`, :func:`join_theta`, :func:`local_system`)
stay importable from here.

Learning and its approximation
------------------------------
Battery ``i`` uses :math:`\nabla_{\theta^i}\pi^i` computed from its own KKT system at the
final prices (the local MPC's KKT sensitivity: the compiled adjoint of
:class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver`, or
:class:`~mpcrl_lite.mpc.sensitivity.PolicySensitivity` on the reference path, see
:mod:`mpcrl_lite.decentralized.coordination`), i.e.
**at fixed grid prices**: the response of the prices to :math:`\theta^i` (and through them
of the other batteries) is ignored. That is exact when the grid limit is slack (the prices
are then ~0 and insensitive) and an approximation when it binds. Exploration is drawn per
battery and the explored actions are projected jointly onto the grid limit, as in the
centralized experiment; random draws follow the same order (per hour: exploration, then
noise), so with the same seed both experiments see the same noise.

Example
-------
>>> from mpcrl_lite import LearningConfig, MPCConfig, SystemConfig
>>> from mpcrl_lite.decentralized.learner import DecentralizedExperiment
>>> exp = DecentralizedExperiment(SystemConfig(), MPCConfig(), LearningConfig(months=2))
>>> history = exp.run(progress=False)                             # doctest: +SKIP
>>> history.update_info[-1]["coordination"]["iterations_mean"]    # doctest: +SKIP
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._util.jsonio import plain
from .._util.threads import one_blas_thread
from .._util.validate import check_int
from ..config import CoordinationConfig, LearningConfig, MPCConfig, SystemConfig
from ..learning.checkpoint import parse_theta
from ..learning.dpg import DPGUpdater
from ..learning.experiment import Experiment
from ..learning.history import History, MonthRecord
from ..learning.learner import Learner, resolve_setup
from ..learning.outdir import RunDirError
from ..learning.step import lstd_policy_gradient
from ..sim.closed_loop import Decision, simulate
from ..sim.exploration import GaussianExploration
from ..system.prices import Prices
from ..theta import PARTS, Theta
from .coordination import CoordinatedMPC, join_theta, split_theta
from .local_qp import local_system

__all__ = ["DecentralizedExperiment", "DecentralizedMonth", "compare_learners", "run_month_decentralized"]

log = logging.getLogger(__name__)

_FORMAT = "mpcrl_lite.DecentralizedCheckpoint/1"


# -- a month in closed loop -------------------------------------------------------------------
@dataclass(eq=False)
class DecentralizedMonth:
    """What a decentralized month adds to its :class:`~mpcrl_lite.learning.history.MonthRecord`.

    Arrays have a leading ``(H, D)`` (hours, days); ``n`` batteries.

    Attributes
    ----------
    grad_pi : numpy.ndarray, shape ``(H, D, n, 10)`` or None
        :math:`\\nabla_{\\theta^i}\\pi^i` at fixed grid prices.
    sens_ok, solver_ok : numpy.ndarray of bool, shape ``(H, D, n)``
    iterations : numpy.ndarray of int, shape ``(H, D)``
        Coordination rounds.
    converged, projected : numpy.ndarray of bool, shape ``(H, D)``
    violation : numpy.ndarray, shape ``(H, D)``
        Relative excess of the coordinated action over the grid limit before projection.
    price_max : numpy.ndarray, shape ``(H, D)``
        Largest grid-capacity price of the hour (over stages, buy and sell).
    solve_time : numpy.ndarray, shape ``(H,)``
        Wall time of each hour's coordination (all days).
    """

    grad_pi: np.ndarray | None
    sens_ok: np.ndarray
    solver_ok: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    projected: np.ndarray
    violation: np.ndarray
    price_max: np.ndarray
    solve_time: np.ndarray

    def summary(self, tol: float) -> dict[str, Any]:
        """Per-month coordination figures (JSON-friendly)."""
        return {
            "iterations_mean": float(self.iterations.mean()),
            "iterations_max": int(self.iterations.max()),
            "not_converged": int(np.count_nonzero(~self.converged)),
            "projected": int(np.count_nonzero(self.projected)),
            "limit_violations": int(np.count_nonzero(self.violation > tol)),
            "max_violation": float(self.violation.max()),
            "price_max": float(self.price_max.max()),
            "solve_time_s": float(self.solve_time.sum()),
            "tol": float(tol),
        }


def run_month_decentralized(
    thetas: Theta | Sequence[Theta],
    policy: CoordinatedMPC,
    prices: Prices,
    system: SystemConfig,
    rng: np.random.Generator,
    exploration_std: float = 0.0,
    sensitivities: bool = True,
    soc0: float | np.ndarray | None = None,
    exploration_bounds: str = "symmetric",
) -> tuple[MonthRecord, DecentralizedMonth]:
    """One month in closed loop with the coordinated local MPCs.

    The counterpart of :func:`mpcrl_lite.sim.closed_loop.run_month` (the same loop,
    :func:`~mpcrl_lite.sim.closed_loop.simulate`), with the same draws in the same order (per
    hour: exploration ``(days, n)`` if ``exploration_std > 0``, then noise ``(days, n)``).

    Parameters
    ----------
    thetas : Theta with ``n`` agents, or ``n`` Theta with ``n = 1``
    policy : CoordinatedMPC
    prices : Prices
        ``prices.days`` days advancing together.
    system : SystemConfig
    rng : numpy.random.Generator
    exploration_std : float
        Std of the Gaussian exploration added to each battery's action (then kept jointly
        within the input bounds and the grid limit as ``exploration_bounds`` says,
        :class:`~mpcrl_lite.sim.exploration.GaussianExploration`).
    sensitivities : bool
        Compute :math:`\\nabla_{\\theta^i}\\pi^i` (needed for learning).
    soc0 : float or array, optional
        Start-of-day soc (default ``system.soc0``), scalar, ``(n,)`` or ``(days, n)``.
    exploration_bounds : str
        ``LearningConfig.exploration_bounds`` (a margin is not used here: the exploration is
        centred on the policy's action, as the critic assumes).

    Returns
    -------
    record : MonthRecord
        As in the centralized experiment (``solver_ok``/``sens_ok`` are True where every
        battery's local problem / sensitivity was fine; ``grad_pi`` is None).
    extra : DecentralizedMonth
    """
    D, H, n, N = prices.days, system.hours_per_day, system.n, system.N
    solver_ok = np.zeros((H, D, n), bool)
    sens_ok = np.zeros((H, D, n), bool)
    grad_pi = np.zeros((H, D, n, len(PARTS))) if sensitivities else None
    iters = np.zeros((H, D), int)
    conv, proj = np.zeros((H, D), bool), np.zeros((H, D), bool)
    viol, pmax = np.zeros((H, D)), np.zeros((H, D))
    times = np.zeros(H)

    def decide(k: int, soc: np.ndarray) -> Decision:
        buy_w, sell_w = prices.window(k, N)
        sol = policy.solve(soc, buy_w, sell_w, thetas)
        solver_ok[k] = sol.success
        iters[k], conv[k], proj[k] = sol.iterations, sol.converged, sol.projected
        viol[k] = sol.violation
        pmax[k] = np.maximum(sol.price_buy.max(1), sol.price_sell.max(1))
        times[k] = sol.solve_time
        if sensitivities:
            grad_pi[k], sens_ok[k] = policy.sensitivity(sol)
        return Decision(sol.action, solver_ok[k].all(-1), sol.planned_power, sens_ok[k].all(-1))

    explore = (GaussianExploration(exploration_std, system, exploration_bounds)
               if exploration_std > 0 else None)
    record = MonthRecord.from_record(simulate(
        decide, prices.buy[:, :H], prices.sell[:, :H], system, rng=rng, soc0=soc0, explore=explore
    ))
    extra = DecentralizedMonth(grad_pi, sens_ok, solver_ok, iters, conv, proj, viol, pmax, times)
    return record, extra


# -- the learning experiment ------------------------------------------------------------------
class DecentralizedExperiment(Learner):
    """Decentralized learning run with the interface of :class:`~mpcrl_lite.learning.experiment.Experiment`.

    Every month all batteries act with their coordinated local MPCs; at the month's end each
    battery fits its own compatible critic (LSTD on :math:`\\tilde L_i`, value features of
    :math:`soc_i`) and takes its own DPG step on :math:`\\theta^i`. The results go into a
    :class:`~mpcrl_lite.learning.history.History` (theta per month is the stacked
    :func:`join_theta`, so every plot works); ``History.update_info`` holds per month the
    coordination figures (``"coordination"``: mean/max rounds, projections, limit
    violations, largest price) and each battery's critic/actor diagnostics (``"agents"``).

    Parameters
    ----------
    system, mpc_config, learning
        As for :class:`~mpcrl_lite.learning.experiment.Experiment` (defaults: the paper's).
    prices : Prices, optional
        Default: the embedded month, ``learning.days_per_month`` days.
    theta0 : Theta, optional
        Initial parameters with ``n`` agents (default :meth:`Theta.nominal`), split into the
        batteries' ``theta^i``.
    coordination : CoordinationConfig, optional
    callbacks : sequence of callables ``callback(month, history, experiment)``
    """

    KIND = "decentralized"
    FORMAT = _FORMAT
    DESC = "learning (decentralized)"

    def __init__(
        self,
        system: SystemConfig | None = None,
        mpc_config: MPCConfig | None = None,
        learning: LearningConfig | None = None,
        prices: Prices | None = None,
        theta0: Theta | None = None,
        coordination: CoordinationConfig | None = None,
        callbacks: Sequence[Callable[[int, History, DecentralizedExperiment], None]] = (),
    ) -> None:
        self.system, self.mpc_config, self.learning, self.prices, theta0 = resolve_setup(
            system, mpc_config, learning, prices, theta0
        )
        if self.learning.gradient != "critic":
            raise ValueError(f"learning.gradient={self.learning.gradient!r}: the decentralized "
                             "learners use their critics; expected 'critic'")
        if self.learning.critic_months != 1:
            raise ValueError(f"learning.critic_months={self.learning.critic_months!r}: each "
                             "decentralized learner fits its critic on its own month; expected 1")
        self.coordination = coordination or CoordinationConfig()
        self.thetas = split_theta(theta0)
        self.callbacks = list(callbacks)
        self.policy = CoordinatedMPC(self.system, self.mpc_config, self.coordination)
        self.updaters = self._new_updaters()
        self.rng = np.random.default_rng(self.learning.seed)
        self.history = History(self.system, self.mpc_config, self.learning, backend=self.backend)
        self.history.prices_origin = dict(getattr(self.prices, "origin", {}) or {})

    def _new_updaters(self) -> list[DPGUpdater]:
        """One fresh optimizer per battery, each with its local system's scales."""
        return [DPGUpdater.from_configs(self.learning, self._local(i), self.prices)
                for i in range(self.system.n)]

    def _local(self, battery: int) -> SystemConfig:
        """Battery ``battery``'s own local system (its alpha scales its updater's steps)."""
        return local_system(self.system, self.coordination.local_grid_factor, battery)

    @property
    def backend(self) -> str:
        """Name recorded in the History."""
        return f"decentralized(n={self.system.n}, tol={self.coordination.tol:g})"

    @property
    def theta(self) -> Theta:
        """The batteries' current parameters stacked into one :class:`Theta`."""
        return join_theta(self.thetas)

    def configs(self) -> dict[str, Any]:
        """The configurations a checkpoint must match (the coordination's too)."""
        return {**super().configs(), "coordination": self.coordination}

    # -- one learning step ----------------------------------------------------------------
    @one_blas_thread
    def learning_step(
        self, record: MonthRecord, extra: DecentralizedMonth
    ) -> tuple[list[np.ndarray], int, list[dict[str, Any]]]:
        """Each battery's LSTD fit and policy gradient on its own cost and soc
        (:func:`mpcrl_lite.learning.step.lstd_policy_gradient`); returns ``(grads, skipped,
        infos)`` with ``grads[i]`` of shape ``(len(PARTS),)``."""
        grads, infos = [], []
        any_skipped = np.zeros(record.stage_cost.shape, bool)
        for i in range(self.system.n):
            use = extra.sens_ok[..., i] & extra.solver_ok[..., i]
            any_skipped |= ~use
            mine = slice(i, i + 1)
            grad, info = lstd_policy_gradient(
                record.soc[..., mine], record.a[..., mine], record.policy[..., mine],
                extra.grad_pi[:, :, i, :, None], record.agent_cost[..., i], use,
                self.learning, self.system.gamma, record.buy,
            )
            if use.any():  # the metric of the natural gradient and of the trust region
                self.updaters[i].observe(extra.grad_pi[:, :, i, :, None][use])
            grads.append(grad)
            infos.append(info)
        return grads, int(np.count_nonzero(any_skipped)), infos

    @one_blas_thread
    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current parameters and update every battery."""
        t0 = time.perf_counter()
        used = list(self.thetas)
        record, extra = run_month_decentralized(
            used, self.policy, self.prices, self.system, self.rng,
            exploration_std=self.learning.exploration_std, sensitivities=True,
            exploration_bounds=self.learning.exploration_bounds,
        )
        self.write_deferred()  # the last month's journal line, beside this update
        grads, skipped, infos = self.learning_step(record, extra)
        n = self.system.n
        full_grad = np.zeros(len(PARTS) * n)
        for i in range(n):
            self.thetas[i] = self.updaters[i].step(used[i], grads[i])
            infos[i].update(self.updaters[i].last_info)
            full_grad[i::n] = grads[i]  # part-major order of Theta.to_vector
        info = {"coordination": extra.summary(self.coordination.tol), "agents": infos}
        info = plain(info)  # as it reads back from history.json (no NaN: null)
        self.history.append(record, join_theta(used), full_grad, skipped,
                            time.perf_counter() - t0, info)
        self.history.theta_final = self.theta.to_vector().tolist()
        return record

    # -- checkpoints ----------------------------------------------------------------------
    def learner_state(self) -> dict[str, Any]:
        """The stacked theta and every battery's optimizer state (part of
        ``checkpoint.json``)."""
        return {"theta": self.theta.to_vector().tolist(),
                "updaters": [u.state_dict() for u in self.updaters]}

    def restore_learner_state(self, state: dict[str, Any], where: str) -> Callable[[], None]:
        """Check the thetas and optimizer states of a checkpoint; return their application."""
        thetas = split_theta(parse_theta(state["theta"], self.system.n, where))
        saved = state["updaters"]
        if not isinstance(saved, list) or len(saved) != self.system.n:
            raise RunDirError(f"{where}: 'updaters' is not a list of {self.system.n} optimizer "
                              "states; start over with --force")
        fresh = self._new_updaters()  # len(saved) == n, checked above
        try:
            for updater, s in zip(fresh, saved):
                updater.load_state_dict(s)
        except (TypeError, ValueError, KeyError, AttributeError) as err:
            raise RunDirError(f"{where}: bad 'updaters' ({err}); start over with --force") from None

        def apply() -> None:
            self.thetas = thetas
            for updater, new in zip(self.updaters, fresh):
                updater.load_state_dict(new.state_dict())
            self.history.backend = self.backend

        return apply


# -- centralized vs decentralized ----------------------------------------------------------
def compare_learners(
    system: SystemConfig | None = None,
    mpc_config: MPCConfig | None = None,
    learning: LearningConfig | None = None,
    months: int = 2,
    coordination: CoordinationConfig | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Run the centralized and the decentralized learner on the same configuration.

    Both start from :meth:`Theta.nominal`, use the same prices and seed (hence the same
    noise) and run ``months`` months of ``learning.days_per_month`` days.

    Returns
    -------
    dict
        ``{"centralized": {...}, "decentralized": {...}, "settings": {...}}``; each learner
        has ``J`` and ``J_per_agent`` per month, ``hours_soc_below_0_1``, the largest
        commanded and applied grid power, ``limit_violations`` (hours x days whose
        commanded action exceeds ``P_bar (1 + tol)``), ``wall_time_s`` per month and
        ``ms_per_step`` (one control step: all days of one hour, sensitivities and the
        month-end update included, i.e. month wall time / hours) and ``theta_final`` (as
        :meth:`Theta.to_dict`; the decentralized one is the stacked :func:`join_theta`, whose
        centralized MPC has the same policy). The decentralized entry also holds the
        coordination figures per month.
    """
    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig()
    learning = learning or LearningConfig()
    coordination = coordination or CoordinationConfig()
    check_int("months", months, 1)
    learning = learning.replace(months=months)
    runs = {
        "centralized": Experiment(system, mpc_config, learning),
        "decentralized": DecentralizedExperiment(system, mpc_config, learning,
                                                 coordination=coordination),
    }
    result: dict[str, Any] = {
        "settings": {
            "system": system.to_dict(), "mpc": mpc_config.to_dict(),
            "learning": learning.to_dict(), "coordination": coordination.to_dict(),
        }
    }
    tol = coordination.tol
    for name, exp in runs.items():
        commanded: list[float] = []
        violations: list[int] = []

        def watch(month: int, history: History, _exp: Any,
                  commanded: list[float] = commanded, violations: list[int] = violations) -> None:
            a = history.last_month.a
            power = np.maximum(np.maximum(a, 0).sum(-1), np.maximum(-a, 0).sum(-1))
            commanded.append(float(power.max()))
            violations.append(int(np.count_nonzero(power > system.P_bar * (1 + tol))))

        exp.callbacks.append(watch)
        history = exp.run(months=months, progress=progress)
        H = system.hours_per_day
        entry = {
            "backend": history.backend,
            "J": list(history.J),
            "J_per_agent": list(history.J_per_agent),
            "hours_soc_below_0_1": list(history.hours_soc_below_0_1),
            "max_P_commanded": commanded,
            "max_P_applied": list(history.max_P_applied),
            "limit_violations": violations,
            "wall_time_s": list(history.wall_time_s),
            "ms_per_step": [1000 * t / H for t in history.wall_time_s],
            "skipped_steps": list(history.skipped_steps),
            "theta_final": history.final_theta().to_dict(),
        }
        if name == "decentralized":
            entry["coordination"] = [info["coordination"] for info in history.update_info]
        result[name] = entry
    return result
