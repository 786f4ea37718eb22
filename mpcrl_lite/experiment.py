r"""The learning experiment: months of 30 days in closed loop, one DPG update per month.

Every month (paper, Section IV):

1. all days of the month start at ``soc0`` and advance together, hour by hour: at hour
   ``k`` one call solves the MPC of every day (:mod:`mpcrl_lite.solvers`), the policy
   sensitivities are computed at the solutions (:mod:`mpcrl_lite.sensitivity`), Gaussian
   exploration is added to the MPC action and projected onto the input bounds and the grid
   limit (:func:`mpcrl_lite.model.project_action`), and the true system takes a step
   (:func:`mpcrl_lite.model.step`) -- the one closed loop,
   :func:`mpcrl_lite.closed_loop.run_month`;
2. LSTD fits the compatible action-value function on the month's transitions
   (:func:`mpcrl_lite.lstd.lstd_q`); each day is an episode, so the last hour of a day does
   not bootstrap (the next day restarts at ``soc0``). The value baseline uses
   :func:`value_baseline_features` (``LearningConfig.value_features``);
3. the policy gradient ``mean(grad pi grad pi^T w)`` moves theta
   (:class:`mpcrl_lite.dpg.DPGUpdater`);
4. every ``LearningConfig.eval_every`` months the parameters of the month are evaluated:
   one more month of the same days on a fixed noise draw (``LearningConfig.eval_seed``),
   without exploration and without sensitivities (:meth:`Experiment.evaluate`). Its J is
   recorded as ``History.J_eval``: the month's own J moves by +-200 from month to month with
   its new noise and exploration, J_eval only with the parameters.

Random draws come from one ``numpy.random.Generator`` seeded with ``LearningConfig.seed``,
in a fixed order (per hour: exploration, then noise), so a seed fixes a run; the evaluation
draws from its own generator, created anew from ``eval_seed`` each time, so it never changes
the learning run. After every
month the run can be checkpointed (History, theta, the updater's state and the generator's
state, all as JSON/npz) and resumed with identical results.

Hours whose MPC failed use the fallback action (idle) and, like hours whose KKT system was
unusable, are left out of LSTD and of the gradient; :attr:`History.skipped_steps` counts
them.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm.auto import tqdm

from .closed_loop import evaluate_mpc, run_month
from .config import LearningConfig, MPCConfig, SystemConfig
from .dpg import DPGUpdater, policy_gradient
from .history import History
from .lstd import compatible_features, lstd_q, value_baseline_features
from .mpc import MPC
from .prices import Prices
from .record import MonthRecord
from .solvers import make_solver
from .theta import Theta

# run_month (mpcrl_lite.closed_loop) and value_baseline_features (mpcrl_lite.lstd) stay
# importable from here.
__all__ = ["Callback", "Experiment", "run_month", "run_months", "value_baseline_features"]

log = logging.getLogger(__name__)

#: ``callback(month_index, history, experiment)``, called after each month's update.
Callback = Callable[[int, History, "Experiment"], None]

CHECKPOINT = "checkpoint.json"


def run_months(
    learner: Any,
    months: int | None,
    out: str | Path | None,
    resume: bool,
    progress: bool,
    desc: str = "learning",
) -> History:
    """The month loop shared by every learner (:class:`Experiment` and
    :class:`~mpcrl_lite.decentralized.DecentralizedExperiment`).

    ``learner`` provides ``learning``, ``history``, ``callbacks``, ``run_one_month()``,
    ``save_checkpoint(dir)`` and ``load_checkpoint(dir)``. Runs until ``months`` months are
    recorded (default ``learning.months``); with ``out`` a checkpoint is written after every
    month, with ``resume`` a run found in ``out`` continues where it stopped.
    """
    months = learner.learning.months if months is None else months
    if isinstance(months, bool) or not isinstance(months, int) or months < 1:
        raise ValueError(f"months={months!r}: expected an integer >= 1")
    out = Path(out) if out is not None else None
    if resume:
        if out is None:
            raise ValueError("resume=True needs out=DIR (where the checkpoint is)")
        if (out / CHECKPOINT).exists():
            learner.load_checkpoint(out)
    history = learner.history
    bar = tqdm(total=months, initial=min(history.months, months), desc=desc, unit="month",
               disable=not progress)
    with bar:
        while learner.history.months < months:
            learner.run_one_month()
            history = learner.history
            m = history.months - 1
            postfix = {"J": f"{history.J[-1]:.1f}"}
            if history.J_eval:
                postfix["J_eval"] = f"{history.J_eval[-1]:.1f}"
            bar.set_postfix(postfix, refresh=False)
            bar.update(1)
            if out is not None:
                learner.save_checkpoint(out)
            for callback in learner.callbacks:
                callback(m, history, learner)
    return learner.history

def resolve_setup(
    system: SystemConfig | None,
    mpc_config: MPCConfig | None,
    learning: LearningConfig | None,
    prices: Prices | None,
    theta0: Theta | None,
) -> tuple[SystemConfig, MPCConfig, LearningConfig, Prices, Theta]:
    """Defaults and consistency checks shared by every learner: the paper's configs, the
    shipped month cut to ``days_per_month`` days, theta0 = the nominal model; prices with
    another number of days or a theta0 for another ``n`` are errors."""
    system = system or SystemConfig()
    mpc_config = mpc_config or MPCConfig()
    learning = learning or LearningConfig()
    if prices is None:
        prices = Prices.month(system, learning.days_per_month)
    if prices.days != learning.days_per_month:
        raise ValueError(
            f"prices have {prices.days} days; expected days_per_month={learning.days_per_month}"
        )
    theta0 = theta0 or Theta.nominal(system)
    if theta0.n != system.n:
        raise ValueError(f"theta0 has n={theta0.n}; expected n={system.n}")
    return system, mpc_config, learning, prices, theta0


class Experiment:
    """The paper's learning run: months x days, LSTD critic, DPG update at each month's end.

    With the default configurations (:mod:`mpcrl_lite.config`) every month's parameters are
    also evaluated on a fixed noise draw (:meth:`evaluate`, ``History.J_eval``), which shows
    the learning trend without the month-to-month noise of ``History.J``.

    Parameters
    ----------
    system, mpc_config, learning
        Configurations (defaults: the paper's).
    prices
        The month's prices (default: the embedded NO3 profile, first
        ``learning.days_per_month`` days).
    theta0
        Initial parameters (default :meth:`Theta.nominal`).
    callbacks
        Called after every month as ``callback(month, history, experiment)``.
    """

    def __init__(
        self,
        system: SystemConfig | None = None,
        mpc_config: MPCConfig | None = None,
        learning: LearningConfig | None = None,
        prices: Prices | None = None,
        theta0: Theta | None = None,
        callbacks: Sequence[Callback] = (),
    ) -> None:
        self.system, self.mpc_config, self.learning, self.prices, self.theta = resolve_setup(
            system, mpc_config, learning, prices, theta0
        )
        self.callbacks = list(callbacks)
        self.mpc = MPC(self.system)
        self.solver = make_solver(self.mpc, self.mpc_config, self.theta)
        self.updater = DPGUpdater.from_configs(self.learning, self.system)
        self.rng = np.random.default_rng(self.learning.seed)
        self.history = History(self.system, self.mpc_config, self.learning, backend=self.solver.name)

    # -- one learning step ----------------------------------------------------------------
    def learning_step(self, record: MonthRecord) -> tuple[np.ndarray, int, dict[str, Any]]:
        """LSTD + policy gradient from a month; returns ``(grad, skipped, info)``."""
        sysc = self.system
        H = sysc.hours_per_day
        use = record.sens_ok & record.solver_ok
        skipped = int(use.size - np.count_nonzero(use))
        if not use.any():
            return np.zeros(self.mpc.n_theta), skipped, {"lstd": "no usable samples"}
        features = value_baseline_features(record.soc, self.learning.value_features)
        phi, phi_next = features[:-1], features[1:]
        psi = compatible_features(record.grad_pi, record.a, record.policy)
        done = np.broadcast_to((np.arange(H) == H - 1)[:, None], use.shape)
        fit = lstd_q(
            phi[use], psi[use], record.stage_cost[use], phi_next[use], sysc.gamma,
            done=done[use], ridge=self.learning.ridge,
        )
        grad = policy_gradient(record.grad_pi[use], fit.w)
        info = {
            "lstd_condition": float(fit.condition),
            "lstd_rank_deficient": bool(fit.rank_deficient),
            "td_rms": float(fit.td_rms),
            "samples": int(fit.n_samples),
        }
        return grad, skipped, info

    # -- evaluation -----------------------------------------------------------------------
    def evaluate(self, theta: Theta | None = None) -> MonthRecord:
        """J of ``theta`` (default: the current parameters) on the fixed evaluation draw.

        The month's days are run once more with noise from a generator seeded with
        ``LearningConfig.eval_seed`` (the same draw every time), without exploration and
        without sensitivities. The learning generator is not touched.
        """
        theta = self.theta if theta is None else theta
        self._check_solver(theta)
        return evaluate_mpc(theta, self.solver, self.prices, self.system,
                            self.learning.eval_seed)

    def evaluation_due(self, month: int) -> bool:
        """True when month ``month`` (counted from 0) is evaluated: every
        ``eval_every`` months and the last month of ``LearningConfig.months``."""
        every = self.learning.eval_every
        return every > 0 and (month % every == 0 or month == self.learning.months - 1)

    def _check_solver(self, theta: Theta) -> None:
        if self.mpc_config.backend == "auto" and not theta.is_convex() and self.solver.name != "ipopt":
            log.info("theta is no longer convex: switching the MPC back-end to IPOPT")
            self.solver = make_solver(self.mpc, self.mpc_config.replace(backend="ipopt"))
            self.history.backend = self.solver.name

    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current theta and update it (and evaluate the
        month's theta when :meth:`evaluation_due`)."""
        t0 = time.perf_counter()
        theta_used = self.theta
        month = self.history.months
        self._check_solver(theta_used)
        record = run_month(
            theta_used, self.solver, self.prices, self.system, self.rng,
            exploration_std=self.learning.exploration_std, sensitivities=True,
        )
        grad, skipped, info = self.learning_step(record)
        self.theta = self.updater.step(theta_used, grad)
        info.update(self.updater.last_info)
        info = json.loads(json.dumps(info, default=_jsonable))
        record.grad_pi = None  # large; not kept in the history
        wall_time = time.perf_counter() - t0
        if self.evaluation_due(month):
            t1 = time.perf_counter()
            self.history.append_evaluation(month, self.evaluate(theta_used))
            info["eval_time_s"] = time.perf_counter() - t1
        self.history.append(record, theta_used, grad, skipped, wall_time, info)
        self.history.theta_final = self.theta.to_vector().tolist()
        return record

    # -- the run --------------------------------------------------------------------------
    def run(
        self,
        months: int | None = None,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
    ) -> History:
        """Run until ``months`` months are recorded (default ``learning.months``).

        With ``out``, a checkpoint is written after every month; with ``resume`` a run
        found in ``out`` continues where it stopped (same results as an uninterrupted run).
        """
        return run_months(self, months, out, resume, progress, desc="learning")

    # -- checkpoints ----------------------------------------------------------------------
    def save_checkpoint(self, directory: str | Path) -> None:
        """History plus everything needed to continue (theta, optimizer, RNG state)."""
        directory = Path(directory)
        self.history.save(directory)
        state = {
            "format": "mpcrl_lite.Checkpoint/1",
            "months_done": self.history.months,
            "theta": self.theta.to_vector().tolist(),
            "updater": self.updater.state_dict(),
            "rng": self.rng.bit_generator.state,
            "system": self.system.to_dict(),
            "mpc": self.mpc_config.to_dict(),
            "learning": self.learning.to_dict(),
        }
        write_checkpoint(directory, state)

    def load_checkpoint(self, directory: str | Path) -> None:
        """Continue from :meth:`save_checkpoint`'s files; the configs must match."""
        directory = Path(directory)
        state = json.loads((directory / CHECKPOINT).read_text())
        for key, cfg in (("system", self.system), ("mpc", self.mpc_config), ("learning", self.learning)):
            saved = type(cfg).from_dict(state[key])
            mine = cfg if key != "learning" else cfg.replace(months=saved.months)
            if saved != mine:
                raise ValueError(
                    f"checkpoint in {directory} was written with a different {key} config: "
                    f"{saved} vs {cfg}"
                )
        self.history = History.load(directory)
        self.theta = Theta.from_vector(np.asarray(state["theta"]), self.system.n)
        self.updater.load_state_dict(state["updater"])
        self.rng.bit_generator.state = state["rng"]
        self._check_solver(self.theta)
        self.history.backend = self.solver.name


def write_checkpoint(directory: Path, state: dict[str, Any]) -> None:
    """Write a learner's checkpoint state as ``directory/checkpoint.json`` atomically (a
    temporary file renamed into place, so an interruption never leaves half a checkpoint)."""
    tmp = directory / (CHECKPOINT + ".tmp")
    tmp.write_text(json.dumps(state, indent=1, default=_jsonable))
    tmp.replace(directory / CHECKPOINT)


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot store {type(value).__name__} in JSON")
