r"""Notebooks 06-08's figures: policies against the bounds, learners, a study's grid.

* :func:`plot_policy_comparison` draws, for each policy of
  :func:`mpcrl_lite.bounds.baselines.evaluate_baselines` (nominal MPC, price rule, learned
  MPCs, the DP's policy), its mean daily cost :math:`J` on the common draw with the 95 %
  Student-t interval over the days, against the best causal cost :math:`J^\star` and the
  clairvoyant bound, each policy's regret :math:`J - J^\star` written beside it (for the
  learned MPC split into the learner's and the class's part when the baselines hold the
  regret split of a tuned class, ``causal['split']``);
* :func:`plot_learning_curves` draws :math:`J` per month of the centralized and the
  decentralized learner of :func:`mpcrl_lite.decentralized.learner.compare_learners` on one
  axes (points only when there are too few months for a line to mean anything);
* :func:`plot_parameter_study` draws notebook 07's study: every run's :math:`J_\text{eval}`
  of the last month with its 95 % interval over the evaluation draws and :math:`J^\star` per
  grid limit (left), the regret :math:`J_\text{eval} - J^\star` over the seeds (right;
  points only when there are too few grid limits for a line to mean anything).

Notebook 08's figure:

* :func:`plot_seed_bands` draws, for each learner, the mean ``J_eval`` over seeds with its
  95 % interval over the seeds (the bands of :func:`mpcrl_lite.studies.study.seed_band`)
  against the nominal MPC, the best parameters of the class and :math:`J^\star`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .._util.stats import mean_ci
from .style import (
    COST_UNIT,
    FIRST_COLOR,
    LAST_COLOR,
    MIN_POINTS_FOR_A_LINE,
    REF_GREY,
    axes_or_new,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["POLICY_LABELS", "plot_learning_curves", "plot_parameter_study",
           "plot_policy_comparison", "plot_seed_bands"]

#: How the policies of ``evaluate_baselines`` are named on the figure.
POLICY_LABELS = {
    "nominal": "nominal MPC (θ0)",
    "rule_based": "price rule",
    "learned": "learned MPC",
    "causal_dp": "DP policy (causal)",
    "clairvoyant": "clairvoyant",
}


def _interval(per_day: Any) -> tuple[float, float, float]:
    """Mean and 95 % interval of the daily costs (the mean twice for one day)."""
    ci = mean_ci(np.asarray(per_day, dtype=float))
    if ci.draws < 2:
        return ci.mean, ci.mean, ci.mean
    return ci.mean, ci.ci_low, ci.ci_high


def plot_policy_comparison(baselines: Mapping[str, Any], ax: Axes | None = None,
                           fig: Figure | None = None, title: str | None = None) -> Figure:
    """J with 95 % intervals per policy against :math:`J^\\star` and the clairvoyant bound.

    Parameters
    ----------
    baselines : dict
        The result of :func:`~mpcrl_lite.bounds.baselines.evaluate_baselines`: its
        ``policies`` (each with ``J_per_day``) and, when computed, ``causal`` (``J_star``,
        ``regret``).
    ax : Axes, optional
        Drawn into; else ``fig`` (cleared) or a new figure.
    fig : Figure, optional
    title : str, optional
        Default names the number of days.

    Returns
    -------
    Figure
        One axes: a row per causal policy (best at the top), the interval as a bar, the mean
        as a point, ``J - J*`` beside it; vertical lines at :math:`J^\\star` and at the
        clairvoyant's mean cost.
    """
    policies = dict(baselines["policies"])
    causal = baselines.get("causal") or {}
    clair = policies.pop("clairvoyant", None)
    rows = sorted(policies, key=lambda name: policies[name]["J"], reverse=True)
    fig, (ax,) = axes_or_new(ax, (1, 1), (8.0, 0.6 * len(rows) + 2.2), "ax", fig)
    days = len(next(iter(policies.values()))["J_per_day"]) if policies else 0
    for y, name in enumerate(rows):
        mean, low, high = _interval(policies[name]["J_per_day"])
        ax.errorbar([mean], [y], xerr=[[mean - low], [high - mean]], fmt="o", color=LAST_COLOR,
                    ecolor=LAST_COLOR, capsize=4, lw=2, label="J, 95 % interval" if y == 0
                    else None)
        regret = causal.get("regret", {}).get(name)
        if regret is not None:
            text = f"J − J* = {regret:+.1f}"
            split = causal.get("split") or {}
            if name == "learned" and "learner" in split and "class" in split:
                # the regret split (bounds.baselines.regret_split): what learning could still
                # gain within the MPC class, and what the class itself costs
                text += (f" = learner {split['learner']['mean']:+.1f}"
                         f" + class {split['class']['mean']:+.1f}")
            ax.annotate(text, (high, y), xytext=(6, 0), textcoords="offset points",
                        va="center", fontsize=9)
    if "J_star" in causal:
        j_star = float(causal["J_star"])
        ax.axvline(j_star, color=FIRST_COLOR, lw=1.8,
                   label=f"J* = {j_star:.1f} (best causal policy)")
    if clair is not None:
        ax.axvline(float(clair["J"]), color=REF_GREY, lw=1.5, ls="--",
                   label=f"clairvoyant bound {float(clair['J']):.1f} (knows the noise)")
    ax.set_yticks(range(len(rows)), [POLICY_LABELS.get(n, n) for n in rows])
    ax.set_ylim(-0.7, len(rows) - 0.3)
    ax.invert_yaxis()
    left, right = ax.get_xlim()
    ax.set_xlim(left, right + 0.18 * (right - left))  # room for the regret labels
    ax.set_xlabel(f"mean daily cost J ({COST_UNIT})")
    ax.grid(True, axis="x", color="0.9")
    fig.legend(loc="outside lower center", ncol=3, fontsize=9)
    ax.set_title(title or f"Policies on one common draw of {days} days: J with 95 % intervals "
                 "over the days", loc="left", fontsize=11)
    return fig


def plot_learning_curves(comparison: Mapping[str, Any], ax: Axes | None = None,
                         fig: Figure | None = None, title: str | None = None) -> Figure:
    """J per month of the centralized and the decentralized learner on one axes.

    Parameters
    ----------
    comparison : dict
        The result of :func:`~mpcrl_lite.decentralized.learner.compare_learners` (its
        ``centralized`` and ``decentralized`` entries, each with ``J`` per month).
    ax : Axes, optional
        Drawn into; else ``fig`` (cleared) or a new figure.
    fig : Figure, optional
    title : str, optional

    Returns
    -------
    Figure
        Months from 1 on the x axis; with fewer than :data:`MIN_POINTS_FOR_A_LINE` months the
        costs are points only.
    """
    fig, (ax,) = axes_or_new(ax, (1, 1), (8.0, 3.8), "ax", fig)
    # the centralized points as large rings, so that the decentralized ones stay visible inside
    # them where the two agree (the first month always: the same policy at theta0)
    styles = {"centralized": (LAST_COLOR, "o", "-", {"ms": 10, "mfc": "none", "mew": 1.8}),
              "decentralized": (FIRST_COLOR, "s", "--", {"ms": 5})}
    months = 0
    for name, (color, marker, line, size) in styles.items():
        J = np.asarray(comparison[name]["J"], dtype=float)
        months = max(months, J.size)
        x = np.arange(1, J.size + 1)
        ax.plot(x, J, marker=marker, ls=line if J.size >= MIN_POINTS_FOR_A_LINE else "none",
                color=color, label=f"{name} learner (last month {J[-1]:.1f})", **size)
    ax.set_xlabel("learning month")
    ax.set_ylabel(f"J ({COST_UNIT})")
    ax.set_xticks(np.arange(1, months + 1) if months <= 12 else ax.get_xticks())
    ax.grid(True, color="0.9")
    ax.legend(fontsize=9)
    ax.set_title(title or "Centralized and decentralized learning: J per month (same prices, "
                 "seed and exploration)", loc="left", fontsize=11)
    return fig


#: Columns :func:`plot_parameter_study` reads from its two tables.
STUDY_RESULTS_COLUMNS = ("P_bar", "noise_var", "seed", "J_eval_last", "J_eval_last_ci_low",
                         "J_eval_last_ci_high", "J_star")
STUDY_STATS_COLUMNS = ("P_bar", "noise_var", "regret_last_mean", "regret_last_std")


def plot_parameter_study(results: Any, stats: Any, axes: Any = None,
                         fig: Figure | None = None) -> Figure:
    r"""Notebook 07's study: each run against :math:`J^\star` (left), the regret (right).

    Parameters
    ----------
    results : pandas.DataFrame
        One row per run: ``P_bar``, ``noise_var``, ``seed``, ``J_eval_last`` with its 95 %
        interval ``J_eval_last_ci_low`` / ``J_eval_last_ci_high``, and ``J_star`` of its
        system.
    stats : pandas.DataFrame
        One row per grid point (``summarize`` over the seeds): ``P_bar``, ``noise_var``,
        ``regret_last_mean``, ``regret_last_std``.
    axes : two Axes, optional
        Drawn into; else ``fig`` (cleared) or a new figure.
    fig : Figure, optional

    Returns
    -------
    Figure
        Left: every run's :math:`J_\text{eval}` as a point with its interval (the seeds of
        a grid point side by side) and :math:`J^\star` of each grid point as a cross. Right:
        the mean regret over the seeds with one standard deviation; joined by a line only
        with at least :data:`MIN_POINTS_FOR_A_LINE` grid limits (two points would draw a
        trend nobody measured). One colour per noise variance.

    Raises
    ------
    ValueError
        If a table lacks a column the figure reads, or holds no row.

    Notes
    -----
    Gids: the runs ``"J_eval[noise_var=v]"`` and ``"regret[noise_var=v]"`` (error-bar
    containers, their data line carries the gid), the crosses ``"J_star[noise_var=v]"``.
    """
    for name, table, columns in (("results", results, STUDY_RESULTS_COLUMNS),
                                 ("stats", stats, STUDY_STATS_COLUMNS)):
        missing = [c for c in columns if c not in getattr(table, "columns", ())]
        if missing:
            raise ValueError(f"{name}: missing column(s) {missing}; expected {list(columns)}")
        if len(table) == 0:
            raise ValueError(f"{name}: no rows to draw")
    fig, (ax_J, ax_r) = axes_or_new(axes, (1, 2), (11.0, 3.8), "axes", fig)
    p_bars = np.unique(np.asarray(results["P_bar"], dtype=float))
    seeds = int(results["seed"].nunique())
    width = 0.08 * (float(p_bars.max() - p_bars.min()) or 1.0)
    noise_groups = list(results.groupby("noise_var"))
    for c, (noise_var, group) in enumerate(noise_groups):
        color = f"C{c}"
        # the seeds of a grid point side by side, the noise variances apart
        offset = (c - (len(noise_groups) - 1) / 2) * width * 1.5
        rank = group["seed"].rank(method="dense").to_numpy() - 1
        x = group["P_bar"].to_numpy(float) + offset + (rank - (seeds - 1) / 2) * width / seeds
        J = group["J_eval_last"].to_numpy(float)
        bars = ax_J.errorbar(x, J, yerr=[J - group["J_eval_last_ci_low"].to_numpy(float),
                                         group["J_eval_last_ci_high"].to_numpy(float) - J],
                             fmt="o", ms=4, capsize=3, color=color,
                             label=f"noise var {noise_var:g}: each run, 95 % interval")
        bars.lines[0].set_gid(f"J_eval[noise_var={noise_var:g}]")
        stars = group.drop_duplicates("P_bar")
        ax_J.plot(stars["P_bar"].to_numpy(float) + offset, stars["J_star"].to_numpy(float), "x",
                  ms=9, mew=2,
                  color=color, gid=f"J_star[noise_var={noise_var:g}]",
                  label=f"J* (noise var {noise_var:g})")
        rows = stats[np.isclose(stats["noise_var"].to_numpy(float), float(noise_var))]
        rows = rows.sort_values("P_bar")
        line = "-" if len(rows) >= MIN_POINTS_FOR_A_LINE else "none"
        bars = ax_r.errorbar(rows["P_bar"].to_numpy(float),
                             rows["regret_last_mean"].to_numpy(float),
                             yerr=rows["regret_last_std"].fillna(0.0).to_numpy(float),
                             marker="o", capsize=4,
                             color=color, ls=line, label=f"noise var {noise_var:g}")
        bars.lines[0].set_gid(f"regret[noise_var={noise_var:g}]")
    for ax in (ax_J, ax_r):
        ax.set_xlabel(r"grid limit $\bar P$ (MW)")
        ax.grid(True, color="0.9")
        ax.legend(fontsize=8)
    ax_J.set_ylabel(f"J ({COST_UNIT})")
    ax_J.set_title(r"$J_\mathrm{eval}$, last month: each run with its 95 % interval",
                   loc="left", fontsize=11)
    ax_r.set_ylabel(rf"$J_\mathrm{{eval}} - J^\star$ ({COST_UNIT})")
    ax_r.set_title(f"regret: mean ± std over {seeds} seed{'s' if seeds != 1 else ''}",
                   loc="left", fontsize=11)
    return fig


#: Colours of the learners of :func:`plot_seed_bands` (others cycle through matplotlib's).
LEARNER_COLORS = {"DPG": LAST_COLOR, "Q-learning": "#2ca02c"}


def plot_seed_bands(bands: Mapping[str, Mapping[str, Any]], J_star: float | None = None,
                    J_class: float | None = None, J_nominal: float | None = None,
                    ax: Axes | None = None, fig: Figure | None = None,
                    title: str | None = None) -> Figure:
    """Mean ``J_eval`` over seeds per learner, with its 95 % interval over the seeds.

    Parameters
    ----------
    bands : dict
        Learner name -> the result of :func:`mpcrl_lite.studies.study.seed_band` (``month``
        from 0, ``mean``, ``ci_low``, ``ci_high``, ``seeds``).
    J_star, J_class, J_nominal : float, optional
        Drawn as horizontal lines (gids ``"J_star"``, ``"J_class"``, ``"J_nominal"``): the
        best causal policy, the best parameters of the MPC class, the nominal MPC.
    ax : Axes, optional
        Drawn into; else ``fig`` (cleared) or a new figure.
    fig : Figure, optional
    title : str, optional

    Returns
    -------
    Figure
        Months from 1 on the x axis (month ``m`` evaluated after ``m - 1`` updates); one line
        per learner (gid ``"mean=<name>"``) and its band where the interval is finite (one
        seed: the line only).
    """
    fig, (ax,) = axes_or_new(ax, (1, 1), (8.0, 4.2), "ax", fig)
    for name, band in bands.items():
        x = np.asarray(band["month"], dtype=float) + 1
        mean = np.asarray(band["mean"], dtype=float)
        low, high = (np.asarray(band[k], dtype=float) for k in ("ci_low", "ci_high"))
        color = LEARNER_COLORS.get(name)
        (line,) = ax.plot(x, mean, marker="o", ms=4, lw=2, color=color, gid=f"mean={name}",
                          label=f"{name}: mean of {band['seeds']} seeds")
        if np.isfinite(low).all() and np.isfinite(high).all():
            ax.fill_between(x, low, high, color=line.get_color(), alpha=0.2, lw=0,
                            label=f"{name}: 95 % interval over the seeds")
    for value, gid, label, style in (
            (J_nominal, "J_nominal", "nominal MPC", {"color": REF_GREY, "ls": "--"}),
            (J_class, "J_class", "best θ of the class", {"color": "black", "ls": "-."}),
            (J_star, "J_star", "J* (best causal policy)", {"color": FIRST_COLOR, "ls": ":"})):
        if value is not None and np.isfinite(value):
            ax.axhline(float(value), lw=1.5, gid=gid, label=f"{label} {float(value):.1f}",
                       **style)
    ax.set_xlabel("learning month (evaluated before its update)")
    ax.set_ylabel(f"J_eval ({COST_UNIT})")
    ax.grid(True, color="0.9")
    ax.legend(fontsize=8, ncol=2)
    ax.set_title(title or "J_eval on the fixed evaluation draws: mean and 95 % interval "
                 "over the seeds", loc="left", fontsize=11)
    return fig
