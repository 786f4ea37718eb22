r"""The learning experiment: months of 30 days in closed loop, one DPG update per month.

Every month (paper, Section IV):

1. all days of the month start at ``soc0`` and advance together, hour by hour: at hour
   ``k`` one call solves the MPC of every day (:mod:`mpcrl_lite.mpc.backends.registry`), the policy
   sensitivities are computed at the solutions (:mod:`mpcrl_lite.mpc.sensitivity`), Gaussian
   exploration is added to the MPC action and kept within the input bounds and the grid
   limit with a zero mean (:func:`mpcrl_lite.sim.exploration.bounded_exploration`,
   ``LearningConfig.exploration_bounds``), and the true system takes a step
   (:func:`mpcrl_lite.system.battery.step`) -- the one closed loop,
   :func:`mpcrl_lite.sim.closed_loop.run_month`;
2. LSTD fits the compatible action-value function on the month's transitions
   (:func:`mpcrl_lite.learning.lstd.lstd_q`); each day is an episode, so the last hour of a day does
   not bootstrap (the next day restarts at ``soc0``). The value baseline uses
   :func:`value_baseline_features` (``LearningConfig.value_features``) (with ``LearningConfig.critic_months > 1``, on
   the transitions of that many months, :mod:`mpcrl_lite.learning.critic_samples`);
3. the policy gradient ``mean(grad pi grad pi^T w)`` moves theta
   (:class:`mpcrl_lite.learning.dpg.DPGUpdater`);
4. every ``LearningConfig.eval_every`` months the parameters of the month are evaluated:
   the month's days once more on each of ``LearningConfig.eval_draws`` fixed noise draws
   (derived from ``eval_seed``, all draws in one batched closed loop), without exploration
   and without sensitivities (:meth:`Experiment.evaluate`). The mean of the draws' J is
   recorded as ``History.J_eval``, with its 95 % confidence interval over the draws
   (``J_eval_ci_low``, ``J_eval_ci_high``): the month's own J moves by +-200 from month to
   month with its new noise and exploration, J_eval only with the parameters.

Random draws come from one ``numpy.random.Generator`` seeded with ``LearningConfig.seed``,
in a fixed order (per hour: exploration, then noise), so a seed fixes a run; the evaluation
draws from its own generators, created anew from ``eval_seed`` each time, so it never
changes the learning run (J and theta of the learning months). After every month the run can be committed to a run directory (History, theta, the updater's state and
the generator's state, all as JSON/npz, :mod:`mpcrl_lite.learning.rundir`) and resumed with identical
results; the month loop, the checkpoints and the learning step are shared with the
decentralized learner (:mod:`mpcrl_lite.learning.learner`).

Hours whose MPC failed use the fallback action (idle) and, like hours whose KKT system was
unusable, are left out of LSTD and of the gradient; :attr:`History.skipped_steps` counts
them.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np

from .._util.jsonio import plain
from .._util.threads import one_blas_thread
from ..config import LearningConfig, MPCConfig, SystemConfig
from ..mpc.backends.registry import make_solver
from ..mpc.formulation import MPC
from ..sim.closed_loop import evaluate_mpc, run_month
from ..sim.exploration import exploration_center
from ..sim.record import MonthRecord
from ..system.prices import Prices
from ..theta import Theta
from . import rundir
from .checkpoint import parse_theta
from .critic_samples import CriticSamples
from .dpg import DPGUpdater
from .eval_worker import EvaluationWorker, worth_a_worker
from .history import History
from .learner import Learner, resolve_setup
from .outdir import RunDirError
from .pathwise import PathwiseGradient, PathwiseRecorder, pathwise_policy_gradient
from .step import lstd_policy_gradient

# run_month (mpcrl_lite.sim.closed_loop), value_baseline_features (mpcrl_lite.learning.lstd), run_months
# and resolve_setup (mpcrl_lite.learning.learner) stay importable from here.
__all__ = ["Callback", "Experiment"]

log = logging.getLogger(__name__)

#: ``callback(month_index, history, experiment)``, called after each month's update.
Callback = Callable[[int, History, "Experiment"], None]


class Experiment(Learner):
    """The paper's learning run: months x days, LSTD critic, DPG update at each month's end.

    With the default configurations (:mod:`mpcrl_lite.config`) every month's parameters are
    also evaluated on ``LearningConfig.eval_draws`` fixed noise draws (:meth:`evaluate`,
    ``History.J_eval`` and its confidence interval), which shows the learning trend without
    the month-to-month noise of ``History.J``.

    Parameters
    ----------
    system, mpc_config, learning
        Configurations (defaults: the paper's).
    prices
        The month's prices (default: the embedded NO3 profile, first
        ``learning.days_per_month`` days); the MPC sees them through
        ``mpc_config.forecast`` (:func:`mpcrl_lite.system.forecast.forecast_prices`), kept as
        :attr:`prices`.
    theta0
        Initial parameters (default ``learning.theta0`` where set, else
        :meth:`Theta.nominal`; both given must agree).
    callbacks
        Called after every month as ``callback(month, history, experiment)``.
    """

    KIND = "centralized"
    FORMAT = "mpcrl_lite.Checkpoint/1"
    DESC = "learning"
    #: The optimizer's class (built with ``from_configs(learning, system)``).
    UPDATER: Any = DPGUpdater

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
        self.updater = self.UPDATER.from_configs(self.learning, self.system, self.prices)
        self.rng = np.random.default_rng(self.learning.seed)
        # the pathwise gradient recorded while the month ran: (its record, the gradient)
        self._pathwise: tuple[MonthRecord, PathwiseGradient] | None = None
        self.history = History(self.system, self.mpc_config, self.learning, backend=self.solver.name)
        self.history.prices_origin = dict(getattr(self.prices, "origin", {}) or {})
        # the critic's samples of the months before the last (LearningConfig.critic_months)
        self._critic_memory: collections.deque[CriticSamples] = collections.deque(
            maxlen=self.learning.critic_months - 1)
        # evaluations out in the worker process: (month, theta, future), oldest first
        self._worker: EvaluationWorker | None = None
        self._pending: list[tuple[int, Theta, Future]] = []

    # -- one learning step ----------------------------------------------------------------
    @one_blas_thread
    def learning_step(self, record: MonthRecord) -> tuple[np.ndarray, int, dict[str, Any]]:
        """LSTD + policy gradient from a month (:func:`mpcrl_lite.learning.step.lstd_policy_gradient`
        on all batteries and the stage cost); returns ``(grad, skipped, info)``.

        With ``LearningConfig.gradient = 'pathwise'`` the gradient is instead the exact
        derivative of the month's discounted cost in theta on the month's noise
        (:func:`mpcrl_lite.learning.pathwise.pathwise_policy_gradient` at the current theta,
        the one the month was simulated with); a day with a failed solve is left out
        (``skipped`` counts its hours).

        With ``LearningConfig.critic_months = K > 1`` the critic is fitted on this month's
        samples and those of the ``K - 1`` months before it (:mod:`mpcrl_lite.learning.critic_samples`;
        each call adds its month to the ones kept, and ``info['critic_months']`` says how many
        the fit used)."""
        if self.learning.gradient == "pathwise":
            pending, self._pathwise = self._pathwise, None
            if pending is not None and pending[0] is record:  # recorded as the month ran
                result = pending[1]
            else:  # a month simulated without the recorder: the month once more
                result = pathwise_policy_gradient(self.theta, self.solver, self.prices,
                                                  self.system, record.noise,
                                                  soc0=record.soc[0])
            days_left_out = int(np.count_nonzero(~result.ok))
            return result.grad, days_left_out * record.hours, {
                "gradient": "pathwise", "days_used": int(result.ok.sum())}
        use = record.sens_ok & record.solver_ok
        skipped = int(use.size - np.count_nonzero(use))
        # the critic's compatible features are a minus the exploration's centre (zero mean)
        center = exploration_center(record.policy, self.system, self.learning.exploration_margin)
        month = CriticSamples(record.soc, record.a, center, record.grad_pi, record.stage_cost,
                              use, record.buy)
        months = [month]
        if self.learning.critic_months > 1:  # with the months before, oldest first
            months = [*self._critic_memory, month]
            self._critic_memory.append(month)
        samples = CriticSamples.join(months) if len(months) > 1 else month
        grad, info = lstd_policy_gradient(
            samples.soc, samples.a, samples.center, samples.grad_pi, samples.cost, samples.use,
            self.learning, self.system.gamma, samples.buy,
        )
        if self.learning.critic_months > 1:
            info["critic_months"] = len(months)
        if use.any():  # the metric of the natural gradient (every sample: no masked copy)
            self.updater.observe(record.grad_pi if use.all() else record.grad_pi[use])
        return grad, skipped, info

    # -- evaluation -----------------------------------------------------------------------
    def evaluate(self, theta: Theta | None = None) -> MonthRecord:
        """``theta`` (default: the current parameters) on the fixed evaluation draws.

        The month's days are run once more on each of ``LearningConfig.eval_draws`` noise
        draws (:func:`mpcrl_lite.sim.closed_loop.evaluate_mpc` with ``eval_seed``: the same draws
        every time), without exploration and without sensitivities, all draws in one batched
        closed loop. The learning generator is not touched.

        Returns
        -------
        MonthRecord
            Of ``eval_draws * days_per_month`` days, draw by draw
            (:func:`mpcrl_lite.sim.closed_loop.draw_J` gives each draw's J).
        """
        theta = self.theta if theta is None else theta
        self._check_solver(theta)
        return evaluate_mpc(theta, self.solver, self.prices, self.system,
                            self.learning.eval_seed, draws=self.learning.eval_draws)

    def evaluation_due(self, month: int) -> bool:
        """True when month ``month`` (counted from 0) is evaluated: every
        ``eval_every`` months and the last month of ``LearningConfig.months``."""
        every = self.learning.eval_every
        return every > 0 and (month % every == 0 or month == self.learning.months - 1)

    def _check_solver(self, theta: Theta) -> None:
        if theta.is_convex() or self.solver.name == "ipopt" or self.mpc_config.backend == "ipopt":
            return
        if self.mpc_config.backend == "auto":
            log.info("theta is no longer convex: switching the MPC back-end to IPOPT")
        else:  # the compiled and numpy interior points solve convex MPCs only
            log.warning("theta is no longer convex (phi1 or T1 < 0): the %r back-end cannot "
                        "solve it; switching the MPC back-end to IPOPT",
                        self.mpc_config.backend)
        self.solver = make_solver(self.mpc, self.mpc_config.replace(backend="ipopt"))
        self.history.backend = self.solver.name

    def month_options(self, recording: bool = False) -> dict[str, Any]:
        """The keyword arguments of :func:`~mpcrl_lite.sim.closed_loop.run_month` besides theta,
        solver, prices, system and rng (runs with equal options can share a loop,
        :mod:`mpcrl_lite.studies.lockstep`); with ``recording``, those of a month that runs
        with :meth:`month_recorder`'s hook."""
        if self.learning.gradient == "pathwise":  # the deterministic policy's month; the
            # gradient carries its own sensitivities (learning_step, or the recorder)
            return {"exploration_std": 0.0, "sensitivities": recording}
        return {"exploration_std": self.learning.exploration_std, "sensitivities": True,
                "exploration_bounds": self.learning.exploration_bounds,
                "exploration_margin": self.learning.exploration_margin}

    def begin_month(self) -> Theta:
        """The theta of the coming month, with the back-end it needs (its evaluation, when
        due, starts now in the worker process of :meth:`evaluations_alongside`)."""
        self._check_solver(self.theta)
        month = self.history.months
        if self._worker is not None and self.evaluation_due(month) \
                and self.solver.name == "kernel" and self.theta.is_convex():
            try:
                future = self._worker.submit(self.theta)
            except Exception as err:  # noqa: BLE001 (e.g. no process could be started)
                log.warning("no evaluation in a worker process (%s): evaluating here", err)
                self._stop_worker()
            else:
                self._pending.append((month, self.theta, future))
        return self.theta

    # -- evaluations beside the months (mpcrl_lite.learning.eval_worker) ----------------------
    #: Evaluate in a worker process while the months run (:meth:`evaluations_alongside`):
    #: ``None`` where it pays (:func:`~mpcrl_lite.learning.eval_worker.worth_a_worker`),
    #: ``False`` never, ``True`` whenever the compiled back-end runs. The results are the same.
    eval_worker: bool | None = None

    @contextlib.contextmanager
    def evaluations_alongside(self, months: int) -> Iterator[None]:
        """The month loop's context (:func:`~mpcrl_lite.learning.learner.run_months`, up to
        ``months`` months): evaluations a stopped run still lacks are made first
        (:meth:`catch_up_evaluations`); then, where it pays, a worker process evaluates each
        due month's theta while this process runs the months on one thread."""
        # a run resumed from its directory caught up already (after_resume); this is for a
        # run interrupted in this process with evaluations out and then run on
        self.catch_up_evaluations()
        ahead = sum(self.evaluation_due(m) for m in range(self.history.months, months))
        use = self.eval_worker
        if use is None:
            use = not self.callbacks and worth_a_worker(self.learning, ahead,
                                                        self.solver.name)
        same_evaluation = type(self).evaluate is Experiment.evaluate  # what the worker runs
        if not (use and ahead and same_evaluation and self.solver.name == "kernel"):
            yield
            return
        self._worker = EvaluationWorker(self.system, self.mpc_config, self.prices,
                                        self.learning)
        solver, threads = self.solver, self.solver.threads
        solver.threads = 1  # the worker's evaluations take the other core
        self._restore_threads = lambda: setattr(solver, "threads", threads)
        try:
            yield
        except BaseException:
            self._pending.clear()  # a run stopped here evaluates them when resumed
            self._stop_worker(wait=False)
            raise
        # idle (every evaluation was collected): its process ends on its own, about 0.25 s
        # that the run need not wait for
        self._stop_worker(wait=False)

    def collect_evaluations(self, wait: bool = False) -> None:
        """Record the evaluations that came back from the worker, in the order of the months
        (all of them, waiting, with ``wait``). One that failed there is made here."""
        while self._pending and (wait or self._pending[0][2].done()):
            month, theta, future = self._pending.pop(0)
            try:
                evaluation = future.result()
            except Exception as err:  # noqa: BLE001 (the same evaluation here raises its own)
                if self._worker is not None:  # (the later ones were cancelled with it)
                    log.warning("the evaluation of month %d failed in the worker process "
                                "(%s); evaluating here from now on", month, err)
                    self._stop_worker(wait=False)
                evaluation = self.evaluate(theta)
            self.history.append_evaluation(month, evaluation, draws=self.learning.eval_draws)

    def _stop_worker(self, wait: bool = True) -> None:
        """Stop the worker (the months to come evaluate here; ``wait`` for its process to
        end) and give the months their threads back."""
        if self._worker is not None:
            self._worker.close(wait)
            self._worker = None
            self._restore_threads()

    def after_resume(self) -> None:
        """Make the evaluations the resumed run lacks (:meth:`catch_up_evaluations`)."""
        self.catch_up_evaluations()

    def catch_up_evaluations(self) -> None:
        """Evaluate the due months the history lacks (a run committed while their
        evaluations were out, then stopped), in order, with the theta they ran with."""
        done = set(self.history.eval_month)
        last = max(done, default=-1)
        for month in range(last + 1, self.history.months):
            if self.evaluation_due(month) and month not in done:
                theta = Theta.from_vector(np.asarray(self.history.theta[month], dtype=float),
                                          self.system.n)
                self.history.append_evaluation(month, self.evaluate(theta),
                                               draws=self.learning.eval_draws)

    @one_blas_thread
    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current theta and update it (and evaluate the
        month's theta when :meth:`evaluation_due`)."""
        t0 = time.perf_counter()
        theta_used = self.begin_month()
        # the pathwise gradient is recorded as the month runs: the policy's solves serve
        # both, where simulating the month and then its gradient would solve every problem
        # twice
        recorder = self.month_recorder()
        record = run_month(theta_used, self.solver, self.prices, self.system, self.rng,
                           on_hour=() if recorder is None else [recorder],
                           **self.month_options(recording=recorder is not None))
        if recorder is not None:
            record = self.keep_month_gradient(record, recorder.result())
        return self.end_month(record, theta_used, time.perf_counter() - t0)

    def month_recorder(self) -> PathwiseRecorder | None:
        """The hour hook that records this learner's gradient while its month runs (with
        ``month_options(recording=True)``), or None: the pathwise gradient's
        :class:`~mpcrl_lite.learning.pathwise.PathwiseRecorder`; the critic learns from the
        month's record alone."""
        if self.learning.gradient != "pathwise":
            return None
        return PathwiseRecorder(self.solver, self.system)

    def keep_month_gradient(self, record: MonthRecord, gradient: PathwiseGradient) -> MonthRecord:
        """Keep the ``gradient`` recorded with ``record`` for :meth:`learning_step` of that
        record; returns the record as :meth:`month_options` gives it (no sensitivities
        kept), bit for bit."""
        record = dataclasses.replace(record, grad_pi=None,
                                     sens_ok=np.zeros_like(record.sens_ok))
        self._pathwise = (record, gradient)
        return record

    def end_month(self, record: MonthRecord, theta_used: Theta, sim_time: float,
                  evaluation: MonthRecord | None = None) -> MonthRecord:
        """Learn from the month ``record`` simulated at ``theta_used`` (in ``sim_time``
        seconds), evaluate ``theta_used`` when due (or take its ``evaluation``) and record
        the month."""
        t0 = time.perf_counter() - sim_time
        month = self.history.months
        self.write_deferred()  # the last month's journal line, beside this update
        grad, skipped, info = self.learning_step(record)
        self.theta = self.updater.step(theta_used, grad)
        info.update(self.updater.last_info)
        info = plain(info)  # as it reads back from history.json (no NaN: null)
        record.grad_pi = None  # large; not kept in the history
        wall_time = time.perf_counter() - t0
        out_in_worker = any(m == month for m, _, _ in self._pending)
        if self.evaluation_due(month) and not out_in_worker:
            t1 = time.perf_counter()
            self.collect_evaluations(wait=True)  # the months before first
            if evaluation is None:
                evaluation = self.evaluate(theta_used)
            self.history.append_evaluation(month, evaluation, draws=self.learning.eval_draws)
            info["eval_time_s"] = time.perf_counter() - t1
        self.history.append(record, theta_used, grad, skipped, wall_time, info)
        self.history.theta_final = self.theta.to_vector().tolist()
        return record

    # -- checkpoints ----------------------------------------------------------------------
    def extra_files(self) -> dict[str, bytes]:
        """``critic.npz``, the critic's samples of the months its next fit uses besides its
        own (``LearningConfig.critic_months > 1`` only)."""
        if self.learning.critic_months == 1:
            return {}
        return {rundir.CRITIC: CriticSamples.to_npz(list(self._critic_memory))}

    def restore_extra_files(self, files: dict[str, bytes], directory: Path) -> Callable[[], None]:
        """Check ``critic.npz`` of a run whose critic is fitted on several months and return
        its application (nothing for a one-month critic)."""
        if self.learning.critic_months == 1:
            return lambda: None
        where = directory / rundir.CRITIC
        if rundir.CRITIC not in files:
            raise RunDirError(f"{where} is missing: a run with critic_months="
                              f"{self.learning.critic_months} keeps its critic's earlier months "
                              f"there; {rundir.RECOVER}")
        months = CriticSamples.from_npz(files[rundir.CRITIC], str(where), self.system.n,
                                        self.learning.critic_months - 1)

        def apply() -> None:
            self._critic_memory.clear()
            self._critic_memory.extend(months)

        return apply

    def learner_state(self) -> dict[str, Any]:
        """theta and the optimizer's state (part of ``checkpoint.json``)."""
        return {"theta": self.theta.to_vector().tolist(), "updater": self.updater.state_dict()}

    def restore_learner_state(self, state: dict[str, Any], where: str) -> Callable[[], None]:
        """Check theta and the optimizer state of a checkpoint; return their application."""
        theta = parse_theta(state["theta"], self.system.n, where)
        updater = self.UPDATER.from_configs(self.learning, self.system, self.prices)
        try:
            updater.load_state_dict(state["updater"])
        except (TypeError, ValueError, KeyError, AttributeError) as err:
            raise RunDirError(f"{where}: bad 'updater' ({err}); start over with --force") from None

        def apply() -> None:
            self.theta = theta
            self.updater.load_state_dict(updater.state_dict())
            if self.history.backend == "ipopt" and self.mpc_config.backend != "ipopt":
                # the run had switched to IPOPT (a non-convex theta): it stays there
                self.solver = make_solver(self.mpc, self.mpc_config.replace(backend="ipopt"))
            self._check_solver(self.theta)
            self.history.backend = self.solver.name

        return apply
