r"""What every learner shares: the month loop, with a checkpoint after every month.

Both learners -- :class:`~mpcrl_lite.learning.experiment.Experiment` (one centralized MPC) and
:class:`~mpcrl_lite.decentralized.learner.DecentralizedExperiment` (one MPC and one learner per
battery) -- are a :class:`Learner`. A subclass simulates and updates one month
(:meth:`Learner.run_one_month`) and says what its state is (:meth:`Learner.learner_state`,
:meth:`Learner.restore_learner_state`); the base runs the months, writes a checkpoint after
each and resumes from one (:mod:`mpcrl_lite.learning.checkpoint`); the update of a month is
:func:`mpcrl_lite.learning.step.lstd_policy_gradient`.

One thread of linear algebra
----------------------------
The month loop runs with the BLAS/LAPACK libraries limited to one thread
(``threadpoolctl``), and so do every learner's ``run_one_month`` and ``learning_step``
called on their own (:func:`mpcrl_lite._util.threads.one_blas_thread`). The matrices of a
month are small (tens to hundreds of rows), where threads cost more than they bring, and a
multi-threaded BLAS may sum in another order on a machine with another number of cores or in
a worker process that limits its threads (Dask does): with one thread, a run gives the same
numbers to the last bit in a notebook, under ``learn``, in a sweep's worker and on any
machine with the same libraries.

Failed solves
-------------
Hours whose MPC failed act with the fallback (idle) and are left out of the learning step.
When more than :data:`MAX_FAILED_SOLVE_SHARE` of a month's solves fail, a warning is logged;
the ``learn`` command exits with status 2 when the whole run exceeds it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack, nullcontext
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from threadpoolctl import threadpool_limits

from .._util.budget import check_memory, learning_estimate
from .._util.malloc import keep_freed_memory
from .._util.progress import progress_bar
from .._util.threads import BLAS_THREADS
from ..config import LearningConfig, MPCConfig, SystemConfig, check_grid_bound
from ..sim.record import MonthRecord
from ..system.forecast import forecast_of, forecast_prices
from ..system.prices import Prices
from ..theta import Theta
from . import outdir
from .checkpoint import Checkpointing, open_run
from .dpg import scales_follow_prices
from .history import History

__all__ = [
    "MAX_FAILED_SOLVE_SHARE",
    "Learner",
    "close_month",
    "finish_checkpoint",
    "resolve_setup",
    "run_months",
]

log = logging.getLogger(__name__)

#: A month (and, for the ``learn`` command, a run) with a larger share of failed MPC solves
#: is reported: its learning signal comes from too few hours to be trusted.
MAX_FAILED_SOLVE_SHARE = 0.5


def resolve_setup(
    system: SystemConfig | None,
    mpc_config: MPCConfig | None,
    learning: LearningConfig | None,
    prices: Prices | None,
    theta0: Theta | None,
) -> tuple[SystemConfig, MPCConfig, LearningConfig, Prices, Theta]:
    """Defaults and consistency checks shared by every learner: the paper's configs, the
    shipped month cut to ``days_per_month`` days, theta0 = ``learning.theta0`` where set, else
    the nominal model; prices with another number of days, a theta0 for another ``n`` or one
    that differs from ``learning.theta0`` are errors.

    The prices returned are those the MPC sees (:func:`mpcrl_lite.system.forecast.forecast_prices`
    of ``MPCConfig.forecast``); prices given already as
    :func:`~mpcrl_lite.system.forecast.until_midnight` set ``forecast='until_midnight'`` in the
    returned config, so that the run records what its MPC saw. ``learning.scale_to_prices=None``
    is resolved for these prices (:func:`~mpcrl_lite.learning.dpg.scales_follow_prices`), so
    that the run records what its learner did."""
    system = check_grid_bound(system or SystemConfig())
    mpc_config = mpc_config or MPCConfig()
    learning = learning or LearningConfig()
    # a month (and an evaluation batch) must fit in memory: refused before anything is built
    check_memory(
        f"days_per_month={learning.days_per_month}, n={system.n}, "
        f"eval_draws={learning.eval_draws}",
        learning_estimate(system.n, learning.days_per_month, 1, learning.eval_draws,
                          learning.eval_every, system.N))
    if prices is None:
        prices = Prices.month(system, learning.days_per_month)
    if prices.days != learning.days_per_month:
        raise ValueError(
            f"prices have {prices.days} days; expected days_per_month={learning.days_per_month}"
        )
    if forecast_of(prices) != mpc_config.forecast and mpc_config.forecast == "paper":
        mpc_config = mpc_config.replace(forecast=forecast_of(prices))
    if learning.scale_to_prices is None:  # recorded as it was resolved
        learning = learning.replace(scale_to_prices=scales_follow_prices(learning, prices))
    prices = forecast_prices(prices, mpc_config)
    if learning.theta0 is not None:  # the start the config names (LearningConfig.theta0)
        size = len(learning.theta0)
        if size != Theta.nominal(system).size:
            raise ValueError(f"learning.theta0 has {size} entries; expected 10 n = "
                             f"{10 * system.n} for n={system.n} (Theta.to_vector)")
        start = Theta.from_vector(np.asarray(learning.theta0), system.n)
        if theta0 is not None and not np.array_equal(theta0.to_vector(), start.to_vector()):
            raise ValueError("theta0 differs from learning.theta0: expected one start (pass "
                             "either, or the same theta to both)")
        theta0 = start
    theta0 = theta0 or Theta.nominal(system)
    if theta0.n != system.n:
        raise ValueError(f"theta0 has n={theta0.n}; expected n={system.n}")
    return system, mpc_config, learning, prices, theta0


def run_months(
    learner: Learner,
    months: int | None,
    out: str | Path | None,
    resume: bool,
    progress: bool,
    desc: str = "learning",
    force: bool = False,
    adopt: bool = False,
) -> History:
    """The month loop of every learner.

    Runs until ``months`` months are recorded (default ``learning.months``). With ``out``
    every month is committed to that run directory, locked for the loop
    (:func:`~mpcrl_lite.learning.outdir.lock_output_dir`: another process there is refused);
    a directory that already holds a run is continued with ``resume`` (verified first, see
    :meth:`Learner.load_checkpoint`; a directory from before the manifest format only with
    ``adopt``), replaced with ``force``, and refused otherwise. ``resume`` in a directory
    without a run starts one.
    """
    keep_freed_memory()  # the months' arrays reuse freed memory (same results, less time)
    with ExitStack() as stack:
        if out is not None:
            Path(out).mkdir(parents=True, exist_ok=True)
            stack.enter_context(outdir.lock_output_dir(out, "learn"))
        return _run_months(learner, months, out, resume, progress, desc, force, adopt)


def _run_months(learner, months, out, resume, progress, desc, force, adopt) -> History:
    months = open_run(learner, months, out, resume, force, adopt)
    out = Path(out) if out is not None else None
    history = learner.history
    bar = progress_bar(total=months, initial=min(history.months, months), desc=desc,
                       unit="month", disable=not progress)
    try:
        with bar, threadpool_limits(limits=BLAS_THREADS), learner.evaluations_alongside(months):
            while learner.history.months < months:
                learner.run_one_month()
                # evaluations made beside the months are recorded as they come; the last
                # month waits for all of them
                learner.collect_evaluations(wait=learner.history.months >= months)
                history = learner.history
                postfix = {"J": f"{history.J[-1]:.1f}"}
                if history.J_eval:
                    postfix["J_eval"] = f"{history.J_eval[-1]:.1f}"
                bar.set_postfix(postfix, refresh=False)
                bar.update(1)
                close_month(learner, out, last=learner.history.months >= months)
    except BaseException:
        finish_checkpoint(learner)
        raise
    learner.wait_for_checkpoint()
    return learner.history


def finish_checkpoint(learner: Learner) -> None:
    """Wait for the learner's checkpoint under way (after an error of the run, which goes
    on: the checkpoint's own error, if any, is dropped; the directory holds the last
    commit that succeeded)."""
    try:
        learner.wait_for_checkpoint()
    except Exception:  # noqa: BLE001, S110 (the run's own error is the one to report)
        pass


def close_month(learner: Learner, out: Path | None, last: bool = True) -> None:
    """What follows every month of :func:`run_months`: the warning on failed solves, the
    checkpoint in ``out`` (``last=False`` for a month after which the run goes on: a line
    appended to the journal, or the whole files of a run's first month written in the
    background unless the learner has callbacks, see
    :meth:`~mpcrl_lite.learning.checkpoint.Checkpointing.save_checkpoint`) and the learner's
    callbacks."""
    history = learner.history
    _warn_failed_solves(history)
    if out is not None:
        # whole files are written while the next month computes, unless it is the last or
        # a callback may look at the directory
        learner.save_checkpoint(out, last=last, background=not last and not learner.callbacks)
    for callback in learner.callbacks:
        callback(history.months - 1, history, learner)


def _warn_failed_solves(history: History) -> None:
    solves = history.system.hours_per_day * history.learning.days_per_month
    failed = history.solver_failures[-1]
    if failed > MAX_FAILED_SOLVE_SHARE * solves:
        log.warning(
            "month %d: %d of %d MPC solves failed (more than MAX_FAILED_SOLVE_SHARE=%g); "
            "those hours idle and are left out of the update",
            history.months - 1, failed, solves, MAX_FAILED_SOLVE_SHARE,
        )


class Learner(Checkpointing):
    """Base of the learners: the month loop (checkpoints and resume from
    :class:`~mpcrl_lite.learning.checkpoint.Checkpointing`).

    A subclass sets :attr:`KIND` (the manifest's learner kind), :attr:`FORMAT` (its
    ``checkpoint.json`` format), the attributes ``system``, ``mpc_config``, ``learning``,
    ``prices``, ``rng``, ``history`` and ``callbacks``, and implements
    :meth:`run_one_month`, :meth:`learner_state` and :meth:`restore_learner_state`.
    """

    KIND: ClassVar[str] = ""
    FORMAT: ClassVar[str] = ""
    DESC: ClassVar[str] = "learning"
    system: SystemConfig
    mpc_config: MPCConfig
    learning: LearningConfig
    prices: Prices
    rng: np.random.Generator
    history: History
    callbacks: list[Callable[..., None]]

    # -- what a subclass provides ---------------------------------------------------------
    def run_one_month(self) -> MonthRecord:
        """Simulate one month with the current parameters, update them, record the month."""
        raise NotImplementedError

    def learner_state(self) -> dict[str, Any]:
        """The learner's own part of ``checkpoint.json`` (theta and optimizer state)."""
        raise NotImplementedError

    def restore_learner_state(self, state: dict[str, Any], where: str) -> Callable[[], None]:
        """Check the learner's part of a checkpoint (raising :class:`RunDirError` naming
        ``where``) and return a function that applies it; nothing changes before that
        function is called."""
        raise NotImplementedError

    def evaluations_alongside(self, months: int) -> AbstractContextManager[None]:
        """The context of :func:`run_months`' loop up to ``months`` months (the centralized
        experiment evaluates in a worker process there, where it pays); nothing here."""
        return nullcontext()

    def collect_evaluations(self, wait: bool = False) -> None:
        """Record the evaluations made beside the months (see :meth:`evaluations_alongside`);
        nothing here."""

    # -- the run --------------------------------------------------------------------------
    def run(
        self,
        months: int | None = None,
        out: str | Path | None = None,
        resume: bool = False,
        progress: bool = True,
        force: bool = False,
        adopt: bool = False,
    ) -> History:
        """Run until ``months`` months are recorded (default ``learning.months``).

        With ``out`` each month is committed to that run directory; ``resume`` continues the
        run found there (same results as an uninterrupted run) and ``force`` replaces it;
        without either, a directory that holds a run is refused. A run directory from before
        the manifest format (no checksums) is resumed only with ``adopt`` (and a warning).
        """
        return run_months(self, months, out, resume, progress, desc=self.DESC, force=force,
                          adopt=adopt)
