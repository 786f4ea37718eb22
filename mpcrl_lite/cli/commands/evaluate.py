"""``python -m mpcrl_lite evaluate``: a learned theta and the nominal MPC on K noise draws of a (new) month."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..._util import jsonio
from ...config import policy_class_of
from ...learning import rundir
from .. import args as _a
from ..args import UsageError

NAME = "evaluate"
HELP = "a learned theta and the nominal MPC on K noise draws"

#: What ``evaluate`` writes.
EVALUATE_OUTPUTS = (rundir.SUMMARY,)


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``evaluate`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--history", type=Path, required=True,
                   help="a learn output directory (its final theta, system and MPC are used)")
    p.add_argument("--out", type=_a.out_dir, required=True, help="output directory")
    p.add_argument("--draws", type=_a.positive_int, default=10,
                   help="K noise draws (draw k uses seed SEED + k; default 10)")
    p.add_argument("--seed", type=_a.nonneg_int, default=0, help="seed of the first draw (default 0)")
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help="days (default the run's days per month, or all of --month)")
    p.add_argument("--class-best", type=Path, default=None, metavar="DIR",
                   help="a tune output directory: its best theta runs on the same draws, and "
                        "the learned theta's regret against J* is split into the learner's "
                        "part and the class's part")
    _a.add_force(p)
    _a.add_price_args(p)
    _a.add_forecast(p, "the MPC's price forecast (default: the run's own; until_midnight is an "
                     "extension beyond the paper whose forecast stops at midnight)")
    _a.add_policy_class(p, "the MPC's policy class, its horizon and forecast (default: the "
                           "run's own; see learn --help)")
    p.add_argument("--quiet", action="store_true", help="no progress output")

    return p


def run(args: argparse.Namespace) -> int:
    """The ``evaluate`` command: the final theta of ``--history`` and the nominal MPC of its
    system on ``--draws`` noise draws of a month (``--prices`` or the shipped one)."""
    from ...learning.history import History
    from ...system.prices import Prices

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
    if args.policy_class is not None:  # its horizon and forecast, a contradiction refused
        system_fields, mpc_fields = {}, {} if args.forecast is None else {"forecast": args.forecast}
        _a.policy_class_fields(args, system_fields, mpc_fields)
        system, mpc_config = system.replace(**system_fields), mpc_config.replace(**mpc_fields)
    prices = _a.month_prices(args, system, args.days)
    days = prices.days if prices is not None else (args.days or history.learning.days_per_month)
    _a.budget(f"--draws {args.draws} --days {days} --n {system.n}", system.n, days,
            runs=2 * args.draws, horizon=system.N)
    from ...bounds.baselines import causal_reference, load_class_best, regret_split
    from ...studies.transfer import evaluate_thetas
    from ...theta import Theta

    thetas = {"nominal": Theta.nominal(system), "learned": history.final_theta()}
    tuned = None
    if args.class_best is not None:
        try:
            tuned = load_class_best(args.class_best)
        except ValueError as err:
            raise UsageError(str(err)) from None
        tuned_N = tuned.get("system", {}).get("N", system.N)
        if tuned["theta_best"].n != system.n or tuned.get("forecast") != mpc_config.forecast \
                or tuned_N != system.N:
            raise UsageError(f"--class-best {args.class_best}: searched for n="
                             f"{tuned['theta_best'].n}, forecast {tuned.get('forecast')!r}, "
                             f"N={tuned_N}; expected the run's class (n={system.n}, forecast "
                             f"{mpc_config.forecast!r}, N={system.N})")
        thetas["class_best"] = tuned["theta_best"]
    out = _a.prepare_out(args, EVALUATE_OUTPUTS)
    if prices is None:
        prices = Prices.month(system, days)
    result = evaluate_thetas(thetas, system, mpc_config, prices, args.draws, args.seed)
    if tuned is not None:
        bound, source = causal_reference(system, prices)
        J_star = bound if isinstance(bound, float) else float(bound.J_star_for(prices).mean())
        policies = result["policies"]
        result["causal"] = {
            "J_star": J_star, "source": source,
            "split": regret_split(policies["learned"]["J"], policies["class_best"]["J"], J_star),
            "class_best": {"dir": str(args.class_best), "J_heldout": tuned.get("J_heldout"),
                           "J_best": tuned.get("J_best")},
        }
    summary = {
        **result,
        "history": str(args.history),
        "months_learned": history.months,
        "days": days,
        "prices": prices.source,
        **({"prices_origin": dict(prices.origin)} if prices.origin else {}),
        "theta_learned": history.final_theta().to_dict(),
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
        "policy_class": policy_class_of(system, mpc_config),
    }
    _a.write_json(out / rundir.SUMMARY, summary)
    policies = summary["policies"]
    printed = {name: policies[name]["J_stats"] for name in policies}
    if "causal" in summary:
        printed["J_star"] = summary["causal"]["J_star"]
        printed["split"] = {k: v["mean"] for k, v in summary["causal"]["split"].items()}
    print(json.dumps(jsonio.plain(printed)))
    return 0


