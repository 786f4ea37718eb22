"""The best-in-class search: 2,500 candidate evaluations x 6 draws (``tune``'s default).

    python benchmarks/bench_tune.py              # 2,500 evaluations x 6 draws, 2 workers
    python benchmarks/bench_tune.py --quick      # 60 evaluations x 2 draws (smoke run)

Prints ONE JSON line: the wall and CPU seconds of the search (``tune_s``, ``tune_cpu_s``:
this process and its worker processes; the held-out judgement apart, ``tune_heldout_s``),
the reference of one candidate at a time (``one_at_a_time_s``: ``evaluate_mpc`` per candidate
on the same draws, measured on a few candidates and extrapolated), their ratio, and the
search's J. The default paper class, ``--workers`` processes (default 2); the kernels are
loaded before the clocks start. The search solves its candidates as ``tune`` does by default
(to the KKT tolerance ``TuneSettings.search_tol``, unpolished); the reference solves
exactly, as the judgement does. Nothing is asserted (target: about 2 minutes on 2 cores).
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


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--reference-candidates", type=int, default=3)
    a = p.parse_args(argv)
    import numpy as np

    from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
    from mpcrl_lite.mpc.backends.kernel import warm_up
    from mpcrl_lite.mpc.backends.registry import make_solver
    from mpcrl_lite.mpc.formulation import MPC
    from mpcrl_lite.sim.closed_loop import evaluate_mpc
    from mpcrl_lite.studies.tune import Space, TuneSettings, tune
    from mpcrl_lite.system.prices import Prices
    from mpcrl_lite.theta import Theta

    warm_up()
    evals, draws = (60, 2) if a.quick else (2500, 6)
    settings = TuneSettings(evals=evals, draws=draws, heldout_draws=30)
    system = SystemConfig()
    prices = Prices.month(system, LearningConfig().days_per_month)
    # the reference: a few candidates of the search's first generation, one at a time
    space = Space(Theta.nominal(system))
    rng = np.random.default_rng(1)
    cands = [space.theta(rng.standard_normal(space.dim)) for _ in range(a.reference_candidates)]
    solver = make_solver(MPC(system), MPCConfig())
    t0, c0 = time.perf_counter(), _cpu()
    for theta in cands:
        evaluate_mpc(theta, solver, prices, system, settings.seed, draws=draws)
    ref_s, ref_cpu = time.perf_counter() - t0, _cpu() - c0
    per_eval, per_eval_cpu = ref_s / len(cands), ref_cpu / len(cands)
    with tempfile.TemporaryDirectory() as out:
        t0, c0 = time.perf_counter(), _cpu()
        result = tune(out, settings, system=system, prices=prices, workers=a.workers,
                      progress=False, figure=False)
        total_s, total_cpu = time.perf_counter() - t0, _cpu() - c0
    search_s = result["search_wall_time_s"]
    print(json.dumps({
        "quick": a.quick, "evals": result["evals"], "draws": draws, "workers": a.workers,
        "tune_s": search_s, "tune_cpu_s": result["search_cpu_time_s"],
        "tune_total_s": total_s, "tune_total_cpu_s": total_cpu,
        "tune_heldout_s": result["heldout_wall_time_s"],
        "one_at_a_time_s": per_eval * result["evals"],
        "one_at_a_time_cpu_s": per_eval_cpu * result["evals"],
        "one_at_a_time_extrapolated_from": len(cands),
        "tune_speedup_vs_one_at_a_time": per_eval * result["evals"] / search_s,
        "search_tol": settings.search_tol,
        "J_best": result["J_best"], "J_best_search": result["J_best_search"],
        "J_heldout": result["J_heldout"],
        "loadavg": list(os.getloadavg()),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
