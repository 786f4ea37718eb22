r"""The learning experiment with LSTD Q-learning instead of the policy gradient.

:class:`QLearningExperiment` is :class:`~mpcrl_lite.learning.experiment.Experiment` (the same
months, closed loop, exploration, evaluation, History, checkpoints and resume) with another
learning step (:mod:`mpcrl_lite.learning.qlearning`):

1. the month runs in closed loop as for DPG, without policy sensitivities; an hour hook
   (:class:`~mpcrl_lite.learning.qlearning.ValueRecorder`) takes :math:`V_\theta` at every
   hour's MPC solutions (no extra solve);
2. at the month's end, :math:`Q_\theta(s_k, a_k)` and its theta gradient (and, for
   ``hessian='full'``, its Hessian) at every applied action, one fixed-first-action MPC per
   hour and day (:meth:`mpcrl_lite.mpc.value.MPCValue.action_value`, warm-started from the
   policy's solution at the same state: on the compiled interior point
   (:mod:`mpcrl_lite.mpc.q_kernel`) when the policy's back-end is the kernel, else IPOPT);
3. the TD errors, the TD gradient and Hessian and the update
   (:class:`~mpcrl_lite.learning.qlearning.QLearningUpdater`).

``History.grad`` holds the TD gradient ``g``; ``History.info`` adds ``td_rms`` (RMS TD
error of the used samples), ``td_mean``, ``samples``, ``q_failures`` (fixed-action solves
that failed) and, for Newton steps, ``newton_shift``. A run directory records the learner
(kind ``q-learning``, ``learning.learner = 'q'``): resuming it with the DPG learner, or a DPG
run with this one, is refused in one line.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from .._util.threads import one_blas_thread
from ..mpc.value import MPCValue
from ..sim.closed_loop import run_month
from ..sim.record import MonthRecord
from ..theta import Theta
from .experiment import Experiment
from .qlearning import QLearningUpdater, ValueRecorder, q_action, td_errors, td_gradient

__all__ = ["QLearningExperiment"]


class QLearningExperiment(Experiment):
    """LSTD Q-learning of the MPC's theta (see the module docstring); the parameters are
    those of :class:`~mpcrl_lite.learning.experiment.Experiment`, with
    ``learning.learner = 'q'`` (set when not)."""

    KIND = "q-learning"
    FORMAT = "mpcrl_lite.QCheckpoint/1"
    DESC = "Q-learning"
    UPDATER = QLearningUpdater

    def __init__(self, system=None, mpc_config=None, learning=None, prices=None, theta0=None,
                 callbacks=()) -> None:
        from ..config import LearningConfig

        learning = learning or LearningConfig(learner="q")
        if learning.learner != "q":
            learning = learning.replace(learner="q")
        super().__init__(system, mpc_config, learning, prices, theta0, callbacks)
        # the fixed-first-action MPCs on the compiled interior point where the policy's MPC
        # runs there, else on IPOPT (the reference)
        self.value = MPCValue(self.mpc, self.mpc_config,
                              backend="kernel" if self.solver.name == "kernel" else "ipopt")
        self._recorder: ValueRecorder | None = None
        self._theta_month: Theta | None = None

    def month_options(self, recording: bool = False) -> dict[str, Any]:
        """As for DPG, without the policy sensitivities (Q-learning does not use them)."""
        return {**super().month_options(recording), "sensitivities": False}

    @one_blas_thread
    def run_one_month(self) -> MonthRecord:
        t0 = time.perf_counter()
        theta_used = self.begin_month()
        self._recorder = ValueRecorder(self.value)
        record = run_month(theta_used, self.solver, self.prices, self.system, self.rng,
                           on_hour=[self._recorder], **self.month_options())
        return self.end_month(record, theta_used, time.perf_counter() - t0)

    def end_month(self, record: MonthRecord, theta_used: Theta, sim_time: float,
                  evaluation: MonthRecord | None = None) -> MonthRecord:
        self._theta_month = theta_used
        return super().end_month(record, theta_used, sim_time, evaluation)

    @one_blas_thread
    def learning_step(self, record: MonthRecord) -> tuple[np.ndarray, int, dict[str, Any]]:
        """TD errors, gradient and Hessian of the month (see the module docstring); returns
        ``(grad, skipped, info)`` and gives the Hessian to the updater."""
        if self._recorder is None or self._theta_month is None:
            raise ValueError("learning_step needs the month's values: run the month with "
                             "run_one_month")
        recorder, self._recorder = self._recorder, None
        m, system = self.mpc, self.system
        H, D = record.stage_cost.shape
        n, N = m.n, m.N
        windows = [self.prices.window(k, N) for k in range(H)]
        buy = np.stack([w[0] for w in windows]).reshape(H * D, N)
        sell = np.stack([w[1] for w in windows]).reshape(H * D, N)
        a = q_action(record.a.reshape(H * D, n), system)
        full = self.learning.hessian == "full"
        q = self.value.action_value(record.soc[:H].reshape(H * D, n), buy, sell,
                                    self._theta_month, a, x0=recorder.x.reshape(H * D, -1),
                                    hessian=full)
        q_ok = q.ok.reshape(H, D)
        delta = td_errors(record.stage_cost, np.nan_to_num(q.value.reshape(H, D)),
                          np.nan_to_num(recorder.value), system.gamma)
        boot = np.ones((H, D), bool)
        boot[: H - 1] = recorder.ok[1:]
        use = q_ok & record.solver_ok & boot
        skipped = int(use.size - np.count_nonzero(use))
        info: dict[str, Any] = {"q_failures": int(np.count_nonzero(~q_ok))}
        if not use.any():
            self.updater.observe(None)
            return np.zeros(m.n_theta), skipped, {**info, "td": "no usable samples"}
        flat = use.ravel()
        g, hess = td_gradient(delta[use], q.grad[flat], q.hess[flat] if full else None,
                              self.learning.hessian)
        self.updater.observe(hess)
        info.update({"td_rms": float(np.sqrt(np.mean(delta[use] ** 2))),
                     "td_mean": float(np.mean(delta[use])),
                     "samples": int(np.count_nonzero(use))})
        return g, skipped, info
