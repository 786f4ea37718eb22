"""Where a learner settles when it starts at its class's best theta.

A learner that ends above its class's best (the learner gap) can do so for two reasons: its
gradient estimate has a fixed point elsewhere (a bias), or it has not got there in the months
it had (the pace of its steps against the distance). Starting it *at* the class's best tells
them apart: a biased learner walks away to its own fixed point, a slow one stays near where
it started, with the noise of its steps around it.

This script runs the default experiment (the shipped month, the paper's class unless
``--policy-class`` says otherwise) from the theta of a stored ``tune.json`` instead of the
nominal theta0, for some seeds and one gradient source, and prints one JSON line per seed with
its evaluations (the default ten draws every five months and the last month), then a summary
line: the median of each seed's evaluations over the last ``--late`` months, those medians'
median, and the median of the final evaluations, beside the class's best on the same draws
(the first evaluation, which is the start).

``python benchmarks/from_class_best.py --gradient critic --seeds 13010-13015
[--tune data/class_best_paper/tune.json] [--months 100] [--late 45] [--out FILE]``

``--config RUN_CONFIG.json`` takes the system, MPC, learning settings and price file of a stored
study's run instead (e.g. ``benchmarks/studies/sep2020_day_end_pathwise_12000/config_seed12000.json``;
its seed is replaced by each of ``--seeds``, its gradient by ``--gradient``): with a class's
best from another month, that asks whether a start in the right basin carries over.

A measurement: ``learn --theta0`` and ``study --theta0`` start runs at a stored theta too
(``LearningConfig.theta0``); this script keeps each seed's evaluations and their late medians
in one file.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

from mpcrl_lite.config import POLICY_CLASSES, LearningConfig, policy_class_configs
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.studies.sweep.grid import SweepRun
from mpcrl_lite.theta import Theta


def seed_range(text: str) -> list[int]:
    """``'13010-13015'`` (both ends included) or ``'1,2,5'``."""
    if "-" in text:
        first, last = (int(x) for x in text.split("-"))
        if last < first:
            raise argparse.ArgumentTypeError(f"seeds {text!r}: the last is below the first")
        return list(range(first, last + 1))
    return [int(x) for x in text.split(",")]


def run_seed(seed: int, gradient: str, theta: Theta, months: int, policy_class: str,
             config: Path | None = None) -> dict:
    if config is None:
        system, mpc = policy_class_configs(policy_class)
        learning, prices = LearningConfig(seed=seed, gradient=gradient), None
    else:  # a stored run's settings (its prices read from its file)
        run = SweepRun.from_config(json.loads(config.read_text()))
        system, mpc, prices = run.system, run.mpc, run.file_month()
        learning = run.learning.replace(seed=seed, gradient=gradient)
    exp = Experiment(system=system, mpc_config=mpc, learning=learning, prices=prices,
                     theta0=theta)
    exp.eval_worker = False  # one process per seed, the evaluations in it
    t0, c0 = time.perf_counter(), time.process_time()
    history = exp.run(months=months, progress=False)
    return {"seed": seed, "gradient": gradient, "eval_month": list(history.eval_month),
            "J_eval": [float(x) for x in history.J_eval],
            "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0}


def summary(rows: list[dict], late: int, months: int) -> dict:
    start = rows[0]["J_eval"][0]
    medians = []
    for row in rows:
        tail = [j for m, j in zip(row["eval_month"], row["J_eval"], strict=True)
                if m >= months - late]
        medians.append(statistics.median(tail))
    finals = [row["J_eval"][-1] for row in rows]
    return {"summary": True, "gradient": rows[0]["gradient"], "seeds": [r["seed"] for r in rows],
            "J_start": start, "late_months": late, "late_median_per_seed": medians,
            "late_median": statistics.median(medians),
            "late_worst": max(max(j for m, j in zip(r["eval_month"], r["J_eval"], strict=True)
                                  if m >= months - late) for r in rows),
            "final_median": statistics.median(finals), "final_worst": max(finals)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gradient", choices=("critic", "pathwise"), required=True)
    parser.add_argument("--seeds", type=seed_range, required=True)
    parser.add_argument("--tune", type=Path, default=Path("data/class_best_paper/tune.json"))
    parser.add_argument("--policy-class", choices=tuple(POLICY_CLASSES), default="paper")
    parser.add_argument("--months", type=int, default=100)
    parser.add_argument("--late", type=int, default=45)
    parser.add_argument("--config", type=Path, help="a stored run's config.json to run with")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    theta = Theta.from_dict(json.loads(args.tune.read_text())["theta_best"])
    rows = []
    out = args.out.open("w") if args.out else None
    for seed in args.seeds:
        row = run_seed(seed, args.gradient, theta, args.months, args.policy_class, args.config)
        rows.append(row)
        for stream in (sys.stdout, out):
            if stream is not None:
                print(json.dumps(row), file=stream, flush=True)
    line = json.dumps({**summary(rows, args.late, args.months), "tune": str(args.tune),
                       **({"config": str(args.config)} if args.config else {})})
    for stream in (sys.stdout, out):
        if stream is not None:
            print(line, file=stream, flush=True)
    if out is not None:
        out.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
