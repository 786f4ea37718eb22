r"""A multi-seed study: the same learning run for many seeds, judged on the evaluation draws.

One learning run shows one seed; whether the learning *works* is a statement over seeds.
:func:`run_study` runs seeds ``seed_start .. seed_start + seeds - 1`` of the default
experiment (or of ``base`` overrides) through the sweep machinery
(:func:`mpcrl_lite.studies.sweep.api.run_sweep` with a grid over ``learning.seed``: serial or on Dask,
every run resumable from its monthly checkpoint, a failed seed recorded in its row without
stopping the others) and judges every run by its evaluation series ``History.J_eval`` (the
mean of ``LearningConfig.eval_draws`` fixed noise draws, the same draws for every seed and
every month: common random numbers).

Convergence (the documented parameter ``threshold``, default 0.9): with ``J_nom`` the
nominal MPC's J (the evaluation of month 0, whose theta is the nominal one; equal for all
seeds) and a target ``J_target``, a seed *converges* when its final evaluation closes at
least ``threshold`` of the gap,

.. math::
   \frac{J_{nom} - J_{eval,final}}{J_{nom} - J_{target}} \ge \text{threshold}.

``J_target`` is the best causal policy's J*. When it is not given (``J_star``),
:func:`run_study` computes it for the study's system and month (``target='causal'``, the
default; :func:`causal_target`): the coupled dynamic program of :mod:`mpcrl_lite.bounds.causal.dp`
where it is exact enough to run (``n <= 3``: seconds per day of prices), else the Lagrangian
lower bound of :mod:`mpcrl_lite.bounds.causal.dual`; if neither can be solved for the system, or
with ``target='best_seen'``, the target is the best ``J_eval`` any seed reached in any month
(then at least one seed's curve touches the target, and the fraction measures how many seeds
end near the best seen). ``study.json`` says which (``J_star_method``, ``J_star_note``).

Every seed is also judged by

* its **regret** ``J_eval_final - J_target`` (NOK/day: what a causal policy could still gain);
* its **late collapse**: ``(J_eval_final - J_eval_best) / (J_nom - J_target)``, the share of
  the gap lost between its best evaluation and its last one; a seed collapses late when
  this exceeds :data:`LATE_COLLAPSE` (5 %).

Written into ``out`` next to the sweep's files (``runs/``, ``results.csv``, ``sweep.json``):

* ``study.csv`` -- one row per seed (:data:`SEED_COLUMNS`);
* ``study_curves.csv`` -- tidy learning curves: one row per (seed, evaluated month) with
  ``J_eval`` and its confidence interval over the draws;
* ``study.json`` -- the summary (:func:`summarize`);
* ``study_j_star.json`` -- the computed J* and what it was computed for (reused when the
  study is run again on the same system and prices);
* ``study_curves.png`` -- every seed's ``J_eval`` curve and their median over seeds.

With a ``tune`` result of the study's class (``class_best``) the regret is split in two
(:func:`class_split`): the learner's part against the class's best theta, on the search's
held-out draws (``learner_gap``) and paired on the runs' own evaluation draws
(``learner_gap_paired``: :func:`class_on_run_draws`, the figure without the draws' noise).
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from .._util import jsonio
from .._util.budget import Budget, check_estimate, learning_estimate
from .._util.stats import mean_ci
from .._util.validate import check_instance, check_int
from ..bounds.baselines import load_class_best
from ..bounds.causal.dual import lagrangian_bound
from ..bounds.causal.table import causal_bound
from ..config import SystemConfig
from ..learning import durable, outdir
from ..learning.checkpoint import prices_fingerprint
from ..learning.experiment import Experiment
from ..learning.history import History
from ..sim.closed_loop import draw_J
from ..system.prices import Prices
from ..theta import Theta
from .sweep.api import run_sweep
from .sweep.grid import load_grid
from .sweep.store import check_out_dir

__all__ = ["LATE_COLLAPSE", "SEED_COLUMNS", "TARGETS", "THRESHOLD", "causal_target",
           "class_on_run_draws", "class_split", "gap_closed", "plot_curves", "run_study",
           "seed_band", "seed_row", "segment_on_run_draws", "summarize", "updates_to_close"]

log = logging.getLogger("mpcrl_lite.studies.study")

#: Default share of the gap ``J_nom - J_target`` a seed must close to count as converged.
THRESHOLD = 0.9
#: Largest share of the gap ``J_nom - J_target`` a seed may lose between its best evaluation
#: and its final one (more is a late collapse).
LATE_COLLAPSE = 0.05
#: What :func:`run_study` judges against when ``J_star`` is not given: ``'causal'`` (J*
#: computed, :func:`causal_target`) or ``'best_seen'`` (the best J_eval of any seed).
TARGETS = ("causal", "best_seen")
#: File of the computed J* in a study's directory.
J_STAR_FILE = "study_j_star.json"
#: Columns of ``study.csv``, one row per seed.
SEED_COLUMNS = (
    "seed", "run_id", "status", "error", "months", "evaluations", "J_eval_nominal",
    "J_eval_final", "J_eval_final_ci_low", "J_eval_final_ci_high", "J_eval_best",
    "best_month", "late_regression", "gap_closed", "converged", "max_P_applied",
    "hours_above_P_bar_last", "regret", "late_regression_share", "late_collapse",
)


def gap_closed(J_final: float, J_nominal: float, J_target: float) -> float:
    """Share of the gap ``J_nominal - J_target`` closed by ``J_final`` (1 at the target, 0
    at the nominal MPC, negative when worse than nominal; NaN when the gap is not
    positive or a value is not finite)."""
    gap = J_nominal - J_target
    if not (math.isfinite(gap) and math.isfinite(J_final)) or gap <= 0:
        return math.nan
    return (J_nominal - J_final) / gap


def seed_row(history: History) -> dict[str, Any]:
    """The figures of one run that do not depend on the other seeds.

    ``J_eval_nominal`` is the evaluation of month 0 (the nominal theta; for runs started at
    ``LearningConfig.theta0`` :func:`run_study` moves it to ``J_eval_start`` and puts the
    nominal theta's J on the same draws in its place), ``J_eval_final``
    the last evaluation (with its confidence interval over the draws), ``J_eval_best`` the
    lowest evaluation and ``best_month`` its month (from 0), ``late_regression`` =
    ``J_eval_final - J_eval_best`` >= 0 (how much the final parameters lost against the best
    ones seen), ``max_P_applied`` the largest applied grid power over all months.
    """
    J = np.asarray(history.J_eval, dtype=float)
    row: dict[str, Any] = {"months": history.months, "evaluations": int(J.size)}
    if J.size and 0 in history.eval_month:
        row["J_eval_nominal"] = float(J[history.eval_month.index(0)])
    if J.size:
        best = int(np.nanargmin(J)) if np.isfinite(J).any() else len(J) - 1
        row.update(
            J_eval_final=float(J[-1]),
            J_eval_final_ci_low=float(history.J_eval_ci_low[-1]),
            J_eval_final_ci_high=float(history.J_eval_ci_high[-1]),
            J_eval_best=float(J[best]),
            best_month=int(history.eval_month[best]),
            late_regression=float(J[-1] - J[best]),
        )
    if history.months:
        row["max_P_applied"] = float(np.nanmax(history.max_P_applied))
        row["hours_above_P_bar_last"] = history.hours_above_P_bar[-1]
    return row


def summarize(
    table: pd.DataFrame, J_star: float | None = None, threshold: float = THRESHOLD,
    J_star_method: str = "given", J_star_note: str = "",
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Judge the seeds of ``table`` (rows of :func:`seed_row` with ``seed`` and ``status``).

    Returns the table with ``gap_closed``, ``converged``, ``regret``,
    ``late_regression_share`` and ``late_collapse`` filled in, and the summary of
    ``study.json``: ``seeds``, ``done``, ``failed_seeds``, ``definition`` (the convergence
    rule in words), ``threshold``, ``J_nominal``, ``J_target``, ``target`` ('J_star' or
    'best_J_eval_reached'), ``fraction_converged`` (of the finished seeds),
    ``converged_seeds``, ``J_eval_final_median``, ``J_eval_final_iqr`` ([q25, q75]),
    ``worst_seed`` ({seed, J_eval_final, regret}), ``late_regression`` ({seed: value}) and
    ``largest_late_regression`` ({seed, value}); and, against the target, ``J_star`` (None
    without one), ``J_star_method`` and ``J_star_note`` (how J* was obtained, as given),
    ``regret`` ({seed: J_eval_final - J_target}), ``regret_median``, ``regret_iqr``
    ([q25, q75]), ``late_collapse_limit`` (:data:`LATE_COLLAPSE`), ``late_regression_share``
    ({seed: late_regression / (J_nominal - J_target)}), ``late_collapse_seeds`` (those above
    the limit), ``late_collapse_count`` and ``no_late_collapse`` (True when that count is 0
    and some seed finished); ``no_improvement_seeds`` and ``no_improvement_count``: the
    seeds whose final J_eval is no lower than their J_eval at month 0 (on the same draws:
    they learned nothing usable; ``J_eval_start`` where the table has it). Statistics are
    over the finished seeds with an evaluation; NaN (``null``) when there is none.
    """
    if isinstance(threshold, bool) or not (isinstance(threshold, (int, float))
                                           and 0 < threshold <= 1):
        raise ValueError(f"threshold={threshold!r}: expected a number in (0, 1]")
    if J_star is not None and not (isinstance(J_star, (int, float)) and math.isfinite(J_star)):
        raise ValueError(f"J_star={J_star!r}: expected a finite number or None")
    table = table.copy()
    for column in ("J_eval_nominal", "J_eval_final", "J_eval_best", "late_regression"):
        if column not in table:
            table[column] = np.nan
    ok = (table["status"] == "done") & table["J_eval_final"].notna()
    good = table[ok]
    J_nominal = float(good["J_eval_nominal"].median()) if len(good) else math.nan
    if J_star is not None:
        J_target, target = float(J_star), "J_star"
    else:
        J_target = float(good["J_eval_best"].min()) if len(good) else math.nan
        target = "best_J_eval_reached"
    closed = [gap_closed(f, J_nominal, J_target) if use else math.nan
              for f, use in zip(table["J_eval_final"], ok)]
    table["gap_closed"] = closed
    table["converged"] = [bool(use and c >= threshold) for c, use in zip(closed, ok)]
    gap = J_nominal - J_target
    table["regret"] = np.where(ok, table["J_eval_final"] - J_target, np.nan)
    share = (table["late_regression"] / gap if math.isfinite(gap) and gap > 0
             else pd.Series(math.nan, index=table.index))
    table["late_regression_share"] = np.where(ok, share, np.nan)
    table["late_collapse"] = [bool(use and v > LATE_COLLAPSE)
                              for v, use in zip(table["late_regression_share"], ok)]
    good = table[ok]
    final = good["J_eval_final"].to_numpy(float)
    regret = good["regret"].to_numpy(float)
    worst = good.loc[good["J_eval_final"].idxmax()] if len(good) else None
    regress = good.set_index("seed")["late_regression"]
    largest = regress.idxmax() if len(regress) else None
    collapsed = [int(s) for s in good.loc[good["late_collapse"], "seed"]]
    # the runs that end no better than they started (the same evaluation draws)
    # (runs started at learning.theta0 are judged against that start, J_eval_start)
    start = "J_eval_start" if "J_eval_start" in good else "J_eval_nominal"
    still = [int(s) for s in good.loc[good["J_eval_final"] >= good[start], "seed"]]
    summary = {
        "seeds": [int(s) for s in table["seed"]],
        "done": int(ok.sum()),
        "failed_seeds": [int(s) for s in table.loc[table["status"] == "failed", "seed"]],
        "definition": (
            f"a seed converges when its final J_eval closes at least {threshold:g} of the "
            "gap between the nominal MPC's J_eval (month 0) and J_target: "
            "(J_nominal - J_eval_final) / (J_nominal - J_target) >= threshold; J_target is "
            + (f"the best causal policy's J* ({J_star_method})" if J_star is not None
               else "the best J_eval reached by any seed in any month")
            + f". A seed collapses late when J_eval_final - J_eval_best exceeds "
            f"{LATE_COLLAPSE:g} of that gap; its regret is J_eval_final - J_target"),
        "threshold": float(threshold),
        "J_nominal": J_nominal,
        "J_target": J_target,
        "target": target,
        "fraction_converged": float(table["converged"][ok].mean()) if len(good) else math.nan,
        "converged_seeds": [int(s) for s in table.loc[table["converged"], "seed"]],
        "J_eval_final_median": float(np.median(final)) if final.size else math.nan,
        "J_eval_final_iqr": ([float(np.percentile(final, 25)), float(np.percentile(final, 75))]
                             if final.size else [math.nan, math.nan]),
        "worst_seed": ({"seed": int(worst["seed"]), "J_eval_final": float(worst["J_eval_final"]),
                        "regret": float(worst["regret"])}
                       if worst is not None else None),
        "late_regression": {str(int(s)): float(v) for s, v in regress.items()},
        "largest_late_regression": ({"seed": int(largest), "value": float(regress[largest])}
                                    if largest is not None else None),
        "J_star": float(J_star) if J_star is not None else None,
        "J_star_method": J_star_method if J_star is not None else None,
        "J_star_note": J_star_note,
        "regret": {str(int(s)): float(v) for s, v in zip(good["seed"], regret)},
        "regret_median": float(np.median(regret)) if regret.size else math.nan,
        "regret_iqr": ([float(np.percentile(regret, 25)), float(np.percentile(regret, 75))]
                       if regret.size else [math.nan, math.nan]),
        "late_collapse_limit": LATE_COLLAPSE,
        # null where there is no gap to share (as study.json writes it)
        "late_regression_share": {str(int(s)): float(v) if math.isfinite(v) else None
                                  for s, v in zip(good["seed"], good["late_regression_share"])},
        "late_collapse_seeds": collapsed,
        "late_collapse_count": len(collapsed),
        "no_late_collapse": bool(len(good)) and not collapsed,
        "no_improvement_seeds": still,
        "no_improvement_count": len(still),
    }
    return table, summary


def causal_target(system: SystemConfig, prices: Prices) -> dict[str, Any]:
    """J* of the best causal policy on ``prices``, by the best method that runs for ``system``.

    The coupled dynamic program (:func:`mpcrl_lite.bounds.causal.dp.causal_optimum`, 41 soc nodes) for
    up to three batteries (identical, or differing: then on the product grid, one soc grid per
    battery), read from the stored table where it covers the system and the
    month (:func:`mpcrl_lite.bounds.causal.table.causal_bound`); beyond, or if it refuses the system, the Lagrangian bound
    (:func:`mpcrl_lite.bounds.causal.dual.lagrangian_bound`); if that is refused too, none.

    Returns
    -------
    dict
        ``J_star`` (NOK/day, None when none could be computed), ``method``
        (``'causal_dp'``, ``'lagrangian_bound'`` or None), ``note`` (what the figure is, in
        words), ``wall_time_s``; with the DP also ``states`` (``'symmetric'`` for identical
        batteries, ``'product'`` for batteries that differ).
    """
    problems = []
    if system.n <= 3:
        try:
            # the stored J* (data/causal_j_star.csv) where it covers the system and month
            bound = causal_bound(system, prices)
        except ValueError as err:
            problems.append(f"causal_optimum: {err}")
        else:
            states = bound.info.get("method", "symmetric")
            where = (" on the product grid of batteries that differ, one soc grid per battery"
                     if states == "product" else "")
            return {"J_star": float(np.mean(bound.J_star_for(prices))), "method": "causal_dp",
                    "states": states,
                    "wall_time_s": bound.wall_time_s, "source": bound.info.get("source"),
                    "note": f"J* is the coupled DP's optimum of the grid model at 41 soc nodes{where} "
                            "(mpcrl_lite.bounds.causal.dp): an estimate, pessimistic by about 2 NOK/day "
                            "for the paper's system (-399.3 against -401.5 refined)"}
    else:
        problems.append(f"causal_optimum: n={system.n} is too large for the exact DP")
    try:
        dual = lagrangian_bound(system, prices)
    except ValueError as err:
        problems.append(f"lagrangian_bound: {err}")
    else:
        return {"J_star": dual.J_bound, "method": "lagrangian_bound",
                "wall_time_s": dual.wall_time_s,
                "note": f"{problems[0]}; J* is replaced by the Lagrangian lower bound "
                        "(mpcrl_lite.bounds.causal.dual), below the true J*: the regret is overstated "
                        "and the gap closed understated"}
    return {"J_star": None, "method": None, "wall_time_s": 0.0,
            "note": f"no causal J* for this system ({'; '.join(problems)}): the target is the "
                    "best J_eval reached by any seed in any month"}


def _study_target(out: Path, system: SystemConfig, prices: Prices) -> dict[str, Any]:
    """:func:`causal_target`, read back from ``out/study_j_star.json`` when it was computed
    for the same system and prices (a rerun of the study does not solve the DP again)."""
    key = {"system": system.to_dict(), "prices": prices_fingerprint(prices)["sha256"]}
    path = out / J_STAR_FILE
    try:
        saved = json.loads(path.read_text())
        if saved.get("for") == jsonio.plain(key):
            return saved["target"]
    except (OSError, ValueError, AttributeError, KeyError):
        pass
    target = causal_target(system, prices)
    out.mkdir(parents=True, exist_ok=True)
    durable.write_json(path, {"for": key, "target": target})
    return target


def updates_to_close(history: History, J_nominal: float, J_target: float,
                     share: float = THRESHOLD) -> int | None:
    """The first evaluated month of ``history`` whose ``J_eval`` closes at least ``share`` of
    the gap ``J_nominal - J_target`` (:func:`gap_closed`), or None when none does.

    Month ``m`` (from 0) is evaluated with the parameters used in that month, i.e. after
    ``m`` updates, so the result is the number of updates the run needed (0: the nominal
    parameters are good enough already). The resolution is ``LearningConfig.eval_every``.
    """
    if isinstance(share, bool) or not (isinstance(share, (int, float)) and 0 < share <= 1):
        raise ValueError(f"share={share!r}: expected a number in (0, 1]")
    for month, J in zip(history.eval_month, history.J_eval):
        closed = gap_closed(float(J), J_nominal, J_target)
        if math.isfinite(closed) and closed >= share:
            return int(month)
    return None


def seed_band(histories: Sequence[History], level: float = 0.95
              ) -> dict[str, np.ndarray]:
    """Mean ``J_eval`` over the seeds of ``histories`` at every evaluated month, with its
    Student-t interval over the seeds (:func:`mpcrl_lite._util.stats.mean_ci`).

    The runs must have been evaluated at the same months (the same ``months`` and
    ``eval_every``); with one seed the interval is NaN.

    Returns
    -------
    dict
        ``month`` (evals,) from 0, ``mean``, ``ci_low``, ``ci_high`` (evals,), ``J_eval``
        (seeds, evals) and ``seeds`` (the number of runs).
    """
    histories = list(histories)
    if not histories:
        raise ValueError("histories is empty: expected at least one run")
    months = list(histories[0].eval_month)
    for h in histories[1:]:
        if list(h.eval_month) != months:
            raise ValueError(f"the runs were evaluated at different months ({months} and "
                             f"{list(h.eval_month)}); expected the same months and eval_every")
    J = np.asarray([h.J_eval for h in histories], dtype=float).reshape(len(histories), -1)
    cis = [mean_ci(J[:, j], level) for j in range(J.shape[1])]
    return {"month": np.asarray(months, dtype=int),
            "mean": np.array([c.mean for c in cis]),
            "ci_low": np.array([c.ci_low for c in cis]),
            "ci_high": np.array([c.ci_high for c in cis]),
            "J_eval": J, "seeds": len(histories)}


def curves_table(histories: Mapping[int, History]) -> pd.DataFrame:
    """Tidy learning curves: ``seed``, ``month`` (from 0), ``J_eval``, ``J_eval_ci_low``,
    ``J_eval_ci_high``, one row per seed and evaluated month."""
    rows = [
        {"seed": seed, "month": m, "J_eval": J, "J_eval_ci_low": lo, "J_eval_ci_high": hi}
        for seed, h in histories.items()
        for m, J, lo, hi in zip(h.eval_month, h.J_eval, h.J_eval_ci_low, h.J_eval_ci_high)
    ]
    return pd.DataFrame(rows, columns=["seed", "month", "J_eval", "J_eval_ci_low",
                                       "J_eval_ci_high"])


def plot_curves(curves: pd.DataFrame, J_target: float | None = None,
                ax: Any = None) -> Any:
    """Every seed's ``J_eval`` against the month (thin) and their median over the seeds
    (thick; at the months every seed evaluated). Line gids ``"seed=<s>"`` and ``"median"``;
    ``J_target`` (if finite) as a dotted line of gid ``"J_target"``. Returns the figure."""
    if ax is None:
        fig, ax = plt.subplots(figsize=(7.0, 4.0))
    else:
        fig = ax.figure
    for seed, group in curves.groupby("seed"):
        ax.plot(group["month"] + 1, group["J_eval"], color="0.6", lw=0.8, gid=f"seed={seed}")
    if len(curves):
        seeds = curves["seed"].nunique()
        wide = curves.pivot_table(index="month", columns="seed", values="J_eval")
        median = wide[wide.notna().sum(axis=1) == seeds].median(axis=1)
        ax.plot(median.index + 1, median.to_numpy(), color="black", lw=2.4, gid="median",
                label=f"median of {seeds} seeds")
    if J_target is not None and math.isfinite(J_target):
        ax.axhline(J_target, color="tab:green", ls=":", lw=1.5, gid="J_target",
                   label="J_target")
    ax.set_xlabel("RL step (month)")
    ax.set_ylabel("J_eval (mean over the evaluation draws)")
    ax.set_title("Learning curves of all seeds", loc="left", fontsize=11)
    ax.grid(True, color="0.9", lw=0.6)
    if len(curves):
        ax.legend(fontsize=8)
    return fig


def _check_study_budget(seeds: int, months: int, seed_start: int, base: Mapping[str, Any],
                        workers: int | None, scheduler: str | None) -> None:
    """The study's runs against the machine before the seed list is even built
    (:func:`mpcrl_lite.studies.sweep.api.check_sweep_budget` for one seed, times the seeds)."""
    one = load_grid({"base": {**base, "learning.months": int(months)},
                     "grid": {"learning.seed": [int(seed_start)]}})
    run = one.runs[0]
    budget = learning_estimate(run.system.n, run.learning.days_per_month, int(months),
                               run.learning.eval_draws, run.learning.eval_every, run.system.N)
    remote = scheduler not in (None, "serial") and workers is None
    slots = 1 if scheduler == "serial" or workers == 0 else (workers or 2)
    seconds = 0.0 if remote else budget.seconds * int(seeds) / slots
    check_estimate(f"seeds={seeds}, months={months} (days_per_month "
                   f"{run.learning.days_per_month}, n {run.system.n})",
                   Budget(budget.memory, seconds))


def run_study(
    seeds: int,
    months: int,
    out: str | os.PathLike,
    seed_start: int = 0,
    base: Mapping[str, Any] | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    J_star: float | None = None,
    threshold: float = THRESHOLD,
    progress: bool = True,
    lockstep: int | None = None,
    target: str = "causal",
    class_best: str | os.PathLike | None = None,
) -> dict[str, Any]:
    """Run (or resume) the study and write its files into ``out``; returns the summary.

    Parameters
    ----------
    seeds, months
        Number of seeds (``>= 1``) and months per run (``>= 1``).
    out
        Output directory (the sweep's layout plus the study's files, see the module
        docstring).
    seed_start
        The first seed (``>= 0``); the seeds are ``seed_start .. seed_start + seeds - 1``.
    base
        More overrides of every run, as the sweep's ``base`` (e.g.
        ``{"learning.days_per_month": 5}``); ``learning.seed`` and ``learning.months`` are
        set here.
    workers, scheduler
        As for :func:`mpcrl_lite.studies.sweep.api.run_sweep` (default: a local Dask cluster of 2
        workers; ``workers=0`` or ``scheduler='serial'``: in this process).
    J_star, threshold
        The convergence rule (:func:`summarize`). Without ``J_star`` the target is set by
        ``target``.
    progress
        Show the sweep's progress bar.
    lockstep
        Runs per task, stepped together in one process (:func:`mpcrl_lite.studies.sweep.api.run_sweep`;
        default each worker's share of the seeds).
    target
        One of :data:`TARGETS`: ``'causal'`` (default) computes J* for the study's system and
        month before any run starts (:func:`causal_target`; kept in ``study_j_star.json``),
        ``'best_seen'`` judges against the best J_eval reached.
    class_best
        A ``tune`` output directory of the study's system and forecast: the summary then has
        ``class_split`` (:func:`class_split`), the regret split into the learner's and the
        class's parts.
    """
    for name, value, low in (("seeds", seeds, 1), ("months", months, 1),
                             ("seed_start", seed_start, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name}={value!r}: expected an integer >= {low}")
    if target not in TARGETS:
        raise ValueError(f"target={target!r}: expected one of {', '.join(map(repr, TARGETS))}")
    base = dict(base or {})
    clash = [k for k in base if k in ("learning.seed", "learning.months")]
    if clash:
        raise ValueError(f"base sets {clash}: the study sets the seeds and the months itself")
    _check_study_budget(seeds, months, seed_start, base, workers, scheduler)
    seed_list = list(range(int(seed_start), int(seed_start) + int(seeds)))
    grid = {"base": {**base, "learning.months": int(months)}, "grid": {"learning.seed": seed_list}}
    # the convergence rule is checked before any run starts
    summarize(pd.DataFrame({"seed": [], "status": []}), J_star, threshold)
    out = Path(outdir.refuse_empty(out))
    method, note = "given", ""
    check_out_dir(out)  # before the DP writes its result there
    out.mkdir(parents=True, exist_ok=True)
    with outdir.lock_output_dir(out, "study"):  # one process at a time in out
        # every run shares the system, the MPC, the month and the evaluation draws (only the
        # seed varies): the first run stands for all of them
        run = load_grid(grid).runs[0]
        if J_star is None and target == "causal":
            month = run.file_month()
            if month is None:  # the shipped month
                month = Prices.month(run.system, run.learning.days_per_month)
            found = _study_target(out, run.system, month)
            J_star, method, note = found["J_star"], found["method"], found["note"]
        elif J_star is None:
            note = "target='best_seen': judged against the best J_eval reached"
        tuned = None
        if class_best is not None:  # checked before the runs start
            tuned = load_class_best(class_best)
            if tuned.get("system") != json.loads(jsonio.dumps(run.system.to_dict())) or \
                    tuned.get("forecast") != run.mpc.forecast:
                raise ValueError(f"--class-best {class_best}: searched for another class (system "
                                 f"or forecast {tuned.get('forecast')!r}) than the study's "
                                 f"(forecast {run.mpc.forecast!r}); expected a tune result of the "
                                 "study's system and forecast")
        table = run_sweep(grid, out, scheduler=scheduler, workers=workers, progress=progress,
                          lockstep=lockstep)
        rows, histories = [], {}
        for seed, (_, result) in zip(seed_list, table.iterrows()):
            row: dict[str, Any] = {"seed": seed, "run_id": result["run_id"],
                                   "status": result["status"], "error": result["error"]}
            if result["status"] == "done":
                history = History.load(out / result["run_dir"])
                histories[seed] = history
                row.update(seed_row(history))
            rows.append(row)
        start = run.learning.theta0
        if start is not None:  # the runs start at learning.theta0, and month 0 evaluates
            # that start: the nominal MPC is evaluated on the same draws for the gap
            nominal, nominal_error = None, None
            try:  # after every run: a failure here must not cost the summary
                nominal = class_on_run_draws(run, Theta.nominal(run.system))
            except Exception as err:  # noqa: BLE001 (recorded in the summary and logged)
                nominal_error = f"{type(err).__name__}: {err}"
                log.warning("study: the nominal theta on the runs' draws failed (%s); the gap "
                            "closed is left out", nominal_error)
            for row in rows:
                if "J_eval_nominal" in row:
                    row["J_eval_start"] = row["J_eval_nominal"]
                    row["J_eval_nominal"] = math.nan if nominal is None else nominal["mean"]
        seed_table, summary = summarize(pd.DataFrame(rows), J_star, threshold,
                                        J_star_method=method or "given", J_star_note=note)
        if start is not None:
            summary["theta0"] = [float(x) for x in start]
            if nominal_error is not None:
                summary["J_nominal_error"] = nominal_error
        if tuned is not None:
            on_runs, failure = None, None
            try:  # after every run: a failure here must not cost the summary
                on_runs = class_on_run_draws(run, tuned["theta_best"])
            except Exception as err:  # noqa: BLE001 (recorded in the summary and logged)
                failure = f"{type(err).__name__}: {err}"
                log.warning("study: the class's best theta on the runs' draws failed (%s); "
                            "the paired learner gap is left out", failure)
            summary["class_split"] = class_split(seed_table, tuned, summary["J_star"], on_runs)
            summary["class_split"]["source"] = str(class_best)
            if failure is not None:
                summary["class_split"]["J_class_eval_error"] = failure
        seed_table = seed_table.reindex(columns=list(SEED_COLUMNS)
                                        + (["J_eval_start"] if start is not None else []))
        curves = curves_table(histories)
        seed_table.to_csv(out / "study.csv", index=False)
        curves.to_csv(out / "study_curves.csv", index=False)
        summary = {"months": int(months), "eval_draws": _eval_draws(histories), **summary}
        durable.write_json(out / "study.json", summary)
        fig = plot_curves(curves, summary["J_target"])
        try:
            with durable.atomic_output(out / "study_curves.png") as tmp:
                fig.savefig(tmp, dpi=120, bbox_inches="tight")
        finally:
            plt.close(fig)
        return summary


def class_on_run_draws(run: Any, theta: Any) -> dict[str, Any] | None:
    """``theta`` (the class's best) in closed loop on the evaluation draws of ``run`` (a
    :class:`~mpcrl_lite.studies.sweep.grid.SweepRun` of the study: its system, MPC, month and
    ``LearningConfig.eval_seed`` / ``eval_draws``), by the runs' own
    :meth:`Experiment.evaluate <mpcrl_lite.learning.experiment.Experiment.evaluate>`: the
    same noise as every run's ``J_eval``, so the difference of the two is paired.

    Returns ``{"mean", "std", "ci_low", "ci_high", "draws", "seed", "J": [per draw]}``, or
    None when the runs are not evaluated (``eval_every = 0``).
    """
    on_draws = _run_draws(run)
    if on_draws is None:
        return None
    J = on_draws(theta)
    learning = run.learning
    return {**mean_ci(J).as_dict(), "draws": int(learning.eval_draws),
            "seed": int(learning.eval_seed), "J": [float(v) for v in J]}


def _run_draws(run: Any) -> Callable[[Theta], np.ndarray] | None:
    """Each evaluation draw's J of a theta on the draws of ``run``, through the runs' own
    :meth:`Experiment.evaluate` (built once, for every theta asked); None when the runs are
    not evaluated (``eval_every = 0``)."""
    learning = run.learning
    if not learning.eval_every:
        return None
    experiment = Experiment(run.system, run.mpc, learning, prices=run.file_month())
    return lambda theta: draw_J(experiment.evaluate(theta), learning.eval_draws)


def segment_on_run_draws(run: Any, start: Theta, end: Theta, points: int = 11) -> dict[str, Any]:
    r"""J along the straight segment from ``start`` to ``end`` (two :class:`~mpcrl_lite.theta.
    Theta` of the run's class, e.g. a run's final theta and the class's best), on the run's own
    evaluation draws (as :func:`class_on_run_draws`): is the class's best in the learner's
    basin, or is there a rise between them?

    ``theta(t) = (1 - t) start + t end`` at ``points`` evenly spaced ``t`` in [0, 1] (2 to
    101). Returns ``{"t", "J"}`` (the mean over the draws at each ``t``), ``"J_start"``,
    ``"J_end"`` and ``"rise"``: how much the worst point is above the worse end,
    ``max J - max(J_start, J_end)`` (0 when J never climbs above its ends: no barrier along
    the segment, though another path may still have one), with the draws and their seed.
    Every ``theta(t)`` is convex when both ends are (a convex combination of two convex
    MPCs, ``phi1, T1 >= 0``), so the compiled back-end solves them all.
    """
    points = check_int("points", points, 2)
    if points > 101:
        raise ValueError(f"points={points}: expected 2 to 101 (one evaluation each)")
    for name, theta in (("start", start), ("end", end)):
        check_instance(name, theta, Theta)
        if theta.n != run.system.n:
            raise ValueError(f"{name} has n={theta.n}; expected the run's n={run.system.n}")
    on_draws = _run_draws(run)
    if on_draws is None:
        raise ValueError("the run is not evaluated (eval_every = 0): no draws to judge on")
    a, b = start.to_vector(), end.to_vector()
    ts = np.linspace(0.0, 1.0, points)
    J = [float(on_draws(Theta.from_vector((1.0 - t) * a + t * b, start.n)).mean()) for t in ts]
    learning = run.learning
    return {"t": [float(t) for t in ts], "J": J, "J_start": J[0], "J_end": J[-1],
            "rise": float(max(J) - max(J[0], J[-1])), "draws": int(learning.eval_draws),
            "seed": int(learning.eval_seed)}


def _gap_stats(prefix: str, seeds: list[int], gaps: np.ndarray) -> dict[str, Any]:
    """Per seed, median, IQR, worst and mean (with its interval) of a learner gap."""
    return {
        prefix: {str(s): float(g) for s, g in zip(seeds, gaps)},
        f"{prefix}_median": float(np.median(gaps)) if gaps.size else math.nan,
        f"{prefix}_iqr": ([float(np.percentile(gaps, 25)), float(np.percentile(gaps, 75))]
                          if gaps.size else [math.nan, math.nan]),
        f"{prefix}_worst": ({"seed": seeds[int(np.argmax(gaps))], "value": float(gaps.max())}
                            if gaps.size else None),
        f"{prefix}_mean": mean_ci(gaps).as_dict() if gaps.size else None,
    }


def class_split(table: pd.DataFrame, tuned: Mapping[str, Any],
                J_star: float | None, on_run_draws: Mapping[str, Any] | None = None
                ) -> dict[str, Any]:
    r"""The regret of every finished seed split in two against the class's best theta:

    ``J_eval_final - J* = (J_eval_final - J_class) [learner] + (J_class - J*) [class]``, with
    ``J_class`` the held-out mean of a ``tune`` result (``tuned``, :func:`mpcrl_lite.bounds.
    baselines.load_class_best`: judged on draws of ``LearningConfig().eval_seed``, which
    include the runs' evaluation draws) and its 95 % interval.

    The held-out draws are more (30 by default) than a run's evaluation draws (10), so
    ``J_class`` and a seed's ``J_eval_final`` are means over different noise, whose difference
    carries the draws' own spread (theta's J varies by about 50 NOK/day from draw to draw:
    the mean of 10 draws by several NOK/day). ``on_run_draws`` (:func:`class_on_run_draws`)
    is the class's best theta on the runs' own draws; with it the learner's part is also given
    paired, ``J_eval_final - J_class_eval`` on the same noise.

    Returns
    -------
    dict
        ``J_class``, ``J_class_ci`` ([low, high]), ``learner_gap`` ({seed: J_eval_final -
        J_class}), ``learner_gap_median``, ``learner_gap_iqr``, ``learner_gap_worst``
        ({seed, value}), ``learner_gap_mean`` (with ``ci_low``/``ci_high`` over the seeds),
        and with J* ``class_gap`` (``J_class - J*``, with the interval of ``J_class``). With
        ``on_run_draws`` also ``J_class_eval`` (it) and ``learner_gap_paired``,
        ``learner_gap_paired_median``, ``_iqr``, ``_worst``, ``_mean`` as above.
    """
    held = tuned["J_heldout"]
    J_class = float(held["mean"])
    ok = (table["status"] == "done") & table["J_eval_final"].notna()
    seeds = [int(v) for v in table.loc[ok, "seed"]]
    final = table.loc[ok, "J_eval_final"].to_numpy(float)
    out: dict[str, Any] = {
        "J_class": J_class,
        "J_class_ci": [held.get("ci_low"), held.get("ci_high")],
        **_gap_stats("learner_gap", seeds, final - J_class),
    }
    if on_run_draws is not None:
        out["J_class_eval"] = dict(on_run_draws)
        out.update(_gap_stats("learner_gap_paired", seeds,
                              final - float(on_run_draws["mean"])))
    if J_star is not None:
        low, high = held.get("ci_low"), held.get("ci_high")
        out["class_gap"] = {"mean": J_class - J_star,
                            "ci_low": None if low is None else low - J_star,
                            "ci_high": None if high is None else high - J_star}
    return out


def _eval_draws(histories: Mapping[int, History]) -> int | None:
    draws = {h.learning.eval_draws for h in histories.values()}
    return draws.pop() if len(draws) == 1 else None
