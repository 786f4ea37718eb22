"""The compiled back-end against the batch interior point, on the same closed-loop problems.

For each size (n agents, horizon N) a month of ``days`` days runs in closed loop for a few
hours (as ``run_month``: warm start from the shifted previous plan, Gaussian exploration, the
true system), once with :class:`~mpcrl_lite.mpc.backends.kernel.KernelSolver` and once with
:class:`~mpcrl_lite.mpc.backends.batch.BatchSolver` from the same states, prices and random draws
(their policies agree to 1e-14, so both see the same problems). Only the solver calls are
timed: ``solve_batch`` + ``sensitivity`` of every hour. Where the size has a copy of the
kernels compiled for it (:data:`~mpcrl_lite.mpc.backends.kernel_sizes.SPECIALISED_SIZES`, the
paper's), the generic kernels run too (``kernel_generic_*``, ``specialised_speedup_cpu``:
generic / specialised CPU, ``specialised_same_bits``: the same actions and sensitivities);
where the factorisation is ``stage`` the same kernels also run on one thread, four problems
at once as by default (``kernel_one_thread_*``: their CPU without a second thread waiting
between calls) and one problem after the other (``kernel_each_*``; ``lanes_speedup_cpu``: one
at a time / four at once, both on one thread; ``lanes_same_bits``).
Reported per problem (one day-hour)
in microseconds, wall (``time.perf_counter``) and CPU (``time.process_time``), the median
over ``--repeats`` runs (and, ``*_min``, the least contended run: on a shared machine the
closest figure to an idle one), the ratio batch / kernel from the same run, the largest
differences of action and sensitivity, and the per-step figures (``days`` problems per
call, ``*_ms_per_step``).

Run ``python benchmarks/bench_kernel.py [--repeats 5] [--days 30] [--quick]``; prints one
JSON line. The kernels are compiled (or loaded from numba's cache) before timing.
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

from mpcrl_lite.config import ConfigWarning, LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.batch import BatchSolver
from mpcrl_lite.mpc.backends.kernel import KernelSolver, warm_up
from mpcrl_lite.mpc.backends.kernel_sizes import SPECIALISED_SIZES
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import MPCPolicy, SensitivityRecorder, simulate
from mpcrl_lite.sim.exploration import GaussianExploration
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

#: (n, N, hours per run): the paper's size, many agents, a long horizon
SIZES = [(3, 12, 24), (100, 12, 3), (3, 48, 24)]
#: per-step targets (days problems per call), milliseconds (reported, never asserted)
TARGETS_US_PER_PROBLEM = {(3, 12): 60.0, (100, 12): 5000.0, (3, 48): 1000.0}


class _Timed:
    """``solver`` with the wall and CPU time of its ``solve_batch`` and ``sensitivity``
    calls summed, and the iteration counts kept (what the per-problem figures count)."""

    def __init__(self, solver) -> None:
        self.solver, self.mpc = solver, solver.mpc
        self.wall = self.cpu = 0.0
        self.iters: list[np.ndarray] = []
        self.ok = True

    def shift(self, x):
        return self.solver.shift(x)

    def _timed(self, call, *args, **kwargs):
        t0, c0 = time.perf_counter(), time.process_time()
        out = call(*args, **kwargs)
        self.wall += time.perf_counter() - t0
        self.cpu += time.process_time() - c0
        return out

    def solve_batch(self, *args, **kwargs):
        sol = self._timed(self.solver.solve_batch, *args, **kwargs)
        self.iters.append(sol.iterations)
        self.ok &= bool(sol.success.all())
        return sol

    def sensitivity(self, solution):
        sens = self._timed(self.solver.sensitivity, solution)
        self.ok &= bool(sens.ok.all())
        return sens


def closed_loop(solver, system: SystemConfig, prices: Prices, hours: int, seed: int) -> dict:
    """``hours`` closed-loop hours (:func:`mpcrl_lite.sim.closed_loop.simulate`, the nominal theta,
    the default exploration) with ``solver``; times of its calls and what it returned."""
    timed = _Timed(solver)
    recorder = SensitivityRecorder()
    record = simulate(
        MPCPolicy(timed, Theta.nominal(system), prices, sensitivities=True),
        prices.buy[:, :system.hours_per_day], prices.sell[:, :system.hours_per_day], system,
        rng=np.random.default_rng(seed), hours=hours, on_hour=[recorder],
        explore=GaussianExploration(LearningConfig().exploration_std, system),
    )
    return {"wall": timed.wall, "cpu": timed.cpu, "action": record.policy[:hours],
            "grad": recorder.grad_pi, "iters": np.concatenate(timed.iters), "ok": timed.ok}


def bench(n: int, N: int, hours: int, days: int, repeats: int) -> dict:
    """Figures of one size (see the module docstring)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        system = SystemConfig(n=n, N=N, P_bar=0.5 * n)
    mpc = MPC(system)
    prices = Prices.month(system, days)
    config = MPCConfig()
    kernel, batch = KernelSolver(mpc, config), BatchSolver(mpc, config)
    # the generic kernels, where the sizes have a specialised copy (kernel_sizes)
    generic = KernelSolver(mpc, config)
    generic.specialise = False
    solvers = {"kernel": kernel, "batch": batch}
    if (n, N) in SPECIALISED_SIZES:
        solvers["kernel_generic"] = generic
    if kernel.method == "stage":
        # the same kernels solving one problem after the other (no lanes; the same bits)
        each = KernelSolver(mpc, config)
        each.lanes = False
        each.threads = 1
        solvers["kernel_each"] = each
        # the default kernels on one thread: their CPU without a second thread's waiting
        one = KernelSolver(mpc, config)
        one.threads = 1
        solvers["kernel_one_thread"] = one
    for solver in solvers.values():
        closed_loop(solver, system, prices, 1, 0)  # first calls (caches, allocations)
    runs = {name: [] for name in solvers}
    for r in range(repeats):
        # alternate the order so that a change of the machine's load hits all alike
        order = list(solvers) if r % 2 == 0 else list(solvers)[::-1]
        for name in order:
            runs[name].append(closed_loop(solvers[name], system, prices, hours, seed=1))
    k, b = runs["kernel"][-1], runs["batch"][-1]
    problems = hours * days
    out = {"n": n, "N": N, "days": days, "hours": hours, "method": kernel.method,
           "structured_adjoint": kernel.structured_adjoint}
    for name, rs in runs.items():
        out[f"{name}_us_per_problem"] = 1e6 * median([x["wall"] for x in rs]) / problems
        out[f"{name}_cpu_us_per_problem"] = 1e6 * median([x["cpu"] for x in rs]) / problems
        # the least contended run: closest to the cost on an idle machine
        out[f"{name}_cpu_us_per_problem_min"] = 1e6 * min(x["cpu"] for x in rs) / problems
        out[f"{name}_ms_per_step"] = 1e3 * median([x["wall"] for x in rs]) / hours
        out[f"{name}_cpu_ms_per_step"] = 1e3 * median([x["cpu"] for x in rs]) / hours
        out[f"{name}_iterations_mean"] = float(rs[-1]["iters"].mean())
        out[f"{name}_all_ok"] = all(x["ok"] for x in rs)
    out["ratio"] = out["batch_us_per_problem"] / out["kernel_us_per_problem"]
    out["ratio_cpu"] = out["batch_cpu_us_per_problem"] / out["kernel_cpu_us_per_problem"]
    out["ratio_cpu_min"] = (out["batch_cpu_us_per_problem_min"]
                            / out["kernel_cpu_us_per_problem_min"])
    if "kernel_generic" in runs:
        # what the copy with the sizes fixed at compile time saves (same results bit for bit)
        out["specialised_speedup_cpu"] = (out["kernel_generic_cpu_us_per_problem"]
                                          / out["kernel_cpu_us_per_problem"])
        out["specialised_speedup_cpu_min"] = (out["kernel_generic_cpu_us_per_problem_min"]
                                              / out["kernel_cpu_us_per_problem_min"])
        g = runs["kernel_generic"][-1]
        out["specialised_same_bits"] = bool(np.array_equal(g["action"], k["action"])
                                            and np.array_equal(g["grad"], k["grad"]))
    if "kernel_each" in runs:
        # what solving four problems at once saves (same results bit for bit)
        out["lanes_speedup_cpu"] = (out["kernel_each_cpu_us_per_problem"]
                                    / out["kernel_one_thread_cpu_us_per_problem"])
        out["lanes_speedup_cpu_min"] = (out["kernel_each_cpu_us_per_problem_min"]
                                        / out["kernel_one_thread_cpu_us_per_problem_min"])
        e = runs["kernel_each"][-1]
        out["lanes_same_bits"] = bool(np.array_equal(e["action"], k["action"])
                                      and np.array_equal(e["grad"], k["grad"]))
    out["max_action_diff"] = float(np.max(np.abs(k["action"] - b["action"])))
    scale = np.maximum(np.abs(b["grad"]).max(axis=-2, keepdims=True), 1e-300)
    out["max_sens_diff_column_relative"] = float(np.max(np.abs(k["grad"] - b["grad"]) / scale))
    out["same_iterations"] = bool(np.array_equal(k["iters"], b["iters"]))
    target = TARGETS_US_PER_PROBLEM.get((n, N))
    if target is not None:
        out["target_us_per_problem"] = target
        out["target_met"] = out["kernel_us_per_problem"] <= target
        out["target_met_cpu"] = out["kernel_cpu_us_per_problem"] <= target
        out["target_met_cpu_min"] = out["kernel_cpu_us_per_problem_min"] <= target
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per back-end and size")
    parser.add_argument("--days", type=int, default=30, help="problems per call")
    parser.add_argument("--quick", action="store_true", help="one repeat, fewer hours")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    compile_s = warm_up()
    info = machine()
    info["loadavg_start"] = info.pop("loadavg", None)
    rows = []
    for n, N, hours in SIZES:
        rows.append(bench(n, N, max(1, hours // 4) if args.quick else hours, args.days,
                          1 if args.quick else args.repeats))
        print(f"[bench_kernel] n={n} N={N}: kernel {rows[-1]['kernel_us_per_problem']:.1f} us "
              f"(cpu {rows[-1]['kernel_cpu_us_per_problem']:.1f}), batch "
              f"{rows[-1]['batch_us_per_problem']:.1f} us per problem", file=sys.stderr)
    main_row = rows[0]
    result = {
        "kernel_us_per_problem": main_row["kernel_us_per_problem"],
        "batch_us_per_problem": main_row["batch_us_per_problem"],
        "kernel_cpu_us_per_problem": main_row["kernel_cpu_us_per_problem"],
        "batch_cpu_us_per_problem": main_row["batch_cpu_us_per_problem"],
        "kernel_cpu_us_per_problem_min": main_row["kernel_cpu_us_per_problem_min"],
        "batch_cpu_us_per_problem_min": main_row["batch_cpu_us_per_problem_min"],
        "ratio": main_row["ratio"],
        "ratio_cpu": main_row["ratio_cpu"],
        "kernel_generic_cpu_us_per_problem": main_row.get("kernel_generic_cpu_us_per_problem"),
        "specialised_speedup_cpu": main_row.get("specialised_speedup_cpu"),
        "specialised_same_bits": main_row.get("specialised_same_bits"),
        "kernel_one_thread_cpu_us_per_problem":
            main_row.get("kernel_one_thread_cpu_us_per_problem"),
        "kernel_one_thread_cpu_us_per_problem_min":
            main_row.get("kernel_one_thread_cpu_us_per_problem_min"),
        "kernel_each_cpu_us_per_problem": main_row.get("kernel_each_cpu_us_per_problem"),
        "lanes_speedup_cpu": main_row.get("lanes_speedup_cpu"),
        "lanes_same_bits": main_row.get("lanes_same_bits"),
        "sizes": rows,
        "warm_up_s": compile_s,
        "total_s": time.perf_counter() - t0,
        "machine": info,
    }
    return print_result(result)


if __name__ == "__main__":
    raise SystemExit(main())
