"""The multi-seed study: K runs in lockstep (and on Dask workers) vs the same runs one by one.

    python benchmarks/bench_study.py            # 20 seeds x 100 months, default configs
    python benchmarks/bench_study.py --quick    # 4 seeds x 4 months (smoke run)

Prints ONE JSON line. Three measurements, each in a fresh interpreter:

* ``study``: ``run_study(seeds, months, workers=2)`` as ``make study`` runs it (a local Dask
  cluster of 2 processes, each learning its share of the seeds in lockstep), including the
  cluster's start and numba's cache load: what a user waits for, less the causal DP that
  gives the study its target J* (computed once per system and month and kept in the study's
  folder; timed apart, ``study_j_star_s``). CPU time is this process's plus that of its
  (finished) worker processes. Runs evaluate on one draw (:data:`EVAL_DRAWS`).
* ``one_by_one``: ``ref_seeds`` of the runs one after another in one process (the reference);
  the time of all ``seeds`` runs is extrapolated from them (``serial_extrapolated``) when
  ``ref_seeds < seeds``, as the runs cost the same up to their noise.
* ``lockstep``: the same ``ref_seeds`` runs in lockstep in one process
  (:func:`mpcrl_lite.studies.lockstep.run_lockstep`), the gain of the lockstep alone.

The last two exclude the kernels' loading (a warm-up first). Every ratio is computed from
figures of this run; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run_json


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


#: Evaluation draws of the timed runs: one, the evaluation schedule the speed targets were set
#: with (the default ten draws cost more CPU time; ``run_all.py`` measures the factor on the
#: paper experiment, ``default_eval_cpu_ratio``).
EVAL_DRAWS = 1


def study(seeds: int, months: int, workers: int = 2) -> dict:
    """``run_study`` on a local cluster of ``workers`` processes (lockstep by default)."""
    from mpcrl_lite.config import LearningConfig, SystemConfig
    from mpcrl_lite.studies.study import causal_target, run_study
    from mpcrl_lite.system.prices import Prices

    # J* (the causal DP the study judges against) is computed once per system and month and
    # kept in the study's folder; it is timed apart from the runs
    system = SystemConfig()
    t0, c0 = time.perf_counter(), _cpu()
    target = causal_target(system, Prices.month(system, LearningConfig().days_per_month))
    j_star_s, j_star_cpu_s = time.perf_counter() - t0, _cpu() - c0
    t0, c0 = time.perf_counter(), _cpu()
    with tempfile.TemporaryDirectory() as out:
        summary = run_study(seeds, months, out, workers=workers, progress=False,
                            base={"learning.eval_draws": EVAL_DRAWS}, J_star=target["J_star"])
    return {"s": time.perf_counter() - t0, "cpu_s": _cpu() - c0, "done": summary["done"],
            "j_star_s": j_star_s, "j_star_cpu_s": j_star_cpu_s}


def _runs(seeds: int, months: int) -> list:
    from mpcrl_lite.config import LearningConfig
    from mpcrl_lite.learning.experiment import Experiment
    from mpcrl_lite.mpc.backends.kernel import warm_up

    warm_up()
    return [Experiment(learning=LearningConfig(months=months, seed=s, eval_draws=EVAL_DRAWS))
            for s in range(seeds)]


def one_by_one(seeds: int, months: int) -> dict:
    """The runs one after another in this process."""
    runs = _runs(seeds, months)
    t0, c0 = time.perf_counter(), time.process_time()
    for run in runs:
        run.run(progress=False)
    return {"s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
            "J_final": [r.history.J[-1] for r in runs]}


def lockstep(seeds: int, months: int) -> dict:
    """The runs in lockstep in this process."""
    from mpcrl_lite.studies.lockstep import run_lockstep

    runs = _runs(seeds, months)
    t0, c0 = time.perf_counter(), time.process_time()
    run_lockstep(runs)
    return {"s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
            "J_final": [r.history.J[-1] for r in runs]}


def _sub(call: str) -> dict:
    return run_json(f"import json, bench_study as b; print(json.dumps(b.{call}))",
                    timeout=4 * 3600)


def run(quick: bool = False, ref_seeds: int | None = None) -> dict:
    seeds, months = (4, 4) if quick else (20, 100)
    ref = ref_seeds or (2 if quick else 4)
    load = [round(x, 2) for x in os.getloadavg()]
    full = _sub(f"study({seeds}, {months})")
    alone = _sub(f"one_by_one({ref}, {months})")
    together = _sub(f"lockstep({ref}, {months})")
    if alone["J_final"] != together["J_final"]:
        raise RuntimeError(f"lockstep and one-by-one runs differ: {together['J_final']} vs "
                           f"{alone['J_final']}")
    scale = seeds / ref
    serial_s, serial_cpu = alone["s"] * scale, alone["cpu_s"] * scale
    tag = f"{seeds}x{months}"
    return {
        "quick": quick,
        "study_seeds": seeds,
        "study_months": months,
        "study_eval_draws": EVAL_DRAWS,
        "study_j_star_s": full["j_star_s"],
        "study_j_star_cpu_s": full["j_star_cpu_s"],
        "study_s": full["s"],
        "study_cpu_s": full["cpu_s"],
        "study_serial_s": serial_s,
        "study_serial_cpu_s": serial_cpu,
        # the same under the names of this size (study_20x100_s for the full run)
        f"study_{tag}_s": full["s"],
        f"study_{tag}_cpu_s": full["cpu_s"],
        f"study_serial_{tag}_s": serial_s,
        f"study_serial_{tag}_cpu_s": serial_cpu,
        "study_serial_seeds_measured": ref,
        "study_serial_extrapolated": ref < seeds,
        "study_speedup_vs_serial": serial_s / full["s"],
        "study_cpu_ratio_vs_serial": full["cpu_s"] / serial_cpu,
        "lockstep_seeds": ref,
        "lockstep_s": together["s"],
        "lockstep_cpu_s": together["cpu_s"],
        "one_by_one_s": alone["s"],
        "one_by_one_cpu_s": alone["cpu_s"],
        "lockstep_cpu_ratio": together["cpu_s"] / alone["cpu_s"],
        "loadavg_start": load,
        "loadavg_end": [round(x, 2) for x in os.getloadavg()],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="multi-seed study: lockstep vs one by one")
    parser.add_argument("--quick", action="store_true", help="4 seeds x 4 months")
    parser.add_argument("--ref-seeds", type=int, default=None,
                        help="seeds run one by one for the reference (default 4, quick 2)")
    args = parser.parse_args(argv)
    print(json.dumps(run(quick=args.quick, ref_seeds=args.ref_seeds)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
