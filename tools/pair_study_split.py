#!/usr/bin/env python
"""Add the paired learner gap to a study summary that was written without it.

``study --class-best DIR`` now judges the class's best theta on the runs' own evaluation
draws too (``study.json`` ``"class_split"``: ``J_class_eval`` and ``learner_gap_paired*``,
:func:`mpcrl_lite.studies.study.class_on_run_draws`). A study run again in its directory gets
them from the resume; this tool gives them to a summary kept without its runs (the layout of
``benchmarks/studies/*``: ``study.json``, ``study.csv`` and one run's ``config_seed*.json``),
from those files and the same library functions. Nothing else of the summary changes.

Usage::

    python tools/pair_study_split.py STUDY_DIR CLASS_BEST_DIR [--check]

``--check`` writes nothing and exits with status 1 if the summary's paired figures differ
from what the files give.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mpcrl_lite._util import jsonio
from mpcrl_lite.bounds.baselines import load_class_best
from mpcrl_lite.studies.study import class_on_run_draws, class_split
from mpcrl_lite.studies.sweep.grid import SweepRun


def paired(study_dir: Path, class_best: Path) -> dict:
    """The summary's ``class_split`` with the paired figures, from the files."""
    summary = json.loads((study_dir / "study.json").read_text())
    configs = sorted(study_dir.glob("config_seed*.json"))
    if not configs:
        raise SystemExit(f"{study_dir}: no config_seed*.json (the configuration of a run)")
    tuned = load_class_best(class_best)
    table = pd.read_csv(study_dir / "study.csv")
    run = SweepRun.from_config(json.loads(configs[0].read_text()))
    split = class_split(table, tuned, summary.get("J_star"),
                        class_on_run_draws(run, tuned["theta_best"]))
    return {**summary["class_split"], **split}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("class_best", type=Path)
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args(argv)
    path = args.study / "study.json"
    summary = json.loads(path.read_text())
    split = json.loads(jsonio.dumps(paired(args.study, args.class_best)))
    if args.check:
        return 0 if summary["class_split"] == split else 1
    summary["class_split"] = split
    path.write_bytes(jsonio.dumps(summary))
    print(json.dumps({"study": str(args.study),
                      "learner_gap_median": split["learner_gap_median"],
                      "learner_gap_paired_median": split["learner_gap_paired_median"],
                      "J_class_eval": split["J_class_eval"]["mean"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
