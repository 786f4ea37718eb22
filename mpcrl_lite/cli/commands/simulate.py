"""``python -m mpcrl_lite simulate``: closed loop of the nominal MPC (theta0) over some days; summary + figure."""

from __future__ import annotations

import argparse
import io
import json
import time

import numpy as np

from ..._util import jsonio
from ...learning import rundir
from .. import args as _a
from ..args import UsageError

NAME = "simulate"
HELP = "closed loop of the nominal MPC"

#: What ``simulate`` writes (summary.json last: it marks a finished result).
SIMULATE_OUTPUTS = ("trajectories.npz", "day0.png", rundir.SUMMARY)


def add_parser(sub) -> argparse.ArgumentParser:
    """The ``simulate`` options."""
    p = sub.add_parser(NAME, help=HELP)
    p.add_argument("--days", type=_a.positive_int, default=None,
                   help="number of days (batch); required without --prices, else the first "
                        "days of --month (default all)")
    p.add_argument("--out", type=_a.out_dir, required=True, help="output directory")
    _a.add_force(p)
    _a.add_price_args(p)
    _a.add_system_args(p)

    return p


def run(args: argparse.Namespace) -> int:
    system, mpc_config, learning = _a.configs(args)  # validate before any work
    prices = _a.month_prices(args, system, args.days)
    if prices is None and args.days is None:
        raise UsageError("--days is missing; expected a number of days (required without "
                         "--prices)")
    days = prices.days if prices is not None else args.days
    _a.budget(f"--days {days} --n {system.n}", system.n, days, horizon=system.N)
    created = not args.out.exists()
    out = _a.prepare_out(args, SIMULATE_OUTPUTS)
    try:
        return _simulate(args, out, system, mpc_config, learning, prices, days)
    except BaseException:  # a failed solve leaves no empty --out behind
        if created and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise


def _simulate(args, out, system, mpc_config, learning, prices, days) -> int:
    """The ``simulate`` command's work, once --out is checked."""
    from ...figures.plots import plot_day
    from ...mpc.backends.registry import make_solver
    from ...mpc.formulation import MPC
    from ...sim.closed_loop import run_month
    from ...system.forecast import forecast_prices
    from ...system.prices import Prices
    from ...theta import Theta

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
        **({"prices_origin": dict(prices.origin)} if prices.origin else {}),
        "theta": theta.to_dict(),
        "system": system.to_dict(),
        "mpc": mpc_config.to_dict(),
    }
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **record.arrays("month"))
    _a.write_bytes(out / "trajectories.npz", buffer.getvalue())
    fig = plot_day(record, day=0)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    _a.write_bytes(out / "day0.png", buffer.getvalue())
    _a.write_json(out / "summary.json", summary)
    print(json.dumps(jsonio.plain({k: summary[k] for k in (
        "J", "max_P_mpc", "max_P_applied", "hours_soc_below_0_1", "solver_failures", "wall_time_s"
    )})))
    return 0


