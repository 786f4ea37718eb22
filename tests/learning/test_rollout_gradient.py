"""The policy gradient from measured slopes of the cost-to-go (mpcrl_lite.learning.rollout_gradient):
it is the gradient of J on the same noise (finite differences in theta), its slopes are the
differences of replayed days, and bad input is refused before any solve."""

from __future__ import annotations

import numpy as np
import pytest

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.learning.rollout_gradient import DEFAULT_EPS, rollout_policy_gradient
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import MPCPolicy, simulate
from mpcrl_lite.system.battery import sample_noise
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SYSTEM = SystemConfig()
DAYS = 3
H = SYSTEM.hours_per_day


@pytest.fixture(scope="module")
def setup():
    prices = Prices.month(SYSTEM, DAYS)
    solver = make_solver(MPC(SYSTEM), MPCConfig(), Theta.nominal(SYSTEM))
    noise = sample_noise(np.random.default_rng(5), (H, DAYS, SYSTEM.n), SYSTEM)
    theta = Theta.nominal(SYSTEM)
    return prices, solver, noise, theta, rollout_policy_gradient(theta, solver, prices, SYSTEM,
                                                                 noise)


def _J(solver, prices, noise, theta):
    record = simulate(MPCPolicy(solver, theta, prices), prices.buy[:, :H], prices.sell[:, :H],
                      SYSTEM, noise=noise)
    return record.J()


def test_it_is_the_gradient_of_J_on_the_same_noise(setup):
    """The deterministic policy gradient theorem, checked: along random directions the
    central difference of J(theta) (same noise, a step that moves the actions by about
    1e-4 MW) equals the rollout gradient's directional derivative. The cost has kinks (the
    soc penalty, buying against selling), so the agreement is to a few per cent, not to
    rounding."""
    prices, solver, noise, theta, result = setup
    assert result.ok.all()
    v0 = theta.to_vector()
    rng = np.random.default_rng(1)
    scale = np.abs(result.grad) / np.abs(result.grad).max()
    errors = []
    for _ in range(4):
        step = 1e-4 * rng.standard_normal(v0.size) * scale
        fd = (_J(solver, prices, noise, Theta.from_vector(v0 + step, SYSTEM.n))
              - _J(solver, prices, noise, Theta.from_vector(v0 - step, SYSTEM.n))) / 2.0
        errors.append(abs(fd - result.grad @ step) / abs(fd))
    assert max(errors) < 0.1, errors
    assert np.median(errors) < 0.06, errors


def test_the_slopes_are_replayed_days(setup):
    """One slope by hand: the last hour's day replayed with battery 0's action moved by
    +-eps is one step of the true system, so its slope is that step's cost difference."""
    prices, solver, noise, theta, result = setup
    from mpcrl_lite.system.battery import step

    record = simulate(MPCPolicy(solver, theta, prices), prices.buy[:, :H], prices.sell[:, :H],
                      SYSTEM, noise=noise)
    k, e = H - 1, np.zeros(SYSTEM.n)
    e[0] = DEFAULT_EPS
    up = step(record.soc[k], record.policy[k] + e, noise[k], prices.buy[:, k], prices.sell[:, k],
              SYSTEM)
    down = step(record.soc[k], record.policy[k] - e, noise[k], prices.buy[:, k],
                prices.sell[:, k], SYSTEM)
    expected = (up.stage_cost - down.stage_cost) / (2 * DEFAULT_EPS)
    np.testing.assert_allclose(result.action_gradient[k, :, 0], expected, rtol=1e-12)
    assert result.grad_pi.shape == (H, DAYS, Theta.nominal(SYSTEM).to_vector().size, SYSTEM.n)
    assert np.isclose(result.J, record.J())


def test_a_wide_difference_is_a_secant(setup):
    """With the half-width of the exploration the slopes are secants: they differ from the
    local slopes (the cost-to-go is not linear over 0.2 MW) but are finite everywhere."""
    prices, solver, noise, theta, result = setup
    wide = rollout_policy_gradient(theta, solver, prices, SYSTEM, noise, eps=0.2)
    assert np.isfinite(wide.action_gradient).all()
    assert not np.allclose(wide.action_gradient, result.action_gradient, rtol=1e-3)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"eps": 0.0}, "eps"),
    ({"eps": float("nan")}, "eps"),
    ({"noise": np.zeros((H, DAYS + 1, SYSTEM.n))}, "noise has shape"),
    ({"noise": np.full((H, DAYS, SYSTEM.n), np.nan)}, "non-finite"),
    ({"theta": Theta.nominal(SystemConfig(n=2))}, "theta="),
])
def test_bad_input_is_refused(setup, kwargs, match):
    prices, solver, noise, theta, _ = setup
    args = {"theta": theta, "noise": noise, **kwargs}
    with pytest.raises(ValueError, match=match):
        rollout_policy_gradient(args["theta"], solver, prices, SYSTEM, args["noise"],
                                **{k: v for k, v in kwargs.items() if k == "eps"})


def test_draws_stacked_are_the_draws_alone(setup):
    """K draws of the month in one call give the mean of the draws' gradients (each draw's
    days are the month's days), as one call per draw would."""
    prices, solver, noise, theta, result = setup
    other = sample_noise(np.random.default_rng(6), (H, DAYS, SYSTEM.n), SYSTEM)
    second = rollout_policy_gradient(theta, solver, prices, SYSTEM, other)
    both = rollout_policy_gradient(theta, solver, prices, SYSTEM,
                                   np.concatenate([noise, other], axis=1))
    np.testing.assert_allclose(both.grad, (result.grad + second.grad) / 2, rtol=1e-9,
                               atol=1e-9 * np.abs(result.grad).max())
    np.testing.assert_allclose(both.J, (result.J + second.J) / 2, rtol=1e-12)
