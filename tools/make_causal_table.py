"""Solve the causal DP (``mpcrl_lite.bounds.causal.dp.causal_optimum``) for the systems the notebooks use
and store J* of every day in ``data/causal_j_star.csv``, its provenance in the file's header
lines (``# key: JSON value``).

J* depends only on the system and the day's prices (not on any learned theta, seed or noise
draw), and the paper's month takes about a minute of CPU per system; the notebooks read the
stored values through :func:`mpcrl_lite.bounds.causal.table.stored_bound` instead of solving the same
DP on every run. ``tests/bounds/test_causal_table.py`` solves some days again and compares.

    PYTHONPATH=$PWD python tools/make_causal_table.py            # the notebooks' systems
    PYTHONPATH=$PWD python tools/make_causal_table.py --sites    # their sites (notebook 06)

``--sites`` writes ``data/causal_j_star_sites.csv`` instead: J* of every day for the sites of
:data:`SITES` (systems with batteries of their own), keyed by
:func:`mpcrl_lite.bounds.causal.table.site_key`.
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
from mpcrl_lite.bounds.causal.table import SITES_CSV, TABLE_CSV, site_key
from mpcrl_lite.config import SystemConfig
from mpcrl_lite.system.prices import DATA_DIR, Prices

#: (P_bar, noise variance) of notebook 07's default grid; (1.5, 0.5) is the paper's system.
SYSTEMS = [(p, v) for p in (1.0, 1.5, 2.0) for v in (0.2, 0.5)]
#: The sites of the notebooks (name: system): notebook 06's mixed site (section 4, its
#: default ``P_BAR``).
SITES = {"notebook 06, mixed site": SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12),
                                                 noise_var=(1.0, 0.5, 0.5), P_bar=1.5)}


def _provenance_header(what: str, function: str, commit: str, runs: list) -> str:
    provenance = {
        "what": what,
        "function": function,
        "tool": "tools/make_causal_table.py",
        "commit": commit,
        "mpcrl_lite": __version__,
        "computed": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "system_defaults": SystemConfig().to_dict(),
        "runs": runs,
    }
    return "".join(f"# {key}: {json.dumps(value)}\n" for key, value in provenance.items())


def _solve(system: SystemConfig, args: argparse.Namespace) -> tuple[dict, list[float]]:
    t0, c0 = time.perf_counter(), time.process_time()
    bound = causal_optimum(system, Prices.default(system), grid=args.grid,
                           action_step=args.action_step, keep_values=False)
    run = {"J_star": bound.J_star, "wall_s": round(time.perf_counter() - t0, 1),
           "cpu_s": round(time.process_time() - c0, 1), **bound.info}
    return run, np.asarray(bound.J_star_per_day).tolist()


def write_table(name: str, columns: str, what: str, entries: list, args: argparse.Namespace,
                commit: str) -> None:
    """Solve every entry ``(fields, prefix, system)`` and write ``name`` in ``args.out``:
    the provenance header, then ``columns`` and the rows ``prefix,grid,action_step,day,J_star``
    (``fields`` describe the entry in the header's ``runs``)."""
    rows, runs = [], []
    for fields, prefix, system in entries:
        run, per_day = _solve(system, args)
        runs.append({**fields, **run})
        print(runs[-1], flush=True)
        rows += [f"{prefix},{args.grid},{args.action_step!r},{d},{j!r}"
                 for d, j in enumerate(per_day)]
    header = _provenance_header(
        "J* of every day (V_0(soc0) of the coupled causal DP, NOK/day) for " + what
        + ", on the days of Prices.default(system)",
        "mpcrl_lite.bounds.causal.dp.causal_optimum(system, Prices.default(system), "
        f"grid={args.grid}, action_step={args.action_step}, keep_values=False)", commit, runs)
    (args.out / name).write_text(header + columns + "\n" + "\n".join(rows) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DATA_DIR)
    parser.add_argument("--grid", type=int, default=41)
    parser.add_argument("--action-step", type=float, default=0.1)
    parser.add_argument("--sites", action="store_true",
                        help=f"the sites of SITES into {SITES_CSV} instead")
    args = parser.parse_args()
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            check=False).stdout.strip() or "unknown"
    if args.sites:
        # the key is JSON with commas: a quoted CSV field
        entries = [({"site": name, "key": site_key(system)},
                    '"' + site_key(system).replace('"', '""') + '"', system)
                   for name, system in SITES.items()]
        write_table(SITES_CSV, "site,grid,action_step,day,J_star",
                    "the notebooks' sites, the systems of the key (the fields that differ "
                    "from SystemConfig())", entries, args, commit)
        return
    entries = [({"P_bar": P_bar, "noise_var": noise_var}, f"{P_bar!r},{noise_var!r}",
                SystemConfig(P_bar=P_bar, noise_var=noise_var)) for P_bar, noise_var in SYSTEMS]
    write_table(TABLE_CSV, "P_bar,noise_var,grid,action_step,day,J_star",
                "the systems SystemConfig(P_bar=..., noise_var=...) with all other fields at "
                "their defaults", entries, args, commit)


if __name__ == "__main__":
    main()
