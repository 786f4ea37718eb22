r"""The evaluation of a month's theta in a second process, while the months go on.

Every ``eval_every`` months :class:`~mpcrl_lite.learning.experiment.Experiment` judges the
theta its month was simulated with on ``eval_draws`` fixed noise draws
(:meth:`Experiment.evaluate`). That theta is known when the month starts, and nothing of the
learning run depends on the evaluation (it draws from its own generators), so the
evaluation can run beside the months. With the default ten draws it is about a quarter of the
paper's run (``7,200`` MPC problems every fifth month, against the month's ``720`` problems
with their sensitivities and its update; ``learn --months 100`` took 11.9 s with ten draws
against 9.0 s with one).

:class:`EvaluationWorker` runs the evaluations in one worker process (started with ``spawn``,
one thread) while this process simulates and learns, on one thread too: each keeps a core.
The results come back in the order of the months and are recorded when they arrive
(:meth:`Experiment.collect_evaluations`); the last month of a run waits for all of them, so a
finished run holds every evaluation. The worker solves the same closed loop with the same
back-end and draws (:func:`mpcrl_lite.sim.closed_loop.evaluate_mpc`), so ``History`` is the
same bit for bit as with the evaluations in this process.

A run directory committed while an evaluation was still out lacks it; a resumed run
evaluates the missing months first (:meth:`Experiment.catch_up_evaluations`), so a run
stopped at any point resumes to the results of an uninterrupted run. An evaluation that fails
in the worker (the worker process died, say) is run again in this process, which gives the
same result or raises the same error, and the rest of the run evaluates here.

A spawned process imports the program's main module again before it serves (as
``__mp_main__``). A package's ``__main__`` (``python -m mpcrl_lite``), an interactive session, a
notebook's kernel and a script that keeps its work under ``if __name__ == "__main__":`` are
safe; a script without that guard would run again in the worker, so its runs evaluate in
their own process (:func:`spawn_safe`).

When it pays (:func:`worth_a_worker`): a spawn-safe program, two cores or more, the compiled
back-end, at least :data:`MIN_EVAL_DAYS` days per evaluation (ten draws of 30 days: yes; one
draw: no, the worker's start, about 1.5 s of CPU, would cost more than it saves) and at least
:data:`MIN_EVALUATIONS` evaluations to come. Measured on two cores (``learn --months 100``,
ten draws): see ``benchmarks/README.md``, "Evaluations beside the months".
"""

from __future__ import annotations

import multiprocessing
import sys
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from .._util.threads import auto_threads
from .._util.workers import end_with_parent
from ..config import LearningConfig, MPCConfig, SystemConfig
from ..sim.closed_loop import evaluate_mpc
from ..sim.record import MonthRecord
from ..system.prices import Prices
from ..theta import Theta

__all__ = ["MIN_EVALUATIONS", "MIN_EVAL_DAYS", "EvaluationWorker", "spawn_safe",
           "worth_a_worker"]

#: Days of closed loop per evaluation (``eval_draws * days_per_month``) from which a run
#: evaluates in a worker process.
MIN_EVAL_DAYS = 100
#: Evaluations still to come in the run from which the worker's start pays (measured: three
#: 40-month runs with 9 evaluations each took 13.3 s against 13.5 s in one process, a 100-month
#: run with 21 of them 0.89x the time).
MIN_EVALUATIONS = 12

_STATE: dict[str, Any] = {}


def _start(system: SystemConfig, mpc_config: MPCConfig, prices: Prices, seed: int,
           draws: int) -> None:
    """The worker's set-up: the MPC and its solver, built as the experiment builds them."""
    from ..mpc.backends.registry import make_solver
    from ..mpc.formulation import MPC

    end_with_parent()  # a run killed outright must not leave its worker waiting for ever
    # one thread (the kernel solver's default in a worker process): the other core is the
    # months'
    _STATE.update(system=system, prices=prices, seed=seed, draws=draws,
                  solver=make_solver(MPC(system), mpc_config))


def _evaluate(theta: Theta) -> MonthRecord:
    s = _STATE
    return evaluate_mpc(theta, s["solver"], s["prices"], s["system"], s["seed"],
                        draws=s["draws"])


def spawn_safe() -> bool:
    """Whether a spawned worker can start without running this program again: the main
    module is a package's ``__main__`` (which spawn does not import again), absent (an
    interactive session), or a file that names ``"__main__"`` (the usual guard of a script's
    work)."""
    main = sys.modules.get("__main__")
    spec = getattr(main, "__spec__", None)
    if spec is not None and (spec.name == "__main__" or spec.name.endswith(".__main__")):
        return True
    path = getattr(main, "__file__", None)
    if path is None:
        return True
    try:
        return "__main__" in Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False


def worth_a_worker(learning: LearningConfig, evaluations_ahead: int, backend: str) -> bool:
    """Whether evaluating in a worker process pays (see the module docstring): ``backend``
    the name of the experiment's solver, ``evaluations_ahead`` the evaluations the run has
    still to make."""
    # two threads for this process's calls (two cores, the main thread of the main process)
    return (backend == "kernel" and auto_threads() >= 2
            and learning.eval_draws * learning.days_per_month >= MIN_EVAL_DAYS
            and evaluations_ahead >= MIN_EVALUATIONS and spawn_safe())


class EvaluationWorker:
    """One worker process evaluating thetas as :meth:`Experiment.evaluate` does.

    Parameters
    ----------
    system, mpc_config, prices
        The experiment's (``prices`` as the MPC sees them, after its forecast).
    learning
        Its ``eval_seed`` and ``eval_draws`` fix the draws.
    """

    def __init__(self, system: SystemConfig, mpc_config: MPCConfig, prices: Prices,
                 learning: LearningConfig) -> None:
        self._pool = ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"), initializer=_start,
            initargs=(system, mpc_config, prices, learning.eval_seed, learning.eval_draws))

    def submit(self, theta: Theta) -> Future:
        """Start the evaluation of ``theta``; the future's result is its ``MonthRecord``."""
        return self._pool.submit(_evaluate, theta)

    def close(self, wait: bool = True) -> None:
        """Stop the worker: evaluations not started are dropped; one under way finishes,
        unread; with ``wait``, once its process has ended."""
        self._pool.shutdown(wait=wait, cancel_futures=True)
