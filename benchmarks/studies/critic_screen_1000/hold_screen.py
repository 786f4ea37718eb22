"""The measurement "more days per update, late" of ``benchmarks/README.md`` (not a package
option): from month ``LATE`` on, theta is held for ``K`` months and the critic of the update
that ends them is fitted on their ``K x 30`` days at that one theta (the paper's rule before
``LATE``). Runs the study in this process (the learner is changed here, not in workers).

    python benchmarks/studies/critic_screen_1000/hold_screen.py K LATE SEEDS SEED_START OUT

(``3 50 10 1000 DIR`` for the stored ``hold3_from50``).
"""

from __future__ import annotations

import sys

import numpy as np

from mpcrl_lite.learning import experiment as experiment_module
from mpcrl_lite.learning.critic_samples import CriticSamples
from mpcrl_lite.learning.step import lstd_policy_gradient
from mpcrl_lite.sim.exploration import exploration_center
from mpcrl_lite.studies.study import run_study

_learning_step = experiment_module.Experiment.learning_step
_end_month = experiment_module.Experiment.end_month


def held_months(K: int, late: int):
    """``learning_step`` and ``end_month`` of the held schedule."""

    def learning_step(self, record):
        month = self.history.months
        if month < late:
            return _learning_step(self, record)
        held = self.__dict__.setdefault("_held", [])
        use = record.sens_ok & record.solver_ok
        center = exploration_center(record.policy, self.system, self.learning.exploration_margin)
        held.append(CriticSamples(record.soc, record.a, center, record.grad_pi,
                                  record.stage_cost, use, record.buy))
        skipped = int(use.size - np.count_nonzero(use))
        if (month - late + 1) % K and month != self.learning.months - 1:
            self._hold = True  # no update this month: theta stays for the next one
            return np.zeros(record.grad_pi.shape[2]), skipped, {}
        s = CriticSamples.join(held)
        held.clear()
        grad, info = lstd_policy_gradient(s.soc, s.a, s.center, s.grad_pi, s.cost, s.use,
                                          self.learning, self.system.gamma, s.buy)
        self.updater.observe(record.grad_pi[use])
        return grad, skipped, info

    def end_month(self, record, theta_used, sim_time, evaluation=None):
        self._hold = False
        step = self.updater.step

        def held_step(theta, grad):
            return theta if self._hold else step(theta, grad)

        self.updater.step = held_step
        try:
            return _end_month(self, record, theta_used, sim_time, evaluation)
        finally:
            del self.updater.step

    return learning_step, end_month


if __name__ == "__main__":
    K, late, seeds, start = (int(a) for a in sys.argv[1:5])
    (experiment_module.Experiment.learning_step,
     experiment_module.Experiment.end_month) = held_months(K, late)
    summary = run_study(seeds, 100, sys.argv[5], seed_start=start, workers=0,
                        class_best="data/class_best_paper", progress=False)
    print(summary["J_eval_final_median"])
