#!/usr/bin/env python
"""J along the straight segment from each run's final theta to its class's best theta.

Is the class's best theta (a ``tune`` result) in the basin the learner ended in? For each
finished run of a study directory, :func:`mpcrl_lite.studies.study.segment_on_run_draws`
scores ``(1 - t) theta_final + t theta_best`` at evenly spaced ``t`` on the run's own
evaluation draws, and this prints one JSON line per run: ``run_seed``, ``t``, ``J``, ``rise`` (how
far J climbs above the worse end; 0: no barrier along the segment) and the draws.

Usage::

    python tools/theta_segment.py STUDY_DIR CLASS_BEST_DIR [--seeds 7000 7005] [--points 11]

``STUDY_DIR`` is the ``--out`` of ``python -m mpcrl_lite study`` (its ``runs/*/`` hold each
run's config and History); ``CLASS_BEST_DIR`` the ``--out`` of ``tune`` for the same class.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mpcrl_lite.bounds.baselines import load_class_best
from mpcrl_lite.learning.history import History
from mpcrl_lite.studies.study import segment_on_run_draws
from mpcrl_lite.studies.sweep.grid import SweepRun


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", type=Path)
    parser.add_argument("class_best", type=Path)
    parser.add_argument("--seeds", type=int, nargs="*", default=None,
                        help="the runs' seeds (default every finished run)")
    parser.add_argument("--points", type=int, default=11)
    args = parser.parse_args(argv)
    best = load_class_best(args.class_best)["theta_best"]
    runs = sorted(p.parent for p in (args.study / "runs").glob("*/done.json"))
    if not runs:
        parser.error(f"{args.study}: no finished run (runs/*/done.json)")
    for folder in runs:
        config = json.loads((folder / "config.json").read_text())
        run = SweepRun.from_config(config)
        if args.seeds is not None and run.learning.seed not in args.seeds:
            continue
        final = History.load(folder).final_theta()
        segment = segment_on_run_draws(run, final, best, points=args.points)
        print(json.dumps({"run_seed": run.learning.seed, **segment}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
