#!/usr/bin/env python
"""Write the student version of the notebooks: every cell tagged ``solution`` is replaced by an
empty exercise cell, all outputs are cleared, and the launch line opens the student copy
(Binder at ``student/``; :func:`mpcrl_lite.publish.launch.student_launch_line`), not the
teacher's notebook with its solutions.

Usage::

    python tools/make_student_version.py [--out student] [NOTEBOOK ...]

NOTEBOOK is a stem such as ``02_mpc_policy`` (default: all of ``notebooks/NN_*.ipynb``). The
placeholder cells are tagged ``exercise`` and keep the solution cell's position, so the
numbering of the cells and the exercise texts stay as in the teacher's version. The parameters
cell, the checks and the summary are unchanged: no cell outside the solutions depends on what a
solution defines (``tests/notebooks/test_notebooks.py`` checks this).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mpcrl_lite.publish.launch import LAUNCH_MARKER, student_launch_line

NOTEBOOK_DIR = ROOT / "notebooks"
PLACEHOLDER = "# Your solution here.\n"


def student_version(nb: nbformat.NotebookNode, stem: str | None = None
                    ) -> nbformat.NotebookNode:
    """A copy of ``nb`` without solutions and outputs; with ``stem``, its launch line (first
    cell) is the student one."""
    out = nbformat.from_dict(nb)
    if stem is not None and out.cells and out.cells[0].cell_type == "markdown":
        paragraphs = out.cells[0].source.split("\n\n")
        out.cells[0].source = "\n\n".join(
            student_launch_line(stem) if p.startswith(LAUNCH_MARKER) else p for p in paragraphs)
    cells = []
    for cell in out.cells:
        tags = list(cell.get("metadata", {}).get("tags", []))
        if cell.cell_type == "code" and "solution" in tags:
            blank = nbformat.v4.new_code_cell(PLACEHOLDER)
            blank.id = f"{cell.id}-student"
            blank.metadata["tags"] = ["exercise"]
            cells.append(blank)
            continue
        if cell.cell_type == "code":
            cell.outputs = []
            cell.execution_count = None
        cells.append(cell)
    out.cells = cells
    return out


def main(argv: list[str] | None = None) -> list[Path]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", help="notebook stems (default: all)")
    parser.add_argument("--out", type=Path, default=ROOT / "student",
                        help="output directory (default: student/)")
    args = parser.parse_args(argv)
    paths = sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb"))
    if args.notebooks:
        known = {p.stem: p for p in paths}
        unknown = [n for n in args.notebooks if n not in known]
        if unknown:
            parser.error(f"unknown notebook(s) {unknown}; expected some of {sorted(known)}")
        paths = [known[n] for n in args.notebooks]
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for path in paths:
        nb = student_version(nbformat.read(path, as_version=4), path.stem)
        nbformat.validate(nb)
        target = args.out / path.name
        nbformat.write(nb, target)
        written.append(target)
        print(f"{target}")
    return written


if __name__ == "__main__":
    main(sys.argv[1:])
