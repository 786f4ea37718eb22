"""``python -m mpcrl_lite baselines``: clairvoyant / nominal / rule-based policies on the same draws as a History,
judged against J* (the regret split in two with ``--class-best``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..._util import jsonio
from .. import args as _a
from ..args import UsageError

NAME = "baselines"
HELP = "baseline policies on the same draws"


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``baselines`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument("--history", type=Path, default=None,
                   help="a learn output directory whose final theta is evaluated too")
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help=f"days (default {_a.LEARNING.days_per_month}, or all of --month)")
    p.add_argument("--no-causal", dest="causal", action="store_false",
                   help="skip J* (by default every policy is judged against the best causal "
                        "policy: the stored table, else the DP or the Lagrangian bound)")
    p.add_argument("--class-best", type=Path, default=None, metavar="DIR",
                   help="a tune output directory: its best theta is evaluated too and the "
                        "regret split into the learner's part and the class's part")
    _a.add_force(p)
    _a.add_price_args(p)
    _a.add_system_args(p)

    return p


def run(args: argparse.Namespace) -> int:
    system, mpc_config, learning = _a.configs(args, days_per_month=args.days)
    prices = _a.month_prices(args, system, args.days)
    if prices is not None:
        system, mpc_config, learning = _a.configs(args, days_per_month=prices.days)
    from ...bounds.baselines import run_baselines_cli

    # the nominal, rule-based and (with --history) learned policies and the clairvoyant LP
    _a.budget(f"--days {learning.days_per_month} --n {system.n}", system.n,
            learning.days_per_month, runs=3, horizon=system.N)
    try:
        result = run_baselines_cli(system, mpc_config, learning, args.history, args.out,
                                   prices=prices, force=args.force, causal=args.causal,
                                   class_best=args.class_best)
    except (ValueError, OSError) as err:  # FileNotFoundError, RunDirError, RunWriteError
        raise UsageError(str(err)) from None
    printed = {k: v["J"] for k, v in result["policies"].items()}
    if "causal" in result:
        printed["J_star"] = result["causal"]["J_star"]
        if "split" in result["causal"]:
            printed["split"] = {k: v["mean"] for k, v in result["causal"]["split"].items()}
    print(json.dumps(jsonio.plain(printed)))
    return 0


