#!/usr/bin/env python
"""Regenerate the reference outputs of the notebooks (``tests/notebook_refs/*.json``).

Each notebook is executed with papermill and the CI profile (``notebooks/ci_parameters.yaml``)
in a temporary directory, exactly as ``tests/test_notebooks.py`` does, and its sanitized outputs
are written as the new reference. Run it after an intended change of a notebook or of results,
and review the diff of the JSON files before committing.

Usage::

    python tools/update_notebook_refs.py [NOTEBOOK ...] [--check]

NOTEBOOK is a stem such as ``03_lstd_value_functions`` (default: all). ``--check`` compares
instead of writing and exits with status 1 on a difference.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import nbref


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("notebooks", nargs="*", help="notebook stems (default: all)")
    parser.add_argument("--check", action="store_true", help="compare, do not write")
    args = parser.parse_args(argv)
    stems = args.notebooks or nbref.stems()
    unknown = sorted(set(stems) - set(nbref.stems()))
    if unknown:
        parser.error(f"unknown notebook(s) {unknown}; expected some of {nbref.stems()}")
    status = 0
    with tempfile.TemporaryDirectory() as tmp:
        for stem in stems:
            t0 = time.perf_counter()
            executed = nbref.execute_ci(stem, Path(tmp) / stem)
            seconds = time.perf_counter() - t0
            if args.check:
                problems = nbref.compare(nbref.load_reference(stem), executed)
                print(f"{stem}: {len(problems)} difference(s) ({seconds:.0f} s)")
                for problem in problems[:20]:
                    print(f"  {problem}")
                status = status or int(bool(problems))
            else:
                path = nbref.write_reference(stem, executed)
                print(f"{stem}: wrote {path.relative_to(ROOT)} ({seconds:.0f} s)")
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
