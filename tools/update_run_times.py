#!/usr/bin/env python
"""Write the notebooks' run times from a report into the documents that show them.

Reads each ``summary.json`` given (written by ``make report`` / ``python -m mpcrl_lite
report``), keeps its seconds per notebook for its profile in ``notebooks/run_times.json`` and
rewrites the marked run-time block of README.md, notebooks/README.md and
notebooks/TEACHING.md (:mod:`mpcrl_lite.publish.run_times`).

Usage::

    python tools/update_run_times.py [reports/summary.json ...] [--source TEXT] [--check]

Without a summary only the documents are rewritten from ``notebooks/run_times.json``.
``--check`` writes nothing and exits with status 1 if a document's block differs.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mpcrl_lite.publish import run_times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("summaries", nargs="*", type=Path, help="a report's summary.json")
    parser.add_argument("--source", default="",
                        help="where the run took place (default: the date of the summary file)")
    parser.add_argument("--check", action="store_true", help="compare, write nothing")
    args = parser.parse_args(argv)
    data = run_times.load()
    for path in args.summaries:
        if not path.is_file():
            parser.error(f"{path}: no such summary (run make report first)")
        day = datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.UTC).date()
        data = run_times.record(json.loads(path.read_text()),
                                args.source or f"report of {day.isoformat()}", data)
    status = 0
    if args.summaries and not args.check:
        run_times.RUN_TIMES.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    for name in run_times.DOCUMENTS:
        path = ROOT / name
        text = path.read_text(encoding="utf-8")
        new = run_times.rewrite(text, data, name)
        if new != text:
            if args.check:
                print(f"{name}: its run-time block differs from notebooks/run_times.json")
                status = 1
            else:
                path.write_text(new, encoding="utf-8")
                print(f"{name}: run-time block rewritten")
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
