"""``python -m mpcrl_lite study``: one learning run per seed (through sweep); convergence, spread, learning curves."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ...config import GRADIENTS, HESSIANS, LEARNERS, OPTIMIZERS, VALUE_FEATURES
from .. import args as _a
from ..args import UsageError

NAME = "study"
HELP = "one learning run per seed, judged on J_eval"

#: ``study --target`` choices: :data:`mpcrl_lite.studies.study.TARGETS` (not imported here, it loads
#: the compiled DP; a test checks that they agree).
STUDY_TARGETS = ("causal", "best_seen")


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``study`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--seeds", type=_a.positive_int, required=True, help="number of seeds")
    p.add_argument("--months", type=_a.positive_int, required=True, help="months per run")
    p.add_argument("--out", type=_a.out_dir, required=True, help="output directory")
    p.add_argument("--seed-start", type=_a.nonneg_int, default=0, help="first seed (default 0)")
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help=f"days per month (default {_a.LEARNING.days_per_month})")
    p.add_argument("--eval-draws", type=_a.positive_int, default=None,
                   help=f"evaluation draws (default {_a.LEARNING.eval_draws})")
    p.add_argument("--j-star", type=_a.finite_float, default=None,
                   help="J of the best causal policy (default: computed, see --target)")
    p.add_argument("--target", choices=STUDY_TARGETS, default="causal",
                   help="without --j-star: causal (default) computes J* for the study's "
                        "system and month (the causal DP for n <= 3, else the Lagrangian "
                        "bound), best_seen judges against the best J_eval reached")
    p.add_argument("--threshold", type=_a.finite_float, default=None,
                   help="share of the gap nominal -> target a converged seed closes "
                        "(default 0.9)")
    _a.add_forecast(p)
    _a.add_policy_class(p)
    p.add_argument("--class-best", type=Path, default=None, metavar="DIR",
                   help="a tune output directory of the study's class: split each seed's "
                        "regret into the learner's part and the class's part (the learner's "
                        "also paired: the class's best theta on the runs' own evaluation "
                        "draws)")
    _a.add_system_file(p)
    _a.add_price_args(p)
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=_a.nonneg_int, default=None, help="local workers (0: serial)")
    p.add_argument("--lockstep", type=_a.positive_int, default=None, metavar="K",
                   help="runs per task, stepped together in one process (default: each "
                        "worker's share; 1: one run per task)")
    p.add_argument("--step-size", type=_a.finite_float, default=None,
                   help=f"every run's step size (default {_a.LEARNING.step_size})")
    p.add_argument("--optimizer", choices=OPTIMIZERS, default=None,
                   help=f"every run's update rule (default {_a.LEARNING.optimizer})")
    p.add_argument("--exploration-std", type=_a.finite_float, default=None,
                   help=f"every run's exploration in MW (default {_a.LEARNING.exploration_std}; "
                        "the critic's)")
    _a.add_update_options(p, "; every run")
    p.add_argument("--learner", choices=LEARNERS, default=None,
                   help="dpg (the policy gradient, default) or q (LSTD Q-learning)")
    p.add_argument("--hessian", choices=HESSIANS, default=None,
                   help="--learner q: the curvature of the update (see learn --help)")
    p.add_argument("--value-features", choices=VALUE_FEATURES, default=None,
                   help="features of the critic's value baseline of every run (default "
                        "LearningConfig().value_features; see learn --help)")
    p.add_argument("--gradient", choices=GRADIENTS, default=None,
                   help="where every run's policy gradient comes from: critic (default, the "
                        "paper's) or pathwise (extension; see learn --help)")
    p.add_argument("--terminal-scale", type=_a.finite_float, default=None,
                   help="Adam's typical magnitude of the terminal weights of every run "
                        "(see learn --help)")
    _a.add_critic_months(p)
    _a.add_theta0(p, "; every run")
    p.add_argument("--reset-momentum-at-bounds", action="store_true",
                   help="every run resets the update's momentum of entries the projection "
                        "holds at a bound (LearningConfig.reset_momentum_at_bounds)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def run(args: argparse.Namespace) -> int:
    from ...studies.study import THRESHOLD, run_study

    # the system file's fields are the sweep base's system.* overrides of every run
    base = {f"system.{name}": value for name, value in _a.system_file(args).items()}
    if args.days is not None:
        base["learning.days_per_month"] = args.days
    if args.eval_draws is not None:
        base["learning.eval_draws"] = args.eval_draws
    if args.forecast is not None:
        base["mpc.forecast"] = args.forecast
    if args.policy_class is not None:  # its horizon and forecast reach every run
        system = {k[len("system."):]: v for k, v in base.items() if k.startswith("system.")}
        mpc = {"forecast": args.forecast} if args.forecast is not None else {}
        _a.policy_class_fields(args, system, mpc)
        base["system.N"], base["mpc.forecast"] = system["N"], mpc["forecast"]
    if args.hessian is not None and args.learner != "q":
        raise UsageError(f"--hessian {args.hessian} needs --learner q")
    # every learning option given reaches each run's LearningConfig as it is named
    for field in ("learner", "hessian", "value_features", "gradient", "scale_to_prices",
                  "step_limit", "step_size", "optimizer", "exploration_std", "step_warmup",
                  "step_decay", "average_months", "terminal_scale", "critic_months"):
        if getattr(args, field) is not None:
            base[f"learning.{field}"] = getattr(args, field)
    if args.reset_momentum_at_bounds:  # a switch: False is "not given"
        base["learning.reset_momentum_at_bounds"] = True
    given = _a.start_theta(args, int(base.get("system.n", _a.SYSTEM.n)))
    if given is not None:
        start, what = given
        base["learning.theta0"] = list(start)
        if not args.quiet:
            print(f"mpcrl_lite study: every run starts from {what}", file=sys.stderr)
    prices = _a.month_prices(args, _a.SYSTEM, args.days)  # checked before any work
    if prices is not None:
        base.update(_a.price_base(args))
        base["learning.days_per_month"] = prices.days
    try:
        summary = run_study(
            args.seeds, args.months, args.out, seed_start=args.seed_start, base=base,
            workers=args.workers, scheduler=args.scheduler, J_star=args.j_star,
            threshold=THRESHOLD if args.threshold is None else args.threshold,
            progress=not args.quiet, lockstep=args.lockstep, target=args.target,
            class_best=args.class_best)
    except (ValueError, OSError) as err:  # GridError, RunDirLocked, a full disk
        raise UsageError(" ".join(str(err).split())) from None
    keys = ("done", "fraction_converged", "J_eval_final_median", "J_eval_final_iqr",
            "worst_seed", "largest_late_regression", "J_target", "J_star_method",
            "regret_median", "regret_iqr", "late_collapse_count", "no_improvement_count")
    printed = {k: summary[k] for k in keys}
    if "class_split" in summary:
        split = summary["class_split"]
        printed.update({"J_class": split["J_class"],
                        "learner_gap_median": split["learner_gap_median"],
                        "class_gap": (split.get("class_gap") or {}).get("mean")})
        if "J_class_eval" in split:  # the class's best on the runs' own evaluation draws
            printed.update({"J_class_eval": split["J_class_eval"]["mean"],
                            "learner_gap_paired_median": split["learner_gap_paired_median"]})
    print(json.dumps({**printed, "study": str(args.out / "study.json")}, default=str))
    return 0


