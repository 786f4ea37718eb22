"""Baselines on common draws: the clairvoyant bound, the nominal MPC, the rule, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite.bounds.baselines import evaluate_baselines, run_baselines_cli
from mpcrl_lite.bounds.clairvoyant import clairvoyant, clairvoyant_lp
from mpcrl_lite.bounds.rule import RuleBasedPolicy
from mpcrl_lite.bounds.scenario import Scenario, evaluate_policy, make_scenario
from mpcrl_lite.config import LearningConfig, MPCConfig, SystemConfig
from mpcrl_lite.learning.history import History
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import MPCPolicy, run_month
from mpcrl_lite.system.battery import penalty
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SYSTEM = SystemConfig()
IPOPT = MPCConfig(backend="ipopt")


@pytest.fixture(scope="module")
def solver() -> IpoptSolver:
    return IpoptSolver(MPC(SYSTEM), IPOPT)


def random_theta(seed: int) -> Theta:
    """A random but well-posed theta (convex MPC, positive model gain)."""
    rng = np.random.default_rng(seed)
    nominal = Theta.nominal(SYSTEM)
    n = SYSTEM.n
    return nominal.replace(
        alpha=nominal.alpha * rng.uniform(0.7, 1.3, n),
        delta=rng.uniform(-0.02, 0.02, n),
        b=rng.uniform(-5, 5, n),
        s=rng.uniform(-5, 5, n),
        phi1=rng.uniform(0, 50, n),
        phi2=rng.uniform(-20, 20, n),
        T1=rng.uniform(0, 50, n),
        T2=rng.uniform(-20, 20, n),
    )


def lp_point(result, scenario: Scenario, day: int) -> np.ndarray:
    """A closed loop written as a point of the clairvoyant LP (the proof's construction)."""
    lay = clairvoyant_lp(scenario, day)[-1]
    t = result.trajectory
    a = t.a[:, day]
    b, s, soc = t.b[:, day], t.s[:, day], t.soc[:, day]
    ub, us = np.minimum(b, np.maximum(a, 0)), np.minimum(s, np.maximum(-a, 0))
    sysc = scenario.system
    z = np.zeros(lay.size)
    values = {
        "ub": ub, "us": us, "eb": b - ub, "es": s - us, "soc": soc[1:],
        "ehi": np.maximum(soc[1:-1] - sysc.soc_high, 0),
        "elo": np.maximum(sysc.soc_low - soc[1:-1], 0),
    }
    for key, value in values.items():
        z[lay.block(key)] = value
    return z


def check_lp_point(scenario: Scenario, day: int, z: np.ndarray, tol: float = 1e-8) -> float:
    """Assert ``z`` is feasible for the day's LP; return its cost (constant included)."""
    c, A_ub, b_ub, A_eq, b_eq, bounds, _ = clairvoyant_lp(scenario, day)
    lower, upper = np.array(bounds).T
    assert np.all(z >= lower - tol) and np.all(z <= upper + tol)
    np.testing.assert_allclose(A_eq @ z, b_eq, atol=tol)
    assert np.all(A_ub @ z <= b_ub + tol), np.max(A_ub @ z - b_ub)
    const = penalty(scenario.soc0[day], scenario.system).sum()
    return float(c @ z + const)


# -- the scenario ---------------------------------------------------------------------------
def test_scenario_is_reproducible_and_validated():
    one, two = make_scenario(SYSTEM, 3, 7), make_scenario(SYSTEM, 3, 7)
    np.testing.assert_array_equal(one.noise, two.noise)
    assert one.noise.shape == (24, 3, 3)
    assert not np.array_equal(one.noise, make_scenario(SYSTEM, 3, 8).noise)
    with pytest.raises(ValueError, match="days=0"):
        make_scenario(SYSTEM, 0, 1)
    with pytest.raises(ValueError, match="seed=-1"):
        make_scenario(SYSTEM, 2, -1)
    with pytest.raises(ValueError, match=r"noise has shape \(24, 2, 2\)"):
        Scenario(SYSTEM, Prices.month(SYSTEM, 2), np.zeros((24, 2, 2)), 0.6)
    with pytest.raises(ValueError, match="prices have 3 days; expected days=2"):
        make_scenario(SYSTEM, 2, 0, prices=Prices.month(SYSTEM, 3))
    # more days than the memory holds: refused before the month is repeated or noise drawn
    with pytest.raises(ValueError, match=r"days=1000000000, n=3: needs about .* GiB"):
        make_scenario(SYSTEM, 10**9, 0)


def test_nominal_evaluation_matches_run_month(solver):
    """The scenario's noise is the one run_month draws from the same seed."""
    scenario = make_scenario(SYSTEM, 2, 11)
    theta = Theta.nominal(SYSTEM)
    mine = evaluate_policy(MPCPolicy(solver, theta, scenario.prices), scenario)
    record = run_month(theta, solver, scenario.prices, SYSTEM, np.random.default_rng(11),
                       exploration_std=0.0, sensitivities=False)
    np.testing.assert_array_equal(record.noise, scenario.noise)
    assert mine.J == pytest.approx(record.J(), rel=1e-10)
    np.testing.assert_allclose(mine.trajectory.soc, record.soc, atol=1e-10)
    # one loop, one record: the MPC's own figures are recorded the same way
    np.testing.assert_allclose(mine.record.policy, record.policy, atol=1e-10)
    np.testing.assert_allclose(mine.record.planned_power, record.planned_power, atol=1e-10)
    assert mine.record.solver_ok.all() and mine.solver_failures == 0


# -- the clairvoyant bound --------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clairvoyant_is_below_every_policy_on_every_day(seed, solver):
    scenario = make_scenario(SYSTEM, 2, seed)
    bound = clairvoyant(scenario)
    others = [
        evaluate_policy(MPCPolicy(solver, Theta.nominal(SYSTEM), scenario.prices), scenario),
        evaluate_policy(MPCPolicy(solver, random_theta(seed), scenario.prices), scenario),
        evaluate_policy(RuleBasedPolicy(scenario.prices, SYSTEM), scenario),
        evaluate_policy(RuleBasedPolicy(scenario.prices, SYSTEM, soc_guard=False), scenario),
    ]
    for other in others:
        assert np.all(bound.J_per_day <= other.J_per_day + 1e-6 * np.abs(other.J_per_day))
    # the bound is tight: a replay of the plan achieves almost the same cost
    assert bound.J <= bound.J_replayed + 1e-6
    assert bound.J_replayed - bound.J <= 0.02 * abs(bound.J) + 1.0


def test_clairvoyant_solution_satisfies_its_constraints():
    scenario = make_scenario(SYSTEM, 2, 3)
    result = clairvoyant(scenario)
    t = result.trajectory
    sysc = SYSTEM
    assert np.all((t.soc >= 0) & (t.soc <= 1))
    # dynamics with the applied powers
    np.testing.assert_allclose(
        t.soc[1:], t.soc[:-1] + sysc.alpha * (scenario.noise + t.b - t.s), atol=1e-7
    )
    # commanded parts within the bounds and the grid limit
    assert np.all(np.abs(t.a) <= sysc.U_bar + 1e-9)
    assert np.all(result.commanded_power <= sysc.P_bar + 1e-7)
    # the controller's extra power only towards an empty / full battery, at most the noise
    extra_buy, extra_sell = result.parts["eb"], result.parts["es"]
    np.testing.assert_allclose(t.correction, extra_buy - extra_sell)
    assert np.all(extra_buy <= np.maximum(-scenario.noise, 0) * (1 - t.soc[1:]) + 1e-7)
    assert np.all(extra_sell <= np.maximum(scenario.noise, 0) * t.soc[1:] + 1e-7)
    # the reported cost is the LP objective
    for day in range(scenario.days):
        *_, lay = clairvoyant_lp(scenario, day)
        z = np.zeros(lay.size)
        for key in ("ub", "us"):
            z[lay.block(key)] = result.parts[key][:, day]
        z[lay.block("eb")], z[lay.block("es")] = extra_buy[:, day], extra_sell[:, day]
        z[lay.block("soc")] = t.soc[1:, day]
        soc = t.soc[1:-1, day]
        z[lay.block("ehi")] = np.maximum(soc - sysc.soc_high, 0)
        z[lay.block("elo")] = np.maximum(sysc.soc_low - soc, 0)
        cost = check_lp_point(scenario, day, z, tol=1e-6)
        assert cost == pytest.approx(result.J_per_day[day], rel=1e-6)


def test_closed_loops_are_feasible_points_of_the_lp(solver):
    """The lower-bound argument, checked: a closed loop (with low-level interventions) is a
    feasible point of the LP whose objective is its cost."""
    scenario = make_scenario(SYSTEM.replace(noise_var=2.0), 2, 5)
    for policy in (RuleBasedPolicy(scenario.prices, scenario.system, soc_guard=False),
                   RuleBasedPolicy(scenario.prices, scenario.system)):
        result = evaluate_policy(policy, scenario)
        assert np.count_nonzero(result.trajectory.correction) > 0
        for day in range(scenario.days):
            cost = check_lp_point(scenario, day, lp_point(result, scenario, day))
            assert cost == pytest.approx(result.J_per_day[day], rel=1e-9, abs=1e-7)


# -- the rule ---------------------------------------------------------------------------------
def test_rule_based_respects_bounds_grid_limit_and_prices():
    system = SystemConfig(n=4, P_bar=1.5)
    prices = Prices.month(system, 5)
    rule = RuleBasedPolicy(prices, system)
    free = RuleBasedPolicy(prices, system, soc_guard=False)
    rng = np.random.default_rng(0)
    median = np.median(prices.buy, axis=1)
    for hour in range(24):
        soc = rng.uniform(0, 1, (5, 4))
        for policy in (rule, free):
            a = policy(hour, soc)
            assert np.all(np.abs(a) <= system.U_bar + 1e-12)
            assert np.all(np.maximum(a, 0).sum(1) <= system.P_bar + 1e-12)
            assert np.all(np.maximum(-a, 0).sum(1) <= system.P_bar + 1e-12)
        a = free(hour, soc)
        cheap = prices.buy[:, hour] < median
        dear = prices.buy[:, hour] > median
        assert np.all(a[cheap] > 0) and np.all(a[dear] < 0)
        np.testing.assert_allclose(np.abs(a[cheap | dear]), system.P_bar / 4)  # equal share
        guarded = rule(hour, soc)  # the expected next soc stays in the band when it acts
        expected = soc + system.alpha * guarded
        assert np.all((expected <= system.soc_high + 1e-12) | (guarded <= 0))
        assert np.all((expected >= system.soc_low - 1e-12) | (guarded >= 0))
        assert np.all(guarded * a >= 0)  # the guard never reverses the rule
    with pytest.raises(ValueError, match="soc_guard"):
        RuleBasedPolicy(prices, system, soc_guard="yes")


# -- the report ---------------------------------------------------------------------------------
def test_evaluate_baselines_report_and_reproducibility():
    theta = random_theta(4)
    one = evaluate_baselines(SYSTEM, IPOPT, days=1, seed=3, thetas={"shaped": theta})
    two = evaluate_baselines(SYSTEM, IPOPT, days=1, seed=3, thetas={"shaped": theta})
    assert list(one["policies"]) == ["clairvoyant", "nominal", "rule_based", "shaped"]
    for name, entry in one["policies"].items():
        for key in ("J", "J_per_agent", "hours_soc_below_0_1", "max_P_applied"):
            assert entry[key] == two["policies"][name][key], (name, key)
        assert entry["J"] >= one["policies"]["clairvoyant"]["J"] - 1e-6
        assert len(entry["J_per_agent"]) == SYSTEM.n
    gap = one["gap_closed"]["shaped"]
    J = {k: v["J"] for k, v in one["policies"].items()}
    assert gap == pytest.approx((J["nominal"] - J["shaped"]) / (J["nominal"] - J["clairvoyant"]))
    json.dumps(one)  # JSON-friendly
    with pytest.raises(ValueError, match="reserved name"):
        evaluate_baselines(SYSTEM, IPOPT, days=1, seed=0, thetas={"nominal": theta})
    with pytest.raises(ValueError, match=r"thetas\['x'\]: expected a Theta with n=3"):
        other = Theta.nominal(SystemConfig(n=2))
        evaluate_baselines(SYSTEM, IPOPT, days=1, seed=0, thetas={"x": other})


def test_run_baselines_cli_with_history(tmp_path):
    learning = LearningConfig(days_per_month=1, seed=2)
    history = History(SYSTEM, IPOPT, learning)
    history.theta_final = Theta.nominal(SYSTEM).to_vector().tolist()
    history.save(tmp_path / "run")
    result = run_baselines_cli(SYSTEM, IPOPT, learning, tmp_path / "run", tmp_path / "out")
    saved = json.loads((tmp_path / "out" / "baselines.json").read_text())
    assert saved["policies"]["learned"]["J"] == result["policies"]["learned"]["J"]
    # the "learned" theta is theta0 here: same cost as the nominal MPC, no gap closed
    assert result["policies"]["learned"]["J"] == pytest.approx(result["policies"]["nominal"]["J"])
    assert result["gap_closed"]["learned"] == pytest.approx(0.0, abs=1e-12)
    with pytest.raises(ValueError, match="has n=3; expected n=2"):
        run_baselines_cli(SystemConfig(n=2, P_bar=1.0), IPOPT, learning, tmp_path / "run",
                          tmp_path / "x")
