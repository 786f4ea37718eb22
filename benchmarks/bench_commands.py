"""What a user waits for: the start-up and the paper's run as commands, whole processes.

Every figure is a fresh ``python`` process timed from outside (wall clock around it, CPU as
the user + system time the operating system accounts to the finished child, as
``/usr/bin/time`` reports them), median over ``--trials`` runs after one warm-up run:

* **start-up**: ``python -c "import mpcrl_lite"`` (``startup_import_s``), the same importing the
  public names (``startup_face_s``), and ``Experiment()`` built, ready to solve
  (``startup_experiment_s``);
* **the paper's run**: ``python -m mpcrl_lite learn --months 100 --eval-draws 1 --no-figures``
  (``paper_command_1_draw_s``) and with the default ten evaluation draws
  (``paper_command_10_draws_s``), start-up and monthly checkpoints included.

Beside them, in the same run, two references: ``python -c "import numpy"`` (what any
process of the package pays before its own code: the interpreter and numpy) and a fixed
CPU-bound workload of about a second (``reference_work_s``: numpy products and a Python
loop, the same in every version of the package). A figure divided by its reference
(``*_vs_reference``) moves less with the machine's speed than the figure itself; the load
average at the start and the end says how busy the machine was.

    .venv/bin/python benchmarks/bench_commands.py [--quick] [--trials 3]

``--quick`` runs 5 months instead of 100 (a smoke run: ``paper_command_*`` are then the
figures of those 5 months, start-up included, not comparable with the targets). Prints one
JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import REPO, median, python_env

#: A fixed amount of CPU work (numpy and plain Python), the yardstick of the machine's speed.
REFERENCE_WORK = r"""
import numpy as np
rng = np.random.default_rng(0)
a = rng.standard_normal((200, 200))
for _ in range(150):
    a = np.tanh(a @ a.T / 200.0)
s = 0
for i in range(3_000_000):
    s += i % 7
print(float(a.sum()) + s)
"""

STARTUP = {
    "startup_reference_s": "import numpy",
    "startup_import_s": "import mpcrl_lite",
    "startup_face_s": ("from mpcrl_lite import Experiment, History, LearningConfig, MPCConfig, "
                       "Prices, SystemConfig, Theta"),
    "startup_experiment_s": "from mpcrl_lite import Experiment\nExperiment()",
}


def timed(argv: list[str], trials: int, warmup: int = 1, fresh_dir: bool = False) -> dict:
    """Median wall and CPU seconds of the process ``argv`` (``{OUT}`` replaced by a new
    empty directory for every run when ``fresh_dir``)."""
    walls, cpus = [], []
    for k in range(warmup + trials):
        with tempfile.TemporaryDirectory(prefix="mpcrl_lite-bench-") as tmp:
            args = [a.replace("{OUT}", str(Path(tmp) / "run")) for a in argv] if fresh_dir \
                else argv
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            proc = subprocess.run(args, capture_output=True, text=True, env=python_env(),
                                  cwd=str(REPO), timeout=3600)
            wall = time.perf_counter() - t0
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(args)} failed ({proc.returncode}): "
                               f"{proc.stderr[-2000:]}")
        if k >= warmup:
            walls.append(wall)
            cpus.append((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))
    return {"wall_s": median(walls), "cpu_s": median(cpus), "walls": walls, "cpus": cpus}


def run(quick: bool = False, trials: int = 3) -> dict:
    python = sys.executable
    out: dict = {"loadavg_start": [round(x, 2) for x in os.getloadavg()], "quick": quick}
    reference = timed([python, "-c", REFERENCE_WORK], trials)
    out["reference_work_s"], out["reference_work_cpu_s"] = reference["wall_s"], reference["cpu_s"]
    for key, code in STARTUP.items():
        figure = timed([python, "-c", code], trials)
        out[key], out[key[:-2] + "_cpu_s"] = figure["wall_s"], figure["cpu_s"]
    for key in ("startup_import_s", "startup_face_s", "startup_experiment_s"):
        out[key.replace("_s", "_vs_reference")] = out[key] / out["startup_reference_s"]
    months = 5 if quick else 100
    for key, extra in (("paper_command_1_draw", ["--eval-draws", "1"]),
                       ("paper_command_10_draws", [])):
        argv = [python, "-m", "mpcrl_lite", "learn", "--months", str(months), "--no-figures",
                "--quiet", "--out", "{OUT}", *extra]
        figure = timed(argv, max(1, trials - 1), fresh_dir=True)
        out[f"{key}_s"], out[f"{key}_cpu_s"] = figure["wall_s"], figure["cpu_s"]
        out[f"{key}_vs_reference"] = out[f"{key}_cpu_s"] / out["reference_work_cpu_s"]
        out[f"{key}_runs"] = figure["walls"]
    out["paper_command_months_run"] = months
    out["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 months instead of 100")
    parser.add_argument("--trials", type=int, default=3, help="counted runs per figure")
    args = parser.parse_args(argv)
    print(json.dumps(run(quick=args.quick, trials=args.trials)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
