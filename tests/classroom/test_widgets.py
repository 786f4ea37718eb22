"""The explorers of mpcrl_lite.classroom.widgets, driven from code (no kernel needed).

Setting a control's value runs the same callback as releasing the slider in a notebook, so each
test changes controls and checks the recomputed result against the invariants of the system:
soc in [0, 1], the MPC's planned grid power below P_bar, the same noise for the same seed.
The classroom requirements are checked on the widget objects: every control has an accessible
name and a tooltip (no ``title="null"``), sliders run from small to large values and send on
release only, days are shown from 1, daily costs are in NOK/day, images are drawn at 150 dpi and
never shown wider than drawn. (``tools/check_widget_accessibility.py`` checks the same in a
browser.)
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import time

import ipywidgets as widgets
import numpy as np
import pytest

from mpcrl_lite.classroom import explorers as explore
from mpcrl_lite.classroom import widgets as w
from mpcrl_lite.classroom.controls import StepSlider, accessible_name, float_slider
from mpcrl_lite.classroom.explorers import (
    DayPrices,
    cached_solver,
    policy_curve,
    simulate_day,
    threshold_rule,
    value_fit,
)
from mpcrl_lite.classroom.widgets import (
    day_explorer,
    lstd_explorer,
    price_day_picker,
    rule_explorer,
    tau_explorer,
)
from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.learning.lstd import lstd_v, state_features, value_baseline_features
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import rollout, run_month
from mpcrl_lite.system.battery import grid_power, split_action
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

PNG = b"\x89PNG"


def _timed(explorer, name, value):
    t0 = time.perf_counter()
    explorer.controls[name].value = value
    seconds = time.perf_counter() - t0
    print(f"{type(explorer).__name__}: {name} = {value!r} -> update in {seconds:.3f} s "
          f"(explorer's own timing {explorer.last_update_s:.3f} s)")
    assert explorer.error is None, explorer.error
    return seconds


def _sliders(explorer):
    return [c for c in explorer.controls.values() if isinstance(c, StepSlider)]


def _png_size(data: bytes) -> tuple[int, int]:
    assert data.startswith(PNG)
    return struct.unpack(">II", data[16:24])


def _all_widgets(widget):
    yield widget
    for child in getattr(widget, "children", ()):
        yield from _all_widgets(child)


@pytest.fixture(scope="module")
def day():
    return day_explorer(seed=0)


@pytest.fixture(scope="module")
def record():
    system = SystemConfig()
    solver = make_solver(MPC(system), MPCConfig())
    return run_month(Theta.nominal(system), solver, Prices.month(system, 4), system,
                     np.random.default_rng(0), exploration_std=0.05, sensitivities=False)


@pytest.fixture(scope="module")
def explorers(day, record):
    """One explorer of each kind (the MPC ones without PNGs where the PNG is not needed)."""
    return {
        "prices": price_day_picker(day=3),
        "rule": rule_explorer(render=False),
        "day": day,
        "tau": tau_explorer(points=7, render=False),
        "lstd": lstd_explorer(record, render=False),
    }


# -- classroom requirements ----------------------------------------------------------------
def test_every_control_has_an_accessible_name_and_a_tooltip(explorers):
    for kind, explorer in explorers.items():
        for name, control in explorer.controls.items():
            assert accessible_name(control).strip(), f"{kind}.{name} has no accessible name"
            assert control.tooltip, f"{kind}.{name} has no tooltip"
            if isinstance(control, StepSlider):
                assert control.aria_label.strip() and control.description.strip()
            else:   # native inputs: the description is tied to the input by <label for>
                assert control.description.strip()
        # an ipywidgets label with tooltip None renders title="null": none may be left unset
        for widget in _all_widgets(explorer):
            if isinstance(widget, widgets.widget_description.DescriptionWidget):
                assert widget.tooltip is not None, f"{kind}: {type(widget).__name__}"


def test_sliders_send_on_release_and_run_from_small_to_large(explorers):
    for kind, explorer in explorers.items():
        for slider in _sliders(explorer):
            assert not slider.continuous_update, f"{kind}.{slider.description}: on drag"
            assert slider.options == sorted(slider.options), f"{kind}: {slider.description}"
            assert len(slider.labels) == len(slider.options)


def test_the_tau_slider_is_logarithmic_and_increases_to_the_right(explorers):
    for kind in ("day", "tau"):
        slider = explorers[kind].controls["tau"]
        assert slider.options == sorted(explore.TAUS)
        ratios = np.diff(np.log10(slider.options))
        np.testing.assert_allclose(ratios, 1.0)              # equal steps = one decade each
        assert slider.value == MPCConfig().tau               # the package default, 0.1
        assert slider.index == len(slider.options) - 1       # 0.1 is the largest: rightmost
        assert slider.labels[0] == "1e-05" and slider.labels[-1] == "1e-01"


def test_defaults_come_from_the_configs(explorers):
    default = MPCConfig()
    assert explore.resolve_mpc_config() == default
    assert explorers["tau"].result["tau"] == default.tau
    assert explorers["day"].mpc_config == default
    config = explore.resolve_mpc_config(MPCConfig(max_iter=50, tol=1e-9), tau=1e-3,
                                        backend="batch")
    assert (config.tau, config.backend, config.max_iter, config.tol) == (1e-3, "batch", 50, 1e-9)
    explorer = day_explorer(mpc_config=MPCConfig(max_iter=77), render=False)
    assert explorer.controls["tau"].value == 0.1 and explorer.mpc_config.max_iter == 77


def test_days_are_counted_from_one_in_the_interface(explorers):
    picker = explorers["prices"]
    slider = picker.controls["day"]
    assert slider.value == 3 and slider.labels[slider.index] == "4 of 30"
    assert slider.labels[0] == "1 of 30" and slider.labels[-1] == "30 of 30"
    texts = [t.get_text() for t in picker.figure.axes[0].texts]
    assert "day 4" in texts and "day 5 (next)" in texts
    rule = explorers["rule"]
    _timed(rule, "day", 7)
    assert rule.figure.axes[0].get_title("left").startswith("Rule, day 8:")
    _timed(rule, "day", 0)


def test_daily_costs_are_in_nok_per_day(explorers):
    for kind in ("rule", "day"):
        explorer = explorers[kind]
        assert "NOK/day" in explorer.status.value
        assert "NOK/day" in explorer.figure.axes[0].get_title("left")


def test_explorer_images_are_sharp_and_not_stretched(explorers):
    picker = explorers["prices"]
    width, height = _png_size(bytes(picker.image.value))
    w_in, h_in = picker.figure.get_size_inches()
    assert (width, height) == (round(w_in * 150), round(h_in * 150))
    assert picker.dpi == 150
    # shown at 100 CSS px per inch (1.5 image pixels per CSS pixel), at most as wide as the
    # output area, with the height following the width
    assert picker.image.width == str(round(w_in * 100))
    assert picker.image.layout.max_width == "100%" and picker.image.layout.height == "auto"
    assert picker.image.layout.width is None


def test_off_grid_slider_values_are_rejected_with_the_value_named():
    slider = float_slider("P_bar (MW)", 1.5, 0.1, 3.0, 0.1, ".1f")
    slider.value = 0.30000000000000004            # round-off of 0.1 + 0.2 is accepted
    assert slider.value == 0.3
    with pytest.raises(ValueError, match=r"P_bar \(MW\)=1.05"):
        slider.value = 1.05
    with pytest.raises(ValueError, match="=9.0"):
        slider.value = 9.0


def test_an_error_is_shown_and_the_explorer_stays_usable(monkeypatch):
    explorer = price_day_picker(render=False)

    def broken(*args, **kwargs):
        raise RuntimeError("no prices <today>")

    monkeypatch.setattr(w, "price_window", broken)
    explorer.controls["hour"].value = 5                # the callback does not raise
    assert isinstance(explorer.error, RuntimeError)
    assert "no prices &lt;today&gt;" in explorer.status.value
    monkeypatch.undo()
    _timed(explorer, "hour", 6)
    assert explorer.result["buy"].shape == (12,)


# -- day explorer --------------------------------------------------------------------------
def test_day_explorer_is_a_widget_with_a_figure(day):
    assert isinstance(day, widgets.VBox)
    assert set(day.controls) == {"P_bar", "noise_var", "price_scale", "tau", "N", "day", "seed"}
    assert bytes(day.image.value).startswith(PNG)
    assert day.result.soc.shape == (25, 1, 3)
    assert "J =" in day.status.value


def test_explorer_pictures_say_what_they_show(day):
    """The picture's alt text carries the figure's numbers: the day's J, the grid limit P̄
    and the panels' series, in plain text (no TeX, no HTML)."""
    alt = day.image.alt
    J = day.result.summary()["J"]
    assert alt.startswith("Figure:") and f"J = {J:.1f} NOK/day" in alt
    assert f"P̄ = {day.values['P_bar']:g} MW" in alt and "agent 1" in alt
    assert "$" not in alt and "\\" not in alt and "<" not in alt.replace("soc < 0.1", "")
    day.controls["P_bar"].value = 1.0
    assert "P̄ = 1 MW" in day.image.alt and day.image.alt != alt
    day.controls["P_bar"].value = 1.5


def test_day_explorer_keeps_the_grid_limit_when_P_bar_changes(day):
    for p_bar in (1.0, 0.5, 2.0, 1.5):
        before = day.updates
        _timed(day, "P_bar", p_bar)
        assert day.updates == before + 1
        summary = day.summary
        assert day.result.system.P_bar == p_bar
        assert summary["max_P_mpc"] <= p_bar
        assert summary["solver_failures"] == 0
        assert 0.0 <= day.result.soc.min() and day.result.soc.max() <= 1.0


def test_day_explorer_noise_variance_scales_the_same_draws(day):
    _timed(day, "noise_var", 0.0)
    assert np.all(day.result.noise == 0.0)
    _timed(day, "noise_var", 1.0)
    unit = day.result.noise.copy()
    _timed(day, "noise_var", 0.25)
    # same seed: the same standard normal draws, scaled by the standard deviation
    np.testing.assert_allclose(day.result.noise, 0.5 * unit, rtol=1e-12)
    _timed(day, "noise_var", 0.5)
    assert 0.0 <= day.result.soc.min() and day.result.soc.max() <= 1.0


def test_day_explorer_price_scale_day_tau_and_horizon(day):
    month = Prices.default()
    _timed(day, "price_scale", 2.0)
    np.testing.assert_allclose(day.result.buy[:, 0], 2.0 * month.buy[0])
    _timed(day, "price_scale", 1.0)
    _timed(day, "day", 7)                          # the day index; the slider shows "8 of 30"
    np.testing.assert_allclose(day.result.buy[:, 0], month.buy[7])
    assert day.figure.axes[0].get_title("left").startswith("MPC, day 8:")
    _timed(day, "day", 0)
    for tau in (1e-1, 1e-5, 1e-4):
        _timed(day, "tau", tau)
        assert day.summary["solver_failures"] == 0
        assert day.summary["max_P_mpc"] <= day.controls["P_bar"].value
    for N in (4, 24, 12):
        _timed(day, "N", N)
        assert day.result.system.N == N
        assert day.summary["max_P_mpc"] <= day.controls["P_bar"].value


def test_day_explorer_switches_between_named_thetas():
    theta0 = Theta.nominal()
    keep = theta0.replace(T2=np.full(3, -300.0))
    explorer = day_explorer(theta={"theta0": theta0, "T2 = -300": keep}, seed=3, render=False)
    assert accessible_name(explorer.controls["theta"]) and explorer.controls["theta"].tooltip
    first = explorer.summary["J"]
    noise = explorer.result.noise.copy()
    _timed(explorer, "theta", "T2 = -300")
    assert explorer.summary["J"] != first
    np.testing.assert_array_equal(explorer.result.noise, noise)   # compared on the same draws


def test_one_day_matches_the_same_day_of_a_whole_month():
    """The one-day view reads on into the next day's prices, exactly as in a month."""
    system = SystemConfig(noise_var=0.0)
    month = Prices.default(system)
    tau = 1e-4  # the same barrier on both sides
    solver = make_solver(MPC(system), MPCConfig(tau=tau))
    full = run_month(Theta.nominal(system), solver, month, system, np.random.default_rng(0),
                     sensitivities=False)
    for d in (4, month.days - 1):
        one = simulate_day(system, day=d, seed=0, tau=tau, prices=month)
        np.testing.assert_allclose(one.soc[:, 0], full.soc[:, d], atol=1e-9)
        np.testing.assert_allclose(one.policy[:, 0], full.policy[:, d], atol=1e-9)
    view = DayPrices(month, 29)
    buy, sell = view.window(20, 12)
    np.testing.assert_array_equal(buy[0], np.concatenate([month.buy[29, 20:], month.buy[0, :8]]))
    np.testing.assert_array_equal(sell, 0.5 * buy)
    with pytest.raises(ValueError, match="day"):
        DayPrices(month, 30)


def test_solvers_are_cached_per_formulation_and_whole_config():
    system = SystemConfig()
    a = cached_solver(system, MPCConfig(tau=1e-4))
    assert a.config == MPCConfig(tau=1e-4)
    assert cached_solver(system.replace(noise_var=0.1, price_scale=2.0), MPCConfig(tau=1e-4)) is a
    assert cached_solver(system.replace(P_bar=1.0), MPCConfig(tau=1e-4)) is not a
    assert cached_solver(system, MPCConfig(tau=1e-3)) is not a
    # every setting counts, not only tau and the back-end
    other = cached_solver(system, MPCConfig(tau=1e-4, max_iter=60))
    assert other is not a and other.config.max_iter == 60
    # the older calls (system, tau[, backend]) and tau= give the same solver
    assert cached_solver(system, 1e-4) is a
    assert cached_solver(system, tau=1e-4) is a
    assert cached_solver(system, 1e-4, "auto") is a
    assert cached_solver(system).config == MPCConfig()
    with pytest.raises(ValueError, match="tau given twice"):
        cached_solver(system, 1e-4, tau=1e-3)
    with pytest.raises(ValueError, match="mpc_config="):
        cached_solver(system, "fast")


def test_day_explorer_seed_redraws_the_noise_and_a_seed_gives_its_day_back(day):
    """The seed control shows simulate_day's day for that seed; another seed draws other
    noise, and going back reproduces the first day exactly."""
    _timed(day, "seed", 12)
    noise, policy, J = day.result.noise.copy(), day.result.policy.copy(), day.summary["J"]
    same = simulate_day(day.result.system, day=day.controls["day"].value, seed=12,
                        tau=float(day.controls["tau"].value))
    np.testing.assert_array_equal(noise, same.noise)
    np.testing.assert_allclose(policy, same.policy, atol=1e-9)
    before = day.updates
    _timed(day, "seed", 13)
    assert day.updates == before + 1
    assert not np.allclose(day.result.noise, noise)
    _timed(day, "seed", 12)
    np.testing.assert_array_equal(day.result.noise, noise)
    np.testing.assert_array_equal(day.result.policy, policy)
    assert day.summary["J"] == J
    _timed(day, "seed", 0)  # the fixture's seed, for whatever runs next


# -- tau explorer --------------------------------------------------------------------------
def test_tau_explorer_policy_curves():
    explorer = tau_explorer(points=11, tau=1e-2, render=False)
    curve = explorer.result
    assert curve["tau"] == 1e-2 and curve["success"].all()
    assert np.all(np.diff(curve["policy"][:, 0]) <= 1e-8)          # never sells less
    assert explorer.reference["tau"] == 1e-5
    _timed(explorer, "tau", 1e-1)
    assert explorer.result["tau"] == 1e-1
    _timed(explorer, "variable", "soc")
    assert explorer.result["x"].min() == 0.0 and explorer.result["x"].max() == 1.0
    _timed(explorer, "P_bar", 1.0)
    pi = explorer.result["policy"]
    assert np.all(np.maximum(np.clip(pi, 0, None).sum(1), np.clip(-pi, 0, None).sum(1)) <= 1.0)


def test_policy_curve_is_symmetric_at_zero_correction():
    curve = policy_curve("theta_s", [-5.0, 0.0, 5.0], tau=1e-3)
    assert np.ptp(curve["policy"][1]) < 1e-6
    assert curve["policy"][0, 0] > curve["policy"][1, 0] > curve["policy"][2, 0]
    with pytest.raises(ValueError, match="variable"):
        policy_curve("alpha")


# -- price picker, rule explorer -----------------------------------------------------------
def test_price_day_picker_shows_the_forecast_window():
    picker = price_day_picker(day=3, hour=20, N=12)
    month = Prices.default()
    np.testing.assert_array_equal(picker.result["buy"],
                                  np.concatenate([month.buy[3, 20:], month.buy[4, :8]]))
    assert picker.controls["hour"].labels[20] == "20:00"
    _timed(picker, "N", 24)
    assert picker.result["buy"].shape == (24,)
    _timed(picker, "day", 29)
    assert picker.result["buy"][4] == month.buy[0, 0]                # the month is cyclic
    assert bytes(picker.image.value).startswith(PNG)


def test_rule_explorer_obeys_the_invariants():
    explorer = rule_explorer(seed=1, render=False)
    system = SystemConfig()
    for name, value in (("buy_below", 60.0), ("sell_above", 30.0), ("noise_var", 1.5),
                        ("soc_min", 0.1), ("soc_max", 0.9), ("day", 12)):
        _timed(explorer, name, value)
        t = explorer.result
        assert 0.0 <= t.soc.min() and t.soc.max() <= 1.0
        commanded = grid_power(*split_action(t.a.reshape(-1, system.n)))
        assert commanded.max() <= system.P_bar + 1e-12
    assert explorer.result.system.noise_var == 1.5


def test_rule_day_is_the_closed_loop_under_the_rule():
    system = SystemConfig()
    month = Prices.default(system)
    day = explore.rule_day(system, day=5, seed=4, buy_below=30.0, sell_above=50.0,
                           prices=month)
    rule = threshold_rule(month.buy[5:6], 30.0, 50.0, system)
    direct = rollout(rule, month.buy[5:6], month.sell[5:6], system, np.random.default_rng(4))
    np.testing.assert_array_equal(day.soc, direct.soc)
    np.testing.assert_array_equal(day.a, direct.a)


# -- LSTD explorer -------------------------------------------------------------------------
def test_lstd_explorer_hour_features_reproduce_the_returns(record):
    explorer = lstd_explorer(record, render=False)
    assert explorer.result["features"] == "paper"
    _timed(explorer, "features", "hour")
    fit = explorer.result
    np.testing.assert_allclose(fit["fit"].v, fit["G"].mean(axis=1), rtol=1e-9)
    _timed(explorer, "days", 2)
    assert explorer.result["G"].shape == (24, 2)
    _timed(explorer, "gamma", 1.0)
    np.testing.assert_allclose(explorer.result["fit"].v, explorer.result["G"].mean(axis=1),
                               rtol=1e-9)


def test_value_fit_and_features_shapes(record):
    hours = np.arange(24)[:, None].repeat(4, axis=1)
    assert state_features(record.soc[:-1], hours, "paper").shape == (24, 4, 7)
    assert state_features(record.soc[:-1], hours, "hour").shape == (24, 4, 24)
    assert state_features(record.soc[:-1], hours, "paper+hour").shape == (24, 4, 30)
    fit = value_fit(record, "paper+hour")
    assert fit["r2"] >= value_fit(record, "hour")["r2"] - 1e-9
    with pytest.raises(ValueError, match="days"):
        value_fit(record, days=5)
    with pytest.raises(ValueError, match="features"):
        value_fit(record, "cubic")
    with pytest.raises(ValueError, match="kind"):
        state_features(record.soc, np.zeros(25), "cubic")


def test_value_fit_uses_the_critics_features(record):
    """The explorer's fit is the learning loop's LSTD on the critic's features."""
    features = value_baseline_features(record.soc, "paper+hour")
    H = record.stage_cost.shape[0]
    done = np.broadcast_to((np.arange(H) == H - 1)[:, None], record.stage_cost.shape)
    direct = lstd_v(features[:-1], record.stage_cost, features[1:], record.system.gamma,
                    done=done)
    np.testing.assert_allclose(value_fit(record, "paper+hour")["fit"].v, direct.v, rtol=1e-12)


def test_data_and_figures_do_not_depend_on_the_widgets():
    """explore and plots sit below widgets in the data flow: no ipywidgets to import them."""
    code = ("import sys; import mpcrl_lite.classroom.explorers, mpcrl_lite.figures.plots, mpcrl_lite.cli.main; "
            "bad = [m for m in ('ipywidgets', 'anywidget', 'mpcrl_lite.classroom.widgets', "
            "'mpcrl_lite.classroom.controls') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False,
                          env={**os.environ, "MPLBACKEND": "Agg"}, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
