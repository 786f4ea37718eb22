"""The output directory of a sweep: where each file lives, atomic JSON, checks before writing.

Layout (see :mod:`mpcrl_lite.studies.sweep.api`)::

    out/grid.yaml, results.csv, results.parquet, sweep.json
    out/runs/<id>/              config.json, history.json/.npz, checkpoint.json,
                                done.json when finished, error.json when it failed
    out/reports/<id>.ipynb      (or <id>.error.json) with notebooks=True

JSON files are written atomically (a temporary file, then a rename), so a crash leaves either
the old file or the new one. A file that is damaged all the same (edited by hand, a full disk)
is reported as a :class:`DamagedFileError` naming it, never as a bare ``JSONDecodeError``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ...learning import durable, outdir
from ...learning.rundir import LEGACY_VALUES
from .grid import SECTIONS, GridError, Sweep, SweepRun, one_line

__all__ = [
    "DamagedFileError",
    "check_out_dir",
    "check_run_dirs",
    "is_done",
    "read_json",
    "report_error_path",
    "report_path",
    "run_dir",
    "write_json",
]


class DamagedFileError(GridError):
    """A file of the output directory that cannot be read back (the message names it)."""


def write_json(path: Path, data: Any) -> None:
    """Write ``data`` as strict JSON to ``path`` atomically
    (:func:`mpcrl_lite.learning.durable.write_json`)."""
    durable.write_json(path, data)


def read_json(path: Path) -> dict[str, Any] | None:
    """The JSON object in ``path``; ``None`` if there is no such file.

    Raises
    ------
    DamagedFileError
        If the file exists but cannot be read, is not valid JSON or holds no JSON object.
    """
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as err:
        raise DamagedFileError(f"{path} cannot be read: {one_line(err)}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise DamagedFileError(
            f"{path} is not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})"
        ) from None
    if not isinstance(data, dict):
        raise DamagedFileError(f"{path} holds a JSON {type(data).__name__}; expected an object")
    return data


def run_dir(out: Path, run: SweepRun) -> Path:
    """The directory of one run."""
    return out / "runs" / run.run_id


def report_path(out: Path, run: SweepRun) -> Path:
    """The executed notebook of one run (``notebooks=True``)."""
    return out / "reports" / f"{run.run_id}.ipynb"


def report_error_path(out: Path, run: SweepRun) -> Path:
    """Where the error of a failed notebook execution is kept."""
    return out / "reports" / f"{run.run_id}.error.json"


def is_done(run: SweepRun, directory: Path) -> bool:
    """Whether the run in ``directory`` finished its requested months.

    A damaged ``done.json`` counts as not finished (the run is then executed again).
    """
    try:
        done = read_json(directory / "done.json")
    except DamagedFileError:
        return False
    months = done.get("months", 0) if done is not None else 0
    return (
        isinstance(months, (int, float)) and months >= run.learning.months
        and (directory / "history.json").exists()
    )


# -- checks before anything is written -----------------------------------------------------
def check_out_dir(out: Path) -> None:
    """Fail in one line if ``out`` cannot be (or become) a directory this process writes to
    (:func:`mpcrl_lite.learning.outdir.check_output_dir`, creating nothing), or if its
    ``runs`` or ``reports`` is a file.

    Raises
    ------
    GridError
        With the check's message.
    """
    try:
        outdir.check_output_dir(out, create=False)
    except outdir.RunDirError as err:
        raise GridError(str(err)) from None
    for sub in ("runs", "reports"):
        if (out / sub).exists() and not (out / sub).is_dir():
            raise GridError(f"--out {out}: {out / sub} is a file; expected a directory")


def check_run_dirs(sweep: Sweep, out: Path) -> None:
    """Refuse run directories written with other settings (``learning.months`` may grow).

    Raises
    ------
    GridError
        Naming the run directory, the setting, the stored and the new value.
    DamagedFileError
        A run's ``config.json`` cannot be read, so its settings cannot be compared.
    """
    for run in sweep.runs:
        config = run_dir(out, run) / "config.json"
        try:
            saved = read_json(config)
        except DamagedFileError as err:
            raise DamagedFileError(
                f"{err}; delete that run directory (or the file) to run it again"
            ) from None
        if saved is None:
            continue
        mine = run.configs()
        for section in SECTIONS:
            old, new = saved.get(section, {}), dict(mine.get(section, {}))
            old = dict(old) if isinstance(old, dict) else {}
            # a field added since the run was written reads as what that run did
            old = {**LEGACY_VALUES.get(section, {}), **old}
            if section == "learning":
                old.pop("months", None)
                new.pop("months", None)
            diff = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
            if diff:
                k = diff[0]
                raise GridError(
                    f"{run_dir(out, run)} holds a run with {section}.{k}={old.get(k)!r}, "
                    f"but this sweep sets {new.get(k)!r}; use another output directory or "
                    "delete that run directory"
                )
