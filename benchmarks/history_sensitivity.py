"""How far a change in the last bits of one month moves the default run's History.

Issue 22 allows a speed-up that changes rounding (a compiled reduction, say) if the default
100-month run's History stays within 1e-9 relative. Whether any such change can stay within
that depends on how the learning loop carries a rounding difference from month to month:
the month's theta decides the next month's actions, whose samples decide the next update.
This script measures it. It runs the default experiment (``Experiment()``: the shipped
month, the paper's class, the default critic and evaluation) several times in this process,
each with one change:

* ``reference``: nothing changed;
* ``weights*(1+EPS)``: every month the critic's fitted weights ``(w, v)`` are multiplied by
  ``1 + EPS`` (a change of a few units in the last place for ``EPS = 1e-15``), the smallest
  change a different rounding of the LSTD fit could make;
* ``lstd by LU``: the LSTD system solved by an LU factorisation (``numpy.linalg.solve``)
  instead of the least-squares solve (``numpy.linalg.lstsq``, SVD), a faster solve of the same
  well-posed system that rounds differently.

For each, against the reference: the first month whose theta differs, and the largest
difference of each History series relative to that series' largest magnitude, after 10, 50
and 100 months, plus the largest elementwise relative difference in the last month's arrays
(entries above 1e-6 in magnitude).

``python benchmarks/history_sensitivity.py [--months 100] [--eps 1e-15]``; prints one JSON
line (a few minutes: one learning run per variant). A measurement, not a package option: it
replaces ``mpcrl_lite.learning.lstd`` functions in its own process.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from typing import Any

import numpy as np

from mpcrl_lite.learning import lstd
from mpcrl_lite.learning.experiment import Experiment

SERIES = ("J", "J_eval", "theta", "grad_norm", "max_P_applied")
CHECK_MONTHS = (10, 50, 100)


@contextmanager
def patched(name: str, replacement: Callable[..., Any]):
    """``lstd.<name>`` replaced for the ``with`` block."""
    original = getattr(lstd, name)
    setattr(lstd, name, replacement(original))
    try:
        yield
    finally:
        setattr(lstd, name, original)


def scaled_weights(eps: float) -> Callable[[Callable], Callable]:
    def wrap(solve: Callable) -> Callable:
        def solve_scaled(*args: Any, **kwargs: Any):
            x, info = solve(*args, **kwargs)
            return x * (1.0 + eps), info
        return solve_scaled
    return wrap


def lu_solve(lstsq: Callable) -> Callable:
    """``numpy.linalg.lstsq``'s signature and outputs, the solution from an LU solve (the
    singular values, which the fit's diagnostics report, still from the SVD)."""
    def solve(a: np.ndarray, b: np.ndarray, rcond: Any = None):
        _, _, rank, singular = lstsq(a, b, rcond=rcond)
        return np.linalg.solve(a, b), np.zeros(0), rank, singular
    return solve


@contextmanager
def lstd_by_lu():
    original = lstd.np.linalg.lstsq

    class _Linalg:  # the module's ``np.linalg`` seen through a proxy with another lstsq
        def __getattr__(self, key: str) -> Any:
            return lu_solve(original) if key == "lstsq" else getattr(np.linalg, key)

    class _Numpy:
        linalg = _Linalg()

        def __getattr__(self, key: str) -> Any:
            return getattr(np, key)

    lstd.np = _Numpy()
    try:
        yield
    finally:
        lstd.np = np


def run(months: int) -> Any:
    exp = Experiment()
    exp.eval_worker = False  # every run in this process, as the reference
    return exp.run(months=months, progress=False)


def relative(a: Any, b: Any) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = np.nanmax(np.abs(a)) if a.size else 0.0
    if a.shape != b.shape:
        return float("inf")
    return float(np.nanmax(np.abs(a - b)) / scale) if scale > 0 else 0.0


def compare(ref: Any, other: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    theta_ref, theta_other = np.asarray(ref.theta), np.asarray(other.theta)
    differs = np.flatnonzero((theta_ref != theta_other).reshape(len(theta_ref), -1).any(axis=1))
    out["first_month_theta_differs"] = int(differs[0]) if differs.size else None
    for months in CHECK_MONTHS:
        if months > ref.months:
            continue
        row = {}
        for key in SERIES:
            series_ref, series_other = getattr(ref, key), getattr(other, key)
            if key == "J_eval":  # evaluated every eval_every months
                keep = [i for i, m in enumerate(ref.eval_month) if m < months]
                series_ref = [series_ref[i] for i in keep]
                series_other = [series_other[i] for i in keep]
            else:
                series_ref, series_other = series_ref[:months], series_other[:months]
            row[key] = relative(series_ref, series_other)
        out[f"relative_after_{months}_months"] = row
    last = {}
    ref_arrays, other_arrays = ref.last_month.arrays("last"), other.last_month.arrays("last")
    for key, value in ref_arrays.items():
        value = np.asarray(value)
        if value.dtype.kind != "f":
            continue
        big = np.abs(value) > 1e-6
        if big.any():
            diff = np.abs(value - np.asarray(other_arrays[key]))[big] / np.abs(value[big])
            last[key] = float(diff.max())
    out["last_month_elementwise_max"] = dict(sorted(last.items(), key=lambda kv: -kv[1])[:4])
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--months", type=int, default=100)
    parser.add_argument("--eps", type=float, default=1e-15)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    reference = run(args.months)
    again = run(args.months)
    result: dict[str, Any] = {"months": args.months, "eps": args.eps,
                              "reference_repeats_bit_for_bit":
                                  compare(reference, again)["first_month_theta_differs"] is None}
    with patched("_solve", scaled_weights(args.eps)):
        result[f"weights*(1+{args.eps:g})"] = compare(reference, run(args.months))
    with lstd_by_lu():
        result["lstd by LU"] = compare(reference, run(args.months))
    result["wall_s"] = time.perf_counter() - t0
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
