"""``python -m mpcrl_lite tune``: the best theta of a policy class (CMA-ES on common random
numbers, judged on held-out draws), resumable; tune.json + tune.png."""

from __future__ import annotations

import argparse
import json

from ..._util import jsonio
from .. import args as _a
from ..args import UsageError

NAME = "tune"
HELP = "best theta of the policy class (derivative-free search)"


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``tune`` options."""
    from ...studies.tune import SEARCH_TOL_MAX, TuneSettings

    d = TuneSettings()
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--out", type=_a.out_dir, required=True, help="output directory")
    p.add_argument("--evals", type=_a.positive_int, default=d.evals,
                   help=f"candidate evaluations (default {d.evals}; whole generations)")
    p.add_argument("--draws", type=_a.positive_int, default=d.draws,
                   help=f"train noise draws, selection (default {d.draws})")
    p.add_argument("--heldout-draws", type=_a.int_at_least(2), default=d.heldout_draws,
                   help=f"held-out noise draws judging the result (default {d.heldout_draws})")
    tied = p.add_mutually_exclusive_group()
    tied.add_argument("--tied", dest="tied", action="store_true", default=d.tied,
                      help="one value per theta part for all batteries (default)")
    tied.add_argument("--untied", dest="tied", action="store_false",
                      help="one value per theta part and battery")
    p.add_argument("--popsize", type=_a.int_at_least(2), default=None,
                   help="candidates per generation (default CMA-ES's, 4 + 3 ln dim)")
    exact = p.add_mutually_exclusive_group()
    exact.add_argument("--search-tol", type=float, default=d.search_tol,
                       help="KKT tolerance of the search's MPC solves, without polishing "
                            f"(default {d.search_tol:g}, at most {SEARCH_TOL_MAX:g}; the result is "
                            "judged with exact solves)")
    exact.add_argument("--exact-search", dest="search_tol", action="store_const", const=None,
                       help="solve the search's MPCs as exactly as the judgement's")
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help=f"days (default {_a.LEARNING.days_per_month}, or all of --month)")
    p.add_argument("--workers", type=_a.positive_int, default=1,
                   help="processes evaluating each generation (default 1)")
    p.add_argument("--resume", action="store_true", help="continue the search found in --out")
    _a.add_force(p)
    _a.add_price_args(p)
    _a.add_system_args(p)
    return p


def run(args: argparse.Namespace) -> int:
    from ...studies.tune import OUTPUTS, TuneSettings, tune
    from ...system.prices import Prices

    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other: --resume continues the "
                         "search in --out, --force replaces it")
    system, mpc_config, learning = _a.configs(args, days_per_month=args.days)
    try:
        settings = TuneSettings(evals=args.evals, draws=args.draws,
                                heldout_draws=args.heldout_draws, seed=args.seed,
                                tied=args.tied, popsize=args.popsize,
                                search_tol=args.search_tol)
    except ValueError as err:
        raise UsageError(str(err)) from None
    prices = _a.month_prices(args, system, args.days)
    days = learning.days_per_month if prices is None else prices.days
    # one generation's closed loop: (popsize, about 16 at most by default) x draws months;
    # checked before the shipped month is repeated to that many days
    _a.budget(f"--days {days} --n {system.n}", system.n, days,
              runs=settings.draws * (settings.popsize or 16), horizon=system.N)
    if prices is None:
        prices = Prices.month(system, days)
    if args.resume:
        out = _a.prepare_out(argparse.Namespace(out=args.out, force=True), OUTPUTS)
    else:
        out = _a.prepare_out(args, OUTPUTS)
    try:
        result = tune(out, settings, system=system, mpc_config=mpc_config, prices=prices,
                      resume=args.resume, workers=args.workers, progress=not args.quiet)
    except (ValueError, OSError) as err:
        raise UsageError(str(err)) from None
    keys = ("J_best", "J_heldout", "J_nominal_heldout", "evals", "search_wall_time_s",
            "search_cpu_time_s")
    print(json.dumps(jsonio.plain({k: result[k] for k in keys})))
    return 0
