"""The causal DP for batteries that differ: one grid per battery on the product state grid.

Checked against the symmetric DP (identical batteries), a plain numpy recursion written from
the module docstring's formula (two batteries that differ in alpha, noise, U_bar and soc0),
the Lagrangian bound (weak duality on the same grid), and its own policy in closed loop.
"""

from __future__ import annotations

import warnings
from itertools import product

import numpy as np
import pytest

from mpcrl_lite.bounds.baselines import causal_reference
from mpcrl_lite.bounds.causal import dp
from mpcrl_lite.bounds.causal.dp import causal_optimum
from mpcrl_lite.bounds.causal.dual import lagrangian_bound
from mpcrl_lite.bounds.causal.grid import day_prices, expected_agent_cost, interpolation_weights
from mpcrl_lite.bounds.causal.mixed import BatteryGrids
from mpcrl_lite.bounds.rule import RuleBasedPolicy
from mpcrl_lite.bounds.scenario import evaluate_policy, make_scenario
from mpcrl_lite.config import ConfigWarning, MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import MPCPolicy
from mpcrl_lite.studies.study import causal_target
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

#: Actions in steps of 0.5 MW and soc nodes every 1/12: a tiny grid for the mixed site's
#: alphas (1/24 and 1/12: 4 and 2 post-decision cells per node).
COARSE = {"grid": 13, "action_step": 0.5}
MIXED_SITE = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 12), noise_var=(1.0, 0.5, 0.5))


def system(**fields) -> SystemConfig:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return SystemConfig(**fields)


#: Two batteries that differ in every way the grids see; the grid limit binds (2 steps of
#: 0.5 MW on each side against 2 + 1 the batteries could take); soc0 on nodes of COARSE.
PAIR = system(n=2, alpha=(1 / 12, 1 / 24), noise_var=(0.5, 1.0), U_bar=(1.0, 0.5),
              P_bar=1.0, soc0=(0.5, 0.75), p=(1000.0, 500.0))


def plain_recursion(sysc: SystemConfig, buy: np.ndarray, sell: np.ndarray, points: int,
                    action_step: float) -> float:
    """``V_0(soc0)`` of one day for two batteries by the textbook loops: every node pair,
    every joint action, ``E V_{k+1}`` as ``w_1 V w_2`` with each battery's own weights."""
    nodes = np.linspace(0.0, 1.0, points)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        own = [sysc.replace(n=1, **{name: sysc.battery(name)[i] for name in
                                    ("alpha", "noise_mean", "noise_var", "U_bar", "p", "soc0")})
               for i in range(2)]
    bound = [round(b.U_bar / action_step) for b in own]
    limit = round(sysc.P_bar / action_step)
    joint = [(m1, m2) for m1, m2 in product(range(-bound[0], bound[0] + 1),
                                            range(-bound[1], bound[1] + 1))
             if max(m1, 0) + max(m2, 0) <= limit and max(-m1, 0) + max(-m2, 0) <= limit]
    steps = np.array(joint)
    value = np.zeros((points, points))
    start = [round(b.soc0 * (points - 1)) for b in own]
    for k in range(sysc.hours_per_day - 1, -1, -1):
        rows = [start[0]] if k == 0 else range(points)
        cols = [start[1]] if k == 0 else range(points)
        new = np.zeros((points, points))
        for j1 in rows:
            for j2 in cols:
                total = np.zeros(len(joint))
                w = []
                for i, j in enumerate((j1, j2)):
                    a = steps[:, i] * action_step
                    total += expected_agent_cost(nodes[j], a, buy[k], sell[k], own[i])
                    w.append(interpolation_weights(nodes[j] + own[i].alpha * a, nodes, own[i]))
                total += sysc.gamma * np.einsum("ap,pq,aq->a", w[0], value, w[1])
                new[j1, j2] = total.min()
        value = new
    return float(value[start[0], start[1]])


def test_identical_batteries_as_lists_give_the_scalar_systems_j_star_exactly():
    prices = Prices.default().take(2)
    paper = SystemConfig()
    scalar = causal_optimum(paper, prices, **COARSE)
    lists = causal_optimum(SystemConfig(alpha=(paper.alpha,) * 3, noise_var=(paper.noise_var,) * 3,
                                        soc0=(paper.soc0,) * 3, p=(paper.p,) * 3),
                           prices, **COARSE)
    assert np.array_equal(lists.J_star_per_day, scalar.J_star_per_day)
    assert lists.info["method"] == scalar.info["method"] == "symmetric"


@pytest.mark.parametrize("n", [1, 2, 3])
def test_the_product_grid_dp_agrees_with_the_symmetric_dp_on_identical_batteries(n):
    sysc = system(n=n)
    buy, sell = day_prices(sysc, Prices.default().take(2))
    symmetric = causal_optimum(sysc, Prices.default().take(2), **COARSE)
    grids = BatteryGrids(sysc, COARSE["grid"], COARSE["action_step"])
    full = dp._solve(sysc, grids, buy, sell, True)
    assert full.info["method"] == "product" and full.info["states"] == COARSE["grid"] ** n
    np.testing.assert_allclose(full.J_star_per_day, symmetric.J_star_per_day, rtol=1e-11)
    # the kept tables are the symmetric ones, expanded
    np.testing.assert_allclose(full.value_table(1, 5), symmetric.value_table(1, 5), rtol=1e-11)


def test_two_batteries_that_differ_match_the_plain_recursion():
    prices = Prices.default().take(2)
    bound = causal_optimum(PAIR, prices, **COARSE)
    assert bound.info["method"] == "product"
    buy, sell = day_prices(PAIR, prices)
    plain = [plain_recursion(PAIR, buy[d], sell[d], points=13, action_step=0.5)
             for d in range(2)]
    np.testing.assert_allclose(bound.J_star_per_day, plain, rtol=1e-10)
    # each battery counts: swapping the two changes J*
    swapped = system(n=2, alpha=(1 / 24, 1 / 12), noise_var=(1.0, 0.5), U_bar=(0.5, 1.0),
                     P_bar=1.0, soc0=(0.75, 0.5), p=(500.0, 1000.0))
    np.testing.assert_allclose(causal_optimum(swapped, prices, **COARSE).J_star_per_day,
                               bound.J_star_per_day, rtol=1e-10)
    assert abs(causal_optimum(PAIR.replace(soc0=(0.75, 0.5)), prices, **COARSE).J_star
               - bound.J_star) > 1.0


def test_weak_duality_and_the_dp_policy_in_closed_loop():
    """The Lagrangian bound lies below J* on the same grid; the DP policy, simulated on the
    true system, costs about J* (the grid model is pessimistic, so the policy does a little
    better: by less than the gap between 21 and 41 soc nodes)."""
    base = Prices.default().take(2)
    sysc = PAIR.replace(soc0=(0.5, 0.5))
    fine = {"grid": 41, "action_step": 0.1}
    bound = causal_optimum(sysc, base, **fine)
    dual = lagrangian_bound(sysc, base, **fine)
    assert np.all(dual.J_bound_per_day <= bound.J_star_per_day + 1e-8)
    coarse = causal_optimum(sysc, base, grid=21, action_step=0.1)
    grid_error = coarse.J_star - bound.J_star
    assert grid_error > 0  # refining the grid model only gains
    days = 1000
    prices = Prices(np.tile(base.buy, (days // 2, 1)))
    policy = bound.policy(prices)
    # its commands keep each battery's own bound and the site's grid limit
    a = policy(3, np.random.default_rng(0).uniform(0.0, 1.0, (days, 2)))
    assert np.all(np.abs(a) <= np.array(sysc.battery("U_bar")) + 1e-12)
    assert np.abs(a[:, 1]).max() == pytest.approx(0.5)
    assert np.maximum(a, 0).sum(axis=1).max() <= sysc.P_bar + 1e-12
    assert np.maximum(-a, 0).sum(axis=1).max() <= sysc.P_bar + 1e-12
    run = evaluate_policy(policy, make_scenario(sysc, days, 11, prices), "dp")
    se = run.J_per_day.std(ddof=1) / np.sqrt(days)
    assert abs(run.J - bound.J_star) < 3 * se + grid_error


def test_the_mixed_site_lies_between_its_lagrangian_bound_and_its_nominal_mpc():
    """On one price day: the dual bound <= J* (the same grid) <= the closed-loop cost of the
    nominal MPC and of the price rule on 48 draws (J* about -543 NOK/day on this coarse grid,
    the MPC about +490 +- 80: its penalties dominate)."""
    base = Prices.default().take(1)
    bound = causal_optimum(MIXED_SITE, base, **COARSE)
    assert bound.info["method"] == "product" and bound.info["states"] == 13 ** 3
    dual = lagrangian_bound(MIXED_SITE, base, **COARSE)
    assert dual.J_bound <= bound.J_star + 1e-8
    days = 48
    prices = Prices(np.tile(base.buy, (days, 1)))
    scenario = make_scenario(MIXED_SITE, days, 3, prices)
    theta = Theta.nominal(MIXED_SITE)
    solver = make_solver(MPC(MIXED_SITE), MPCConfig(backend="batch"), theta)
    for name, policy in {"nominal": MPCPolicy(solver, theta, prices),
                         "rule": RuleBasedPolicy(prices, MIXED_SITE)}.items():
        run = evaluate_policy(policy, scenario, name)
        se = run.J_per_day.std(ddof=1) / np.sqrt(days)
        assert bound.J_star < run.J - 3 * se, name


def test_baselines_and_study_targets_solve_the_dp_for_batteries_that_differ():
    prices = Prices.default().take(1)
    reference, source = causal_reference(PAIR, prices)
    assert source == "coupled DP (solved, one grid per battery)"
    assert reference.info["method"] == "product"
    assert reference.J_star == causal_optimum(PAIR, prices, keep_values=False).J_star
    target = causal_target(PAIR, prices)
    assert target["method"] == "causal_dp" and target["states"] == "product"
    assert target["J_star"] == pytest.approx(reference.J_star, rel=1e-12)
    assert "one soc grid per battery" in target["note"]


def test_a_battery_off_the_grid_is_named_in_one_line():
    sysc = system(alpha=(1 / 12, 1 / 7, 1 / 12))
    with pytest.raises(ValueError) as info:
        causal_optimum(sysc, Prices.default().take(1), **COARSE)
    text = str(info.value)
    assert "\n" not in text and text.startswith("battery 1 (alpha=0.142857")
    with pytest.raises(ValueError, match=r"^n=4 with alpha=\[.*at most 3 batteries"):
        causal_optimum(system(n=4, alpha=(1 / 12, 1 / 24, 1 / 12, 1 / 12)),
                       Prices.default().take(1), **COARSE)
