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
    five = {k: {"J": list(np.linspace(-150, -200, 5))} for k in ("centralized", "decentralized")}
    fig = plot_learning_curves(five)
    assert all(line.get_linestyle() != "None" for line in fig.axes[0].get_lines())
    plt.close(fig)


def test_seed_bands_draw_the_mean_its_band_and_the_reference_lines():
    from mpcrl_lite.figures.comparison import plot_seed_bands

    two = {"month": np.array([0, 5, 9]), "mean": np.array([1500.0, 100.0, -150.0]),
           "ci_low": np.array([1500.0, 50.0, -180.0]), "ci_high": np.array([1500.0, 150.0, -120.0]),
           "seeds": 2}
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
