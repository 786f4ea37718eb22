r"""Many learning runs at once: ``K`` runs stepped month by month in lockstep, one process.

A study repeats the same learning run for several seeds, noise variances or grid limits. Run
one after another, each run pays the loop's Python work (the per-hour numpy calls of
:func:`~mpcrl_lite.sim.closed_loop.simulate`, the solver's set-up) on ``D = 30`` rows at a time;
:func:`run_lockstep` advances the runs together instead, so that work is paid once per group
of runs on ``K * D`` rows.

One month of runs in lockstep
-----------------------------
1. Every run takes its month's theta (:meth:`Experiment.begin_month
   <mpcrl_lite.learning.experiment.Experiment.begin_month>`; a non-convex theta may switch a run to
   IPOPT).
2. The runs are grouped: runs share a loop when they share the MPC formulation and the true
   system's dynamics (every :class:`~mpcrl_lite.config.SystemConfig` field except
   ``noise_mean`` and ``noise_var``; e.g. runs with different ``P_bar`` form different groups),
   the :class:`~mpcrl_lite.config.MPCConfig`, the compiled back-end (``'kernel'``), the
   exploration settings and the prices. Runs that differ in ``seed``, ``noise_var``,
   ``noise_mean``, the learning rule or the evaluation settings share a group.
3. A group of ``K`` runs is one closed loop of ``K * D`` days
   (:func:`~mpcrl_lite.sim.closed_loop.run_month` with one theta per run): at each hour one solver
   call solves the ``K * D`` MPCs, each row with its run's theta, and computes their
   sensitivities; the random draws go through :class:`~mpcrl_lite.sim.closed_loop.RunBlocks`, so
   each run draws its exploration and its noise (of its own variance) from its own generator
   in the order of the run alone.
4. The record is cut into the runs' months, and each run learns, updates, is evaluated when
   due (:meth:`Experiment.end_month <mpcrl_lite.learning.experiment.Experiment.end_month>`) and commits
   its checkpoint (:func:`mpcrl_lite.learning.learner.close_month`: the files of
   :func:`~mpcrl_lite.learning.learner.run_months`), then its callbacks run.

Identical to the runs alone
---------------------------
The compiled back-end solves each problem on its own (a loop over the rows, the parameter
vector of a row holds its theta), and every other step of the loop -- exploration, the true
system's step, the sensitivities, the warm start -- works row by row; the months are cut
into contiguous arrays before anything sums over them. So each run's
:class:`~mpcrl_lite.learning.history.History`, theta, optimizer state and generator state are bit for
bit those of the run alone (``tests/studies/test_lockstep.py``); only the timings
(``History.wall_time``, ``info['eval_time_s']``) differ: a run of a group is given the
group's simulation time divided by ``K`` plus its own learning time. A run directory written
in lockstep resumes alone and the other way round.

Failures
--------
A solve that fails idles its own row, as in the run alone. An exception in the group's loop
(for instance a run whose theta makes the MPC data non-finite) restores every run's generator
and runs each of the group's runs alone for that month, so only the faulty run fails; an
exception in a run's own learning step, checkpoint or callbacks fails that run only. A failed
run stops (as :func:`~mpcrl_lite.learning.learner.run_months` would raise) and its exception is
returned in its place; the others go on.

Other learners (the decentralized one) and runs on other back-ends are stepped alone within
the same loop.

Cost (``benchmarks/bench_study.py``): see ``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from .._util.malloc import keep_freed_memory
from .._util.progress import progress_bar
from ..learning.checkpoint import open_run
from ..learning.experiment import Experiment
from ..learning.history import History
from ..learning.learner import BLAS_THREADS, Learner, close_month, finish_checkpoint
from ..sim.closed_loop import RunBlocks, run_month
from ..sim.record import MonthRecord
from ..theta import Theta

__all__ = ["group_key", "run_lockstep", "split_record"]

log = logging.getLogger(__name__)

#: The system's fields that only the noise draws use (each run draws its own).
NOISE_FIELDS = ("noise_mean", "noise_var")


def group_key(learner: Learner) -> tuple | None:
    """What runs sharing one closed loop must have in common (see the module docstring), or
    None for a run that is stepped alone (another learner, another back-end)."""
    if type(learner) is not Experiment or learner.solver.name != "kernel":
        return None
    system = {k: v for k, v in learner.system.to_dict().items() if k not in NOISE_FIELDS}
    prices = learner.prices
    return (
        json.dumps(system, sort_keys=True),
        json.dumps(learner.mpc_config.to_dict(), sort_keys=True),
        json.dumps(learner.month_options(), sort_keys=True),
        np.asarray(prices.buy).shape, np.asarray(prices.buy).tobytes(), float(prices.sell_ratio),
    )


def split_record(record: MonthRecord, systems: Sequence[Any]) -> list[MonthRecord]:
    """Cut a month of ``K = len(systems)`` runs in lockstep (``K * D`` days, run by run)
    into the runs' months, each with its own system and contiguous arrays of ``D`` days."""
    K = len(systems)
    if K < 1 or record.days % K:
        raise ValueError(f"a record of {record.days} days: expected {K} runs of equal days")
    D = record.days // K
    parts = []
    for r, system in enumerate(systems):
        rows = slice(r * D, (r + 1) * D)
        fields = {name: np.ascontiguousarray(value[:, rows]) if isinstance(value, np.ndarray)
                  else value for name, value in record.fields().items()}
        fields["system"] = system
        grad = None if record.grad_pi is None else np.ascontiguousarray(record.grad_pi[:, rows])
        parts.append(MonthRecord(**fields, grad_pi=grad))
    return parts


def run_lockstep(
    learners: Sequence[Learner],
    months: int | None = None,
    outs: Sequence[str | Path | None] | None = None,
    resume: bool = False,
    force: bool = False,
    progress: bool = False,
    on_failure: Callable[[int, BaseException], None] | None = None,
) -> list[History | BaseException]:
    """Run ``learners`` to ``months`` months each, month by month in lockstep.

    Each run gives what ``learner.run(months, out, resume=resume, force=force)`` gives alone
    (see the module docstring), with the same run directories.

    Parameters
    ----------
    learners
        The runs (:class:`~mpcrl_lite.learning.experiment.Experiment` share loops; others are stepped
        alone).
    months
        Months to reach per run (default each run's ``learning.months``).
    outs
        One run directory (or None) per learner; default none.
    resume, force
        As for :meth:`Learner.run <mpcrl_lite.learning.learner.Learner.run>`, for every run.
    progress
        Show one progress bar over the months of all runs.
    on_failure
        Called as ``on_failure(index, exception)`` when a run fails (then it stops).

    Returns
    -------
    list
        Per learner, its :class:`~mpcrl_lite.learning.history.History`, or the exception that stopped
        it (an error in its directory, its loop, its learning step or its callbacks).
    """
    learners = list(learners)
    outs_list = [None] * len(learners) if outs is None else list(outs)
    if len(outs_list) != len(learners):
        raise ValueError(f"{len(outs_list)} run directories for {len(learners)} learners: "
                         "expected one (or None) per learner")
    if months is not None and (isinstance(months, bool) or not isinstance(months, int)
                               or months < 1):
        raise ValueError(f"months={months!r}: expected an integer >= 1")
    paths = [None if o is None else Path(o) for o in outs_list]
    keep_freed_memory()  # the months' arrays reuse freed memory (same results, less time)
    results: list[History | BaseException | None] = [None] * len(learners)
    targets = [0] * len(learners)

    def fail(i: int, err: BaseException) -> None:
        log.info("run %d failed: %s: %s", i, type(err).__name__, err)
        results[i] = err
        if on_failure is not None:
            on_failure(i, err)

    for i, learner in enumerate(learners):
        try:
            targets[i] = open_run(learner, months, paths[i], resume, force)
        except Exception as err:  # noqa: BLE001 (this run fails; the others go on)
            fail(i, err)

    def alone(i: int) -> None:
        try:
            learners[i].run_one_month()
            close_month(learners[i], paths[i], last=learners[i].history.months >= targets[i])
        except Exception as err:  # noqa: BLE001
            fail(i, err)

    def together(group: list[int], thetas: list[Theta]) -> None:
        runs = [learners[i] for i in group]
        states = [run.rng.bit_generator.state for run in runs]
        first = runs[0]
        t0 = time.perf_counter()
        # a learner whose gradient is recorded as its month runs (the pathwise one): one
        # recorder for the group's days, each run's share of it after
        recorder = first.month_recorder()
        try:
            record = run_month(thetas, first.solver, first.prices, first.system,
                               RunBlocks([r.rng for r in runs], [r.system for r in runs]),
                               on_hour=() if recorder is None else [recorder],
                               **first.month_options(recording=recorder is not None))
        except Exception as err:  # noqa: BLE001 (find the faulty run: each alone)
            log.info("a group of %d runs failed together (%s); running them alone",
                     len(group), err)
            for run, state in zip(runs, states, strict=True):
                run.rng.bit_generator.state = state
            for i in group:
                alone(i)
            return
        share = (time.perf_counter() - t0) / len(group)
        parts = split_record(record, [r.system for r in runs])
        if recorder is not None:
            D = record.days // len(runs)
            parts = [run.keep_month_gradient(part, recorder.result(slice(r * D, (r + 1) * D)))
                     for r, (run, part) in enumerate(zip(runs, parts, strict=True))]
        for i, run, part, theta in zip(group, runs, parts, thetas, strict=True):
            try:
                run.end_month(part, theta, share)
                close_month(run, paths[i], last=run.history.months >= targets[i])
            except Exception as err:  # noqa: BLE001
                fail(i, err)

    total = sum(max(t - r.history.months, 0) for t, r in zip(targets, learners, strict=True))
    with progress_bar(total=total, desc="lockstep", unit="month", disable=not progress) as bar, \
            threadpool_limits(limits=BLAS_THREADS):
        while True:
            active = [i for i, r in enumerate(learners)
                      if results[i] is None and r.history.months < targets[i]]
            if not active:
                break
            groups: dict[Any, list[int]] = {}
            thetas: dict[int, Theta] = {}
            for i in active:
                try:
                    if isinstance(learners[i], Experiment):
                        thetas[i] = learners[i].begin_month()
                    key = group_key(learners[i])
                except Exception as err:  # noqa: BLE001
                    fail(i, err)
                    continue
                groups.setdefault(("alone", i) if key is None else key, []).append(i)
            for key, group in groups.items():
                if key[0] == "alone" or len(group) == 1:
                    for i in group:
                        alone(i)
                else:
                    together(group, [thetas[i] for i in group])
            bar.update(len(active))
    for i, learner in enumerate(learners):  # the failed runs' checkpoints under way
        if results[i] is not None:
            finish_checkpoint(learner)
    return [learner.history if result is None else result
            for learner, result in zip(learners, results, strict=True)]
