"""The explorers of mpcrl_lite.widgets, driven from code (no kernel needed).

Setting a control's value runs the same callback as releasing the slider in a notebook, so each
test changes controls and checks the recomputed result against the invariants of the system:
soc in [0, 1], the MPC's planned grid power below P_bar, the same noise for the same seed.
Update times are printed (``pytest -s``), not asserted: timings belong in benchmarks/.
"""

from __future__ import annotations

import time

import ipywidgets as widgets
import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.experiment import run_month
from mpcrl_lite.model import grid_power, split_action
from mpcrl_lite.mpc import MPC
from mpcrl_lite.prices import Prices
from mpcrl_lite.solvers import make_solver
from mpcrl_lite.theta import Theta
from mpcrl_lite.widgets import (DayPrices, cached_solver, day_explorer, lstd_explorer,
                                policy_curve, price_day_picker, rule_explorer, simulate_day,
                                state_features, tau_explorer, value_fit)

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
    return [c for c in explorer.controls.values()
            if isinstance(c, (widgets.FloatSlider, widgets.IntSlider, widgets.SelectionSlider))]


@pytest.fixture(scope="module")
def day():
    return day_explorer(seed=0)


# -- day explorer --------------------------------------------------------------------------
def test_day_explorer_is_a_widget_with_a_figure(day):
    assert isinstance(day, widgets.VBox)
    assert set(day.controls) == {"P_bar", "noise_var", "price_scale", "tau", "N", "day", "seed"}
    assert all(not s.continuous_update for s in _sliders(day)), "must update on release only"
    assert bytes(day.image.value).startswith(PNG)
    assert day.result.soc.shape == (25, 1, 3)
    assert "J =" in day.status.value


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
    _timed(day, "day", 7)
    np.testing.assert_allclose(day.result.buy[:, 0], month.buy[7])
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
    first = explorer.summary["J"]
    noise = explorer.result.noise.copy()
    _timed(explorer, "theta", "T2 = -300")
    assert explorer.summary["J"] != first
    np.testing.assert_array_equal(explorer.result.noise, noise)   # compared on the same draws


def test_one_day_matches_the_same_day_of_a_whole_month():
    """The one-day view reads on into the next day's prices, exactly as in a month."""
    system = SystemConfig(noise_var=0.0)
    month = Prices.default(system)
    tau = 1e-4  # the same barrier on both sides (the widgets' default)
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


def test_solvers_are_cached_per_formulation():
    system = SystemConfig()
    a = cached_solver(system, 1e-4)
    assert cached_solver(system.replace(noise_var=0.1, price_scale=2.0), 1e-4) is a
    assert cached_solver(system.replace(P_bar=1.0), 1e-4) is not a
    assert cached_solver(system, 1e-3) is not a


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
    explorer = tau_explorer(points=11, tau=1e-2)
    assert all(not s.continuous_update for s in _sliders(explorer))
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
    _timed(picker, "N", 24)
    assert picker.result["buy"].shape == (24,)
    _timed(picker, "day", 29)
    assert picker.result["buy"][4] == month.buy[0, 0]                # the month is cyclic
    assert bytes(picker.image.value).startswith(PNG)


def test_rule_explorer_obeys_the_invariants():
    explorer = rule_explorer(seed=1)
    system = SystemConfig()
    for name, value in (("buy_below", 60.0), ("sell_above", 30.0), ("noise_var", 1.5),
                        ("soc_min", 0.1), ("soc_max", 0.9), ("day", 12)):
        _timed(explorer, name, value)
        t = explorer.result
        assert 0.0 <= t.soc.min() and t.soc.max() <= 1.0
        commanded = grid_power(*split_action(t.a.reshape(-1, system.n)))
        assert commanded.max() <= system.P_bar + 1e-12
    assert explorer.result.system.noise_var == 1.5


# -- LSTD explorer -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def record():
    system = SystemConfig()
    solver = make_solver(MPC(system), MPCConfig())
    return run_month(Theta.nominal(system), solver, Prices.month(system, 4), system,
                     np.random.default_rng(0), exploration_std=0.05, sensitivities=False)


def test_lstd_explorer_hour_features_reproduce_the_returns(record):
    explorer = lstd_explorer(record)
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
    with pytest.raises(ValueError, match="kind"):
        state_features(record.soc, np.zeros(25), "cubic")
