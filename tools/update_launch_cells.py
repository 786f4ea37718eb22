#!/usr/bin/env python
"""Bring the first cells of the notebooks up to date with ``mpcrl_lite.publish.launch``: the Colab and
Binder launch line under the title, the paper's citation at the end of the title cell, and the
install cell (the first code cell, a no-op wherever the package is importable).

Usage::

    python tools/update_launch_cells.py            # rewrite the notebooks that differ
    python tools/update_launch_cells.py --check    # only report them (exit status 1)

Run it after changing ``REPOSITORY`` or ``BRANCH`` in ``mpcrl_lite/launch.py`` (a fork) or the
citation in ``mpcrl_lite/references.py``. The install cell produces no output where the package
is installed, but its source is part of the notebook references: run
``tools/update_notebook_refs.py`` afterwards when a cell changed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mpcrl_lite.publish.launch import apply_launch_cells

NOTEBOOK_DIR = ROOT / "notebooks"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="report, do not write")
    args = parser.parse_args(argv)
    stale = []
    for path in sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.ipynb")):
        nb = nbformat.read(path, as_version=4)
        updated = apply_launch_cells(nb, path.stem)
        if updated != nb:
            stale.append(path.name)
            if not args.check:
                nbformat.validate(updated)
                nbformat.write(updated, path)
    verb = "differ" if args.check else "updated"
    print(f"{len(stale)} notebook(s) {verb}: {', '.join(stale) or '-'}")
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
