"""Solve the causal DP (``mpcrl_lite.bounds.causal.dp.causal_optimum``) for the systems the notebooks use
and store J* of every day in ``data/causal_j_star.csv``, its provenance in the file's header
lines (``# key: JSON value``).

J* depends only on the system and the day's prices (not on any learned theta, seed or noise
draw), and the paper's month takes about a minute of CPU per system; the notebooks read the
stored values through :func:`mpcrl_lite.bounds.causal.table.stored_bound` instead of solving the same
DP on every run. ``tests/bounds/test_causal_table.py`` solves some days again and compares.

    PYTHONPATH=$PWD python tools/make_causal_table.py            # the notebooks' systems
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

from mpcrl_lite import __version__
from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.causal.table import TABLE_CSV
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.system.prices import DATA_DIR, Prices

#: (P_bar, noise variance) of notebook 07's default grid; (1.5, 0.5) is the paper's system.
SYSTEMS = [(p, v) for p in (1.0, 1.5, 2.0) for v in (0.2, 0.5)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DATA_DIR)
    parser.add_argument("--grid", type=int, default=41)
    parser.add_argument("--action-step", type=float, default=0.1)
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            check=False).stdout.strip() or "unknown"
    rows, runs = [], []
    for P_bar, noise_var in SYSTEMS:
        system = SystemConfig(P_bar=P_bar, noise_var=noise_var)
        prices = Prices.default(system)
        t0, c0 = time.perf_counter(), time.process_time()
        bound = causal_optimum(system, prices, grid=args.grid, action_step=args.action_step,
                               keep_values=False)
        runs.append({"P_bar": P_bar, "noise_var": noise_var, "J_star": bound.J_star,
                     "wall_s": round(time.perf_counter() - t0, 1),
                     "cpu_s": round(time.process_time() - c0, 1), **bound.info})
        print(runs[-1], flush=True)
        rows += [f"{P_bar!r},{noise_var!r},{args.grid},{args.action_step!r},{d},{j!r}"
                 for d, j in enumerate(np.asarray(bound.J_star_per_day).tolist())]
    provenance = {
        "what": "J* of every day (V_0(soc0) of the coupled causal DP, NOK/day) for the systems "
                "SystemConfig(P_bar=..., noise_var=...) with all other fields at their defaults, "
                "on the days of Prices.default(system)",
        "function": "mpcrl_lite.bounds.causal.dp.causal_optimum(system, Prices.default(system), "
                    f"grid={args.grid}, action_step={args.action_step}, keep_values=False)",
        "tool": "tools/make_causal_table.py",
        "commit": commit,
        "mpcrl_lite": __version__,
        "computed": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "system_defaults": SystemConfig().to_dict(),
        "runs": runs,
    }
    header = "".join(f"# {key}: {json.dumps(value)}\n" for key, value in provenance.items())
    (args.out / TABLE_CSV).write_text(header + "P_bar,noise_var,grid,action_step,day,J_star\n"
                                      + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
