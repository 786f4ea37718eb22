"""Run every benchmark and print ONE JSON line, then the scaling table.

    .venv/bin/python benchmarks/run_all.py            # full run (4-13 min on 2 cores)
    .venv/bin/python benchmarks/run_all.py --quick    # smoke run (~1-2 min)

The mpcrl comparison needs the benchmark-only requirements
(``pip install -r benchmarks/requirements.txt``); without them it is skipped with a message
on stderr and ``mpcrl_ms_per_step: null``. Nothing is installed by this script.

Every ratio is computed from figures measured in this same run. Files (the scaling figure,
with ``--out`` the JSON) go to ``benchmarks/results/`` (git-ignored): a run rewrites nothing
that is tracked. Each measurement runs in its
own interpreter, so imports, caches and memory of one part do not leak into another. Wall
times are the headline figures; CPU times (``*_cpu_*``) are reported next to them because
on a shared machine the wall clock also measures the other processes (see README.md).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_learning
import bench_mpcrl
from _common import machine, run_json

#: The targets quoted in README.md (reported, never asserted).
TARGETS = {
    "speedup_vs_mpcrl": (">=", 50.0),
    "paper_experiment_s": ("<=", 8.0),
    "peak_rss_mb": ("<=", 500.0),
    "n100_ms_per_step": ("<=", 5.0),
    "N48_ms_per_step": ("<=", 1.0),
    "cold_start_s": ("<=", 3.0),
    "kernel_us_per_problem": ("<=", 60.0),
    "kernel_cpu_us_per_problem": ("<=", 25.0),
    # the same on one thread: the kernel's own CPU, without numba's second thread waiting
    "kernel_one_thread_cpu_us_per_problem": ("<=", 25.0),
    "decentralized_n20_s_per_month": ("<=", 1.0),
    "study_20x100_s": ("<=", 45.0),
    "startup_import_s": ("<=", 0.3),
    "startup_experiment_s": ("<=", 0.5),
    "paper_command_1_draw_s": ("<=", 3.0),
    "paper_command_10_draws_s": ("<=", 5.0),
    "tune_s": ("<=", 120.0),
    "q_month_ratio": ("<=", 2.0),
    # the paper's run with its run directory: the share of its time in the monthly commits
    "checkpoint_share": ("<=", 0.05),
}

#: Where ``make bench`` writes its files (git-ignored; nothing tracked is rewritten).
RESULTS = Path(__file__).resolve().parent / "results"


def _log(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _sub(call: str) -> dict:
    """``bench_learning.<call>`` in a fresh interpreter."""
    return run_json(f"import json, bench_learning as b; print(json.dumps(b.{call}))",
                    timeout=4 * 3600)


def _try(label: str, fn):
    """``fn()``, or None (logged) if it fails: one broken reference must not end the run."""
    try:
        return fn()
    except Exception as err:  # noqa: BLE001  (reported, the run goes on)
        _log(f"{label} FAILED: {str(err).strip().splitlines()[-1] if str(err).strip() else err}")
        return None


def _kernel_ms(kernel: dict | None, n: int, N: int) -> float | None:
    """Solve + sensitivity per problem (one day-hour) of the default back-end, in ms."""
    for row in (kernel or {}).get("sizes", []):
        if row["n"] == n and row["N"] == N:
            return row["kernel_us_per_problem"] / 1e3
    return None


def run(quick: bool = False, skip_mpcrl: bool = False) -> dict:
    info = machine()
    info["loadavg_start"] = info.pop("loadavg", None)
    t_start = time.perf_counter()
    result: dict = {"quick": quick}

    _log("our learning step (run_month + LSTD/DPG update)")
    ours = _sub(f"learning_step(months={1 if quick else 3})")
    _log("our learning step without warm start")
    ours_cold = _sub(f"learning_step(months={1 if quick else 3}, warm_start=False)")

    mpcrl = mpcrl_lbx = None
    mpcrl_cold = mpcrl_cold_cached = None
    if skip_mpcrl:
        _log("mpcrl comparison skipped (--skip-mpcrl)")
        result["mpcrl_skipped"] = "--skip-mpcrl"
    elif not bench_mpcrl.available():
        msg = ("mpcrl is not importable: skipping the mpcrl comparison "
               "(pip install -r benchmarks/requirements.txt to enable it)")
        _log(msg)
        result["mpcrl_skipped"] = msg
    else:
        _log("mpcrl learning step (same MPC, LstdDpgAgent)")
        days = 1 if quick else 3
        mpcrl = _try("mpcrl learning step", lambda: run_json(
            "import sys, bench_mpcrl; "
            f"sys.exit(bench_mpcrl.main(['--days', '{days}', '--warmup-days', '1']))",
            timeout=3600,
        ))
        if not quick:
            _log("mpcrl learning step, box bounds as variable bounds (inexact sensitivity)")
            mpcrl_lbx = _try("mpcrl (bounds in lbx)", lambda: run_json(
                "import sys, bench_mpcrl; "
                f"sys.exit(bench_mpcrl.main(['--days', '{days}', '--bounds-in-lbx']))",
                timeout=3600,
            ))
        _log("mpcrl cold start")
        mpcrl_cold_cached = _try("mpcrl cold start", lambda: bench_mpcrl.cold_start_subprocess(
            fresh_numba_cache=False))
        if not quick:
            mpcrl_cold = _try("mpcrl cold start (empty numba cache)",
                              lambda: bench_mpcrl.cold_start_subprocess(fresh_numba_cache=True))

    months = 3 if quick else 100
    _log(f"paper experiment ({months} months{', extrapolated to 100' if quick else ''})")
    paper = bench_learning.paper_experiment(months=months, eval_draws=1)
    _log("paper experiment with the default evaluation (LearningConfig.eval_draws draws)")
    paper_draws = _try("paper experiment (default eval_draws)",
                       lambda: bench_learning.paper_experiment(months=months))
    _log("paper experiment, learning only (eval_every=0)")
    paper_learn = _try("paper experiment (eval_every=0)",
                       lambda: bench_learning.paper_experiment(months=months, eval_every=0))

    _log("monthly checkpoints: the paper's run with a run directory and without")
    checkpoints = _try("checkpoint share", lambda: bench_learning.checkpoint_share(
        months=6 if quick else 100, trials=1 if quick else 3))
    if checkpoints is not None:
        _log(f"checkpoints: {100 * checkpoints['checkpoint_share']:.1f} % of the run "
             f"(largest {100 * checkpoints['checkpoint_share_max']:.1f} %); a month "
             f"{checkpoints['month_ms_with_dir']:.1f} ms with the directory, "
             f"{checkpoints['month_ms_without_dir']:.1f} ms without (cpu "
             f"{checkpoints['month_cpu_ms_with_dir']:.1f} / "
             f"{checkpoints['month_cpu_ms_without_dir']:.1f})")

    _log("a Q-learning month beside a DPG month (alternating, one process)")
    qmonth = _try("Q-learning month", lambda: _sub(f"q_month(months={1 if quick else 6})"))
    if qmonth is not None:
        _log(f"Q-learning month {qmonth['q_month_s']:.2f} s (cpu {qmonth['q_month_cpu_s']:.2f}), "
             f"DPG month {qmonth['dpg_month_s']:.2f} s: ratio {qmonth['q_month_ratio']:.2f}")

    _log("compiled kernel vs batch interior point (same inputs)")
    kernel = _try("kernel benchmark", lambda: run_json(
        "import sys, bench_kernel; "
        f"sys.exit(bench_kernel.main({['--quick'] if quick else []!r}))", timeout=3600))

    _log("decentralized learner, n = 20: compiled coordination vs the reference rounds")
    dec = _try("decentralized benchmark", lambda: run_json(
        "import sys, bench_decentralized; "
        f"sys.exit(bench_decentralized.main({['--quick'] if quick else []!r}))", timeout=3600))
    if dec is not None:
        _log(f"decentralized n=20: {dec['decentralized_n20_s_per_month']:.2f} s/month "
             f"(cpu {dec['decentralized_n20_cpu_s_per_month']:.2f}), reference "
             f"{dec['decentralized_n20_reference_s_per_month']:.2f} s/month: ratio "
             f"{dec['decentralized_n20_ratio']:.1f} (cpu {dec['decentralized_n20_ratio_cpu']:.1f})")
    _log("multi-seed study, runs in lockstep on 2 workers vs one by one")
    study = _try("study benchmark", lambda: run_json(
        "import sys, bench_study; "
        f"sys.exit(bench_study.main({['--quick'] if quick else []!r}))", timeout=4 * 3600))

    _log("best-in-class search: 2,500 evaluations x 6 draws on 2 workers")
    search = _try("tune benchmark", lambda: run_json(
        "import sys, bench_tune; "
        f"sys.exit(bench_tune.main({['--quick'] if quick else []!r}))", timeout=4 * 3600))

    _log("cold start")
    cold = bench_learning.cold_start(trials=1 if quick else 3)

    _log("start-up and the paper's run as commands (whole processes, beside references)")
    commands = _try("command benchmark", lambda: run_json(
        "import sys, bench_commands; "
        f"sys.exit(bench_commands.main({['--quick', '--trials', '1'] if quick else []!r}))",
        timeout=4 * 3600))
    if commands is not None:
        _log(f"start-up: import {commands['startup_import_s']:.2f} s, Experiment() "
             f"{commands['startup_experiment_s']:.2f} s (python + numpy "
             f"{commands['startup_reference_s']:.2f} s); learn 100 months: 1 draw "
             f"{commands['paper_command_1_draw_s']:.1f} s (cpu "
             f"{commands['paper_command_1_draw_cpu_s']:.1f}), 10 draws "
             f"{commands['paper_command_10_draws_s']:.1f} s (cpu "
             f"{commands['paper_command_10_draws_cpu_s']:.1f}); reference work "
             f"{commands['reference_work_s']:.2f} s; load {commands['loadavg_start']} -> "
             f"{commands['loadavg_end']}")

    _log("scaling")
    rows = bench_learning.scaling(quick=quick)
    # written into the git-ignored results folder (the smoke run draws none)
    figure = None if quick else bench_learning.scaling_figure(rows, RESULTS / "scaling.png")

    ms = ours["ms_per_step"]
    result.update({
        "ms_per_step": ms,
        "cpu_ms_per_step": ours["cpu_ms_per_step"],
        "mpcrl_ms_per_step": None if mpcrl is None else mpcrl["ms_per_step"],
        "mpcrl_cpu_ms_per_step": None if mpcrl is None else mpcrl["cpu_ms_per_step"],
        "speedup_vs_mpcrl": None if mpcrl is None else mpcrl["ms_per_step"] / ms,
        "speedup_vs_mpcrl_cpu": None if mpcrl is None
        else mpcrl["cpu_ms_per_step"] / ours["cpu_ms_per_step"],
        "mpcrl_bounds_in_lbx_ms_per_step": None if mpcrl_lbx is None
        else mpcrl_lbx["ms_per_step"],
        "speedup_vs_mpcrl_bounds_in_lbx": None if mpcrl_lbx is None
        else mpcrl_lbx["ms_per_step"] / ms,
        "ms_per_step_no_warm_start": ours_cold["ms_per_step"],
        "cpu_ms_per_step_no_warm_start": ours_cold["cpu_ms_per_step"],
        "paper_experiment_s": paper["paper_experiment_s"],
        "paper_experiment_cpu_s": paper["paper_experiment_cpu_s"],
        "paper_experiment_months_run": paper["months"],
        "paper_experiment_extrapolated": paper["extrapolated"],
        "peak_rss_mb": paper["peak_rss_mb"],
        "paper_experiment_default_eval_s": None if paper_draws is None
        else paper_draws["paper_experiment_s"],
        "paper_experiment_default_eval_cpu_s": None if paper_draws is None
        else paper_draws["paper_experiment_cpu_s"],
        "default_eval_cpu_ratio": None if paper_draws is None
        else paper_draws["paper_experiment_cpu_s"] / paper["paper_experiment_cpu_s"],
        "paper_experiment_learning_only_s": None if paper_learn is None
        else paper_learn["paper_experiment_s"],
        "paper_experiment_learning_only_cpu_s": None if paper_learn is None
        else paper_learn["paper_experiment_cpu_s"],
        "cold_start_s": cold["cold_start_s"],
        "cold_start_cpu_s": cold["cpu_s"],
        "mpcrl_cold_start_s": None if mpcrl_cold_cached is None
        else mpcrl_cold_cached["cold_start_s"],
        "mpcrl_first_day_s": None if mpcrl_cold is None else mpcrl_cold["first_day_s"],
        "mpcrl_first_day_cached_jit_s": None if mpcrl_cold_cached is None
        else mpcrl_cold_cached["first_day_s"],
        "kernel_us_per_problem": None if kernel is None else kernel["kernel_us_per_problem"],
        "batch_us_per_problem": None if kernel is None else kernel["batch_us_per_problem"],
        "kernel_cpu_us_per_problem": None if kernel is None
        else kernel["kernel_cpu_us_per_problem"],
        "batch_cpu_us_per_problem": None if kernel is None
        else kernel["batch_cpu_us_per_problem"],
        "kernel_vs_batch": None if kernel is None else kernel["ratio"],
        **{key: None if kernel is None else kernel.get(key) for key in (
            "kernel_one_thread_cpu_us_per_problem", "kernel_one_thread_cpu_us_per_problem_min",
            "kernel_each_cpu_us_per_problem", "lanes_speedup_cpu", "lanes_same_bits")},
        **{key: None if dec is None else dec[key] for key in (
            "decentralized_n20_s_per_month", "decentralized_n20_cpu_s_per_month",
            "decentralized_n20_reference_s_per_month",
            "decentralized_n20_reference_cpu_s_per_month", "decentralized_n20_ratio",
            "decentralized_n20_ratio_cpu")},
        "scaling": rows,
    })
    for key in ("startup_reference_s", "startup_import_s", "startup_face_s",
                "startup_experiment_s", "paper_command_1_draw_s", "paper_command_10_draws_s",
                "reference_work_s"):
        result[key] = None if commands is None else commands[key]
        result[key[:-2] + "_cpu_s"] = None if commands is None else commands[key[:-2] + "_cpu_s"]
    # the study's keys (the 20x100 ones are null in the smoke run, which runs 4x4)
    study = study or {}
    for key in ("study_20x100_s", "study_20x100_cpu_s", "study_serial_20x100_s",
                "study_serial_20x100_cpu_s", "study_serial_extrapolated",
                "study_serial_seeds_measured", "study_speedup_vs_serial",
                "study_cpu_ratio_vs_serial", "lockstep_cpu_ratio", "study_j_star_s",
                "study_j_star_cpu_s", "study_eval_draws"):
        result[key] = study.get(key)
    for key in ("q_month_s", "q_month_cpu_s", "dpg_month_s", "dpg_month_cpu_s", "q_month_ratio",
                "q_month_ratio_cpu"):
        result[key] = None if qmonth is None else qmonth[key]
    for key in ("checkpoint_share", "checkpoint_share_max", "month_ms_with_dir",
                "month_ms_without_dir", "month_cpu_ms_with_dir", "month_cpu_ms_without_dir",
                "checkpoint_ms_per_month"):
        result[key] = None if checkpoints is None else checkpoints[key]
    search = search or {}
    for key in ("tune_s", "tune_cpu_s", "tune_heldout_s", "one_at_a_time_s",
                "one_at_a_time_cpu_s", "tune_speedup_vs_one_at_a_time"):
        result[key] = search.get(key)
    values = {
        "tune_s": result["tune_s"],
        "speedup_vs_mpcrl": result["speedup_vs_mpcrl"],
        "paper_experiment_s": result["paper_experiment_s"],
        "peak_rss_mb": result["peak_rss_mb"],
        "n100_ms_per_step": _kernel_ms(kernel, 100, 12),
        "study_20x100_s": result["study_20x100_s"],
        "N48_ms_per_step": _kernel_ms(kernel, 3, 48),
        "cold_start_s": result["cold_start_s"],
        "kernel_us_per_problem": result["kernel_us_per_problem"],
        "kernel_cpu_us_per_problem": result["kernel_cpu_us_per_problem"],
        "kernel_one_thread_cpu_us_per_problem": result["kernel_one_thread_cpu_us_per_problem"],
        "decentralized_n20_s_per_month": result["decentralized_n20_s_per_month"],
        "q_month_ratio": result["q_month_ratio"],
        "checkpoint_share": result["checkpoint_share"],
        **{key: result[key] for key in ("startup_import_s", "startup_experiment_s",
                                        "paper_command_1_draw_s", "paper_command_10_draws_s")},
    }
    targets = {}
    for name, (op, bound) in TARGETS.items():
        v = values[name]
        met = None if v is None else (v >= bound if op == ">=" else v <= bound)
        targets[name] = {"value": v, "target": f"{op} {bound:g}", "met": met}
    result["targets"] = targets
    info["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    result["machine"] = info
    result["details"] = {
        "ours": ours, "ours_no_warm_start": ours_cold, "mpcrl": mpcrl,
        "mpcrl_bounds_in_lbx": mpcrl_lbx, "mpcrl_cold_fresh_numba": mpcrl_cold,
        "mpcrl_cold_cached_numba": mpcrl_cold_cached, "paper": paper,
        "paper_default_eval": paper_draws,
        "paper_learning_only": paper_learn, "cold": cold, "kernel": kernel,
        "decentralized": dec, "study": study, "commands": commands, "q_month": qmonth,
        "checkpoints": checkpoints,
        "figure": None if figure is None else str(figure),
    }
    result["total_s"] = time.perf_counter() - t_start
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="mpcrl_lite benchmarks (prints one JSON line)")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 1 month, 3 months of the paper run (extrapolated), "
                             "fewer scaling sizes")
    parser.add_argument("--skip-mpcrl", action="store_true", help="leave out the mpcrl comparison")
    parser.add_argument("--out", type=Path,
                        help="also write the JSON to this file (make bench: "
                             "benchmarks/results/bench-<date>.json, git-ignored)")
    args = parser.parse_args(argv)
    result = run(quick=args.quick, skip_mpcrl=args.skip_mpcrl)
    line = json.dumps(result)
    print(line, flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(line + "\n")
    print()
    print(bench_learning.scaling_table(result["scaling"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
