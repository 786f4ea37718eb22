"""Decentralized MPCs coordinated by grid prices, and the decentralized learner."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from mpcrl_lite.config import (
    ConfigWarning,
    CoordinationConfig,
    LearningConfig,
    MPCConfig,
    SystemConfig,
)
from mpcrl_lite.decentralized.coordination import CoordinatedMPC, join_theta, split_theta
from mpcrl_lite.decentralized.learner import DecentralizedExperiment
from mpcrl_lite.decentralized.local_qp import local_system
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.mpc.backends.ipopt import IpoptSolver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

IPOPT = MPCConfig(backend="ipopt")
TIGHT = SystemConfig()  # n = 3, P_bar = 1.5 < n U_bar


def loose_system() -> SystemConfig:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        return SystemConfig(P_bar=4.0)  # > n U_bar = 3: the limit can never bind


def shaped_theta(system: SystemConfig, seed: int = 0) -> Theta:
    rng = np.random.default_rng(seed)
    n = system.n
    return Theta.nominal(system).replace(
        b=rng.uniform(-3, 3, n), phi1=rng.uniform(5, 40, n), phi2=rng.uniform(-30, 0, n),
        T1=rng.uniform(5, 40, n), T2=rng.uniform(-30, 0, n),
    )


def states(days: int, n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.05, 0.95, (days, n))


def grid_multipliers(solution, mpc: MPC) -> tuple[np.ndarray, np.ndarray]:
    """The centralized MPC's multipliers of its grid rows, (days, N) for buy and sell."""
    per_stage = 8 * mpc.n + 2
    mu = solution.mu.reshape(len(solution), mpc.N, per_stage)
    return mu[:, :, 4 * mpc.n], mu[:, :, 4 * mpc.n + 1]


# -- helpers ----------------------------------------------------------------------------------
def test_theta_split_join_and_local_system():
    theta = shaped_theta(TIGHT, 3)
    parts = split_theta(theta)
    assert [t.n for t in parts] == [1, 1, 1]
    assert join_theta(parts) == theta
    assert parts[1].phi1[0] == theta.phi1[1]
    local = local_system(TIGHT)
    assert local.n == 1 and local.P_bar == 1e4 * 1.5 and local.alpha == TIGHT.alpha
    with pytest.raises(ValueError, match="n=1 each"):
        join_theta([theta])
    with pytest.raises(ValueError, match="tol=0"):
        CoordinationConfig(tol=0.0)
    with pytest.raises(ValueError, match="max_iter=0"):
        CoordinationConfig(max_iter=0)
    policy = CoordinatedMPC(TIGHT, IPOPT)
    prices = Prices.month(TIGHT, 2)
    buy, sell = prices.window(0, TIGHT.N)
    with pytest.raises(ValueError, match="expected 3 Theta objects"):
        policy.solve(states(2, 3), buy, sell, parts[:2])
    with pytest.raises(ValueError, match=r"soc has shape \(2, 2\)"):
        policy.solve(states(2, 2), buy, sell, theta)


# -- coordination -----------------------------------------------------------------------------
@pytest.mark.parametrize("hour", [3, 17])
def test_tight_limit_respected_positive_prices_and_equal_to_centralized(hour):
    days = 4
    prices = Prices.month(TIGHT, days)
    buy, sell = prices.window(hour, TIGHT.N)
    soc = states(days, 3, hour)
    theta = Theta.nominal(TIGHT)
    coordinated = CoordinatedMPC(TIGHT, IPOPT)
    sol = coordinated.solve(soc, buy, sell, theta)
    assert sol.converged.all() and not sol.projected.any()
    # the limit holds for the action and for the whole plan, strictly
    a = sol.action
    assert np.all(np.maximum(a, 0).sum(1) < TIGHT.P_bar)
    assert np.all(np.maximum(-a, 0).sum(1) < TIGHT.P_bar)
    assert np.all(sol.planned_power < TIGHT.P_bar) and np.all(sol.violation < 0)
    # the limit binds somewhere: grid prices far above the barrier level tau / P_bar
    assert max(sol.price_buy.max(), sol.price_sell.max()) > 1.0
    # ... and the coordinated local MPCs are the centralized MPC, prices its grid multipliers
    mpc = MPC(TIGHT)
    ref = IpoptSolver(mpc, IPOPT).solve_batch(soc, buy, sell, theta)
    np.testing.assert_allclose(sol.action, ref.action, atol=1e-6)
    mu_b, mu_s = grid_multipliers(ref, mpc)
    np.testing.assert_allclose(sol.price_buy, mu_b, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(sol.price_sell, mu_s, rtol=1e-5, atol=1e-8)


def test_unconverged_coordination_falls_back_to_projection():
    days = 3
    prices = Prices.month(TIGHT, days)
    buy, sell = prices.window(18, TIGHT.N)
    policy = CoordinatedMPC(TIGHT, IPOPT, CoordinationConfig(max_iter=2))
    sol = policy.solve(states(days, 3, 5), buy, sell, Theta.nominal(TIGHT))
    assert not sol.converged.any() and sol.projected.all()
    assert np.all(sol.iterations == 2) and sol.success.all()
    a = sol.action
    assert np.all(np.maximum(a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    assert np.all(np.maximum(-a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    assert np.all(np.abs(a) <= TIGHT.U_bar + 1e-12)
    _grad, ok = policy.sensitivity(sol)  # local IPOPT solutions: exact local KKT points
    assert ok.all()


def test_empty_and_full_batteries_start_strictly_inside_and_converge():
    # soc 0 or 1 with the guess b = s puts the planned soc at 0 or 1: the soc band's slacks
    # must start clearly above their bounds, not at a vanishing distance
    days = 2
    prices = Prices.month(TIGHT, days)
    buy, sell = prices.window(18, TIGHT.N)
    soc = np.array([[0.0, 1.0, 0.5], [1.0, 0.0, 0.0]])
    theta = Theta.nominal(TIGHT)
    sol = CoordinatedMPC(TIGHT, IPOPT).solve(soc, buy, sell, theta)
    assert sol.converged.all() and not sol.projected.any() and sol.success.all()
    ref = IpoptSolver(MPC(TIGHT), IPOPT).solve_batch(soc, buy, sell, theta)
    np.testing.assert_allclose(sol.action, ref.action, atol=1e-6)


def test_singular_newton_system_falls_back_for_that_day_only(monkeypatch):
    days = 3
    prices = Prices.month(TIGHT, days)
    buy, sell = prices.window(18, TIGHT.N)
    soc = states(days, 3, 5)
    soc[1, 0] = 0.123456  # marks day 1: its first dynamics row reads soc0 (theta_delta = 0)
    theta = Theta.nominal(TIGHT)
    reference = CoordinatedMPC(TIGHT, IPOPT).solve(soc, buy, sell, theta)
    assert reference.converged.all()

    policy = CoordinatedMPC(TIGHT, IPOPT)
    newton = policy._qp.newton

    def singular_on_day_1(Hd, q, A, e, *args):
        if np.isclose(e[:, 0], 0.123456, rtol=0, atol=1e-12).any():
            raise np.linalg.LinAlgError("Singular matrix")
        return newton(Hd, q, A, e, *args)

    monkeypatch.setattr(policy._qp, "newton", singular_on_day_1)
    sol = policy.solve(soc, buy, sell, theta)  # no exception mid-run
    # day 1 stops its rounds and takes the documented fallback: local IPOPT and projection
    np.testing.assert_array_equal(sol.converged, [True, False, True])
    np.testing.assert_array_equal(sol.projected, [False, True, False])
    assert sol.success.all()
    a = sol.action
    assert np.all(np.maximum(a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    assert np.all(np.maximum(-a, 0).sum(1) <= TIGHT.P_bar + 1e-12)
    assert np.all(np.abs(a) <= TIGHT.U_bar + 1e-12)
    # the other days are coordinated as without the failure
    np.testing.assert_allclose(a[[0, 2]], reference.action[[0, 2]], atol=1e-9)
    np.testing.assert_allclose(sol.price_buy[[0, 2]], reference.price_buy[[0, 2]],
                               rtol=1e-6, atol=1e-9)


def test_loose_limit_splits_into_independent_problems():
    # nearly exact MPC (tau = 1e-4): the slack grid limit's barrier then moves the policy by
    # less than 1e-6, so every battery solves its own problem as if it were alone
    exact = MPCConfig.paper(backend="ipopt")
    system = loose_system()
    days, hour = 3, 18
    prices = Prices.month(system, days)
    buy, sell = prices.window(hour, system.N)
    soc = states(days, 3, 7)
    theta = shaped_theta(system, 1)
    sol = CoordinatedMPC(system, exact).solve(soc, buy, sell, theta)
    assert sol.converged.all()
    # the prices are zero up to the barrier: tau / (P_bar - n U_bar) at most
    barrier_level = exact.tau / (system.P_bar - system.n * system.U_bar)
    assert sol.price_buy.max() <= barrier_level * (1 + 1e-9)
    assert sol.price_sell.max() <= barrier_level * (1 + 1e-9)
    # same policy as the centralized MPC ...
    ref = IpoptSolver(MPC(system), exact).solve_batch(soc, buy, sell, theta)
    np.testing.assert_allclose(sol.action, ref.action, atol=1e-6)
    # ... and as every battery alone, solving its own MPC without any price
    local = IpoptSolver(MPC(local_system(system)), exact)
    for i, theta_i in enumerate(split_theta(theta)):
        alone = local.solve_batch(soc[:, i : i + 1], buy, sell, theta_i)
        np.testing.assert_allclose(sol.action[:, i], alone.action[:, 0], atol=1e-6)


def test_local_sensitivity_at_fixed_prices_matches_finite_differences():
    days, hour = 2, 17
    prices = Prices.month(TIGHT, days)
    buy, sell = prices.window(hour, TIGHT.N)
    soc = states(days, 3, 2)
    theta = shaped_theta(TIGHT, 2)
    policy = CoordinatedMPC(TIGHT, IPOPT)
    sol = policy.solve(soc, buy, sell, theta)
    grad, ok = policy.sensitivity(sol)
    assert ok.all() and grad.shape == (days, 3, 10)
    local = IpoptSolver(policy.local_mpc, IPOPT)
    i, h = 1, 1e-5
    for part in ("phi2", "T2", "b"):
        k = Theta.index(1, part).start
        theta_i = split_theta(theta)[i]
        vec = theta_i.to_vector()
        actions = []
        for sign in (1, -1):
            shifted = Theta.from_vector(vec + sign * h * np.eye(10)[k], 1)
            p = sol.p[:, i]  # the local MPC at the coordinated (fixed) grid prices
            N = TIGHT.N
            res = local.solve_batch(p[:, :1], p[:, 1 : 1 + N], p[:, 1 + N : 1 + 2 * N], shifted)
            actions.append(res.action[:, 0])
        fd = (actions[0] - actions[1]) / (2 * h)
        np.testing.assert_allclose(grad[:, i, k], fd, rtol=1e-4, atol=1e-6)


# -- learning ---------------------------------------------------------------------------------
def test_first_month_equals_the_centralized_experiment():
    learning = LearningConfig(days_per_month=2, months=1, seed=4)
    central = Experiment(TIGHT, IPOPT, learning).run(progress=False)
    local = DecentralizedExperiment(TIGHT, IPOPT, learning).run(progress=False)
    # same policy (theta0), same draws: the same month
    assert local.J[0] == pytest.approx(central.J[0], rel=1e-7)
    np.testing.assert_allclose(local.last_month.a, central.last_month.a, atol=1e-6)


def test_decentralized_learning_runs_and_resumes_identically(tmp_path):
    # the paper's plain gradient step, tiny: theta moves, but stays close to theta0
    learning = LearningConfig(days_per_month=3, months=2, seed=1, optimizer="sgd",
                              step_size=1e-9)
    def experiment() -> DecentralizedExperiment:
        return DecentralizedExperiment(TIGHT, IPOPT, learning)

    straight = experiment().run(out=tmp_path / "a", progress=False)
    experiment().run(months=1, out=tmp_path / "b", progress=False)
    resumed = experiment().run(out=tmp_path / "b", resume=True, progress=False)
    assert straight.months == resumed.months == 2
    assert straight.J == resumed.J
    assert straight.theta_final == resumed.theta_final
    assert straight.update_info[1]["agents"] == resumed.update_info[1]["agents"]
    # each battery learned its own theta^i; the stacked theta changed
    assert straight.theta_final != straight.theta[0]
    info = straight.update_info[-1]
    coordination = info["coordination"]
    assert coordination["limit_violations"] == 0 and coordination["projected"] == 0
    assert 1 <= coordination["iterations_mean"] <= coordination["iterations_max"]
    assert len(info["agents"]) == 3 and all("grad_norm" in a for a in info["agents"])
    assert max(straight.max_P_mpc) < TIGHT.P_bar
    json.dumps(straight.summary())
    # a centralized checkpoint is refused with a clear message
    Experiment(TIGHT, IPOPT, learning.replace(days_per_month=1)).run(
        months=1, out=tmp_path / "c", progress=False
    )
    with pytest.raises(ValueError, match="centralized run"):
        DecentralizedExperiment(TIGHT, IPOPT, learning.replace(days_per_month=1)).run(
            out=tmp_path / "c", resume=True, progress=False
        )
