"""Tests of the figures (mpcrl_lite.figures.plots): structure, plotted data, reference lines, files."""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.figure import Figure

from mpcrl_lite.config import LearningConfig, SystemConfig
from mpcrl_lite.figures import plots
from mpcrl_lite.figures.paper import (
    PAPER_FIGURES,
    fig1_trajectories,
    fig2_performance,
    fig3_gradient_norm,
    fig4_grid_power,
    fig5_policy_and_agent_costs,
    fig6_prices,
    fig7_theta,
    save_paper_figures,
)
from mpcrl_lite.figures.plots import plot_day
from mpcrl_lite.figures.style import FIRST_COLOR, LAST_COLOR, find_lines
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.history import History
from mpcrl_lite.mpc.formulation import Plan
from mpcrl_lite.system.prices import Prices

DAYS, MONTHS = 3, 2


@pytest.fixture(scope="module")
def history() -> History:
    """A real (short) learning run: 2 months of 3 days."""
    learning = LearningConfig(days_per_month=DAYS, months=MONTHS)
    return Experiment(learning=learning).run(progress=False)


@pytest.fixture(autouse=True)
def _no_show_and_close(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("plots must not call plt.show()")

    monkeypatch.setattr(plt, "show", refuse)
    yield
    plt.close("all")


def one_line(fig_or_ax, gid: str):
    lines = find_lines(fig_or_ax, gid)
    assert len(lines) == 1, f"expected one line {gid!r}, found {len(lines)}"
    return lines[0]


def hline_at(fig_or_ax, gid: str, value: float) -> None:
    """A reference line ``gid`` exists in every given axes and is horizontal at ``value``."""
    lines = find_lines(fig_or_ax, gid)
    assert lines, f"no reference line {gid!r}"
    for line in lines:
        np.testing.assert_allclose(np.asarray(line.get_ydata(), float), value)


def days_concat(values: np.ndarray, days, i=None) -> np.ndarray:
    if i is None:
        return np.concatenate([values[:, d] for d in days])
    return np.concatenate([values[:, d, i] for d in days])


# -- plot_day ----------------------------------------------------------------------------------
def test_plot_day_data_and_references(history):
    rec = history.last_month
    H, _, n = rec.policy.shape
    fig = plot_day(rec, day=1)
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 4
    for i in range(n):
        np.testing.assert_allclose(one_line(fig, f"soc[{i + 1}]").get_ydata(), rec.soc[:, 1, i])
        np.testing.assert_allclose(one_line(fig, f"policy[{i + 1}]").get_ydata()[:H],
                                   rec.policy[:, 1, i])
        np.testing.assert_allclose(one_line(fig, f"net_power[{i + 1}]").get_ydata()[:H],
                                   rec.b[:, 1, i] - rec.s[:, 1, i])
    np.testing.assert_allclose(one_line(fig, "grid_power").get_ydata()[:H], rec.grid_power[:, 1])
    np.testing.assert_allclose(one_line(fig, "buy").get_ydata()[:H], rec.buy[:, 1])
    np.testing.assert_allclose(one_line(fig, "sell").get_ydata()[:H],
                               history.system.sell_ratio * rec.buy[:, 1])
    hline_at(fig, "soc_low", 0.1)
    hline_at(fig, "soc_high", 0.9)
    hline_at(fig, "soc_min", 0.0)
    hline_at(fig, "soc_max", 1.0)
    hline_at(fig, "P_bar", history.system.P_bar)
    assert fig.axes[-1].get_xlim() == (0.0, float(H))
    assert "NOK/MWh" in fig.axes[-1].get_ylabel()
    assert "MW" in fig.axes[1].get_ylabel() and "MW" in fig.axes[2].get_ylabel()


def test_plot_day_uses_given_prices_and_axes(history):
    rec = history.first_month
    prices = Prices.month(history.system, DAYS).scaled(2.0)
    fig0, axes = plt.subplots(4, 1)
    fig = plot_day(rec, day=2, prices=prices, axes=axes)
    assert fig is fig0
    np.testing.assert_allclose(one_line(fig, "buy").get_ydata()[:24], prices.buy[2])
    np.testing.assert_allclose(one_line(fig, "sell").get_ydata()[:24], prices.sell[2])


@pytest.mark.parametrize("day", [DAYS, -1, 1.0, True])
def test_plot_day_rejects_bad_day(history, day):
    with pytest.raises(ValueError, match=f"day={day!r}"):
        plot_day(history.last_month, day=day)


def test_plot_day_rejects_short_prices_and_wrong_axes(history):
    prices = Prices.month(history.system, 1)
    with pytest.raises(ValueError, match="day=2"):
        plot_day(history.last_month, day=2, prices=prices)
    _, axes = plt.subplots(2, 1)
    with pytest.raises(ValueError, match="expected 4"):
        plot_day(history.last_month, axes=axes)


def _extent(fig, artist):
    return artist.get_window_extent(fig.canvas.get_renderer())


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_plot_day_legends_never_cover_data_nor_the_P_bar_line(history):
    rec = history.last_month
    fig = plot_day(rec, day=1)
    fig.canvas.draw()
    ax_p = fig.axes[2]
    p_bar = _extent(fig, one_line(ax_p, "P_bar"))
    legend = _extent(fig, ax_p.get_legend())
    assert not _overlap(legend, p_bar)
    # every legend stands beside its panel, outside the area where the data are drawn
    for ax in fig.axes:
        if ax.get_legend() is not None:
            assert not _overlap(_extent(fig, ax.get_legend()), _extent(fig, ax.patch)), ax


def test_plot_day_grid_panel_has_headroom_and_the_planned_power(history):
    rec = history.last_month
    P_bar = history.system.P_bar
    fig = plot_day(rec, day=1)
    ax_p = fig.axes[2]
    np.testing.assert_allclose(one_line(fig, "planned_power").get_ydata()[:-1],
                               rec.planned_power[:, 1])
    highest = max(P_bar, rec.grid_power[:, 1].max(), rec.planned_power[:, 1].max())
    low, top = ax_p.get_ylim()
    assert low == 0.0 and top >= highest + 0.2 * (highest - low)   # nothing on the top edge
    assert find_lines(plot_day(rec, day=1, planned=False), "planned_power") == []


def test_plot_day_explains_the_dashed_and_solid_net_power(history):
    fig = plot_day(history.last_month, day=0)
    legend = fig.axes[1].get_legend()
    entries = dict(zip([t.get_text() for t in legend.get_texts()], legend.legend_handles))
    dashed = [text for text, h in entries.items() if h.get_linestyle() == "--"]
    solid = [text for text, h in entries.items() if h.get_linestyle() == "-"]
    assert dashed == [r"policy $\pi^i(s)$"] and solid[0].startswith("applied b − s")
    assert {line.get_linestyle() for line in fig.axes[1].get_lines()
            if str(line.get_gid()).startswith("policy[")} == {"--"}


def test_plot_day_title_days_from_one_and_into_a_given_figure(history):
    rec = history.last_month
    fig = plot_day(rec, day=2)
    assert fig.axes[0].get_title("left") == f"Day 3 of {DAYS}: closed loop"
    target = Figure(figsize=(6, 6))
    assert plot_day(rec, 0, fig=target, title="mine") is target
    assert len(target.axes) == 4 and target.axes[0].get_title("left") == "mine"
    plot_day(rec, 1, fig=target)                           # cleared and drawn again
    assert len(target.axes) == 4
    _, axes = plt.subplots(4, 1)
    with pytest.raises(ValueError, match="not both"):
        plot_day(rec, axes=axes, fig=target)


def test_draw_day_is_plot_day_of_the_record(history):
    rec = history.last_month
    fig = plots.draw_day(Figure(), rec, rec.buy[:, 1], day=1, title="t",
                         policy=rec.policy[:, 1], planned=rec.planned_power[:, 1])
    np.testing.assert_allclose(one_line(fig, "soc[2]").get_ydata(), rec.soc[:, 1, 1])
    assert find_lines(fig, "planned_power")
    with pytest.raises(ValueError, match="buy"):
        plots.draw_day(Figure(), rec, 2.0 * rec.buy[:, 1], day=1)


def _plan_curve_fit() -> tuple[Plan, dict, dict]:
    """A random plan, a policy curve (tanh) and a value fit, for the plot functions."""
    rng = np.random.default_rng(0)
    b, s = rng.uniform(0, 0.5, (12, 3)), rng.uniform(0, 0.5, (12, 3))
    plan = Plan(b=b, s=s, soc=rng.uniform(0, 1, (13, 3)), sigma_hi=np.zeros((12, 3)),
                sigma_lo=np.zeros((12, 3)))
    x = np.linspace(-1.0, 1.0, 9)
    curve = {"x": x, "policy": np.tanh(np.c_[x, x, x]), "tau": 0.1, "label": "x"}
    G = rng.normal(size=(24, 3))
    fit = {"V": G + 0.1, "G": G, "r2": 0.9, "features": "hour", "days": 3, "gamma": 0.99}
    return plan, curve, fit


def test_price_window_plan_policy_curve_and_value_fit():
    prices = Prices.default()
    fig = plots.plot_price_window(prices, day=29, hour=20, N=12)
    np.testing.assert_allclose(one_line(fig, "buy").get_ydata()[:48],
                               np.concatenate([prices.buy[29], prices.buy[0]]))
    (window,) = [p for p in fig.axes[0].patches if p.get_gid() == "window"]
    assert window.get_x() == 20 and window.get_width() == 12
    assert "day 30" in [t.get_text() for t in fig.axes[0].texts]
    with pytest.raises(ValueError, match="hour=24"):
        plots.plot_price_window(prices, 0, 24, 12)

    system = SystemConfig()
    plan, curve, fit = _plan_curve_fit()
    b, s = plan.b, plan.s
    fig = plots.plot_plan(plan, system, buy=prices.buy[0, :12], title="plan")
    assert len(fig.axes) == 4
    np.testing.assert_allclose(one_line(fig, "sum_b").get_ydata()[:-1], b.sum(axis=1))
    np.testing.assert_allclose(one_line(fig, "net_power[2]").get_ydata()[:-1], b[:, 1] - s[:, 1])
    assert fig.axes[2].get_ylim()[1] > max(system.P_bar, b.sum(1).max(), s.sum(1).max())
    assert len(plots.draw_plan(Figure(), plan, system).axes) == 3

    x = curve["x"]
    fig = plots.plot_policy_curve(curve, {**curve, "tau": 1e-5})
    np.testing.assert_allclose(one_line(fig, "slope").get_ydata(), np.gradient(np.tanh(x), x))
    assert one_line(fig, "policy reference").get_linestyle() == "--"

    fig = plots.plot_value_fit(fit)
    np.testing.assert_allclose(one_line(fig, "mean V").get_ydata(),
                               (fit["G"] + 0.1).mean(axis=1))
    assert len(plots.draw_value_fit(Figure(), fit).axes) == 3        # two panels, a colorbar


def _colours_near(fig, ax, x: float, y: float, colours: dict[str, str], reach: int = 10):
    """Which of ``colours`` (name: hex) the rendered figure shows in the pixel column at data
    ``x``, within ``reach`` pixels of data ``y``."""
    from matplotlib.colors import to_rgb

    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].astype(float)
    px, py = ax.transData.transform((x, y))
    row, col = image.shape[0] - round(float(py)), round(float(px))
    column = image[max(row - reach, 0): row + reach + 1, col]
    return {name for name, hex_ in colours.items()
            if (np.abs(column - 255.0 * np.asarray(to_rgb(hex_))).max(axis=1) < 40).any()}


def test_plan_grid_sums_stay_visible_at_the_limit_and_at_zero():
    """Notebook 02's plan with T2 = -300: nothing bought or sold for 6 steps, then the sold sum
    exactly at P_bar. The sold line must show at P_bar (not under its dashes), and where both
    sums are 0 the bought and the sold line must both show."""
    system = SystemConfig()
    N, n = 12, system.n
    s = np.zeros((N, n))
    s[6:] = system.P_bar / n
    plan = Plan(b=np.zeros((N, n)), s=s, soc=np.full((N + 1, n), 0.5),
                sigma_hi=np.zeros((N, n)), sigma_lo=np.zeros((N, n)))
    fig = plots.plot_plan(plan, system)
    fig.set_dpi(150)
    ax = fig.axes[2]
    colours = {"bought": FIRST_COLOR, "sold": LAST_COLOR, "P_bar": "#000000"}
    for x in (7.5, 9.5, 11.5):
        assert {"sold", "P_bar"} <= _colours_near(fig, ax, x, system.P_bar, colours), x
    for x in (1.5, 3.5, 5.5):
        assert {"bought", "sold"} <= _colours_near(fig, ax, x, 0.0, colours), x
    bought, sold, limit = (one_line(fig, g) for g in ("sum_b", "sum_s", "P_bar"))
    assert limit.get_zorder() > sold.get_zorder() > bought.get_zorder()
    assert bought.get_linewidth() > sold.get_linewidth() > limit.get_linewidth()


# -- Fig. 1 ------------------------------------------------------------------------------------
def test_fig1_first_red_last_blue(history):
    n = history.system.n
    fig = fig1_trajectories(history)
    assert len(fig.axes) == 2 * n
    days = list(range(DAYS))  # the default takes at most five days; the month has three
    for i in range(n):
        for key, rec, color in (("first", history.first_month, FIRST_COLOR),
                                ("last", history.last_month, LAST_COLOR)):
            soc = one_line(fig, f"soc[{i + 1}] {key}")
            y = np.asarray(soc.get_ydata(), float)
            np.testing.assert_allclose(y[~np.isnan(y)], days_concat(rec.soc, days, i))
            assert soc.get_color() == color
            pol = one_line(fig, f"policy[{i + 1}] {key}")
            np.testing.assert_allclose(pol.get_ydata()[:-1], days_concat(rec.policy, days, i))
            assert pol.get_color() == color
    hline_at(fig, "soc_low", 0.1)
    hline_at(fig, "soc_high", 0.9)
    assert len(find_lines(fig, "soc_low")) == n
    assert fig.axes[0].get_xlim() == (0.0, 24.0 * DAYS)


def test_fig1_selected_days(history):
    fig = fig1_trajectories(history, days=[2])
    np.testing.assert_allclose(one_line(fig, "policy[1] last").get_ydata()[:-1],
                               history.last_month.policy[:, 2, 0])
    with pytest.raises(ValueError, match="day=7"):
        fig1_trajectories(history, days=(0, 7))
    with pytest.raises(ValueError, match="days=0"):
        fig1_trajectories(history, days=0)


# -- Figs. 2 and 3 -----------------------------------------------------------------------------
def test_fig2_performance(history):
    fig = fig2_performance(history)
    assert len(fig.axes) == 1
    line = one_line(fig, "J")
    np.testing.assert_allclose(line.get_ydata(), history.J)
    np.testing.assert_allclose(line.get_xdata(), np.arange(1, MONTHS + 1))
    assert find_lines(fig, "J_rolling") == []  # fewer months than the window
    assert "NOK/day" in fig.axes[0].get_ylabel()       # a daily cost
    assert history.J_eval  # the default evaluates the first and the last month
    evaluation = one_line(fig, "J_eval")
    np.testing.assert_allclose(evaluation.get_ydata(), history.J_eval)
    np.testing.assert_allclose(evaluation.get_xdata(), np.asarray(history.eval_month) + 1)
    K = history.learning.eval_draws
    assert K > 1 and evaluation.get_label() == f"evaluation (mean of {K} fixed draws)"
    # the confidence interval over the draws, around the mean: with two evaluations an error
    # bar on each (no band, no line between them)
    assert len(history.J_eval) == 2 and evaluation.get_linestyle() == "None"
    band = [c for c in fig.axes[0].collections if c.get_gid() == "J_eval_ci"]
    assert len(band) == 1
    y = np.concatenate([seg[:, 1] for seg in band[0].get_segments()])
    np.testing.assert_allclose([y.min(), y.max()],
                               [min(history.J_eval_ci_low), max(history.J_eval_ci_high)])
    assert all(lo < J < hi for lo, J, hi in zip(history.J_eval_ci_low, history.J_eval,
                                                history.J_eval_ci_high))
    no_eval = dataclasses.replace(history, eval_month=[], J_eval=[], J_eval_ci_low=[],
                                  J_eval_ci_high=[])
    assert find_lines(fig2_performance(no_eval), "J_eval") == []
    # one draw (or a file from before the interval): the line without a band
    one = dataclasses.replace(history, learning=history.learning.replace(eval_draws=1),
                              J_eval_ci_low=[float("nan")] * len(history.J_eval),
                              J_eval_ci_high=[float("nan")] * len(history.J_eval))
    fig = fig2_performance(one)
    assert one_line(fig, "J_eval").get_label() == "evaluation (fixed draw)"
    assert [c for c in fig.axes[0].collections if c.get_gid() == "J_eval_ci"] == []


def test_fig2_rolling_mean_on_a_longer_history(history):
    J = [float(v) for v in np.linspace(100.0, 50.0, 12)]
    longer = dataclasses.replace(history, J=J)
    fig = fig2_performance(longer, rolling=4)
    rolling = one_line(fig, "J_rolling")
    expected = [np.mean(J[k - 3 : k + 1]) for k in range(3, 12)]
    np.testing.assert_allclose(rolling.get_ydata(), expected)
    # centred: the mean of months k-3 .. k is drawn at their middle, k - 1.5 (months from 1)
    np.testing.assert_allclose(rolling.get_xdata(), np.arange(4, 13) - 1.5)
    assert "centred" in rolling.get_label()
    with pytest.raises(ValueError, match="rolling=0"):
        fig2_performance(longer, rolling=0)


def test_fig2_centred_mean_of_a_step_changes_at_the_step(history):
    """J drops from 100 to 50 after month 6: the centred mean passes half-way (75) between
    months 6 and 7, where the step is; a trailing mean would pass it two months later."""
    J = [100.0] * 6 + [50.0] * 6
    fig = fig2_performance(dataclasses.replace(history, J=J), rolling=4)
    rolling = one_line(fig, "J_rolling")
    x, y = np.asarray(rolling.get_xdata()), np.asarray(rolling.get_ydata())
    assert x[np.flatnonzero(y == 75.0)].tolist() == [6.5]
    assert (y[x < 6.5] > 75.0).all() and (y[x > 6.5] < 75.0).all()
    # every mean lies within the months it averages: never above the data before the step
    assert (y <= 100.0).all() and (y[x >= 8.5] == 50.0).all()


def test_fig3_gradient_norm_log_scale(history):
    fig3, ax = plt.subplots()
    fig = fig3_gradient_norm(history, ax=ax)
    assert fig is fig3 and len(fig.axes) == 1
    assert ax.get_yscale() == "log"
    np.testing.assert_allclose(one_line(fig, "grad_norm").get_ydata(), history.grad_norm)


# -- Fig. 4 ------------------------------------------------------------------------------------
def test_fig4_grid_power_against_P_bar(history):
    rec = history.last_month
    fig = fig4_grid_power(history)
    assert len(fig.axes) == 1
    days = range(DAYS)
    np.testing.assert_allclose(one_line(fig, "grid_power").get_ydata()[:-1],
                               days_concat(rec.grid_power, days))
    np.testing.assert_allclose(one_line(fig, "planned_power").get_ydata()[:-1],
                               days_concat(rec.planned_power, days))
    hline_at(fig, "P_bar", history.system.P_bar)
    assert one_line(fig, "grid_power").get_color() == LAST_COLOR
    assert "MW" in fig.axes[0].get_ylabel() and "(h)" in fig.axes[0].get_xlabel()
    over = np.count_nonzero(rec.grid_power > history.system.P_bar + 1e-9)
    shaded = [p for p in fig.axes[0].patches if p.get_gid() == "P_over"]
    assert (len(shaded) > 0) == (over > 0)
    # the per-month applied power: the largest over all months, the share above P_bar
    note = [t for t in fig.axes[0].texts if t.get_gid() == "P_applied_months"]
    assert len(note) == 1
    top = int(np.argmax(history.max_P_applied))
    assert f"{history.max_P_applied[top]:.2f} MW (month {top + 1})" in note[0].get_text()
    last = 100.0 * over / (rec.grid_power.size)
    assert f"{last:.1f} % (month {MONTHS})" in note[0].get_text()


def _all_texts(fig) -> list[str]:
    """Every text a figure shows: titles, axis labels, legend entries and free texts."""
    texts = [t.get_text() for t in fig.texts]
    for ax in fig.axes:
        texts += [ax.get_title(loc) for loc in ("left", "center", "right")]
        texts += [ax.get_xlabel(), ax.get_ylabel()] + [t.get_text() for t in ax.texts]
        legend = ax.get_legend()
        if legend is not None:
            texts += [t.get_text() for t in legend.get_texts()]
    for legend in fig.legends:
        texts += [t.get_text() for t in legend.get_texts()]
    return [t for t in texts if t]


def test_the_grid_limit_is_written_as_mathtext_on_every_figure(history, tmp_path):
    """P̄ is ``$\\bar P$`` wherever a figure names it, never the plain identifier P_bar."""
    figures = [make(history) for make in (fig1_trajectories, fig2_performance,
                                          fig3_gradient_norm, fig4_grid_power,
                                          fig5_policy_and_agent_costs)]
    figures += [fig7_theta(history), plot_day(history.last_month, day=0)]
    texts = [t for fig in figures for t in _all_texts(fig)]
    named = [t for t in texts if r"\bar P" in t]
    assert len(named) >= 3, named  # Fig. 4's legend, shading and note, the day's legend
    assert not [t for t in texts if "P_bar" in t or "P̄" in t]


def test_fig4_days(history):
    fig = fig4_grid_power(history, days=2)
    assert fig.axes[0].get_xlim() == (0.0, 48.0)
    with pytest.raises(ValueError, match=f"days={DAYS + 1}"):
        fig4_grid_power(history, days=DAYS + 1)


# -- Fig. 5 ------------------------------------------------------------------------------------
def test_fig5_policy_scatter_and_agent_costs(history):
    n = history.system.n
    rec = history.last_month
    fig = fig5_policy_and_agent_costs(history)
    assert len(fig.axes) == 2
    ax_pi, ax_J = fig.axes
    scatters = {c.get_gid(): c for c in ax_pi.collections}
    J_i = np.asarray(history.J_per_agent)
    for i in range(n):
        points = scatters[f"policy[{i + 1}]"].get_offsets()
        np.testing.assert_allclose(points[:, 1], rec.policy[:, :, i].reshape(-1))
        hours = np.floor(points[:, 0]).astype(int)  # every point sits inside its hour
        np.testing.assert_array_equal(hours, np.repeat(np.arange(rec.policy.shape[0]), DAYS))
        np.testing.assert_allclose(one_line(ax_J, f"J[{i + 1}]").get_ydata(), J_i[:, i])
    ubar = sorted(float(line.get_ydata()[0]) for line in find_lines(ax_pi, "U_bar"))
    assert ubar == [-history.system.U_bar, history.system.U_bar]


# -- Fig. 6 ------------------------------------------------------------------------------------
def test_fig6_prices():
    prices = Prices.default()
    fig = fig6_prices(prices)
    lines = [line for line in fig.axes[0].get_lines() if line.get_gid().startswith("buy day")]
    assert len(lines) == 5
    for d, line in enumerate(lines):
        np.testing.assert_allclose(line.get_ydata(), prices.buy[d])
    assert "NOK/MWh" in fig.axes[0].get_ylabel()
    fig = fig6_prices(prices, days=[4, 20])
    np.testing.assert_allclose(one_line(fig, "buy day 21").get_ydata(), prices.buy[20])
    with pytest.raises(ValueError, match="day=40"):
        fig6_prices(prices, days=(0, 40))
    with pytest.raises(ValueError, match="days=\\[\\]"):
        fig6_prices(prices, days=[])


# -- Fig. 7 ------------------------------------------------------------------------------------
def _untied(history: History) -> History:
    """The history with agent i's theta moved by i/10 (plus a tenth of its size): per-agent
    values that differ in every part."""
    n = history.system.n
    shift = np.tile(np.arange(n) / 10.0, len(history.theta_final) // n)

    def untie(t):
        t = np.asarray(t, dtype=float)
        return list(t + shift * (1.0 + np.abs(t)))

    return dataclasses.replace(history, theta=[untie(t) for t in history.theta],
                               theta_final=untie(history.theta_final))


@pytest.mark.parametrize("part", ["delta", "alpha", "T1"])
def test_fig7_theta(history, part):
    untied = _untied(history)
    fig = fig7_theta(untied, part)
    values = untied.theta_part(part)
    assert values.shape == (MONTHS + 1, history.system.n)
    assert not np.allclose(values, values[:, :1])
    for i in range(history.system.n):
        line = one_line(fig, f"theta_{part}[{i + 1}]")
        np.testing.assert_allclose(line.get_ydata(), values[:, i])
        np.testing.assert_allclose(line.get_xdata(), np.arange(MONTHS + 1))
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert len(labels) == history.system.n and not any("tied" in t for t in labels)


def test_fig7_draws_tied_agents_as_one_line_labelled_tied(history):
    """With tie_agents (the default) every agent holds the same value: one line, one legend
    entry that says so, instead of n entries over one visible line."""
    assert history.learning.tie_agents
    values = history.theta_part("delta")
    np.testing.assert_array_equal(values, np.repeat(values[:, :1], history.system.n, axis=1))
    fig = fig7_theta(history, "delta")
    ax = fig.axes[0]
    data_lines = [line for line in ax.get_lines() if (line.get_gid() or "").startswith("theta_")]
    assert [line.get_gid() for line in data_lines] == ["theta_delta[tied]"]
    np.testing.assert_allclose(data_lines[0].get_ydata(), values[:, 0])
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert len(labels) == 1 and f"all {history.system.n} agents (tied)" in labels[0]


def test_fig7_unknown_part(history):
    with pytest.raises(ValueError, match="'gamma'"):
        fig7_theta(history, "gamma")


# -- empty history, files ----------------------------------------------------------------------
def test_empty_history_is_rejected(history):
    empty = History(history.system, history.mpc, history.learning)
    for make in (fig2_performance, fig3_gradient_norm, fig1_trajectories, fig4_grid_power):
        with pytest.raises(ValueError, match="no months"):
            make(empty)


def test_save_paper_figures(history, tmp_path):
    paths = save_paper_figures(history, tmp_path / "figs")
    assert [p.name for p in paths] == list(PAPER_FIGURES)
    assert PAPER_FIGURES[-1] == "fig7_theta_delta.png"
    for path in paths:
        data = path.read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 5000, path
    assert plt.get_fignums() == []  # every figure was closed


def test_figures_from_a_saved_history(history, tmp_path):
    loaded = History.load(history.save(tmp_path / "run"))
    fig = fig1_trajectories(loaded)
    np.testing.assert_allclose(one_line(fig, "policy[2] first").get_ydata()[:-1],
                               days_concat(history.first_month.policy, range(DAYS), 1))
    fig = fig5_policy_and_agent_costs(loaded)
    np.testing.assert_allclose(one_line(fig, "J[3]").get_ydata(),
                               np.asarray(history.J_per_agent)[:, 2])


def test_public_api():
    for name in plots.__all__:
        assert hasattr(plots, name), name


def test_fig2_draws_few_evaluations_as_points_with_error_bars(history):
    """Two evaluations: no line and no band between them (a trend nobody measured)."""
    two = dataclasses.replace(history, eval_month=history.eval_month[:2],
                              J_eval=history.J_eval[:2],
                              J_eval_ci_low=history.J_eval_ci_low[:2],
                              J_eval_ci_high=history.J_eval_ci_high[:2])
    fig = fig2_performance(two)
    evaluation = one_line(fig, "J_eval")
    assert evaluation.get_linestyle() == "None" and len(evaluation.get_xdata()) == 2
    ax = fig.axes[0]
    bars = [c for c in ax.collections if c.get_gid() == "J_eval_ci"]
    assert len(bars) == 1 and len(bars[0].get_segments()) == 2  # one error bar per point
    low, high = sorted(bars[0].get_segments()[0][:, 1])
    assert (low, high) == pytest.approx((two.J_eval_ci_low[0], two.J_eval_ci_high[0]))
    assert not [c for c in ax.collections if c.get_gid() == "J_eval_ci"
                and type(c).__name__ == "FillBetweenPolyCollection"]
    # the evaluations sit at the first and the last month: drawn above those months' markers
    marks = [line for line in ax.get_lines() if line.get_label() in ("first month", "last month")]
    assert len(marks) == 2
    assert evaluation.get_zorder() > max(m.get_zorder() for m in marks)
    assert bars[0].get_zorder() > max(m.get_zorder() for m in marks)


def test_fig2_draws_three_evaluations_as_a_line_with_a_band(history):
    J = [float(v) for v in np.linspace(100.0, 60.0, 4)]
    months = [0, 1, 3]
    J_eval = [J[m] for m in months]
    three = dataclasses.replace(history, J=J, eval_month=months, J_eval=J_eval,
                                J_eval_ci_low=[j - 5.0 for j in J_eval],
                                J_eval_ci_high=[j + 5.0 for j in J_eval])
    fig = fig2_performance(three)
    assert one_line(fig, "J_eval").get_linestyle() == "--"
    (band,) = [c for c in fig.axes[0].collections if c.get_gid() == "J_eval_ci"]
    y = band.get_paths()[0].vertices[:, 1]
    np.testing.assert_allclose([y.min(), y.max()], [min(J_eval) - 5.0, max(J_eval) + 5.0])


def test_every_figure_is_drawn_inside_its_canvas(history):
    """The notebooks show figures uncropped; nothing may then fall off their edge."""
    from conftest import assert_drawn_inside

    prices = Prices.default()
    system = SystemConfig()
    plan, curve, fit = _plan_curve_fit()
    figures = [
        fig1_trajectories(history), fig2_performance(history), fig3_gradient_norm(history),
        fig4_grid_power(history), fig5_policy_and_agent_costs(history), fig6_prices(prices),
        fig7_theta(history, part="delta"), fig7_theta(_untied(history), part="T1"),
        plot_day(history.last_month, day=1),
        plots.plot_price_window(prices, day=29, hour=20, N=12),
        plots.plot_plan(plan, system, buy=prices.buy[0, :12], title="plan"),
        plots.plot_policy_curve(curve, {**curve, "tau": 1e-5}), plots.plot_value_fit(fit),
    ]
    for fig in figures:
        assert_drawn_inside(fig)
