"""Command line: ``python -m mpcrl_lite COMMAND ...``.

Commands
--------
simulate   closed loop of the nominal MPC (theta0) over some days; summary + figure
learn      the learning experiment (months x days, LSTD + DPG); History + summary + figures
report     execute every notebook into a report directory (papermill)
baselines  clairvoyant / nominal / rule-based policies on the same draws as a History
evaluate   a learned theta and the nominal MPC on K noise draws of a (new) month
sweep      a grid of learning runs on Dask
study      one learning run per seed (through sweep); convergence, spread, learning curves

``learn``, ``simulate``, ``baselines`` and ``evaluate`` read another month of prices with
``--prices EXPORT.csv --area AREA --month YYYY-MM`` (a Nord Pool export). ``learn``,
``simulate``, ``baselines``, ``evaluate`` and ``study`` take ``--forecast {paper,
until_midnight}`` (``MPCConfig.forecast``): the paper's MPC by default, or the extension beyond
the paper whose forecast stops at midnight (:mod:`mpcrl_lite.system.forecast`).

Bad arguments end with one line on stderr (``mpcrl_lite <command>: error: ...``) and exit
status 2, never with a traceback; nothing is computed or written before every argument,
the output directory and the size of the work (memory available, time limit: see
:mod:`mpcrl_lite.cli.inputs`) have been checked. Outputs are written atomically and finished
results are never replaced without ``--force``.
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .._util import jsonio
from ..config import (
    BACKENDS,
    FORECASTS,
    OPTIMIZERS,
    PAPER_TAU,
    LearningConfig,
    MPCConfig,
    SystemConfig,
)
from ..learning import rundir
from ..publish.report import PROFILES

# The heavier modules (CasADi, the solvers, matplotlib) are imported inside each command, so
# that --help and argument errors answer at once.

__all__ = ["build_parser", "main"]


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message}\n")


class UsageError(Exception):
    """A bad value found after parsing (reported in one line, exit 2)."""


def _int_at_least(low: int):
    """argparse type: an integer >= ``low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{value} must be >= {low}")
        return value

    return parse


_positive_int = _int_at_least(1)
_nonneg_int = _int_at_least(0)


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


#: ``study --target`` choices: :data:`mpcrl_lite.studies.study.TARGETS` (not imported here, it loads
#: the compiled DP; a test checks that they agree).
STUDY_TARGETS = ("causal", "best_seen")

# Defaults shown in --help are read from the configs, never copied.
_SYSTEM, _MPC, _LEARNING = SystemConfig(), MPCConfig(), LearningConfig()


def _add_system_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=_nonneg_int, default=_LEARNING.seed,
                   help=f"random seed (default {_LEARNING.seed})")
    p.add_argument("--p-bar", type=_float, default=None,
                   help=f"grid peak bound P_bar (default {_SYSTEM.P_bar:g})")
    p.add_argument("--noise-var", type=_float, default=None,
                   help=f"variance of the production-demand noise (default {_SYSTEM.noise_var:g})")
    p.add_argument("--n", type=_positive_int, default=None,
                   help=f"number of batteries (default {_SYSTEM.n})")
    p.add_argument("--tau", type=_float, default=None,
                   help=f"MPC barrier parameter in NOK (default {_MPC.tau:g}; "
                        f"{PAPER_TAU:g} is the nearly exact MPC)")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help=f"MPC solver back-end (default {_MPC.backend})")
    _add_forecast(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_forecast(p: argparse.ArgumentParser, help_text: str | None = None) -> None:
    p.add_argument("--forecast", choices=FORECASTS, default=None,
                   help=help_text or (
                       f"the MPC's price forecast (default {_MPC.forecast}: the paper's, "
                       "reading on into the next day; until_midnight is an extension beyond "
                       "the paper whose forecast stops at midnight)"))


def _add_price_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--prices", type=Path, default=None, metavar="EXPORT.csv",
                   help="a Nord Pool price export (default: the shipped November 2020 month)")
    p.add_argument("--area", default=None,
                   help="area column of --prices (default Tr.heim)")
    p.add_argument("--month", default=None, metavar="YYYY-MM",
                   help="month of --prices to use (every hour of every day must have a price)")


def _add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace the results found in --out (they are refused otherwise)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m mpcrl_lite``."""
    parser = _Parser(prog="mpcrl_lite", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    p = sub.add_parser("simulate", help="closed loop of the nominal MPC")
    p.add_argument("--days", type=_positive_int, default=None,
                   help="number of days (batch); required without --prices, else the first "
                        "days of --month (default all)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    _add_force(p)
    _add_price_args(p)
    _add_system_args(p)

    p = sub.add_parser("learn", help="the learning experiment")
    p.add_argument("--months", type=_positive_int, required=True, help="learning steps (months)")
    p.add_argument("--out", type=str, required=True,
                   help="run directory (committed after every month; see mpcrl_lite.learning.rundir)")
    p.add_argument("--days", type=_positive_int, default=None,
                   help=f"days per month (default {_LEARNING.days_per_month})")
    p.add_argument("--resume", action="store_true", help="continue the run found in --out")
    p.add_argument("--force", action="store_true",
                   help="replace the results found in --out (they are refused otherwise)")
    p.add_argument("--step-size", type=_float, default=None, help="DPG step size")
    p.add_argument("--optimizer", choices=OPTIMIZERS, default=None,
                   help=f"DPG update rule (default {_LEARNING.optimizer}; sgd is the "
                        "paper's plain gradient step)")
    p.add_argument("--exploration-std", type=_float, default=None)
    p.add_argument("--eval-draws", type=_positive_int, default=None,
                   help=f"noise draws of each evaluation (default {_LEARNING.eval_draws}; "
                        "runs from before the option were evaluated on 1)")
    p.add_argument("--decentralized", action="store_true",
                   help="one MPC and one learner per battery; the MPCs are coordinated on the "
                        "grid limit by per-stage grid prices found with a decomposed Newton "
                        "method (the same policy as the centralized MPC)")
    p.add_argument("--no-figures", action="store_true", help="skip writing the figures")
    _add_price_args(p)
    _add_system_args(p)

    p = sub.add_parser("report", help="execute every notebook into a report directory")
    p.add_argument("--out", type=Path, default=Path("reports"), help="report directory")
    p.add_argument("--profile", choices=PROFILES, default="full",
                   help="parameters: the notebooks' defaults (full), the small CI profile or "
                        "the lesson-sized classroom profile")
    p.add_argument("--notebooks", nargs="*", default=None, help="only these notebooks")
    _add_force(p)

    p = sub.add_parser("baselines", help="baseline policies on the same draws")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--history", type=Path, default=None,
                   help="a learn output directory whose final theta is evaluated too")
    p.add_argument("--days", type=_positive_int, default=None,
                   help=f"days (default {_LEARNING.days_per_month}, or all of --month)")
    _add_force(p)
    _add_price_args(p)
    _add_system_args(p)

    p = sub.add_parser("evaluate", help="a learned theta and the nominal MPC on K noise draws")
    p.add_argument("--history", type=Path, required=True,
                   help="a learn output directory (its final theta, system and MPC are used)")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--draws", type=_positive_int, default=10,
                   help="K noise draws (draw k uses seed SEED + k; default 10)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="seed of the first draw (default 0)")
    p.add_argument("--days", type=_positive_int, default=None,
                   help="days (default the run's days per month, or all of --month)")
    _add_force(p)
    _add_price_args(p)
    _add_forecast(p, "the MPC's price forecast (default: the run's own; until_midnight is an "
                     "extension beyond the paper whose forecast stops at midnight)")
    p.add_argument("--quiet", action="store_true", help="no progress output")

    p = sub.add_parser("sweep", help="a grid of learning runs on Dask")
    p.add_argument("--grid", type=Path, required=True, help="YAML file with the grid")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=_nonneg_int, default=None, help="local workers (0: serial)")
    p.add_argument("--only", action="append", default=None, metavar="ID",
                   help="execute only this run id (repeatable); a rerun executes failed/unfinished runs")
    p.add_argument("--notebooks", action="store_true",
                   help="also execute notebook 05 per grid point into DIR/reports/")
    p.add_argument("--lockstep", type=_positive_int, default=None, metavar="K",
                   help="runs per task, stepped together in one process (default: each "
                        "worker's share; 1: one run per task)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("study", help="one learning run per seed, judged on J_eval")
    p.add_argument("--seeds", type=_positive_int, required=True, help="number of seeds")
    p.add_argument("--months", type=_positive_int, required=True, help="months per run")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--seed-start", type=_nonneg_int, default=0, help="first seed (default 0)")
    p.add_argument("--days", type=_positive_int, default=None,
                   help=f"days per month (default {_LEARNING.days_per_month})")
    p.add_argument("--eval-draws", type=_positive_int, default=None,
                   help=f"evaluation draws (default {_LEARNING.eval_draws})")
    p.add_argument("--j-star", type=_float, default=None,
                   help="J of the best causal policy (default: computed, see --target)")
    p.add_argument("--target", choices=STUDY_TARGETS, default="causal",
                   help="without --j-star: causal (default) computes J* for the study's "
                        "system and month (the causal DP for n <= 3, else the Lagrangian "
                        "bound), best_seen judges against the best J_eval reached")
    p.add_argument("--threshold", type=_float, default=None,
                   help="share of the gap nominal -> target a converged seed closes "
                        "(default 0.9)")
    _add_forecast(p)
    p.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    p.add_argument("--workers", type=_nonneg_int, default=None, help="local workers (0: serial)")
    p.add_argument("--lockstep", type=_positive_int, default=None, metavar="K",
                   help="runs per task, stepped together in one process (default: each "
                        "worker's share; 1: one run per task)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


# -- configs from arguments ----------------------------------------------------------------
def _configs(args: argparse.Namespace, **learning: Any):
    system = {}
    if args.p_bar is not None:
        system["P_bar"] = args.p_bar
    if args.noise_var is not None:
        system["noise_var"] = args.noise_var
    if args.n is not None:
        system["n"] = args.n
    mpc = {}
    if args.tau is not None:
        mpc["tau"] = args.tau
    if args.backend is not None:
        mpc["backend"] = args.backend
    if args.forecast is not None:
        mpc["forecast"] = args.forecast
    learning = {k: v for k, v in learning.items() if v is not None}
    try:
        return (
            SystemConfig(**system),
            MPCConfig(**mpc),
            LearningConfig(seed=args.seed, **learning),
        )
    except ValueError as err:
        raise UsageError(str(err)) from None


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Strict JSON (NaN as null), written atomically."""
    try:
        rundir.write_json(path, data)
    except OSError as err:
        raise UsageError(str(err)) from None


def _write_bytes(path: Path, data: bytes) -> None:
    try:
        rundir.write_atomic(path, data)
    except OSError as err:
        raise UsageError(str(err)) from None


def _prices(args: argparse.Namespace, system: SystemConfig, days: int | None):
    """The month of ``--prices/--area/--month`` (None without ``--prices``), checked."""
    from . import inputs as cli_inputs

    if args.prices is None:
        given = [f for f, v in (("--area", args.area), ("--month", args.month)) if v is not None]
        if given:
            raise UsageError(f"{' and '.join(given)} given without --prices; expected "
                             "--prices EXPORT.csv with them")
        return None
    if args.month is None:
        raise UsageError(f"--prices {args.prices} given without --month; expected --month "
                         "YYYY-MM (the month of the export to use)")
    try:
        area = args.area if args.area is not None else "Tr.heim"
        return cli_inputs.month_prices(args.prices, area, args.month, system, days)
    except ValueError as err:
        raise UsageError(str(err)) from None


def _budget(what: str, n: int, days: int, runs: int = 1, sensitivities: bool = False,
            horizon: int = SystemConfig().N) -> None:
    from . import inputs as cli_inputs

    try:
        cli_inputs.check_budget(what, n, days, runs, sensitivities, horizon)
    except ValueError as err:
        raise UsageError(str(err)) from None


def _out(args: argparse.Namespace, outputs: tuple[str, ...]) -> Path:
    """--out checked (writable, no finished results unless --force) before any work."""
    from . import inputs as cli_inputs

    try:
        return cli_inputs.prepare_out(args.out, outputs, force=args.force)
    except ValueError as err:
        raise UsageError(str(err)) from None


#: What ``simulate`` writes (summary.json last: it marks a finished result).
SIMULATE_OUTPUTS = ("trajectories.npz", "day0.png", rundir.SUMMARY)
#: What ``evaluate`` writes.
EVALUATE_OUTPUTS = (rundir.SUMMARY,)


# -- commands ------------------------------------------------------------------------------
def cmd_simulate(args: argparse.Namespace) -> int:
    system, mpc_config, learning = _configs(args)  # validate before any work
    prices = _prices(args, system, args.days)
    if prices is None and args.days is None:
        raise UsageError("--days is missing; expected a number of days (required without "
                         "--prices)")
    days = prices.days if prices is not None else args.days
    _budget(f"--days {days} --n {system.n}", system.n, days, horizon=system.N)
    out = _out(args, SIMULATE_OUTPUTS)
    from ..figures.plots import plot_day
    from ..mpc.backends.registry import make_solver
    from ..mpc.formulation import MPC
    from ..sim.closed_loop import run_month
    from ..system.forecast import forecast_prices
    from ..system.prices import Prices
    from ..theta import Theta

    if prices is None:
        prices = Prices.month(system, days)
    prices = forecast_prices(prices, mpc_config)
    theta = Theta.nominal(system)
    mpc = MPC(system)
    solver = make_solver(mpc, mpc_config, theta)
    rng = np.random.default_rng(learning.seed)
    t0 = time.perf_counter()
    record = run_month(theta, solver, prices, system, rng, exploration_std=0.0, sensitivities=False)
    elapsed = time.perf_counter() - t0
    summary = {
        **record.summary(),
        "days": days,
        "P_bar": system.P_bar,
        "noise_var": system.noise_var,
        "seed": learning.seed,
        "backend": solver.name,
        "wall_time_s": elapsed,
        "ms_per_mpc_solve": 1000 * elapsed / (days * system.hours_per_day),
        "prices": prices.source,
        "theta": theta.to_dict(),
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
    }
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **record.arrays("month"))
    _write_bytes(out / "trajectories.npz", buffer.getvalue())
    fig = plot_day(record, day=0)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    _write_bytes(out / "day0.png", buffer.getvalue())
    _write_json(out / "summary.json", summary)
    print(json.dumps(jsonio.plain({k: summary[k] for k in (
        "J", "max_P_mpc", "max_P_applied", "hours_soc_below_0_1", "solver_failures", "wall_time_s"
    )})))
    return 0


def _run_eval_draws(out: Path) -> int | None:
    """``learning.eval_draws`` of the run in ``out`` (None if there is none to read: the
    resume then reports what is wrong)."""
    for name in ("checkpoint.json", "history.json"):
        try:
            learning = json.loads((out / name).read_text())["learning"]
            return LearningConfig.from_dict(learning).eval_draws
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            continue
    return None


#: LearningConfig fields ``learn`` has no flag for: a resumed run keeps the run's own.
_RUN_FIELDS = ("exploration_bounds", "exploration_margin", "ridge", "value_features",
               "learn_constants", "grad_clip", "tie_agents", "natural_damping", "step_warmup",
               "step_decay", "max_policy_change", "average_months", "keep_well_posed",
               "alpha_min")


def _run_learning(out: Path) -> dict[str, Any]:
    """The fields of ``_RUN_FIELDS`` of the run in ``out`` ({} if there is none to read: the
    resume then reports what is wrong)."""
    for name in ("checkpoint.json", "history.json"):
        try:
            learning = LearningConfig.from_dict(json.loads((out / name).read_text())["learning"])
            return {field: getattr(learning, field) for field in _RUN_FIELDS}
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            continue
    return {}


def _run_forecast(out: Path) -> str | None:
    """``mpc.forecast`` of the run in ``out`` (None if there is none to read: the resume then
    reports what is wrong)."""
    for name in ("checkpoint.json", "history.json"):
        try:
            return MPCConfig.from_dict(json.loads((out / name).read_text())["mpc"]).forecast
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            continue
    return None


def cmd_learn(args: argparse.Namespace) -> int:
    """The ``learn`` command. Everything about ``--out`` is checked before any month runs:
    a directory holding results (a run, a History, a summary or figures of ``learn``) is
    continued with ``--resume``, replaced with ``--force`` and refused otherwise; a run that
    does not verify is refused (one line: what is wrong, how to recover)."""
    eval_draws = args.eval_draws
    if args.resume and eval_draws is None:
        # a resumed run keeps its evaluation draws (1 for runs from before the option)
        eval_draws = _run_eval_draws(Path(args.out))
    kept = _run_learning(Path(args.out)) if args.resume else {}  # and its learner's settings
    if args.resume and args.forecast is None:  # and its MPC's forecast
        args.forecast = _run_forecast(Path(args.out))
    system, mpc_config, learning = _configs(
        args, months=args.months, days_per_month=args.days, step_size=args.step_size,
        optimizer=args.optimizer, exploration_std=args.exploration_std,
        eval_draws=eval_draws, **kept,
    )
    prices = _prices(args, system, args.days)
    if prices is not None:  # the month's days
        system, mpc_config, learning = _configs(
            args, months=args.months, days_per_month=prices.days, step_size=args.step_size,
            optimizer=args.optimizer, exploration_std=args.exploration_std, **kept,
        )
    _budget(f"--months {args.months} --days {learning.days_per_month} --n {system.n}",
            system.n, learning.days_per_month, runs=args.months, sensitivities=True,
            horizon=system.N)

    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other: --resume continues the run "
                         "in --out, --force replaces it")
    try:
        out = rundir.check_output_dir(args.out)
    except rundir.RunDirError as err:
        raise UsageError(str(err)) from None
    from ..figures.paper import PAPER_FIGURES
    from ..learning.experiment import Experiment
    from ..learning.learner import MAX_FAILED_SOLVE_SHARE

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
        from ..decentralized.learner import DecentralizedExperiment

        exp = DecentralizedExperiment(system, mpc_config, learning, prices=prices)
    else:
        exp = Experiment(system, mpc_config, learning, prices=prices)
    try:
        # a run found in --out is verified before any month runs
        history = exp.run(months=args.months, out=out, resume=args.resume,
                          progress=not args.quiet)
    except (ValueError, OSError) as err:  # RunDirError, RunWriteError
        raise UsageError(str(err)) from None
    summary = {**history.summary(), "forecast": history.mpc.forecast}
    try:
        rundir.write_json(out / rundir.SUMMARY, summary)
    except OSError as err:
        raise UsageError(str(err)) from None
    if not args.no_figures:
        from ..figures.paper import save_paper_figures

        save_paper_figures(history, out, prices=exp.prices)
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
    share = history.failed_solve_share()
    if share > MAX_FAILED_SOLVE_SHARE:
        raise UsageError(
            f"{100 * share:.0f} % of the MPC solves failed (solver_failures in "
            f"{out / rundir.SUMMARY}); expected at most {100 * MAX_FAILED_SOLVE_SHARE:.0f} % "
            "(MAX_FAILED_SOLVE_SHARE): the results are kept but the learning is not "
            "trustworthy; check --tau, --backend and the system")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from ..publish.report import notebook_paths, run_report

    try:  # the notebooks are checked before --out is created
        paths = notebook_paths(args.notebooks)
    except ValueError as err:
        raise UsageError(str(err)) from None
    outputs = (rundir.SUMMARY, *(f"{p.stem}{ext}" for p in paths for ext in (".ipynb", ".html")))
    from . import inputs as cli_inputs

    try:  # run_report checks the parameters, then creates --out and checks it is writable
        cli_inputs.refuse_finished(args.out, outputs, force=args.force)
        summary = run_report(args.out, profile=args.profile, notebooks=args.notebooks)
    except (ValueError, OSError) as err:
        raise UsageError(" ".join(str(err).split())) from None
    print(json.dumps({"report": str(args.out), "notebooks": list(summary["notebooks"])}))
    return 0


def cmd_baselines(args: argparse.Namespace) -> int:
    system, mpc_config, learning = _configs(args, days_per_month=args.days)
    prices = _prices(args, system, args.days)
    if prices is not None:
        system, mpc_config, learning = _configs(args, days_per_month=prices.days)
    from ..bounds.baselines import run_baselines_cli

    # the nominal, rule-based and (with --history) learned policies and the clairvoyant LP
    _budget(f"--days {learning.days_per_month} --n {system.n}", system.n,
            learning.days_per_month, runs=3, horizon=system.N)
    try:
        result = run_baselines_cli(system, mpc_config, learning, args.history, args.out,
                                   prices=prices, force=args.force)
    except (ValueError, OSError) as err:  # FileNotFoundError, RunDirError, RunWriteError
        raise UsageError(str(err)) from None
    print(json.dumps(jsonio.plain({k: v["J"] for k, v in result["policies"].items()})))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """The ``evaluate`` command: the final theta of ``--history`` and the nominal MPC of its
    system on ``--draws`` noise draws of a month (``--prices`` or the shipped one)."""
    from ..learning.history import History
    from ..system.prices import Prices

    try:
        history = History.load(args.history)
    except (ValueError, OSError) as err:  # FileNotFoundError, RunDirError
        raise UsageError(f"--history {args.history}: {err}") from None
    if not history.theta_final:
        raise UsageError(f"--history {args.history}: no final theta (no month finished); "
                         "expected a run with at least one month")
    system, mpc_config = history.system, history.mpc
    if args.forecast is not None:
        mpc_config = mpc_config.replace(forecast=args.forecast)
    prices = _prices(args, system, args.days)
    days = prices.days if prices is not None else (args.days or history.learning.days_per_month)
    _budget(f"--draws {args.draws} --days {days} --n {system.n}", system.n, days,
            runs=2 * args.draws, horizon=system.N)
    out = _out(args, EVALUATE_OUTPUTS)
    from ..studies.transfer import evaluate_thetas
    from ..theta import Theta

    if prices is None:
        prices = Prices.month(system, days)
    result = evaluate_thetas(
        {"nominal": Theta.nominal(system), "learned": history.final_theta()},
        system, mpc_config, prices, args.draws, args.seed,
    )
    summary = {
        **result,
        "history": str(args.history),
        "months_learned": history.months,
        "days": days,
        "prices": prices.source,
        "theta_learned": history.final_theta().to_dict(),
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
    }
    _write_json(out / rundir.SUMMARY, summary)
    policies = summary["policies"]
    print(json.dumps(jsonio.plain({name: policies[name]["J_stats"] for name in policies})))
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from ..studies.sweep.api import run_sweep_cli

    try:
        table = run_sweep_cli(args.grid, args.out, scheduler=args.scheduler, workers=args.workers,
                              notebooks=args.notebooks, progress=not args.quiet, only=args.only,
                              lockstep=args.lockstep)
    except (ValueError, FileNotFoundError) as err:
        raise UsageError(str(err)) from None
    print(json.dumps({"runs": len(table), "failed": int((table["status"] == "failed").sum()),
                      "table": str(args.out / "results.csv")}))
    return 0


def cmd_study(args: argparse.Namespace) -> int:
    from ..studies.study import THRESHOLD, run_study

    base = {}
    if args.days is not None:
        base["learning.days_per_month"] = args.days
    if args.eval_draws is not None:
        base["learning.eval_draws"] = args.eval_draws
    if args.forecast is not None:
        base["mpc.forecast"] = args.forecast
    try:
        summary = run_study(
            args.seeds, args.months, args.out, seed_start=args.seed_start, base=base,
            workers=args.workers, scheduler=args.scheduler, J_star=args.j_star,
            threshold=THRESHOLD if args.threshold is None else args.threshold,
            progress=not args.quiet, lockstep=args.lockstep, target=args.target)
    except (ValueError, FileNotFoundError) as err:
        raise UsageError(str(err)) from None
    keys = ("done", "fraction_converged", "J_eval_final_median", "J_eval_final_iqr",
            "worst_seed", "largest_late_regression", "J_target", "J_star_method",
            "regret_median", "regret_iqr", "late_collapse_count")
    print(json.dumps({**{k: summary[k] for k in keys}, "study": str(args.out / "study.json")},
                     default=str))
    return 0


COMMANDS = {
    "simulate": cmd_simulate,
    "learn": cmd_learn,
    "report": cmd_report,
    "baselines": cmd_baselines,
    "evaluate": cmd_evaluate,
    "sweep": cmd_sweep,
    "study": cmd_study,
}


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return COMMANDS[args.command](args)
    except UsageError as err:
        print(f"mpcrl_lite {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mpcrl_lite {args.command}: interrupted (checkpoints, if any, are kept)", file=sys.stderr)
        return 130
