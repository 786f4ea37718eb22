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

Dask workers need ``mpcrl_lite`` importable and, with a remote scheduler, ``out`` on a file
system they share with the client. Two sweeps must not write into the same ``out`` at once.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
import platform
import re
import time
import traceback
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import pandas as pd

from .config import LearningConfig, MPCConfig, SystemConfig

__all__ = [
    "SECTIONS",
    "NOTEBOOK",
    "NOTEBOOK_PARAMETERS",
    "FAIL_ENV",
    "GridError",
    "InjectedFailure",
    "SweepRun",
    "Sweep",
    "load_grid",
    "run_sweep",
    "run_sweep_cli",
    "load_results",
    "summarize",
]

log = logging.getLogger(__name__)

#: Grid sections and the configuration class each one sets.
SECTIONS: dict[str, type] = {"system": SystemConfig, "mpc": MPCConfig, "learning": LearningConfig}

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
#: a run. Such a
#: run raises :class:`InjectedFailure` right after its first month has been checkpointed,
#: as a crash mid-run would. Unset (the normal case) it does nothing.
FAIL_ENV = "MPCRL_LITE_SWEEP_FAIL"

_ID_MAX = 100
#: Result columns a grid column must not shadow (the grid key keeps its section then).
_RESERVED = frozenset({
    "run_id", "status", "error", "cached", "months_requested", "months", "J_first", "J_last",
    "hours_soc_below_0_1_first", "hours_soc_below_0_1_last", "max_P_mpc", "skipped_steps",
    "solver_failures", "wall_time_s", "task_time_s", "backend", "run_dir", "notebook",
    "notebook_error",
})
_ID_UNSAFE = re.compile(r"[^A-Za-z0-9._+=,-]")


class GridError(ValueError):
    """A sweep description that cannot be run (raised before any run starts)."""


class InjectedFailure(RuntimeError):
    """Raised by a run named in the environment variable :data:`FAIL_ENV` (tests only)."""


# -- the grid ------------------------------------------------------------------------------
@dataclass(frozen=True)
class SweepRun:
    """One grid point: its id, the values that define it and its three configurations.

    Attributes
    ----------
    run_id : directory name and row key, built from the grid values
    values : ``{'section.field': value}`` of the grid keys, in grid order
    overrides : base overrides and grid values together (every field the sweep sets)
    system, mpc, learning : the validated configurations
    """

    run_id: str
    values: dict[str, Any]
    overrides: dict[str, Any]
    system: SystemConfig
    mpc: MPCConfig
    learning: LearningConfig

    def configs(self) -> dict[str, dict[str, Any]]:
        """The three configurations as plain dicts (as stored in ``config.json``)."""
        return {
            "system": self.system.to_dict(),
            "mpc": self.mpc.to_dict(),
            "learning": self.learning.to_dict(),
        }


@dataclass(frozen=True)
class Sweep:
    """A validated sweep: base overrides, grid and the resulting runs (grid order).

    Attributes
    ----------
    base : ``{'section.field': value}`` applied to every run
    grid : ``{'section.field': [values]}``
    columns : ``{'section.field': column}``; the column is the field name unless two
        sections share it
    runs : every grid point
    """

    base: dict[str, Any]
    grid: dict[str, list[Any]]
    columns: dict[str, str]
    runs: tuple[SweepRun, ...]

    @property
    def run_ids(self) -> list[str]:
        """The ids of all runs, in grid order."""
        return [r.run_id for r in self.runs]

    def to_dict(self) -> dict[str, Any]:
        """The sweep in the YAML format (dotted keys; tuples as lists)."""
        plain = lambda v: list(v) if isinstance(v, tuple) else v  # noqa: E731
        return {
            "base": {k: plain(v) for k, v in self.base.items()},
            "grid": {k: [plain(v) for v in vs] for k, vs in self.grid.items()},
        }


def _split_key(key: Any, where: str) -> tuple[str, str]:
    if not isinstance(key, str) or key.count(".") != 1:
        raise GridError(
            f"{where} key {key!r}: expected 'section.field' with section one of {list(SECTIONS)}"
        )
    section, name = key.split(".")
    if section not in SECTIONS:
        raise GridError(
            f"{where} key {key!r}: unknown section {section!r}; expected one of {list(SECTIONS)}"
        )
    allowed = [f.name for f in fields(SECTIONS[section])]
    if name not in allowed:
        raise GridError(
            f"{where} key {key!r}: {SECTIONS[section].__name__} has no field {name!r}; "
            f"expected one of {allowed}"
        )
    return section, name


def _as_value(value: Any) -> Any:
    # YAML lists stand for the configs' tuples (omega, omega_f)
    return tuple(value) if isinstance(value, list) else value


def _parse_base(base: Any) -> dict[str, Any]:
    if base is None:
        return {}
    if not isinstance(base, Mapping):
        raise GridError(f"base: expected a mapping of section -> {{field: value}}, got {base!r}")
    flat: dict[str, Any] = {}
    for key, value in base.items():
        if key in SECTIONS:
            if value is None:
                continue
            if not isinstance(value, Mapping):
                raise GridError(f"base.{key}: expected a mapping of field -> value, got {value!r}")
            items = [(f"{key}.{name}", v) for name, v in value.items()]
        elif isinstance(value, Mapping):
            raise GridError(f"base key {key!r}: unknown section; expected one of {list(SECTIONS)}")
        else:
            items = [(key, value)]
        for dotted, v in items:
            _split_key(dotted, "base")
            if dotted in flat:
                raise GridError(f"base key {dotted!r} is given twice")
            flat[dotted] = _as_value(v)
    return flat


def _format_value(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return "_".join(_format_value(v) for v in value)
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _run_id(values: Mapping[str, Any], columns: Mapping[str, str]) -> str:
    # sorted by column, so reordering the keys of a grid file keeps every run's directory
    pairs = sorted((columns[k], _format_value(v)) for k, v in values.items())
    text = ",".join(f"{name}={value}" for name, value in pairs)
    safe = _ID_UNSAFE.sub("_", text)
    if len(safe) > _ID_MAX:
        digest = hashlib.sha1(text.encode()).hexdigest()[:10]
        safe = f"{safe[: _ID_MAX - 12]}~{digest}"
    return safe


def _yaml_hint(value: Any) -> str:
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return ""
        return f" (YAML read {value!r} as text; write numbers like 1.0e-4 with a dot)"
    return ""


def load_grid(grid: Mapping[str, Any] | str | os.PathLike) -> Sweep:
    """Read and validate a sweep description; build every run's configurations.

    Parameters
    ----------
    grid
        A mapping with keys ``base`` (optional) and ``grid``, or the path of a YAML file
        holding one (see the module docstring).

    Returns
    -------
    Sweep

    Raises
    ------
    GridError
        (a ``ValueError``) naming the bad key, value or grid point: unknown section or
        field, a key that is not a non-empty list, a key both in ``base`` and ``grid``,
        a value rejected by the configuration's validation, two grid points with the same id.
    FileNotFoundError
        If ``grid`` is a path that does not exist.
    """
    if isinstance(grid, (str, os.PathLike)):
        import yaml

        path = Path(grid)
        if not path.exists():
            raise FileNotFoundError(f"grid file {path} not found")
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as err:
            raise GridError(f"{path}: not valid YAML: {err}") from None
    else:
        data = grid
    if not isinstance(data, Mapping):
        raise GridError(
            f"a sweep is a mapping with keys 'base' and 'grid'; got {type(data).__name__}"
        )
    unknown = sorted(set(data) - {"base", "grid"})
    if unknown:
        raise GridError(
            f"unknown top-level key(s) {unknown}; expected 'base' (optional) and 'grid'"
        )
    base = _parse_base(data.get("base"))
    raw = data.get("grid")
    if not isinstance(raw, Mapping) or not raw:
        raise GridError("'grid' must be a non-empty mapping of 'section.field' -> [values]")

    axes: dict[str, list[Any]] = {}
    for key, values in raw.items():
        _split_key(key, "grid")
        if key in base:
            raise GridError(f"grid key {key!r} is also set in base; keep one of them")
        if not isinstance(values, list):
            raise GridError(f"grid key {key!r}: expected a list of values, got {values!r}")
        if not values:
            raise GridError(f"grid key {key!r}: empty list of values")
        values = [_as_value(v) for v in values]
        for i, v in enumerate(values):
            if v in values[:i]:
                raise GridError(f"grid key {key!r}: value {v!r} is listed twice")
        axes[key] = values

    # a column is named by its field unless that is ambiguous or taken by the results
    names = [k.split(".")[1] for k in axes]
    columns = {
        k: name if names.count(name) == 1 and name not in _RESERVED else k
        for k, name in zip(axes, names)
    }

    runs: list[SweepRun] = []
    seen: dict[str, dict[str, Any]] = {}
    for combo in itertools.product(*axes.values()):
        values = dict(zip(axes, combo))
        run_id = _run_id(values, columns)
        if run_id in seen:
            raise GridError(f"grid points {seen[run_id]} and {values} get the same id {run_id!r}")
        seen[run_id] = values
        overrides = {**base, **values}
        configs = {}
        for section, cls in SECTIONS.items():
            prefix = section + "."
            kwargs = {k[len(prefix):]: v for k, v in overrides.items() if k.startswith(prefix)}
            try:
                configs[section] = cls(**kwargs)
            except (ValueError, TypeError) as err:
                hints = "".join(_yaml_hint(v) for v in kwargs.values())
                # the config's message starts with 'field=value': blame base or the grid point
                field = re.match(r"(\w+)=", str(err))
                key = f"{section}.{field.group(1)}" if field else ""
                where = "base" if key in base else f"grid point {run_id}"
                raise GridError(f"{where} ({section}): {err}{hints}") from None
        runs.append(SweepRun(run_id, values, overrides, configs["system"], configs["mpc"],
                             configs["learning"]))
    return Sweep(base=base, grid=axes, columns=columns, runs=tuple(runs))


# -- one run (executed on a worker) --------------------------------------------------------
def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    tmp.replace(path)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _is_done(run: SweepRun, run_dir: Path) -> bool:
    done = _read_json(run_dir / "done.json")
    return done is not None and done.get("months", 0) >= run.learning.months and (
        run_dir / "history.json"
    ).exists()


def _report_path(out: Path, run: SweepRun) -> Path:
    return out / "reports" / f"{run.run_id}.ipynb"


def _injected_failure(run_id: str):
    ids = {s.strip() for s in os.environ.get(FAIL_ENV, "").split(";") if s.strip()}
    if run_id not in ids:
        return None

    def fail(month: int, history: Any, experiment: Any) -> None:
        raise InjectedFailure(f"run {run_id} failed on purpose after month {month} ({FAIL_ENV})")

    return fail


def _learn(run: SweepRun, run_dir: Path) -> None:
    from .experiment import Experiment

    run_dir.mkdir(parents=True, exist_ok=True)
    for name in ("done.json", "error.json"):
        (run_dir / name).unlink(missing_ok=True)
    _write_json(run_dir / "config.json", {"run_id": run.run_id, **run.configs()})
    t0 = time.perf_counter()
    try:
        fail = _injected_failure(run.run_id)
        exp = Experiment(run.system, run.mpc, run.learning, callbacks=[fail] if fail else ())
        history = exp.run(out=run_dir, resume=True, progress=False)
    except Exception as err:  # the sweep goes on; the error is kept next to the run
        _write_json(run_dir / "error.json", {
            "type": type(err).__name__,
            "message": str(err),
            "traceback": traceback.format_exc(),
            "seconds": time.perf_counter() - t0,
            "host": platform.node(),
            "pid": os.getpid(),
        })
        return
    _write_json(run_dir / "done.json", {
        "months": history.months,
        "seconds": time.perf_counter() - t0,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "host": platform.node(),
        "pid": os.getpid(),
    })


def _notebook_parameters(run: SweepRun, mapping: Mapping[str, str]) -> dict[str, Any]:
    return {mapping[k]: list(v) if isinstance(v, tuple) else v for k, v in run.overrides.items()}


def _execute_report(run: SweepRun, out: Path, notebook: Path, mapping: Mapping[str, str]) -> None:
    from .report import execute_notebook

    target = _report_path(out, run)
    partial = out / "reports" / ".partial" / target.name
    partial.parent.mkdir(parents=True, exist_ok=True)
    error_file = out / "reports" / f"{run.run_id}.error.json"
    error_file.unlink(missing_ok=True)
    try:
        execute_notebook(notebook, partial, _notebook_parameters(run, mapping), cwd=out / "reports")
    except Exception as err:
        _write_json(error_file, {"type": type(err).__name__, "message": str(err),
                                 "traceback": traceback.format_exc()})
        return
    partial.replace(target)


def _task(
    run: SweepRun, out: str, notebook: str | None, mapping: Mapping[str, str]
) -> dict[str, Any]:
    """Everything a grid point still needs (the learning run, its report); returns its row."""
    out_dir = Path(out)
    run_dir = out_dir / "runs" / run.run_id
    t0 = time.perf_counter()
    if not _is_done(run, run_dir):
        _learn(run, run_dir)
    if notebook is not None and not _report_path(out_dir, run).exists():
        _execute_report(run, out_dir, Path(notebook), mapping)
    row = _row(run, out_dir, notebook is not None)
    row["task_time_s"] = time.perf_counter() - t0
    return row


# -- the table -----------------------------------------------------------------------------
def _row(run: SweepRun, out: Path, notebooks: bool) -> dict[str, Any]:
    """The table row of a run, read from its directory."""
    from .history import History

    run_dir = out / "runs" / run.run_id
    row: dict[str, Any] = {"run_id": run.run_id}
    row.update({k: list(v) if isinstance(v, tuple) else v for k, v in run.values.items()})
    error = _read_json(run_dir / "error.json")
    if _is_done(run, run_dir):
        row["status"], row["error"] = "done", ""
    elif error is not None:
        row["status"], row["error"] = "failed", f"{error['type']}: {error['message']}"
    else:
        row["status"], row["error"] = "pending", ""
    row["months_requested"] = run.learning.months
    history = None
    if (run_dir / "history.json").exists():
        try:
            history = History.load(run_dir)
        except (OSError, ValueError, KeyError) as err:
            row["error"] = row["error"] or f"{type(err).__name__}: {err}"
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
        report = _report_path(out, run)
        nb_error = _read_json(out / "reports" / f"{run.run_id}.error.json")
        row["notebook"] = str(report.relative_to(out)) if report.exists() else ""
        row["notebook_error"] = (
            "" if nb_error is None else f"{nb_error['type']}: {nb_error['message']}"
        )
    return row


_FIRST = ["run_id"]
_AFTER_GRID = ["status", "error", "cached", "months_requested", "months", "J_first", "J_last"]
_TAIL = [
    "hours_soc_below_0_1_first", "hours_soc_below_0_1_last", "max_P_mpc", "skipped_steps",
    "solver_failures", "wall_time_s", "task_time_s", "backend", "run_dir", "notebook",
    "notebook_error",
]


def _table(sweep: Sweep, rows: Mapping[str, dict[str, Any]], notebooks: bool) -> pd.DataFrame:
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


def _write_table(table: pd.DataFrame, out: Path) -> None:
    tmp = out / "results.csv.tmp"
    table.to_csv(tmp, index=False)
    tmp.replace(out / "results.csv")
    try:
        tmp = out / "results.tmp.parquet"
        table.to_parquet(tmp, index=False)
        tmp.replace(out / "results.parquet")
    except ImportError:  # pyarrow is optional; the csv is always written
        log.warning("pyarrow is not installed: %s not written", out / "results.parquet")


def load_results(out: str | os.PathLike) -> pd.DataFrame:
    """The results table of a sweep directory (``results.parquet``, else ``results.csv``)."""
    out = Path(out)
    if (out / "results.parquet").exists():
        return pd.read_parquet(out / "results.parquet")
    if (out / "results.csv").exists():
        return pd.read_csv(out / "results.csv", keep_default_na=False, na_values=[""])
    raise FileNotFoundError(f"no results.parquet or results.csv in {out}: not a sweep directory")


# -- checks before anything runs -----------------------------------------------------------
def _check_run_dirs(sweep: Sweep, out: Path) -> None:
    for run in sweep.runs:
        saved = _read_json(out / "runs" / run.run_id / "config.json")
        if saved is None:
            continue
        mine = run.configs()
        for section in SECTIONS:
            old, new = dict(saved.get(section, {})), dict(mine[section])
            if section == "learning":
                old.pop("months", None)
                new.pop("months", None)
            diff = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
            if diff:
                k = diff[0]
                raise GridError(
                    f"{out / 'runs' / run.run_id} holds a run with {section}.{k}={old.get(k)!r}, "
                    f"but this sweep sets {new.get(k)!r}; use another output directory or "
                    "delete that run directory"
                )


def _check_notebook(sweep: Sweep, notebook: Path, mapping: Mapping[str, str]) -> None:
    from .report import _check_values, notebook_parameters

    if not notebook.exists():
        raise FileNotFoundError(f"notebook {notebook} not found (needed for notebooks=True)")
    for key in list(sweep.base) + list(sweep.grid):
        if key not in mapping:
            where = "base" if key in sweep.base else "grid"
            raise GridError(
                f"notebooks=True: {where} key {key!r} has no notebook parameter, so the report "
                f"would not show this run; mapped keys: {sorted(mapping)}"
            )
    allowed = notebook_parameters(notebook)
    for run in sweep.runs:
        _check_values(notebook.name, _notebook_parameters(run, mapping), allowed)


# -- the sweep -----------------------------------------------------------------------------
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
        Before anything runs: invalid grid, unknown ``only`` id, a run directory holding a
        run with other settings, an unmapped notebook parameter.
    """
    t_start = time.perf_counter()
    sweep = load_grid(grid)
    out = Path(out).resolve()
    serial = scheduler == "serial" or workers == 0
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 0
    ):
        raise GridError(f"workers={workers!r}: expected an integer >= 0")
    if workers and scheduler not in (None, "serial"):
        raise GridError(
            "workers sets the size of the local cluster; it cannot be used with a scheduler address"
        )
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
        from .report import NOTEBOOK_DIR

        nb_path = Path(notebook).resolve() if notebook is not None else NOTEBOOK_DIR / NOTEBOOK
        _check_notebook(sweep, nb_path, mapping)
    _check_run_dirs(sweep, out)

    out.mkdir(parents=True, exist_ok=True)
    import yaml

    (out / "grid.yaml").write_text(yaml.safe_dump(sweep.to_dict(), sort_keys=False))
    rows = {run.run_id: _row(run, out, notebooks) for run in sweep.runs}
    for row in rows.values():
        row["cached"] = row["status"] == "done"
    todo = [
        run for run in sweep.runs
        if run.run_id in selected and (
            rows[run.run_id]["status"] != "done" or (notebooks and not rows[run.run_id]["notebook"])
        )
    ]
    _write_table(_table(sweep, rows, notebooks), out)

    def finished(run: SweepRun, row: dict[str, Any]) -> None:
        row["cached"] = False
        rows[run.run_id] = row
        _write_table(_table(sweep, rows, notebooks), out)

    args = (str(out), None if nb_path is None else str(nb_path), mapping)
    try:
        if not todo:
            pass
        elif serial:
            _run_serial(todo, args, finished, progress)
        else:
            _run_dask(todo, args, finished, progress, scheduler, workers, out)
    finally:
        table = _table(sweep, rows, notebooks)
        table.attrs.update({
            "wall_time_s": time.perf_counter() - t_start,
            "executed": len(todo),
            "failed": int((table["status"] == "failed").sum()),
            "scheduler": "serial" if serial else (scheduler or f"local:{workers or 2}"),
        })
        _write_table(table, out)
        _write_json(out / "sweep.json", {**table.attrs, "runs": len(table)})
    return table


def _run_serial(todo: Sequence[SweepRun], args: tuple, finished, progress: bool) -> None:
    from tqdm.auto import tqdm

    with tqdm(total=len(todo), desc="sweep (serial)", unit="run", disable=not progress) as bar:
        for run in todo:
            row = _task(run, *args)
            finished(run, row)
            bar.update(1)


def _run_dask(
    todo: Sequence[SweepRun], args: tuple, finished, progress: bool,
    scheduler: str | None, workers: int | None, out: Path,
) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as err:
        raise ImportError(
            "Dask is needed for parallel sweeps: pip install 'mpcrl_lite[sweep]' "
            "(or pass scheduler='serial')"
        ) from err
    from contextlib import ExitStack

    from tqdm.auto import tqdm

    with ExitStack() as stack:
        if scheduler is None:
            cluster = stack.enter_context(LocalCluster(
                n_workers=workers or 2, threads_per_worker=1, processes=True,
                host="127.0.0.1", dashboard_address="127.0.0.1:0",
                # shutdown races (a worker's last heartbeat) log tracebacks at ERROR level;
                # a run's own errors are in its error.json, a lost worker raises here
                silence_logs=logging.CRITICAL,
            ))
            client = stack.enter_context(Client(cluster))
        else:
            client = stack.enter_context(Client(scheduler))
        token = os.urandom(4).hex()
        futures = {
            client.submit(_task, run, *args, key=f"sweep-{token}-{run.run_id}", pure=False): run
            for run in todo
        }
        failed = 0
        with tqdm(total=len(todo), desc="sweep", unit="run", disable=not progress) as bar:
            for future in as_completed(futures):
                run = futures[future]
                try:
                    row = future.result()
                except Exception as err:  # the worker died or the task could not run
                    run_dir = out / "runs" / run.run_id
                    run_dir.mkdir(parents=True, exist_ok=True)
                    _write_json(run_dir / "error.json", {
                        "type": type(err).__name__, "message": str(err),
                        "traceback": "".join(traceback.format_exception(err)),
                    })
                    row = _row(run, out, args[1] is not None)
                if row["status"] == "failed":
                    failed += 1
                    bar.set_postfix(failed=failed, refresh=False)
                finished(run, row)
                bar.update(1)


def run_sweep_cli(
    grid_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    scheduler: str | None = None,
    workers: int | None = None,
    notebooks: bool = False,
    progress: bool = True,
    only: Iterable[str] | None = None,
) -> pd.DataFrame:
    """The ``sweep`` command: :func:`run_sweep` on a YAML file.

    Running the command again on the same ``--out`` executes only what is unfinished or
    failed; ``only`` restricts it to the given run ids. Returns the results table (also in
    ``out_dir/results.csv``).
    """
    return run_sweep(grid_path, out_dir, scheduler=scheduler, workers=workers,
                     notebooks=notebooks, progress=progress, only=only)


# -- analysis ------------------------------------------------------------------------------
def summarize(
    table: pd.DataFrame,
    by: Sequence[str] = ("P_bar", "noise_var"),
    metrics: Sequence[str] | None = None,
) -> pd.DataFrame:
    """Mean and standard deviation over the other grid keys (usually the seeds).

    Parameters
    ----------
    table
        A results table from :func:`run_sweep` or :func:`load_results`; only rows with
        ``status == 'done'`` are used.
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
