"""The decentralized learner with n = 20 batteries: seconds per learning month.

One month is :meth:`DecentralizedExperiment.run_one_month
<mpcrl_lite.decentralized.learner.DecentralizedExperiment.run_one_month>` with the default
configurations and ``SystemConfig(n=20)`` (30 days x 24 hours, coordination of the 20 local
MPCs at every hour, their sensitivities, each battery's LSTD fit and DPG step). Measured
with the compiled coordination (``MPCConfig()``, back-end ``'auto'``) and, as the
reference in the same run, with the reference rounds and CasADi sensitivities
(``MPCConfig(backend='batch')``), both after the kernels and caches are loaded; wall
(``time.perf_counter``) and CPU (``time.process_time``) seconds, the ratio reference /
compiled.

``--quick`` times one compiled month and the reference's coordination (solve and
sensitivity) on 3 of its hours, from the compiled month's states; the reference month is
then extrapolated (the compiled month plus 24/3 times the difference of the two
coordinations on those hours) and marked ``reference_extrapolated``.

Run ``python benchmarks/bench_decentralized.py [--quick] [--repeats 3]``; prints one JSON
line.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, median, print_result

from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.mpc.backends.kernel import warm_up

SYSTEM = SystemConfig(n=20)
#: the target quoted in the issue (reported, never asserted)
TARGET_S_PER_MONTH = 1.0
QUICK_HOURS = (0, 9, 18)


def experiment(backend: str) -> DecentralizedExperiment:
    exp = DecentralizedExperiment(SYSTEM, MPCConfig(backend=backend), LearningConfig())
    # load every cache (CasADi maps, compiled kernels) before timing
    buy, sell = exp.prices.window(0, SYSTEM.N)
    soc = np.full((exp.prices.days, SYSTEM.n), SYSTEM.soc0)
    exp.policy.sensitivity(exp.policy.solve(soc, buy, sell, exp.thetas))
    return exp


def month(backend: str) -> tuple[float, float, DecentralizedExperiment, object]:
    """Wall and CPU seconds of one learning month, the experiment and its record."""
    exp = experiment(backend)
    t0, c0 = time.perf_counter(), time.process_time()
    record = exp.run_one_month()
    return time.perf_counter() - t0, time.process_time() - c0, exp, record


def coordination(exp: DecentralizedExperiment, record, hours: tuple[int, ...]
                 ) -> tuple[float, float]:
    """Wall and CPU seconds of the coordination and sensitivities of ``hours``, from the
    states of ``record``."""
    policy, wall, cpu = exp.policy, 0.0, 0.0
    thetas = exp.thetas
    for k in hours:
        buy, sell = exp.prices.window(k, SYSTEM.N)
        t0, c0 = time.perf_counter(), time.process_time()
        policy.sensitivity(policy.solve(record.soc[k], buy, sell, thetas))
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
    return wall, cpu


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="one month; the reference extrapolated from 3 hours")
    parser.add_argument("--repeats", type=int, default=3, help="compiled months (median)")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")  # n = 20 with P_bar = 1.5 warns that the limit binds
    t_start = time.perf_counter()
    warm_up()
    info = machine()
    info["loadavg_start"] = info.pop("loadavg", None)
    walls, cpus = [], []
    for _ in range(1 if args.quick else max(1, args.repeats)):
        wall, cpu, exp, record = month("auto")
        walls.append(wall)
        cpus.append(cpu)
        print(f"[bench_decentralized] compiled month: {wall:.2f} s wall, {cpu:.2f} s CPU",
              file=sys.stderr)
    wall, cpu = median(walls), median(cpus)
    if args.quick:
        ref = experiment("batch")
        ref.thetas = list(exp.thetas)  # both time the same policy on the same states
        fast_w, fast_c = coordination(exp, record, QUICK_HOURS)
        ref_w, ref_c = coordination(ref, record, QUICK_HOURS)
        scale = SYSTEM.hours_per_day / len(QUICK_HOURS)
        ref_wall, ref_cpu = wall + scale * (ref_w - fast_w), cpu + scale * (ref_c - fast_c)
    else:
        ref_wall, ref_cpu, _, _ = month("batch")
    print(f"[bench_decentralized] reference month: {ref_wall:.2f} s wall, {ref_cpu:.2f} s "
          f"CPU{' (extrapolated)' if args.quick else ''}", file=sys.stderr)
    result = {
        "decentralized_n20_s_per_month": wall,
        "decentralized_n20_cpu_s_per_month": cpu,
        "decentralized_n20_reference_s_per_month": ref_wall,
        "decentralized_n20_reference_cpu_s_per_month": ref_cpu,
        "decentralized_n20_ratio": ref_wall / wall,
        "decentralized_n20_ratio_cpu": ref_cpu / cpu,
        "reference_extrapolated": bool(args.quick),
        "months_s": walls,
        "months_cpu_s": cpus,
        "iterations_mean": exp.history.update_info[-1]["coordination"]["iterations_mean"],
        "target_s_per_month": TARGET_S_PER_MONTH,
        "target_met": wall <= TARGET_S_PER_MONTH,
        "target_met_cpu": cpu <= TARGET_S_PER_MONTH,
        "total_s": time.perf_counter() - t_start,
        "machine": info,
    }
    return print_result(result)


if __name__ == "__main__":
    raise SystemExit(main())
