"""Notebook 06's figures: policies with 95 % intervals against J* and the clairvoyant bound,
and the two learners' curves on one axes."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import pytest

from mpcrl_lite._util.stats import mean_ci
from mpcrl_lite.figures.comparison import plot_learning_curves, plot_policy_comparison
from mpcrl_lite.figures.style import find_lines

#: learning curves of five months for both learners (notebook 06's comparison)
_FIVE_MONTHS = {k: {"J": list(np.linspace(-150, -200, 5))} for k in ("centralized", "decentralized")}
#: a seed band of two seeds over three evaluated months (notebook 08's figure)
_TWO_SEEDS = {"month": np.array([0, 5, 9]), "mean": np.array([1500.0, 100.0, -150.0]),
              "ci_low": np.array([1500.0, 50.0, -180.0]),
              "ci_high": np.array([1500.0, 150.0, -120.0]), "seeds": 2}


@pytest.fixture
def baselines():
    rng = np.random.default_rng(3)
    policies = {}
    for name, mean in (("clairvoyant", -600.0), ("nominal", -150.0), ("rule_based", 50.0),
                       ("learned", -220.0)):
        per_day = mean + 40.0 * rng.standard_normal(12)
        policies[name] = {"J": float(per_day.mean()), "J_per_day": per_day.tolist()}
    j_star = -399.3
    regret = {k: v["J"] - j_star for k, v in policies.items()}
    return {"policies": policies, "causal": {"J_star": j_star, "regret": regret}}


def test_policy_comparison_draws_intervals_bounds_and_regrets(baselines):
    fig = plot_policy_comparison(baselines)
    (ax,) = fig.axes
    labels = [t.get_text() for t in ax.get_yticklabels()]
    assert labels == ["price rule", "nominal MPC (θ0)", "learned MPC"]  # worst first
    # each row: the mean as a point, the 95 % Student-t interval as its error bar
    for container, name in zip(ax.containers, ["rule_based", "nominal", "learned"]):
        ci = mean_ci(np.asarray(baselines["policies"][name]["J_per_day"]))
        (x,), _ = container.lines[0].get_data()
        assert x == pytest.approx(ci.mean)
        segment = container.lines[2][0].get_segments()[0]
        assert sorted(segment[:, 0]) == pytest.approx([ci.ci_low, ci.ci_high])
    verticals = {line.get_label(): line.get_xdata()[0] for line in ax.get_lines()
                 if line.get_label().startswith(("J*", "clairvoyant"))}
    assert verticals["J* = -399.3 (best causal policy)"] == pytest.approx(-399.3)
    clair = baselines["policies"]["clairvoyant"]["J"]
    assert any(np.isclose(x, clair) for x in verticals.values())
    texts = {t.get_text() for t in ax.texts}
    assert f"J − J* = {baselines['causal']['regret']['learned']:+.1f}" in texts
    plt.close(fig)
    # with the regret split of a tuned class, the learned row says how it splits
    regret = baselines["causal"]["regret"]["learned"]
    baselines["causal"]["split"] = {"learner": {"mean": regret - 100.0},
                                    "class": {"mean": 100.0}}
    fig = plot_policy_comparison(baselines)
    texts = {t.get_text() for t in fig.axes[0].texts}
    assert f"J − J* = {regret:+.1f} = learner {regret - 100:+.1f} + class +100.0" in texts
    plt.close(fig)


def test_learning_curves_on_one_axes_points_only_when_few_months():
    two = {"centralized": {"J": [-150.0, -170.0]}, "decentralized": {"J": [-150.0, -160.0]}}
    fig = plot_learning_curves(two)
    (ax,) = fig.axes
    lines = ax.get_lines()
    assert [list(line.get_ydata()) for line in lines] == [[-150.0, -170.0], [-150.0, -160.0]]
    assert all(line.get_linestyle() == "None" for line in lines)  # two points: no trend drawn
    assert list(lines[0].get_xdata()) == [1, 2]
    plt.close(fig)
    fig = plot_learning_curves(_FIVE_MONTHS)
    assert all(line.get_linestyle() != "None" for line in fig.axes[0].get_lines())
    plt.close(fig)


def _study(p_bars, seeds=2, noise_vars=(0.5,)):
    """Tables shaped as notebook 07's ``results`` and ``stats``."""
    import pandas as pd

    rows = []
    for v in noise_vars:
        for p in p_bars:
            for seed in range(seeds):
                J = -100.0 * p - 10.0 * seed - 50.0 * v
                rows.append({"P_bar": p, "noise_var": v, "seed": seed, "J_eval_last": J,
                             "J_eval_last_ci_low": J - 20.0, "J_eval_last_ci_high": J + 25.0,
                             "J_star": -400.0 - 10.0 * p})
    results = pd.DataFrame(rows)
    results["regret_last"] = results["J_eval_last"] - results["J_star"]
    stats = (results.groupby(["P_bar", "noise_var"], as_index=False)["regret_last"]
             .agg(regret_last_mean="mean", regret_last_std="std"))
    return results, stats


def _container(ax, gid):
    (found,) = [c for c in ax.containers if c.lines[0].get_gid() == gid]
    return found


def test_parameter_study_draws_two_grid_limits_as_points_without_a_trend():
    """Notebook 07's classroom and test profiles run two grid limits: the regret panel shows
    two points with their spreads and no line between them."""
    from mpcrl_lite.figures.comparison import plot_parameter_study

    results, stats = _study([1.5, 2.0])
    fig = plot_parameter_study(results, stats)
    ax_J, ax_r = fig.axes
    regret = _container(ax_r, "regret[noise_var=0.5]")
    assert regret.lines[0].get_linestyle() == "None" and regret.lines[0].get_marker() == "o"
    np.testing.assert_allclose(regret.lines[0].get_xdata(), [1.5, 2.0])
    np.testing.assert_allclose(regret.lines[0].get_ydata(), stats["regret_last_mean"])
    runs = _container(ax_J, "J_eval[noise_var=0.5]").lines[0]
    assert runs.get_linestyle() == "None"
    np.testing.assert_allclose(sorted(runs.get_ydata()), sorted(results["J_eval_last"]))
    # the two seeds of a grid point side by side around it, J* of each grid limit once
    x = np.asarray(runs.get_xdata())
    assert np.all(np.abs(x - results["P_bar"].to_numpy()) < 0.1) and len(set(x)) == 4
    (stars,) = [line for line in ax_J.get_lines() if line.get_gid() == "J_star[noise_var=0.5]"]
    np.testing.assert_allclose(stars.get_ydata(), [-415.0, -420.0])
    for ax in (ax_J, ax_r):
        assert ax.get_xlabel() == r"grid limit $\bar P$ (MW)"
    assert "over 2 seeds" in ax_r.get_title("left")
    plt.close(fig)


def test_parameter_study_joins_three_grid_limits_and_refuses_bad_tables():
    from mpcrl_lite.figures.comparison import plot_parameter_study

    results, stats = _study([1.0, 1.5, 2.0], seeds=3, noise_vars=(0.2, 0.5))
    fig = plot_parameter_study(results, stats)
    for v in ("0.2", "0.5"):
        line = _container(fig.axes[1], f"regret[noise_var={v}]").lines[0]
        assert line.get_linestyle() == "-" and len(line.get_xdata()) == 3
    plt.close(fig)
    with pytest.raises(ValueError, match=r"results: missing column\(s\) \['J_star'\]"):
        plot_parameter_study(results.drop(columns="J_star"), stats)
    with pytest.raises(ValueError, match="stats: no rows"):
        plot_parameter_study(results, stats.iloc[:0])
def test_seed_bands_draw_the_mean_its_band_and_the_reference_lines():
    from mpcrl_lite.figures.comparison import plot_seed_bands

    two = _TWO_SEEDS
    one = {"month": np.array([0, 5, 9]), "mean": np.array([1500.0, -50.0, -100.0]),
           "ci_low": np.full(3, np.nan), "ci_high": np.full(3, np.nan), "seeds": 1}
    fig = plot_seed_bands({"DPG": two, "Q-learning": one}, J_star=-399.3, J_class=-230.0,
                          J_nominal=1500.0)
    (ax,) = fig.axes
    (dpg,) = find_lines(ax, "mean=DPG")
    assert list(dpg.get_xdata()) == [1, 6, 10] and list(dpg.get_ydata()) == [1500, 100, -150]
    assert len(find_lines(ax, "mean=Q-learning")) == 1
    # one band: the learner with two seeds; one seed has no interval over the seeds
    (band,) = ax.collections
    low, high = band.get_paths()[0].vertices[:, 1].min(), band.get_paths()[0].vertices[:, 1].max()
    assert (low, high) == pytest.approx((-180.0, 1500.0))
    for gid, value in (("J_star", -399.3), ("J_class", -230.0), ("J_nominal", 1500.0)):
        (line,) = find_lines(ax, gid)
        assert line.get_ydata()[0] == pytest.approx(value)
    plt.close(fig)
    fig = plot_seed_bands({"DPG": two})  # no reference lines unless given
    assert not find_lines(fig.axes[0], "J_star")
    plt.close(fig)


def test_comparison_figures_are_drawn_inside_their_canvas(baselines):
    """The notebooks show figures uncropped; nothing may then fall off their edge."""
    from conftest import assert_drawn_inside

    from mpcrl_lite.figures.comparison import plot_parameter_study, plot_seed_bands

    figures = [plot_policy_comparison(baselines), plot_learning_curves(_FIVE_MONTHS),
               plot_parameter_study(*_study([1.0, 1.5, 2.0], noise_vars=(0.5, 1.0))),
               plot_seed_bands({"DPG": _TWO_SEEDS}, J_star=-399.3, J_class=-230.0,
                               J_nominal=1500.0)]
    for fig in figures:
        assert_drawn_inside(fig)
        plt.close(fig)
