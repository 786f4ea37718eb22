"""Grid points of a sweep, as executed on a worker: their learning runs and their reports.

:func:`run_chunk` is the unit of work the scheduler hands out: a chunk of grid points whose
learning runs advance month by month in lockstep in one process
(:func:`mpcrl_lite.studies.lockstep.run_lockstep`: the runs that share an MPC share its solver
calls; each run's results are bit for bit those of the run alone). Each run is learned (or
resumed) in ``out/runs/<id>/`` and, with a notebook, its report executed; whatever fails is
written next to the run (``error.json``, ``reports/<id>.error.json``) instead of being
raised, so one failing grid point never stops the others. It returns the runs' table rows.
:func:`run_task` is the chunk of one grid point.
"""

from __future__ import annotations

import os
import platform
import time
import traceback
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...learning.experiment import Experiment
from ...learning.q_experiment import QLearningExperiment
from ...publish.report import _check_values, execute_notebook, notebook_parameters
from ..lockstep import run_lockstep
from .grid import GridError, MissingFileError, Sweep, SweepRun
from .store import (
    is_done,
    read_json,
    report_error_path,
    report_path,
    run_dir,
    write_json,
)
from .table import run_row

__all__ = [
    "FAIL_ENV",
    "NOTEBOOK",
    "NOTEBOOK_PARAMETERS",
    "InjectedFailure",
    "check_notebook",
    "notebook_values",
    "run_chunk",
    "run_task",
]

#: The notebook executed per grid point with ``notebooks=True``.
NOTEBOOK = "05_three_agent_learning.ipynb"

#: Configuration field -> parameter of notebook 05. With ``notebooks=True`` every field set
#: by the sweep (base or grid) must appear here, so each report shows exactly its run.
NOTEBOOK_PARAMETERS: dict[str, str] = {
    "system.P_bar": "P_BAR",
    "system.noise_var": "NOISE_VAR",
    "learning.seed": "SEED",
    "learning.months": "MONTHS",
    "learning.days_per_month": "DAYS",
}

#: Test hook: run ids separated by ``;`` (ids contain commas), read by the worker executing
#: a run. Such a run raises :class:`InjectedFailure` right after its first month has been
#: checkpointed, as a crash mid-run would. Unset (the normal case) it does nothing.
FAIL_ENV = "MPCRL_LITE_SWEEP_FAIL"


class InjectedFailure(RuntimeError):
    """Raised by a run named in the environment variable :data:`FAIL_ENV` (tests only)."""


def _injected_failure(run_id: str):
    ids = {s.strip() for s in os.environ.get(FAIL_ENV, "").split(";") if s.strip()}
    if run_id not in ids:
        return None

    def fail(month: int, history: Any, experiment: Any) -> None:
        raise InjectedFailure(f"run {run_id} failed on purpose after month {month} ({FAIL_ENV})")

    return fail


def _error(err: BaseException, seconds: float) -> dict[str, Any]:
    return {
        "type": type(err).__name__,
        "message": str(err),
        "traceback": "".join(traceback.format_exception(err)),
        "seconds": seconds,
        "host": platform.node(),
        "pid": os.getpid(),
    }


def _learn(runs: list[SweepRun], out: Path) -> None:
    """Learn (or resume) the runs in lockstep; each ends with done.json or error.json."""
    t0 = time.perf_counter()
    learners, directories, chunk = [], [], []
    for run in runs:
        directory = run_dir(out, run)
        directory.mkdir(parents=True, exist_ok=True)
        for name in ("done.json", "error.json"):
            (directory / name).unlink(missing_ok=True)
        write_json(directory / "config.json", {"run_id": run.run_id, **run.configs()})
        try:
            # the files a resume reads, checked here so that a damaged one is named in
            # error.json
            for name in ("checkpoint.json", "history.json"):
                read_json(directory / name)
            fail = _injected_failure(run.run_id)
            kind = QLearningExperiment if run.learning.learner == "q" else Experiment
            learners.append(kind(run.system, run.mpc, run.learning, prices=run.file_month(),
                                 callbacks=[fail] if fail else ()))
        except Exception as err:  # noqa: BLE001 (the sweep goes on; the error is kept next to the run)
            write_json(directory / "error.json", _error(err, time.perf_counter() - t0))
            continue
        directories.append(directory)
        chunk.append(run)
    results = run_lockstep(learners, outs=directories, resume=True) if learners else []
    for directory, result in zip(directories, results, strict=True):
        seconds = time.perf_counter() - t0
        if isinstance(result, BaseException):
            write_json(directory / "error.json", _error(result, seconds))
            continue
        write_json(directory / "done.json", {
            "months": result.months,
            "seconds": seconds,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "host": platform.node(),
            "pid": os.getpid(),
        })


# -- the report notebook -------------------------------------------------------------------
def notebook_values(run: SweepRun, mapping: Mapping[str, str]) -> dict[str, Any]:
    """The notebook parameters of a run: every field it sets, renamed by ``mapping``."""
    return {mapping[k]: list(v) if isinstance(v, tuple) else v for k, v in run.overrides.items()}


def check_notebook(sweep: Sweep, notebook: Path, mapping: Mapping[str, str]) -> None:
    """Fail before anything runs if a report could not show its run.

    Raises
    ------
    MissingFileError
        The notebook does not exist.
    GridError
        A field the sweep sets has no notebook parameter in ``mapping``.
    ValueError
        The notebook lacks a mapped parameter or would get a value of the wrong type.
    """
    if not notebook.exists():
        raise MissingFileError(f"notebook {notebook} not found (needed for notebooks=True)")
    for key in list(sweep.base) + list(sweep.grid):
        if key not in mapping:
            where = "base" if key in sweep.base else "grid"
            raise GridError(
                f"notebooks=True: {where} key {key!r} has no notebook parameter, so the report "
                f"would not show this run; mapped keys: {sorted(mapping)}"
            )
    allowed = notebook_parameters(notebook)
    for run in sweep.runs:
        _check_values(notebook.name, notebook_values(run, mapping), allowed)


def _execute_report(run: SweepRun, out: Path, notebook: Path, mapping: Mapping[str, str]) -> None:
    target = report_path(out, run)
    partial = out / "reports" / ".partial" / target.name
    partial.parent.mkdir(parents=True, exist_ok=True)
    error_file = report_error_path(out, run)
    error_file.unlink(missing_ok=True)
    try:
        execute_notebook(notebook, partial, notebook_values(run, mapping), cwd=out / "reports")
    except Exception as err:  # noqa: BLE001 (a failed report is recorded, the run stays done)
        write_json(error_file, {"type": type(err).__name__, "message": str(err),
                                "traceback": traceback.format_exc()})
        return
    partial.replace(target)


# -- the unit of work ----------------------------------------------------------------------
def run_chunk(
    runs: list[SweepRun], out: str, notebook: str | None, mapping: Mapping[str, str]
) -> list[dict[str, Any]]:
    """Everything some grid points still need (their learning runs, in lockstep, and their
    reports); returns their rows in the order of ``runs``.

    Parameters
    ----------
    runs
        The grid points.
    out
        The sweep's output directory (a string, as it travels to Dask workers).
    notebook
        The report notebook, or ``None`` for no report.
    mapping
        Field -> notebook parameter (see :data:`NOTEBOOK_PARAMETERS`).

    Notes
    -----
    A row's ``task_time_s`` is its share of the chunk's learning time plus its report's.
    """
    out_dir = Path(out)
    t0 = time.perf_counter()
    _learn([run for run in runs if not is_done(run, run_dir(out_dir, run))], out_dir)
    share = (time.perf_counter() - t0) / max(len(runs), 1)
    rows = []
    for run in runs:
        t1 = time.perf_counter()
        if notebook is not None and not report_path(out_dir, run).exists():
            _execute_report(run, out_dir, Path(notebook), mapping)
        row = run_row(run, out_dir, notebook is not None)
        row["task_time_s"] = share + time.perf_counter() - t1
        rows.append(row)
    return rows


def run_task(
    run: SweepRun, out: str, notebook: str | None, mapping: Mapping[str, str]
) -> dict[str, Any]:
    """Everything a grid point still needs (its learning run, its report); returns its row
    (:func:`run_chunk` of one grid point)."""
    return run_chunk([run], out, notebook, mapping)[0]
