"""Parameter sweeps: a grid of learning runs, on Dask or serially, into one tidy table.

A sweep is described by a small YAML file (or the same structure as a dict)::

    base:                      # optional: overrides applied to every run
      system: {N: 12}
      learning: {months: 3, days_per_month: 5}
    grid:                      # cartesian product, in the order written
      system.P_bar: [1.0, 1.5]
      system.noise_var: [0.2, 0.5]
      learning.seed: [0, 1, 2]

Keys are ``section.field`` with ``section`` one of ``system``, ``mpc``, ``learning`` (the
fields of :class:`~mpcrl_lite.config.SystemConfig`, :class:`~mpcrl_lite.config.MPCConfig`
and :class:`~mpcrl_lite.config.LearningConfig`); ``base`` may be written per section, as
above, or with the same dotted keys. :func:`load_grid` builds and validates the
configurations of *every* run before anything starts, and its errors name the bad key or
the grid point and the value.

Layout of the output directory ``out``::

    out/grid.yaml               the sweep as understood (base + grid)
    out/results.csv, .parquet   one row per run (rewritten as runs finish)
    out/sweep.json              the last invocation: wall time, runs executed, failures
    out/runs/<id>/              one run: config.json, history.json/.npz, checkpoint.json,
                                done.json when finished, error.json when it failed
    out/reports/<id>.ipynb      with notebooks=True: notebook 05 executed for the grid point
                                (``<id>.error.json`` instead if it failed)

A run's ``<id>`` is its grid values sorted by name, e.g. ``P_bar=1.0,noise_var=0.2,seed=0``
(the order of the grid's keys changes the table's row order, never the ids). A run is
finished when ``done.json`` exists and its History holds the requested months; running the
same sweep again skips finished runs, resumes interrupted ones from their last monthly
checkpoint and retries failed ones. ``only=[id, ...]`` restricts the execution to some runs
(the table still lists every run). A finished run is recomputed only if its directory is
deleted; a run directory written with different settings (other than ``learning.months``,
which may grow) is refused before anything starts.

Everything that can be checked is checked before anything is written: the grid, the
arguments, the output directory (not a file, writable), the run directories already there,
the report notebook and, for ``scheduler='tcp://...'``, that a Dask scheduler answers there
within ``connect_timeout`` seconds. Each failure is a :class:`GridError` (a ``ValueError``)
with a one-line message; the ``sweep`` command prints it as one line and exits with status 2.

Each task (a Dask task, or the serial loop's step) learns a chunk of runs month by month in
lockstep in one process (:mod:`mpcrl_lite.studies.lockstep`: runs that share the MPC formulation
share its solver calls, each run with its own generator, update and checkpoint, and each
run's results are bit for bit those of the run alone). ``lockstep=K`` sets the runs per
task; by default each worker gets its share of the runs as one task (serial: all runs), and
``lockstep=1`` gives one run per task. A finished chunk reports its runs to the table.

Dask workers need ``mpcrl_lite`` importable and, with a remote scheduler, ``out`` on a file
system they share with the client. Two sweeps must not write into the same ``out`` at once.

The parts, one module each (all public names are importable from here):

* :mod:`mpcrl_lite.studies.sweep.grid` -- the grid: parsing, validation, run ids (:func:`load_grid`);
* :mod:`mpcrl_lite.studies.sweep.store` -- the output directory: paths, atomic JSON, checks;
* :mod:`mpcrl_lite.studies.sweep.table` -- the results table (:func:`load_results`, :func:`summarize`);
* :mod:`mpcrl_lite.studies.sweep.run` -- grid points on a worker (learning runs in lockstep,
  report notebooks);
* :mod:`mpcrl_lite.studies.sweep.schedule` -- serial or Dask execution, the scheduler check;
* this module -- :func:`run_sweep` and the ``sweep`` command (:func:`run_sweep_cli`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from ..._util.budget import Budget, check_estimate, learning_estimate
from ...learning import outdir
from ...publish.report import NOTEBOOK_DIR
from .grid import (
    SECTIONS,
    GridError,
    MissingFileError,
    Sweep,
    SweepRun,
    load_grid,
    one_line,
)
from .run import (
    FAIL_ENV,
    NOTEBOOK,
    NOTEBOOK_PARAMETERS,
    InjectedFailure,
    check_notebook,
)
from .schedule import (
    CONNECT_TIMEOUT,
    DaskMissingError,
    SchedulerError,
    check_address,
    check_scheduler,
    require_dask,
    run_dask,
    run_serial,
)
from .store import DamagedFileError, check_out_dir, check_run_dirs, write_json
from .table import load_results, results_table, run_row, summarize, write_table

__all__ = [
    "CONNECT_TIMEOUT",
    "FAIL_ENV",
    "NOTEBOOK",
    "NOTEBOOK_PARAMETERS",
    "SECTIONS",
    "DamagedFileError",
    "DaskMissingError",
    "GridError",
    "InjectedFailure",
    "MissingFileError",
    "SchedulerError",
    "Sweep",
    "SweepRun",
    "check_scheduler",
    "check_sweep_budget",
    "load_grid",
    "load_results",
    "run_sweep",
    "run_sweep_cli",
    "summarize",
]


def _check_arguments(scheduler: Any, workers: Any, lockstep: Any = None) -> None:
    if lockstep is not None and (
        isinstance(lockstep, bool) or not isinstance(lockstep, int) or lockstep < 1
    ):
        raise GridError(f"lockstep={lockstep!r}: expected None (each worker's share) or an "
                        "integer >= 1 (runs per task)")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 0
    ):
        raise GridError(f"workers={workers!r}: expected an integer >= 0")
    if scheduler is not None and not isinstance(scheduler, str):
        raise GridError(
            f"scheduler={scheduler!r}: expected None (a local cluster), 'serial' or the "
            "address of a Dask scheduler"
        )
    if workers is not None and scheduler not in (None, "serial"):
        raise GridError(
            f"workers={workers!r} and scheduler={scheduler!r} contradict each other: workers "
            "sets the size of a local cluster (0: serial), a scheduler address runs on that "
            "scheduler's workers; expected one of them"
        )
    if scheduler not in (None, "serial"):
        check_address(scheduler)


def check_sweep_budget(sweep: Sweep, scheduler: str | None = None,
                       workers: int | None = None) -> Budget:
    """The memory of the largest run and the run time of all of them (shared by the local
    workers; a remote cluster's size is not known, so only memory is checked there) against
    the machine (:func:`mpcrl_lite._util.budget.check_estimate`), before anything starts.

    Raises
    ------
    GridError
        One line naming the number of runs and the largest one.
    """
    budgets = [learning_estimate(r.system.n, r.learning.days_per_month, r.learning.months,
                                 r.learning.eval_draws, r.learning.eval_every, r.system.N)
               for r in sweep.runs]
    largest = max(range(len(budgets)), key=lambda i: budgets[i].seconds)
    run = sweep.runs[largest]
    remote = scheduler not in (None, "serial") and workers is None
    slots = 1 if scheduler == "serial" or workers == 0 else (workers or 2)
    total = Budget(max(b.memory for b in budgets),
                   0.0 if remote else sum(b.seconds for b in budgets) / slots)
    what = (f"the sweep's {len(budgets)} run(s) (the largest: run {run.run_id!r}, learning.months "
            f"{run.learning.months}, days_per_month {run.learning.days_per_month}, n "
            f"{run.system.n})")
    try:
        return check_estimate(what, total)
    except ValueError as err:
        raise GridError(str(err)) from None


def run_sweep(
    grid: Mapping[str, Any] | str | os.PathLike,
    out: str | os.PathLike,
    scheduler: str | None = None,
    workers: int | None = None,
    notebooks: bool = False,
    progress: bool = True,
    only: Iterable[str] | None = None,
    notebook: str | os.PathLike | None = None,
    notebook_parameters: Mapping[str, str] | None = None,
    connect_timeout: float = CONNECT_TIMEOUT,
    lockstep: int | None = None,
) -> pd.DataFrame:
    """Run every unfinished grid point; return (and save) one row per run.

    Parameters
    ----------
    grid
        The sweep, as a mapping or a YAML path (see :func:`load_grid`).
    out
        Output directory (created); see the module docstring for its layout.
    scheduler
        ``None``: a local Dask cluster of ``workers`` processes (default 2, one thread
        each, listening on 127.0.0.1 only; closed at the end). ``'serial'``: run in this
        process, one after another. Otherwise the address of a running Dask scheduler.
    workers
        Number of local worker processes; ``0`` means serial.
    notebooks
        Also execute the notebook (default :data:`NOTEBOOK`) per grid point into
        ``out/reports/<id>.ipynb`` with the parameters of :data:`NOTEBOOK_PARAMETERS`.
    progress
        Show a progress bar over the runs to execute.
    only
        Run ids to execute (others are only read back); unfinished ones among them run.
    notebook
        The notebook executed with ``notebooks=True`` (default: the package's notebook 05).
    notebook_parameters
        Field -> notebook parameter mapping (default :data:`NOTEBOOK_PARAMETERS`).
    connect_timeout
        Seconds to wait for the scheduler at a ``scheduler`` address to answer, checked
        before anything is written (default :data:`CONNECT_TIMEOUT`).
    lockstep
        Runs per task, learned month by month in lockstep in one process
        (:mod:`mpcrl_lite.studies.lockstep`; same results as one by one). Default: each worker's
        share of the runs as one task (serial: all runs); ``1``: one run per task.

    Returns
    -------
    pandas.DataFrame
        One row per run in grid order: ``run_id``, the grid values (one column each, named
        by field), ``status`` ('done', 'failed' or 'pending'), ``error`` ('Type: message'),
        ``cached`` (finished before this call), ``months_requested``, ``months``,
        ``J_first``/``J_last`` and per agent ``J_<i>_first``/``J_<i>_last``,
        ``hours_soc_below_0_1_first``/``_last``, ``max_P_mpc`` (over all months),
        ``skipped_steps`` and ``solver_failures`` (totals), ``wall_time_s`` (learning time
        summed over months), ``task_time_s`` (this call), ``backend``, ``run_dir`` and with
        notebooks ``notebook``/``notebook_error``. ``table.attrs`` holds the sweep's wall
        time and counts. The table is also written to ``out/results.csv`` and
        ``out/results.parquet``, updated each time a run finishes.

    Raises
    ------
    GridError
        (a ``ValueError``, message in one line) before anything is written: invalid grid or
        grid file, bad arguments, unknown ``only`` id, ``out`` a file or not writable, a run
        directory holding a run with other settings or a damaged ``config.json``
        (:class:`DamagedFileError`), an unmapped notebook parameter, no scheduler answering
        at the ``scheduler`` address (:class:`SchedulerError`), Dask not installed
        (:class:`DaskMissingError`, also an ``ImportError``).
    """
    t_start = time.perf_counter()
    sweep = load_grid(grid)
    _check_arguments(scheduler, workers, lockstep)
    check_sweep_budget(sweep, scheduler, workers)
    try:
        out = Path(outdir.refuse_empty(out)).resolve()
    except outdir.RunDirError as err:
        raise GridError(str(err)) from None
    serial = scheduler == "serial" or workers == 0
    selected = set(sweep.run_ids)
    if only is not None:
        only = [only] if isinstance(only, str) else list(only)
        unknown = [i for i in only if i not in selected]
        if unknown:
            raise GridError(f"unknown run id(s) {unknown}; this sweep has {sweep.run_ids}")
        selected = set(only)
    mapping = dict(NOTEBOOK_PARAMETERS if notebook_parameters is None else notebook_parameters)
    nb_path: Path | None = None
    if notebooks:
        nb_path = Path(notebook).resolve() if notebook is not None else NOTEBOOK_DIR / NOTEBOOK
        check_notebook(sweep, nb_path, mapping)
    check_out_dir(out)
    check_run_dirs(sweep, out)
    if not serial and scheduler is not None:
        check_scheduler(scheduler, connect_timeout)

    try:
        grid_text = yaml.safe_dump(sweep.to_dict(), sort_keys=False)
    except yaml.YAMLError as err:  # e.g. numpy scalars in a grid given as a dict
        what = " ".join(a if isinstance(a, str) else repr(a) for a in err.args)
        raise GridError(
            f"the sweep cannot be saved as grid.yaml ({one_line(what)}); "
            "give its values as plain numbers, strings and lists"
        ) from None
    try:  # the lock needs the directory
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise GridError(f"output directory {out} cannot be written: {err}") from None
    with outdir.lock_output_dir(out, "sweep"):  # one process at a time in out
        rows = {run.run_id: run_row(run, out, notebooks) for run in sweep.runs}
        for row in rows.values():
            row["cached"] = row["status"] == "done"
        todo = [
            run for run in sweep.runs
            if run.run_id in selected and (
                rows[run.run_id]["status"] != "done" or (notebooks and not rows[run.run_id]["notebook"])
            )
        ]
        if todo and not serial:
            require_dask()

        # the first writes: a failure here (a full disk, a race) is still one line
        try:
            out.mkdir(parents=True, exist_ok=True)
            (out / "grid.yaml").write_text(grid_text)
            write_table(results_table(sweep, rows, notebooks), out)
        except OSError as err:
            raise GridError(f"output directory {out} cannot be written: {err}") from None

        def finished(run: SweepRun, row: dict[str, Any]) -> None:
            row["cached"] = False
            rows[run.run_id] = row
            write_table(results_table(sweep, rows, notebooks), out)

        args = (str(out), None if nb_path is None else str(nb_path), mapping)
        try:
            if not todo:
                pass
            elif serial:
                run_serial(todo, args, finished, progress, lockstep)
            else:
                run_dask(todo, args, finished, progress, scheduler, workers, out, lockstep)
        finally:
            table = results_table(sweep, rows, notebooks)
            table.attrs.update({
                "wall_time_s": time.perf_counter() - t_start,
                "executed": len(todo),
                "failed": int((table["status"] == "failed").sum()),
                "scheduler": "serial" if serial else (scheduler or f"local:{workers or 2}"),
            })
            write_table(table, out)
            write_json(out / "sweep.json", {**table.attrs, "runs": len(table)})
        return table


def run_sweep_cli(
    grid_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    scheduler: str | None = None,
    workers: int | None = None,
    notebooks: bool = False,
    progress: bool = True,
    only: Iterable[str] | None = None,
    connect_timeout: float = CONNECT_TIMEOUT,
    lockstep: int | None = None,
) -> pd.DataFrame:
    """The ``sweep`` command: :func:`run_sweep` on a YAML file.

    Running the command again on the same ``--out`` executes only what is unfinished or
    failed; ``only`` restricts it to the given run ids. Returns the results table (also in
    ``out_dir/results.csv``). Every error found before the runs start is a ``ValueError``
    with a one-line message (the command prints it and exits with status 2).
    """
    return run_sweep(grid_path, out_dir, scheduler=scheduler, workers=workers,
                     notebooks=notebooks, progress=progress, only=only,
                     connect_timeout=connect_timeout, lockstep=lockstep)
