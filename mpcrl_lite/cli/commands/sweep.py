"""``python -m mpcrl_lite sweep``: a grid of learning runs on Dask."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .. import args as _a
from ..args import UsageError

NAME = "sweep"
HELP = "a grid of learning runs on Dask"


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``sweep`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--grid", type=Path, required=True, help="YAML file with the grid")
    p.add_argument("--out", type=_a.out_dir, required=True, help="output directory")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=_a.nonneg_int, default=None, help="local workers (0: serial)")
    p.add_argument("--only", action="append", default=None, metavar="ID",
                   help="execute only this run id (repeatable); a rerun executes failed/unfinished runs")
    p.add_argument("--notebooks", action="store_true",
                   help="also execute notebook 05 per grid point into DIR/reports/")
    p.add_argument("--lockstep", type=_a.positive_int, default=None, metavar="K",
                   help="runs per task, stepped together in one process (default: each "
                        "worker's share; 1: one run per task)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    return p


def run(args: argparse.Namespace) -> int:
    from ...studies.sweep.api import run_sweep_cli

    try:
        table = run_sweep_cli(args.grid, args.out, scheduler=args.scheduler, workers=args.workers,
                              notebooks=args.notebooks, progress=not args.quiet, only=args.only,
                              lockstep=args.lockstep)
    except (ValueError, OSError) as err:  # GridError, RunDirLocked, a full disk
        raise UsageError(" ".join(str(err).split())) from None
    print(json.dumps({"runs": len(table), "failed": int((table["status"] == "failed").sum()),
                      "table": str(args.out / "results.csv")}))
    return 0


