r"""Timings of mpcrl_lite's learning loop, the paper experiment, the cold start and scaling.

Every figure is a wall-clock time on this machine (see benchmarks/README.md for how to
read them under load).

* **ms per learning step** -- :func:`mpcrl_lite.sim.closed_loop.run_month` with sensitivities
  and exploration, 30 days x 24 h, default back-end (``MPCConfig()``, 'auto'), divided by
  the 720 day-hours it simulates, plus the month's LSTD fit and DPG update
  (:meth:`Experiment.learning_step` and :meth:`DPGUpdater.step`) divided by 720. Median over
  the measured months after one warm-up month.
* **paper experiment** -- ``Experiment().run(progress=False)`` (100 months x 30 days x 24 h,
  n = 3, N = 12, sensitivities and updates included, default configs, so also the
  evaluation months of ``LearningConfig.eval_every``) in a fresh interpreter; wall time of
  ``run`` and the process's peak resident set size (``ru_maxrss``), so the peak is this
  run's own. ``eval_every=0`` gives the learning alone.
* **checkpoints** -- the paper's run (one evaluation draw) with a run directory and without,
  alternating in one interpreter: the share of its wall time spent committing months
  (:func:`checkpoint_share`), and a month's time with and without the directory.
* **cold start** -- a fresh interpreter, from its launch to the first solved MPC (import
  mpcrl_lite, build the formulation and the default back-end, solve one problem); the
  median of a few launches. The time to the first sensitivity is reported too.
* **scaling** -- closed-loop hours of a 30-day month (as in ``run_month``: warm starts from
  the shifted previous plans, exploration, the true system), timing only the solver calls:
  ``solve_batch`` + ``sensitivity`` per day-hour, for n in {3, 10, 30, 100} (N = 12,
  ``P_bar = 0.5 n``) and N in {12, 24, 48} (n = 3), with the batch back-end (default
  ``MPCConfig``, and again with ``warm_start=False``) and, for n <= 10, the reference
  IPOPT + KKT back-end.

Run ``python benchmarks/bench_learning.py [--quick] [--part steps|paper|cold|scaling]``;
prints one JSON line (and, with ``--table``, the scaling table).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import BENCH_DIR, median, python_env, run_json

__all__ = [
    "checkpoint_share",
    "cold_start",
    "learning_step",
    "main",
    "paper_experiment",
    "scaling",
    "scaling_figure",
    "scaling_table",
]

N_SIZES = (3, 10, 30, 100)
HORIZONS = (12, 24, 48)
IPOPT_MAX_N = 10


# -- ms per learning step ------------------------------------------------------------------
def learning_step(months: int = 2, warmup: int = 1, warm_start: bool = True) -> dict:
    """Our learning step (see the module docstring), in this interpreter.

    ``warm_start=False`` is the same run with ``MPCConfig(warm_start=False)`` (each hour's
    problems start from the solver's default point instead of the shifted previous plan).
    """
    import numpy as np
    from threadpoolctl import threadpool_limits

    from mpcrl_lite.config import MPCConfig
    from mpcrl_lite.learning.experiment import Experiment
    from mpcrl_lite.learning.learner import BLAS_THREADS
    from mpcrl_lite.sim.closed_loop import run_month

    exp = Experiment(mpc_config=MPCConfig(warm_start=warm_start))
    H, D = exp.system.hours_per_day, exp.learning.days_per_month
    steps = H * D
    month_s, update_s, month_cpu, update_cpu = [], [], [], []
    # one BLAS thread, as in every learning month (``run`` and ``run_one_month``): OpenBLAS's
    # threads, spinning after each LSTD product, would take the cores from the kernel's
    with threadpool_limits(limits=BLAS_THREADS):
        for m in range(warmup + months):
            rng = np.random.default_rng(m)
            t0, c0 = time.perf_counter(), time.process_time()
            record = run_month(exp.theta, exp.solver, exp.prices, exp.system, rng,
                               exploration_std=exp.learning.exploration_std, sensitivities=True)
            t1, c1 = time.perf_counter(), time.process_time()
            grad, _, _ = exp.learning_step(record)
            exp.theta = exp.updater.step(exp.theta, grad)
            t2, c2 = time.perf_counter(), time.process_time()
            if m >= warmup:
                month_s.append(t1 - t0)
                update_s.append(t2 - t1)
                month_cpu.append(c1 - c0)
                update_cpu.append(c2 - c1)
            ok = float(np.mean(record.solver_ok & record.sens_ok))
    run_ms = 1e3 * median(month_s) / steps
    upd_ms = 1e3 * median(update_s) / steps
    return {
        "ms_per_step": run_ms + upd_ms,
        "cpu_ms_per_step": 1e3 * (median(month_cpu) + median(update_cpu)) / steps,
        "run_month_ms_per_step": run_ms,
        "update_ms_per_step": upd_ms,
        "update_ms_per_month": 1e3 * median(update_s),
        "month_s": month_s,
        "backend": exp.solver.name,
        "warm_start": warm_start,
        "usable_fraction": ok,
        "months_measured": months,
    }


def q_month(months: int = 3, warmup: int = 1) -> dict:
    """A learning month of the LSTD Q-learner (``learner='q'``: the month without
    sensitivities, then one fixed-first-action MPC per day-hour for Q and its gradient, the
    TD update) beside a month of the default DPG learner, in this interpreter, the two
    alternating; no evaluation months. Wall and CPU seconds per month (medians) and the ratio
    Q / DPG (issue target: at most 2).

    The allocator keeps freed memory for reuse as in every run (``keep_freed_memory``, which
    ``run_months`` and the commands set): without it glibc's own thresholds, which move with
    what the process freed before, decided whether a Q month's megabyte arrays came back as
    fresh pages, and the ratio moved with the process's history (1.86-2.08 against 1.72-1.78
    with the runs' setting, 2026-12-07)."""
    from mpcrl_lite._util.malloc import keep_freed_memory
    from mpcrl_lite.config import LearningConfig
    from mpcrl_lite.learning.experiment import Experiment
    from mpcrl_lite.learning.q_experiment import QLearningExperiment

    keep_freed_memory()  # as in every run (run_months, the commands)

    runs = {"q": QLearningExperiment(learning=LearningConfig(learner="q", eval_every=0)),
            "dpg": Experiment(learning=LearningConfig(eval_every=0))}
    wall: dict[str, list[float]] = {"q": [], "dpg": []}
    cpu_s: dict[str, list[float]] = {"q": [], "dpg": []}
    for m in range(warmup + months):
        for name in (("q", "dpg") if m % 2 == 0 else ("dpg", "q")):
            t0, c0 = time.perf_counter(), time.process_time()
            runs[name].run_one_month()
            if m >= warmup:
                wall[name].append(time.perf_counter() - t0)
                cpu_s[name].append(time.process_time() - c0)
    q, d = median(wall["q"]), median(wall["dpg"])
    qc, dc = median(cpu_s["q"]), median(cpu_s["dpg"])
    return {"q_month_s": q, "q_month_cpu_s": qc, "dpg_month_s": d, "dpg_month_cpu_s": dc,
            "q_month_ratio": q / d, "q_month_ratio_cpu": qc / dc, "q_months_measured": months}


# -- the paper experiment ------------------------------------------------------------------
_PAPER_CODE = r"""
import json, resource, time
t0 = time.perf_counter()
from mpcrl_lite.config import LearningConfig, MPCConfig
from mpcrl_lite.learning.experiment import Experiment
exp = Experiment(mpc_config=MPCConfig(warm_start={warm_start}),
                 learning=LearningConfig(months={months}{extra}))
def cpu():  # with the evaluation worker's (a child, reaped at the end of the run)
    return sum(r.ru_utime + r.ru_stime for r in (
        resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)))
t1, c1 = time.perf_counter(), cpu()
history = exp.run(progress=False)
t2, c2 = time.perf_counter(), cpu()
print(json.dumps({{
    "run_s": t2 - t1, "run_cpu_s": c2 - c1, "setup_s": t1 - t0, "months": history.months,
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    "backend": exp.solver.name, "skipped_steps": int(sum(history.skipped_steps)),
    "solver_failures": int(sum(history.solver_failures)),
    "J_first": float(history.J[0]), "J_last": float(history.J[-1]),
}}))
"""


def paper_experiment(months: int = 100, warm_start: bool = True,
                     eval_every: int | None = None, eval_draws: int | None = None) -> dict:
    """The paper's run in a fresh interpreter (its own peak RSS); with ``months < 100`` the
    wall time is also extrapolated to 100 months. ``eval_every`` and ``eval_draws`` override
    ``LearningConfig.eval_every`` (0: no evaluation months, learning only) and
    ``LearningConfig.eval_draws`` (the speed targets count one draw, the evaluation schedule
    the targets were set with; the default ten draws are measured beside it)."""
    extra = "" if eval_every is None else f", eval_every={eval_every}"
    extra += "" if eval_draws is None else f", eval_draws={eval_draws}"
    code = _PAPER_CODE.format(months=months, warm_start=warm_start, extra=extra)
    out = run_json(code, timeout=4 * 3600)
    out["warm_start"] = warm_start
    out["eval_every"] = eval_every
    out["eval_draws"] = eval_draws
    out["paper_experiment_s"] = out["run_s"] * (100 / months)
    out["paper_experiment_cpu_s"] = out["run_cpu_s"] * (100 / months)
    out["extrapolated"] = months != 100
    return out


# -- checkpoints -----------------------------------------------------------------------------
_CHECKPOINT_CODE = r"""
import json, tempfile, time
from pathlib import Path
from mpcrl_lite.config import LearningConfig
from mpcrl_lite.learning.checkpoint import Checkpointing
from mpcrl_lite.learning.experiment import Experiment
spent = [0.0]
save = Checkpointing.save_checkpoint
def timed(self, *args, **kwargs):
    t = time.perf_counter()
    try:
        return save(self, *args, **kwargs)
    finally:
        spent[0] += time.perf_counter() - t
Checkpointing.save_checkpoint = timed
def run(out):
    exp = Experiment(learning=LearningConfig(months={months}, eval_draws=1))
    exp.run(months=1, progress=False)  # the kernels loaded, the first month's set-up done
    spent[0] = 0.0
    t, c = time.perf_counter(), time.process_time()
    exp.run(progress=False, out=out)
    return time.perf_counter() - t, time.process_time() - c
walls, cpus, shares = {{"with": [], "without": []}}, {{"with": [], "without": []}}, []
with tempfile.TemporaryDirectory() as tmp:
    for trial in range({trials}):
        for kind in ("without", "with"):
            wall, cpu = run(str(Path(tmp) / f"run{{trial}}") if kind == "with" else None)
            walls[kind].append(wall)
            cpus[kind].append(cpu)
            if kind == "with":
                shares.append(spent[0] / wall)
print(json.dumps({{"walls": walls, "cpus": cpus, "shares": shares, "months": {months}}}))
"""


def checkpoint_share(months: int = 100, trials: int = 3) -> dict:
    """The monthly checkpoints of the paper's run (one evaluation draw) in a fresh
    interpreter: the same run with a run directory and without, alternating, ``trials``
    times. Reports the share of the run's wall time spent in
    :meth:`~mpcrl_lite.learning.checkpoint.Checkpointing.save_checkpoint` (median and
    largest), and the months' wall and CPU time with and without the directory (medians;
    their difference is what the checkpoints cost the run, waits and contention
    included)."""
    out = run_json(_CHECKPOINT_CODE.format(months=months, trials=trials), timeout=3600)
    per_month = {kind: median(out["walls"][kind]) / (months - 1) * 1e3 for kind in out["walls"]}
    cpu_month = {kind: median(out["cpus"][kind]) / (months - 1) * 1e3 for kind in out["cpus"]}
    return {
        "checkpoint_share": median(out["shares"]), "checkpoint_share_max": max(out["shares"]),
        "month_ms_with_dir": per_month["with"], "month_ms_without_dir": per_month["without"],
        "month_cpu_ms_with_dir": cpu_month["with"],
        "month_cpu_ms_without_dir": cpu_month["without"],
        "checkpoint_ms_per_month": per_month["with"] - per_month["without"],
        "months": months, "trials": trials,
    }


# -- cold start ----------------------------------------------------------------------------
_COLD_CODE = r"""
import os, time
t_launch = float(os.environ["BENCH_T0"])
t_start = time.time()
import mpcrl_lite
from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.theta import Theta
t_import = time.time()
system = SystemConfig()
theta = Theta.nominal(system)
solver = make_solver(MPC(system), MPCConfig(), theta)
buy, sell = Prices.month(system, 1).window(0, system.N)
sol = solver.solve_batch([[system.soc0] * system.n], buy, sell, theta)
t_solve = time.time()
cpu_solve = time.process_time()
sens = solver.sensitivity(sol)
t_sens = time.time()
import json
print(json.dumps({
    "cold_start_s": t_solve - t_launch, "interpreter_s": t_start - t_launch,
    "import_s": t_import - t_start, "first_sensitivity_s": t_sens - t_launch,
    "cpu_s": cpu_solve, "ok": bool(sol.success[0] and sens.ok[0]), "backend": solver.name,
}))
"""


def _launch(code: str, env: dict | None = None) -> dict:
    env = dict(env or python_env())
    env["BENCH_T0"] = repr(time.time())
    return run_json(code, env=env, timeout=600)


def cold_start(trials: int = 3) -> dict:
    """Median over ``trials`` fresh interpreters (see the module docstring)."""
    runs = [_launch(_COLD_CODE) for _ in range(trials)]
    out = {k: median([r[k] for r in runs]) for k in
           ("cold_start_s", "interpreter_s", "import_s", "first_sensitivity_s", "cpu_s")}
    out["trials"] = [r["cold_start_s"] for r in runs]
    out["ok"] = all(r["ok"] for r in runs)
    out["backend"] = runs[0]["backend"]
    return out


# -- scaling -------------------------------------------------------------------------------
class _TimedSolver:
    """A solver back-end that times its own ``solve_batch`` and ``sensitivity`` calls, so the
    closed loop (:func:`mpcrl_lite.sim.closed_loop.simulate`) runs unchanged around it."""

    def __init__(self, solver) -> None:
        self.solver, self.mpc = solver, solver.mpc
        self.solve_s = self.sens_s = self.cpu_s = 0.0
        self.iterations: list[float] = []
        self.failures = self.sens_bad = 0

    def solve_batch(self, *args, **kwargs):
        import numpy as np

        t0, c0 = time.perf_counter(), time.process_time()
        sol = self.solver.solve_batch(*args, **kwargs)
        self.solve_s += time.perf_counter() - t0
        self.cpu_s += time.process_time() - c0
        self.iterations.append(float(np.mean(sol.iterations)))
        self.failures += sol.failures
        return sol

    def sensitivity(self, sol):
        t0, c0 = time.perf_counter(), time.process_time()
        sens = self.solver.sensitivity(sol)
        self.sens_s += time.perf_counter() - t0
        self.cpu_s += time.process_time() - c0
        self.sens_bad += sens.skipped - sol.failures
        return sens


def _closed_loop_ms(solver, system, prices, theta, hours: int, seed: int = 0) -> dict:
    """ms per day-hour of ``solve_batch`` + ``sensitivity`` over ``hours`` closed-loop hours
    of all days of ``prices`` (the loop of ``run_month`` with exploration 0.05, timing the
    solver calls only)."""
    import numpy as np

    from mpcrl_lite.sim.closed_loop import MPCPolicy, simulate
    from mpcrl_lite.sim.exploration import GaussianExploration

    timed = _TimedSolver(solver)
    H = system.hours_per_day
    simulate(MPCPolicy(timed, theta, prices, sensitivities=True), prices.buy[:, :H],
             prices.sell[:, :H], system, rng=np.random.default_rng(seed),
             explore=GaussianExploration(0.05, system), hours=hours)
    count = prices.days * hours
    return {
        "ms": 1e3 * (timed.solve_s + timed.sens_s) / count,
        "cpu_ms": 1e3 * timed.cpu_s / count,
        "solve_ms": 1e3 * timed.solve_s / count,
        "sens_ms": 1e3 * timed.sens_s / count,
        "iterations": float(np.mean(timed.iterations)),
        "failures": int(timed.failures),
        "sens_unusable": int(timed.sens_bad),
        "problems": count,
    }


def scaling_point(n: int, N: int, backend: str, hours: int, days: int = 30,
                  warm_start: bool = True) -> dict:
    """One row of the scaling study (fresh solver; one warm-up hour not timed)."""
    import warnings

    from mpcrl_lite.config import ConfigWarning, MPCConfig, SystemConfig
    from mpcrl_lite.mpc.backends.registry import make_solver
    from mpcrl_lite.mpc.formulation import MPC
    from mpcrl_lite.system.prices import Prices
    from mpcrl_lite.theta import Theta

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        system = SystemConfig(n=n, N=N, P_bar=0.5 * n)
    t0 = time.perf_counter()
    mpc = MPC(system)
    solver = make_solver(mpc, MPCConfig(backend=backend, warm_start=warm_start))
    theta = Theta.nominal(system)
    prices = Prices.month(system, days)
    _closed_loop_ms(solver, system, prices.take(min(days, 2)), theta, hours=1)  # warm-up
    setup_s = time.perf_counter() - t0
    row = _closed_loop_ms(solver, system, prices, theta, hours=hours)
    row.update({"n": n, "N": N, "P_bar": 0.5 * n, "backend": solver.name, "hours": hours,
                "days": days, "setup_s": setup_s, "warm_start": warm_start})
    return row


def scaling_plan(quick: bool) -> list[tuple[int, int, str, int, int, bool]]:
    """``(n, N, backend, hours, days, warm_start)`` of every measured point.

    The batch back-end runs whole days (24 closed-loop hours, 720 problems) with the default
    warm start and again without it; IPOPT + KKT a few hours (its cost per problem hardly
    varies). The quick plan leaves out n = 100 and N = 48 and runs 4 hours.
    """
    plan = []
    sizes = (3, 10, 30) if quick else N_SIZES
    horizons = (12, 24) if quick else HORIZONS
    hours = 4 if quick else 24
    ipopt_hours = 2 if quick else 6
    points = [(n, 12) for n in sizes] + [(3, N) for N in horizons if N != 12]
    for n, N in points:
        plan.append((n, N, "batch", hours, 30, True))
        plan.append((n, N, "batch", hours, 30, False))
        if n <= IPOPT_MAX_N:
            plan.append((n, N, "ipopt", ipopt_hours, 30, True))
    return plan


def scaling(quick: bool = False, subprocess: bool = True) -> list[dict]:
    """Merged rows ``{n, N, P_bar, batch_ms, ..., batch_cold_ms, ..., ipopt_kkt_ms, ...}``
    (``batch_cold``: the batch back-end with ``warm_start=False``); each point runs in its own
    interpreter by default so one size's memory and caches do not leak into the next."""
    rows: dict[tuple[int, int], dict] = {}
    for n, N, backend, hours, days, warm in scaling_plan(quick):
        args = f"{n}, {N}, {backend!r}, {hours}, {days}, {warm}"
        if subprocess:
            code = f"import json, bench_learning as b; print(json.dumps(b.scaling_point({args})))"
            point = run_json(code, timeout=3600)
        else:
            point = scaling_point(n, N, backend, hours, days, warm)
        row = rows.setdefault((n, N), {"n": n, "N": N, "P_bar": 0.5 * n})
        key = "ipopt_kkt" if backend == "ipopt" else ("batch" if warm else "batch_cold")
        for field in ("ms", "cpu_ms", "solve_ms", "sens_ms", "iterations", "problems"):
            row[f"{key}_{field}"] = point[field]
        row[f"{key}_failures"] = point["failures"] + point["sens_unusable"]
    out = sorted(rows.values(), key=lambda r: (r["N"] != 12, r["n"], r["N"]))
    for row in out:
        if "ipopt_kkt_ms" in row and "batch_ms" in row:
            row["speedup_vs_ipopt"] = row["ipopt_kkt_ms"] / row["batch_ms"]
    return out


def scaling_table(rows: list[dict]) -> str:
    """Markdown table of :func:`scaling`'s rows (wall ms per day-hour, CPU ms in brackets)."""
    def f(x, fmt="{:.2f}"):
        return "--" if x is None else fmt.format(x)

    def both(r, key):
        if r.get(f"{key}_ms") is None:
            return "--"
        return f"{r[f'{key}_ms']:.2f} ({r[f'{key}_cpu_ms']:.2f})"

    lines = [
        (
            "| n | N | P_bar | batch: ms/step (CPU) | solve | sens | iters | fails "
            "| batch, no warm start: ms/step (CPU) | iters | fails "
            "| IPOPT+KKT: ms/step (CPU) | batch speedup vs IPOPT |"
        ),
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n']} | {r['N']} | {r['P_bar']:g} | {both(r, 'batch')} | "
            f"{f(r.get('batch_solve_ms'))} | {f(r.get('batch_sens_ms'))} | "
            f"{f(r.get('batch_iterations'), '{:.1f}')} | {r.get('batch_failures', '--')} | "
            f"{both(r, 'batch_cold')} | {f(r.get('batch_cold_iterations'), '{:.1f}')} | "
            f"{r.get('batch_cold_failures', '--')} | {both(r, 'ipopt_kkt')} | "
            f"{f(r.get('speedup_vs_ipopt'), '{:.1f}x')} |"
        )
    return "\n".join(lines)


def scaling_figure(rows: list[dict], path: Path = BENCH_DIR / "results" / "scaling.png"
                   ) -> Path:
    """Log-log figure: ms per step vs n (N = 12) and vs N (n = 3)."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), constrained_layout=True)
    panels = (
        (axes[0], [r for r in rows if r["N"] == 12], "n", "batteries n (N = 12, P_bar = 0.5 n)",
         50.0, 100),
        (axes[1], [r for r in rows if r["n"] == 3], "N", "horizon N (n = 3)", 5.0, 48),
    )
    for ax, sub, key, label, target, at in panels:
        sub = sorted(sub, key=lambda r: r[key])
        for col, name, style in (("batch_ms", "batch (default: warm start)", "o-"),
                                 ("batch_cold_ms", "batch, warm_start=False", "^:"),
                                 ("ipopt_kkt_ms", "IPOPT + KKT (reference)", "s--")):
            pts = [(r[key], r[col]) for r in sub if r.get(col) is not None]
            if pts:
                ax.loglog(*zip(*pts), style, label=name)
        ax.plot([at], [target], "r*", markersize=12, label=f"target ({target:g} ms at {key}={at})")
        ax.set_xlabel(label)
        ax.set_ylabel("wall ms per day-hour (solve + sensitivity)")
        xs = sorted({r[key] for r in sub})
        ax.set_xticks(xs)
        ax.set_xticklabels([str(x) for x in xs])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("mpcrl_lite: MPC solve + policy sensitivity per day-hour "
                 "(30 days per call; wall time, see benchmarks/README.md)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# -- command line --------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: fewer months and sizes")
    parser.add_argument("--part", choices=("steps", "paper", "cold", "scaling", "all"),
                        default="all")
    parser.add_argument("--table", action="store_true", help="also print the scaling table")
    args = parser.parse_args(argv)
    os.environ.setdefault("MPLBACKEND", "Agg")
    out: dict = {}
    if args.part in ("steps", "all"):
        out["learning_step"] = learning_step(months=1 if args.quick else 3)
    if args.part in ("paper", "all"):
        out["paper"] = paper_experiment(months=3 if args.quick else 100)
    if args.part in ("cold", "all"):
        out["cold"] = cold_start(trials=1 if args.quick else 3)
    if args.part in ("scaling", "all"):
        rows = scaling(quick=args.quick)
        out["scaling"] = rows
        out["figure"] = None if args.quick else str(scaling_figure(rows))
    print(json.dumps(out))
    if args.table and "scaling" in out:
        print(scaling_table(out["scaling"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
