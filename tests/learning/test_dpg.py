"""The policy gradient estimate, the update rules and the theta update (mask, clip, projection)."""

from __future__ import annotations

import json
import warnings
from typing import Any

import numpy as np
import pytest

from mpcrl_lite.config import (
    OPTIMIZERS,
    PAPER_STEP_SIZE,
    Q_STEP_LIMIT,
    ConfigWarning,
    LearningConfig,
    SystemConfig,
)
from mpcrl_lite.learning.dpg import (
    DEFAULT_SCALE,
    REFERENCE_PRICE,
    DPGUpdater,
    learnable_mask,
    part_scales,
    policy_gradient,
    policy_metric,
    price_level,
    scales_follow_prices,
)
from mpcrl_lite.learning.update_rules import (
    ADAM_BETAS,
    ADAM_EPS,
    ADAM_STEP_SIZE,
    UPDATE_RULES,
    Adam,
    GradientDescent,
    UpdateRule,
    make_update_rule,
)
from mpcrl_lite.theta import CONSTANT_PARTS, PARTS, Theta

N = 3
ALPHA = 1.0 / 12.0


def theta_from(seed: int = 0) -> Theta:
    """A theta well inside the projection's bounds."""
    rng = np.random.default_rng(seed)
    vector = rng.normal(size=10 * N)
    theta = Theta.from_vector(vector, N)
    return theta.replace(alpha=np.full(N, ALPHA), phi1=np.full(N, 5.0), T1=np.full(N, 5.0))


def updater(**changes) -> DPGUpdater:
    base = {"step_size": 0.1, "keep_well_posed": False, "optimizer": "sgd",
            "tie_agents": False, **changes}
    return DPGUpdater(LearningConfig(**base), N, ALPHA)


def sensitivities(seed: int, samples: int = 40) -> np.ndarray:
    """Random policy sensitivities (samples, 10 N, N), zero for the constants phi3, T3."""
    G = np.random.default_rng(seed).normal(size=(samples, 10 * N, N))
    G[:, ~learnable_mask(N)] = 0.0
    return G


# -- policy_gradient -------------------------------------------------------------------------
def test_policy_gradient_hand_computed():
    # two samples, n_theta = 2, n = 1:  grad_pi^T w = 3 for both;  mean of grad_pi * 3
    grad_pi = np.array([[[1.0], [2.0]], [[0.0], [3.0]]])
    np.testing.assert_allclose(policy_gradient(grad_pi, np.array([1.0, 1.0])), [1.5, 7.5])
    # one sample, n = 2: G G^T w with G = [[1, 0], [1, 1], [0, 2]], w = [1, -1, 2]
    G = np.array([[1.0, 0.0], [1.0, 1.0], [0.0, 2.0]])
    w = np.array([1.0, -1.0, 2.0])
    # G^T w = [0, 3];  G [0, 3] = [0, 3, 6]
    np.testing.assert_allclose(policy_gradient(G, w), [0.0, 3.0, 6.0])


def test_policy_gradient_batch_dims_and_errors():
    rng = np.random.default_rng(1)
    grad_pi = rng.normal(size=(24, 30, 10 * N, N))
    w = rng.normal(size=10 * N)
    expected = np.mean([g @ g.T @ w for g in grad_pi.reshape(-1, 10 * N, N)], axis=0)
    np.testing.assert_allclose(policy_gradient(grad_pi, w), expected, rtol=1e-12)
    with pytest.raises(ValueError, match=r"w has shape \(29,\); expected \(30,\)"):
        policy_gradient(grad_pi, w[:29])
    with pytest.raises(ValueError, match="grad_pi has shape"):
        policy_gradient(w, w)


def test_policy_gradient_of_an_affine_scalar_policy():
    """u = k x + m, grad_theta pi = [x, 1]; if the critic's action gradient is the true
    dQ/du = g1 x + g0 (w = (g1, g0)), the gradient is E[[x, 1] (g1 x + g0)]."""
    x = np.array([-1.0, 0.5, 2.0])
    grad_pi = np.stack([x, np.ones(3)], axis=-1)[..., None]  # (3, 2, 1)
    g1, g0 = 0.7, -0.2
    expected = [np.mean(x * (g1 * x + g0)), np.mean(g1 * x + g0)]
    np.testing.assert_allclose(policy_gradient(grad_pi, np.array([g1, g0])), expected)


# -- mask ------------------------------------------------------------------------------------
def test_learnable_mask():
    mask = learnable_mask(N, learn_constants=False)
    assert mask.shape == (10 * N,) and mask.dtype == bool
    assert mask.sum() == 8 * N  # the paper's 24 parameters for n = 3
    for part in PARTS:
        assert mask[Theta.index(N, part)].all() == (part not in CONSTANT_PARTS)
    assert learnable_mask(N, learn_constants=True).all()
    with pytest.raises(ValueError, match="n=0"):
        learnable_mask(0)


# -- SGD ---------------------------------------------------------------------------------------
def test_sgd_step_is_theta_minus_step_times_grad_on_learnable_parts():
    theta = theta_from(2)
    grad = np.random.default_rng(3).normal(size=10 * N)
    up = updater(step_size=0.01)
    new = up.step(theta, grad)
    mask = learnable_mask(N)
    expected = np.where(mask, theta.to_vector() - 0.01 * grad, theta.to_vector())
    np.testing.assert_array_equal(new.to_vector(), expected)
    np.testing.assert_array_equal(new.phi3, theta.phi3)
    np.testing.assert_array_equal(new.T3, theta.T3)
    info = up.last_info
    assert info["step"] == 1 and not info["clipped"] and info["projected"] == []
    np.testing.assert_allclose(info["step_norm"], 0.01 * np.linalg.norm(grad[mask]))
    # with learn_constants the constants move as well
    new = updater(step_size=0.01, learn_constants=True).step(theta, grad)
    np.testing.assert_array_equal(new.to_vector(), theta.to_vector() - 0.01 * grad)


def test_paper_rule_is_one_call_away():
    config = LearningConfig.paper()
    assert config.optimizer == "sgd" and config.step_size == PAPER_STEP_SIZE == 5e-8
    up = DPGUpdater(config, N, ALPHA)
    theta = Theta.nominal(SystemConfig(n=N))
    grad = np.zeros(10 * N)
    grad[Theta.index(N, "delta")] = 1e6
    new = up.step(theta, grad)
    np.testing.assert_allclose(new.delta, theta.delta - 5e-8 * 1e6)


def test_default_is_per_part_scaled_adam():
    config = LearningConfig()
    assert config.optimizer == "adam" and config.step_size == ADAM_STEP_SIZE
    up = DPGUpdater.from_configs(config, SystemConfig(n=N))
    expected = part_scales(ALPHA)
    for part in PARTS:
        np.testing.assert_allclose(up.scale[Theta.index(N, part)], expected[part])
    assert expected["alpha"] == expected["delta"] == pytest.approx(ALPHA)
    assert expected["b"] == DEFAULT_SCALE["b"] == 10.0 and expected["T2"] == 100.0
    # the first Adam step moves every learnable entry by step_size times its scale
    theta = theta_from(5)  # phi1 = T1 = 5: the projection does not interfere
    grad = np.random.default_rng(0).normal(size=10 * N)
    new = up.step(theta, grad)
    move = np.abs(new.to_vector() - theta.to_vector())
    mask = learnable_mask(N)
    np.testing.assert_allclose(move[mask], (ADAM_STEP_SIZE * up.scale)[mask], rtol=1e-6)
    assert np.all(move[~mask] == 0)
    # the scales follow the unit of the prices
    cheap = DPGUpdater.from_configs(config, SystemConfig(n=N, price_scale=1e-3))
    np.testing.assert_allclose(cheap.scale[Theta.index(N, "phi2")], 0.1)
    np.testing.assert_allclose(cheap.scale[Theta.index(N, "alpha")], ALPHA)
    with pytest.raises(ValueError, match="price_scale"):
        part_scales(ALPHA, 0.0)


def test_scales_follow_the_months_price_level_on_request():
    """scale_to_prices: the cost parts' scales (and the terminal scale) are multiplied by the
    month's mean buying price over the shipped month's; the model parts keep theirs."""
    from mpcrl_lite.system.prices import Prices, load_default_profile

    assert REFERENCE_PRICE == float(load_default_profile().mean())
    shipped = Prices.default()
    assert price_level(shipped) == 1.0 and price_level(shipped.buy) == 1.0
    system = SystemConfig(n=N)
    config = LearningConfig(scale_to_prices=True, gradient="pathwise")
    plain = DPGUpdater.from_configs(config.replace(scale_to_prices=False), system, shipped)
    # the shipped month: the same scales bit for bit, so the same History
    np.testing.assert_array_equal(DPGUpdater.from_configs(config, system, shipped).scale,
                                  plain.scale)
    dear = shipped.scaled(2.5)
    assert price_level(dear) == pytest.approx(2.5, rel=1e-15)
    up = DPGUpdater.from_configs(config, system, dear)
    model = np.zeros(10 * N, dtype=bool)
    for part in ("alpha", "delta"):
        model[Theta.index(N, part)] = True
    np.testing.assert_array_equal(up.scale[model], plain.scale[model])
    np.testing.assert_allclose(up.scale[~model], price_level(dear) * plain.scale[~model],
                               rtol=1e-15)
    np.testing.assert_allclose(up.scale[Theta.index(N, "T1")], 2.5 * config.terminal_scale)
    # off, the prices change nothing
    np.testing.assert_array_equal(
        DPGUpdater.from_configs(config.replace(scale_to_prices=False), system, dear).scale,
        plain.scale)
    # the default (None) follows prices read from a file, not the shipped month or arrays
    auto = LearningConfig()
    assert auto.scale_to_prices is None and auto.to_dict()["scale_to_prices"] is None
    filed = Prices(dear.buy, origin={"file": "prices.csv", "month": "2020-10"})
    assert not scales_follow_prices(auto, shipped) and not scales_follow_prices(auto, dear)
    assert scales_follow_prices(auto, filed)
    assert not scales_follow_prices(auto.replace(scale_to_prices=False), filed)
    np.testing.assert_array_equal(DPGUpdater.from_configs(auto, system, dear).scale,
                                  DPGUpdater.from_configs(auto, system).scale)
    np.testing.assert_array_equal(
        DPGUpdater.from_configs(auto, system, filed).scale,
        DPGUpdater.from_configs(auto.replace(scale_to_prices=True), system, dear).scale)
    # a config written before the field reads back as its run learned: without it
    old = {k: v for k, v in auto.to_dict().items() if k != "scale_to_prices"}
    assert LearningConfig.from_dict(old).scale_to_prices is False
    assert LearningConfig.from_dict(auto.to_dict()).scale_to_prices is None
    with pytest.raises(ValueError, match="without the month's prices"):
        DPGUpdater.from_configs(config, system)
    with pytest.raises(ValueError, match="not positive; expected scale_to_prices=False"):
        price_level(-shipped.buy)
    with pytest.raises(ValueError, match="expected finite prices"):
        price_level(np.array([1.0, np.nan]))


def test_step_limit_shortens_a_step_that_runs_away():
    """step_limit: no entry moves by more than step_limit of its scale; a longer step keeps
    its direction; shorter steps (and no limit) are untouched, bit for bit."""
    theta = theta_from(3)
    grad = np.random.default_rng(3).normal(size=10 * N) * 1e3
    free = updater()
    limited = updater(step_limit=2.0)
    full = free.step(theta, grad).to_vector() - theta.to_vector()
    assert free.config.step_limit == 0.0 and "step_limited" not in free.last_info
    moved = limited.step(theta, grad).to_vector() - theta.to_vector()
    reach = np.abs(moved) / limited.scale
    assert reach.max() == pytest.approx(2.0, rel=1e-12)
    factor = limited.last_info["step_limited"]
    assert 0.0 < factor < 1.0
    np.testing.assert_allclose(moved, factor * full, rtol=1e-12, atol=1e-15)
    # a short step is not touched
    short = updater(step_limit=2.0)
    small = short.step(theta, grad * 1e-9).to_vector()
    np.testing.assert_array_equal(small, updater().step(theta, grad * 1e-9).to_vector())
    assert short.last_info["step_limited"] == 1.0
    # off by default; the Q-learner's inner updater applies it to its Newton steps
    assert LearningConfig().step_limit == 0.0 and "step_limit" not in LearningConfig().to_dict()
    q = LearningConfig(learner="q", step_limit=Q_STEP_LIMIT)
    assert q.to_dict()["step_limit"] == 5.0 and LearningConfig.from_dict(q.to_dict()) == q
    from mpcrl_lite.learning.qlearning import QLearningUpdater

    assert QLearningUpdater(q, SystemConfig(n=N)).inner.config.step_limit == 5.0


def test_scaled_gradient_norm_is_recorded():
    up = updater(optimizer="adam", step_size=ADAM_STEP_SIZE)
    grad = np.random.default_rng(1).normal(size=10 * N)
    up.step(theta_from(3), grad)
    g = np.where(learnable_mask(N), grad, 0.0)
    assert up.last_info["grad_norm"] == pytest.approx(np.linalg.norm(g))
    assert up.last_info["grad_norm_scaled"] == pytest.approx(np.linalg.norm(up.scale * g))


# -- clipping and projection -----------------------------------------------------------------
def test_clipping_rescales_the_step_to_the_bound():
    theta = theta_from(4)
    grad = np.random.default_rng(5).normal(size=10 * N)
    free = updater(step_size=1.0).step(theta, grad)
    up = updater(step_size=1.0, grad_clip=0.5)
    clipped = up.step(theta, grad)
    step = theta.to_vector() - clipped.to_vector()
    np.testing.assert_allclose(np.linalg.norm(step), 0.5)
    free_step = theta.to_vector() - free.to_vector()
    np.testing.assert_allclose(step, free_step * 0.5 / np.linalg.norm(free_step))
    assert up.last_info["clipped"] and up.last_info["step_norm"] == pytest.approx(0.5)
    assert up.last_info["raw_step_norm"] == pytest.approx(np.linalg.norm(free_step))
    # a step already small enough is left alone
    small = updater(step_size=1e-3, grad_clip=0.5)
    small.step(theta, grad)
    assert not small.last_info["clipped"]


def test_projection_keeps_the_mpc_well_posed():
    theta = theta_from(6).replace(
        alpha=np.array([0.002, ALPHA, ALPHA]), phi1=np.array([0.1, 1.0, 1.0]),
        T1=np.array([1.0, 1.0, 0.05]),
    )
    grad = np.zeros(10 * N)
    grad[Theta.index(N, "alpha")] = [1.0, 0.0, 0.0]  # alpha[1] -> 0.002 - 0.01 < alpha_min
    grad[Theta.index(N, "phi1")] = [20.0, 0.0, 0.0]  # phi1[1] -> 0.1 - 0.2 < 0
    grad[Theta.index(N, "T1")] = [0.0, 0.0, 10.0]  # T1[3] -> 0.05 - 0.1 < 0
    grad[Theta.index(N, "phi2")] = [100.0, 0.0, 0.0]  # unconstrained: moves freely
    up = updater(step_size=0.01, keep_well_posed=True, alpha_min=1e-3)
    new = up.step(theta, grad)
    np.testing.assert_allclose(new.alpha, [1e-3, ALPHA, ALPHA])
    np.testing.assert_allclose(new.phi1, [0.0, 1.0, 1.0])
    np.testing.assert_allclose(new.T1, [1.0, 1.0, 0.0])
    np.testing.assert_allclose(new.phi2[0], theta.phi2[0] - 1.0)
    assert new.is_convex()
    assert up.last_info["projected"] == ["alpha[1]", "phi1[1]", "T1[3]"]
    assert up.last_info["projection_norm"] == pytest.approx(np.linalg.norm([0.009, 0.1, 0.05]))
    # without the projection the same step leaves the convex set
    assert not updater(step_size=0.01).step(theta, grad).is_convex()


def test_momentum_into_a_held_bound_is_reset_on_request():
    """Adam's first moment of an entry the projection holds at its bound is zeroed with
    reset_momentum_at_bounds: when the gradient turns, the entry leaves the bound at once,
    while without the option the momentum keeps it there; the other entries keep theirs."""
    n_phi1, n_phi2 = Theta.index(N, "phi1"), Theta.index(N, "phi2")
    theta = theta_from(6).replace(phi1=np.zeros(N), T1=np.ones(N))
    push = np.zeros(10 * N)
    push[n_phi1], push[n_phi2] = 1.0, 1.0  # phi1 would go below 0
    turn = np.zeros(10 * N)
    turn[n_phi1], turn[n_phi2] = -0.5, 1.0  # now phi1 should grow (a weaker pull)
    ends = {}
    for reset in (False, True):
        up = DPGUpdater.from_configs(LearningConfig(reset_momentum_at_bounds=reset),
                                     SystemConfig(n=N))
        held = up.step(theta, push)
        np.testing.assert_array_equal(held.phi1, 0.0)
        assert up.last_info["projected"] == ["phi1[1]", "phi1[2]", "phi1[3]"]
        assert np.all(up.rule.m[n_phi2] != 0.0)
        assert np.all((up.rule.m[n_phi1] == 0.0) == reset)
        ends[reset] = up.step(held, turn)
    np.testing.assert_array_equal(ends[False].phi1, 0.0)  # still pushed into the bound
    assert np.all(ends[True].phi1 > 0.0)
    np.testing.assert_array_equal(ends[True].phi2, ends[False].phi2)
    assert "reset_momentum_at_bounds" not in LearningConfig().to_dict()
    on = LearningConfig(reset_momentum_at_bounds=True)
    assert LearningConfig.from_dict(on.to_dict()) == on


# -- Adam --------------------------------------------------------------------------------------
def test_adam_first_and_second_steps_by_hand():
    theta = theta_from(7)
    rng = np.random.default_rng(8)
    g1, g2 = rng.normal(size=(2, 10 * N))
    up = updater(optimizer="adam", step_size=ADAM_STEP_SIZE)
    mask = learnable_mask(N)
    scale = np.ones(10 * N)
    for part, value in part_scales(ALPHA).items():
        scale[Theta.index(N, part)] = value
    b1, b2 = ADAM_BETAS
    # first step: m_hat = g, v_hat = g^2  =>  direction = scale * g / (|g| + eps)
    new = up.step(theta, g1)
    d1 = np.where(mask, scale * g1 / (np.abs(g1) + ADAM_EPS), 0.0)
    np.testing.assert_allclose(new.to_vector(), theta.to_vector() - ADAM_STEP_SIZE * d1, rtol=1e-14)
    # second step
    newer = up.step(new, g2)
    m = (1 - b1) * (b1 * g1 + g2)
    v = (1 - b2) * (b2 * g1**2 + g2**2)
    d2 = np.where(mask, scale * (m / (1 - b1**2)) / (np.sqrt(v / (1 - b2**2)) + ADAM_EPS), 0.0)
    np.testing.assert_allclose(
        newer.to_vector(), new.to_vector() - ADAM_STEP_SIZE * d2, rtol=1e-13
    )
    np.testing.assert_array_equal(newer.phi3, theta.phi3)


def test_adam_custom_scale_and_small_step_warning():
    up = DPGUpdater(
        LearningConfig(optimizer="adam", step_size=0.1, keep_well_posed=False), N, ALPHA,
        scale={"b": 100.0},
    )
    theta = theta_from(9)
    grad = np.ones(10 * N)
    new = up.step(theta, grad)
    np.testing.assert_allclose(theta.b - new.b, 0.1 * 100.0, rtol=1e-7)
    np.testing.assert_allclose(theta.alpha - new.alpha, 0.1 * ALPHA, rtol=1e-7)
    np.testing.assert_allclose(theta.phi2 - new.phi2, 0.1 * DEFAULT_SCALE["phi2"], rtol=1e-7)
    with pytest.warns(ConfigWarning, match="optimizer='adam'"):
        DPGUpdater(LearningConfig(optimizer="adam", step_size=PAPER_STEP_SIZE), N, ALPHA)
    with pytest.raises(ValueError, match="unknown part"):
        DPGUpdater(LearningConfig(optimizer="adam", step_size=0.1), N, ALPHA, scale={"x": 1.0})


# -- update rules ------------------------------------------------------------------------------
def test_every_optimizer_name_has_one_update_rule():
    assert set(UPDATE_RULES) == set(OPTIMIZERS)
    for name, rule in UPDATE_RULES.items():
        assert issubclass(rule, UpdateRule) and rule.name == name
        up = DPGUpdater(LearningConfig(optimizer=name, step_size=0.02), N, ALPHA)
        assert type(up.rule) is rule and up.rule.size == 10 * N
    assert UPDATE_RULES["sgd"] is GradientDescent and UPDATE_RULES["adam"] is Adam


def test_adam_rule_keeps_the_operation_order_of_its_formula():
    """Written out with the same floating-point operations in the same order, so equal to
    the last bit: learning runs are reproduced exactly across versions."""
    rng = np.random.default_rng(13)
    size = 10 * N
    scale = rng.uniform(0.01, 100.0, size)
    rule = Adam(size, scale)
    (b1, b2), eps = ADAM_BETAS, ADAM_EPS
    m, v = np.zeros(size), np.zeros(size)
    for t in range(1, 21):
        g = rng.normal(size=size) * 10.0 ** rng.integers(-4, 9, size=size)
        m = b1 * m + (1.0 - b1) * g
        v = b2 * v + (1.0 - b2) * g**2
        expected = scale * (m / (1.0 - b1**t)) / (np.sqrt(v / (1.0 - b2**t)) + eps)
        np.testing.assert_array_equal(rule.direction(g, t), expected)
    np.testing.assert_array_equal(rule.m, m)
    np.testing.assert_array_equal(rule.v, v)
    rule.reset()
    assert not rule.m.any() and not rule.v.any()


@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_updater_moves_theta_by_step_size_times_the_rules_direction(optimizer):
    config = LearningConfig(optimizer=optimizer, step_size=0.03, keep_well_posed=False,
                            tie_agents=False, natural_damping=0.0)
    up = DPGUpdater(config, N, ALPHA)
    twin = make_update_rule(optimizer, 10 * N, scale=up.scale, damping=0.0)
    theta = theta_from(14)
    for t, g in enumerate(np.random.default_rng(15).normal(size=(5, 10 * N)), start=1):
        G = sensitivities(100 + t)
        up.observe(G)  # the metric, used by the natural gradient only
        new = up.step(theta, g)
        direction = twin.direction(np.where(up.mask, g, 0.0), t, metric=policy_metric(G))
        np.testing.assert_array_equal(new.to_vector(), theta.to_vector() - 0.03 * direction)
        theta = new


def test_make_update_rule_passes_each_rule_only_its_options():
    sgd = make_update_rule("sgd", 4, scale=np.ones(4), betas=(0.5, 0.5), eps=1.0)
    g = np.array([1.0, -2.0, 0.0, 3.0])
    assert sgd.direction(g, 1) is g and sgd.state_arrays() == {}
    adam = make_update_rule("adam", 4, scale=np.ones(4), betas=(0.5, 0.5), eps=1.0)
    assert adam.betas == (0.5, 0.5) and adam.eps == 1.0
    natural = make_update_rule("natural", 4, scale=np.ones(4), betas=(0.5, 0.5), damping=0.1)
    assert natural.betas == (0.5, 0.5) and natural.damping == 0.1
    with pytest.raises(ValueError, match=r"^optimizer='rmsprop': expected one of 'sgd', 'adam', "
                                         r"'natural'"):
        make_update_rule("rmsprop", 4)
    with pytest.raises(ValueError, match=r"betas\[0\]=1.0: expected a value in \[0, 1\)"):
        Adam(4, np.ones(4), betas=(1.0, 0.5))
    with pytest.raises(ValueError, match=r"eps=0: expected a value in \(0, inf\)"):
        Adam(4, np.ones(4), eps=0)
    with pytest.raises(ValueError, match=r"scale has shape \(3,\); expected \(4,\)"):
        Adam(4, np.ones(3))


@pytest.mark.parametrize("optimizer", OPTIMIZERS)
def test_checkpoint_layout_is_one_for_every_rule(optimizer):
    up = DPGUpdater(LearningConfig(optimizer=optimizer, step_size=0.02), N, ALPHA)
    up.observe(sensitivities(16))
    up.step(theta_from(16), np.random.default_rng(17).normal(size=10 * N))
    state = json.loads(json.dumps(up.state_dict()))
    assert list(state) == ["optimizer", "n", "step_count", "m", "v"]
    assert state["optimizer"] == optimizer and state["n"] == N and state["step_count"] == 1
    assert len(state["m"]) == len(state["v"]) == 10 * N
    if optimizer == "sgd":  # no moments: zeros, as every checkpoint written so far
        assert not any(state["m"]) and not any(state["v"])
    else:
        assert any(state["m"]) and any(state["v"])


def test_a_checkpoint_written_in_the_old_layout_resumes():
    """The JSON keys of DPGUpdater.state_dict are a contract: a state written before the
    update rules had classes loads, and the next Adam step uses its moments."""
    size = 10
    m = [0.1 * (i - 4) for i in range(size)]
    v = [0.01 * (i + 1) for i in range(size)]
    text = json.dumps({"optimizer": "adam", "n": 1, "step_count": 2, "m": m, "v": v})
    up = DPGUpdater(LearningConfig(step_size=0.02, keep_well_posed=False), 1, ALPHA)
    up.load_state_dict(json.loads(text))
    assert up.state_dict() == json.loads(text)
    theta = Theta.nominal(SystemConfig(n=1, P_bar=0.5))
    g = np.linspace(-1.0, 1.0, size)
    new = up.step(theta, g)
    (b1, b2), t = ADAM_BETAS, 3
    g = np.where(up.mask, g, 0.0)
    m_t = b1 * np.array(m) + (1.0 - b1) * g
    v_t = b2 * np.array(v) + (1.0 - b2) * g**2
    direction = up.scale * (m_t / (1.0 - b1**t)) / (np.sqrt(v_t / (1.0 - b2**t)) + ADAM_EPS)
    np.testing.assert_array_equal(new.to_vector(), theta.to_vector() - 0.02 * direction)
    assert up.step_count == 3


# -- checkpoints -------------------------------------------------------------------------------
@pytest.mark.parametrize("optimizer", ["sgd", "adam"])
def test_state_dict_round_trip_resumes_exactly(optimizer):
    config = LearningConfig(optimizer=optimizer, step_size=0.05, grad_clip=1.0)
    grads = np.random.default_rng(10).normal(size=(6, 10 * N))
    original = DPGUpdater(config, N, ALPHA)
    theta = theta_from(11)
    for g in grads[:3]:
        theta = original.step(theta, g)
    state = json.loads(json.dumps(original.state_dict()))  # through JSON, as a checkpoint
    resumed = DPGUpdater(config, N, ALPHA)
    resumed.load_state_dict(state)
    theta_a = theta_b = Theta.from_dict(json.loads(json.dumps(theta.to_dict())))
    for g in grads[3:]:
        theta_a = original.step(theta_a, g)
        theta_b = resumed.step(theta_b, g)
        assert theta_a == theta_b
        assert original.last_info == resumed.last_info
    assert resumed.step_count == 6


def test_load_state_dict_rejects_mismatches():
    sgd = DPGUpdater(LearningConfig.paper(), N, ALPHA)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConfigWarning)
        adam = DPGUpdater(LearningConfig(optimizer="adam"), N, ALPHA)
    with pytest.raises(ValueError, match="state optimizer='sgd'; expected 'adam'"):
        adam.load_state_dict(sgd.state_dict())
    state = sgd.state_dict()
    with pytest.raises(ValueError, match="state n=3; expected 2"):
        DPGUpdater(LearningConfig.paper(), 2, ALPHA).load_state_dict(state)
    with pytest.raises(ValueError, match=r"state 'm' has shape \(2,\)"):
        sgd.load_state_dict(dict(state, m=[0.0, 0.0]))
    with pytest.raises(ValueError, match="expected"):
        sgd.load_state_dict({"m": []})


# -- errors ------------------------------------------------------------------------------------
def test_step_errors():
    up = updater()
    theta = theta_from(12)
    with pytest.raises(ValueError, match=r"grad has shape \(29,\); expected \(30,\)"):
        up.step(theta, np.zeros(29))
    with pytest.raises(ValueError, match="non-finite"):
        up.step(theta, np.full(30, np.nan))
    with pytest.raises(ValueError, match="expected a Theta with n=3"):
        up.step(Theta.nominal(SystemConfig(n=2)), np.zeros(30))
    with pytest.raises(ValueError, match="system_alpha=0"):
        DPGUpdater(LearningConfig(), N, 0.0)
    with pytest.warns(ConfigWarning, match="alpha_min"):
        DPGUpdater(LearningConfig(alpha_min=0.5), N, ALPHA)
    assert up.step_count == 0  # failed calls do not count


def test_from_configs():
    up = DPGUpdater.from_configs(LearningConfig(), SystemConfig(n=2))
    assert up.n == 2 and up.system_alpha == pytest.approx(1 / 12) and up.mask.sum() == 16


def _learn_and_resume(tmp_path, capsys, flag: str, *extra: str) -> tuple[list[str], Any]:
    """``learn`` one month with ``flag``, resume to two without it: the command's common
    arguments and the History."""
    from conftest import run_cli

    from mpcrl_lite.learning.history import History

    common = ["learn", "--days", "3", "--out", str(tmp_path / "run"), "--no-figures",
              "--eval-draws", "1", *extra]
    status, _, err = run_cli([*common, "--months", "1", flag], capsys)
    assert status == 0, err
    status, _, err = run_cli([*common, "--months", "2", "--resume"], capsys)
    assert status == 0, err
    history = History.load(tmp_path / "run")
    assert history.months == 2
    return common, history


def test_learn_scales_to_prices_on_request(tmp_path, capsys):
    """learn --scale-to-prices records the option, a resume keeps it (with or without the
    flag); the updater's scales are the month's; the Q-learner's inner updater and every
    decentralized local updater follow too."""
    from conftest import run_cli

    from mpcrl_lite.decentralized.learner import DecentralizedExperiment
    from mpcrl_lite.learning.experiment import Experiment
    from mpcrl_lite.learning.q_experiment import QLearningExperiment
    from mpcrl_lite.system.prices import Prices

    (tmp_path / "dear.yaml").write_text("price_scale: 2.0\n")
    common, history = _learn_and_resume(tmp_path, capsys, "--scale-to-prices",
                                         "--system", str(tmp_path / "dear.yaml"))
    assert history.learning.scale_to_prices
    status, _, err = run_cli([*common, "--months", "3", "--resume", "--scale-to-prices"],
                             capsys)
    assert status == 0, err
    system = SystemConfig(price_scale=2.0)
    learning = LearningConfig(days_per_month=3, scale_to_prices=True)
    prices = Prices.month(system, 3)
    level = price_level(prices)
    exp = Experiment(system, learning=learning, prices=prices)
    plain = DPGUpdater.from_configs(learning.replace(scale_to_prices=False),
                                    SystemConfig(price_scale=1.0))
    b = Theta.index(system.n, "b")
    np.testing.assert_allclose(exp.updater.scale[b], level * plain.scale[b], rtol=1e-15)
    q = QLearningExperiment(system, learning=learning.replace(learner="q"), prices=prices)
    np.testing.assert_allclose(q.updater.inner.scale[b], level * plain.scale[b], rtol=1e-15)
    dec = DecentralizedExperiment(system, learning=learning, prices=prices)
    for local in dec.updaters:  # one battery each: its part b is entry 2
        np.testing.assert_allclose(local.scale[2], level * plain.scale[b][0], rtol=1e-15)


def test_learn_limits_the_steps_on_request(tmp_path, capsys):
    """learn --step-limit records the limit, a resume keeps it and refuses another; each
    update's info says by how much its step was shortened."""
    from conftest import run_cli

    common, history = _learn_and_resume(tmp_path, capsys, "--step-limit=5", "--learner", "q")
    assert history.learning.step_limit == 5.0 and history.learning.learner == "q"
    assert all(0.0 < info["step_limited"] <= 1.0 for info in history.update_info)
    status, _, err = run_cli([*common, "--months", "3", "--resume", "--step-limit", "0"],
                             capsys)
    assert status == 2 and "--step-limit 0.0 with --resume" in err, err


def test_learn_resets_momentum_at_bounds_on_request(tmp_path, capsys):
    """learn --reset-momentum-at-bounds records the option, a resume keeps it."""
    _, history = _learn_and_resume(tmp_path, capsys, "--reset-momentum-at-bounds")
    assert history.learning.reset_momentum_at_bounds
