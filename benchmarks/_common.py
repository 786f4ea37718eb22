"""Small helpers shared by the benchmark scripts (timing, subprocesses, machine facts).

Nothing here is part of the package; the benchmarks import it as a sibling module.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
REPO = BENCH_DIR.parent


def python_env() -> dict[str, str]:
    """Environment for child processes: the repository and this folder on the path, one
    BLAS thread per process unless the caller chose otherwise, headless matplotlib."""
    env = dict(os.environ)
    paths = [str(REPO), str(BENCH_DIR)]
    if env.get("PYTHONPATH"):
        paths.append(env["PYTHONPATH"])
    env["PYTHONPATH"] = os.pathsep.join(paths)
    env.setdefault("MPLBACKEND", "Agg")
    return env


def run_json(code: str, timeout: float = 3600.0, env: dict[str, str] | None = None,
             python: str | None = None) -> dict[str, Any]:
    """Run ``code`` in a fresh interpreter and parse the last line of its stdout as JSON.

    The child's own wall clock and ``ru_maxrss`` are what the caller usually wants, so the
    code is expected to print them itself; a failure raises with the child's stderr.
    """
    proc = subprocess.run(
        [python or sys.executable, "-c", code],
        capture_output=True, text=True, timeout=timeout, env=env or python_env(), cwd=str(REPO),
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"benchmark subprocess failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}"
        )
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    if not lines:
        raise RuntimeError(f"benchmark subprocess printed nothing; stderr:\n{proc.stderr[-4000:]}")
    return json.loads(lines[-1])


def median(values: list[float]) -> float:
    values = sorted(values)
    k = len(values)
    if k == 0:
        return float("nan")
    mid = k // 2
    return values[mid] if k % 2 else 0.5 * (values[mid - 1] + values[mid])


def timeit_ms(fn, repeat: int = 5, min_time: float = 0.2) -> tuple[float, list[float]]:
    """Median wall time of ``fn()`` in ms over ``repeat`` rounds (each round runs ``fn``
    until ``min_time`` seconds have passed and reports the mean of that round)."""
    rounds = []
    for _ in range(repeat):
        calls, t0 = 0, time.perf_counter()
        while True:
            fn()
            calls += 1
            elapsed = time.perf_counter() - t0
            if elapsed >= min_time:
                break
        rounds.append(1e3 * elapsed / calls)
    return median(rounds), rounds


def machine() -> dict[str, Any]:
    """What the figures were measured on: CPU, cores, load, library versions."""
    info: dict[str, Any] = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cores": os.cpu_count(),
    }
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    info["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        info["loadavg"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    for name in ("numpy", "scipy", "casadi"):
        try:
            module = __import__(name)
            info[name] = getattr(module, "__version__", "?")
        except ImportError:
            pass
    return info


def print_result(result: dict[str, Any]) -> int:
    """Print ``result`` as ONE JSON line, with the load average at the end of the run added
    to ``result["machine"]``; returns the exit status 0."""
    try:
        result["machine"]["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    print(json.dumps(result))
    return 0
