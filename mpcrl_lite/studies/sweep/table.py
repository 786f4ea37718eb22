"""The tidy results table of a sweep: one row per run, read from the run's directory.

:func:`run_row` reads what a run left on disk (status, error, the History's key numbers), so
the table of a sweep can be rebuilt at any time, including by a later call that executes
nothing. :func:`results_table` puts the rows in grid order with the same columns whatever has
run so far; :func:`write_table` saves it as ``results.csv`` (and ``results.parquet`` when
pyarrow is installed); :func:`load_results` reads it back and :func:`summarize` aggregates it
over the seeds.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from ...learning.history import History
from .grid import Sweep, SweepRun, one_line
from .store import (
    DamagedFileError,
    is_done,
    read_json,
    report_error_path,
    report_path,
    run_dir,
)

__all__ = ["COLUMNS", "load_results", "results_table", "run_row", "summarize", "write_table"]

log = logging.getLogger(__name__)

_FIRST = ["run_id"]
_AFTER_GRID = ["status", "error", "cached", "months_requested", "months", "J_first", "J_last"]
_TAIL = [
    "hours_soc_below_0_1_first", "hours_soc_below_0_1_last", "max_P_mpc", "skipped_steps",
    "solver_failures", "wall_time_s", "task_time_s", "backend", "run_dir", "notebook",
    "notebook_error",
]
#: The table's columns other than the grid values and the per-agent ``J_<i>_first/_last``.
COLUMNS: tuple[str, ...] = (*_FIRST, *_AFTER_GRID, *_TAIL)


def _error_text(error: Mapping[str, Any]) -> str:
    return f"{error.get('type', 'Error')}: {error.get('message', '')}"


def _read_error(path: Path) -> str | None:
    """'Type: message' of an error file, ``None`` without one; a damaged file is an error too."""
    try:
        error = read_json(path)
    except DamagedFileError as err:
        return f"{type(err).__name__}: {err}"
    return None if error is None else _error_text(error)


def _status(run: SweepRun, directory: Path) -> tuple[str, str]:
    if is_done(run, directory):
        return "done", ""
    error = _read_error(directory / "error.json")
    if error is not None:
        return "failed", error
    try:
        read_json(directory / "done.json")
    except DamagedFileError as err:  # is_done() said no because of it
        return "failed", f"{type(err).__name__}: {err}"
    return "pending", ""


def _load_history(directory: Path) -> History:
    try:
        return History.load(directory)
    except json.JSONDecodeError as err:  # its message names no file
        raise DamagedFileError(
            f"{directory / 'history.json'} is not valid JSON "
            f"(line {err.lineno}, column {err.colno}: {err.msg})"
        ) from None
    except ValueError as err:  # the run directory does not verify (the message names the file)
        raise DamagedFileError(str(err)) from None


def run_row(run: SweepRun, out: Path, notebooks: bool) -> dict[str, Any]:
    """The table row of a run, read from its directory (keys: grid keys, not columns)."""
    directory = run_dir(out, run)
    row: dict[str, Any] = {"run_id": run.run_id}
    row.update({k: list(v) if isinstance(v, tuple) else v for k, v in run.values.items()})
    row["status"], row["error"] = _status(run, directory)
    row["months_requested"] = run.learning.months
    history = None
    if (directory / "history.json").exists():
        try:
            history = _load_history(directory)
        # whatever is wrong with a run's files stays in its row; the other runs go on
        except Exception as err:  # noqa: BLE001
            row["error"] = row["error"] or f"{type(err).__name__}: {one_line(err)}"
    row["months"] = history.months if history is not None else 0
    if history is not None and history.months:
        row["J_first"], row["J_last"] = history.J[0], history.J[-1]
        for when, idx in (("first", 0), ("last", -1)):
            for i, value in enumerate(history.J_per_agent[idx], start=1):
                row[f"J_{i}_{when}"] = value
        row["hours_soc_below_0_1_first"] = history.hours_soc_below_0_1[0]
        row["hours_soc_below_0_1_last"] = history.hours_soc_below_0_1[-1]
        row["max_P_mpc"] = max(history.max_P_mpc)
        row["skipped_steps"] = int(sum(history.skipped_steps))
        row["solver_failures"] = int(sum(history.solver_failures))
        row["wall_time_s"] = float(sum(history.wall_time_s))
        row["backend"] = history.backend
    row["run_dir"] = str(Path("runs") / run.run_id)
    if notebooks:
        report = report_path(out, run)
        row["notebook"] = str(report.relative_to(out)) if report.exists() else ""
        row["notebook_error"] = _read_error(report_error_path(out, run)) or ""
    return row


def results_table(
    sweep: Sweep, rows: Mapping[str, dict[str, Any]], notebooks: bool
) -> pd.DataFrame:
    """The rows of :func:`run_row` as one table in grid order, grid keys renamed to columns."""
    records = []
    for run in sweep.runs:
        record = {sweep.columns[k]: v for k, v in rows[run.run_id].items() if k in sweep.columns}
        record.update({k: v for k, v in rows[run.run_id].items() if k not in sweep.columns})
        records.append(record)
    # the same columns whatever has run so far (missing values are NaN)
    n = max(run.system.n for run in sweep.runs)
    agents = [f"J_{i}_{when}" for when in ("first", "last") for i in range(1, n + 1)]
    tail = _TAIL if notebooks else [c for c in _TAIL if not c.startswith("notebook")]
    order = _FIRST + list(sweep.columns.values()) + _AFTER_GRID + agents + tail
    return pd.DataFrame.from_records(records).reindex(columns=order)


def write_table(table: pd.DataFrame, out: Path) -> None:
    """Save ``table`` as ``out/results.csv`` and, with pyarrow, ``out/results.parquet``
    (each written aside and renamed; a failed write, e.g. a full disk, removes its temporary
    file and raises the ``OSError``)."""
    tmp = out / "results.csv.tmp"
    try:
        table.to_csv(tmp, index=False)
        tmp.replace(out / "results.csv")
        tmp = out / "results.tmp.parquet"
        table.to_parquet(tmp, index=False)
        tmp.replace(out / "results.parquet")
    except ImportError:  # pyarrow is optional; the csv is always written
        log.warning("pyarrow is not installed: %s not written", out / "results.parquet")
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_results(out: str | os.PathLike) -> pd.DataFrame:
    """The results table of a sweep directory (``results.parquet``, else ``results.csv``)."""
    out = Path(out)
    if (out / "results.parquet").exists():
        return pd.read_parquet(out / "results.parquet")
    if (out / "results.csv").exists():
        return pd.read_csv(out / "results.csv", keep_default_na=False, na_values=[""])
    raise FileNotFoundError(f"no results.parquet or results.csv in {out}: not a sweep directory")


def summarize(
    table: pd.DataFrame,
    by: Sequence[str] = ("P_bar", "noise_var"),
    metrics: Sequence[str] | None = None,
) -> pd.DataFrame:
    """Mean and standard deviation over the other grid keys (usually the seeds).

    Parameters
    ----------
    table
        A results table from :func:`~mpcrl_lite.studies.sweep.api.run_sweep` or :func:`load_results`;
        only rows with ``status == 'done'`` are used.
    by
        Columns to group by.
    metrics
        Columns to aggregate (default: ``J_first``, ``J_last``, the per-agent last-month
        ``J_<i>_last``, ``hours_soc_below_0_1_first``/``_last``, ``max_P_mpc``,
        ``skipped_steps``, ``wall_time_s``, the ones present).

    Returns
    -------
    pandas.DataFrame
        One row per group: the ``by`` columns, ``runs`` (count), then ``<metric>_mean``
        and ``<metric>_std`` (sample std, NaN for a single run).
    """
    by = [by] if isinstance(by, str) else list(by)
    missing = [c for c in by if c not in table.columns]
    if missing:
        raise ValueError(
            f"by={by}: column(s) {missing} not in the table; columns are {list(table.columns)}"
        )
    if metrics is None:
        agents = sorted((c for c in table.columns if re.fullmatch(r"J_\d+_last", c)),
                        key=lambda c: int(c.split("_")[1]))
        wanted = ["J_first", "J_last", *agents, "hours_soc_below_0_1_first",
                  "hours_soc_below_0_1_last", "max_P_mpc", "skipped_steps", "wall_time_s"]
        metrics = [c for c in wanted if c in table.columns]
    else:
        metrics = list(metrics)
        missing = [c for c in metrics if c not in table.columns]
        if missing:
            raise ValueError(f"metrics: column(s) {missing} not in the table")
    done = table[table["status"] == "done"] if "status" in table.columns else table
    grouped = done.groupby(by, sort=True, dropna=False)
    result = grouped.size().rename("runs").to_frame()
    stats = grouped[metrics].agg(["mean", "std"])
    stats.columns = [f"{m}_{s}" for m, s in stats.columns]
    return result.join(stats).reset_index()
