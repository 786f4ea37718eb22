"""The causal optimum of the paper's system: figures, grid refinement and timings.

    .venv/bin/python benchmarks/bench_causal.py                 # ~5-10 min on one core
    .venv/bin/python benchmarks/bench_causal.py --quick         # 3 days, coarse checks
    .venv/bin/python benchmarks/bench_causal.py --days 30000    # the DP policy on 30 000 days
    .venv/bin/python benchmarks/bench_causal.py --fine          # also J* on 61 nodes (+3-8 min)
    .venv/bin/python benchmarks/bench_causal.py --system examples/mixed_site.yaml
                                                                # batteries that differ (~6 min)

Prints progress on stderr and ONE JSON line on stdout:

* ``J_star``: the coupled DP (``n = 3``, 41 nodes, 0.1 MW) -- the grid model's optimum, an
  estimate of the causal optimum; with ``--fine`` also on 61 nodes, and the Richardson
  extrapolation of the two (the grid error falls as ``h^2``, measured on one battery below);
* ``J_bound``: the Lagrangian bound on the same grid (exactly below ``J_star``) and on a fine
  single-battery grid (241 nodes, 0.05 MW: the converged bound on the true system);
  ``J_relaxed``: the coupling dropped (``lambda = 0``), same grids;
* ``dp_policy``: the DP policy of the 41-node DP in closed loop on the true system
  (:func:`mpcrl_lite.bounds.baselines.evaluate_policy`) on ``--days`` days of the repeated month, mean
  and 95 % confidence interval -- an achievable cost;
* ``single_battery_refinement``: ``J_relaxed`` (one battery x 3) on grids 21..241, to show the
  grid error and its ``h^2`` rate (identical batteries only: with ``--system`` of batteries
  that differ the DP runs on the product grid, one soc grid per battery);
* wall and CPU times of each part, and ``matmul_gflops`` measured in the same run (on a
  shared machine the wall clock also measures the other processes; CPU time does not).

Nothing is asserted here; the tests (``tests/bounds/test_causal.py``) check the relations.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

import numpy as np

from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.causal.dual import lagrangian_bound
from mpcrl_lite.bounds.scenario import evaluate_policy, make_scenario
from mpcrl_lite.cli.inputs import read_system_file
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.system.prices import Prices


def _log(msg: str) -> None:
    print(f"[causal {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _timed(fn, *args, **kwargs):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args, **kwargs)
    return out, {"wall_s": round(time.perf_counter() - wall, 2),
                 "cpu_s": round(time.process_time() - cpu, 2)}


def _gflops() -> float:
    a = np.random.default_rng(0).random((1000, 1000))
    a @ a
    t = time.perf_counter()
    a @ a
    return 2e9 / (time.perf_counter() - t) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--days", type=int, default=3000, help="closed-loop days of the policy")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--quick", action="store_true", help="3 price days, 300 policy days")
    parser.add_argument("--fine", action="store_true", help="also the coupled DP on 61 nodes")
    parser.add_argument("--system", help="a YAML file of SystemConfig fields (default: the "
                        "paper's system)")
    args = parser.parse_args()
    if args.system is None:
        system = SystemConfig()
    else:
        try:
            system = SystemConfig.from_dict(read_system_file(args.system))
        except ValueError as err:
            parser.error(str(err))
    prices = Prices.default(system)
    if args.quick:
        prices, args.days = prices.take(3), 300
    out: dict = {"n": system.n, "price_days": prices.days, "matmul_gflops": round(_gflops(), 1)}

    _log("coupled DP, 41 nodes")
    bound, out["time_J_star_41"] = _timed(causal_optimum, system, prices)
    out["J_star_41"] = bound.J_star
    out["grid_41"] = {**bound.grid.describe(), **bound.info}
    if args.fine:
        _log("coupled DP, 61 nodes")
        fine, out["time_J_star_61"] = _timed(causal_optimum, system, prices, grid=61,
                                             keep_values=False)
        out["J_star_61"] = fine.J_star
        # error ~ C h^2 with h = 1/40 and 1/60: J = J61 + (J61 - J41) h61^2 / (h41^2 - h61^2)
        out["J_star_richardson"] = fine.J_star + (fine.J_star - bound.J_star) * 4 / 5

    _log("Lagrangian bound on the same grid")
    dual, out["time_bound_41"] = _timed(lagrangian_bound, system, prices)
    out["J_bound_41"], out["J_relaxed_41"] = dual.J_bound, dual.J_relaxed
    out["bound_below_J_star_every_day"] = bool(np.all(dual.J_bound_per_day
                                                      <= bound.J_star_per_day + 1e-9))
    _log("Lagrangian bound on 241 nodes, 0.05 MW")
    dual_fine, out["time_bound_241"] = _timed(lagrangian_bound, system, prices, grid=241,
                                              action_step=0.05)
    out["J_bound_241"], out["J_relaxed_241"] = dual_fine.J_bound, dual_fine.J_relaxed

    _log(f"DP policy in closed loop, {args.days} days")
    policy_prices = Prices(np.resize(prices.buy, (args.days, prices.buy.shape[1])))
    scenario = make_scenario(system, args.days, args.seed, policy_prices)
    result, out["time_policy"] = _timed(evaluate_policy, bound.policy(policy_prices), scenario,
                                        "dp")
    per_day = result.J_per_day
    half = 1.96 * per_day.std(ddof=1) / np.sqrt(per_day.size)
    out["dp_policy"] = {"J": result.J, "ci95_half_width": half, "days": args.days,
                        "seed": args.seed, "J_star_41_same_days": float(
                            bound.J_star_per_day[np.arange(args.days) % prices.days].mean())}

    if not system.identical:
        print(json.dumps(out))
        return
    _log("single-battery refinement")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # one battery: the grid limit cannot bind, as intended
        one = system.replace(n=1)
    refinement = {}
    for grid, step in ((21, 0.1), (41, 0.1), (61, 0.1), (121, 0.1), (241, 0.05)):
        single = causal_optimum(one, prices, grid=grid, action_step=step, keep_values=False)
        refinement[f"{grid}/{step:g}"] = system.n * single.J_star
    out["single_battery_refinement"] = refinement
    print(json.dumps(out))


if __name__ == "__main__":
    main()
