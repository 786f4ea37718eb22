"""``python -m mpcrl_lite learn``: the learning experiment (months x days, LSTD + DPG); History + summary + figures."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..._util import jsonio
from ...config import (
    GRADIENTS,
    HESSIANS,
    LEARNERS,
    OPTIMIZERS,
    PRICE_FEATURES_MIN_DAYS,
    VALUE_FEATURE_SETS,
    VALUE_FEATURES,
    LearningConfig,
    MPCConfig,
    SystemConfig,
    policy_class_of,
)
from ...learning import durable, outdir, rundir
from .. import args as _a
from ..args import UsageError

NAME = "learn"
HELP = "the learning experiment"


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``learn`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--months", type=_a.positive_int, required=True, help="learning steps (months)")
    p.add_argument("--out", type=str, required=True,
                   help="run directory (committed after every month; see mpcrl_lite.learning.rundir)")
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help=f"days per month (default {_a.LEARNING.days_per_month})")
    p.add_argument("--resume", action="store_true", help="continue the run found in --out")
    p.add_argument("--force", action="store_true",
                   help="replace the results found in --out (they are refused otherwise)")
    p.add_argument("--adopt", action="store_true",
                   help="with --resume: continue a run written before the manifest format "
                        "(no manifest.json, so its files cannot be verified; a warning says so)")
    p.add_argument("--step-size", type=_a.finite_float, default=None, help="DPG step size")
    p.add_argument("--optimizer", choices=OPTIMIZERS, default=None,
                   help=f"DPG update rule (default {_a.LEARNING.optimizer}; sgd is the "
                        "paper's plain gradient step)")
    p.add_argument("--exploration-std", type=_a.finite_float, default=None)
    p.add_argument("--value-features", choices=VALUE_FEATURES, default=None,
                   help=f"features of the critic's value baseline (default "
                        f"{_a.LEARNING.value_features}, hour*paper for months of fewer than "
                        f"{PRICE_FEATURES_MIN_DAYS} days; "
                        + "; ".join(f"{k}: {v}" for k, v in VALUE_FEATURE_SETS.items())
                        + "; a resumed run keeps its own)")
    p.add_argument("--gradient", choices=GRADIENTS, default=None,
                   help="where the policy gradient comes from: critic (default, the paper's "
                        "LSTD compatible critic from explored actions) or pathwise (extension: "
                        "the exact derivative of the month's simulated cost on its noise, "
                        "which needs the model; mpcrl_lite.learning.pathwise); a resumed run "
                        "keeps its own")
    p.add_argument("--terminal-scale", type=_a.finite_float, default=None,
                   help="Adam's typical magnitude of the terminal weights T1, T2 (default 100 "
                        "with --gradient critic, 3000 with pathwise; a resumed run keeps its "
                        "own)")
    p.add_argument("--reset-momentum-at-bounds", action="store_const", const=True,
                   default=None,
                   help="reset the update's momentum of entries the projection holds at a "
                        "bound (LearningConfig.reset_momentum_at_bounds; a resumed run keeps "
                        "its own)")
    _a.add_critic_months(p, "; a resumed run keeps its own")
    _a.add_theta0(p, "; a resumed run keeps its own")
    _a.add_update_options(p, "; a resumed run keeps its own")
    p.add_argument("--learner", choices=LEARNERS, default=None,
                   help="dpg: the paper's policy gradient (default); q: LSTD Q-learning with the "
                        "MPC as the action-value function (a resumed run keeps its own)")
    p.add_argument("--hessian", choices=HESSIANS, default=None,
                   help=f"--learner q only: the curvature of the update (default "
                        f"{_a.LEARNING.hessian}: Gauss-Newton; full: with the Hessian of Q; "
                        "none: a first-order step with --optimizer and --step-size)")
    p.add_argument("--newton-step", type=_a.finite_float, default=None,
                   help=f"--learner q: the fraction of the Newton step (default "
                        f"{_a.LEARNING.newton_step})")
    p.add_argument("--eval-draws", type=_a.positive_int, default=None,
                   help=f"noise draws of each evaluation (default {_a.LEARNING.eval_draws}; "
                        "runs from before the option were evaluated on 1)")
    p.add_argument("--eval-here", action="store_true",
                   help="evaluate in this process, never in a second one (by default, with "
                        "two cores and long evaluations, a worker process evaluates each "
                        "month's theta while the months run: the same results, sooner)")
    p.add_argument("--decentralized", action="store_true",
                   help="one MPC and one learner per battery; the MPCs are coordinated on the "
                        "grid limit by per-stage grid prices found with a decomposed Newton "
                        "method (the same policy as the centralized MPC)")
    p.add_argument("--no-figures", action="store_true", help="skip writing the figures")
    _a.add_price_args(p)
    _a.add_system_args(p)

    return p


def _from_run(out: Path, read: Callable[[dict[str, Any]], Any], default: Any = None) -> Any:
    """``read`` of the configs the run in ``out`` recorded (its ``checkpoint.json``, else its
    ``history.json``); ``default`` if neither can be read (the resume then reports what is
    wrong)."""
    for name in ("checkpoint.json", "history.json"):
        try:
            return read(json.loads((out / name).read_text()))
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            continue
    return default


def _run_eval_draws(out: Path) -> int | None:
    """``learning.eval_draws`` of the run in ``out`` (None if there is none to read)."""
    return _from_run(out, lambda c: LearningConfig.from_dict(c["learning"]).eval_draws)


#: LearningConfig fields a resumed run keeps (those ``learn`` has a flag for are checked
#: against it in :func:`run`: another value with ``--resume`` is refused).
_RUN_FIELDS = ("exploration_bounds", "exploration_margin", "ridge", "value_features", "gradient",
               "terminal_scale", "reset_momentum_at_bounds", "scale_to_prices", "step_limit",
               "learn_constants", "grad_clip", "tie_agents", "natural_damping", "step_warmup",
               "step_decay", "max_policy_change", "average_months", "keep_well_posed",
               "alpha_min", "critic_months", "theta0")


def _run_learning(out: Path) -> dict[str, Any]:
    """The fields of ``_RUN_FIELDS`` of the run in ``out`` ({} if there is none to read)."""
    def read(configs: dict[str, Any]) -> dict[str, Any]:
        learning = LearningConfig.from_dict(configs["learning"])
        return {field: getattr(learning, field) for field in _RUN_FIELDS}

    return _from_run(out, read, {})


def _run_learner(out: Path) -> dict[str, Any]:
    """``learner`` and ``hessian`` of the run in ``out`` ({} if there is none to read)."""
    def read(configs: dict[str, Any]) -> dict[str, Any]:
        learning = LearningConfig.from_dict(configs["learning"])
        return {"learner": learning.learner, "hessian": learning.hessian,
                "newton_step": learning.newton_step}

    return _from_run(out, read, {})


def _run_policy_class(out: Path) -> str | None:
    """The named policy class of the run in ``out`` (:func:`mpcrl_lite.config.policy_class_of`;
    None if there is none to read or its horizon and forecast name no class)."""
    return _from_run(out, lambda c: policy_class_of(SystemConfig.from_dict(c["system"]),
                                                    MPCConfig.from_dict(c["mpc"])))


def _run_forecast(out: Path) -> str | None:
    """``mpc.forecast`` of the run in ``out`` (None if there is none to read)."""
    return _from_run(out, lambda c: MPCConfig.from_dict(c["mpc"]).forecast)


def run(args: argparse.Namespace) -> int:
    """The ``learn`` command. Everything about ``--out`` is checked before any month runs:
    a directory holding results (a run, a History, a summary or figures of ``learn``) is
    continued with ``--resume``, replaced with ``--force`` and refused otherwise; a run that
    does not verify is refused (one line: what is wrong, how to recover)."""
    eval_draws = args.eval_draws
    if args.resume and eval_draws is None:
        # a resumed run keeps its evaluation draws (1 for runs from before the option)
        eval_draws = _run_eval_draws(Path(args.out))
    kept = _run_learning(Path(args.out)) if args.resume else {}  # and its learner's settings
    if args.hessian is not None and args.learner != "q" and not (
            args.resume and args.learner is None):
        raise UsageError(f"--hessian {args.hessian} needs --learner q (the policy gradient has "
                         "no Hessian option)")
    if args.learner == "q" and args.decentralized:
        raise UsageError("--learner q with --decentralized: the decentralized learners use the "
                         "policy gradient; expected one of them")
    chosen = {"learner": args.learner, "hessian": args.hessian,
              "newton_step": args.newton_step}
    if args.resume:  # a resumed run keeps its learner unless one is named
        run_learner = _run_learner(Path(args.out))
        for key, value in run_learner.items():
            if chosen[key] is None and (key == "learner" or args.learner is None
                                        or args.learner == run_learner.get("learner")):
                chosen[key] = value
    kept = {**kept, **{k: v for k, v in chosen.items() if v is not None}}
    for flag, field in (("--value-features", "value_features"), ("--gradient", "gradient"),
                        ("--terminal-scale", "terminal_scale"),
                        ("--reset-momentum-at-bounds", "reset_momentum_at_bounds"),
                        ("--scale-to-prices", "scale_to_prices"),
                        ("--step-limit", "step_limit"), ("--step-warmup", "step_warmup"),
                        ("--step-decay", "step_decay"), ("--average-months", "average_months"),
                        ("--critic-months", "critic_months")):
        value = getattr(args, field)
        if value is None:
            continue
        if args.resume and kept.get(field, value) != value:
            named = f"{flag} {value}"
            if isinstance(value, bool):  # a switch: --flag or --no-flag
                named = flag if value else "--no-" + flag[2:]
            raise UsageError(f"{named} with --resume: the run in {args.out} learns with "
                             f"{kept[field]!r}; expected that or no {flag}")
        kept[field] = value
    if args.decentralized and args.critic_months not in (None, 1):
        raise UsageError(f"--critic-months {args.critic_months} with --decentralized: each "
                         "decentralized learner fits its critic on its own month; expected "
                         "--critic-months 1 or no --decentralized")
    if args.decentralized and args.gradient not in (None, "critic"):
        raise UsageError(f"--gradient {args.gradient} with --decentralized: the "
                         "decentralized learners use their critics; expected --gradient "
                         "critic or no --decentralized")
    if args.resume and args.forecast is None and args.policy_class is None:
        args.forecast = _run_forecast(Path(args.out))  # and its MPC's forecast
        if args.system is None:  # and its policy class (horizon and forecast)
            args.policy_class = _run_policy_class(Path(args.out))
    # every learning option once: a price file's month only changes the days
    learning_options = dict(months=args.months, step_size=args.step_size,
                            optimizer=args.optimizer, exploration_std=args.exploration_std,
                            eval_draws=eval_draws, **kept)
    system, mpc_config, learning = _a.configs(args, days_per_month=args.days,
                                              **learning_options)
    prices = _a.month_prices(args, system, args.days)
    if prices is not None:  # the month's days
        system, mpc_config, learning = _a.configs(args, days_per_month=prices.days,
                                                  **learning_options)
    given = _a.start_theta(args, system.n)
    if given is not None:
        start, what = given
        if args.resume and kept.get("theta0", start) != start:
            raise UsageError(f"--theta0 {args.theta0} with --resume: the run in {args.out} "
                             "started from another theta; expected the same or no --theta0")
        learning = learning.replace(theta0=start)
        if not args.quiet:
            print(f"mpcrl_lite learn: starting from {what}", file=sys.stderr)
    _a.learning_budget(f"--months {args.months} --days {learning.days_per_month} --n {system.n} "
                       f"--eval-draws {learning.eval_draws}", system, learning)
    if args.adopt and not args.resume:
        raise UsageError("--adopt without --resume: --adopt continues a run written before "
                         "the manifest format; expected --resume --adopt")
    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other: --resume continues the run "
                         "in --out, --force replaces it")
    try:
        out = outdir.check_output_dir(args.out)
        with outdir.lock_output_dir(out, NAME):  # one process at a time in --out
            return _learn(args, out, system, mpc_config, learning, prices)
    except outdir.RunDirError as err:
        raise UsageError(str(err)) from None


def _learn(args, out, system, mpc_config, learning, prices) -> int:
    """The ``learn`` command once --out is checked and locked."""
    from ...figures.paper import PAPER_FIGURES
    from ...learning.experiment import Experiment
    from ...learning.learner import MAX_FAILED_SOLVE_SHARE

    outputs = (rundir.SUMMARY, *PAPER_FIGURES)
    found = rundir.inspect(out, others=outputs)
    if args.force:
        rundir.clear(out, others=outputs)
    elif args.resume and not found.holds_run and found.others:
        raise UsageError(
            f"--out {args.out}: nothing to resume (no run) but it holds "
            f"{', '.join(found.others)}: use --force to replace them or choose another --out")
    elif args.resume and not found.holds_run:
        print(f"mpcrl_lite learn: no run in {args.out} to resume: starting a new one",
              file=sys.stderr)
    elif not args.resume and found.names:
        what = "a run" if found.holds_run else "results"
        raise UsageError(
            f"--out {args.out} already holds {what} ({', '.join(found.names)}); pass "
            "--resume to continue it, --force to replace it, or choose another --out")
    if args.decentralized:
        from ...decentralized.learner import DecentralizedExperiment

        exp = DecentralizedExperiment(system, mpc_config, learning, prices=prices)
    elif learning.learner == "q":
        from ...learning.q_experiment import QLearningExperiment

        exp = QLearningExperiment(system, mpc_config, learning, prices=prices)
    else:
        exp = Experiment(system, mpc_config, learning, prices=prices)
    if args.eval_here:
        exp.eval_worker = False
    try:
        # a run found in --out is verified before any month runs
        history = exp.run(months=args.months, out=out, resume=args.resume,
                          progress=not args.quiet, adopt=args.adopt)
    except (ValueError, OSError) as err:  # RunDirError, RunWriteError
        raise UsageError(str(err)) from None
    summary = {**history.summary(), "forecast": history.mpc.forecast,
               "policy_class": history.policy_class}
    if history.learning.theta0 is not None:  # where the run started (--theta0)
        from ...theta import Theta

        summary["theta0"] = Theta.from_vector(list(history.learning.theta0),
                                              history.system.n).to_dict()
    try:
        durable.write_json(out / rundir.SUMMARY, summary)
    except OSError as err:
        raise UsageError(str(err)) from None
    if not args.no_figures:
        from ...figures.paper import save_paper_figures

        try:
            save_paper_figures(history, out, prices=exp.prices)
        except OSError as err:  # a full disk: the run is committed all the same
            raise UsageError(
                f"the run is committed in {out} ({history.months} months) but its figures "
                f"could not be written ({err.strerror or err}); free the space and run the "
                "same command with --resume to write them") from None
    print(json.dumps(jsonio.plain({
        "months": history.months,
        "J_first": history.J[0],
        "J_last": history.J[-1],
        "hours_soc_below_0_1_first": history.hours_soc_below_0_1[0],
        "hours_soc_below_0_1_last": history.hours_soc_below_0_1[-1],
        "J_eval_first": history.J_eval[0] if history.J_eval else None,
        "J_eval_last": history.J_eval[-1] if history.J_eval else None,
        "max_P_mpc": max(history.max_P_mpc),
        "max_P_applied": max(history.max_P_applied),
        "skipped_steps": int(sum(history.skipped_steps)),
        "wall_time_s": float(sum(history.wall_time_s)),
    })))
    _warn_if_not_improved(history)
    share = history.failed_solve_share()
    if share > MAX_FAILED_SOLVE_SHARE:
        raise UsageError(
            f"{100 * share:.0f} % of the MPC solves failed (solver_failures in "
            f"{out / rundir.SUMMARY}); expected at most {100 * MAX_FAILED_SOLVE_SHARE:.0f} % "
            "(MAX_FAILED_SOLVE_SHARE): the results are kept but the learning is not "
            "trustworthy; check --tau, --backend and the system")
    return 0


def _warn_if_not_improved(history) -> None:
    """One line on stderr when the last evaluation is no better than the first (the run's
    starting theta, on the same draws): the run has learned nothing usable
    (:meth:`History.improvement <mpcrl_lite.learning.history.History.improvement>`). The
    hint names the pathwise gradient only where it could replace the run's critic (a
    policy-gradient run; the decentralized learner records no evaluations, so it gets no
    verdict)."""
    verdict = history.improvement()
    if verdict is None or verdict["improved_on_start"]:
        return
    critic = history.learning.gradient == "critic" and history.learning.learner == "dpg"
    hint = ("another --seed, or --gradient pathwise (an extension that needs the model)"
            if critic else "another --seed")
    print(f"mpcrl_lite learn: warning: after {history.months} months J_eval is "
          f"{verdict['J_eval_last']:.1f} NOK/day, no lower than the starting theta's "
          f"{verdict['J_eval_start']:.1f} on the same evaluation draws: this run learned "
          f"nothing usable (summary.json 'improvement'); try {hint}", file=sys.stderr)
