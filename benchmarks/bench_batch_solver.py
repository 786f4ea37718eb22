"""Timing of the batch interior point against IPOPT + the CasADi KKT sensitivity.

For each size (n agents, horizon N) one month-hour is solved: ``days`` problems with random
states, random price windows and theta0, all at once by :class:`BatchSolver`, one by one by
:class:`IpoptSolver` (on a sample of the days when IPOPT is slow). Printed are milliseconds
per problem (median of repeated calls, ``time.perf_counter``), the speed-up, and the batch
solver's Newton iterations (mean / max over the days) and cold start (construction plus the
first solve and sensitivity).

Run ``python benchmarks/bench_batch_solver.py [--repeats 5] [--days 30] [--tau 1e-4]
[--quick] [--no-ipopt]``.
On a shared machine the figures vary with its load; a multithreaded BLAS can also stall on a
busy machine (setting ``OPENBLAS_NUM_THREADS=1`` before starting Python avoids that).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from mpcrl_lite.config import ConfigWarning, MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.mpc.sensitivity import PolicySensitivity
from mpcrl_lite.theta import Theta

SIZES = [(3, 12), (3, 48), (10, 12), (30, 12), (100, 12)]
#: IPOPT samples per size (IPOPT + KKT takes about 0.5 s per problem at n = 100)
IPOPT_SAMPLES = {3: 30, 10: 10, 30: 3, 100: 2}


def median_time(fn, repeats: int) -> tuple[float, object]:
    """Median wall time of ``fn()`` over ``repeats`` calls, and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def bench(n: int, N: int, days: int, repeats: int, with_ipopt: bool, tau: float) -> dict:
    """Figures of one size."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        system = SystemConfig(n=n, N=N, P_bar=0.5 * n)
    mpc = MPC(system)
    config = MPCConfig(tau=tau)
    rng = np.random.default_rng(n * 1000 + N)
    prices = rng.uniform(5.0, 130.0, (days, N))
    buy, sell = prices, 0.5 * prices
    soc0 = rng.uniform(0.05, 0.95, (days, n))
    theta = Theta.nominal(system)

    t0 = time.perf_counter()
    solver = BatchSolver(mpc, config)
    first = solver.solve_batch(soc0, buy, sell, theta)
    solver.sensitivity(first)
    cold = time.perf_counter() - t0

    t_solve, sol = median_time(lambda: solver.solve_batch(soc0, buy, sell, theta), repeats)
    t_sens, sens = median_time(lambda: solver.sensitivity(sol), repeats)
    row = {
        "n": n, "N": N, "days": days, "solve": 1e3 * t_solve / days, "sens": 1e3 * t_sens / days,
        "iters": f"{sol.iterations.mean():.1f}/{sol.iterations.max()}", "cold": 1e3 * cold,
        "ok": bool(sol.success.all() and sens.ok.all()),
    }
    if with_ipopt:
        k = min(days, IPOPT_SAMPLES.get(n, 3) if N <= 12 else 10)
        ipopt = IpoptSolver(mpc, config)
        reference = PolicySensitivity(mpc, config)
        ipopt.solve_batch(soc0[:1], buy[:1], sell[:1], theta)  # warm up
        t_isolve, isol = median_time(
            lambda: ipopt.solve_batch(soc0[:k], buy[:k], sell[:k], theta), max(1, repeats // 2))
        t_isens, _ = median_time(lambda: reference(isol), max(1, repeats // 2))
        row.update(ipopt_solve=1e3 * t_isolve / k, ipopt_sens=1e3 * t_isens / k, samples=k,
                   max_action_diff=float(np.max(np.abs(isol.action - sol.action[:k]))))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="calls per measurement")
    parser.add_argument("--days", type=int, default=30, help="problems per call")
    parser.add_argument("--quick", action="store_true", help="only n <= 10 and one repeat")
    parser.add_argument("--no-ipopt", action="store_true", help="skip the IPOPT reference")
    parser.add_argument("--tau", type=float, default=MPCConfig().tau,
                        help="barrier parameter (default: MPCConfig's)")
    args = parser.parse_args()
    sizes = [s for s in SIZES if not args.quick or s[0] <= 10]
    repeats = 1 if args.quick else args.repeats

    head = (f"{'n':>4} {'N':>3} | {'batch solve':>11} {'sens':>7} {'total':>7} | "
            f"{'ipopt solve':>11} {'kkt sens':>8} {'total':>7} | {'speed-up':>8} | "
            f"{'iters':>7} {'cold ms':>8} {'max |da|':>9}")
    print(f"ms per problem (median of calls over a month-hour of {args.days} days, tau = "
          f"{args.tau:g}; IPOPT on a sample of the days)")
    print(head)
    print("-" * len(head))
    for n, N in sizes:
        r = bench(n, N, args.days, repeats, not args.no_ipopt, args.tau)
        total = r["solve"] + r["sens"]
        line = f"{n:>4} {N:>3} | {r['solve']:>11.3f} {r['sens']:>7.3f} {total:>7.3f} | "
        if "ipopt_solve" in r:
            itotal = r["ipopt_solve"] + r["ipopt_sens"]
            line += (f"{r['ipopt_solve']:>11.3f} {r['ipopt_sens']:>8.3f} {itotal:>7.3f} | "
                     f"{itotal / total:>7.1f}x | ")
        else:
            line += f"{'-':>11} {'-':>8} {'-':>7} | {'-':>8} | "
        line += f"{r['iters']:>7} {r['cold']:>8.1f} "
        line += f"{r.get('max_action_diff', float('nan')):>9.1e}"
        if not r["ok"]:
            line += "  (failures!)"
        print(line, flush=True)


if __name__ == "__main__":
    main()
