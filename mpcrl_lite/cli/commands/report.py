"""``python -m mpcrl_lite report``: execute every notebook into a report directory (papermill)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ...learning import rundir
from ...publish.report import PROFILES
from .. import args as _a
from ..args import UsageError

NAME = "report"
HELP = "execute every notebook into a report directory"


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``report`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--out", type=_a.out_dir, default=Path("reports"), help="report directory")
    p.add_argument("--profile", choices=PROFILES, default="full",
                   help="parameters: the notebooks' defaults (full), the small CI profile or "
                        "the lesson-sized classroom profile")
    p.add_argument("--notebooks", nargs="*", default=None, help="only these notebooks")
    _a.add_force(p)

    return p


def run(args: argparse.Namespace) -> int:
    from ...publish.report import notebook_paths, run_report

    try:  # the notebooks are checked before --out is created
        paths = notebook_paths(args.notebooks)
    except ValueError as err:
        raise UsageError(str(err)) from None
    outputs = (rundir.SUMMARY, *(f"{p.stem}{ext}" for p in paths for ext in (".ipynb", ".html")))
    from .. import inputs as cli_inputs

    try:  # run_report checks the parameters, then creates --out and checks it is writable
        cli_inputs.refuse_finished(args.out, outputs, force=args.force)
        summary = run_report(args.out, profile=args.profile, notebooks=args.notebooks)
    except (ValueError, OSError) as err:
        raise UsageError(" ".join(str(err).split())) from None
    print(json.dumps({"report": str(args.out), "notebooks": list(summary["notebooks"])}))
    return 0


