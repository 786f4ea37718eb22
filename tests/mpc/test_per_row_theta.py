"""One theta per row in every back-end: a call whose rows carry different thetas (runs or
candidates stacked in one call) gives each row what a call with that row's theta alone gives
(solutions, warm-started solutions, sensitivities), and :class:`MPCPolicy` / :func:`run_month`
with a list of thetas give each block the month of its theta alone."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import convex_theta

from mpcrl_lite.config import MPCConfig, SystemConfig
from mpcrl_lite.mpc.backends.registry import REGISTRY, make_solver
from mpcrl_lite.mpc.formulation import MPC
from mpcrl_lite.sim.closed_loop import RunBlocks, run_month
from mpcrl_lite.system.prices import Prices
from mpcrl_lite.theta import Theta

BACKENDS = sorted(REGISTRY)
ROWS = 3  # rows per theta


@pytest.fixture(scope="module")
def small_mpc() -> MPC:
    return MPC(SystemConfig(N=6))


@pytest.fixture(scope="module")
def thetas(small_mpc) -> list[Theta]:
    rng = np.random.default_rng(31)
    n = small_mpc.n
    return [Theta.nominal(small_mpc.system), convex_theta(rng, n),
            convex_theta(rng, n, quadratic=True)]


def problems(mpc: MPC, thetas: list[Theta], seed: int = 5):
    """States and price windows of ``ROWS`` rows per theta, the rows interleaved
    (theta 0, 1, 2, 0, 1, 2, ...), and each row's theta vector."""
    rng = np.random.default_rng(seed)
    rows = ROWS * len(thetas)
    soc = rng.uniform(0.1, 0.9, (rows, mpc.n))
    buy = rng.uniform(5.0, 130.0, (rows, mpc.N))
    which = np.tile(np.arange(len(thetas)), ROWS)
    vectors = np.stack([thetas[k].to_vector() for k in which])
    return soc, buy, 0.5 * buy, which, vectors


def tolerance(name: str) -> dict:
    """The compiled and the numpy interior points repeat their arithmetic exactly; IPOPT's
    iterations are row by row too, its polish to rounding level."""
    return {"atol": 1e-9, "rtol": 1e-9} if name == "ipopt" else {"atol": 0.0, "rtol": 0.0}


@pytest.mark.parametrize("name", BACKENDS)
def test_each_row_gets_its_own_theta(small_mpc, thetas, name):
    solver = make_solver(small_mpc, MPCConfig(backend=name))
    soc, buy, sell, which, vectors = problems(small_mpc, thetas)
    mixed = solver.solve_batch(soc, buy, sell, vectors)
    assert mixed.success.all()
    for k, theta in enumerate(thetas):
        rows = np.flatnonzero(which == k)
        alone = solver.solve_batch(soc[rows], buy[rows], sell[rows], theta)
        for key in ("action", "x", "lam", "mu", "cost"):
            np.testing.assert_allclose(getattr(mixed, key)[rows], getattr(alone, key),
                                       err_msg=f"{name}: {key} of theta {k}", **tolerance(name))
        assert [mixed.status[r] for r in rows] == list(alone.status)
    # the thetas really differ in what they do (else the test could not fail)
    first = mixed.action[which == 0]
    assert not np.allclose(first, mixed.action[which == 2], atol=1e-3)


@pytest.mark.parametrize("name", BACKENDS)
def test_warm_start_and_sensitivity_per_row(small_mpc, thetas, name):
    solver = make_solver(small_mpc, MPCConfig(backend=name))
    soc, buy, sell, which, vectors = problems(small_mpc, thetas, seed=6)
    first = solver.solve_batch(soc, buy, sell, vectors)
    warm = small_mpc.shift(first.x)
    mixed = solver.solve_batch(soc, np.roll(buy, -1, axis=1), np.roll(sell, -1, axis=1),
                               vectors, x0=warm)
    sens = solver.sensitivity(mixed)
    for k, theta in enumerate(thetas):
        rows = np.flatnonzero(which == k)
        alone = solver.solve_batch(soc[rows], np.roll(buy[rows], -1, axis=1),
                                   np.roll(sell[rows], -1, axis=1), theta, x0=warm[rows])
        np.testing.assert_allclose(mixed.x[rows], alone.x, **tolerance(name))
        ref = solver.sensitivity(alone)
        np.testing.assert_allclose(sens.grad[rows], ref.grad, atol=1e-9, rtol=1e-7)
        np.testing.assert_array_equal(sens.ok[rows], ref.ok)


@pytest.mark.parametrize("name", BACKENDS)
def test_run_month_with_a_list_of_thetas(small_mpc, thetas, name):
    """Runs stacked in lockstep: each block is the month of its theta alone."""
    system = small_mpc.system
    solver = make_solver(small_mpc, MPCConfig(backend=name))
    days = 2
    rng = np.random.default_rng(2)
    buy = rng.uniform(5.0, 130.0, (days, system.hours_per_day))
    prices = Prices(buy)
    seeds = [11, 12, 13]
    blocks = RunBlocks([np.random.default_rng(s) for s in seeds], [system] * len(seeds))
    together = run_month(thetas, solver, prices, system, blocks, exploration_std=0.05,
                         sensitivities=False)
    for k, (theta, seed) in enumerate(zip(thetas, seeds, strict=True)):
        alone = run_month(theta, solver, prices, system, np.random.default_rng(seed),
                          exploration_std=0.05, sensitivities=False)
        rows = slice(k * days, (k + 1) * days)
        np.testing.assert_allclose(together.soc[:, rows], alone.soc, **tolerance(name))
        # (J sums over hours and agents: a different array width may round differently)
        np.testing.assert_allclose(together.J_per_day()[rows], alone.J_per_day(),
                                   rtol=1e-12)
