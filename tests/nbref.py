"""Reference outputs of the notebooks: execute, sanitize, store, compare (nbval-style).

Used by ``tests/notebooks/test_notebooks.py`` and ``tools/update_notebook_refs.py``.

A reference (``tests/notebook_refs/<stem>.json``) holds, for every code cell of the notebook as
committed, its id, a hash of its source, whether its output is ignored, and its sanitized
outputs after execution with the CI profile (``notebooks/ci_parameters.yaml``):

* ``stdout`` streams, joined per cell;
* ``text/plain`` of results and displays, and the JSON of :func:`mpcrl_lite.publish.report.show_summary`
  (keys sorted);
* *excluded*: ``stderr`` (warnings, progress bars), figures (``image/*``), widgets, HTML, and
  every output of cells tagged ``nbval-ignore-output`` (timings, interactive sections).

Text goes through the regular expressions of ``tests/sanitize.cfg`` (nbval's format), and
floats with more than :data:`STORED_DIGITS` significant digits are rounded when stored.
Comparison splits texts into numbers and the text between them: the text must be equal, the
numbers equal within ``rtol`` (relative) or ``atol`` (absolute), so round-off differences
between machines or solver back-ends pass while a changed result fails.
"""

from __future__ import annotations

import configparser
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import nbformat

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOK_DIR = ROOT / "notebooks"
REF_DIR = Path(__file__).resolve().parent / "notebook_refs"
SANITIZE_CFG = Path(__file__).resolve().parent / "sanitize.cfg"

#: Tags of cells whose outputs are not compared.
IGNORE_TAGS = ("nbval-ignore-output",)
#: MIME types never compared (figures, widgets, rich displays).
EXCLUDED_MIME = ("image/", "application/vnd.jupyter.widget", "text/html", "text/markdown",
                 "text/latex")
SUMMARY_MIME = "application/json"
#: Significant digits of floats in stored references.
STORED_DIGITS = 6
#: Default tolerances of the comparison.
RTOL = 1e-4
ATOL = 1e-12
#: Text that must never appear in any output (IPOPT's banner and statistics).
IPOPT_MARKERS = ("Ipopt", "EXIT:", "******")

NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


# -- sanitizing ----------------------------------------------------------------------------
def sanitizers(path: Path = SANITIZE_CFG) -> list[tuple[re.Pattern[str], str]]:
    """The (regex, replacement) rules of an nbval sanitize file."""
    parser = configparser.ConfigParser(interpolation=None)
    parser.read(path)
    return [(re.compile(parser[s]["regex"], re.MULTILINE), parser[s]["replace"])
            for s in parser.sections()]


def round_floats(text: str, digits: int = STORED_DIGITS) -> str:
    """Round numbers written with a decimal point or exponent to ``digits`` significant digits
    (integers are kept as they are)."""

    def repl(match: re.Match[str]) -> str:
        token = match.group(0)
        if not any(c in token for c in ".eE"):
            return token
        mantissa = re.sub(r"[eE].*", "", token).lstrip("+-").replace(".", "").lstrip("0")
        if len(mantissa) <= digits:
            return token
        value = float(token)
        return f"{value:.{digits}g}" if token[0] != "+" else f"{value:+.{digits}g}"

    return NUMBER.sub(repl, text)


def sanitize(text: str, rules: list[tuple[re.Pattern[str], str]] | None = None) -> str:
    rules = sanitizers() if rules is None else rules
    for regex, replacement in rules:
        text = regex.sub(replacement, text)
    return text.rstrip()


def cell_outputs(cell: Any, rules: list[tuple[re.Pattern[str], str]] | None = None) -> list[str]:
    """The compared outputs of one executed code cell, sanitized (see the module docstring)."""
    texts: list[str] = []
    stdout = ""
    for out in cell.get("outputs", []):
        kind = out.get("output_type")
        if kind == "stream":
            if out.get("name") == "stdout":
                stdout += out.get("text", "")
            continue
        if stdout:
            texts.append(stdout)
            stdout = ""
        if kind == "error":
            texts.append(f"ERROR {out.get('ename')}: {out.get('evalue')}")
        elif kind in ("display_data", "execute_result"):
            data = out.get("data", {})
            if SUMMARY_MIME in data:
                texts.append(json.dumps(data[SUMMARY_MIME], indent=1, sort_keys=True))
            elif any(m.startswith(EXCLUDED_MIME) for m in data):
                continue
            elif "text/plain" in data:
                texts.append(data["text/plain"])
    if stdout:
        texts.append(stdout)
    return [sanitize(t, rules) for t in texts]


def source_hash(source: str) -> str:
    return hashlib.sha1(source.strip().encode()).hexdigest()[:16]


def is_injected(cell: Any) -> bool:
    return "injected-parameters" in cell.get("metadata", {}).get("tags", [])


def make_reference(stem: str, executed: Any, parameters: dict[str, Any]) -> dict[str, Any]:
    """The reference of an executed notebook (code cells only, injected cell dropped)."""
    rules = sanitizers()
    cells = []
    for cell in executed.cells:
        if cell.cell_type != "code" or is_injected(cell):
            continue
        ignored = any(t in cell.metadata.get("tags", []) for t in IGNORE_TAGS)
        cells.append({
            "id": cell.get("id"),
            "source_sha1": source_hash(cell.source),
            "ignore_output": ignored,
            "outputs": [] if ignored else [round_floats(t) for t in cell_outputs(cell, rules)],
        })
    return {
        "notebook": stem,
        "profile": "ci",
        "parameters": parameters,
        "tolerance": {"rtol": RTOL, "atol": ATOL},
        "cells": cells,
    }


# -- comparing -----------------------------------------------------------------------------
def _split(text: str) -> tuple[list[str], list[str]]:
    """Text between the numbers (whitespace removed: column alignment of printed arrays moves
    when a digit or a sign changes) and the numbers themselves."""
    words = [re.sub(r"\s+", "", w) for w in NUMBER.split(text)]
    numbers = NUMBER.findall(text)
    return words, numbers


def compare_text(expected: str, actual: str, rtol: float = RTOL, atol: float = ATOL) -> str | None:
    """``None`` if the texts agree (numbers within tolerance), else a short description."""
    w_exp, n_exp = _split(expected)
    w_act, n_act = _split(actual)
    if w_exp != w_act or len(n_exp) != len(n_act):
        exp_lines, act_lines = expected.splitlines(), actual.splitlines()
        for i, (e, a) in enumerate(zip(exp_lines, act_lines)):
            if _split(e)[0] != _split(a)[0]:
                return f"text differs at line {i + 1}:\n  expected: {e}\n  actual:   {a}"
        return (f"text differs: expected {len(exp_lines)} line(s), got {len(act_lines)}:\n"
                f"  expected: {expected[:300]!r}\n  actual:   {actual[:300]!r}")
    for e, a in zip(n_exp, n_act):
        x, y = float(e), float(a)
        if math.isnan(x) and math.isnan(y):
            continue
        if not abs(x - y) <= atol + rtol * max(abs(x), abs(y)):
            line = next((ln for ln in actual.splitlines() if a in ln), actual[:200])
            return f"number {a} differs from the reference {e} (rtol {rtol:g}) in: {line.strip()}"
    return None


@dataclass
class Mismatch:
    cell: str
    message: str

    def __str__(self) -> str:
        return f"cell {self.cell}: {self.message}"


def compare(reference: dict[str, Any], executed: Any) -> list[Mismatch]:
    """All differences between an executed notebook and its reference."""
    rules = sanitizers()
    tol = reference.get("tolerance", {})
    rtol, atol = tol.get("rtol", RTOL), tol.get("atol", ATOL)
    by_id = {c["id"]: c for c in reference["cells"]}
    problems: list[Mismatch] = []
    for cell in executed.cells:
        if cell.cell_type != "code" or is_injected(cell):
            continue
        ref = by_id.get(cell.get("id"))
        if ref is None:
            problems.append(Mismatch(str(cell.get("id")), "not in the reference"))
            continue
        if ref["ignore_output"]:
            continue
        actual = cell_outputs(cell, rules)
        expected = ref["outputs"]
        if len(actual) != len(expected):
            problems.append(Mismatch(ref["id"], f"{len(actual)} output(s), reference has "
                                                f"{len(expected)}: {actual!r:.400}"))
            continue
        for e, a in zip(expected, actual):
            message = compare_text(e, a, rtol, atol)
            if message:
                problems.append(Mismatch(ref["id"], message))
    return problems


# -- execution -----------------------------------------------------------------------------
def ci_parameters() -> dict[str, dict[str, Any]]:
    from mpcrl_lite.publish.report import profile_parameters

    return profile_parameters("ci")


def notebook_path(stem: str) -> Path:
    return NOTEBOOK_DIR / f"{stem}.ipynb"


def stems() -> list[str]:
    return [p.stem for p in sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))]


def execute_ci(stem: str, workdir: Path, timeout: int = 600) -> Any:
    """Execute one notebook with its CI parameters in ``workdir`` (also the working directory),
    with ``MPLBACKEND=Agg``; returns the executed notebook."""
    from mpcrl_lite.publish.report import execute_notebook

    workdir.mkdir(parents=True, exist_ok=True)
    old = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = "Agg"
    try:
        return execute_notebook(notebook_path(stem), workdir / f"{stem}.ipynb",
                                ci_parameters().get(stem, {}), cwd=workdir, timeout=timeout)
    finally:
        if old is None:
            os.environ.pop("MPLBACKEND", None)
        else:
            os.environ["MPLBACKEND"] = old


def reference_path(stem: str) -> Path:
    return REF_DIR / f"{stem}.json"


def load_reference(stem: str) -> dict[str, Any]:
    return json.loads(reference_path(stem).read_text())


def write_reference(stem: str, executed: Any) -> Path:
    REF_DIR.mkdir(parents=True, exist_ok=True)
    ref = make_reference(stem, executed, ci_parameters().get(stem, {}))
    path = reference_path(stem)
    path.write_text(json.dumps(ref, indent=1, ensure_ascii=False) + "\n")
    return path


def read_notebook(stem: str) -> Any:
    return nbformat.read(notebook_path(stem), as_version=4)
