r"""How reliably the learner learns on seeds nobody tuned it on, and how close it gets.

For every candidate (a set of :class:`~mpcrl_lite.config.LearningConfig` fields, optionally
the day-end forecast of :mod:`mpcrl_lite.system.forecast`) and every learning seed, a full run of
``--months`` months is made; the parameters in use every 10th month and the final ones are
evaluated on ``--draws`` noise draws of the month (seeds ``7000 .. 7000 + draws - 1``, common
to every candidate and seed, without exploration), and every 5th month on the fixed
evaluation draw ``LearningConfig.eval_seed`` (the ``History.J_eval`` of a default run).

Printed per candidate (J in NOK/day, lower is better): the median final J over the seeds,
its inter-quartile range, the worst and best seed, how many seeds close at least 90 % of the
gap between the nominal MPC (``J_NOMINAL``) and the best causal policy (``J_STAR``), the
median regret ``J - J_STAR``, and the late regression ``final - best`` of each seed (on the
``draws`` draws over the checkpoints, and on the single evaluation draw), with the number of
seeds that regress by more than 5 % of the gap.

``J_STAR`` = -401.5 (exact coupled dynamic program of the month, 3 000 days) and
``J_NOMINAL`` = 1576 (the nominal MPC on the same days) were measured with the causal-optimum
benchmark on the same month, noise and cost.

Run ``python benchmarks/bench_learner_robustness.py [--seeds 200-219] [--draws 10]
[--candidates old,default,day-end] [--quick] [--json FILE]``. A 100-month run with its
evaluations takes 15-60 s with the default (kernel) back-end on two cores, depending on the
load; the default study (3 candidates, 20 seeds) 15-60 minutes. ``--quick`` runs 2 seeds of 20
months (a smoke test; its numbers mean nothing).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

# One BLAS thread: the critic's small solves (about 200 x 200 with 'hour*paper') are ten
# times slower with two threads fighting for two busy cores. Set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from mpcrl_lite.config import LearningConfig
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.sim.closed_loop import evaluate_mpc
from mpcrl_lite.system.forecast import until_midnight

J_STAR = -401.5
J_NOMINAL = 1576.0
#: Every candidate: LearningConfig fields and whether the MPC's forecast stops at midnight.
CANDIDATES: dict[str, dict[str, Any]] = {
    # the defaults before this study: projected exploration, per-battery parameters, one
    # value slope for the whole day
    "old": {"learning": {"exploration_bounds": "project", "exploration_margin": 0.0,
                         "tie_agents": False, "value_features": "paper+hour"}},
    "default": {"learning": {}},
    "day-end": {"learning": {}, "day_end": True},
    "natural": {"learning": {"optimizer": "natural", "step_size": 0.08,
                             "max_policy_change": 0.1, "natural_damping": 0.01}},
    "untied": {"learning": {"tie_agents": False}},
    "paper+hour": {"learning": {"value_features": "paper+hour"}},
    "project": {"learning": {"exploration_bounds": "project"}},
    "margin": {"learning": {"exploration_margin": 0.2}},
}
EVERY_K, EVERY_EVAL = 10, 5


def run(candidate: str, seed: int, months: int, draws: int) -> dict[str, Any]:
    """One learning run and its evaluations."""
    spec = CANDIDATES[candidate]
    learning = LearningConfig(months=months, seed=seed, eval_every=0, **spec["learning"])
    experiment = Experiment(learning=learning)
    if spec.get("day_end"):
        experiment.prices = until_midnight(experiment.prices)
    t0 = time.perf_counter()
    thetas = {0: experiment.theta}
    for month in range(1, months + 1):
        experiment.run_one_month()
        thetas[month] = experiment.theta
    learn_s = time.perf_counter() - t0

    def J(theta, noise_seed):
        return float(evaluate_mpc(theta, experiment.solver, experiment.prices,
                                  experiment.system, noise_seed).J())

    noise = [7000 + k for k in range(draws)]
    checkpoints = sorted({m for m in thetas if m and m % EVERY_K == 0} | {months})
    k_draws = {m: float(np.mean([J(thetas[m], s) for s in noise])) for m in checkpoints}
    eval_draw = {m: J(thetas[m], learning.eval_seed) for m in thetas if m % EVERY_EVAL == 0}
    return {"candidate": candidate, "seed": seed, "learn_s": learn_s,
            "total_s": time.perf_counter() - t0, "J_draws": k_draws, "J_eval": eval_draw,
            "final": k_draws[months]}


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The figures of one candidate over its seeds (see the module docstring)."""
    gap = J_NOMINAL - J_STAR
    final = np.array([r["final"] for r in runs])
    late = np.array([r["final"] - min(r["J_draws"].values()) for r in runs])
    months = max(max(r["J_eval"]) for r in runs)
    late_eval = np.array([r["J_eval"][months] - min(r["J_eval"].values()) for r in runs])
    q1, median, q3 = np.percentile(final, [25, 50, 75])
    return {
        "seeds": len(runs), "median": median, "q1": q1, "q3": q3,
        "worst": float(final.max()), "best": float(final.min()),
        "closing_90": int(np.sum(final <= J_NOMINAL - 0.9 * gap)),
        "median_regret": median - J_STAR,
        "late_median": float(np.median(late)), "late_max": float(late.max()),
        "late_over_5pc": int(np.sum(late > 0.05 * gap)),
        "late_eval_max": float(late_eval.max()),
        "late_eval_over_5pc": int(np.sum(late_eval > 0.05 * gap)),
    }


def table(summaries: dict[str, dict[str, Any]]) -> str:
    gap = J_NOMINAL - J_STAR
    header = (
        f"| candidate | seeds | median J | IQR | worst | best | J <= "
        f"{J_NOMINAL - 0.9 * gap:.0f} | median regret | late regression (draws): median / "
        f"max / > {0.05 * gap:.0f} | late regression (J_eval): max / > {0.05 * gap:.0f} |"
    )
    lines = [header, "|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in summaries.items():
        lines.append(
            f"| {name} | {s['seeds']} | {s['median']:.0f} | {s['q1']:.0f} .. {s['q3']:.0f} | "
            f"{s['worst']:.0f} | {s['best']:.0f} | {s['closing_90']}/{s['seeds']} | "
            f"{s['median_regret']:.0f} | {s['late_median']:.0f} / {s['late_max']:.0f} / "
            f"{s['late_over_5pc']} | {s['late_eval_max']:.0f} / {s['late_eval_over_5pc']} |"
        )
    return "\n".join(lines)


def _seeds(text: str) -> list[int]:
    if "-" in text:
        low, high = (int(x) for x in text.split("-"))
        return list(range(low, high + 1))
    return [int(x) for x in text.split(",")]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="200-219", help="'200-219' or '1,5,9'")
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--months", type=int, default=100)
    parser.add_argument("--candidates", default="old,default,day-end",
                        help=f"comma-separated, some of {list(CANDIDATES)}")
    parser.add_argument("--quick", action="store_true", help="2 seeds, 20 months, 2 draws")
    parser.add_argument("--json", help="also write every run to this file")
    args = parser.parse_args(argv)
    seeds, draws, months = _seeds(args.seeds), args.draws, args.months
    if args.quick:
        seeds, draws, months = seeds[:2], 2, 20
    names = args.candidates.split(",")
    unknown = sorted(set(names) - set(CANDIDATES))
    if unknown:
        parser.error(f"unknown candidate(s) {unknown}; expected some of {list(CANDIDATES)}")
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name in names}
    for name in names:
        for seed in seeds:
            result = run(name, seed, months, draws)
            runs[name].append(result)
            print(f"{name} seed {seed}: final {result['final']:.1f} NOK/day "
                  f"({result['total_s']:.0f} s)", file=sys.stderr, flush=True)
    print(table({name: summarise(r) for name, r in runs.items()}))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
