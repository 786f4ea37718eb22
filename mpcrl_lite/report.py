"""Notebooks as parameterised reports: papermill execution, parameter checks, summaries.

Conventions the notebooks follow (see ``notebooks/``):

* one cell tagged ``parameters`` holds literals in UPPER_CASE names;
* the cell after it calls :func:`check_parameters`, so a name injected by papermill that the
  notebook does not know is an error, not a silent no-op (papermill itself only warns);
* one cell tagged ``summary`` calls :func:`show_summary` with the notebook's key numbers; the
  report runner collects them into ``summary.json``.

:func:`run_report` executes every notebook (``NN_*.ipynb``) into a directory as executed
``.ipynb`` and HTML, with the notebooks' defaults (``profile='full'``) or the small
parameter set of ``notebooks/ci_parameters.yaml`` (``profile='ci'``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

__all__ = [
    "NOTEBOOK_DIR",
    "CI_PARAMETERS",
    "notebook_paths",
    "notebook_parameters",
    "check_parameters",
    "show_summary",
    "read_summary",
    "execute_notebook",
    "run_report",
    "profile_parameters",
]

#: The project's notebooks (resolved through the package, not the working directory).
NOTEBOOK_DIR = Path(__file__).resolve().parent.parent / "notebooks"
#: The small CI profile: ``{notebook stem: {PARAMETER: value}}``.
CI_PARAMETERS = NOTEBOOK_DIR / "ci_parameters.yaml"
SUMMARY_MIME = "application/json"


def notebook_paths(names: list[str] | None = None) -> list[Path]:
    """The numbered notebooks ``NN_*.ipynb`` in order, or the ones named (stem or file)."""
    paths = sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))
    if names is None:
        return paths
    by_name = {p.stem: p for p in paths} | {p.name: p for p in paths}
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise ValueError(f"unknown notebook(s) {unknown}; expected some of {[p.stem for p in paths]}")
    return [by_name[n] for n in names]


def notebook_parameters(path: str | Path) -> dict[str, dict[str, Any]]:
    """The parameters cell of a notebook: ``{name: {'default': ..., 'type': ..., 'help': ...}}``."""
    import papermill

    path = Path(path)
    if not path.is_absolute() and not path.exists():
        path = NOTEBOOK_DIR / path
    info = papermill.inspect_notebook(str(path))
    return {
        name: {
            "default": spec.get("default"),
            "type": spec.get("inferred_type_name"),
            "help": spec.get("help", ""),
        }
        for name, spec in info.items()
    }


_TYPES = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}


def _check_values(notebook: str, values: dict[str, Any], allowed: dict[str, dict[str, Any]]) -> None:
    unknown = sorted(set(values) - set(allowed))
    if unknown:
        raise ValueError(
            f"{notebook}: unknown parameter(s) {unknown}; this notebook takes {sorted(allowed)}"
        )
    for name, value in values.items():
        types = _TYPES.get(str(allowed[name]["type"]))
        if types is None:
            continue
        ok = isinstance(value, types) and not (bool not in types and isinstance(value, bool))
        if not ok:
            raise ValueError(
                f"{notebook}: parameter {name}={value!r} has type {type(value).__name__}; "
                f"expected {allowed[name]['type']}"
            )


def check_parameters(namespace: dict[str, Any], notebook: str) -> dict[str, Any]:
    """Reject UPPER_CASE names in ``namespace`` that are not parameters of ``notebook``.

    Called in the cell right after the parameters cell with ``globals()``; returns the
    parameter values (for the summary). Wrong types (e.g. a string for a float) are errors.
    """
    allowed = notebook_parameters(notebook)
    values = {
        k: v for k, v in namespace.items()
        if k.isupper() and not k.startswith("_") and not callable(v) and not isinstance(v, type(json))
    }
    _check_values(notebook, values, allowed)
    return {k: values[k] for k in allowed if k in values}


#: Significant digits of the floats a summary shows: enough for every result, and a change in
#: the last digit from round-off stays far below the notebook tests' tolerance (1e-4).
SUMMARY_DIGITS = 6


def show_summary(values: dict[str, Any]) -> None:
    """Display the notebook's key numbers as JSON (read back by :func:`read_summary`), floats
    rounded to :data:`SUMMARY_DIGITS` significant digits."""
    from IPython.display import display

    data = _round_floats(json.loads(json.dumps(values, default=_jsonable)))
    display({SUMMARY_MIME: data, "text/plain": json.dumps(data, indent=1)}, raw=True)


def _round_floats(value: Any) -> Any:
    if isinstance(value, float):
        return float(f"{value:.{SUMMARY_DIGITS}g}")  # nan and inf stay as they are
    if isinstance(value, dict):
        return {k: _round_floats(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_round_floats(v) for v in value]
    return value


def read_summary(notebook: Any) -> dict[str, Any]:
    """The JSON shown by :func:`show_summary` in an executed notebook (nbformat node)."""
    for cell in notebook.cells:
        if cell.cell_type != "code" or "summary" not in cell.metadata.get("tags", []):
            continue
        for output in cell.get("outputs", []):
            data = output.get("data", {})
            if SUMMARY_MIME in data:
                return dict(data[SUMMARY_MIME])
    return {}


def profile_parameters(profile: str) -> dict[str, dict[str, Any]]:
    """Parameters per notebook stem for ``'full'`` (none: the defaults) or ``'ci'``."""
    if profile == "full":
        return {}
    if profile != "ci":
        raise ValueError(f"profile={profile!r}: expected 'full' or 'ci'")
    import yaml

    data = yaml.safe_load(CI_PARAMETERS.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{CI_PARAMETERS}: expected a mapping of notebook -> parameters")
    return data


def execute_notebook(
    path: str | Path, output: str | Path, parameters: dict[str, Any] | None = None,
    cwd: str | Path | None = None, timeout: int = 3600,
):
    """Run one notebook with papermill after checking ``parameters`` against its cell.

    Returns the executed notebook (nbformat node); raises ``ValueError`` for unknown or
    mistyped parameters before anything runs.
    """
    import papermill

    path = Path(path)
    parameters = dict(parameters or {})
    _check_values(path.name, parameters, notebook_parameters(path))
    return papermill.execute_notebook(
        str(path), str(output), parameters=parameters, kernel_name="python3",
        cwd=str(cwd) if cwd else None, progress_bar=False, execution_timeout=timeout,
    )


def run_report(
    out: str | Path, profile: str = "full", notebooks: list[str] | None = None
) -> dict[str, Any]:
    """Execute the notebooks into ``out`` (``.ipynb`` + ``.html``) and write
    ``out/summary.json`` with each notebook's key numbers, parameters and run time."""
    from nbconvert import HTMLExporter

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    params = profile_parameters(profile)
    paths = notebook_paths(notebooks)
    # check every notebook's parameters before executing any of them
    for path in paths:
        _check_values(path.name, params.get(path.stem, {}), notebook_parameters(path))
    exporter = HTMLExporter()
    summary: dict[str, Any] = {"profile": profile, "notebooks": {}}
    for path in paths:
        t0 = time.perf_counter()
        nb = execute_notebook(path, out / path.name, params.get(path.stem, {}), cwd=out)
        seconds = time.perf_counter() - t0
        html, _ = exporter.from_notebook_node(nb)
        (out / f"{path.stem}.html").write_text(html, encoding="utf-8")
        summary["notebooks"][path.stem] = {
            "seconds": round(seconds, 1),
            "parameters": params.get(path.stem, {}),
            "results": read_summary(nb),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def _jsonable(value: Any) -> Any:
    import numpy as np

    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot show {type(value).__name__} in a summary")
