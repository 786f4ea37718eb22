"""Many candidates at once (mpcrl_lite.sim.candidates): K thetas x M draws x D days in one
closed loop give each candidate and draw the J of that candidate evaluated alone on that draw
(common random numbers), on every back-end and with the day-end forecast."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import convex_theta

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.registry import make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.candidates import candidate_noise, check_draws, evaluate_candidates
from mpcrl_lite.sim.closed_loop import draw_J, evaluate_mpc
from mpcrl_lite.system.forecast import forecast_prices
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

SEED = 4


@pytest.fixture(scope="module")
def setup():
    system = SystemConfig(N=6)
    prices = Prices.month(system, 3)
    rng = np.random.default_rng(8)
    thetas = [Theta.nominal(system), convex_theta(rng, system.n),
              convex_theta(rng, system.n, quadratic=True)]
    return system, prices, thetas


@pytest.mark.parametrize(("backend", "forecast"), [("kernel", "paper"), ("batch", "paper"),
                                                   ("kernel", "until_midnight")])
def test_candidates_equal_one_at_a_time(setup, backend, forecast):
    system, prices, thetas = setup
    cfg = MPCConfig(backend=backend, forecast=forecast)
    solver = make_solver(MPC(system), cfg)
    J = evaluate_candidates(thetas, system, cfg, prices, SEED, 3, solver=solver)
    assert J.shape == (3, 3)
    seen = forecast_prices(prices, cfg)
    for k, theta in enumerate(thetas):
        alone = draw_J(evaluate_mpc(theta, solver, seen, system, SEED, draws=3), 3)
        np.testing.assert_allclose(J[k], alone, rtol=1e-12, atol=0.0)
    # the candidates differ, and so do the draws (else the comparison could not fail)
    assert np.ptp(J[:, 0]) > 1.0 and np.ptp(J[0]) > 1e-3


def test_draws_by_index_are_columns_of_the_full_set(setup):
    system, prices, thetas = setup
    cfg = MPCConfig()
    solver = make_solver(MPC(system), cfg)
    full = evaluate_candidates(np.stack([t.to_vector() for t in thetas]), system, cfg, prices,
                               SEED, 4, solver=solver)
    some = evaluate_candidates(thetas, system, cfg, prices, SEED, [3, 1], solver=solver)
    np.testing.assert_allclose(some, full[:, [3, 1]], rtol=1e-12, atol=0.0)
    noise = candidate_noise(system, prices.days, SEED, [3, 1])
    np.testing.assert_array_equal(noise[:, prices.days:], candidate_noise(system, prices.days,
                                                                         SEED, [1]))


def test_one_candidate_without_a_solver(setup):
    system, prices, thetas = setup
    J = evaluate_candidates(thetas[:1], system, None, prices, SEED, 2)
    solver = make_solver(MPC(system), MPCConfig())
    ref = draw_J(evaluate_mpc(thetas[0], solver, prices, system, SEED, draws=2), 2)
    np.testing.assert_allclose(J[0], ref, rtol=1e-12, atol=0.0)


@pytest.mark.parametrize(("draws", "match"), [(0, "draws=0"), ([], "distinct"),
                                              ([1, 1], "distinct"), ([-1], "distinct"),
                                              (True, "draws=True"), ("ab", "sequence of draw")])
def test_bad_draws(draws, match):
    with pytest.raises(ValueError, match=match):
        check_draws(draws)


def test_bad_candidates(setup):
    system, prices, thetas = setup
    with pytest.raises(ValueError, match="got one Theta"):
        evaluate_candidates(thetas[0], system, None, prices, SEED)
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        evaluate_candidates(np.zeros(3), system, None, prices, SEED)
    with pytest.raises(ValueError, match="n=3"):
        evaluate_candidates([Theta.nominal(SystemConfig(n=2))], system, None, prices, SEED)
    with pytest.raises(ValueError, match="another system"):
        evaluate_candidates(thetas, system, None, prices, SEED,
                            solver=make_solver(MPC(SystemConfig()), MPCConfig()))


def test_a_candidate_does_not_depend_on_the_others(setup):
    """Bit for bit: a candidate's J is the same alone and among others (so a search gives
    the same candidates however its generations are split over workers)."""
    system, prices, thetas = setup
    cfg = MPCConfig()
    solver = make_solver(MPC(system), cfg)
    together = evaluate_candidates(thetas, system, cfg, prices, SEED, 2, solver=solver)
    for k, theta in enumerate(thetas):
        alone = evaluate_candidates([theta], system, cfg, prices, SEED, 2, solver=solver)
        np.testing.assert_array_equal(together[k], alone[0])
