"""Notebooks as parameterised reports: papermill execution, parameter checks, summaries.

Conventions the notebooks follow (see ``notebooks/``):

* one cell tagged ``parameters`` holds literals in UPPER_CASE names;
* the cell after it calls :func:`check_parameters`, so a name injected by papermill that is
  not exactly one of the notebook's parameters (``-p months 5``, ``-p P_Bar 1.0``) is an
  error naming the closest one, not a silent no-op (papermill itself only warns);
* one cell tagged ``summary`` calls :func:`show_summary` with the notebook's key numbers; the
  report runner collects them into ``summary.json``.

:func:`run_report` executes every notebook (``NN_*.ipynb``) into a directory as executed
``.ipynb`` and HTML, with the notebooks' defaults (``profile='full'``), the small parameter set
of ``notebooks/ci_parameters.yaml`` (``profile='ci'``) or the lesson-sized one of
``notebooks/classroom_parameters.yaml`` (``profile='classroom'``). The HTML pages work offline
(:mod:`mpcrl_lite.publish.html_export`): local MathJax, static pictures of the explorers, alt texts.

Kernels are started on this machine over IPC sockets in a private folder rather than TCP
ports (no network exposure, and no transport warning in the output), with the
:mod:`mpcrl_lite.publish.alt_text` extension loaded so that figures carry their descriptions.
"""

from __future__ import annotations

import ast
import difflib
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from .._util.jsonio import plain
from .._util.resources import package_folder
from .._util.validate import InputTypeError, check_choice
from ..learning import durable, outdir
from .claims import check_claims
from .html_export import copy_mathjax, write_html

__all__ = [
    "CI_PARAMETERS",
    "CLASSROOM_PARAMETERS",
    "KERNEL_EXTENSIONS",
    "NOTEBOOK_DIR",
    "PROFILES",
    "ClaimError",
    "check_parameters",
    "execute_notebook",
    "notebook_parameters",
    "notebook_paths",
    "profile_parameters",
    "read_summary",
    "run_report",
    "show_summary",
]

#: The project's notebooks (resolved through the package, not the working directory): the
#: repository's ``notebooks/`` in a checkout, ``mpcrl_lite/notebooks`` in an installed wheel.
NOTEBOOK_DIR = package_folder("notebooks")
#: The small CI profile: ``{notebook stem: {PARAMETER: value}}``.
CI_PARAMETERS = NOTEBOOK_DIR / "ci_parameters.yaml"
#: The lesson-sized profile (every notebook within about a minute), same format.
CLASSROOM_PARAMETERS = NOTEBOOK_DIR / "classroom_parameters.yaml"
#: Parameter profiles: the notebooks' defaults, and the files above.
PROFILES = ("full", "ci", "classroom")
#: IPython extensions loaded into every kernel started by :func:`execute_notebook`.
KERNEL_EXTENSIONS = ("mpcrl_lite.publish.alt_text",)
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
    """The parameters cell of a notebook: ``{name: {'default': ..., 'type': ..., 'help': ...}}``.

    The same answer as ``papermill.inspect_notebook``: ``default`` the value's source text,
    ``type`` the annotation (``'None'`` without one), ``help`` the line's comment. A cell of
    plain one-line assignments (every notebook here) is read with :mod:`ast` and
    :mod:`tokenize`, because :func:`check_parameters` runs in every notebook's kernel, where
    importing papermill (with nbformat and jsonschema) would cost about 2 s; any other cell is
    left to papermill.
    """
    path = Path(path)
    if not path.is_absolute() and not path.exists():
        path = NOTEBOOK_DIR / path
    with open(path, encoding="utf-8") as f:
        cells = json.load(f).get("cells", [])
    tagged = [c for c in cells if "parameters" in c.get("metadata", {}).get("tags", [])]
    if not tagged:
        return {}
    source = tagged[0].get("source", "")
    fast = _plain_parameters("".join(source) if isinstance(source, list) else source)
    if fast is not None:
        return fast
    import papermill

    info = papermill.inspect_notebook(str(path))
    return {
        name: {
            "default": spec.get("default"),
            "type": spec.get("inferred_type_name"),
            "help": spec.get("help", ""),
        }
        for name, spec in info.items()
    }


def _plain_parameters(source: str) -> dict[str, dict[str, Any]] | None:
    """:func:`notebook_parameters` of a cell whose statements are all one-line assignments to
    a name (``NAME: type = value  # help`` or ``NAME = value  # help``); ``None`` for any
    other cell (a syntax error, a statement over several lines, a ``# type:`` comment)."""
    import io
    import tokenize

    try:
        tree = ast.parse(source)
        tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    except (SyntaxError, tokenize.TokenError):
        return None
    comments = {t.start[0]: t.string for t in tokens if t.type == tokenize.COMMENT}
    lines = source.splitlines()
    out: dict[str, dict[str, Any]] = {}
    for node in tree.body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) \
                and node.value is not None:
            name, kind = node.target.id, ast.unparse(node.annotation)
        elif isinstance(node, ast.Assign) and len(node.targets) == 1 \
                and isinstance(node.targets[0], ast.Name):
            name, kind = node.targets[0].id, "None"
        else:
            return None
        if node.end_lineno != node.lineno or lines[node.lineno - 1].count("=") != 1:
            return None
        comment = comments.get(node.lineno, "#")[1:].strip()
        if comment.startswith("type:"):
            return None
        out[name] = {"default": ast.get_source_segment(source, node.value), "type": kind,
                     "help": comment}
    return out


_TYPES = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}

#: First line of the cell papermill injects with the parameters it is given.
_INJECTED_HEADER = "# Parameters"


def _closest(name: str, allowed: dict[str, Any]) -> str:
    """The parameter whose name is most like ``name`` (ignoring case)."""
    by_upper = {a.upper(): a for a in allowed}
    match = difflib.get_close_matches(name.upper(), list(by_upper), n=1, cutoff=0.0)
    return by_upper[match[0]]


def _check_values(notebook: str, values: dict[str, Any], allowed: dict[str, dict[str, Any]]) -> None:
    unknown = sorted(set(values) - set(allowed))
    if unknown:
        hints = ", ".join(f"{_closest(n, allowed)!r} for {n!r}" for n in unknown) if allowed else ""
        raise ValueError(
            f"{notebook}: unknown parameter(s) {unknown}"
            + (f"; did you mean {hints}?" if hints else "")
            + f" Names must match exactly; this notebook takes {sorted(allowed)}"
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


def _injected_names(namespace: dict[str, Any]) -> set[str]:
    """Names assigned in the cells papermill injected, read from the kernel's input history.

    papermill runs its parameters as a cell starting with ``# Parameters``; IPython keeps the
    source of every executed cell in ``In``. Without that history (a plain dict) there is
    nothing to read.
    """
    history = namespace.get("In")
    if not isinstance(history, list):
        return set()
    names: set[str] = set()
    for source in history:
        if not isinstance(source, str) or not source.lstrip().startswith(_INJECTED_HEADER):
            continue
        try:
            tree = ast.parse(source)
        except SyntaxError:
            continue
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else (
                [node.target] if isinstance(node, ast.AnnAssign) else [])
            names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def check_parameters(namespace: dict[str, Any], notebook: str) -> dict[str, Any]:
    """Reject names given to ``notebook`` that are not exactly its parameters.

    Called in the cell right after the parameters cell with ``globals()``; returns the
    parameter values (for the summary). Checked are every name papermill injected (read from
    the kernel's input history, so ``-p months 5`` or ``-p P_Bar 1.0`` is caught although the
    parameters are ``MONTHS`` and ``P_BAR``) and every UPPER_CASE global. An unknown name is
    an error naming the closest parameter; a wrong type (e.g. a string for a float) is an
    error too.
    """
    allowed = notebook_parameters(notebook)
    candidates = {
        k for k, v in namespace.items()
        if k.isupper() and not k.startswith("_") and not callable(v)
        and not isinstance(v, type(json))
    }
    candidates |= {k for k in _injected_names(namespace) if k in namespace}
    values = {k: namespace[k] for k in candidates}
    _check_values(notebook, values, allowed)
    return {k: values[k] for k in allowed if k in values}


#: Significant digits of the floats a summary shows: enough for every result, and a change in
#: the last digit from round-off stays far below the notebook tests' tolerance (1e-4).
SUMMARY_DIGITS = 6


def show_summary(values: dict[str, Any]) -> None:
    """Display the notebook's key numbers as JSON (read back by :func:`read_summary`), floats
    rounded to :data:`SUMMARY_DIGITS` significant digits."""
    from IPython.display import display

    data = _round_floats(plain(values, keep_nonfinite=True))
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
    """Parameters per notebook stem for ``'full'`` (none: the defaults), ``'ci'`` or
    ``'classroom'``."""
    if check_choice("profile", profile, PROFILES) == "full":
        return {}
    import yaml

    path = CI_PARAMETERS if profile == "ci" else CLASSROOM_PARAMETERS
    data = yaml.safe_load(path.read_text()) or {}
    if not isinstance(data, dict):
        raise InputTypeError(
            f"{path}: expected a mapping of notebook -> parameters, got {type(data).__name__}"
        )
    return data


#: How long a finished notebook's kernel may take to exit before it is terminated (half of it)
#: and killed (jupyter_client's ``KernelManager.shutdown_wait_time``, default 5 s). At exit,
#: ipykernel signals every child process of its process group and waits for it to end; the
#: resource tracker that multiprocessing starts beside a spawned worker (the evaluation worker
#: of :class:`~mpcrl_lite.learning.experiment.Experiment`) ignores those signals, so a
#: notebook that evaluated in a worker kept its kernel for half of that time, 2.5 s, after
#: its last cell. Every output is in hand when the kernel is asked to shut down.
KERNEL_SHUTDOWN_WAIT_S = 1.0


def _kernel_options(socket_dir: str) -> dict[str, Any]:
    """papermill/nbclient options for a local kernel: IPC sockets inside ``socket_dir`` (where
    the platform has them), the :data:`KERNEL_EXTENSIONS`, and the kernel's own log silenced
    below CRITICAL: when a notebook is done the kernel manager interrupts the kernel (SIGINT)
    before shutting it down, and a kernel caught in a message handler then logs
    ``[IPKernelApp] ERROR | KeyboardInterrupt caught in kernel`` on our stderr; a failing cell
    is reported by papermill, not by that log."""
    from traitlets.config import Config

    options: dict[str, Any] = {
        "extra_arguments": [*(f"--IPKernelApp.extensions={name}" for name in KERNEL_EXTENSIONS),
                            "--IPKernelApp.log_level=CRITICAL"],
    }
    manager: dict[str, Any] = {"shutdown_wait_time": KERNEL_SHUTDOWN_WAIT_S}
    if os.name == "posix":
        manager.update(transport="ipc", ip=os.path.join(socket_dir, "kernel"))
    options["config"] = Config({"KernelManager": manager})
    return options


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
    # A short private path: Unix socket names are limited to ~100 characters.
    with tempfile.TemporaryDirectory(prefix="mpcrl-kernel-") as socket_dir:
        return papermill.execute_notebook(
            str(path), str(output), parameters=parameters, kernel_name="python3",
            cwd=str(cwd) if cwd else None, progress_bar=False, execution_timeout=timeout,
            **_kernel_options(socket_dir),
        )


def run_report(
    out: str | Path, profile: str = "full", notebooks: list[str] | None = None
) -> dict[str, Any]:
    """Execute the notebooks into ``out`` (``.ipynb`` + offline ``.html``, MathJax in
    ``out/mathjax``) and write ``out/summary.json`` with each notebook's key numbers,
    parameters and run time, and the check of the prose's claims for ``profile``
    (:mod:`mpcrl_lite.publish.claims`): a claim that does not hold raises :class:`ClaimError`
    once everything is written."""
    out = Path(outdir.refuse_empty(out))
    params = profile_parameters(profile)
    paths = notebook_paths(notebooks)
    # check every notebook's parameters before executing any of them (or creating ``out``)
    for path in paths:
        _check_values(path.name, params.get(path.stem, {}), notebook_parameters(path))
    out = outdir.check_output_dir(out)
    with outdir.lock_output_dir(out, "report"):  # one process at a time in out
        copy_mathjax(out)  # before any work: fails at once if the MathJax files are missing
        summary: dict[str, Any] = {"profile": profile, "notebooks": {}}
        for path in paths:
            t0 = time.perf_counter()
            # papermill saves the notebook after every cell: written aside, renamed when done
            with durable.atomic_output(out / path.name,
                                      failed=out / f"{path.stem}.failed.ipynb") as partial:
                nb = execute_notebook(path, partial, params.get(path.stem, {}), cwd=out)
            seconds = time.perf_counter() - t0
            with durable.atomic_output(out / f"{path.stem}.html") as partial:
                write_html(nb, partial)
            summary["notebooks"][path.stem] = {
                "seconds": round(seconds, 1),
                "parameters": params.get(path.stem, {}),
                "results": read_summary(nb),
            }
            durable.write_json(out / "summary.json", summary)
        # what the prose claims about these runs (notebooks/claims.yaml), checked last
        summary["claims"] = check_claims(
            {stem: entry["results"] for stem, entry in summary["notebooks"].items()}, profile)
        durable.write_json(out / "summary.json", summary)
        if summary["claims"]["failed"]:
            raise ClaimError(f"{len(summary['claims']['failed'])} claim(s) of the notebooks' prose "
                             "do not hold for this run (notebooks/claims.yaml): "
                             + "; ".join(summary["claims"]["failed"]))
        return summary


class ClaimError(ValueError):
    """A sentence of a notebook states a number that its run does not give."""
