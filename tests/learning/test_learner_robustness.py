"""What makes the learner robust: a zero-mean exploration, the natural gradient, the trust
region, averaging, the step schedule, tied agents and the day-end forecast."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mpcrl_lite.config import LearningConfig, SystemConfig
from mpcrl_lite.learning.dpg import DPGUpdater, learnable_mask, policy_gradient, policy_metric
from mpcrl_lite.learning.experiment import Experiment
from mpcrl_lite.learning.update_rules import NaturalGradient, natural_direction
from mpcrl_lite.sim.closed_loop import simulate
from mpcrl_lite.sim.exploration import GaussianExploration, bounded_exploration, exploration_center
from mpcrl_lite.system.battery import project_action
from mpcrl_lite.system.forecast import DayEndPrices, until_midnight
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import PARTS, Theta

SYSTEM = SystemConfig()  # n = 3, U_bar = 1, P_bar = 1.5
N = SYSTEM.n
ALPHA = SYSTEM.alpha

#: Actions at or next to the bounds: one battery near +U_bar, a row on the selling face of
#: the grid limit (slack 0.01), a row on the buying face, two batteries at opposite bounds.
NEAR_BOUNDS = np.array([
    [0.97, 0.3, 0.0],
    [-0.5, -0.5, -0.49],
    [0.6, 0.6, 0.295],
    [0.99, -0.99, 0.0],
])


def _feasible(a: np.ndarray, system: SystemConfig = SYSTEM, tol: float = 1e-12) -> bool:
    return bool(
        np.all(np.abs(a) <= system.U_bar + tol)
        and np.all(np.maximum(a, 0).sum(-1) <= system.P_bar + tol)
        and np.all(np.maximum(-a, 0).sum(-1) <= system.P_bar + tol)
    )


# -- exploration: zero mean -------------------------------------------------------------------
def _draws(size: int = 40_000, std: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Every row of NEAR_BOUNDS repeated ``size`` times, and the Gaussian explorations."""
    pi = np.repeat(NEAR_BOUNDS, size, axis=0)
    e = std * np.random.default_rng(seed).standard_normal(pi.shape)
    return pi, e


def _mean_and_error(x: np.ndarray, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row of NEAR_BOUNDS: the mean of x and its Monte Carlo standard error."""
    x = x.reshape(rows, -1, x.shape[-1])
    return x.mean(axis=1), x.std(axis=1) / np.sqrt(x.shape[1])


def test_projection_shifts_the_exploration_mean_near_the_bounds():
    """Projecting pi + e onto the bounds moves the mean of a - pi inwards by many standard
    errors: the bias the compatible critic cannot tolerate."""
    pi, e = _draws()
    mean, error = _mean_and_error(project_action(pi + e, SYSTEM) - pi, len(NEAR_BOUNDS))
    assert np.abs(mean / np.maximum(error, 1e-12)).max() > 20.0
    assert mean[0, 0] < -0.03  # the battery at 0.97 is pushed down on average
    assert mean[1].sum() > 0.03  # the sellers at the grid limit sell less on average


@pytest.mark.parametrize("bounds", ["symmetric", "radial"])
@pytest.mark.parametrize("margin", [0.0, 0.2])
def test_bounded_exploration_has_zero_mean_near_the_bounds(bounds, margin):
    pi, e = _draws()
    center = exploration_center(pi, SYSTEM, margin)
    a = bounded_exploration(center, e, SYSTEM, bounds)
    assert _feasible(a)
    mean, error = _mean_and_error(a - center, len(NEAR_BOUNDS))
    assert np.all(np.abs(mean) <= 4.0 * error + 1e-12), (mean, error)
    # and there is exploration to speak of: around a centre with a margin every battery
    # moves, without one only the sliding along the grid faces is left on those rows
    rms = np.sqrt(((a - center) ** 2).reshape(len(NEAR_BOUNDS), -1, N).mean(axis=1))
    if margin:
        assert rms.min() > 0.04, rms


def test_bounded_exploration_is_odd_feasible_and_exact_inside():
    rng = np.random.default_rng(1)
    for system in (SYSTEM, SystemConfig(n=5, P_bar=2.0), SystemConfig(n=2, P_bar=1.0)):
        n = system.n
        pi = project_action(rng.uniform(-1.3, 1.3, size=(3000, n)), system)  # many on faces
        pi[:500] = np.clip(pi[:500], -0.2, 0.2) / n  # deep inside
        e = 0.3 * rng.standard_normal(pi.shape)
        e[:500] *= 0.1
        for bounds in ("symmetric", "radial"):
            plus = bounded_exploration(pi, e, system, bounds)
            minus = bounded_exploration(pi, -e, system, bounds)
            np.testing.assert_allclose(plus - pi, -(minus - pi), atol=1e-12)
            assert _feasible(plus, system) and _feasible(minus, system)
            # both pi + e and pi - e are feasible: nothing changes
            np.testing.assert_allclose(plus[:500], pi[:500] + e[:500], atol=1e-15)
            if bounds == "symmetric":
                radial = bounded_exploration(pi, e, system, "radial")
                kept = ((plus - pi) ** 2).sum(-1) - ((radial - pi) ** 2).sum(-1)
                assert kept.min() >= -1e-12  # never less than the radial step
    with pytest.raises(ValueError, match="bounds='clip': expected one of"):
        bounded_exploration(pi, e, SYSTEM, "clip")


def test_sliding_along_a_grid_face_keeps_half_the_exploration():
    """At the selling face (all three batteries at -0.5), no exploration across the face
    has zero mean, so the radial step leaves nothing; sliding along the face keeps the two
    thirds of e that are tangent to it (minus what the radial guard removes)."""
    pi = np.tile([[-0.5, -0.5, -0.5]], (20_000, 1))
    e = 0.2 * np.random.default_rng(2).standard_normal(pi.shape)
    energy = (e**2).sum()
    radial = bounded_exploration(pi, e, SYSTEM, "radial")
    symmetric = bounded_exploration(pi, e, SYSTEM, "symmetric")
    assert ((radial - pi) ** 2).sum() / energy < 1e-6
    assert ((symmetric - pi) ** 2).sum() / energy > 0.5
    np.testing.assert_allclose((symmetric - pi).sum(-1), 0.0, atol=1e-12)  # along the face


def test_exploration_center():
    pi = project_action(np.random.default_rng(3).uniform(-1.2, 1.2, size=(2000, N)), SYSTEM)
    assert exploration_center(pi, SYSTEM, 0.0) is pi
    m = 0.2
    c = exploration_center(pi, SYSTEM, m)
    assert np.all(np.abs(c) <= SYSTEM.U_bar - m + 1e-12)
    assert np.all(np.maximum(c, 0).sum(-1) <= SYSTEM.P_bar - m + 1e-12)
    assert np.all(np.maximum(-c, 0).sum(-1) <= SYSTEM.P_bar - m + 1e-12)
    assert np.all(np.sign(c) * np.sign(pi) >= 0)  # pulled towards zero, never across it
    inside = (np.abs(pi) <= SYSTEM.U_bar - m).all(-1) & (
        np.maximum(np.maximum(pi, 0).sum(-1), np.maximum(-pi, 0).sum(-1)) <= SYSTEM.P_bar - m)
    assert inside.any()
    np.testing.assert_array_equal(c[inside], pi[inside])
    with pytest.raises(ValueError, match=r"margin=0.8: expected a value in \[0, 0.5\]"):
        exploration_center(pi, SYSTEM, 0.8)


def test_gaussian_exploration_draws_once_per_hour_and_explores_around_the_center():
    days, std, margin = 4, 0.3, 0.2
    buy = 50.0 + 40.0 * np.sin(np.arange(days * 24).reshape(days, 24) / 3.0)

    def rule(hour, soc):
        return np.where(soc < 0.5, 0.99, -0.99)  # at the bounds, the grid limit binds

    record = simulate(rule, buy, 0.5 * buy, SYSTEM, rng=np.random.default_rng(9),
                      explore=GaussianExploration(std, SYSTEM, margin=margin))
    replay = np.random.default_rng(9)
    for k in range(24):
        e = std * replay.standard_normal((days, N))
        replay.normal(size=(days, N))  # the hour's noise
        center = exploration_center(record.policy[k], SYSTEM, margin)
        np.testing.assert_array_equal(record.a[k], bounded_exploration(center, e, SYSTEM))
    with pytest.raises(ValueError, match="margin=0.1 with bounds='project'"):
        GaussianExploration(std, SYSTEM, "project", margin=0.1)
    with pytest.raises(ValueError, match="exploration_margin=0.1 with exploration_bounds"):
        LearningConfig(exploration_bounds="project", exploration_margin=0.1)


# -- the natural gradient -----------------------------------------------------------------------
def _sensitivities(rng, samples=400, n_theta=6, n=2):
    """Random policy sensitivities whose rows have very different units."""
    units = np.array([1e-3, 1.0, 10.0, 100.0, 0.1, 1.0])[:n_theta]
    return rng.normal(size=(samples, n_theta, n)) * units[None, :, None]


def test_natural_gradient_is_the_fisher_preconditioned_gradient():
    rng = np.random.default_rng(4)
    G = _sensitivities(rng)
    w = rng.normal(size=6)
    F, g = policy_metric(G), policy_gradient(G, w)
    np.testing.assert_allclose(F, np.einsum("sti,sui->tu", G, G) / len(G), rtol=1e-12)
    # with the compatible critic, g = F w, and the natural gradient F^-1 g is w itself
    np.testing.assert_allclose(F @ w, g, rtol=1e-10)
    np.testing.assert_allclose(natural_direction(g, F), w, rtol=1e-8)
    np.testing.assert_allclose(natural_direction(g, F), np.linalg.solve(F, g), rtol=1e-8)
    lam = 0.1
    damped = np.linalg.solve(F + lam * np.diag(np.diag(F)), g)
    np.testing.assert_allclose(natural_direction(g, F, lam), damped, rtol=1e-8)
    # an entry the policy does not depend on gets no direction
    G0 = G.copy()
    G0[:, 2] = 0.0
    d = natural_direction(policy_gradient(G0, w), policy_metric(G0))
    assert d[2] == 0.0
    np.testing.assert_allclose(np.delete(d, 2), np.delete(w, 2), rtol=1e-8)


def test_natural_gradient_does_not_depend_on_the_units_of_theta():
    """Measuring theta_j in other units (theta' = D theta) changes the vanilla gradient's
    effect on the actions, not the natural gradient's."""
    rng = np.random.default_rng(5)
    G, w = _sensitivities(rng), rng.normal(size=6)
    D = np.array([1e3, 1.0, 0.1, 1e-2, 10.0, 2.0])
    G2 = G / D[None, :, None]  # d pi / d theta' = d pi / d theta / D
    g, g2 = policy_gradient(G, w), policy_gradient(G2, w * D)  # w' = D w keeps Q_w
    for damping in (0.0, 0.01):
        move = np.einsum("sti,t->si", G, natural_direction(g, policy_metric(G), damping))
        move2 = np.einsum("sti,t->si", G2, natural_direction(g2, policy_metric(G2), damping))
        np.testing.assert_allclose(move2, move, rtol=1e-8, atol=1e-12)
    vanilla = np.einsum("sti,t->si", G, g)
    vanilla2 = np.einsum("sti,t->si", G2, g2)
    assert not np.allclose(vanilla, vanilla2, rtol=0.1)


def _observed_step(up: DPGUpdater, theta: Theta, G: np.ndarray, w: np.ndarray) -> Theta:
    up.observe(G)
    return up.step(theta, policy_gradient(G, w))


def test_natural_rule_moves_the_actions_by_the_step_size_at_first():
    """The first step of the normalised natural gradient is d / sqrt(d' F d) times the
    step size: the RMS change of the action is the step size (in MW), along w."""
    rng = np.random.default_rng(6)
    config = LearningConfig(optimizer="natural", step_size=0.03, keep_well_posed=False,
                            tie_agents=False, natural_damping=0.0)
    up = DPGUpdater(config, N, ALPHA)
    assert isinstance(up.rule, NaturalGradient)
    G = rng.normal(size=(300, 10 * N, N))
    G[:, ~learnable_mask(N)] = 0.0
    w = np.where(learnable_mask(N), rng.normal(size=10 * N), 0.0)
    theta = Theta.nominal(SYSTEM)
    new = _observed_step(up, theta, G, w)
    change = new.to_vector() - theta.to_vector()
    F = policy_metric(G)
    assert np.sqrt(change @ F @ change) == pytest.approx(0.03, rel=1e-6)
    assert up.last_info["policy_change"] == pytest.approx(0.03, rel=1e-6)
    np.testing.assert_allclose(change / np.linalg.norm(change), -w / np.linalg.norm(w),
                               atol=1e-8)
    with pytest.raises(ValueError, match="call observe"):
        up.step(theta, policy_gradient(G, w))  # the metric is used by one step only


def test_trust_region_bounds_the_change_of_the_policy():
    rng = np.random.default_rng(7)
    config = LearningConfig(optimizer="sgd", step_size=1.0, keep_well_posed=False,
                            tie_agents=False, max_policy_change=0.01)
    up = DPGUpdater(config, N, ALPHA)
    G = rng.normal(size=(200, 10 * N, N))
    w = rng.normal(size=10 * N)
    theta = Theta.nominal(SYSTEM)
    new = _observed_step(up, theta, G, w)
    change = new.to_vector() - theta.to_vector()
    F = np.where(np.outer(learnable_mask(N), learnable_mask(N)), policy_metric(G), 0.0)
    assert np.sqrt(change @ F @ change) == pytest.approx(0.01, rel=1e-9)
    assert up.last_info["trust_region"] is True
    g = np.where(learnable_mask(N), policy_gradient(G, w), 0.0)
    np.testing.assert_allclose(change / np.linalg.norm(change), -g / np.linalg.norm(g),
                               atol=1e-12)
    # a small step is left alone
    small = DPGUpdater(config.replace(step_size=1e-9), N, ALPHA)
    moved = _observed_step(small, theta, G, w).to_vector() - theta.to_vector()
    np.testing.assert_allclose(moved, -1e-9 * g, rtol=1e-6)  # rounding of theta + 1e-9
    assert small.last_info["trust_region"] is False
    with pytest.raises(ValueError, match="call observe"):
        DPGUpdater(config, N, ALPHA).step(theta, g)


# -- averaging, schedules, tying --------------------------------------------------------------
def test_averaging_returns_the_running_mean_of_the_raw_iterates():
    """With M months, theta_t = theta_{t-1} + (rho_t - theta_{t-1}) / min(t + 1, M): the plain
    mean of rho_0..rho_t while t + 1 <= M, an exponential average after."""
    M, step = 3, 0.1
    config = LearningConfig(optimizer="sgd", step_size=step, keep_well_posed=False,
                            tie_agents=False, average_months=M)
    up = DPGUpdater(config, N, ALPHA)
    grads = np.random.default_rng(8).normal(size=(6, 10 * N))
    mask = learnable_mask(N)
    theta = Theta.nominal(SYSTEM)
    rho = [theta.to_vector()]
    avg = theta.to_vector()
    for t, g in enumerate(grads, start=1):
        theta = up.step(theta, g)
        rho.append(rho[-1] - step * np.where(mask, g, 0.0))
        avg = avg + (rho[-1] - avg) / min(t + 1, M)
        np.testing.assert_allclose(theta.to_vector(), avg, rtol=1e-12, atol=1e-15)
        if t + 1 <= M:
            np.testing.assert_allclose(theta.to_vector(), np.mean(rho, axis=0), atol=1e-14)
    np.testing.assert_allclose(up.raw, rho[-1], atol=1e-14)


def test_step_size_warm_up_and_decay():
    config = LearningConfig(optimizer="sgd", step_size=0.2, keep_well_posed=False,
                            step_warmup=4, step_decay=10)
    up = DPGUpdater(config, N, ALPHA)
    theta = Theta.nominal(SYSTEM)
    sizes = []
    for _ in range(12):
        theta = up.step(theta, np.ones(10 * N))
        sizes.append(up.last_info["step_size"])
    t = np.arange(1, 13)
    np.testing.assert_allclose(sizes, 0.2 * np.minimum(1.0, t / 4) / (1.0 + (t - 1) / 10))


@pytest.mark.parametrize("optimizer", ["sgd", "adam", "natural"])
def test_tied_agents_move_alike(optimizer):
    rng = np.random.default_rng(9)
    config = LearningConfig(optimizer=optimizer, step_size=0.02, tie_agents=True)
    up = DPGUpdater(config, N, ALPHA)
    theta = Theta.nominal(SYSTEM)
    for _ in range(3):
        G = rng.normal(size=(100, 10 * N, N))
        theta = _observed_step(up, theta, G, rng.normal(size=10 * N))
    for part in PARTS:
        values = getattr(theta, part)
        np.testing.assert_allclose(values, values[0], rtol=1e-12, atol=1e-15, err_msg=part)
    assert not np.allclose(theta.to_vector(), Theta.nominal(SYSTEM).to_vector())
    if optimizer == "sgd":  # the step is the mean of each part's gradient
        up = DPGUpdater(config.replace(keep_well_posed=False), N, ALPHA)
        g = rng.normal(size=10 * N)
        move = up.step(Theta.nominal(SYSTEM), g).to_vector() - Theta.nominal(SYSTEM).to_vector()
        mean = np.repeat(np.where(learnable_mask(N), g, 0).reshape(10, N).mean(1), N)
        np.testing.assert_allclose(move, -0.02 * mean, rtol=1e-12)


@pytest.mark.parametrize("changes", [{"optimizer": "natural", "step_size": 0.03},
                                     {"optimizer": "adam", "average_months": 4}])
def test_checkpoint_of_the_new_state_resumes_exactly(changes):
    config = LearningConfig(**changes)
    rng = np.random.default_rng(10)
    batches = [(rng.normal(size=(50, 10 * N, N)), rng.normal(size=10 * N)) for _ in range(6)]
    original = DPGUpdater(config, N, ALPHA)
    theta = Theta.nominal(SYSTEM)
    for G, w in batches[:3]:
        theta = _observed_step(original, theta, G, w)
    state = json.loads(json.dumps(original.state_dict()))
    assert ("theta_raw" in state) == bool(config.average_months)
    resumed = DPGUpdater(config, N, ALPHA)
    resumed.load_state_dict(state)
    theta_a = theta_b = theta
    for G, w in batches[3:]:
        theta_a = _observed_step(original, theta_a, G, w)
        theta_b = _observed_step(resumed, theta_b, G, w)
        np.testing.assert_array_equal(theta_a.to_vector(), theta_b.to_vector())
    with pytest.raises(ValueError, match="'theta_raw' has shape"):
        resumed.load_state_dict(dict(state, theta_raw=[0.0]))


def test_short_run_with_every_option_stays_tied_and_convex():
    learning = LearningConfig(months=2, days_per_month=2, seed=3, eval_every=0,
                              optimizer="natural", step_size=0.05, max_policy_change=0.05,
                              average_months=3, exploration_margin=0.2, tie_agents=True,
                              value_features="hour*paper")
    experiment = Experiment(system=SystemConfig(N=6), learning=learning)
    history = experiment.run(progress=False)
    assert history.months == 2
    theta = experiment.theta
    assert theta.is_convex()
    for part in PARTS:
        np.testing.assert_allclose(getattr(theta, part), getattr(theta, part)[0], rtol=1e-12)
    assert all("policy_change" in info for info in history.update_info)


# -- the day-end forecast -------------------------------------------------------------------------
def test_day_end_forecast_stops_at_midnight():
    prices = Prices.month(SYSTEM, 5)
    late = until_midnight(prices)
    assert isinstance(late, DayEndPrices) and late.days == 5
    np.testing.assert_array_equal(late.buy, prices.buy)  # what the system is charged
    np.testing.assert_array_equal(late.sell, prices.sell)
    for hour in (0, 11, 12, 20, 23):
        buy, sell = late.window(hour, 12)
        ref_buy, ref_sell = prices.window(hour, 12)
        today = hour + np.arange(12) < 24
        np.testing.assert_array_equal(buy[:, today], ref_buy[:, today])
        np.testing.assert_array_equal(sell[:, today], ref_sell[:, today])
        assert np.all(buy[:, ~today] == 0.0) and np.all(sell[:, ~today] == 0.0)
    assert "until midnight" in late.source and repr(late).startswith("DayEndPrices(days=5")
    # a file's month keeps its origin (recorded by a run, and it sets the step scales)
    filed = Prices(prices.buy, origin={"file": "prices.csv", "month": "2020-10"})
    assert until_midnight(filed).origin == filed.origin
    with pytest.raises(ValueError, match="prices: expected a Prices"):
        until_midnight(prices.buy)


# -- configs of earlier runs ----------------------------------------------------------------------
def test_a_config_saved_before_the_options_reads_back_as_its_run_went():
    """A LearningConfig written before exploration_bounds and tie_agents existed belongs to a
    run that projected its exploration and learned every battery's own parameters: it must
    resume that way, whatever today's defaults."""
    saved = LearningConfig().to_dict()
    for field in ("exploration_bounds", "exploration_margin", "tie_agents", "eval_draws",
                  "natural_damping", "step_warmup", "step_decay", "max_policy_change",
                  "average_months"):
        saved.pop(field)
    old = LearningConfig.from_dict(saved)
    assert (old.exploration_bounds, old.tie_agents, old.eval_draws) == ("project", False, 1)
    assert (old.exploration_margin, old.step_decay, old.average_months) == (0.0, 0, 0)
    assert old.max_policy_change is None and old.optimizer == LearningConfig().optimizer
    today = LearningConfig()
    assert LearningConfig.from_dict(json.loads(json.dumps(today.to_dict()))) == today


def test_effective_gradient_is_what_the_rule_sees():
    g = np.arange(10.0 * N)
    tied = DPGUpdater(LearningConfig(), N, ALPHA).effective_gradient(g)
    untied = DPGUpdater(LearningConfig(tie_agents=False), N, ALPHA).effective_gradient(g)
    np.testing.assert_array_equal(untied, np.where(learnable_mask(N), g, 0.0))
    np.testing.assert_allclose(tied, np.repeat(untied.reshape(10, N).mean(axis=1), N))
    with pytest.raises(ValueError, match=r"grad has shape \(3,\)"):
        DPGUpdater(LearningConfig(), N, ALPHA).effective_gradient(np.zeros(3))
