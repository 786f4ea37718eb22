"""Evaluations in a worker process beside the months (:mod:`mpcrl_lite.learning.eval_worker`):
the same History bit for bit, every evaluation recorded by the end of a run, a run stopped
while evaluations were out resumes to the uninterrupted results, and an evaluation that fails
in the worker is made in this process."""

from __future__ import annotations

import json
import logging
import shutil
import sys
import types
from concurrent.futures import Future

import pytest
from conftest import assert_workers_die_with

from mpcrl_lite import LearningConfig, SystemConfig
from mpcrl_lite._util import jsonio
from mpcrl_lite.learning import eval_worker
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.studies.lockstep import run_lockstep

SMALL = SystemConfig(N=6)
LEARNING = LearningConfig(days_per_month=4, months=5, eval_every=2, eval_draws=3, seed=11)


def results(history: History) -> str:
    """What a History holds but its timings, as exact JSON (floats by repr)."""
    data = {k: getattr(history, k) for k in History.STORED_SERIES if k != "wall_time_s"}
    data["update_info"] = [{k: v for k, v in info.items() if not k.endswith("time_s")}
                           for info in history.update_info]
    data["theta_final"] = history.theta_final
    return json.dumps(jsonio.plain(data), sort_keys=True)


def run(worker: bool | None, out=None, months: int | None = None, resume: bool = False,
        learning: LearningConfig = LEARNING) -> Experiment:
    experiment = Experiment(SMALL, learning=learning)
    experiment.eval_worker = worker
    experiment.run(months, out=out, resume=resume, progress=False)
    return experiment


@pytest.fixture(scope="module")
def in_process() -> Experiment:
    return run(False)


def test_the_worker_gives_the_history_of_evaluations_in_this_process(in_process, monkeypatch):
    submitted = []
    real = eval_worker.EvaluationWorker.submit

    def spy(self, theta):
        submitted.append(theta.to_vector().tolist())
        return real(self, theta)

    monkeypatch.setattr(eval_worker.EvaluationWorker, "submit", spy)
    beside = run(True)
    assert results(beside.history) == results(in_process.history)
    # months 0, 2 and 4 (the last) were evaluated, all of them in the worker, each with the
    # theta its month ran with
    assert beside.history.eval_month == [0, 2, 4]
    assert submitted == [beside.history.theta[m] for m in (0, 2, 4)]
    assert beside._worker is None and beside._pending == []
    assert beside.solver.threads is None  # the months' thread count is given back


def test_a_run_stopped_with_evaluations_out_resumes_to_the_same_results(in_process, tmp_path):
    """The commits of months 0-3 may lack evaluations still out in the worker; the resumed run
    makes them first."""
    out = tmp_path / "run"
    run(True, out=out, months=4)
    assert History.load(out).eval_month == [0, 2]
    # the commit of month 3 made while both evaluations were still out (a kill then leaves
    # the directory so)
    experiment = Experiment(SMALL, learning=LEARNING)
    experiment.load_checkpoint(out)
    for name in History.EVAL_SERIES + History.EVAL_CI_SERIES:
        del getattr(experiment.history, name)[:]
    experiment.save_checkpoint(out)
    assert History.load(out).months == 4 and History.load(out).eval_month == []
    lockstep_copy = tmp_path / "lockstep"
    shutil.copytree(out, lockstep_copy)
    resumed = run(True, out=out, resume=True)
    assert resumed.history.eval_month == [0, 2, 4]
    assert results(resumed.history) == results(in_process.history)
    assert results(History.load(out)) == results(in_process.history)
    # a study resumes the same directory in lockstep to the same results
    [history] = run_lockstep([Experiment(SMALL, learning=LEARNING)], outs=[lockstep_copy],
                             resume=True)
    assert results(history) == results(in_process.history)


def test_an_evaluation_that_fails_in_the_worker_is_made_here(in_process, monkeypatch, caplog):
    def broken(self, theta):
        future = Future()
        future.set_exception(RuntimeError("the worker process died"))
        return future

    monkeypatch.setattr(eval_worker.EvaluationWorker, "submit", broken)
    with caplog.at_level(logging.WARNING, logger="mpcrl_lite.learning.experiment"):
        experiment = run(True)
    assert results(experiment.history) == results(in_process.history)
    warnings = [r.getMessage() for r in caplog.records if "failed in the worker" in r.getMessage()]
    assert len(warnings) == 1 and "month 0" in warnings[0] and "died" in warnings[0]


def test_the_worker_runs_only_where_it_pays(monkeypatch):
    monkeypatch.setattr(eval_worker, "auto_threads", lambda: 2)
    paper = LearningConfig()  # 10 draws of 30 days
    assert eval_worker.worth_a_worker(paper, 21, "kernel")
    assert not eval_worker.worth_a_worker(paper, 21, "batch")
    assert not eval_worker.worth_a_worker(paper, eval_worker.MIN_EVALUATIONS - 1, "kernel")
    assert not eval_worker.worth_a_worker(paper.replace(eval_draws=1), 21, "kernel")
    monkeypatch.setattr(eval_worker, "auto_threads", lambda: 1)
    assert not eval_worker.worth_a_worker(paper, 21, "kernel")


def test_by_default_the_worker_serves_long_evaluations_of_runs_without_callbacks(monkeypatch):
    submitted = []
    real = eval_worker.EvaluationWorker.submit
    monkeypatch.setattr(eval_worker.EvaluationWorker, "submit",
                        lambda self, theta: submitted.append(theta) or real(self, theta))
    monkeypatch.setattr(eval_worker, "auto_threads", lambda: 2)
    run(None)  # 3 draws of 4 days: below MIN_EVAL_DAYS
    assert submitted == []
    # 100 days per evaluation, as many evaluations as it takes
    long = LEARNING.replace(eval_draws=25, eval_every=1, months=eval_worker.MIN_EVALUATIONS)
    Experiment(SMALL, learning=long, callbacks=[lambda *a: None]).run(progress=False)
    assert submitted == []
    alone = Experiment(SMALL, learning=long)
    alone.run(progress=False)
    months = list(range(eval_worker.MIN_EVALUATIONS))
    assert len(submitted) == len(months) and alone.history.eval_month == months
    short = Experiment(SMALL, learning=long.replace(months=eval_worker.MIN_EVALUATIONS - 1))
    short.run(progress=False)
    assert len(submitted) == len(months)  # too few evaluations to pay for the worker


def _main_module(monkeypatch, tmp_path, text: str | None, spec_name: str | None = None):
    main = types.ModuleType("__main__")
    if text is not None:
        script = tmp_path / "script.py"
        script.write_text(text)
        main.__file__ = str(script)
    main.__spec__ = None if spec_name is None else types.SimpleNamespace(name=spec_name)
    monkeypatch.setitem(sys.modules, "__main__", main)


def test_a_script_without_a_main_guard_evaluates_in_its_own_process(tmp_path, monkeypatch):
    """A spawned worker imports the main module again: an unguarded script would run again."""
    monkeypatch.setattr(eval_worker, "auto_threads", lambda: 2)
    paper = LearningConfig()
    _main_module(monkeypatch, tmp_path, "from mpcrl_lite import Experiment\nExperiment().run()\n")
    assert not eval_worker.spawn_safe()
    assert not eval_worker.worth_a_worker(paper, 21, "kernel")
    _main_module(monkeypatch, tmp_path, "def main():\n    pass\n\n"
                                        "if __name__ == \"__main__\":\n    main()\n")
    assert eval_worker.spawn_safe() and eval_worker.worth_a_worker(paper, 21, "kernel")
    _main_module(monkeypatch, tmp_path, None)  # an interactive session
    assert eval_worker.spawn_safe()
    _main_module(monkeypatch, tmp_path, "import sys\nsys.exit(1)\n", "mpcrl_lite.__main__")
    assert eval_worker.spawn_safe()  # a package's __main__ is not imported again


def test_the_worker_ends_when_its_run_is_killed():
    """A run killed outright (SIGKILL) leaves no worker process behind."""
    code = ("from mpcrl_lite import Experiment, LearningConfig, SystemConfig\n"
            "e = Experiment(SystemConfig(N=6), learning=LearningConfig(days_per_month=4, "
            "months=500, eval_every=1, eval_draws=3))\n"
            "e.eval_worker = True\n"
            "e.run(progress=False)\n")
    assert_workers_die_with([sys.executable, "-c", code], match="spawn_main")


def test_a_run_interrupted_in_its_process_with_evaluations_out_catches_up(in_process):
    """The same object run on after a stop that left evaluations out (no run directory)."""
    experiment = run(False, months=4)
    assert experiment.history.eval_month == [0, 2]
    for name in History.EVAL_SERIES + History.EVAL_CI_SERIES:
        del getattr(experiment.history, name)[:]  # as the stop left them: still out
    experiment.run(progress=False)
    assert experiment.history.eval_month == [0, 2, 4]
    assert results(experiment.history) == results(in_process.history)
