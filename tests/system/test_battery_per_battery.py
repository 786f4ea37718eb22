"""The true model with batteries that differ: each battery is the one-battery model of its own
parameters."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import SystemConfig
from mpcrl_lite.system.battery import project_action, sample_noise, step

MIXED = SystemConfig(alpha=(1 / 24, 1 / 12, 1 / 10), U_bar=(2.0, 1.0, 0.5), P_bar=2.0,
                     noise_mean=(0.1, 0.0, -0.1), noise_var=(1.0, 0.5, 0.2),
                     p=(500.0, 1000.0, 2000.0), soc0=(0.5, 0.6, 0.7))


def _alone(i: int) -> SystemConfig:
    return SystemConfig(n=1, P_bar=10.0, **{name: MIXED.battery(name)[i] for name in
                                            ("alpha", "U_bar", "noise_mean", "noise_var", "p",
                                             "soc0")})


@pytest.mark.filterwarnings("ignore::mpcrl_lite.config.ConfigWarning")
def test_each_battery_steps_as_its_own_model():
    rng = np.random.default_rng(0)
    soc = rng.uniform(0.0, 1.0, (50, 3))
    a = rng.uniform(-2.0, 2.0, (50, 3))
    noise = rng.normal(0.0, 1.0, (50, 3))
    buy, sell = rng.uniform(10, 100, 50), rng.uniform(5, 50, 50)
    res = step(soc, a, noise, buy, sell, MIXED)
    for i in range(3):
        one = step(soc[:, i:i + 1], a[:, i:i + 1], noise[:, i:i + 1], buy, sell, _alone(i))
        np.testing.assert_array_equal(res.soc_next[:, i], one.soc_next[:, 0])
        np.testing.assert_array_equal(res.agent_cost[:, i], one.agent_cost[:, 0])


def test_noise_has_each_batterys_distribution():
    draw = sample_noise(np.random.default_rng(1), (200_000, 3), MIXED)
    np.testing.assert_allclose(draw.mean(axis=0), [0.1, 0.0, -0.1], atol=0.01)
    np.testing.assert_allclose(draw.var(axis=0), [1.0, 0.5, 0.2], rtol=0.02)
    # hour by hour equals one draw (the closed loop's contract)
    rng1, rng2 = np.random.default_rng(3), np.random.default_rng(3)
    whole = sample_noise(rng1, (4, 5, 3), MIXED)
    np.testing.assert_array_equal(whole, np.stack([sample_noise(rng2, (5, 3), MIXED)
                                                   for _ in range(4)]))
    with pytest.raises(ValueError, match="shape ending in n=3"):
        sample_noise(np.random.default_rng(0), (5,), MIXED)


def test_projection_keeps_each_batterys_bound_and_the_grid_limit():
    rng = np.random.default_rng(4)
    a = rng.uniform(-3.0, 3.0, (500, 3))
    x = project_action(a, MIXED)
    U = np.array(MIXED.U_bar)
    assert np.all(np.abs(x) <= U + 1e-12)
    assert np.all(np.maximum(x, 0).sum(1) <= MIXED.P_bar + 1e-9)
    assert np.all(np.maximum(-x, 0).sum(1) <= MIXED.P_bar + 1e-9)
    inside = np.array([[1.5, 0.4, 0.1]])
    np.testing.assert_array_equal(project_action(inside, MIXED), inside)
    # optimality: no feasible point on a random segment towards x is closer to a
    for _ in range(20):
        y = project_action(rng.uniform(-3, 3, (1, 3)), MIXED)
        t = rng.uniform(0, 1)
        z = t * x[:1] + (1 - t) * y  # feasible (convex set)
        assert np.linalg.norm(x[:1] - a[:1]) <= np.linalg.norm(z - a[:1]) + 1e-12


def test_identical_tuples_give_the_scalars_numbers():
    rng = np.random.default_rng(5)
    soc, a, noise = rng.uniform(0, 1, (20, 3)), rng.uniform(-1, 1, (20, 3)), rng.normal(size=(20, 3))
    same = SystemConfig(alpha=(1 / 12,) * 3, p=(1000.0,) * 3, U_bar=(1.0,) * 3)
    r1 = step(soc, a, noise, 50.0, 25.0, SystemConfig())
    r2 = step(soc, a, noise, 50.0, 25.0, same)
    np.testing.assert_array_equal(r1.soc_next, r2.soc_next)
    np.testing.assert_array_equal(r1.agent_cost, r2.agent_cost)
    np.testing.assert_array_equal(project_action(3 * a, SystemConfig()), project_action(3 * a, same))
